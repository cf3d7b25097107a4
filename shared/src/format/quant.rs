//! Quantization helpers shared by the skeleton, bark mesh and leaf records.

use glam::{Quat, Vec2, Vec3};

/// Quantizes `v` over `[lo, hi]` to 16 bits. Values outside are clamped; a degenerate range
/// quantizes to 0. Error ≤ (hi − lo) / 131070.
pub fn quantize_u16(v: f32, lo: f32, hi: f32) -> u16 {
    let span = hi - lo;
    if span <= 0.0 || !span.is_finite() {
        return 0;
    }
    (((v - lo) / span).clamp(0.0, 1.0) * 65535.0).round() as u16
}

/// Inverse of [`quantize_u16`].
pub fn dequantize_u16(q: u16, lo: f32, hi: f32) -> f32 {
    lo + (q as f32 / 65535.0) * (hi - lo)
}

/// Quantizes a point over the box `[lo, hi]`.
pub fn quantize_point(p: Vec3, lo: Vec3, hi: Vec3) -> [u16; 3] {
    [
        quantize_u16(p.x, lo.x, hi.x),
        quantize_u16(p.y, lo.y, hi.y),
        quantize_u16(p.z, lo.z, hi.z),
    ]
}

/// Inverse of [`quantize_point`].
pub fn dequantize_point(q: [u16; 3], lo: Vec3, hi: Vec3) -> Vec3 {
    Vec3::new(
        dequantize_u16(q[0], lo.x, hi.x),
        dequantize_u16(q[1], lo.y, hi.y),
        dequantize_u16(q[2], lo.z, hi.z),
    )
}

const SQRT_HALF: f32 = std::f32::consts::FRAC_1_SQRT_2;

/// Packs a unit quaternion as smallest-three in 32 bits (2-bit index + 3 × 10 bits).
/// Angular error ≤ 0.25°.
pub fn pack_quat(q: Quat) -> u32 {
    let q = q.normalize();
    let c = [q.x, q.y, q.z, q.w];
    let mut largest = 0;
    for i in 1..4 {
        if c[i].abs() > c[largest].abs() {
            largest = i;
        }
    }
    let sign = if c[largest] < 0.0 { -1.0 } else { 1.0 };
    let mut out = (largest as u32) << 30;
    let mut shift = 20;
    for (i, &v) in c.iter().enumerate() {
        if i == largest {
            continue;
        }
        let n = ((v * sign / SQRT_HALF).clamp(-1.0, 1.0) + 1.0) * 0.5;
        out |= ((n * 1023.0).round() as u32 & 0x3FF) << shift;
        shift -= 10;
    }
    out
}

/// Inverse of [`pack_quat`]; every 32-bit value decodes to a unit quaternion.
pub fn unpack_quat(v: u32) -> Quat {
    let largest = (v >> 30) as usize;
    let mut c = [0.0f32; 4];
    let mut shift = 20;
    let mut sum = 0.0;
    for (i, slot) in c.iter_mut().enumerate() {
        if i == largest {
            continue;
        }
        let q = ((v >> shift) & 0x3FF) as f32 / 1023.0;
        let x = (q * 2.0 - 1.0) * SQRT_HALF;
        *slot = x;
        sum += x * x;
        shift -= 10;
    }
    c[largest] = (1.0 - sum).max(0.0).sqrt();
    Quat::from_xyzw(c[0], c[1], c[2], c[3]).normalize()
}

/// Octahedral encoding of a unit vector in two bytes.
pub fn pack_octahedral(n: Vec3) -> [u8; 2] {
    let n = n.try_normalize().unwrap_or(Vec3::Y);
    let l1 = n.x.abs() + n.y.abs() + n.z.abs();
    let mut p = Vec2::new(n.x, n.y) / l1;
    if n.z < 0.0 {
        p = (Vec2::ONE - Vec2::new(p.y.abs(), p.x.abs())) * Vec2::new(p.x.signum(), p.y.signum());
    }
    let q = |x: f32| (((x.clamp(-1.0, 1.0) + 1.0) * 0.5) * 255.0).round() as u8;
    [q(p.x), q(p.y)]
}

/// Inverse of [`pack_octahedral`]; always returns a unit vector.
pub fn unpack_octahedral(b: [u8; 2]) -> Vec3 {
    let x = b[0] as f32 / 255.0 * 2.0 - 1.0;
    let y = b[1] as f32 / 255.0 * 2.0 - 1.0;
    let z = 1.0 - x.abs() - y.abs();
    let (x, y) = if z < 0.0 {
        ((1.0 - y.abs()) * x.signum(), (1.0 - x.abs()) * y.signum())
    } else {
        (x, y)
    };
    Vec3::new(x, y, z).try_normalize().unwrap_or(Vec3::Y)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        #[test]
        fn quat_round_trip_within_bound(x in -1.0f32..1.0, y in -1.0f32..1.0, z in -1.0f32..1.0, w in -1.0f32..1.0) {
            let q = Quat::from_xyzw(x, y, z, w);
            prop_assume!(q.length() > 0.1);
            let q = q.normalize();
            let r = unpack_quat(pack_quat(q));
            let angle = q.angle_between(r).to_degrees();
            prop_assert!(angle <= 0.25, "angle error {angle}");
        }

        #[test]
        fn u16_round_trip_within_bound(v in -5.0f32..20.0) {
            let q = quantize_u16(v, -5.0, 20.0);
            let back = dequantize_u16(q, -5.0, 20.0);
            prop_assert!((back - v).abs() <= 25.0 / 131_070.0 + 1e-5);
        }

        #[test]
        fn octahedral_is_unit(a in any::<u8>(), b in any::<u8>()) {
            let n = unpack_octahedral([a, b]);
            prop_assert!((n.length() - 1.0).abs() < 1e-4);
        }
    }

    #[test]
    fn octahedral_round_trip() {
        for v in [Vec3::X, Vec3::NEG_Y, Vec3::new(0.3, -0.5, -0.8), Vec3::Z, Vec3::NEG_Z] {
            let v = v.normalize();
            let r = unpack_octahedral(pack_octahedral(v));
            assert!(v.angle_between(r).to_degrees() < 1.5, "{v} -> {r}");
        }
    }
}

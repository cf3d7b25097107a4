//! Regular view grids: seed 001's latitude–longitude grid and the hemi-octahedral grid;
//! directions of their frames and the frame(s) to show for a view direction.
//!
//! Conventions: as the atlas module (directions tree → camera, Y up, azimuth θ from +X toward
//! −Z, elevation σ above the horizon); frame indices are layout-local.

use glam::Vec3;

use super::{AtlasLayout, AtlasLayoutKind};

/// Direction from azimuth `theta` and elevation `sigma` (radians), see the module doc.
pub fn lat_long_direction(theta: f32, sigma: f32) -> Vec3 {
    Vec3::new(sigma.cos() * theta.cos(), sigma.sin(), -sigma.cos() * theta.sin())
}

/// Azimuth θ ∈ (−π, π] and elevation σ ∈ [−π/2, π/2] of a direction (inverse of
/// [`lat_long_direction`]).
pub fn direction_angles(d: Vec3) -> (f32, f32) {
    let d = d.normalize_or(Vec3::X);
    ((-d.z).atan2(d.x), d.y.clamp(-1.0, 1.0).asin())
}

/// Hemi-octahedral encoding of a direction in the upper hemisphere into `[-1, 1]²`.
///
/// `p = (x, z) / (|x| + |y| + |z|)` then rotated 45°: `u = p.x + p.z`, `v = p.x − p.z`. Directions
/// below the horizon are mirrored to `y ≥ 0` first (a tree billboard is never seen from below;
/// the nearest frames of the horizon serve).
pub fn hemi_oct_encode(d: Vec3) -> (f32, f32) {
    let d = Vec3::new(d.x, d.y.abs(), d.z);
    let s = d.x.abs() + d.y + d.z.abs();
    if !(s > 0.0 && s.is_finite()) {
        return (0.0, 0.0);
    }
    let (px, pz) = (d.x / s, d.z / s);
    ((px + pz).clamp(-1.0, 1.0), (px - pz).clamp(-1.0, 1.0))
}

/// Inverse of [`hemi_oct_encode`]: unit direction (y ≥ 0) of a point of `[-1, 1]²`.
pub fn hemi_oct_decode(u: f32, v: f32) -> Vec3 {
    let (px, pz) = (0.5 * (u + v), 0.5 * (u - v));
    let y = (1.0 - px.abs() - pz.abs()).max(0.0);
    Vec3::new(px, y, pz).normalize_or(Vec3::Y)
}

/// Direction of hemi-octahedral frame (`col`, `row`) in a `side × side` grid: the cell centre
/// `u = (col + ½)/side · 2 − 1`, `v = (row + ½)/side · 2 − 1`, decoded.
pub fn hemi_oct_direction(col: u32, row: u32, side: u32) -> Vec3 {
    let n = side.max(1) as f32;
    hemi_oct_decode((col as f32 + 0.5) / n * 2.0 - 1.0, (row as f32 + 0.5) / n * 2.0 - 1.0)
}

/// The three hemi-octahedral frames to blend for a view direction `view_dir` (tree → camera)
/// in a `side × side` grid, with barycentric weights.
///
/// Contract: frame indices are layout-local (`row · side + col`, add the layout's first frame),
/// weights are ≥ 0 and sum to 1; looking exactly from a frame's direction gives that frame
/// weight 1. Method: encode the direction ([`hemi_oct_encode`]), move to grid coordinates
/// `g = (u + 1)/2 · side − ½` (cell centres at integers), clamp to `[0, side − 1]`, take the grid
/// cell `(⌊g⌋, ⌊g⌋ + 1)` and split it along its anti-diagonal: the lower triangle
/// (00, 10, 01) with weights `(1 − fx − fy, fx, fy)` when `fx + fy ≤ 1`, else the upper one
/// (11, 01, 10) with weights `(fx + fy − 1, 1 − fx, 1 − fy)`. A client that finds one of
/// the three frames absent (empty) drops it and renormalises the other weights.
pub fn hemi_oct_blend(view_dir: Vec3, side: u32) -> [(u32, f32); 3] {
    let n = side.max(1);
    if n == 1 {
        return [(0, 1.0), (0, 0.0), (0, 0.0)];
    }
    let (u, v) = hemi_oct_encode(view_dir);
    let nf = n as f32;
    let gx = ((u + 1.0) * 0.5 * nf - 0.5).clamp(0.0, nf - 1.0);
    let gy = ((v + 1.0) * 0.5 * nf - 0.5).clamp(0.0, nf - 1.0);
    // gx, gy ≥ 0 after the clamp (NaN casts to 0 either way): truncation is the floor,
    // without a libm call (clients run this per far tree and frame).
    let x0 = (gx as u32).min(n - 2);
    let y0 = (gy as u32).min(n - 2);
    let (fx, fy) = (gx - x0 as f32, gy - y0 as f32);
    let idx = |dx: u32, dy: u32| (y0 + dy) * n + x0 + dx;
    if fx + fy <= 1.0 {
        [(idx(0, 0), 1.0 - fx - fy), (idx(1, 0), fx), (idx(0, 1), fy)]
    } else {
        [(idx(1, 1), fx + fy - 1.0), (idx(0, 1), 1.0 - fx), (idx(1, 0), 1.0 - fy)]
    }
}

/// Seed 001's lookup on its regular grid: of the four control points around `view_dir` (the
/// columns either side of its azimuth, wrapping, and the rows either side of its elevation,
/// clamped), the nearest by angle (layout-local index). `None` for another layout kind.
///
/// Rounding azimuth and elevation separately is not the same: toward the top rows a column
/// step spans a smaller angle (cos σ), so the nearer frame can be the other row's.
pub fn lat_long_nearest(layout: &AtlasLayout, view_dir: Vec3) -> Option<u32> {
    let AtlasLayoutKind::LatLong {
        elevation_min,
        elevation_step,
        azimuth_step,
    } = layout.kind
    else {
        return None;
    };
    let d = view_dir.normalize_or(Vec3::X);
    let (theta, sigma) = direction_angles(d);
    let cols = i64::from(layout.cols.max(1));
    let rows = i64::from(layout.rows.max(1));
    let c0 = if azimuth_step > 0.0 {
        (theta / azimuth_step).floor() as i64
    } else {
        0
    };
    let r0 = if elevation_step > 0.0 {
        ((sigma - elevation_min) / elevation_step).floor() as i64
    } else {
        0
    };
    let mut best = (f32::NEG_INFINITY, 0i64);
    for (c, r) in [(c0, r0), (c0 + 1, r0), (c0, r0 + 1), (c0 + 1, r0 + 1)] {
        let (c, r) = (c.rem_euclid(cols), r.clamp(0, rows - 1));
        let dir = lat_long_direction(c as f32 * azimuth_step, elevation_min + r as f32 * elevation_step);
        let dot = dir.dot(d);
        if dot > best.0 {
            best = (dot, r * cols + c);
        }
    }
    Some(best.1 as u32)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::format::atlas::DEFAULT_HEMI_OCT_SIDE;

    proptest::proptest! {
        /// The cell is taken by truncation: the same frames and weights as with `floor`.
        #[test]
        fn hemi_oct_cell_by_truncation_is_the_floor(x in -1.0f32..1.0, y in -1.0f32..1.0, z in -1.0f32..1.0, side in 2u32..20) {
            let dir = Vec3::new(x, y, z).normalize_or_zero();
            let (u, v) = hemi_oct_encode(dir);
            let nf = side as f32;
            let gx = ((u + 1.0) * 0.5 * nf - 0.5).clamp(0.0, nf - 1.0);
            let gy = ((v + 1.0) * 0.5 * nf - 0.5).clamp(0.0, nf - 1.0);
            let x0 = (gx.floor() as u32).min(side - 2);
            let y0 = (gy.floor() as u32).min(side - 2);
            let cell = hemi_oct_blend(dir, side).map(|(f, _)| (f % side).min(x0 + 1).max(x0) == f % side && (f / side).min(y0 + 1).max(y0) == f / side);
            proptest::prop_assert!(cell.iter().all(|&b| b), "frames outside the floor cell ({x0}, {y0})");
        }
    }

    #[test]
    fn hemi_oct_round_trip_and_blend() {
        let n = u32::from(DEFAULT_HEMI_OCT_SIDE);
        for row in 0..n {
            for col in 0..n {
                let d = hemi_oct_direction(col, row, n);
                assert!(d.y >= 0.0 && (d.length() - 1.0).abs() < 1e-5);
                let w = hemi_oct_blend(d, n);
                let best = w.iter().max_by(|a, b| a.1.total_cmp(&b.1)).unwrap();
                assert_eq!(best.0, row * n + col, "frame ({col}, {row})");
                assert!((best.1 - 1.0).abs() < 1e-3, "weight {}", best.1);
            }
        }
        // Arbitrary directions, also below the horizon and degenerate ones.
        let dirs =
            crate::raster::fibonacci_sphere(300)
                .into_iter()
                .chain([Vec3::Y, -Vec3::Y, Vec3::X, Vec3::ZERO, Vec3::NAN]);
        for d in dirs {
            let w = hemi_oct_blend(d, n);
            let sum: f32 = w.iter().map(|x| x.1).sum();
            assert!((sum - 1.0).abs() < 1e-5, "{d}: {w:?}");
            assert!(w.iter().all(|x| x.1 >= -1e-6 && x.0 < n * n));
            // The heaviest frame is among the nearest few by angle.
            if d.is_finite() && d.length() > 0.5 {
                let dd = Vec3::new(d.x, d.y.abs(), d.z).normalize();
                let best = w.iter().max_by(|a, b| a.1.total_cmp(&b.1)).unwrap().0;
                let ang = |i: u32| hemi_oct_direction(i % n, i / n, n).angle_between(dd);
                let nearest = (0..n * n).map(ang).fold(f32::INFINITY, f32::min);
                assert!(ang(best) < nearest + 0.2, "{d}");
            }
        }
        assert_eq!(hemi_oct_blend(Vec3::Y, 1), [(0, 1.0), (0, 0.0), (0, 0.0)]);
    }

    #[test]
    fn lat_long_nearest_wraps_and_clamps() {
        let l = AtlasLayout {
            kind: AtlasLayoutKind::LatLong {
                elevation_min: 0.0,
                elevation_step: 0.25,
                azimuth_step: std::f32::consts::PI / 4.0,
            },
            cols: 8,
            rows: 4,
            first_frame: 0,
        };
        for i in 0..32 {
            assert_eq!(lat_long_nearest(&l, l.direction(i).unwrap()), Some(i));
        }
        assert_eq!(lat_long_nearest(&l, lat_long_direction(-0.1, -0.5)), Some(0));
        assert_eq!(lat_long_nearest(&l, Vec3::Y), Some(3 * 8));
        // Within the grid's elevations the four-point rule finds the nearest frame of the grid.
        for k in 0..500 {
            let d = lat_long_direction(k as f32 * 0.137, (k % 50) as f32 * 0.018);
            let got = lat_long_nearest(&l, d).unwrap();
            let best = (0..32)
                .map(|i| l.direction(i).unwrap().dot(d))
                .fold(f32::NEG_INFINITY, f32::max);
            assert!(l.direction(got).unwrap().dot(d) >= best - 1e-6, "{k}");
        }
        let (t, s) = direction_angles(lat_long_direction(1.0, 0.3));
        assert!((t - 1.0).abs() < 1e-5 && (s - 0.3).abs() < 1e-5);
    }
}

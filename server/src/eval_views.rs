//! `eval-views`: seed 001's billboard lookups compared at the same frame count, on a `.ctree`.
//! For arbitrary view directions, how well the frame a lookup picks stands in for the tree seen
//! from that direction, on the regular grids and on irregular (photo-like) view sets.
//!
//! **Sets** (about `frames` frames each):
//! - *lat-long*: seed 001's grid, 12 azimuths × 4 elevations (0°, 20°, 40°, 60°) for 48, looked up
//!   by seed 001's four-point rule ([`lat_long_nearest`]);
//! - *hemi-oct*: the hemi-octahedral grid of side ⌊√frames⌉, the heaviest frame of its blend;
//! - *views, even*: an irregular but even set (a Fibonacci spiral over the upper hemisphere),
//!   looked up by spherical Delaunay triangulation ([`ViewSphere::nearest`]);
//! - *views, photo set*: a photographer's set ([`photo_views`]: nothing from a 100° sector
//!   except a drone's few, nothing from below 5°), by [`ViewSphere::nearest`] and by seed 001's
//!   rule alone (the nearest vertex of the located triangle; the nearest view outside).
//!
//! **Queries**: `queries` directions uniform over the upper hemisphere (fixed by `seed`).
//! **Figures** per set: silhouette IoU of the picked frame against the tree seen from the
//! query (orthographic renders of the framing sphere, the frame placed by its root anchor as a
//! client places it), mean and 10th percentile, by elevation band; the angle between query and
//! picked frame; lookup time per query. Renders: the bake's far-tree mesh at `resolution`².

use std::time::Instant;

use canopy_shared::format::DecodedTree;
use canopy_shared::format::atlas::{AtlasLayout, AtlasLayoutKind};
use canopy_shared::format::atlas::{
    ViewSphere, hemi_oct_blend, hemi_oct_direction, lat_long_direction, lat_long_nearest,
};
use canopy_shared::metrics;
use canopy_shared::raster::{Camera, EMPTY_ITEM, RasterError, RenderOptions, Scene, render};
use canopy_shared::rng::SplitMix64;
use glam::Vec3;
use rayon::prelude::*;
use serde::Serialize;

use crate::bake::atlas::far_tree_mesh;
use crate::bake::views::photo_views;
use crate::bake::vmi::{leaf_materials, leaf_texture};

/// Options of [`eval_views`].
#[derive(Debug, Clone)]
pub struct ViewEvalOptions {
    /// Frames per set (the lat-long grid keeps 12 × 4 = 48 whatever this is).
    pub frames: usize,
    /// Query directions.
    pub queries: usize,
    /// Image side, pixels.
    pub resolution: u32,
    /// Seed of the queries and the photo set.
    pub seed: u64,
}

impl Default for ViewEvalOptions {
    fn default() -> Self {
        Self {
            frames: 48,
            queries: 200,
            resolution: 96,
            seed: 1,
        }
    }
}

/// Elevation bands of the per-band figures, degrees.
pub const BANDS_DEG: [(f32, f32); 3] = [(0.0, 30.0), (30.0, 60.0), (60.0, 90.0)];

/// One set and lookup.
#[derive(Debug, Clone, Serialize)]
pub struct ViewSetRow {
    /// Set and lookup.
    pub name: String,
    /// Frames in the set.
    pub frames: usize,
    /// Mean silhouette IoU.
    pub iou_mean: f64,
    /// 10th percentile of the IoU.
    pub iou_p10: f64,
    /// Mean IoU per elevation band ([`BANDS_DEG`]).
    pub iou_by_band: Vec<f64>,
    /// Mean angle between query and picked frame, degrees.
    pub angle_mean_deg: f64,
    /// Largest such angle, degrees.
    pub angle_max_deg: f64,
    /// Lookup time per query, nanoseconds (mean over the queries repeated).
    pub lookup_ns: f64,
}

/// What [`eval_views`] measured.
#[derive(Debug, Clone, Serialize)]
pub struct ViewEvalReport {
    /// Tree name.
    pub name: String,
    /// Image side.
    pub resolution: u32,
    /// Queries.
    pub queries: usize,
    /// Queries per band.
    pub queries_by_band: Vec<usize>,
    /// One row per set and lookup.
    pub rows: Vec<ViewSetRow>,
    /// Photo set: share of queries in no Delaunay triangle (outside the views' coverage).
    pub photo_outside_share: f64,
    /// Photo set: share of the queries inside a triangle whose nearest vertex is not the
    /// nearest view (where seed 001's rule alone picks a farther frame).
    pub photo_rule_miss_share: f64,
}

/// Renders one direction: coverage mask and the root anchor in pixels (column, row).
struct View {
    mask: Vec<bool>,
    root: (f32, f32),
}

/// Total renders [`eval_views`] makes (for a progress bar).
pub fn render_count(opts: &ViewEvalOptions) -> u64 {
    let side = (opts.frames as f64).sqrt().round().max(2.0) as u64;
    (opts.queries.max(1) + 48 + 2 * opts.frames.max(3)) as u64 + side * side
}

/// Evaluates the lookups on `tree`; `tick` is called once per render.
pub fn eval_views(
    tree: &DecodedTree,
    opts: &ViewEvalOptions,
    tick: &(dyn Fn() + Sync),
) -> Result<ViewEvalReport, RasterError> {
    let model = tree.to_model(0.0);
    let (lo, hi) = model.bounds().unwrap_or((Vec3::ZERO, Vec3::ZERO));
    let (lo, hi) = (lo.min(Vec3::ZERO), hi.max(Vec3::ZERO));
    let center = 0.5 * (lo + hi);
    let radius = (0.5 * (hi - lo).length()).max(1e-3);
    let side = opts.resolution.max(16);
    let mesh = far_tree_mesh(&model, 2.0 * radius / side as f32, 0.1, 4);
    let mats = leaf_materials(&model);
    let tex = [leaf_texture()];
    let scene = Scene::single(&mesh, &mats, &tex);
    let ropts = RenderOptions {
        shade: false,
        ..RenderOptions::default()
    };
    let render_dirs = |dirs: &[Vec3]| -> Result<Vec<View>, RasterError> {
        dirs.par_iter()
            .map(|&d| {
                let cam = Camera::orbit_orthographic(center, radius, d);
                let f = render(&scene, &cam, side, side, &ropts)?;
                tick();
                let root = cam
                    .project(Vec3::ZERO, side, side)
                    .map_or((0.5, 0.0), |(p, _)| (p.x, p.y));
                Ok(View {
                    mask: f.item.iter().map(|&i| i != EMPTY_ITEM).collect(),
                    root,
                })
            })
            .collect()
    };

    // Queries, uniform over the upper hemisphere (sin σ uniform).
    let mut rng = SplitMix64::new(opts.seed);
    let queries: Vec<Vec3> = (0..opts.queries.max(1))
        .map(|_| {
            let y = rng.uniform(0.0, 1.0) as f32;
            let az = rng.uniform(-std::f64::consts::PI, std::f64::consts::PI) as f32;
            lat_long_direction(az, y.asin())
        })
        .collect();
    let band_of = |q: Vec3| {
        let e = q.y.clamp(-1.0, 1.0).asin().to_degrees();
        BANDS_DEG
            .iter()
            .position(|&(a, b)| e >= a && e < b)
            .unwrap_or(BANDS_DEG.len() - 1)
    };
    let truth = render_dirs(&queries)?;

    // The sets.
    let lat_long = AtlasLayout {
        kind: AtlasLayoutKind::LatLong {
            elevation_min: 0.0,
            elevation_step: 20f32.to_radians(),
            azimuth_step: 30f32.to_radians(),
        },
        cols: 12,
        rows: 4,
        first_frame: 0,
    };
    let ll_dirs: Vec<Vec3> = (0..48).filter_map(|k| lat_long.direction(k)).collect();
    let n_side = (opts.frames as f64).sqrt().round().max(2.0) as u32;
    let ho_dirs: Vec<Vec3> = (0..n_side * n_side)
        .map(|k| hemi_oct_direction(k % n_side, k / n_side, n_side))
        .collect();
    let n = opts.frames.max(3);
    let golden = std::f32::consts::PI * (3.0 - 5f32.sqrt());
    let even_dirs: Vec<Vec3> = (0..n)
        .map(|i| {
            let y = (i as f32 + 0.5) / n as f32;
            let r = (1.0 - y * y).sqrt();
            let phi = i as f32 * golden;
            Vec3::new(r * phi.cos(), y, r * phi.sin())
        })
        .collect();
    let photo_dirs: Vec<Vec3> = photo_views(n, opts.seed)
        .iter()
        .map(|&[a, e]| lat_long_direction(a.to_radians(), e.to_radians()))
        .collect();
    let even_sphere = ViewSphere::new(&even_dirs);
    let photo_sphere = ViewSphere::new(&photo_dirs);

    // Each set's frames rendered once: lat-long, hemi-oct, even, photo.
    let dir_sets: [&Vec<Vec3>; 4] = [&ll_dirs, &ho_dirs, &even_dirs, &photo_dirs];
    let rendered: Vec<Vec<View>> = dir_sets.iter().map(|d| render_dirs(d)).collect::<Result<_, _>>()?;
    type Lookup<'a> = Box<dyn Fn(Vec3) -> usize + Sync + 'a>;
    let sets: Vec<(String, usize, Lookup)> = vec![
        (
            "lat-long 12×4, seed 001's four-point nearest".into(),
            0,
            Box::new(|q| lat_long_nearest(&lat_long, q).unwrap_or(0) as usize),
        ),
        (
            format!("hemi-oct {n_side}×{n_side}, heaviest of the blend"),
            1,
            Box::new(move |q| {
                hemi_oct_blend(q, n_side)
                    .into_iter()
                    .max_by(|a, b| a.1.total_cmp(&b.1))
                    .map_or(0, |x| x.0 as usize)
            }),
        ),
        (
            format!("views, even irregular {n}: Delaunay, nearest"),
            2,
            Box::new(|q| even_sphere.nearest(q, 0).map_or(0, |x| x.0 as usize)),
        ),
        (
            format!("views, photo set {n}: Delaunay, nearest"),
            3,
            Box::new(|q| photo_sphere.nearest(q, 0).map_or(0, |x| x.0 as usize)),
        ),
        (
            format!("views, photo set {n}: seed 001's triangle vertex"),
            3,
            Box::new(|q| {
                photo_sphere
                    .nearest_of_triangle(q, 0)
                    .or_else(|| photo_sphere.nearest(q, 0).map(|x| x.0))
                    .unwrap_or(0) as usize
            }),
        ),
    ];

    let mut rows = Vec::new();
    for (name, set, lookup) in &sets {
        let (dirs, frames) = (dir_sets[*set], &rendered[*set]);
        let picks: Vec<usize> = queries.iter().map(|&q| lookup(q)).collect();
        let mut ious = Vec::with_capacity(queries.len());
        let mut by_band = vec![(0.0f64, 0usize); BANDS_DEG.len()];
        let (mut angle_sum, mut angle_max) = (0.0f64, 0.0f64);
        for ((q, t), &p) in queries.iter().zip(&truth).zip(&picks) {
            let f = &frames[p.min(frames.len() - 1)];
            let shifted = shift_mask(&f.mask, side, t.root.0 - f.root.0, t.root.1 - f.root.1);
            let iou = metrics::iou(&t.mask, &shifted).unwrap_or(0.0);
            ious.push(iou);
            let b = &mut by_band[band_of(*q)];
            b.0 += iou;
            b.1 += 1;
            let angle = f64::from(q.angle_between(dirs[p.min(dirs.len() - 1)]).to_degrees());
            angle_sum += angle;
            angle_max = angle_max.max(angle);
        }
        // Lookup time: every query, repeated to about 200,000 lookups.
        let reps = (200_000 / queries.len()).max(1);
        let t0 = Instant::now();
        let mut acc = 0usize;
        for _ in 0..reps {
            for &q in &queries {
                acc = acc.wrapping_add(std::hint::black_box(lookup(std::hint::black_box(q))));
            }
        }
        std::hint::black_box(acc);
        let lookup_ns = t0.elapsed().as_nanos() as f64 / (reps * queries.len()) as f64;
        let mut sorted = ious.clone();
        sorted.sort_by(f64::total_cmp);
        rows.push(ViewSetRow {
            name: name.clone(),
            frames: dirs.len(),
            iou_mean: ious.iter().sum::<f64>() / ious.len() as f64,
            iou_p10: sorted[sorted.len() / 10],
            iou_by_band: by_band
                .iter()
                .map(|&(s, c)| if c == 0 { f64::NAN } else { s / c as f64 })
                .collect(),
            angle_mean_deg: angle_sum / queries.len() as f64,
            angle_max_deg: angle_max,
            lookup_ns,
        });
    }
    let mut outside = 0usize;
    let mut misses = 0usize;
    for &q in &queries {
        match (photo_sphere.nearest_of_triangle(q, 0), photo_sphere.nearest(q, 0)) {
            (None, _) => outside += 1,
            (Some(a), Some((b, _))) if a != b => misses += 1,
            _ => {}
        }
    }
    let mut queries_by_band = vec![0; BANDS_DEG.len()];
    for &q in &queries {
        queries_by_band[band_of(q)] += 1;
    }
    Ok(ViewEvalReport {
        name: tree.directory.name.clone(),
        resolution: side,
        queries: queries.len(),
        queries_by_band,
        rows,
        photo_outside_share: outside as f64 / queries.len() as f64,
        photo_rule_miss_share: misses as f64 / queries.len() as f64,
    })
}

/// `mask` (side²) moved by (`dx`, `dy`) pixels, rounded; what moves out is dropped.
fn shift_mask(mask: &[bool], side: u32, dx: f32, dy: f32) -> Vec<bool> {
    let (dx, dy) = (dx.round() as i64, dy.round() as i64);
    let s = i64::from(side);
    let mut out = vec![false; mask.len()];
    for y in 0..s {
        let sy = y - dy;
        if !(0..s).contains(&sy) {
            continue;
        }
        for x in 0..s {
            let sx = x - dx;
            if (0..s).contains(&sx) {
                out[(y * s + x) as usize] = mask[(sy * s + sx) as usize];
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn masks_shift_and_clip() {
        let m = vec![true, false, false, false];
        assert_eq!(shift_mask(&m, 2, 1.0, 0.0), vec![false, true, false, false]);
        assert_eq!(shift_mask(&m, 2, 0.0, 1.0), vec![false, false, true, false]);
        assert_eq!(shift_mask(&m, 2, -1.0, 0.0), vec![false; 4]);
        assert_eq!(shift_mask(&m, 2, 0.4, 0.0), m);
    }
}

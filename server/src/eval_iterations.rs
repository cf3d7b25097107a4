//! `eval-iterations`: seed 000's iteration count as a level of detail, measured on a `.ctree`.
//! For every iteration count `k`, what a client fetches and draws of the tree grown `k`
//! iterations, against the full tree, and against VMI prefixes alone at the same bytes.
//!
//! **Levels.** For each `k` in `0..=K`:
//! - *model after k* (seed 000's exact level): the skeleton of iterations `≤ k` and the leaves
//!   created in iterations `≤ k` (each leaf's iteration byte). Answers "how much of the shape do
//!   the first `k` iterations fix".
//! - *iteration level* (what the client draws, `iterN` rungs): the skeleton of iterations `≤ k`
//!   and every leaf of the leaf nodes whose branch was born in iterations `≤ k`. A leaf node
//!   holds the leaves of its branch's later sub-branches too (the hierarchy merges them), so it
//!   keeps more leaves than the exact level; it is what byte ranges can select.
//! - *VMI at the same bytes*: the whole skeleton and the uniform VMI prefix whose bytes are the
//!   largest not above the iteration level's (prefixes are fetched by bands, so bytes step).
//!
//! **Bytes** are what a client fetches: header, directory, node table, materials, bark mesh, the
//! skeleton prefix of the iterations drawn and the leaf blocks drawn (records + CRC per block).
//!
//! **Images.** Each method is rendered with the shared CPU rasterizer (leaves alpha-tested, bark
//! tubes; lit) from [`crate::eval::eval_directions`] views at `resolution²`, the camera just
//! holding the tree's bounding sphere, so the tree is about `resolution` pixels tall: the range
//! where the ladder draws geometry. **Figures** (means over views): silhouette IoU of the
//! "anything drawn" masks (`|A ∩ R| / |A ∪ R|`), coverage precision and recall, colour SSIM
//! over a grey background.

use canopy_shared::format::directory::{SectionKind, leaf_node_iterations};
use canopy_shared::format::leaf::{BandLayout, keep_count};
use canopy_shared::format::{DecodedTree, HEADER_LEN, LEAF_RECORD_LEN};
use canopy_shared::metrics;
use canopy_shared::model::TreeModel;
use canopy_shared::raster::{Camera, Frame, RasterError};
use rayon::prelude::*;
use serde::Serialize;

use crate::eval::{eval_directions, flatten, render_tree};

/// Options of [`eval_iterations`].
#[derive(Debug, Clone)]
pub struct IterationEvalOptions {
    /// Views (≥ 1).
    pub views: usize,
    /// Image side in pixels (≥ 16).
    pub resolution: u32,
    /// Folder for image strips (`<tree>-k<k>.png`: iteration level | VMI prefix at the same
    /// bytes | full tree, the most nearly horizontal view, over grey) for the last [`STRIP_ROWS`] iteration counts
    /// below `K`; `None` writes none.
    pub strips: Option<std::path::PathBuf>,
}

/// Iteration counts below `K` that get an image strip.
pub const STRIP_ROWS: usize = 3;

impl Default for IterationEvalOptions {
    fn default() -> Self {
        Self {
            views: 8,
            resolution: 256,
            strips: None,
        }
    }
}

/// Errors of [`eval_iterations`].
#[derive(Debug, thiserror::Error)]
pub enum IterationEvalError {
    /// Bad options.
    #[error("bad options: {0}")]
    Options(String),
    /// The tree has no iterations to leave out (an import).
    #[error("the tree has no L-system iterations (K = 0): nothing to leave out")]
    NoIterations,
    /// Rendering failed.
    #[error(transparent)]
    Raster(#[from] RasterError),
    /// An image strip could not be written.
    #[error("image strip: {0}")]
    Strip(String),
    /// Metrics failed.
    #[error(transparent)]
    Metrics(#[from] metrics::MetricsError),
}

/// Quality of one method against the full tree (means over views).
#[derive(Debug, Clone, Copy, Serialize, PartialEq)]
pub struct Quality {
    /// Silhouette IoU.
    pub iou: f64,
    /// Coverage precision.
    pub precision: f64,
    /// Coverage recall.
    pub recall: f64,
    /// Colour SSIM.
    pub ssim: f64,
}

/// One iteration count.
#[derive(Debug, Clone, Serialize)]
pub struct IterationRow {
    /// Iterations drawn `0..=k`.
    pub k: u8,
    /// `k + 1` over `K + 1`.
    pub iteration_fraction: f64,
    /// Skeleton branches of iterations `≤ k`.
    pub branches: u32,
    /// Skeleton bytes of iterations `≤ k`.
    pub skeleton_bytes: u64,
    /// Leaves created in iterations `≤ k` (the exact level).
    pub leaves_exact: u64,
    /// Leaves of the leaf nodes born in iterations `≤ k` (the iteration level).
    pub leaves_level: u64,
    /// Bytes of the iteration level.
    pub bytes: u64,
    /// The exact level against the full tree.
    pub exact: Quality,
    /// The iteration level against the full tree.
    pub level: Quality,
    /// VMI prefix rate whose bytes are the largest not above [`Self::bytes`] (`None`: even the
    /// smallest prefix costs more).
    pub vmi_rate: Option<f32>,
    /// Its bytes.
    pub vmi_bytes: u64,
    /// Its quality.
    pub vmi: Option<Quality>,
}

/// The report of [`eval_iterations`].
#[derive(Debug, Clone, Serialize)]
pub struct IterationEvalReport {
    /// Model name.
    pub name: String,
    /// L-system iterations `K`.
    pub iterations: u8,
    /// Leaves of the full tree.
    pub leaves: u64,
    /// Bytes of the full geometry (every iteration, every leaf).
    pub full_bytes: u64,
    /// Views per method.
    pub views: usize,
    /// Image side, pixels.
    pub resolution: u32,
    /// One row per `k`, `0..=K`.
    pub rows: Vec<IterationRow>,
    /// Fewest iterations whose exact level reaches silhouette IoU 0.9, as a fraction of `K`
    /// (seed 000: about 75 % of the iterations fix the overall shape).
    pub shape_fraction_iou_090: Option<f64>,
    /// Image strips written (paths).
    pub strips: Vec<String>,
    /// The same for the iteration level the client draws (leaf nodes of branches born by `k`,
    /// with all their leaves).
    pub level_shape_fraction_iou_090: Option<f64>,
}

/// Writes frames side by side over grey (what a person compares).
fn write_strip(path: &std::path::Path, frames: &[&Frame], res: u32) -> Result<(), IterationEvalError> {
    let (w, n) = (res as usize, frames.len());
    let mut px = vec![[128u8, 128, 128, 255]; w * n * w];
    for (i, f) in frames.iter().enumerate() {
        for (j, c) in f.color.iter().enumerate().take(w * w) {
            let a = u32::from(c[3]);
            let o = &mut px[(j / w) * w * n + i * w + j % w];
            for ch in 0..3 {
                o[ch] = ((u32::from(c[ch]) * a + 128 * (255 - a)) / 255) as u8;
            }
        }
    }
    metrics::write_png(path, res * n as u32, res, &px)
        .map_err(|e| IterationEvalError::Strip(format!("{}: {e}", path.display())))
}

/// Renders needed by [`eval_iterations`] (for a progress bar).
pub fn render_count(tree: &DecodedTree, opts: &IterationEvalOptions) -> u64 {
    (opts.views * (1 + 3 * tree.directory.iteration_table.len())) as u64
}

/// Bytes every geometry level fetches: header, directory, node table, materials, bark mesh.
fn fixed_bytes(tree: &DecodedTree) -> u64 {
    let d = &tree.directory;
    let len = |k: SectionKind| d.section(k).map_or(0, |e| e.length);
    HEADER_LEN as u64
        + u64::from(tree.header.directory_len)
        + len(SectionKind::NodeTable)
        + len(SectionKind::Materials)
        + len(SectionKind::BarkMesh)
}

/// Bytes of the leaf blocks holding the first `keep[o]` leaves of each leaf node.
fn leaf_bytes(layout: &BandLayout, keep: &[u32]) -> u64 {
    let counts = layout.leaf_counts();
    let mut total = 0u64;
    for (o, (&k, &n)) in keep.iter().zip(counts).enumerate() {
        for band in 0..layout.bands_for_keep(n, k) {
            if let Some(b) = layout.block(band, o) {
                total += u64::from(b.count) * LEAF_RECORD_LEN as u64 + 4;
            }
        }
    }
    total
}

/// Evaluates every iteration count of `tree` (see the module doc). `tick` is called once per
/// render.
pub fn eval_iterations(
    tree: &DecodedTree,
    opts: &IterationEvalOptions,
    tick: &(dyn Fn() + Sync),
) -> Result<IterationEvalReport, IterationEvalError> {
    if opts.views == 0 || opts.resolution < 16 {
        return Err(IterationEvalError::Options("views ≥ 1 and resolution ≥ 16".into()));
    }
    let d = &tree.directory;
    let table = &d.iteration_table;
    if d.iterations == 0 || table.len() < 2 {
        return Err(IterationEvalError::NoIterations);
    }
    let (model, lists) = flatten(tree);
    let counts: Vec<u32> = tree.node_leaves.iter().map(|v| v.len() as u32).collect();
    let layout = BandLayout::new(&d.band_edges, &counts);
    let node_iteration = leaf_node_iterations(&tree.nodes, table);
    let fixed = fixed_bytes(tree);
    let skeleton_all = u64::from(table.last().map_or(0, |e| e.skeleton_bytes_end));
    let full_bytes = fixed + skeleton_all + leaf_bytes(&layout, &counts);
    let (lo, hi) = (d.bounds_min, d.bounds_max);
    let center = 0.5 * (lo + hi);
    let radius = 0.5 * (hi - lo).length();
    let dirs = eval_directions(opts.views);
    // The strips show the most nearly horizontal view (how a tree is mostly seen).
    let side = (0..dirs.len())
        .min_by(|&a, &b| dirs[a].y.abs().total_cmp(&dirs[b].y.abs()))
        .unwrap_or(0);
    let cams: Vec<Camera> = dirs
        .into_iter()
        .map(|dir| Camera::orbit_perspective(center, radius, dir, 2.0 * (1.0f32 / 3.0).asin()))
        .collect();
    let res = opts.resolution;
    let render_all = |m: &TreeModel, subset: Option<&[u32]>| -> Result<Vec<Frame>, RasterError> {
        cams.par_iter()
            .map(|c| {
                let f = render_tree(m, subset, 1.0, c, res);
                tick();
                f
            })
            .collect()
    };
    let refs = render_all(&model, None)?;
    let score = |frames: &[Frame]| -> Result<Quality, IterationEvalError> {
        let mut acc = [0f64; 4];
        for (r, a) in refs.iter().zip(frames) {
            let (rc, ac) = (r.coverage(), a.coverage());
            let cov = metrics::coverage(&rc, &ac)?;
            let (both, either) = rc.iter().zip(&ac).fold((0u64, 0u64), |(b, e), (&x, &y)| {
                (b + u64::from(x && y), e + u64::from(x || y))
            });
            acc[0] += if either == 0 { 1.0 } else { both as f64 / either as f64 };
            acc[1] += cov.precision;
            acc[2] += cov.recall;
            acc[3] += metrics::ssim_rgba(&r.color, &a.color, res, res, [128, 128, 128])?;
        }
        let n = frames.len().max(1) as f64;
        Ok(Quality {
            iou: acc[0] / n,
            precision: acc[1] / n,
            recall: acc[2] / n,
            ssim: acc[3] / n,
        })
    };
    // Uniform VMI prefixes by band edge: (bytes, rate), ascending in bytes.
    let vmi_steps: Vec<(u64, f32)> = (0..=200)
        .map(|i| {
            let rate = 1.0 - i as f32 / 200.0;
            let keep: Vec<u32> = counts.iter().map(|&n| keep_count(n, rate)).collect();
            (fixed + skeleton_all + leaf_bytes(&layout, &keep), rate)
        })
        .collect();
    let last = table.len() - 1;
    let mut rows = Vec::with_capacity(table.len());
    let mut strips = Vec::new();
    if let Some(dir) = &opts.strips {
        std::fs::create_dir_all(dir).map_err(|e| IterationEvalError::Strip(format!("{}: {e}", dir.display())))?;
    }
    for (k, e) in table.iter().enumerate() {
        let k8 = k as u8;
        let mut m = model.clone();
        m.branches.truncate(e.branches_end as usize);
        let exact: Vec<u32> = (0..m.leaves.len() as u32)
            .filter(|&i| m.leaves[i as usize].iteration <= k8)
            .collect();
        let level: Vec<u32> = lists
            .iter()
            .zip(&node_iteration)
            .filter(|(_, it)| **it <= k8)
            .flat_map(|(l, _)| l.iter().copied())
            .collect();
        let level_keep: Vec<u32> = counts
            .iter()
            .zip(&node_iteration)
            .map(|(&n, &it)| if it <= k8 { n } else { 0 })
            .collect();
        let bytes = fixed + u64::from(e.skeleton_bytes_end) + leaf_bytes(&layout, &level_keep);
        let exact_q = score(&render_all(&m, Some(&exact))?)?;
        let level_frames = render_all(&m, Some(&level))?;
        let level_q = score(&level_frames)?;
        let vmi = vmi_steps.iter().rev().find(|(b, _)| *b <= bytes).copied();
        let vmi_q = match vmi {
            Some((_, rate)) if k < last => {
                let subset: Vec<u32> = lists
                    .iter()
                    .flat_map(|l| l[..keep_count(l.len() as u32, rate) as usize].iter().copied())
                    .collect();
                let vmi_frames = render_all(&model, Some(&subset))?;
                if let Some(dir) = opts.strips.as_ref().filter(|_| k + STRIP_ROWS >= last) {
                    let path = dir.join(format!("{}-k{k}.png", d.name));
                    let views = [&level_frames[side], &vmi_frames[side], &refs[side]];
                    write_strip(&path, &views, res)?;
                    strips.push(path.display().to_string());
                }
                Some(score(&vmi_frames)?)
            }
            Some(_) => Some(level_q),
            None => None,
        };
        rows.push(IterationRow {
            k: k8,
            iteration_fraction: f64::from(k8) / f64::from(d.iterations.max(1)),
            branches: e.branches_end,
            skeleton_bytes: u64::from(e.skeleton_bytes_end),
            leaves_exact: exact.len() as u64,
            leaves_level: level.len() as u64,
            bytes,
            exact: exact_q,
            level: level_q,
            vmi_rate: vmi.map(|v| v.1),
            vmi_bytes: vmi.map_or(0, |v| v.0),
            vmi: vmi_q,
        });
    }
    let shape_fraction_iou_090 = rows
        .iter()
        .find(|r| r.exact.iou >= 0.9)
        .map(|r| f64::from(r.k) / f64::from(d.iterations));
    let level_shape_fraction_iou_090 = rows
        .iter()
        .find(|r| r.level.iou >= 0.9)
        .map(|r| f64::from(r.k) / f64::from(d.iterations));
    Ok(IterationEvalReport {
        name: d.name.clone(),
        iterations: d.iterations,
        leaves: u64::from(d.leaf_count),
        full_bytes,
        views: opts.views,
        resolution: res,
        rows,
        shape_fraction_iou_090,
        level_shape_fraction_iou_090,
        strips,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bake::{BakeOptions, bake_model};
    use crate::lsystem::Limits;
    use crate::species::{SpeciesSpec, grow_iterations};
    use canopy_shared::format::{LeafOrder, encode_tree};

    /// The demo's shrub grown 6 iterations, baked without stand-ins.
    fn shrub() -> DecodedTree {
        let spec = SpeciesSpec::from_toml_str(include_str!("../../assets/species/small_shrub.toml"))
            .unwrap_or_else(|e| panic!("{e}"));
        let model = grow_iterations(&spec, 6, &Limits::default()).unwrap_or_else(|e| panic!("{e}"));
        let opts = BakeOptions {
            order: LeafOrder::Generation,
            atlas: None,
            hull: None,
            cloud: None,
            ..BakeOptions::default()
        };
        let (baked, _) = bake_model(&model, &opts).unwrap_or_else(|e| panic!("{e}"));
        DecodedTree::decode(&encode_tree(&baked).unwrap_or_else(|e| panic!("{e}"))).unwrap_or_else(|e| panic!("{e}"))
    }

    #[test]
    fn fewer_iterations_cost_fewer_bytes_and_the_last_is_the_tree() {
        let tree = shrub();
        let opts = IterationEvalOptions {
            views: 2,
            resolution: 48,
            strips: Some(std::env::temp_dir().join(format!("canopy-eval-iterations-{}", std::process::id()))),
        };
        let rep = eval_iterations(&tree, &opts, &|| {}).unwrap_or_else(|e| panic!("{e}"));
        // One strip per iteration count in the last three below K, three views wide.
        assert!(
            !rep.strips.is_empty() && rep.strips.len() <= STRIP_ROWS,
            "{:?}",
            rep.strips
        );
        for p in &rep.strips {
            let img = image::open(p).unwrap_or_else(|e| panic!("{p}: {e}"));
            assert_eq!((img.width(), img.height()), (3 * 48, 48));
        }
        assert_eq!(rep.rows.len(), usize::from(rep.iterations) + 1);
        let last = rep.rows.last().unwrap_or_else(|| panic!("rows"));
        // Every iteration drawn: the full tree, pixel for pixel, at the full bytes.
        assert_eq!(last.bytes, rep.full_bytes);
        assert_eq!(last.leaves_exact, rep.leaves);
        assert!((last.exact.iou - 1.0).abs() < 1e-9 && (last.level.iou - 1.0).abs() < 1e-9);
        for w in rep.rows.windows(2) {
            assert!(w[0].bytes <= w[1].bytes && w[0].skeleton_bytes <= w[1].skeleton_bytes);
            // A leaf node keeps its later sub-branches' leaves: never fewer than the exact level.
            assert!(w[0].leaves_level >= w[0].leaves_exact);
        }
        // The first iteration alone is not the tree.
        assert!(rep.rows[0].exact.iou < 0.9, "{:?}", rep.rows[0].exact);
        assert!(rep.rows[0].bytes < rep.full_bytes);
    }

    #[test]
    fn bad_options_are_refused() {
        let tree = shrub();
        for (views, resolution) in [(0, 64), (2, 8)] {
            let bad = IterationEvalOptions {
                views,
                resolution,
                strips: None,
            };
            assert!(matches!(
                eval_iterations(&tree, &bad, &|| {}),
                Err(IterationEvalError::Options(_))
            ));
        }
    }
}

//! `eval-order`: how well each leaf order's prefixes look like the full tree (seed 004's
//! precision and recall), with and without seed 004's leaf enlargement.
//!
//! For every view (perspective, whole tree, directions that the VMI bake does not use: a
//! Fibonacci sphere turned by a fixed rotation, so no direction coincides with the bake's), the
//! full tree and every (order, rate, enlargement) simplification are rendered with the shared CPU
//! rasterizer, bark included. Figures, averaged over views:
//!
//! - **precision / recall** (surface agreement): a pixel agrees when both images show leaf there
//!   at depths within `SURFACE_TOLERANCE` × the tree's radius; precision = agreeing / leaf pixels
//!   of the simplification, recall = agreeing / leaf pixels of the full tree. Revealing leaves the
//!   full tree hides (deeper surface) costs precision, dropping visible leaves costs recall, and an
//!   enlarged leaf that covers its removed neighbour's pixels at about the same depth counts as
//!   right, as it should.
//! - **item precision / recall**: the same with "the same leaf" instead of "about the same depth"
//!   (strict; enlargement necessarily loses here).
//! - **coverage precision / recall**: the same on "any leaf or bark" masks (a plain subset always
//!   has coverage precision 1; enlargement trades it for recall).
//! - **SSIM** of the colour images over a grey background.
//!
//! A rate `R` keeps the first `round(n·(1 − R))` leaves of each node; enlargement scales the kept
//! leaves by `s = √((1 − R_l)/(1 − R_c))` with `R_l = 0`.
//!
//! The random order is a stochastic baseline: unless it is the file's own order (one draw, as
//! stored), it is drawn `random_draws` times (seeds `seed`, `seed + 1`, …) and its rows are the
//! means over draws, with the range of precision and recall.

use canopy_shared::format::leaf::keep_count;
use canopy_shared::format::{DecodedTree, LeafOrder};
use canopy_shared::metrics::{self, CoverageStats};
use canopy_shared::model::TreeModel;
use canopy_shared::raster::{
    BARK_ITEM, Camera, EMPTY_ITEM, Frame, Projection, RasterError, RasterMesh, RenderOptions, Scene, TreeMeshOptions,
    fibonacci_sphere, render,
};
use glam::{Quat, Vec3};
use rayon::prelude::*;
use serde::Serialize;

use crate::bake::{order, vmi};

/// Options of the evaluation.
#[derive(Debug, Clone)]
pub struct EvalOptions {
    /// Simplification rates to evaluate.
    pub rates: Vec<f32>,
    /// Views.
    pub views: usize,
    /// Square image size, pixels.
    pub resolution: u32,
    /// Seed of the first random order.
    pub seed: u64,
    /// Random orders drawn (seeds `seed`, `seed + 1`, …); the random rows are their means, with
    /// the range over draws. One draw is a sample of a stochastic baseline, not the baseline.
    pub random_draws: usize,
    /// VMI parameters, for orders computed here.
    pub vmi: vmi::VmiOptions,
}

impl Default for EvalOptions {
    fn default() -> Self {
        Self {
            rates: vec![0.5, 0.8, 0.9, 0.95, 0.98],
            views: 16,
            resolution: 256,
            seed: 7,
            random_draws: 5,
            vmi: vmi::VmiOptions::default(),
        }
    }
}

/// Why an evaluation failed.
#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    /// A rate outside [0, 1).
    #[error("rates must be in [0, 1), got {0}")]
    BadRate(f32),
    /// Rendering failed.
    #[error(transparent)]
    Raster(#[from] RasterError),
    /// A metric failed.
    #[error(transparent)]
    Metrics(#[from] metrics::MetricsError),
    /// An order could not be built.
    #[error(transparent)]
    Order(#[from] order::OrderError),
}

/// Depth tolerance of the surface agreement, as a fraction of the tree's bounding radius.
pub const SURFACE_TOLERANCE: f32 = 0.05;

/// Figures of one (order, enlargement, rate), means over views.
#[derive(Debug, Clone, Serialize)]
pub struct RateRow {
    /// Simplification rate.
    pub rate: f32,
    /// Leaves drawn.
    pub leaves: u64,
    /// Surface-agreement precision.
    pub precision: f64,
    /// Surface-agreement recall.
    pub recall: f64,
    /// Item-agreement precision.
    pub item_precision: f64,
    /// Item-agreement recall.
    pub item_recall: f64,
    /// Coverage precision.
    pub coverage_precision: f64,
    /// Coverage recall.
    pub coverage_recall: f64,
    /// Colour SSIM.
    pub ssim: f64,
    /// Over the draws of a stochastic order (random): the lowest and highest precision.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub precision_range: Option<[f64; 2]>,
    /// Over the draws of a stochastic order: the lowest and highest recall.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub recall_range: Option<[f64; 2]>,
}

/// One order's rows, plain and enlarged.
#[derive(Debug, Clone, Serialize)]
pub struct OrderReport {
    /// Order name.
    pub order: String,
    /// Where the order came from: `file` or `computed`.
    pub source: &'static str,
    /// Orders drawn and averaged (1 unless stochastic).
    pub draws: usize,
    /// Without enlargement.
    pub plain: Vec<RateRow>,
    /// With seed 004's enlargement.
    pub enlarged: Vec<RateRow>,
}

/// The whole report.
#[derive(Debug, Clone, Serialize)]
pub struct EvalReport {
    /// Tree name.
    pub name: String,
    /// Leaves of the full tree.
    pub leaves: u64,
    /// Views.
    pub views: usize,
    /// Image size.
    pub resolution: u32,
    /// One entry per order.
    pub orders: Vec<OrderReport>,
}

/// Eval view directions: a Fibonacci sphere turned by a fixed rotation, so none coincides with the
/// bake's Fibonacci views.
pub fn eval_directions(n: usize) -> Vec<Vec3> {
    let turn = Quat::from_axis_angle(Vec3::new(1.0, 2.0, 3.0).normalize(), 0.618);
    fibonacci_sphere(n).into_iter().map(|d| turn * d).collect()
}

/// The tree as a model whose leaves are the file's leaves, node by node, and each node's leaf
/// index list in the file's order.
pub(crate) fn flatten(tree: &DecodedTree) -> (TreeModel, Vec<Vec<u32>>) {
    let mut model = tree.to_model(0.0);
    model.leaves.clear();
    let mut lists = Vec::with_capacity(tree.node_leaves.len());
    for leaves in &tree.node_leaves {
        let base = model.leaves.len() as u32;
        model.leaves.extend_from_slice(leaves);
        lists.push((base..base + leaves.len() as u32).collect());
    }
    (model, lists)
}

pub(crate) fn render_tree(
    model: &TreeModel,
    subset: Option<&[u32]>,
    scale: f32,
    cam: &Camera,
    res: u32,
) -> Result<Frame, RasterError> {
    let mesh = RasterMesh::from_tree(
        model,
        &TreeMeshOptions {
            leaf_subset: subset,
            leaf_scale: scale,
            ..TreeMeshOptions::default()
        },
    );
    let materials = vmi::leaf_materials(model);
    let textures = [vmi::leaf_texture()];
    let scene = Scene::single(&mesh, &materials, &textures);
    render(&scene, cam, res, res, &RenderOptions::default())
}

fn leaf_items(f: &Frame) -> Vec<u32> {
    f.item
        .iter()
        .map(|&i| if i == BARK_ITEM { EMPTY_ITEM } else { i })
        .collect()
}

/// Eye distance of every leaf pixel (`None` for empty and bark pixels), from NDC depth in [0, 1]
/// of a perspective camera with planes `near`, `far`: `d = f·n / (f − z·(f − n))`.
fn leaf_distances(f: &Frame, near: f32, far: f32) -> Vec<Option<f32>> {
    f.item
        .iter()
        .zip(&f.depth)
        .map(|(&i, &z)| (i != BARK_ITEM && i != EMPTY_ITEM).then(|| far * near / (far - z * (far - near))))
        .collect()
}

/// Surface agreement of `approx` against `reference` (see the module doc).
fn surface_agreement(reference: &[Option<f32>], approx: &[Option<f32>], tolerance: f32) -> (f64, f64) {
    let (mut a, mut r, mut both) = (0u64, 0u64, 0u64);
    for (rr, aa) in reference.iter().zip(approx) {
        a += u64::from(aa.is_some());
        r += u64::from(rr.is_some());
        if let (Some(x), Some(y)) = (rr, aa) {
            both += u64::from((x - y).abs() <= tolerance);
        }
    }
    let ratio = |n: u64, d: u64| if d == 0 { 1.0 } else { n as f64 / d as f64 };
    (ratio(both, a), ratio(both, r))
}

/// Each leaf node's leaf indices, in one order.
type NodeLists = Vec<Vec<u32>>;

/// Evaluates the file's order and the others (random, area, and VMI when the file is not VMI)
/// on the same hierarchy. `tick` is called once per render.
pub fn eval_orders(tree: &DecodedTree, opts: &EvalOptions, tick: &(dyn Fn() + Sync)) -> Result<EvalReport, EvalError> {
    if let Some(&r) = opts.rates.iter().find(|r| !(0.0..1.0).contains(*r)) {
        return Err(EvalError::BadRate(r));
    }
    let (model, file_lists) = flatten(tree);
    let file_order = tree.directory.leaf_order;
    // (name, source, draws: one set of node lists per draw)
    let mut orders: Vec<(String, &'static str, Vec<NodeLists>)> =
        vec![(file_order.name().to_owned(), "file", vec![file_lists.clone()])];
    for o in [LeafOrder::Vmi, LeafOrder::Random, LeafOrder::Area] {
        if o == file_order {
            continue;
        }
        let draws = if o == LeafOrder::Random {
            opts.random_draws.max(1)
        } else {
            1
        };
        let mut sets = Vec::with_capacity(draws);
        for k in 0..draws as u64 {
            let mut lists = file_lists.clone();
            if o == LeafOrder::Vmi {
                vmi::vmi_order(&model, &tree.nodes, &mut lists, &opts.vmi)?;
            } else {
                order::order_leaves(&model, &mut lists, o, opts.seed.wrapping_add(k))?;
            }
            sets.push(lists);
        }
        orders.push((o.name().to_owned(), "computed", sets));
    }
    let (lo, hi) = (tree.directory.bounds_min, tree.directory.bounds_max);
    let center = (lo + hi) * 0.5;
    let radius = (hi - lo).length() * 0.5;
    let cams: Vec<Camera> = eval_directions(opts.views)
        .into_iter()
        .map(|d| Camera::orbit_perspective(center, radius.max(1e-3), d, 40f32.to_radians()))
        .collect();
    let res = opts.resolution;
    let refs: Vec<Frame> = cams
        .par_iter()
        .map(|c| {
            let f = render_tree(&model, None, 1.0, c, res);
            tick();
            f
        })
        .collect::<Result<_, _>>()?;

    let views = EvalViews {
        cams: &cams,
        refs: &refs,
        tolerance: SURFACE_TOLERANCE * radius,
        res,
    };
    let mut reports = Vec::new();
    for (name, source, draws) in &orders {
        let mut plain = Vec::new();
        let mut enlarged = Vec::new();
        for &rate in &opts.rates {
            for enlarge in [false, true] {
                let rows = draws
                    .iter()
                    .map(|lists| views.eval_prefix(&model, lists, rate, enlarge, tick))
                    .collect::<Result<Vec<_>, _>>()?;
                let row = mean_row(&rows);
                if enlarge { enlarged.push(row) } else { plain.push(row) }
            }
        }
        reports.push(OrderReport {
            order: name.clone(),
            source,
            draws: draws.len(),
            plain,
            enlarged,
        });
    }
    Ok(EvalReport {
        name: tree.directory.name.clone(),
        leaves: model.leaves.len() as u64,
        views: opts.views,
        resolution: res,
        orders: reports,
    })
}

/// The mean of rows of the same (rate, enlargement) over draws, with the precision and recall
/// ranges when there is more than one draw.
fn mean_row(rows: &[RateRow]) -> RateRow {
    let n = rows.len().max(1) as f64;
    let mean = |f: fn(&RateRow) -> f64| rows.iter().map(f).sum::<f64>() / n;
    let range = |f: fn(&RateRow) -> f64| {
        (rows.len() > 1).then(|| {
            let lo = rows.iter().map(f).fold(f64::INFINITY, f64::min);
            let hi = rows.iter().map(f).fold(f64::NEG_INFINITY, f64::max);
            [lo, hi]
        })
    };
    RateRow {
        rate: rows.first().map_or(0.0, |r| r.rate),
        leaves: rows.first().map_or(0, |r| r.leaves),
        precision: mean(|r| r.precision),
        recall: mean(|r| r.recall),
        item_precision: mean(|r| r.item_precision),
        item_recall: mean(|r| r.item_recall),
        coverage_precision: mean(|r| r.coverage_precision),
        coverage_recall: mean(|r| r.coverage_recall),
        ssim: mean(|r| r.ssim),
        precision_range: range(|r| r.precision),
        recall_range: range(|r| r.recall),
    }
}

/// The evaluation's cameras and full-detail renders.
struct EvalViews<'a> {
    cams: &'a [Camera],
    refs: &'a [Frame],
    /// Surface-agreement depth tolerance, metres.
    tolerance: f32,
    res: u32,
}

impl EvalViews<'_> {
    /// Figures of one order's prefixes at `rate`, plain or enlarged, averaged over the views.
    fn eval_prefix(
        &self,
        model: &TreeModel,
        lists: &[Vec<u32>],
        rate: f32,
        enlarge: bool,
        tick: &(dyn Fn() + Sync),
    ) -> Result<RateRow, EvalError> {
        let res = self.res;
        let subset: Vec<u32> = lists
            .iter()
            .flat_map(|l| l[..keep_count(l.len() as u32, rate) as usize].iter().copied())
            .collect();
        let scale = if enlarge { (1.0 / (1.0 - rate)).sqrt() } else { 1.0 };
        let per_view: Vec<[f64; 7]> = self
            .cams
            .par_iter()
            .zip(self.refs.par_iter())
            .map(|(cam, r)| -> Result<[f64; 7], EvalError> {
                let f = render_tree(model, Some(&subset), scale, cam, res)?;
                tick();
                let (near, far) = match cam.projection {
                    Projection::Perspective { near, far, .. } | Projection::Orthographic { near, far, .. } => {
                        (near, far)
                    }
                };
                let (p, rc) = surface_agreement(
                    &leaf_distances(r, near, far),
                    &leaf_distances(&f, near, far),
                    self.tolerance,
                );
                let items: CoverageStats = metrics::item_agreement(&leaf_items(r), &leaf_items(&f), EMPTY_ITEM)?;
                let cov = metrics::coverage(&r.coverage(), &f.coverage())?;
                let ssim = metrics::ssim_rgba(&r.color, &f.color, res, res, [128, 128, 128])?;
                Ok([p, rc, items.precision, items.recall, cov.precision, cov.recall, ssim])
            })
            .collect::<Result<_, _>>()?;
        let n = per_view.len().max(1) as f64;
        let mean = |k: usize| per_view.iter().map(|v| v[k]).sum::<f64>() / n;
        Ok(RateRow {
            rate,
            leaves: subset.len() as u64,
            precision: mean(0),
            recall: mean(1),
            item_precision: mean(2),
            item_recall: mean(3),
            coverage_precision: mean(4),
            coverage_recall: mean(5),
            ssim: mean(6),
            precision_range: None,
            recall_range: None,
        })
    }
}

/// Renders needed by [`eval_orders`] for a file in order `file_order` (for a progress bar).
pub fn render_count(opts: &EvalOptions, file_order: LeafOrder) -> u64 {
    let draws: usize = [LeafOrder::Vmi, LeafOrder::Random, LeafOrder::Area]
        .into_iter()
        .filter(|&o| o != file_order)
        .map(|o| {
            if o == LeafOrder::Random {
                opts.random_draws.max(1)
            } else {
                1
            }
        })
        .sum::<usize>()
        + 1;
    (opts.views * (1 + draws * opts.rates.len() * 2)) as u64
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::bake::cloud::leaf_ball;
    use crate::bake::{BakeOptions, bake_model};
    use canopy_shared::format::encode_tree;
    use std::sync::atomic::{AtomicU64, Ordering};

    #[test]
    fn random_rows_are_means_over_draws_and_every_render_is_counted() {
        let model = leaf_ball(600, 0.25, 5);
        let opts = BakeOptions {
            atlas: None,
            hull: None,
            cloud: None,
            ..BakeOptions::default()
        };
        let (baked, _) = bake_model(&model, &opts).unwrap();
        let tree = DecodedTree::decode(&encode_tree(&baked).unwrap()).unwrap();
        let eopts = EvalOptions {
            rates: vec![0.5, 0.9],
            views: 3,
            resolution: 64,
            random_draws: 3,
            ..EvalOptions::default()
        };
        let renders = AtomicU64::new(0);
        let rep = eval_orders(&tree, &eopts, &|| {
            renders.fetch_add(1, Ordering::Relaxed);
        })
        .unwrap();
        assert_eq!(
            renders.load(Ordering::Relaxed),
            render_count(&eopts, tree.directory.leaf_order)
        );
        let names: Vec<(&str, usize)> = rep.orders.iter().map(|o| (o.order.as_str(), o.draws)).collect();
        assert_eq!(names, [("vmi", 1), ("random", 3), ("area", 1)]);
        for o in &rep.orders {
            for row in o.plain.iter().chain(&o.enlarged) {
                assert_eq!(row.precision_range.is_some(), o.draws > 1, "{}", o.order);
                if let (Some(p), Some(r)) = (row.precision_range, row.recall_range) {
                    assert!(
                        p[0] <= row.precision && row.precision <= p[1],
                        "{p:?} {}",
                        row.precision
                    );
                    assert!(r[0] <= row.recall && row.recall <= r[1], "{r:?} {}", row.recall);
                    assert!(p[0] < p[1] || r[0] < r[1], "three seeds drew the same prefixes");
                }
                assert!((0.0..=1.0).contains(&row.precision) && (0.0..=1.0).contains(&row.recall));
            }
        }
        // A plain prefix shows a subset of the leaves: coverage precision 1, recall below 1.
        let vmi = &rep.orders[0].plain[1];
        assert!(vmi.coverage_precision > 0.999 && vmi.coverage_recall < 0.9, "{vmi:?}");
    }
}

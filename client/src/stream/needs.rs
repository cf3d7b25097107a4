//! The needs stage: what each model is needed for this frame, summed over its visible
//! instances, and the visual gain of each leaf node still to fetch. The selection stage fills the
//! per-representation gains as it meets instances; this module holds the type and the two
//! reductions over the geometry trees.
//!
//! Conventions: a gain is a projected height squared (pixels², capped at 10⁴ px), summed over
//! the instances that want a unit; a leaf node's gain is per leaf.

use super::geometry::{TreeState, geo_keep};
use super::model::Models;
use super::select::{KeepOf, Selection};
use super::view::{Camera, Viewport};
use crate::lod::{projected_height, sphere_distance};

/// Per-model needs gathered over the instances of one frame (buffers kept between frames).
#[derive(Debug, Default)]
pub(crate) struct Need {
    /// Some instance of the model is visible this frame.
    pub used: bool,
    /// Some instance of the model is drawn as geometry.
    pub geometry: bool,
    /// Some instance would be drawn as geometry, but the model's geometry part (node table
    /// and materials) has not been opened yet.
    pub geometry_missing: bool,
    /// Most skeleton iterations any geometry instance draws (valid when `geometry`).
    pub iterations: u8,
    /// Most leaves any instance keeps of each leaf node (valid when `geometry`).
    pub keep: Vec<u32>,
    /// Summed gain per hull level; `None`: not needed.
    pub hull: Vec<Option<f64>>,
    /// Summed gain per atlas image (`frame × resolutions + resolution`); `None`: not needed.
    pub images: Vec<Option<f64>>,
    /// Summed gain per billboard-cloud level; `None`: not needed.
    pub clouds: Vec<Option<f64>>,
}

/// Each model's keep maxima over its geometry trees, in draw order (culled nodes keep 0,
/// which leaves it alone).
pub(crate) fn keep_maxima(models: &Models, trees: &[TreeState], sel: &mut Selection) {
    for g in &sel.geo {
        let Some(idx) = models.index(g.model) else {
            continue;
        };
        let keep = geo_keep(trees, g, idx);
        for (n, &k) in sel.needs[g.model].keep.iter_mut().zip(keep) {
            *n = (*n).max(k);
        }
    }
}

/// Visual gain per leaf of model `m`'s leaf nodes in `nodes` (the rest stay 0): the most any
/// visible instance gives, `(projected node height)² / leaves`.
pub(crate) fn leaf_gains(
    models: &Models,
    sel: &Selection,
    m: usize,
    cam: &Camera,
    vp: &Viewport,
    nodes: &[usize],
    out: &mut [f32],
) {
    let Some(idx) = models.index(m) else { return };
    for g in sel.geo.iter().filter(|g| g.model == m) {
        let vis = (g.keep == KeepOf::Masked).then_some(&g.culled_vis);
        for &o in nodes {
            if vis.is_some_and(|v| !v[o]) {
                continue;
            }
            let node = &idx.nodes[idx.leaf_nodes[o]];
            let nc = g.model_m.transform_point3(node.sphere_center);
            let nd = sphere_distance(cam.eye, nc, node.sphere_radius * g.scale);
            let npx = projected_height(2.0 * node.sphere_radius * g.scale, nd, vp.height as f32, vp.fov_y).min(1e4);
            let gain = npx * npx / node.leaf_count.max(1) as f32;
            out[o] = out[o].max(gain);
        }
    }
}

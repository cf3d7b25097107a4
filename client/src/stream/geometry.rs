//! The geometry stage: each tree drawn as geometry this frame gets its per-leaf-node keep counts.
//! Nodes are culled where the tree crosses a frustum plane, switch control advances the
//! per-tree LOD state for the visible nodes (seed 004 culls first), and keep counts are lowered
//! to the pixel budget where it limits the tree. It also owns the lifetime of that state: a tree
//! no longer drawn as geometry loses it.
//!
//! With [`StreamOptions::plan_on_pool`](super::StreamOptions::plan_on_pool) the trees run on
//! rayon's pool (one job per tree, or per batch when the selection loop hands them over as it
//! meets them); no job reads what another writes, so the result does not depend on it or on the
//! thread count.

use std::sync::Arc;

use super::model::{Model, ModelIndex, ModelState};
use super::select::{GeoDraw, KeepOf, Selection};
use crate::lod::{Frustum, LeafTable, LodParams, TreeLodState, budget_keep, visible_leaves_world};

/// One tree's share of the geometry stage's state.
#[derive(Debug, Default)]
pub(crate) struct TreeState {
    /// Switch-control state while the tree is drawn as geometry.
    pub lod: Option<Box<TreeLodState>>,
    /// Frame (+ 1) in which the tree was last drawn as geometry.
    pub lod_frame: u64,
}

impl TreeState {
    /// Marks the tree drawn as geometry in `frame`: at full rate it keeps no switch-control
    /// state, otherwise its state is made on first use (over the model's `table`). Whether it
    /// has state.
    pub fn begin(&mut self, full_rate: bool, table: &Arc<LeafTable>, frame: u64) -> bool {
        self.lod_frame = frame + 1;
        if full_rate {
            self.lod = None;
            false
        } else {
            self.lod
                .get_or_insert_with(|| Box::new(TreeLodState::with_table(Arc::clone(table))));
            true
        }
    }
}

/// The geometry stage's state: one [`TreeState`] per loaded instance (instance order) and the
/// trees whose state was advanced last frame.
#[derive(Debug, Default)]
pub(crate) struct GeometryStates {
    pub trees: Vec<TreeState>,
    live: Vec<u32>,
}

impl GeometryStates {
    /// Follows the instances into their new order: `from[k]` is the index instance `k` had
    /// before (`None`: a new instance, or a record that replaced one, with fresh state).
    pub fn reorder(&mut self, from: &[Option<usize>]) {
        let mut old = std::mem::take(&mut self.trees);
        self.trees = from
            .iter()
            .map(|o| o.and_then(|o| old.get_mut(o).map(std::mem::take)).unwrap_or_default())
            .collect();
    }

    /// Counts every tree holding a state as live (after the instances were placed again).
    pub fn refresh_live(&mut self) {
        self.live = (0..self.trees.len() as u32)
            .filter(|&i| self.trees[i as usize].lod.is_some())
            .collect();
    }
}

/// Geometry trees per frame from which their updates run on the thread pool (with
/// [`StreamOptions::plan_on_pool`](super::StreamOptions::plan_on_pool)): below it the pool's hand-off costs more than it saves.
/// The instance loop starts them on the pool as it meets them when the previous frame had this
/// many; otherwise they run after the loop.
pub const PARALLEL_GEOMETRY_TREES: usize = 4;

/// Geometry trees per job when the instance loop hands them to the pool as it goes: fewer
/// hand-offs (each may wake a sleeping worker) against a finer split of the work.
pub(crate) const GEOMETRY_BATCH: usize = 8;

/// Runs `f` inside a rayon scope whose calling thread is this one (jobs spawned on it go to the
/// pool) when `on`, else with no pool.
pub(crate) fn with_pool<'s, R>(on: bool, f: impl FnOnce(Option<&rayon::Scope<'s>>) -> R) -> R {
    if on {
        rayon::in_place_scope(|s| f(Some(s)))
    } else {
        f(None)
    }
}

/// The frame's geometry trees, after the selection loop ([`GeometryJobs::run`] each), when the
/// loop did not start them on the pool already: with [`PARALLEL_GEOMETRY_TREES`] or more (and
/// the pool allowed) they run on the thread pool; the result does not depend on it.
pub(crate) fn run_after_loop(
    models: &[Model],
    trees: &mut [TreeState],
    lod: &LodParams,
    on_pool: bool,
    frustum: &Frustum,
    dt: f32,
    sel: &mut Selection,
) {
    // The instances of the geometry draws, in draw order (ascending instance index).
    let draws = sel.geo.len();
    let mut jobs: Vec<(&mut TreeState, &mut GeoDraw)> = Vec::with_capacity(draws);
    // Split off each draw's instance in turn: O(draws), not a pass over every instance.
    let (mut rest, mut base): (&mut [TreeState], usize) = (trees, 0);
    for g in &mut sel.geo {
        let i = g.inst as usize;
        let Some(k) = i.checked_sub(base).filter(|&k| k < rest.len()) else {
            continue;
        };
        let Some((inst, tail)) = std::mem::take(&mut rest)[k..].split_first_mut() else {
            break;
        };
        jobs.push((inst, g));
        (rest, base) = (tail, i + 1);
    }
    // One geometry draw per instance, pushed in instance order: every draw found its own.
    debug_assert_eq!(jobs.len(), draws, "geometry draws out of instance order");
    let ctx = GeometryJobs {
        models,
        lod,
        frustum,
        dt,
    };
    let work = |(tree, g): &mut (&mut TreeState, &mut GeoDraw)| ctx.run(tree, g);
    if on_pool && jobs.len() >= PARALLEL_GEOMETRY_TREES {
        use rayon::prelude::*;
        jobs.par_iter_mut().for_each(work);
    } else {
        jobs.iter_mut().for_each(work);
    }
}

/// Trees that stopped being drawn as geometry (not drawn so in `frame`) lose their switch
/// state; `live` becomes this frame's geometry trees.
pub(crate) fn retire_states(states: &mut GeometryStates, geo: &[GeoDraw], frame: u64) {
    let GeometryStates { trees, live } = states;
    for &i in live.iter() {
        if let Some(tree) = trees.get_mut(i as usize)
            && tree.lod_frame != frame + 1
        {
            tree.lod = None;
        }
    }
    live.clear();
    live.extend(geo.iter().map(|g| g.inst));
}

/// Keep counts of a geometry draw, culled nodes at 0.
pub(crate) fn geo_keep<'a>(trees: &'a [TreeState], g: &'a GeoDraw, idx: &'a ModelIndex) -> &'a [u32] {
    match g.keep {
        KeepOf::Full => idx.layout.leaf_counts(),
        KeepOf::State => trees[g.inst as usize]
            .lod
            .as_ref()
            .map_or(idx.layout.leaf_counts(), |s| s.keep()),
        KeepOf::Masked => &g.culled_keep,
    }
}

/// What every geometry job of a frame reads.
#[derive(Clone, Copy)]
pub(crate) struct GeometryJobs<'s> {
    pub models: &'s [Model],
    pub lod: &'s LodParams,
    pub frustum: &'s Frustum,
    pub dt: f32,
}

impl<'s> GeometryJobs<'s> {
    /// Runs [`Self::run`] for each tree of `batch` on the pool, in order, and sends each
    /// result back with its draw index.
    pub fn spawn(
        self,
        pool: &rayon::Scope<'s>,
        batch: Vec<(u32, &'s mut TreeState, GeoDraw)>,
        done: &std::sync::mpsc::Sender<(u32, GeoDraw)>,
    ) {
        let done = done.clone();
        pool.spawn(move |_| {
            for (gi, tree, mut g) in batch {
                self.run(tree, &mut g);
                // The receiver lives until the scope has ended.
                let _ = done.send((gi, g));
            }
        });
    }

    /// One geometry tree's share of the frame: nodes culled where the tree crosses a frustum
    /// plane, then switch control advanced by `dt` for the visible nodes (when it has state;
    /// seed 004 culls first), keep counts lowered to the pixel budget where it limits the tree.
    /// Reads nothing another tree's job writes.
    pub fn run(self, tree: &mut TreeState, g: &mut GeoDraw) {
        let ModelState::Open(idx) = &self.models[g.model].state else {
            return;
        };
        // Node culling only for trees that cross a frustum plane. Planes every node sphere
        // is inside of (with a margin for rounding) pass every node: test only the others.
        let crossing = self
            .frustum
            .crossing(g.center, idx.lod.node_reach * g.scale * 1.0001 + 0.01);
        let culls = !crossing.planes().is_empty();
        g.culled_vis.clear();
        if culls {
            // The crossing planes taken into the model's frame, so that the walk reads the
            // model's node spheres (shared by its instances, and so mostly in cache) instead of
            // placed ones.
            visible_leaves_world(
                &crossing.in_frame_of(g.model_m),
                &idx.lod.node_spheres,
                &idx.nodes,
                &idx.lod.subtree_reach,
                &idx.lod.leaves_before,
                1.0,
                &mut g.culled_vis,
            );
        }
        if let (Some(eye), Some(state)) = (g.eye_model, tree.lod.as_mut()) {
            let mut p = self.lod.clone();
            p.near /= g.scale;
            p.far /= g.scale;
            state.update_visible(&p, eye, self.dt, &g.culled_vis);
        }
        let counts = idx.layout.leaf_counts();
        let keep = match (g.keep, &tree.lod) {
            (KeepOf::State, Some(st)) => st.keep(),
            _ => counts,
        };
        // Leaf nodes of branches born after the drawn iterations keep nothing.
        let fewer_iterations = g.iterations < idx.lod.max_leaf_iteration;
        if !culls && !g.budget.limits() && !fewer_iterations {
            return;
        }
        g.culled_keep.clear();
        if !culls {
            g.culled_keep.extend_from_slice(keep);
            g.culled_vis.resize(keep.len(), true);
        } else if g.culled_vis.len() == keep.len() {
            // Branch-free, so that it vectorises: 0 where culled.
            g.culled_keep
                .extend(keep.iter().zip(&g.culled_vis).map(|(&k, &v)| k * u32::from(v)));
        } else {
            // Not one flag per leaf node (malformed tables): culled wherever there is none.
            let vis = &g.culled_vis;
            g.culled_keep.extend(
                keep.iter()
                    .enumerate()
                    .map(|(o, &k)| if vis.get(o) == Some(&true) { k } else { 0 }),
            );
        }
        if g.budget.limits() {
            let f = g.budget.keep_fraction;
            for (k, &n) in g.culled_keep.iter_mut().zip(counts) {
                *k = (*k).min(budget_keep(n, f));
            }
        }
        if fewer_iterations {
            for (k, &it) in g.culled_keep.iter_mut().zip(&idx.lod.leaf_iteration) {
                if it > g.iterations {
                    *k = 0;
                }
            }
        }
        g.keep = KeepOf::Masked;
    }
}

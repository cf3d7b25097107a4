//! Per-tree glue: culling, representation and the per-node rates of one tree instance.
//!
//! Node records are in the model's frame; an instance is placed by a transform. The helpers here
//! take the eye already transformed into the model frame (`eye_model = instance⁻¹ · eye`), which
//! is exact for rigid transforms with uniform scale 1; for a scaled instance pass the scaled
//! distances yourself via the lower-level functions.

use std::sync::Arc;

use canopy_shared::format::NodeRecord;
use canopy_shared::format::leaf::keep_count;
use canopy_shared::format::node::NodeKind;
use glam::{Mat4, Vec3, Vec4};

use super::frustum::Frustum;
use super::projection::{LadderStep, Representation, choose_representation, projected_height};
use super::rate::{RateConsts, TreeStats, combine, f1_layer, f3_density};
use super::switch::SwitchState;
use super::{LodParams, clamp01, sphere_distance};

/// Marks the nodes whose bounding sphere (transformed by `model`) may be visible; a culled node
/// culls its whole subtree (`subtree_end`) in one step.
pub fn visible_nodes(frustum: &Frustum, model: Mat4, nodes: &[NodeRecord]) -> Vec<bool> {
    let mut out = Vec::new();
    visible_nodes_world(frustum, &world_spheres(model, nodes), nodes, &mut out);
    out
}

/// The node spheres placed by `model` (centre, radius): what [`visible_nodes`] tests, computed
/// once for an instance that stays in view.
pub fn world_spheres(model: Mat4, nodes: &[NodeRecord]) -> Vec<Vec4> {
    let scale = model.to_scale_rotation_translation().0.abs().max_element();
    nodes
        .iter()
        .map(|n| model.transform_point3(n.sphere_center).extend(n.sphere_radius * scale))
        .collect()
}

/// [`visible_nodes`] from [`world_spheres`], into `out`.
pub fn visible_nodes_world(frustum: &Frustum, spheres: &[Vec4], nodes: &[NodeRecord], out: &mut Vec<bool>) {
    out.clear();
    out.resize(nodes.len(), false);
    let mut i = 0usize;
    while i < nodes.len().min(spheres.len()) {
        let s = spheres[i];
        if frustum.intersects_sphere(s.truncate(), s.w) {
            out[i] = true;
            i += 1;
        } else {
            i = (nodes[i].subtree_end as usize).max(i + 1);
        }
    }
}

/// Node `i`'s subtree as [`visible_nodes_world`] skips it: `i .. max(subtree_end, i + 1)`, cut
/// at `n`.
#[inline]
fn skip_end(nodes: &[NodeRecord], i: usize, n: usize) -> usize {
    (nodes[i].subtree_end as usize).max(i + 1).min(n)
}

/// Per node (model frame): the radius about its sphere centre of a sphere holding every node
/// sphere of its subtree (as [`visible_nodes_world`] skips it), itself included; infinite when
/// infinite, and for every node once the scan has read `SUBTREE_REACH_WORK` × `nodes.len()`
/// records (a malformed file whose subtrees all span the rest would cost O(n²)). A NaN centre
/// or radius is left out of the maximum; such a node can never be accepted by
/// [`visible_leaves_world`] anyway (its plane distances are NaN). A world sphere of this radius
/// (scaled, with a margin) wholly inside every plane means every node of the subtree passes
/// the frustum test; an infinite reach is never inside.
pub fn subtree_reach(nodes: &[NodeRecord]) -> Vec<f32> {
    let n = nodes.len();
    let budget = n.saturating_mul(SUBTREE_REACH_WORK);
    let mut work = 0usize;
    (0..n)
        .map(|i| {
            let end = skip_end(nodes, i, n);
            work = work.saturating_add(end - i);
            if work > budget {
                return f32::INFINITY;
            }
            let c = nodes[i].sphere_center;
            let r = nodes[i..end]
                .iter()
                .map(|m| m.sphere_center.distance(c) + m.sphere_radius.max(0.0))
                .fold(0f32, f32::max);
            if r.is_finite() { r } else { f32::INFINITY }
        })
        .collect()
}

/// Records [`subtree_reach`] may read per node before it gives up (well-formed hierarchies read
/// about their depth, under 20).
const SUBTREE_REACH_WORK: usize = 64;

/// Per node, the leaf nodes before it (`nodes.len() + 1` entries): leaf ordinals of the nodes
/// `a..b` are `before[a]..before[b]`.
pub fn leaves_before(nodes: &[NodeRecord]) -> Vec<u32> {
    let mut out = Vec::with_capacity(nodes.len() + 1);
    let mut k = 0u32;
    out.push(0);
    for n in nodes {
        k += u32::from(n.kind == NodeKind::Leaf);
        out.push(k);
    }
    out
}

/// [`visible_nodes_world`] read at the leaf nodes: appends one visibility per leaf ordinal to
/// `vis_out`. `reach` is [`subtree_reach`], `before` [`leaves_before`] and `scale` the
/// instance's scale (as [`world_spheres`] takes it).
///
/// The same result as testing every node: a subtree whose reach sphere is wholly inside every
/// plane has every node sphere inside (each is within the reach of the subtree's root), so the
/// walk would visit and keep each of them; it is kept in one step instead.
pub fn visible_leaves_world(
    frustum: &Frustum,
    spheres: &[Vec4],
    nodes: &[NodeRecord],
    reach: &[f32],
    before: &[u32],
    scale: f32,
    vis_out: &mut Vec<bool>,
) {
    let n = nodes.len().min(spheres.len());
    if before.len() != nodes.len() + 1 || reach.len() != nodes.len() {
        // Not what the tables promise: the node walk, gathered.
        let mut vis = Vec::new();
        visible_nodes_world(frustum, spheres, nodes, &mut vis);
        let leaves = nodes.iter().enumerate().filter(|(_, m)| m.kind == NodeKind::Leaf);
        vis_out.extend(leaves.map(|(ni, _)| vis[ni]));
        return;
    }
    let total = before[nodes.len()] as usize;
    // Margins for rounding: world centres and plane distances are computed in f32.
    let (rel, abs) = (scale.abs() * 1.0001, 0.01);
    let planes = frustum.planes();
    let mut i = 0usize;
    while i < n {
        let s = spheres[i];
        let (c, r) = (s.truncate(), s.w.max(0.0));
        let inner = reach[i] * rel + abs;
        let mut culled = false;
        let mut inside = true;
        for p in planes {
            let d = p.truncate().dot(c) + p.w;
            if !(d.is_nan() || d >= -r) {
                culled = true;
                break;
            }
            // False for NaN and for an infinite reach. Rounding of f32 centres and plane
            // distances grows with the coordinates: the slack follows them.
            let slack = 8.0 * f32::EPSILON * (p.truncate().abs().dot(c.abs()) + p.w.abs());
            inside &= inner.is_finite() && d >= inner + slack;
        }
        if culled || inside {
            let end = skip_end(nodes, i, n);
            let (a, b) = (before[i] as usize, before[end] as usize);
            vis_out.extend(std::iter::repeat_n(!culled, b - a));
            i = end;
        } else {
            if nodes[i].kind == NodeKind::Leaf {
                vis_out.push(true);
            }
            i += 1;
        }
    }
    // Nodes the walk never reached.
    vis_out.extend(std::iter::repeat_n(false, total - before[i] as usize));
}

/// Seed 000 representation of a tree of `height` whose bounding sphere is (`center`, `radius`).
pub fn tree_representation(
    ladder: &[LadderStep],
    height: f32,
    eye: Vec3,
    center: Vec3,
    radius: f32,
    screen_px: f32,
    fov_y: f32,
) -> Option<Representation> {
    let d = sphere_distance(eye, center, radius);
    choose_representation(ladder, projected_height(height, d, screen_px, fov_y))
}

/// The per-leaf-node data the rates read, gathered once per model (leaf-node ordinal order) and
/// shared by every instance of it.
#[derive(Debug, Clone)]
pub struct LeafTable {
    stats: TreeStats,
    /// One record per leaf node: what one evaluation reads lies together.
    leaves: Vec<LeafRec>,
}

/// What the rates read of one leaf node.
#[derive(Debug, Clone, Copy)]
struct LeafRec {
    center: Vec3,
    radius: f32,
    /// Unit growth direction (valid when `has_growth`; degenerate ones give f5 = 0).
    growth: Vec3,
    has_growth: bool,
    branch_level: u8,
    sphere_layer: u8,
    density: f32,
    leaf_count: u32,
}

impl LeafTable {
    /// The leaf nodes of a node table.
    pub fn new(nodes: &[NodeRecord]) -> Self {
        Self {
            stats: TreeStats::from_nodes(nodes),
            leaves: nodes
                .iter()
                .filter(|n| n.kind == NodeKind::Leaf)
                .map(|n| {
                    let growth = n.growth_direction.try_normalize();
                    LeafRec {
                        center: n.sphere_center,
                        radius: n.sphere_radius,
                        growth: growth.unwrap_or(Vec3::ZERO),
                        has_growth: growth.is_some(),
                        branch_level: n.branch_level,
                        sphere_layer: n.sphere_layer,
                        density: n.leaf_density,
                        leaf_count: n.leaf_count,
                    }
                })
                .collect(),
        }
    }

    /// Leaf nodes.
    pub fn len(&self) -> usize {
        self.leaves.len()
    }

    /// Whether there are no leaf nodes.
    pub fn is_empty(&self) -> bool {
        self.leaves.is_empty()
    }

    /// Seed 004's proposal for leaf node `i` seen from `eye` with `current` in force: the same
    /// factors as [`super::rate::node_rate`] (bit for bit), plus what [`still_radius`] needs.
    #[inline]
    fn propose(&self, p: &LodParams, k: &RateConsts, i: usize, eye: Vec3, current: f32) -> Proposal {
        let l = &self.leaves[i];
        let los = l.center - eye;
        let len = los.length();
        let d = len - l.radius.max(0.0);
        let distance = if d.is_finite() { d.max(0.0) } else { 0.0 };
        let rcp = len.recip();
        let cos_growth = if l.has_growth && rcp.is_finite() && rcp > 0.0 {
            (los * rcp).dot(l.growth)
        } else {
            f32::NAN
        };
        // NaN (no growth direction, eye at the centre) reads as 0, as in `f5_direction`.
        let f5 = if cos_growth.is_nan() { 0.0 } else { clamp01(cos_growth) };
        let f = [
            f1_layer(p, l.sphere_layer),
            k.f2(p, l.branch_level, distance),
            f3_density(&self.stats, l.density, current),
            k.f4(p, distance),
            f5,
        ];
        Proposal {
            rate: combine(p, f),
            f,
            distance,
            sight: len,
            cos_growth,
        }
    }

    /// `q` again with `current` in force instead: only f3 reads it.
    #[inline]
    fn repropose(&self, p: &LodParams, i: usize, q: Proposal, current: f32) -> Proposal {
        let mut f = q.f;
        f[2] = f3_density(&self.stats, self.leaves[i].density, current);
        Proposal {
            rate: combine(p, f),
            f,
            ..q
        }
    }
}

#[derive(Debug, Clone, Copy)]
struct Proposal {
    rate: f32,
    f: [f32; 5],
    distance: f32,
    /// `|centre − eye|`.
    sight: f32,
    /// Cosine of the angle between the line of sight and the growth direction, unclipped (f5
    /// before `clamp01`); NaN when f5 is 0 for want of either direction.
    cos_growth: f32,
}

/// How far (model frame) the eye may move before a leaf node's proposal could differ from the
/// rate in force (`current`) by switch control's step threshold; 0 when it may already. `q` must
/// be the proposal made with `current` in force (f3 reads it). While the eye stays
/// inside, switch control provably applies no change, so the node need not be evaluated.
///
/// Bounds, for an eye displacement `δ` (the sphere distance `d` moves by at most `δ`): on
/// `near < d < far`, `|Δf2| ≤ k1·BL/ln h·δ/d_min` and `|Δf4| ≤ k3/ln 10·δ/d_min`; beyond `far`
/// both are constant; the line of sight turns by at most `φ = asin(x)`, `x = δ/|centre − eye| < 1`,
/// so f5 = clip(cos θ) stays between clip(cos(θ ± φ)) (taken as 1 and 0 past 0 and π): exactly 0
/// while a node faces away by more than φ, second order in φ near θ = 0 (without the angle,
/// `asin(x) ≤ x/(1 − x)`);
/// f1 and f3 (the rate in force) do not move. The step threshold is monotone in `d`, so its
/// smallest value on `[d − δ, d + δ]` is at an end. Intervals that hold `near` or `far` (where f2
/// and f4 jump) give 0.
fn still_radius(p: &LodParams, k: &RateConsts, branch_level: u8, has_growth: bool, q: Proposal, current: f32) -> f32 {
    let Some(bound) = StillBound::new(p, k, branch_level, has_growth, q, current) else {
        return 0.0;
    };
    let first = bound.first_guess();
    for f in [1.0, 0.9, 0.7, 0.5, 0.3, 0.1] {
        let delta = first * f;
        if delta.is_finite() && delta > 0.0 && bound.fits(delta) {
            return delta;
        }
    }
    0.0
}

/// The bound of [`still_radius`] for one leaf node's proposal.
struct StillBound<'a> {
    p: &'a LodParams,
    /// `|proposal − rate in force|`.
    gap: f32,
    /// Sphere distance.
    d0: f32,
    /// `|centre − eye|`.
    sight: f32,
    /// Step threshold at `d0`.
    step0: f32,
    /// Bound on `|Δ(α2·f2 + α4·f4)|` per metre of eye movement, times the distance.
    a: f32,
    /// `|α5|`, 0 without a growth direction.
    b: f32,
    /// `cos θ` and `sin θ` (θ: line of sight to growth direction; NaN when unknown, then f5
    /// is bounded by the angle alone). `sin θ` is rounded up (see [`Self::new`]).
    cos: f32,
    sin: f32,
}

impl<'a> StillBound<'a> {
    /// Float slack: the proposal itself is computed with rounding.
    const SLACK: f32 = 1e-5;

    /// `None` when switch control may already apply a change (no room under the threshold).
    fn new(
        p: &'a LodParams,
        k: &RateConsts,
        branch_level: u8,
        has_growth: bool,
        q: Proposal,
        current: f32,
    ) -> Option<Self> {
        let gap = (q.rate - current).abs();
        let d0 = q.distance;
        let step0 = SwitchState::step_threshold(p, d0);
        // Written to be false for NaN.
        let room = step0 - gap > Self::SLACK && q.sight > 0.0;
        if !room {
            return None;
        }
        let bl = f32::from(branch_level).min(k.bl_max);
        let a = p.weights[1].abs() * (k.k1 * bl / k.ln_h).abs()
            + p.weights[3].abs() * k.k3.abs() * std::f32::consts::LOG10_E;
        let b = if has_growth { p.weights[4].abs() } else { 0.0 };
        let cos = q.cos_growth.clamp(-1.0, 1.0);
        // `sin θ` from a rounded cosine is least accurate near θ = 0 and π (a cosine 1e-7 off
        // moves it by up to 5e-4): the 1e-6 under the root keeps it at least 1e-3.
        let sin = ((1.0 - cos * cos).max(0.0) + 1e-6).sqrt().min(1.0);
        Some(Self {
            p,
            gap,
            d0,
            sight: q.sight,
            step0,
            a,
            b,
            cos,
            sin,
        })
    }

    /// Whether no eye movement of at most `delta` can bring a proposal to the step threshold.
    fn fits(&self, delta: f32) -> bool {
        let p = self.p;
        let (lo, hi) = (self.d0 - delta, self.d0 + delta);
        let above_near = lo > p.near && lo > 0.0;
        if !above_near {
            return false;
        }
        let dist_term = if hi < p.far {
            self.a * delta / lo
        } else if lo >= p.far {
            0.0
        } else {
            return false;
        };
        let x = delta / self.sight;
        let closer = x < 1.0;
        if !closer {
            return false;
        }
        // Non-decreasing in the distance for k1 > 0: the smallest is at `lo`.
        let step_min = if p.switch_k1 > 0.0 {
            SwitchState::step_threshold(p, lo)
        } else {
            SwitchState::step_threshold(p, lo).min(SwitchState::step_threshold(p, hi))
        };
        self.gap + dist_term + self.b * self.f5_move(x) + Self::SLACK < step_min
    }

    /// Bound on `|Δf5|` when the line of sight turns by at most `asin(x)` (`0 ≤ x < 1`).
    fn f5_move(&self, x: f32) -> f32 {
        let (u, s) = (self.cos, self.sin);
        if u.is_nan() {
            return x / (1.0 - x);
        }
        let c = (1.0 - x * x).max(0.0).sqrt();
        let now = clamp01(u);
        // cos(θ − φ), or 1 once φ reaches θ (cos θ ≥ cos φ); cos(θ + φ), or −1 past π.
        let hi = if u >= c { 1.0 } else { u * c + s * x };
        let lo = if -u >= c { -1.0 } else { u * c - s * x };
        (clamp01(hi) - now).max(now - clamp01(lo)).max(0.0)
    }

    /// A guess at the largest radius that [`Self::fits`] (which is what makes an answer safe).
    /// f5 moves about `sin θ·x` per `x` while the node faces the eye (θ < π/2, `cos θ > 0`); a
    /// node facing away keeps f5 = 0 for `x ≤ −cos θ`, so the guess without f5 stands when it
    /// lies inside that margin; beyond it f5 grows about as `x + cos θ`, which is the full
    /// slope with `b·(−cos θ)` more room.
    fn first_guess(&self) -> f32 {
        let (u, b) = (self.cos, self.b);
        if u.is_nan() || b == 0.0 {
            return self.guess(b, 0.0);
        }
        if u > 0.0 {
            return self.guess(b * self.sin, 0.0);
        }
        let without = self.guess(0.0, 0.0);
        let margin = -u * self.sight;
        if without <= margin {
            without
        } else {
            margin.max(self.guess(b, -u * b))
        }
    }

    /// With `y = δ/d0`, the bound is at most `gap + c·y/(1 − y)` (`c = a + b·d0/sight`, `b` the
    /// slope of f5's term per `x`) and the threshold falls about linearly as the eye nears,
    /// `step0 − e·y` below its cap (`e = d0·step'`); they meet at the smaller root of
    /// `e·y² − (c + e + room)·y + room = 0`, with `extra` added to the room.
    fn guess(&self, b: f32, extra: f32) -> f32 {
        let p = self.p;
        let span = p.far - p.near;
        let ratio = (self.d0 - p.near) / span;
        let step_slope = if self.step0 < p.switch_max_step && ratio > 0.0 && p.switch_k1 > 0.0 {
            // The default k1 = 1 needs no powf.
            let pow = if p.switch_k1 == 1.0 {
                1.0
            } else {
                ratio.powf(p.switch_k1 - 1.0)
            };
            p.switch_k1 * pow / span
        } else {
            0.0
        };
        let room = self.step0 - self.gap - Self::SLACK + extra;
        let c = self.a + b * self.d0 / self.sight;
        let e = if step_slope.is_finite() {
            self.d0 * step_slope
        } else {
            0.0
        };
        let s = c + e + room;
        // The smaller root in the form that does not cancel (and reads room/(c + room) at e = 0).
        let y = 2.0 * room / (s + (s * s - 4.0 * e * room).max(0.0).sqrt());
        if y.is_finite() && y > 0.0 {
            y * self.d0
        } else {
            self.d0.max(1.0)
        }
    }
}

/// Seed 004 state of one tree instance drawn as geometry: switch control per leaf node.
///
/// Every frame each *visible* leaf node's rate is proposed and passed through switch control
/// (seed 004 culls first; a culled node keeps its rate in force while its hold time runs), but
/// a node is only *evaluated* once the eye has travelled (path length, model frame) past the
/// `still_radius` found at its last evaluation: until then no proposal can pass the step
/// threshold, so the outcome is the same as evaluating it (its hold time still advances every
/// frame). Most nodes of a tree in view are skipped from one frame to the next.
#[derive(Debug, Clone)]
pub struct TreeLodState {
    table: Arc<LeafTable>,
    rate: Vec<f32>,
    held: Vec<f32>,
    keep: Vec<u32>,
    /// Path length at which each node must be evaluated again.
    expire: Vec<f64>,
    /// Whether each node has been evaluated since the state was made: the first evaluation
    /// applies the proposal as it is (switch control governs changes, and a node that just
    /// came into view has no rate to change from).
    seen: Vec<bool>,
    travelled: f64,
    /// Scratch: the nodes due for evaluation this update.
    due: Vec<u32>,
    eye: Vec3,
    params: Option<(LodParams, RateConsts)>,
    /// No update yet: the eye has no previous position to travel from.
    fresh: bool,
    evaluated: usize,
}

impl TreeLodState {
    /// Fresh state for a node table (no leaf node seen yet).
    pub fn new(nodes: &[NodeRecord]) -> Self {
        Self::with_table(Arc::new(LeafTable::new(nodes)))
    }

    /// Fresh state over a model's shared leaf table.
    pub fn with_table(table: Arc<LeafTable>) -> Self {
        let n = table.len();
        Self {
            table,
            rate: vec![0.0; n],
            held: vec![f32::INFINITY; n],
            keep: vec![0; n],
            expire: vec![f64::NEG_INFINITY; n],
            seen: vec![false; n],
            travelled: 0.0,
            due: Vec::new(),
            eye: Vec3::ZERO,
            params: None,
            fresh: true,
            evaluated: 0,
        }
    }

    /// Statistics used by f3.
    pub fn stats(&self) -> &TreeStats {
        &self.table.stats
    }

    /// Rates in force, per leaf node (ordinal order); 0 for nodes never visible.
    pub fn rates(&self) -> impl Iterator<Item = f32> + '_ {
        self.rate.iter().copied()
    }

    /// Keep counts in force, per leaf node (ordinal order); 0 for nodes never visible.
    pub fn keep(&self) -> &[u32] {
        &self.keep
    }

    /// Leaf nodes evaluated by the last update (the others were culled or provably could not
    /// change).
    pub fn evaluated(&self) -> usize {
        self.evaluated
    }

    /// [`Self::update_visible`] with every leaf node visible.
    pub fn update(&mut self, p: &LodParams, eye_model: Vec3, dt: f32) -> &[u32] {
        self.update_visible(p, eye_model, dt, &[])
    }

    /// Advances `dt` seconds with the eye at `eye_model` (model frame): proposes the rate of
    /// each leaf node that `visible` marks (one flag per leaf node, ordinal order; any other
    /// length, such as empty, marks every node) and applies it through switch control. Culled
    /// nodes keep their rate in force; their hold time runs. Returns the keep count per leaf
    /// node (read it only where visible: a culled node's may be stale).
    pub fn update_visible(&mut self, p: &LodParams, eye_model: Vec3, dt: f32, visible: &[bool]) -> &[u32] {
        if self.params.as_ref().is_none_or(|(q, _)| q != p) {
            // New parameters: every bound is stale.
            self.params = Some((p.clone(), RateConsts::new(p)));
            self.expire.fill(f64::NEG_INFINITY);
        }
        let Some((p, k)) = &self.params else {
            return &self.keep;
        };
        let t = &*self.table;
        let all = visible.len() != t.len();
        self.evaluated = 0;
        if self.fresh {
            // Every node is due (no bound yet) and unseen; the path starts here.
            self.fresh = false;
        } else {
            let moved = eye_model.distance(self.eye);
            // A non-finite move (NaN eye) evaluates everything.
            self.travelled += if moved.is_finite() {
                f64::from(moved)
            } else {
                f64::INFINITY
            };
            if dt.is_finite() && dt > 0.0 {
                // Its own pass, so that it vectorises: every hold time advances every frame.
                for h in &mut self.held {
                    *h += dt;
                }
            }
        }
        self.eye = eye_model;
        // The visible nodes due for evaluation: only `expire > travelled` skips a node, so a NaN
        // expiry is due.
        // A culled node is left as it is: evaluated once it is visible again.
        let mut due = std::mem::take(&mut self.due);
        due.clear();
        let travelled = self.travelled;
        // One scan, monomorphised for "all visible" and for a mask.
        fn collect_due(due: &mut Vec<u32>, expire: &[f64], travelled: f64, visible: impl Iterator<Item = bool>) {
            due.extend(
                expire
                    .iter()
                    .zip(visible)
                    .enumerate()
                    .filter(|&(_, (&e, v))| v && e.partial_cmp(&travelled) != Some(std::cmp::Ordering::Greater))
                    .map(|(i, _)| i as u32),
            );
        }
        if all {
            collect_due(&mut due, &self.expire, travelled, std::iter::repeat(true));
        } else {
            collect_due(&mut due, &self.expire, travelled, visible.iter().copied());
        }
        self.evaluated = due.len();
        for &i in &due {
            let i = i as usize;
            let l = &t.leaves[i];
            let (mut q, sw, changed) = if self.seen[i] {
                let mut sw = SwitchState {
                    rate: self.rate[i],
                    held_s: self.held[i],
                };
                // The hold time already advanced above.
                let q = t.propose(p, k, i, eye_model, sw.rate);
                let changed = sw.update(p, q.rate, q.distance, 0.0).1;
                (q, sw, changed)
            } else {
                self.seen[i] = true;
                let q = t.propose(p, k, i, eye_model, 0.0);
                (q, SwitchState::new(q.rate), true)
            };
            if changed {
                self.keep[i] = keep_count(l.leaf_count, sw.rate);
                // The next proposal reads the new rate in force (f3): bound from that one.
                q = t.repropose(p, i, q, sw.rate);
            }
            self.rate[i] = sw.rate;
            self.held[i] = sw.held_s;
            let r = still_radius(p, k, l.branch_level, l.has_growth, q, sw.rate);
            self.expire[i] = if self.travelled.is_finite() {
                self.travelled + f64::from(r)
            } else {
                f64::NEG_INFINITY
            };
        }
        self.due = due;
        &self.keep
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lod::frustum::DepthRange;
    use crate::lod::projection::DEFAULT_LADDER;
    use crate::lod::rate::node_rate;
    use canopy_shared::format::{NO_BRANCH, NO_PARENT};
    use std::f32::consts::FRAC_PI_2;

    fn nodes() -> Vec<NodeRecord> {
        let rec = |parent, subtree_end, kind, leaf_count, c: Vec3| NodeRecord {
            parent,
            subtree_end,
            kind,
            branch_level: 2,
            sphere_layer: 1,
            branch: NO_BRANCH,
            leaf_count,
            growth_direction: Vec3::Y,
            length: 5.0,
            sphere_center: c,
            sphere_radius: 1.0,
            leaf_density: 2.0,
        };
        vec![
            rec(NO_PARENT, 4, NodeKind::Branch, 0, Vec3::new(0.0, 0.0, -10.0)),
            rec(0, 3, NodeKind::Branch, 0, Vec3::new(0.0, 0.0, 50.0)),
            rec(1, 3, NodeKind::Leaf, 100, Vec3::new(0.0, 0.0, -10.0)),
            rec(0, 4, NodeKind::Leaf, 100, Vec3::new(0.0, 0.0, -10.0)),
        ]
    }

    #[test]
    fn culled_subtree_is_skipped() {
        let proj = Mat4::perspective_rh(FRAC_PI_2, 1.0, 0.5, 1000.0);
        let f = Frustum::from_view_proj(
            proj * Mat4::look_at_rh(Vec3::ZERO, Vec3::NEG_Z, Vec3::Y),
            DepthRange::ZeroToOne,
        );
        // Node 1 (behind the eye) is culled and takes its child with it, although the child's own
        // sphere is in view: spheres cover subtrees, so this never happens in a valid file.
        assert_eq!(
            visible_nodes(&f, Mat4::IDENTITY, &nodes()),
            vec![true, false, false, true]
        );
        // Moving the instance 200 m behind the eye culls the root and everything.
        let m = Mat4::from_translation(Vec3::new(0.0, 0.0, 200.0));
        assert_eq!(visible_nodes(&f, m, &nodes()), vec![false; 4]);
    }

    #[test]
    fn representation_by_distance() {
        let rep = |z: f32| {
            tree_representation(
                &DEFAULT_LADDER,
                20.0,
                Vec3::ZERO,
                Vec3::new(0.0, 0.0, z),
                5.0,
                1000.0,
                FRAC_PI_2,
            )
        };
        assert_eq!(rep(0.0), Some(Representation::Geometry)); // inside the sphere
        assert_eq!(rep(-50.0), Some(Representation::Geometry)); // 45 m: 222 px
        assert_eq!(rep(-105.0), Some(Representation::Hull { level: 0 })); // 100 m: 100 px
        assert_eq!(rep(-205.0), Some(Representation::Hull { level: 1 })); // 200 m: 50 px
        assert_eq!(
            rep(-1005.0),
            Some(Representation::Billboard(
                crate::lod::projection::BillboardKind::HemiOct
            ))
        ); // 10 px
    }

    #[test]
    fn tree_state_rates_and_keep_counts() {
        let p = LodParams {
            near: 5.0,
            far: 1000.0,
            ..LodParams::default()
        };
        let n = nodes();
        let mut st = TreeLodState::new(&n);
        assert_eq!(st.stats().min_density, 2.0);
        // Eye inside the leaf spheres: f1 = 0 (layer 1), f2 = f4 = f5 = 0, f3 = 2/1 − 1 → 1:
        // rate 0.2, keep 80.
        let keep = st.update(&p, Vec3::new(0.0, 0.0, -10.0), 0.016).to_vec();
        assert_eq!(keep, vec![80, 80]);
        // Far below: f4 = 1, f2 = 0.5, f5 = 0 (growth +Y, sight −Y... eye above looks down: +Y
        // growth against a −Y line of sight), f3 with LD = 2·0.8 = 1.6 → 0.6.
        let keep = st.update(&p, Vec3::new(0.0, 1e5, -10.0), 10.0).to_vec();
        let want = 0.1 * 0.5 + 0.2 * 0.6 + 0.3;
        assert!(
            st.rates().all(|r| (r - want).abs() < 1e-5),
            "{:?}",
            st.rates().collect::<Vec<_>>()
        );
        assert_eq!(keep, vec![keep_count(100, want); 2]);
        // 499 m away the proposal is ≈ 0.297: a step of ≈ 0.17 is below the capped step
        // threshold 0.25, so the old rate holds however long we wait.
        let _ = st.update(&p, Vec3::new(0.0, 509.0, -10.0), 0.1).to_vec();
        let _ = st.update(&p, Vec3::new(0.0, 509.0, -10.0), 100.0).to_vec();
        assert!(st.rates().all(|r| (r - want).abs() < 1e-5));
        // Back inside the crown: thresholds are 0, the change applies at once (rate ≠ want).
        let keep = st.update(&p, Vec3::new(0.0, 0.0, -10.0), 0.0).to_vec();
        assert!(st.rates().all(|r| r < want));
        assert!(keep.iter().all(|&k| k > keep_count(100, want)));
    }

    #[test]
    fn a_tree_first_seen_far_away_starts_at_its_proposed_rate() {
        let p = LodParams {
            near: 5.0,
            far: 1000.0,
            ..LodParams::default()
        };
        let n = nodes();
        let eye = Vec3::new(0.0, 400.0, -10.0);
        let mut st = TreeLodState::new(&n);
        let keep = st.update(&p, eye, 0.016).to_vec();
        // Without the fresh start, switch control (step threshold ≈ 0.25 at 400 m) would hold
        // every node at rate 0 and fetch all leaves of a far tree.
        let proposed = node_rate(&p, st.stats(), &n[2], eye, 0.0).rate;
        assert!(proposed > 0.1, "{proposed}");
        assert!(keep.iter().all(|&k| k < 100), "{keep:?}");
    }

    /// A crown of `count` leaf nodes (random spheres, layers, levels, densities and growth)
    /// under one trunk node.
    fn crown(count: usize, seed: u64) -> Vec<NodeRecord> {
        let mut rng = canopy_shared::lsystem::rng::SplitMix64::new(seed);
        let mut u = |a: f64, b: f64| rng.uniform(a, b) as f32;
        let mut out = vec![NodeRecord {
            parent: NO_PARENT,
            subtree_end: count as u32 + 1,
            kind: NodeKind::Branch,
            branch_level: 1,
            sphere_layer: 1,
            branch: NO_BRANCH,
            leaf_count: 0,
            growth_direction: Vec3::Y,
            length: 10.0,
            sphere_center: Vec3::new(0.0, 8.0, 0.0),
            sphere_radius: 9.0,
            leaf_density: 0.0,
        }];
        for i in 0..count {
            out.push(NodeRecord {
                parent: 0,
                subtree_end: i as u32 + 2,
                kind: NodeKind::Leaf,
                branch_level: u(1.0, 9.0) as u8,
                sphere_layer: u(1.0, 4.0) as u8,
                branch: NO_BRANCH,
                leaf_count: u(1.0, 400.0) as u32,
                growth_direction: Vec3::new(u(-1.0, 1.0), u(-1.0, 1.0), u(-1.0, 1.0)),
                length: 1.0,
                sphere_center: Vec3::new(u(-6.0, 6.0), u(2.0, 14.0), u(-6.0, 6.0)),
                sphere_radius: u(0.1, 1.5),
                leaf_density: u(0.5, 40.0),
            });
        }
        out
    }

    /// The rule as written: every leaf node proposed and passed through switch control every
    /// frame. Returns the keep counts after each frame.
    fn every_node_every_frame(p: &LodParams, nodes: &[NodeRecord], eyes: &[Vec3], dt: f32) -> Vec<Vec<u32>> {
        every_node_with_dts(p, nodes, eyes, &vec![dt; eyes.len()])
            .into_iter()
            .map(|(keep, _)| keep)
            .collect()
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(48))]
        /// Skipping nodes changes nothing: along any camera path (slow drifts, jumps, the eye
        /// inside the crown, beyond `far`) the keep counts equal those of evaluating every node
        /// every frame.
        #[test]
        fn skipping_nodes_matches_evaluating_every_node(
            seed in 0u64..1000, x0 in -300.0f32..300.0, y0 in 0.0f32..200.0, z0 in -300.0f32..300.0,
            steps in proptest::collection::vec((-4.0f32..4.0, -2.0f32..2.0, -4.0f32..4.0, 0u8..20), 1..80),
            far in 60.0f32..600.0, k1 in 0.5f32..2.0,
        ) {
            let nodes = crown(40, seed);
            let p = LodParams { near: 5.0, far, switch_k1: k1, ..LodParams::default() };
            let mut eye = Vec3::new(x0, y0, z0);
            let mut eyes = vec![eye];
            for &(dx, dy, dz, jump) in &steps {
                // One step in twenty jumps (a teleport or a fast pan).
                let s = if jump == 0 { 40.0 } else { 1.0 };
                eye += Vec3::new(dx, dy, dz) * s;
                eyes.push(eye);
            }
            let want = every_node_every_frame(&p, &nodes, &eyes, 1.0 / 30.0);
            let mut st = TreeLodState::new(&nodes);
            for (f, &e) in eyes.iter().enumerate() {
                let got = st.update(&p, e, 1.0 / 30.0).to_vec();
                proptest::prop_assert_eq!(&got, &want[f], "frame {}", f);
            }
        }
    }

    /// A random node hierarchy of about `count` nodes in preorder (`subtree_end` set), leaves
    /// and branches mixed, spheres anywhere (a child's sphere need not lie in its parent's).
    fn random_hierarchy(count: usize, seed: u64) -> Vec<NodeRecord> {
        let mut rng = canopy_shared::lsystem::rng::SplitMix64::new(seed);
        let mut out: Vec<NodeRecord> = Vec::new();
        fn grow(
            out: &mut Vec<NodeRecord>,
            rng: &mut canopy_shared::lsystem::rng::SplitMix64,
            parent: u32,
            depth: u32,
            budget: usize,
        ) {
            let i = out.len();
            let mut u = |a: f64, b: f64| rng.uniform(a, b) as f32;
            let leaf = depth >= 5 || budget <= 1 || u(0.0, 1.0) < 0.3;
            out.push(NodeRecord {
                parent,
                subtree_end: 0,
                kind: if leaf { NodeKind::Leaf } else { NodeKind::Branch },
                branch_level: depth as u8,
                sphere_layer: 1,
                branch: NO_BRANCH,
                leaf_count: if leaf { 10 } else { 0 },
                growth_direction: Vec3::Y,
                length: 1.0,
                sphere_center: Vec3::new(u(-15.0, 15.0), u(0.0, 25.0), u(-15.0, 15.0)),
                sphere_radius: u(-0.5, 6.0),
                leaf_density: 1.0,
            });
            if !leaf {
                let kids = (u(1.0, 5.0) as usize).min(budget - 1);
                let share = (budget - 1) / kids.max(1);
                for _ in 0..kids {
                    grow(out, rng, i as u32, depth + 1, share.max(1));
                }
            }
            out[i].subtree_end = out.len() as u32;
        }
        while out.len() < count {
            let budget = count - out.len();
            grow(&mut out, &mut rng, NO_PARENT, 0, budget);
        }
        out
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(256))]
        /// Leaf visibility and masked keep counts with whole subtrees kept in one step equal the
        /// node-by-node walk read at the leaf nodes, for any frustum and placement.
        #[test]
        fn leaf_culling_matches_the_node_walk(
            seed in 0u64..10_000, count in 1usize..400,
            ex in -60.0f32..60.0, ey in -10.0f32..40.0, ez in -60.0f32..60.0,
            yaw in -3.2f32..3.2, pitch in -1.5f32..1.5, fov in 0.3f32..2.0,
            px in -500.0f32..500.0, pz in -500.0f32..500.0, rot in -3.2f32..3.2, scale in 0.3f32..3.0,
            bad_end in proptest::option::of((0usize..400, 0u32..500)),
        ) {
            let mut nodes = random_hierarchy(count, seed);
            if let Some((k, e)) = bad_end {
                // A malformed subtree end: the walk's rule still applies.
                let k = k % nodes.len();
                nodes[k].subtree_end = e;
            }
            let model = Mat4::from_scale_rotation_translation(
                Vec3::splat(scale),
                glam::Quat::from_rotation_y(rot),
                Vec3::new(px, 0.0, pz),
            );
            let eye = Vec3::new(px + ex, ey, pz + ez);
            let dir = Vec3::new(yaw.sin() * pitch.cos(), pitch.sin(), -yaw.cos() * pitch.cos());
            let view = Mat4::look_at_rh(eye, eye + dir, Vec3::Y);
            let f = Frustum::from_view_proj(Mat4::perspective_rh(fov, 1.5, 0.5, 800.0) * view, DepthRange::ZeroToOne);
            let spheres = world_spheres(model, &nodes);
            let before = leaves_before(&nodes);
            let reach = subtree_reach(&nodes);
            let mut walk = Vec::new();
            visible_nodes_world(&f, &spheres, &nodes, &mut walk);
            let leaf_ids: Vec<usize> = (0..nodes.len()).filter(|&i| nodes[i].kind == NodeKind::Leaf).collect();
            let want_vis: Vec<bool> = leaf_ids.iter().map(|&i| walk[i]).collect();
            // Appends after what is already there.
            let mut vis = vec![true];
            visible_leaves_world(&f, &spheres, &nodes, &reach, &before, scale, &mut vis);
            proptest::prop_assert_eq!(&vis[1..], &want_vis[..]);
            // Only the planes the tree crosses, as the streamer calls it.
            let all = f.crossing(model.transform_point3(Vec3::ZERO), 1e3);
            let mut vis2 = Vec::new();
            visible_leaves_world(&all, &spheres, &nodes, &reach, &before, scale, &mut vis2);
            let mut walk2 = Vec::new();
            visible_nodes_world(&all, &spheres, &nodes, &mut walk2);
            let want2: Vec<bool> = leaf_ids.iter().map(|&i| walk2[i]).collect();
            proptest::prop_assert_eq!(vis2, want2);
        }
    }

    /// [`every_node_every_frame`] with a frame time per frame (0 and negative ones add nothing).
    fn every_node_with_dts(
        p: &LodParams,
        nodes: &[NodeRecord],
        eyes: &[Vec3],
        dts: &[f32],
    ) -> Vec<(Vec<u32>, Vec<f32>)> {
        every_visible_node(p, nodes, eyes, dts, &[])
    }

    /// The reference for culling: every *visible* node (`visible[f]`, one flag per leaf node;
    /// missing or empty: all) evaluated every frame; every hold time runs; a node's first
    /// visible frame starts it at its proposal. Keep counts of nodes never seen are 0.
    fn every_visible_node(
        p: &LodParams,
        nodes: &[NodeRecord],
        eyes: &[Vec3],
        dts: &[f32],
        visible: &[Vec<bool>],
    ) -> Vec<(Vec<u32>, Vec<f32>)> {
        let stats = TreeStats::from_nodes(nodes);
        let leaves: Vec<&NodeRecord> = nodes.iter().filter(|n| n.kind == NodeKind::Leaf).collect();
        let mut sw = vec![SwitchState::new(0.0); leaves.len()];
        let mut seen = vec![false; leaves.len()];
        let mut out = Vec::new();
        for (f, (&eye, &dt)) in eyes.iter().zip(dts).enumerate() {
            let mut keep = Vec::new();
            for (o, (n, s)) in leaves.iter().zip(&mut sw).enumerate() {
                let vis = visible.get(f).and_then(|v| v.get(o)).is_none_or(|&v| v);
                if !vis {
                    if f > 0 && dt.is_finite() && dt > 0.0 {
                        s.held_s += dt;
                    }
                } else if !seen[o] {
                    seen[o] = true;
                    *s = SwitchState::new(node_rate(p, &stats, n, eye, 0.0).rate);
                } else {
                    let r = node_rate(p, &stats, n, eye, s.rate);
                    s.update(p, r.rate, r.distance, dt);
                }
                keep.push(if seen[o] { keep_count(n.leaf_count, s.rate) } else { 0 });
            }
            out.push((keep, sw.iter().map(|s| s.rate).collect()));
        }
        out
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(48))]
        /// Skipping nodes gives the rates and keep counts of evaluating every node every frame,
        /// with frame times that vary (tiny, long, zero, negative) and slow approaches where hold
        /// times matter.
        #[test]
        fn skipping_nodes_matches_every_node_with_varying_frame_times(
            seed in 0u64..1000, x0 in -200.0f32..200.0, y0 in 0.0f32..100.0, z0 in -200.0f32..200.0,
            steps in proptest::collection::vec((-3.0f32..3.0, -1.0f32..1.0, -3.0f32..3.0, 0u8..20, -0.01f32..0.3), 1..120),
            far in 60.0f32..600.0, k2 in 0.3f32..3.0,
        ) {
            let nodes = crown(40, seed);
            let p = LodParams { near: 5.0, far, switch_k2: k2, ..LodParams::default() };
            let mut eye = Vec3::new(x0, y0, z0);
            let (mut eyes, mut dts) = (vec![eye], vec![1.0 / 30.0]);
            for &(dx, dy, dz, kind, dt) in &steps {
                let s = if kind == 0 { 30.0 } else { 1.0 };
                eye += Vec3::new(dx, dy, dz) * s;
                eyes.push(eye);
                dts.push(match kind {
                    1 => 0.0,
                    2 => 1e-4,
                    _ => dt,
                });
            }
            let want = every_node_with_dts(&p, &nodes, &eyes, &dts);
            let mut st = TreeLodState::new(&nodes);
            for (f, (&e, &dt)) in eyes.iter().zip(&dts).enumerate() {
                let got = st.update(&p, e, dt).to_vec();
                proptest::prop_assert_eq!(&got, &want[f].0, "frame {}", f);
                proptest::prop_assert_eq!(st.rates().collect::<Vec<_>>(), want[f].1.clone(), "frame {}", f);
            }
        }
    }

    /// A long path with varying frame times (hold times summed over thousands of frames) gives
    /// the keep counts of evaluating every node.
    #[test]
    fn subtree_reach_gives_up_on_malformed_files_and_stays_exact() {
        // Every subtree spans the rest of the file: the scan stops at its budget, the nodes after
        // it get an infinite reach (never accepted whole), and the culling still equals the walk,
        // also with a camera far from the origin and an infinite far plane.
        let mut nodes = random_hierarchy(3000, 9);
        let n = nodes.len();
        for m in &mut nodes {
            m.subtree_end = n as u32;
        }
        let reach = subtree_reach(&nodes);
        let capped = reach.iter().filter(|r| r.is_infinite()).count();
        assert!(capped > n / 2, "{capped} of {n} capped");
        assert!(reach[0].is_finite());
        let model = Mat4::from_translation(Vec3::new(3.0e5, 0.0, -2.0e5));
        let spheres = world_spheres(model, &nodes);
        let before = leaves_before(&nodes);
        let eye = Vec3::new(3.0e5, 5.0, -2.0e5 + 60.0);
        let view = Mat4::look_at_rh(eye, eye - Vec3::Z, Vec3::Y);
        for proj in [
            Mat4::perspective_rh(1.0, 1.5, 0.5, 800.0),
            Mat4::perspective_infinite_rh(1.0, 1.5, 0.5),
        ] {
            let f = Frustum::from_view_proj(proj * view, DepthRange::ZeroToOne);
            let mut walk = Vec::new();
            visible_nodes_world(&f, &spheres, &nodes, &mut walk);
            let mut vis = Vec::new();
            visible_leaves_world(&f, &spheres, &nodes, &reach, &before, 1.0, &mut vis);
            let leaf_ids: Vec<usize> = (0..n).filter(|&i| nodes[i].kind == NodeKind::Leaf).collect();
            let want: Vec<bool> = leaf_ids.iter().map(|&i| walk[i]).collect();
            assert_eq!(vis, want);
        }
    }

    #[test]
    fn long_paths_with_varying_frame_times_match_every_node() {
        let nodes = crown(30, 7);
        let p = LodParams {
            near: 5.0,
            far: 300.0,
            ..LodParams::default()
        };
        let frames = 9000;
        let eyes: Vec<Vec3> = (0..frames)
            .map(|f| {
                let t = f as f32 * 0.01;
                Vec3::new(80.0 * t.cos(), 20.0 + 15.0 * (t * 0.7).sin(), 80.0 * t.sin())
            })
            .collect();
        let dts: Vec<f32> = (0..frames)
            .map(|f| {
                if f % 7 == 0 {
                    0.0
                } else {
                    0.004 + (f % 5) as f32 * 0.003
                }
            })
            .collect();
        let want = every_node_with_dts(&p, &nodes, &eyes, &dts);
        let mut st = TreeLodState::new(&nodes);
        for (f, (&e, &dt)) in eyes.iter().zip(&dts).enumerate() {
            let got = st.update(&p, e, dt).to_vec();
            assert_eq!(got, want[f].0, "frame {f}");
        }
    }

    /// The radius found is safe (it fits) and not far below the largest that fits (found here by
    /// bisection), over proposals at every distance, gap and switch exponent: a loose radius
    /// costs evaluations every frame.
    #[test]
    fn still_radius_is_close_to_the_largest_that_fits() {
        let mut rng = canopy_shared::lsystem::rng::SplitMix64::new(11);
        let (mut sum, mut n) = (0.0f64, 0u32);
        for case in 0..4000 {
            let p = LodParams {
                switch_k1: [1.0, 0.5, 2.0][case % 3],
                ..LodParams::default()
            };
            let k = RateConsts::new(&p);
            let distance = rng.uniform(0.0, 700.0) as f32;
            let current = rng.uniform(0.0, 1.0) as f32;
            let step = SwitchState::step_threshold(&p, distance);
            let q = Proposal {
                rate: current + step * rng.uniform(-1.0, 1.0) as f32,
                f: [0.0; 5],
                distance,
                sight: distance + rng.uniform(0.0, 5.0) as f32,
                cos_growth: if case % 4 == 0 {
                    f32::NAN
                } else {
                    rng.uniform(-1.0, 1.0) as f32
                },
            };
            let bl = (case % 7) as u8;
            let r = still_radius(&p, &k, bl, case % 5 != 0, q, current);
            let Some(bound) = StillBound::new(&p, &k, bl, case % 5 != 0, q, current) else {
                assert_eq!(r, 0.0);
                continue;
            };
            // The largest radius that fits (fits is monotone: a larger radius only loosens
            // every term of the bound).
            let (mut good, mut bad) = (0.0f32, distance.max(1.0) * 2.0);
            for _ in 0..40 {
                let mid = 0.5 * (good + bad);
                if bound.fits(mid) { good = mid } else { bad = mid }
            }
            if r > 0.0 {
                assert!(bound.fits(r), "case {case}: {r} does not fit");
            }
            if good > 1e-3 {
                assert!(r <= good * 1.0001, "case {case}: {r} > largest {good}");
                sum += f64::from(r / good);
                n += 1;
            }
        }
        let mean = sum / f64::from(n);
        assert!(n > 1000, "{n} cases with room");
        // 0.78 here (0.74 for nodes facing away, whose largest radius the angle bound made
        // larger); the linear guess of the bound without the angle gave 0.66.
        assert!(mean > 0.75, "mean radius is {mean:.3} of the largest that fits");
    }

    /// f5's bound holds for real eye moves: a random node (centre, growth direction) and eye,
    /// moved by at most `δ` in a random direction, never changes f5 by more than
    /// `f5_move(δ/sight)`; and a node facing away by more than the turn keeps f5 at exactly 0.
    #[test]
    fn f5_moves_within_its_bound() {
        let mut rng = canopy_shared::lsystem::rng::SplitMix64::new(5);
        let p = LodParams::default();
        let k = RateConsts::new(&p);
        let unit = |rng: &mut canopy_shared::lsystem::rng::SplitMix64| loop {
            let v = Vec3::new(
                rng.uniform(-1.0, 1.0) as f32,
                rng.uniform(-1.0, 1.0) as f32,
                rng.uniform(-1.0, 1.0) as f32,
            );
            if let Some(u) = v.try_normalize() {
                break u;
            }
        };
        let mut zero_kept = 0;
        for case in 0..20_000 {
            let center = unit(&mut rng) * rng.uniform(0.0, 5.0) as f32;
            let growth = unit(&mut rng);
            let sight = rng.uniform(0.5, 200.0) as f32;
            let eye = center - unit(&mut rng) * sight;
            let los = center - eye;
            let cos_growth = (los / los.length()).dot(growth);
            let q = Proposal {
                rate: 0.5,
                f: [0.0; 5],
                distance: 100.0,
                sight: los.length(),
                cos_growth,
            };
            let bound = StillBound::new(&p, &k, 1, true, q, 0.5).expect("room at rate 0.5, gap 0");
            let x = rng.uniform(0.0, 0.999) as f32;
            let delta = x * q.sight;
            // Mostly moves of the full length (the worst case), some shorter.
            let len = if case % 3 == 0 {
                delta * rng.uniform(0.0, 1.0) as f32
            } else {
                delta
            };
            let moved = eye + unit(&mut rng) * len;
            let los2 = center - moved;
            let f5_before = clamp01(cos_growth);
            let f5_after = clamp01((los2 / los2.length()).dot(growth));
            let change = (f5_after - f5_before).abs();
            let allowed = bound.f5_move(x);
            assert!(
                change <= allowed + 1e-5,
                "case {case}: f5 moved {change} > {allowed} (cos {cos_growth}, x {x})"
            );
            if cos_growth < 0.0 && x < -cos_growth * 0.999 {
                assert_eq!(allowed, 0.0, "case {case}: facing away by more than the turn");
                zero_kept += 1;
            }
        }
        assert!(zero_kept > 1000, "{zero_kept} nodes facing away");
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(48))]
        /// With culling (seed 004 culls first), skipping nodes gives the rates of evaluating every
        /// visible node every frame, and the same keep counts wherever a node is visible: culled
        /// nodes keep their rate while their hold time runs, nodes first seen late start at their
        /// proposal. Masks: all visible, a plane through the crown (as a frustum side cuts it),
        /// or nodes toggling at random.
        #[test]
        fn skipping_culled_nodes_matches_every_visible_node(
            seed in 0u64..1000, x0 in -150.0f32..150.0, y0 in 0.0f32..80.0, z0 in -150.0f32..150.0,
            steps in proptest::collection::vec((-3.0f32..3.0, -1.0f32..1.0, -3.0f32..3.0, 0u8..3, -7.0f32..7.0, 0u8..20), 1..100),
        ) {
            let nodes = crown(60, seed);
            let centres: Vec<Vec3> =
                nodes.iter().filter(|n| n.kind == NodeKind::Leaf).map(|n| n.sphere_center).collect();
            let p = LodParams { near: 5.0, far: 300.0, ..LodParams::default() };
            let mut rng = canopy_shared::lsystem::rng::SplitMix64::new(seed);
            let mut eye = Vec3::new(x0, y0, z0);
            let (mut eyes, mut masks) = (vec![eye], vec![vec![true; centres.len()]]);
            for &(dx, dy, dz, mode, cut, jump) in &steps {
                let s = if jump == 0 { 30.0 } else { 1.0 };
                eye += Vec3::new(dx, dy, dz) * s;
                eyes.push(eye);
                masks.push(match mode {
                    0 => vec![true; centres.len()],
                    1 => centres.iter().map(|c| c.x < cut).collect(),
                    _ => centres.iter().map(|_| rng.uniform(0.0, 1.0) < 0.6).collect(),
                });
            }
            let dts = vec![1.0 / 30.0; eyes.len()];
            let want = every_visible_node(&p, &nodes, &eyes, &dts, &masks);
            let mut st = TreeLodState::new(&nodes);
            for (f, &e) in eyes.iter().enumerate() {
                let got = st.update_visible(&p, e, dts[f], &masks[f]).to_vec();
                for (o, &v) in masks[f].iter().enumerate() {
                    if v {
                        proptest::prop_assert_eq!(got[o], want[f].0[o], "frame {} node {}", f, o);
                    }
                }
                proptest::prop_assert_eq!(st.rates().collect::<Vec<_>>(), want[f].1.clone(), "frame {}", f);
                let visible = masks[f].iter().filter(|&&v| v).count();
                proptest::prop_assert!(st.evaluated() <= visible, "frame {}: culled nodes evaluated", f);
            }
        }
    }

    /// Nodes that face away (f5 = 0) and turn towards the eye as it passes them sideways: f5
    /// rises from 0 while their distance barely changes, so only the angle bound can call them
    /// back in time. Skipping must still match evaluating every node every frame.
    #[test]
    fn nodes_turning_to_face_a_passing_eye_match_every_node() {
        let p = LodParams::default();
        let mut nodes = crown(300, 17);
        for n in &mut nodes[1..] {
            n.growth_direction = Vec3::new(1.0, 0.0, -0.05 * (n.sphere_center.x + 1.0));
        }
        // Sideways along −X at 40 m, half a metre a frame.
        let eyes: Vec<Vec3> = (0..120).map(|f| Vec3::new(2.0 - 0.5 * f as f32, 8.0, 40.0)).collect();
        let want = every_node_every_frame(&p, &nodes, &eyes, 1.0 / 30.0);
        let changed = want.windows(2).filter(|w| w[0] != w[1]).count();
        assert!(changed > 20, "the reference changes in {changed} frames only");
        let mut st = TreeLodState::new(&nodes);
        let mut evaluated = 0;
        for (f, &e) in eyes.iter().enumerate() {
            assert_eq!(st.update(&p, e, 1.0 / 30.0), want[f].as_slice(), "frame {f}");
            evaluated += st.evaluated();
        }
        // Skipping still skips: well under every node every frame.
        assert!(evaluated < 300 * 120 / 4, "{evaluated} evaluations");
    }

    #[test]
    fn nodes_are_evaluated_again_only_when_the_eye_has_moved_enough() {
        let p = LodParams::default();
        let nodes = crown(200, 3);
        let mut st = TreeLodState::new(&nodes);
        let eye = Vec3::new(0.0, 60.0, 150.0);
        st.update(&p, eye, 1.0 / 30.0);
        assert_eq!(st.evaluated(), 200);
        // A still camera: nothing can change, nothing is evaluated.
        st.update(&p, eye, 1.0 / 30.0);
        assert_eq!(st.evaluated(), 0);
        // A flyover step (25 m/s at 30 fps) evaluates few nodes.
        st.update(&p, eye + Vec3::new(0.83, 0.0, 0.0), 1.0 / 30.0);
        assert!(st.evaluated() < 20, "{}", st.evaluated());
        // Crossing to the other side of the tree evaluates every node.
        st.update(&p, Vec3::new(0.0, 60.0, -150.0), 1.0 / 30.0);
        assert_eq!(st.evaluated(), 200);
        // New parameters invalidate every bound.
        let q = LodParams { far: 400.0, ..p };
        st.update(&q, Vec3::new(0.0, 60.0, -150.0), 1.0 / 30.0);
        assert_eq!(st.evaluated(), 200);
    }
}

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
    center: Vec<Vec3>,
    radius: Vec<f32>,
    /// Unit growth direction, `None` when degenerate (f5 is then 0).
    growth: Vec<Option<Vec3>>,
    branch_level: Vec<u8>,
    sphere_layer: Vec<u8>,
    density: Vec<f32>,
    leaf_count: Vec<u32>,
}

impl LeafTable {
    /// The leaf nodes of a node table.
    pub fn new(nodes: &[NodeRecord]) -> Self {
        let leaves: Vec<&NodeRecord> = nodes.iter().filter(|n| n.kind == NodeKind::Leaf).collect();
        Self {
            stats: TreeStats::from_nodes(nodes),
            center: leaves.iter().map(|n| n.sphere_center).collect(),
            radius: leaves.iter().map(|n| n.sphere_radius).collect(),
            growth: leaves.iter().map(|n| n.growth_direction.try_normalize()).collect(),
            branch_level: leaves.iter().map(|n| n.branch_level).collect(),
            sphere_layer: leaves.iter().map(|n| n.sphere_layer).collect(),
            density: leaves.iter().map(|n| n.leaf_density).collect(),
            leaf_count: leaves.iter().map(|n| n.leaf_count).collect(),
        }
    }

    /// Leaf nodes.
    pub fn len(&self) -> usize {
        self.center.len()
    }

    /// Whether there are no leaf nodes.
    pub fn is_empty(&self) -> bool {
        self.center.is_empty()
    }

    /// Seed 004's proposal for leaf node `i` seen from `eye` with `current` in force: the same
    /// factors as [`super::rate::node_rate`] (bit for bit), plus what [`still_radius`] needs.
    #[inline]
    fn propose(&self, p: &LodParams, k: &RateConsts, i: usize, eye: Vec3, current: f32) -> Proposal {
        let los = self.center[i] - eye;
        let len = los.length();
        let d = len - self.radius[i].max(0.0);
        let distance = if d.is_finite() { d.max(0.0) } else { 0.0 };
        let rcp = len.recip();
        let f5 = match self.growth[i] {
            Some(g) if rcp.is_finite() && rcp > 0.0 => clamp01((los * rcp).dot(g)),
            _ => 0.0,
        };
        let f = [
            f1_layer(p, self.sphere_layer[i]),
            k.f2(p, self.branch_level[i], distance),
            f3_density(&self.stats, self.density[i], current),
            k.f4(p, distance),
            f5,
        ];
        Proposal {
            rate: combine(p, f),
            f,
            distance,
            sight: len,
        }
    }

    /// `q` again with `current` in force instead: only f3 reads it.
    #[inline]
    fn repropose(&self, p: &LodParams, i: usize, q: Proposal, current: f32) -> Proposal {
        let mut f = q.f;
        f[2] = f3_density(&self.stats, self.density[i], current);
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
}

/// How far (model frame) the eye may move before a leaf node's proposal could differ from the
/// rate in force (`current`) by switch control's step threshold; 0 when it may already. `q` must
/// be the proposal made with `current` in force (f3 reads it). While the eye stays
/// inside, switch control provably applies no change, so the node need not be evaluated.
///
/// Bounds, for an eye displacement `δ` (the sphere distance `d` moves by at most `δ`): on
/// `near < d < far`, `|Δf2| ≤ k1·BL/ln h·δ/d_min` and `|Δf4| ≤ k3/ln 10·δ/d_min`; beyond `far`
/// both are constant; f5 (a cosine) moves by at most the angle the line of sight turns, which is
/// at most `asin(x) ≤ x/(1 − x)` with `x = δ/|centre − eye| < 1`;
/// f1 and f3 (the rate in force) do not move. The step threshold is monotone in `d`, so its
/// smallest value on `[d − δ, d + δ]` is at an end. Intervals that hold `near` or `far` (where f2
/// and f4 jump) give 0.
fn still_radius(p: &LodParams, k: &RateConsts, branch_level: u8, has_growth: bool, q: Proposal, current: f32) -> f32 {
    // Float slack: the proposal itself is computed with rounding.
    const SLACK: f32 = 1e-5;
    let gap = (q.rate - current).abs();
    let d0 = q.distance;
    let step0 = SwitchState::step_threshold(p, d0);
    // Written to be false for NaN.
    let room = step0 - gap > SLACK && q.sight > 0.0;
    if !room {
        return 0.0;
    }
    let bl = f32::from(branch_level).min(k.bl_max);
    let a =
        p.weights[1].abs() * (k.k1 * bl / k.ln_h).abs() + p.weights[3].abs() * k.k3.abs() * std::f32::consts::LOG10_E;
    let b = if has_growth { p.weights[4].abs() } else { 0.0 };
    let fits = |delta: f32| -> bool {
        let (lo, hi) = (d0 - delta, d0 + delta);
        let above_near = lo > p.near && lo > 0.0;
        if !above_near {
            return false;
        }
        let dist_term = if hi < p.far {
            a * delta / lo
        } else if lo >= p.far {
            0.0
        } else {
            return false;
        };
        let x = delta / q.sight;
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
        gap + dist_term + b * x / (1.0 - x) + SLACK < step_min
    };
    let rate_per_m = a / d0.max(1e-6) + b / q.sight;
    let first = if rate_per_m > 0.0 {
        (step0 - gap) / rate_per_m
    } else {
        d0.max(1.0)
    };
    for f in [0.8, 0.5, 0.25, 0.1] {
        let delta = first * f;
        if delta.is_finite() && delta > 0.0 && fits(delta) {
            return delta;
        }
    }
    0.0
}

/// Seed 004 state of one tree instance drawn as geometry: switch control per leaf node.
///
/// Every frame each leaf node's rate is proposed and passed through switch control, but a node
/// is only *evaluated* once the eye has travelled (path length, model frame) past the
/// [`still_radius`] found at its last evaluation: until then no proposal can pass the step
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
    travelled: f64,
    eye: Vec3,
    params: Option<(LodParams, RateConsts)>,
    /// No update yet: the first proposal applies as it is (switch control governs changes, and
    /// a tree that just came into view has no rate to change from).
    fresh: bool,
    evaluated: usize,
}

impl TreeLodState {
    /// Fresh state for a node table (every leaf node at rate 0).
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
            travelled: 0.0,
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

    /// Rates in force, per leaf node (ordinal order).
    pub fn rates(&self) -> impl Iterator<Item = f32> + '_ {
        self.rate.iter().copied()
    }

    /// Keep counts in force, per leaf node (ordinal order).
    pub fn keep(&self) -> &[u32] {
        &self.keep
    }

    /// Leaf nodes evaluated by the last update (the others provably could not change).
    pub fn evaluated(&self) -> usize {
        self.evaluated
    }

    /// Advances `dt` seconds with the eye at `eye_model` (model frame): proposes each leaf node's
    /// rate and applies it through switch control. Returns the keep count per leaf node.
    pub fn update(&mut self, p: &LodParams, eye_model: Vec3, dt: f32) -> &[u32] {
        if self.params.as_ref().is_none_or(|(q, _)| q != p) {
            // New parameters: every bound is stale.
            self.params = Some((p.clone(), RateConsts::new(p)));
            self.expire.fill(f64::NEG_INFINITY);
        }
        let Some((p, k)) = &self.params else {
            return &self.keep;
        };
        let t = &*self.table;
        self.evaluated = 0;
        if self.fresh {
            for i in 0..t.len() {
                let q = t.propose(p, k, i, eye_model, 0.0);
                let sw = SwitchState::new(q.rate);
                self.rate[i] = sw.rate;
                self.held[i] = sw.held_s;
                self.keep[i] = keep_count(t.leaf_count[i], sw.rate);
                // The next proposal reads the rate now in force (f3): bound from that one.
                let q = t.repropose(p, i, q, sw.rate);
                self.expire[i] = f64::from(still_radius(p, k, t.branch_level[i], t.growth[i].is_some(), q, sw.rate));
            }
            self.evaluated = t.len();
            self.fresh = false;
            self.eye = eye_model;
            return &self.keep;
        }
        let moved = eye_model.distance(self.eye);
        // A non-finite move (NaN eye) evaluates everything.
        self.travelled += if moved.is_finite() {
            f64::from(moved)
        } else {
            f64::INFINITY
        };
        self.eye = eye_model;
        let add = dt.is_finite() && dt > 0.0;
        for i in 0..t.len() {
            if add {
                self.held[i] += dt;
            }
            if self.expire[i] > self.travelled {
                continue;
            }
            self.evaluated += 1;
            let mut sw = SwitchState {
                rate: self.rate[i],
                held_s: self.held[i],
            };
            // The hold time already advanced above.
            let mut q = t.propose(p, k, i, eye_model, sw.rate);
            if sw.update(p, q.rate, q.distance, 0.0).1 {
                self.keep[i] = keep_count(t.leaf_count[i], sw.rate);
                // The next proposal reads the new rate in force (f3): bound from that one.
                q = t.repropose(p, i, q, sw.rate);
            }
            self.rate[i] = sw.rate;
            self.held[i] = sw.held_s;
            let r = still_radius(p, k, t.branch_level[i], t.growth[i].is_some(), q, sw.rate);
            self.expire[i] = if self.travelled.is_finite() {
                self.travelled + f64::from(r)
            } else {
                f64::NEG_INFINITY
            };
        }
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
        let stats = TreeStats::from_nodes(nodes);
        let leaves: Vec<&NodeRecord> = nodes.iter().filter(|n| n.kind == NodeKind::Leaf).collect();
        let mut sw = vec![SwitchState::new(0.0); leaves.len()];
        let mut out = Vec::new();
        for (f, &eye) in eyes.iter().enumerate() {
            let mut keep = Vec::new();
            for (n, s) in leaves.iter().zip(&mut sw) {
                let r = node_rate(p, &stats, n, eye, s.rate);
                if f == 0 {
                    *s = SwitchState::new(r.rate);
                } else {
                    s.update(p, r.rate, r.distance, dt);
                }
                keep.push(keep_count(n.leaf_count, s.rate));
            }
            out.push(keep);
        }
        out
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

//! Seed 004 state of one tree instance drawn as geometry: switch control per leaf node, with
//! nodes skipped while the eye stays within their still radius. Leaf nodes are indexed by leaf
//! ordinal (their order among the leaf nodes of the node table); the eye is in the model frame.

use std::sync::Arc;

use canopy_shared::format::NodeRecord;
use canopy_shared::format::leaf::keep_count;
use glam::Vec3;

use super::leaf_table::LeafTable;
use super::still_radius::still_radius;
use crate::lod::LodParams;
use crate::lod::rate::{RateConsts, TreeStats};
use crate::lod::switch::SwitchState;

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
    use canopy_shared::format::node::NodeKind;

    use super::*;
    use crate::lod::rate::node_rate;
    use crate::lod::tree::fixtures::{crown, nodes};

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
            let mut rng = canopy_shared::rng::SplitMix64::new(seed);
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

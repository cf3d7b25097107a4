//! Per-tree glue: culling, representation and the per-node rates of one tree instance.
//!
//! Node records are in the model's frame; an instance is placed by a transform. The helpers here
//! take the eye already transformed into the model frame (`eye_model = instance⁻¹ · eye`), which
//! is exact for rigid transforms with uniform scale 1; for a scaled instance pass the scaled
//! distances yourself via the lower-level functions.

use canopy_shared::format::NodeRecord;
use canopy_shared::format::leaf::keep_count;
use canopy_shared::format::node::NodeKind;
use glam::{Mat4, Vec3};

use super::frustum::Frustum;
use super::projection::{LadderStep, Representation, choose_representation, projected_height};
use super::rate::{TreeStats, node_rate};
use super::switch::SwitchState;
use super::{LodParams, sphere_distance};

/// Marks the nodes whose bounding sphere (transformed by `model`) may be visible; a culled node
/// culls its whole subtree (`subtree_end`) in one step.
pub fn visible_nodes(frustum: &Frustum, model: Mat4, nodes: &[NodeRecord]) -> Vec<bool> {
    let scale = model.to_scale_rotation_translation().0.abs().max_element();
    let mut out = vec![false; nodes.len()];
    let mut i = 0usize;
    while i < nodes.len() {
        let n = &nodes[i];
        let c = model.transform_point3(n.sphere_center);
        if frustum.intersects_sphere(c, n.sphere_radius * scale) {
            out[i] = true;
            i += 1;
        } else {
            i = (n.subtree_end as usize).max(i + 1);
        }
    }
    out
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

/// Seed 004 state of one tree instance drawn as geometry: one [`SwitchState`] per leaf node.
#[derive(Debug, Clone)]
pub struct TreeLodState {
    stats: TreeStats,
    switches: Vec<SwitchState>,
    /// No update yet: the first proposal applies as it is (switch control governs changes, and
    /// a tree that just came into view has no rate to change from).
    fresh: bool,
}

impl TreeLodState {
    /// Fresh state for a node table (every leaf node at rate 0).
    pub fn new(nodes: &[NodeRecord]) -> Self {
        let leaf_nodes = nodes.iter().filter(|n| n.kind == NodeKind::Leaf).count();
        Self {
            stats: TreeStats::from_nodes(nodes),
            switches: vec![SwitchState::new(0.0); leaf_nodes],
            fresh: true,
        }
    }

    /// Statistics used by f3.
    pub fn stats(&self) -> &TreeStats {
        &self.stats
    }

    /// Rates in force, per leaf node (ordinal order).
    pub fn rates(&self) -> impl Iterator<Item = f32> + '_ {
        self.switches.iter().map(|s| s.rate)
    }

    /// Advances `dt` seconds with the eye at `eye_model` (model frame): proposes each leaf node's
    /// rate and applies it through switch control. Returns the keep count per leaf node.
    pub fn update(&mut self, p: &LodParams, nodes: &[NodeRecord], eye_model: Vec3, dt: f32) -> Vec<u32> {
        let mut keep = Vec::with_capacity(self.switches.len());
        for (node, sw) in nodes
            .iter()
            .filter(|n| n.kind == NodeKind::Leaf)
            .zip(&mut self.switches)
        {
            let r = node_rate(p, &self.stats, node, eye_model, sw.rate);
            let rate = if self.fresh {
                *sw = SwitchState::new(r.rate);
                sw.rate
            } else {
                sw.update(p, r.rate, r.distance, dt).0
            };
            keep.push(keep_count(node.leaf_count, rate));
        }
        self.fresh = false;
        keep
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lod::frustum::DepthRange;
    use crate::lod::projection::DEFAULT_LADDER;
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
        let keep = st.update(&p, &n, Vec3::new(0.0, 0.0, -10.0), 0.016);
        assert_eq!(keep, vec![80, 80]);
        // Far below: f4 = 1, f2 = 0.5, f5 = 0 (growth +Y, sight −Y... eye above looks down: +Y
        // growth against a −Y line of sight), f3 with LD = 2·0.8 = 1.6 → 0.6.
        let keep = st.update(&p, &n, Vec3::new(0.0, 1e5, -10.0), 10.0);
        let want = 0.1 * 0.5 + 0.2 * 0.6 + 0.3;
        assert!(
            st.rates().all(|r| (r - want).abs() < 1e-5),
            "{:?}",
            st.rates().collect::<Vec<_>>()
        );
        assert_eq!(keep, vec![keep_count(100, want); 2]);
        // 499 m away the proposal is ≈ 0.297: a step of ≈ 0.17 is below the capped step
        // threshold 0.25, so the old rate holds however long we wait.
        let _ = st.update(&p, &n, Vec3::new(0.0, 509.0, -10.0), 0.1);
        let _ = st.update(&p, &n, Vec3::new(0.0, 509.0, -10.0), 100.0);
        assert!(st.rates().all(|r| (r - want).abs() < 1e-5));
        // Back inside the crown: thresholds are 0, the change applies at once (rate ≠ want).
        let keep = st.update(&p, &n, Vec3::new(0.0, 0.0, -10.0), 0.0);
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
        let keep = st.update(&p, &n, eye, 0.016);
        // Without the fresh start, switch control (step threshold ≈ 0.25 at 400 m) would hold
        // every node at rate 0 and fetch all leaves of a far tree.
        let proposed = node_rate(&p, st.stats(), &n[2], eye, 0.0).rate;
        assert!(proposed > 0.1, "{proposed}");
        assert!(keep.iter().all(|&k| k < 100), "{keep:?}");
    }
}

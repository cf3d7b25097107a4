//! Frustum culling of one tree instance's nodes. Node spheres are placed in the world by the
//! instance transform ([`world_spheres`]); a node whose sphere is outside the frustum culls its
//! whole subtree (`subtree_end`) in one step, and a subtree whose reach sphere lies wholly inside
//! every plane is kept in one step ([`visible_leaves_world`]): both give exactly the node walk's
//! answer. Visibility is reported per node, or per leaf node in leaf-ordinal order.

use canopy_shared::format::NodeRecord;
use canopy_shared::format::node::NodeKind;
use glam::{Mat4, Vec4};

use crate::lod::frustum::Frustum;

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

#[cfg(test)]
mod tests {
    use canopy_shared::format::NO_BRANCH;
    use canopy_shared::format::NO_PARENT;
    use glam::Vec3;
    use std::f32::consts::FRAC_PI_2;

    use super::*;
    use crate::lod::frustum::DepthRange;
    use crate::lod::tree::fixtures::nodes;

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

    /// A random node hierarchy of about `count` nodes in preorder (`subtree_end` set), leaves
    /// and branches mixed, spheres anywhere (a child's sphere need not lie in its parent's).
    fn random_hierarchy(count: usize, seed: u64) -> Vec<NodeRecord> {
        let mut rng = canopy_shared::rng::SplitMix64::new(seed);
        let mut out: Vec<NodeRecord> = Vec::new();
        fn grow(
            out: &mut Vec<NodeRecord>,
            rng: &mut canopy_shared::rng::SplitMix64,
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
}

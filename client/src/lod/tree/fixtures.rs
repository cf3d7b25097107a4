//! Node tables the tests of this module share.

use canopy_shared::format::node::NodeKind;
use canopy_shared::format::{NO_BRANCH, NO_PARENT, NodeRecord};
use glam::Vec3;

pub(super) fn nodes() -> Vec<NodeRecord> {
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

/// A crown of `count` leaf nodes (random spheres, layers, levels, densities and growth)
/// under one trunk node.
pub(super) fn crown(count: usize, seed: u64) -> Vec<NodeRecord> {
    let mut rng = canopy_shared::rng::SplitMix64::new(seed);
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

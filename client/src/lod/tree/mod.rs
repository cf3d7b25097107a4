//! Per-tree glue: culling, representation and the per-node rates of one tree instance.
//!
//! Node records are in the model's frame; an instance is placed by a transform. The helpers here
//! take the eye already transformed into the model frame (`eye_model = instance⁻¹ · eye`), which
//! is exact for rigid transforms with uniform scale 1; for a scaled instance pass the scaled
//! distances yourself via the lower-level functions.
//!
//! # Modules
//!
//! - `culling`: node and leaf-node visibility against a frustum, a culled node culling its
//!   subtree ([`visible_nodes_world`], [`visible_leaves_world`] with [`subtree_reach`] and
//!   [`leaves_before`]).
//! - `leaf_table`: what the rates read of each leaf node, shared by every instance of a model
//!   ([`LeafTable`]), and seed 004's proposal for one leaf node.
//! - `still_radius`: how far the eye may move before a node's proposal could pass switch
//!   control's step threshold (with its proof).
//! - `state`: per-instance switch control over the leaf nodes ([`TreeLodState`]), skipping nodes
//!   that provably cannot change.
//!
//! Rates follow the conventions of [`crate::lod`]: 0 draws every leaf of a node, 1 none.

mod culling;
#[cfg(test)]
mod fixtures;
mod leaf_table;
mod state;
mod still_radius;

use glam::Vec3;

pub use culling::{
    leaves_before, subtree_reach, visible_leaves_world, visible_nodes, visible_nodes_world, world_spheres,
};
pub use leaf_table::LeafTable;
pub use state::TreeLodState;

use super::projection::{LadderStep, Representation, choose_representation, projected_height};
use super::sphere_distance;

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

#[cfg(test)]
mod tests {
    use std::f32::consts::FRAC_PI_2;

    use super::*;
    use crate::lod::projection::{HULL_LADDER_SPEC, parse_ladder};

    #[test]
    fn representation_by_distance() {
        let hulls = parse_ladder(HULL_LADDER_SPEC).expect("hull ladder");
        let rep =
            |z: f32| tree_representation(&hulls, 20.0, Vec3::ZERO, Vec3::new(0.0, 0.0, z), 5.0, 1000.0, FRAC_PI_2);
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
}

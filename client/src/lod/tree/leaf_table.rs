//! The per-leaf-node data seed 004's rates read, gathered once per model ([`LeafTable`]), and
//! the proposal for one leaf node: every factor comes from [`crate::lod::rate`], so a
//! proposal equals [`crate::lod::rate::node_rate`] bit for bit, plus what the still radius
//! needs (sight length, unclipped growth cosine).

use canopy_shared::format::NodeRecord;
use canopy_shared::format::node::NodeKind;
use glam::Vec3;

#[cfg(doc)]
use super::still_radius::still_radius;
use crate::lod::rate::{RateConsts, TreeStats, combine, f1_layer, f3_density, f5_from_cosine, growth_cosine};
use crate::lod::{LodParams, surface_distance};

/// The per-leaf-node data the rates read, gathered once per model (leaf-node ordinal order) and
/// shared by every instance of it.
#[derive(Debug, Clone)]
pub struct LeafTable {
    pub(super) stats: TreeStats,
    /// One record per leaf node: what one evaluation reads lies together.
    pub(super) leaves: Vec<LeafRec>,
}

/// What the rates read of one leaf node.
#[derive(Debug, Clone, Copy)]
pub(super) struct LeafRec {
    center: Vec3,
    radius: f32,
    /// Unit growth direction (valid when `has_growth`; degenerate ones give f5 = 0).
    growth: Vec3,
    pub(super) has_growth: bool,
    pub(super) branch_level: u8,
    sphere_layer: u8,
    density: f32,
    pub(super) leaf_count: u32,
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

    /// Seed 004's proposal for leaf node `i` seen from `eye` with `current` in force: the factors
    /// of [`crate::lod::rate::node_rate`] (bit for bit: the same functions on the same floats),
    /// plus what [`still_radius`] needs.
    #[inline]
    pub(super) fn propose(&self, p: &LodParams, k: &RateConsts, i: usize, eye: Vec3, current: f32) -> Proposal {
        let l = &self.leaves[i];
        let los = l.center - eye;
        let sight = los.length();
        let distance = surface_distance(sight, l.radius);
        let cos_growth = growth_cosine(los, sight, l.has_growth.then_some(l.growth));
        let f = [
            f1_layer(p, l.sphere_layer),
            k.f2(p, l.branch_level, distance),
            f3_density(&self.stats, l.density, current),
            k.f4(p, distance),
            f5_from_cosine(cos_growth),
        ];
        Proposal {
            rate: combine(p, f),
            f,
            distance,
            sight,
            cos_growth,
        }
    }

    /// `q` again with `current` in force instead: only f3 reads it.
    #[inline]
    pub(super) fn repropose(&self, p: &LodParams, i: usize, q: Proposal, current: f32) -> Proposal {
        let mut f = q.f;
        f[2] = f3_density(&self.stats, self.leaves[i].density, current);
        Proposal {
            rate: combine(p, f),
            f,
            ..q
        }
    }
}

/// One leaf node's proposal: the rate, its factors, and what the still radius reads.
#[derive(Debug, Clone, Copy)]
pub(super) struct Proposal {
    pub(super) rate: f32,
    pub(super) f: [f32; 5],
    /// Sphere distance.
    pub(super) distance: f32,
    /// `|centre − eye|`.
    pub(super) sight: f32,
    /// Cosine of the angle between the line of sight and the growth direction, unclipped (f5
    /// before `clamp01`); NaN when f5 is 0 for want of either direction.
    pub(super) cos_growth: f32,
}

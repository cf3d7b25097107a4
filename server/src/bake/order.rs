//! Leaf orders inside each leaf node: the prefix of a node's order is the simplification the
//! client draws. Generation, random (stochastic pruning, Cook et al. 2007) and by area are here;
//! VMI (seed 004) is `vmi.rs`.

use canopy_shared::format::LeafOrder;
use canopy_shared::model::TreeModel;
use canopy_shared::rng::SplitMix64;

/// Why an order could not be built.
#[derive(Debug, thiserror::Error)]
pub enum OrderError {
    /// VMI needs renders: it is built by `bake::vmi`, not here.
    #[error("the VMI order is built by bake::vmi::vmi_order")]
    NeedsRenders,
}

/// Reorders the leaves of every leaf node (indices into `model.leaves`) in place.
///
/// - `Generation`: ascending leaf index (as grown or imported).
/// - `Random`: a Fisher–Yates shuffle per node, seeded by `seed` and the node's position, so the
///   result does not depend on anything else.
/// - `Area`: decreasing blade area, ties by index.
pub fn order_leaves(
    model: &TreeModel,
    node_leaves: &mut [Vec<u32>],
    order: LeafOrder,
    seed: u64,
) -> Result<(), OrderError> {
    match order {
        LeafOrder::Generation => node_leaves.iter_mut().for_each(|v| v.sort_unstable()),
        LeafOrder::Random => {
            for (i, v) in node_leaves.iter_mut().enumerate() {
                v.sort_unstable();
                let mut rng = SplitMix64::new(seed ^ (i as u64).wrapping_mul(0xA24B_AED4_963E_E407));
                for j in (1..v.len()).rev() {
                    let k = rng.below(j as u64 + 1) as usize;
                    v.swap(j, k);
                }
            }
        }
        LeafOrder::Area => {
            for v in node_leaves.iter_mut() {
                v.sort_by(|&a, &b| {
                    let (la, lb) = (&model.leaves[a as usize], &model.leaves[b as usize]);
                    lb.area().total_cmp(&la.area()).then(a.cmp(&b))
                });
            }
        }
        LeafOrder::Vmi => return Err(OrderError::NeedsRenders),
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use canopy_shared::model::{Leaf, Materials, ModelSource};
    use glam::Vec3;

    fn model(n: usize) -> TreeModel {
        TreeModel {
            name: "t".into(),
            branches: Vec::new(),
            leaves: (0..n)
                .map(|i| Leaf {
                    center: Vec3::ZERO,
                    normal: Vec3::Z,
                    axis: Vec3::Y,
                    width: 0.01 * (i % 7) as f32 + 0.01,
                    length: 0.05,
                    branch: None,
                    iteration: 0,
                    material: 0,
                })
                .collect(),
            bark_mesh: canopy_shared::model::TriangleMesh::default(),
            materials: Materials::default(),
            iterations: 0,
            source: ModelSource::Gltf,
        }
    }

    #[test]
    fn random_is_a_seeded_permutation() {
        let m = model(100);
        let mut a = vec![(0..100).collect::<Vec<u32>>()];
        let mut b = a.clone();
        order_leaves(&m, &mut a, LeafOrder::Random, 7).expect("order");
        order_leaves(&m, &mut b, LeafOrder::Random, 7).expect("order");
        assert_eq!(a, b);
        assert_ne!(a[0], (0..100).collect::<Vec<u32>>());
        let mut s = a[0].clone();
        s.sort_unstable();
        assert_eq!(s, (0..100).collect::<Vec<u32>>());
        let mut c = vec![(0..100).collect::<Vec<u32>>()];
        order_leaves(&m, &mut c, LeafOrder::Random, 8).expect("order");
        assert_ne!(a, c);
    }

    #[test]
    fn area_is_decreasing() {
        let m = model(50);
        let mut a = vec![(0..50).collect::<Vec<u32>>()];
        order_leaves(&m, &mut a, LeafOrder::Area, 0).expect("order");
        assert!(
            a[0].windows(2)
                .all(|w| m.leaves[w[0] as usize].area() >= m.leaves[w[1] as usize].area())
        );
    }
}

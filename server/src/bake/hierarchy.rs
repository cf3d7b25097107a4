//! Seed 004's node hierarchy, built from a tree model (spec: `docs/format.md#hierarchy`).
//!
//! L-system trees: one branch node per branch of level ≤ `Lc`, each with a leaf-node child
//! holding its leaves and those of its deeper sub-branches. Imported trees (no skeleton): a k-d
//! split of the leaf centres.

use canopy_shared::format::{NO_BRANCH, NO_PARENT, NodeKind, NodeRecord};
use canopy_shared::model::TreeModel;
use glam::Vec3;

/// Smallest mean leaf-node size the cut level aims for.
pub const TARGET_LEAVES_PER_NODE: usize = 48;

/// Largest leaf node, as a multiple of the target: a branch whose (merged) leaves exceed it gets
/// several leaf-node children, split by k-d on the leaf centres. Keeps per-node rates fine-grained
/// and the VMI bake's O(n²) per node bounded.
pub const MAX_NODE_FACTOR: usize = 4;

/// A node hierarchy: records in preorder and the leaves (indices into the model) of each leaf
/// node, leaf nodes in preorder, leaves in generation order.
#[derive(Debug, Clone)]
pub struct Hierarchy {
    /// Node records, preorder.
    pub nodes: Vec<NodeRecord>,
    /// Leaf indices per leaf node.
    pub node_leaves: Vec<Vec<u32>>,
    /// The cut level `Lc` (deepest branch level that has its own node); 0 for k-d hierarchies.
    pub cut_level: u8,
}

/// A growing bounding volume: the box gives the centre, the points give the radius.
#[derive(Default, Clone)]
struct Bounds {
    lo: Option<(Vec3, Vec3)>,
    spheres: Vec<(Vec3, f32)>,
}

impl Bounds {
    fn add(&mut self, c: Vec3, r: f32) {
        let (lo, hi) = self.lo.unwrap_or((c, c));
        self.lo = Some((lo.min(c - Vec3::splat(r)), hi.max(c + Vec3::splat(r))));
        self.spheres.push((c, r));
    }
    fn sphere(&self) -> (Vec3, f32) {
        let Some((lo, hi)) = self.lo else {
            return (Vec3::ZERO, 0.0);
        };
        let c = (lo + hi) * 0.5;
        let r = self.spheres.iter().map(|&(p, r)| p.distance(c) + r).fold(0.0, f32::max);
        (c, r)
    }
}

fn leaf_radius(model: &TreeModel, i: u32) -> (Vec3, f32) {
    let l = &model.leaves[i as usize];
    (l.center, 0.5 * l.width.hypot(l.length))
}

/// Seed 004's bounding-sphere layer: 1 if the node centre lies in the outer third of the crown
/// sphere's radius, 2 in the middle third, 3 in the inner third.
pub fn sphere_layer(center: Vec3, crown_center: Vec3, crown_radius: f32) -> u8 {
    if crown_radius <= 0.0 {
        return 1;
    }
    let t = center.distance(crown_center) / crown_radius;
    if t >= 2.0 / 3.0 {
        1
    } else if t >= 1.0 / 3.0 {
        2
    } else {
        3
    }
}

fn crown_sphere(model: &TreeModel) -> (Vec3, f32) {
    let mut b = Bounds::default();
    for i in 0..model.leaves.len() as u32 {
        let (c, r) = leaf_radius(model, i);
        b.add(c, r);
    }
    b.sphere()
}

/// Builds the hierarchy of `model`, choosing L-system or k-d grouping by whether the leaves know
/// their branches.
pub fn build(model: &TreeModel, target: usize) -> Hierarchy {
    let target = target.max(1);
    let mut h = if !model.branches.is_empty() && model.leaves.iter().all(|l| l.branch.is_some()) {
        build_from_skeleton(model, target)
    } else {
        build_kd(model, target)
    };
    finish(model, &mut h);
    h
}

/// Owner node-branch of every branch for cut level `lc`.
fn owners(model: &TreeModel, lc: u8) -> Vec<u32> {
    let mut owner = vec![0u32; model.branches.len()];
    for (i, b) in model.branches.iter().enumerate() {
        owner[i] = match b.parent {
            Some(p) if b.level > lc => owner[p as usize],
            _ => i as u32,
        };
    }
    owner
}

fn build_from_skeleton(model: &TreeModel, target: usize) -> Hierarchy {
    let max_level = model.branches.iter().map(|b| b.level).max().unwrap_or(1);
    let leaf_branch = |l: &canopy_shared::Leaf| l.branch.unwrap_or(0) as usize;
    let mut cut = 1;
    for lc in (1..=max_level).rev() {
        let owner = owners(model, lc);
        let mut has = vec![false; model.branches.len()];
        for l in &model.leaves {
            has[owner[leaf_branch(l)] as usize] = true;
        }
        let groups = has.iter().filter(|&&x| x).count().max(1);
        if model.leaves.len() / groups >= target {
            cut = lc;
            break;
        }
    }
    let owner = owners(model, cut);
    let mut owned_leaves: Vec<Vec<u32>> = vec![Vec::new(); model.branches.len()];
    for (i, l) in model.leaves.iter().enumerate() {
        owned_leaves[owner[leaf_branch(l)] as usize].push(i as u32);
    }
    // Length and points of the branches merged into each node-branch.
    let mut owned_len = vec![0.0f32; model.branches.len()];
    let mut owned_bounds: Vec<Bounds> = vec![Bounds::default(); model.branches.len()];
    for (i, b) in model.branches.iter().enumerate() {
        let o = owner[i] as usize;
        owned_len[o] += b.length();
        for p in &b.points {
            owned_bounds[o].add(p.position, p.radius);
        }
    }
    let mut children: Vec<Vec<u32>> = vec![Vec::new(); model.branches.len()];
    let mut roots = Vec::new();
    for (i, b) in model.branches.iter().enumerate() {
        if owner[i] as usize != i {
            continue;
        }
        match b.parent {
            Some(p) => children[owner[p as usize] as usize].push(i as u32),
            None => roots.push(i as u32),
        }
    }
    let mut h = Hierarchy {
        nodes: Vec::new(),
        node_leaves: Vec::new(),
        cut_level: cut,
    };
    let synthetic_root = roots.len() != 1;
    if synthetic_root {
        // Several trunks (or none): a root node without a skeleton branch holds them.
        h.nodes.push(blank_node(NO_PARENT, NodeKind::Branch, 1, NO_BRANCH));
    }
    // Iterative preorder: (branch, parent node index).
    let mut stack: Vec<(u32, u32)> = roots
        .iter()
        .rev()
        .map(|&r| (r, if synthetic_root { 0 } else { NO_PARENT }))
        .collect();
    while let Some((bi, parent)) = stack.pop() {
        let b = &model.branches[bi as usize];
        let idx = h.nodes.len() as u32;
        let mut n = blank_node(parent, NodeKind::Branch, b.level, bi);
        n.growth_direction = b.growth_direction();
        n.length = b.length();
        let (c, r) = owned_bounds[bi as usize].sphere();
        n.sphere_center = c;
        n.sphere_radius = r;
        h.nodes.push(n);
        let leaves = std::mem::take(&mut owned_leaves[bi as usize]);
        let total = leaves.len();
        let density = total as f32 / owned_len[bi as usize].max(1e-3);
        for piece in split_kd(model, leaves, target * MAX_NODE_FACTOR) {
            let mut ln = blank_node(idx, NodeKind::Leaf, b.level, bi);
            ln.growth_direction = n.growth_direction;
            // Each piece keeps the branch's density: it carries its share of the length.
            ln.length = owned_len[bi as usize] * piece.len() as f32 / total as f32;
            ln.leaf_count = piece.len() as u32;
            ln.leaf_density = density;
            h.nodes.push(ln);
            h.node_leaves.push(piece);
        }
        for &c in children[bi as usize].iter().rev() {
            stack.push((c, idx));
        }
    }
    h
}

/// Splits `idx` (leaf indices) at the median of the longest axis of their centres until every
/// piece holds at most `max` leaves. Pieces come out in a fixed spatial order; each is sorted.
fn split_kd(model: &TreeModel, idx: Vec<u32>, max: usize) -> Vec<Vec<u32>> {
    let max = max.max(1);
    let mut out = Vec::new();
    let mut stack = vec![idx];
    while let Some(mut v) = stack.pop() {
        if v.is_empty() {
            continue;
        }
        if v.len() <= max {
            v.sort_unstable();
            out.push(v);
            continue;
        }
        let (lo, hi) = v.iter().fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(a, b), &i| {
            let c = model.leaves[i as usize].center;
            (a.min(c), b.max(c))
        });
        let ext = hi - lo;
        let axis = if ext.x >= ext.y && ext.x >= ext.z {
            0
        } else if ext.y >= ext.z {
            1
        } else {
            2
        };
        let mid = v.len() / 2;
        v.select_nth_unstable_by(mid, |&a, &b| {
            let (ca, cb) = (
                model.leaves[a as usize].center[axis],
                model.leaves[b as usize].center[axis],
            );
            ca.total_cmp(&cb).then(a.cmp(&b))
        });
        let right = v.split_off(mid);
        stack.push(right);
        stack.push(v);
    }
    out
}

fn blank_node(parent: u32, kind: NodeKind, level: u8, branch: u32) -> NodeRecord {
    NodeRecord {
        parent,
        subtree_end: 0,
        kind,
        branch_level: level.max(1),
        sphere_layer: 1,
        branch,
        leaf_count: 0,
        growth_direction: Vec3::Y,
        length: 0.0,
        sphere_center: Vec3::ZERO,
        sphere_radius: 0.0,
        leaf_density: 0.0,
    }
}

fn build_kd(model: &TreeModel, target: usize) -> Hierarchy {
    let mut h = Hierarchy {
        nodes: Vec::new(),
        node_leaves: Vec::new(),
        cut_level: 0,
    };
    let (lo, hi) = model.bounds().unwrap_or((Vec3::ZERO, Vec3::ZERO));
    let mut root = blank_node(NO_PARENT, NodeKind::Branch, 1, NO_BRANCH);
    root.length = hi.y - lo.y.min(0.0);
    h.nodes.push(root);
    let all: Vec<u32> = (0..model.leaves.len() as u32).collect();
    if all.is_empty() {
        return h;
    }
    // Work items: (leaf indices, parent node, level of a branch node made here).
    let mut stack: Vec<(Vec<u32>, u32, u8)> = vec![(all, 0, 2)];
    while let Some((mut idx, parent, level)) = stack.pop() {
        let centroid = idx.iter().map(|&i| model.leaves[i as usize].center).sum::<Vec3>() / idx.len() as f32;
        if idx.len() <= 2 * target {
            let mut ln = blank_node(parent, NodeKind::Leaf, level.saturating_sub(1).max(1), NO_BRANCH);
            ln.growth_direction = centroid.try_normalize().unwrap_or(Vec3::Y);
            ln.length = centroid.length();
            ln.leaf_count = idx.len() as u32;
            ln.leaf_density = idx.len() as f32 / ln.length.max(1e-3);
            idx.sort_unstable();
            h.nodes.push(ln);
            h.node_leaves.push(idx);
            continue;
        }
        let (clo, chi) = idx.iter().fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(a, b), &i| {
            let c = model.leaves[i as usize].center;
            (a.min(c), b.max(c))
        });
        let ext = chi - clo;
        let axis = if ext.x >= ext.y && ext.x >= ext.z {
            0
        } else if ext.y >= ext.z {
            1
        } else {
            2
        };
        let mid = idx.len() / 2;
        idx.select_nth_unstable_by(mid, |&a, &b| {
            model.leaves[a as usize].center[axis].total_cmp(&model.leaves[b as usize].center[axis])
        });
        let right = idx.split_off(mid);
        let node_idx = if parent == 0 && level == 2 && h.nodes.len() == 1 {
            // The root itself is the first k-d cell.
            0
        } else {
            let mut bn = blank_node(parent, NodeKind::Branch, level, NO_BRANCH);
            bn.growth_direction = centroid.try_normalize().unwrap_or(Vec3::Y);
            bn.length = centroid.length();
            h.nodes.push(bn);
            h.nodes.len() as u32 - 1
        };
        let child_level = if node_idx == 0 { 2 } else { level.saturating_add(1) };
        stack.push((right, node_idx, child_level));
        stack.push((idx, node_idx, child_level));
    }
    h
}

/// Fills subtree ends, bounding spheres, branch-node densities and sphere layers.
fn finish(model: &TreeModel, h: &mut Hierarchy) {
    let n = h.nodes.len();
    for i in 0..n {
        h.nodes[i].subtree_end = i as u32 + 1;
    }
    // Leaf-node spheres from their leaves.
    let mut li = 0;
    for node in &mut h.nodes {
        if node.kind == NodeKind::Leaf {
            let mut b = Bounds::default();
            for &l in &h.node_leaves[li] {
                let (c, r) = leaf_radius(model, l);
                b.add(c, r);
            }
            (node.sphere_center, node.sphere_radius) = b.sphere();
            li += 1;
        }
    }
    // Bottom-up (reverse preorder): subtree ends, spheres, leaf and length totals.
    let mut leaves_below = vec![0u64; n];
    let mut length_below = vec![0f32; n];
    for i in (0..n).rev() {
        let node = h.nodes[i];
        if node.kind == NodeKind::Leaf {
            leaves_below[i] += u64::from(node.leaf_count);
        } else {
            length_below[i] += node.length;
        }
        if node.parent != NO_PARENT {
            let p = node.parent as usize;
            leaves_below[p] += leaves_below[i];
            length_below[p] += length_below[i];
            let end = h.nodes[i].subtree_end;
            let parent = &mut h.nodes[p];
            parent.subtree_end = parent.subtree_end.max(end);
            // Grow the parent's sphere to enclose the child's.
            let (pc, pr) = (parent.sphere_center, parent.sphere_radius);
            let (cc, cr) = (node.sphere_center, node.sphere_radius);
            if pr == 0.0 && pc == Vec3::ZERO {
                (parent.sphere_center, parent.sphere_radius) = (cc, cr);
            } else {
                let d = pc.distance(cc);
                if d + cr > pr {
                    if d + pr <= cr {
                        (parent.sphere_center, parent.sphere_radius) = (cc, cr);
                    } else {
                        let r = 0.5 * (d + pr + cr);
                        let dir = (cc - pc) / d.max(1e-9);
                        parent.sphere_center = pc + dir * (r - pr);
                        parent.sphere_radius = r;
                    }
                }
            }
        }
    }
    let (cc, cr) = crown_sphere(model);
    for (i, node) in h.nodes.iter_mut().enumerate() {
        if node.kind == NodeKind::Branch {
            node.leaf_density = leaves_below[i] as f32 / length_below[i].max(1e-3);
        }
        node.sphere_layer = sphere_layer(node.sphere_center, cc, cr);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use canopy_shared::format::node::{decode_nodes, encode_nodes};
    use canopy_shared::model::{Branch, Leaf, Materials, ModelSource, SkeletonPoint};

    fn leaf(c: Vec3, branch: Option<u32>) -> Leaf {
        Leaf {
            center: c,
            normal: Vec3::Z,
            axis: Vec3::Y,
            width: 0.05,
            length: 0.08,
            branch,
            iteration: 0,
            material: 0,
        }
    }

    fn branch(a: Vec3, b: Vec3, parent: Option<u32>, level: u8) -> Branch {
        Branch {
            points: vec![
                SkeletonPoint {
                    position: a,
                    radius: 0.1,
                },
                SkeletonPoint {
                    position: b,
                    radius: 0.05,
                },
            ],
            parent,
            level,
            iteration: 0,
        }
    }

    fn model(branches: Vec<Branch>, leaves: Vec<Leaf>) -> TreeModel {
        TreeModel {
            name: "t".into(),
            branches,
            leaves,
            bark_mesh: canopy_shared::model::TriangleMesh::default(),
            materials: Materials::default(),
            iterations: 0,
            source: ModelSource::LSystem,
        }
    }

    fn check(h: &Hierarchy, leaves: usize, branches: u32) {
        let bytes = encode_nodes(&h.nodes);
        decode_nodes(&bytes, h.nodes.len() as u32, branches).expect("valid preorder");
        let mut seen: Vec<u32> = h.node_leaves.iter().flatten().copied().collect();
        seen.sort_unstable();
        assert_eq!(
            seen,
            (0..leaves as u32).collect::<Vec<_>>(),
            "every leaf in exactly one node"
        );
    }

    #[test]
    fn skeleton_tree_gets_node_per_branch_and_spheres_cover_leaves() {
        let mut bs = vec![branch(Vec3::ZERO, Vec3::Y * 4.0, None, 1)];
        let mut ls = Vec::new();
        for k in 0..6 {
            let dir = Vec3::new((k as f32).cos(), 0.3, (k as f32).sin());
            bs.push(branch(
                Vec3::Y * (1.0 + k as f32 * 0.5),
                Vec3::Y * (1.0 + k as f32 * 0.5) + dir * 2.0,
                Some(0),
                2,
            ));
            for j in 0..60 {
                ls.push(leaf(
                    Vec3::Y * (1.0 + k as f32 * 0.5) + dir * (j as f32 / 30.0),
                    Some(k + 1),
                ));
            }
        }
        let m = model(bs, ls);
        let h = build(&m, 48);
        check(&h, m.leaves.len(), m.branches.len() as u32);
        assert_eq!(h.cut_level, 2);
        assert_eq!(h.node_leaves.len(), 6);
        assert_eq!(h.nodes.len(), 13);
        for (n, leaves) in h.nodes.iter().filter(|n| n.kind == NodeKind::Leaf).zip(&h.node_leaves) {
            for &l in leaves {
                let c = m.leaves[l as usize].center;
                assert!(c.distance(n.sphere_center) <= n.sphere_radius + 1e-4);
            }
            assert!(
                h.nodes[0].sphere_radius + 1e-4 >= h.nodes[0].sphere_center.distance(n.sphere_center) + n.sphere_radius
            );
        }
    }

    #[test]
    fn small_groups_merge_into_parent_levels() {
        // 6 twigs of 10 leaves: below the target, so twigs merge into the trunk.
        let mut bs = vec![branch(Vec3::ZERO, Vec3::Y * 4.0, None, 1)];
        let mut ls = Vec::new();
        for k in 0..6u32 {
            bs.push(branch(Vec3::Y, Vec3::new(1.0, 2.0, k as f32), Some(0), 2));
            for _ in 0..10 {
                ls.push(leaf(Vec3::new(1.0, 2.0, k as f32), Some(k + 1)));
            }
        }
        let m = model(bs, ls);
        let h = build(&m, 48);
        check(&h, 60, 7);
        assert_eq!(h.cut_level, 1);
        assert_eq!(h.node_leaves.len(), 1);
    }

    #[test]
    fn kd_hierarchy_for_imports() {
        let ls: Vec<Leaf> = (0..1000)
            .map(|i| {
                leaf(
                    Vec3::new((i % 10) as f32, (i / 100) as f32, ((i / 10) % 10) as f32),
                    None,
                )
            })
            .collect();
        let m = model(Vec::new(), ls);
        let h = build(&m, 48);
        check(&h, 1000, 0);
        assert!(h.node_leaves.iter().all(|v| v.len() <= 96 && !v.is_empty()));
        assert!(h.node_leaves.len() >= 1000 / 96);
    }

    #[test]
    fn empty_model_has_a_root() {
        let h = build(&model(Vec::new(), Vec::new()), 48);
        check(&h, 0, 0);
        assert_eq!(h.nodes.len(), 1);
    }
}

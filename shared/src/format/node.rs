//! The node table (spec: `docs/format.md#node-table-kind-1`): seed 004's multi-way hierarchy.

use glam::Vec3;

use super::bytes::{Cursor, Writer};
use super::{FormatError, NO_BRANCH, NO_PARENT, NODE_RECORD_LEN};

/// Kind of a node.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum NodeKind {
    /// A branch: no leaves of its own; children are branch and leaf nodes.
    Branch,
    /// A leaf node: holds leaves, has no children.
    Leaf,
}

/// One node of the hierarchy.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NodeRecord {
    /// Parent node index, [`NO_PARENT`] for the root.
    pub parent: u32,
    /// One past the last descendant (preorder).
    pub subtree_end: u32,
    /// Branch or leaf node.
    pub kind: NodeKind,
    /// Branch level: trunk 1.
    pub branch_level: u8,
    /// Bounding-sphere layer: 1 outermost … 3 inner.
    pub sphere_layer: u8,
    /// Skeleton branch index or [`NO_BRANCH`].
    pub branch: u32,
    /// Leaves held (leaf nodes only).
    pub leaf_count: u32,
    /// Unit growth direction.
    pub growth_direction: Vec3,
    /// Branch length, metres.
    pub length: f32,
    /// Bounding-sphere centre, metres.
    pub sphere_center: Vec3,
    /// Bounding-sphere radius, metres.
    pub sphere_radius: f32,
    /// Initial leaf density, leaves per metre.
    pub leaf_density: f32,
}

impl NodeRecord {
    /// Appends the 56-byte record.
    pub(crate) fn encode(&self, w: &mut Writer) {
        w.u32(self.parent);
        w.u32(self.subtree_end);
        w.u8(match self.kind {
            NodeKind::Branch => 0,
            NodeKind::Leaf => 1,
        });
        w.u8(self.branch_level);
        w.u8(self.sphere_layer);
        w.u8(0);
        w.u32(self.branch);
        w.u32(self.leaf_count);
        for v in self.growth_direction.to_array() {
            w.f32(v);
        }
        w.f32(self.length);
        for v in self.sphere_center.to_array() {
            w.f32(v);
        }
        w.f32(self.sphere_radius);
        w.f32(self.leaf_density);
    }

    fn decode_one(c: &mut Cursor) -> Result<Self, FormatError> {
        let parent = c.u32()?;
        let subtree_end = c.u32()?;
        let kind = match c.u8()? {
            0 => NodeKind::Branch,
            1 => NodeKind::Leaf,
            v => return Err(FormatError::invalid("node kind", v.to_string())),
        };
        let branch_level = c.u8()?;
        let sphere_layer = c.u8()?;
        c.u8()?;
        let branch = c.u32()?;
        let leaf_count = c.u32()?;
        let gx = c.finite_f32("growth direction")?;
        let gy = c.finite_f32("growth direction")?;
        let gz = c.finite_f32("growth direction")?;
        let length = c.finite_f32("branch length")?;
        let sx = c.finite_f32("sphere centre")?;
        let sy = c.finite_f32("sphere centre")?;
        let sz = c.finite_f32("sphere centre")?;
        let sphere_radius = c.finite_f32("sphere radius")?;
        let leaf_density = c.finite_f32("leaf density")?;
        Ok(Self {
            parent,
            subtree_end,
            kind,
            branch_level,
            sphere_layer,
            branch,
            leaf_count,
            growth_direction: Vec3::new(gx, gy, gz),
            length,
            sphere_center: Vec3::new(sx, sy, sz),
            sphere_radius,
            leaf_density,
        })
    }
}

/// Encodes a node table.
pub fn encode_nodes(nodes: &[NodeRecord]) -> Vec<u8> {
    let mut w = Writer::default();
    for n in nodes {
        n.encode(&mut w);
    }
    w.buf
}

/// Decodes and validates a node table of `count` records against `branch_count` skeleton
/// branches. Checks the preorder structure: root first, parents precede children, subtree ends
/// nest, leaf nodes have no children and at least one leaf.
pub fn decode_nodes(bytes: &[u8], count: u32, branch_count: u32) -> Result<Vec<NodeRecord>, FormatError> {
    let need = u64::from(count) * NODE_RECORD_LEN as u64;
    if bytes.len() as u64 != need {
        return Err(FormatError::Truncated {
            what: "node table",
            need,
            have: bytes.len() as u64,
        });
    }
    let mut c = Cursor::new(bytes, "node table");
    let mut nodes = Vec::with_capacity(count as usize);
    for i in 0..count {
        let n = NodeRecord::decode_one(&mut c)?;
        let bad = |d: String| Err(FormatError::invalid("node", format!("node {i}: {d}")));
        if (i == 0) != (n.parent == NO_PARENT) {
            return bad("only the first node is the root".into());
        }
        if n.parent != NO_PARENT {
            if n.parent >= i {
                return bad(format!("parent {} does not precede it", n.parent));
            }
            let p = &nodes[n.parent as usize];
            let p: &NodeRecord = p;
            if p.kind == NodeKind::Leaf || i >= p.subtree_end || n.subtree_end > p.subtree_end {
                return bad(format!("does not nest inside parent {}", n.parent));
            }
        }
        if n.subtree_end <= i || n.subtree_end > count {
            return bad(format!("subtree end {} out of range", n.subtree_end));
        }
        if n.branch != NO_BRANCH && n.branch >= branch_count {
            return bad(format!("branch {} out of range", n.branch));
        }
        if !(1..=3).contains(&n.sphere_layer) || n.branch_level == 0 {
            return bad("sphere layer or branch level out of range".into());
        }
        if n.sphere_radius < 0.0 || n.length < 0.0 || n.leaf_density < 0.0 {
            return bad("negative radius, length or density".into());
        }
        match n.kind {
            NodeKind::Leaf if n.leaf_count == 0 || n.subtree_end != i + 1 => {
                return bad("a leaf node must hold leaves and have no children".into());
            }
            NodeKind::Branch if n.leaf_count != 0 => {
                return bad("a branch node holds no leaves".into());
            }
            _ => {}
        }
        nodes.push(n);
    }
    if let Some(root) = nodes.first()
        && root.subtree_end != count
    {
        return Err(FormatError::invalid("node", "the root does not span the table"));
    }
    Ok(nodes)
}

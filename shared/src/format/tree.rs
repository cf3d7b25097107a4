//! Whole-file encoding and decoding: [`encode_tree`] writes a `.ctree`, [`DecodedTree::decode`]
//! reads one back with every check of the spec.

use glam::Vec3;

use super::directory::{Directory, SectionEntry, SectionKind};
use super::header::Header;
use super::leaf::{BandLayout, LeafFrame, QuantizedLeaf, decode_block, encode_block, keep_count};
use super::materials::{decode_materials, encode_materials};
use super::mesh::{decode_mesh, encode_mesh};
use super::node::{NodeKind, NodeRecord, decode_nodes, encode_nodes};
use super::skeleton::{SkeletonFrame, decode_skeleton, encode_skeleton};
use super::skeleton_radii::{encode_skeleton_radii, thickest_per_iteration};
use super::{FLAG_BLOCK_CRC, FormatError, HEADER_LEN, LeafOrder, NO_BRANCH, crc32};
use crate::model::{Branch, Leaf, Materials, ModelSource, TreeModel, TriangleMesh};

/// Everything the encoder writes: a baked tree.
#[derive(Debug, Clone)]
pub struct BakedTree {
    /// Model name.
    pub name: String,
    /// Provenance.
    pub source: ModelSource,
    /// Order of the leaves in `node_leaves`.
    pub leaf_order: LeafOrder,
    /// L-system iterations.
    pub iterations: u8,
    /// Band edges (see [`super::leaf::DEFAULT_BAND_EDGES`]).
    pub band_edges: Vec<u16>,
    /// Skeleton in iteration order, parents first.
    pub branches: Vec<Branch>,
    /// Materials.
    pub materials: Materials,
    /// Imported bark mesh (may be empty).
    pub bark_mesh: TriangleMesh,
    /// Node hierarchy in preorder.
    pub nodes: Vec<NodeRecord>,
    /// Leaves of each leaf node (leaf nodes in preorder), most important first.
    pub node_leaves: Vec<Vec<Leaf>>,
    /// Encoded crown-hull section (`format::hull`), empty if none.
    pub hulls: SectionBody,
    /// Encoded billboard-atlas section (`format::atlas`), empty if none.
    pub atlases: SectionBody,
    /// Encoded billboard-cloud section (`format::cloud`), empty if none.
    pub clouds: SectionBody,
}

/// The encoded bytes of an optional section and its item count.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct SectionBody {
    /// Section bytes.
    pub bytes: Vec<u8>,
    /// Items (hull levels, atlas frames, cloud levels).
    pub item_count: u32,
}

fn bounds_of(t: &BakedTree) -> (Vec3, Vec3) {
    let mut lo = Vec3::splat(f32::INFINITY);
    let mut hi = Vec3::splat(f32::NEG_INFINITY);
    let mut add = |p: Vec3| {
        lo = lo.min(p);
        hi = hi.max(p);
    };
    for b in &t.branches {
        for p in &b.points {
            add(p.position);
        }
    }
    for l in t.node_leaves.iter().flatten() {
        add(l.center);
    }
    for &p in &t.bark_mesh.positions {
        add(p);
    }
    if lo.cmpgt(hi).any() {
        (Vec3::ZERO, Vec3::ZERO)
    } else {
        (lo, hi)
    }
}

fn check_baked(t: &BakedTree) -> Result<(), FormatError> {
    let leaf_nodes: Vec<&NodeRecord> = t.nodes.iter().filter(|n| n.kind == NodeKind::Leaf).collect();
    if t.nodes.is_empty() {
        return Err(FormatError::invalid("baked tree", "no nodes"));
    }
    if leaf_nodes.len() != t.node_leaves.len() {
        return Err(FormatError::invalid(
            "baked tree",
            format!("{} leaf nodes but {} leaf lists", leaf_nodes.len(), t.node_leaves.len()),
        ));
    }
    for (n, leaves) in leaf_nodes.iter().zip(&t.node_leaves) {
        if n.leaf_count as usize != leaves.len() {
            return Err(FormatError::invalid(
                "baked tree",
                "leaf node count disagrees with its leaves",
            ));
        }
    }
    let finite_leaves = t.node_leaves.iter().flatten().all(|l| {
        l.center.is_finite()
            && l.normal.is_finite()
            && l.axis.is_finite()
            && l.width.is_finite()
            && l.length.is_finite()
    });
    let finite_branches = t
        .branches
        .iter()
        .all(|b| b.points.iter().all(|p| p.position.is_finite() && p.radius.is_finite()));
    if !finite_leaves || !finite_branches || !t.bark_mesh.positions.iter().all(|p| p.is_finite()) {
        return Err(FormatError::invalid("baked tree", "non-finite geometry"));
    }
    if t.branches.windows(2).any(|w| w[0].iteration > w[1].iteration) {
        return Err(FormatError::invalid(
            "baked tree",
            "branches are not in iteration order",
        ));
    }
    if t.branches.iter().any(|b| b.iteration > t.iterations)
        || t.node_leaves.iter().flatten().any(|l| l.iteration > t.iterations)
    {
        return Err(FormatError::invalid(
            "baked tree",
            "an element's iteration exceeds the iteration count",
        ));
    }
    if t.materials.leaf.is_empty() || t.materials.leaf.len() > 255 {
        return Err(FormatError::invalid("baked tree", "leaf material count not in 1..=255"));
    }
    if t.bark_mesh
        .indices
        .iter()
        .any(|&i| i as usize >= t.bark_mesh.positions.len())
        || !t.bark_mesh.indices.len().is_multiple_of(3)
    {
        return Err(FormatError::invalid("baked tree", "bark mesh indices out of range"));
    }
    Ok(())
}

/// Encodes a baked tree as a complete `.ctree` file.
///
/// Fails on inconsistent input (leaf lists that disagree with the node table, non-finite
/// geometry, branches out of iteration order) rather than writing a file a reader would reject.
pub fn encode_tree(t: &BakedTree) -> Result<Vec<u8>, FormatError> {
    check_baked(t)?;
    let (lo, hi) = bounds_of(t);
    let all_leaves = || t.node_leaves.iter().flatten();
    let leaf_frame = LeafFrame {
        lo,
        hi,
        width_max: all_leaves().map(|l| l.width).fold(1e-6, f32::max),
        length_max: all_leaves().map(|l| l.length).fold(1e-6, f32::max),
    };
    let skel_frame = SkeletonFrame {
        lo,
        hi,
        radius_max: t
            .branches
            .iter()
            .flat_map(|b| &b.points)
            .map(|p| p.radius)
            .fold(1e-6, f32::max),
    };
    let mut leaves_end = vec![0u32; t.iterations as usize + 1];
    for l in all_leaves() {
        leaves_end[l.iteration as usize] += 1;
    }
    for k in 1..leaves_end.len() {
        leaves_end[k] += leaves_end[k - 1];
    }
    let (skeleton, iteration_table) = encode_skeleton(&t.branches, &skel_frame, t.iterations, &leaves_end);

    let leaf_counts: Vec<u32> = t.node_leaves.iter().map(|v| v.len() as u32).collect();
    let layout = BandLayout::new(&t.band_edges, &leaf_counts);
    let quantized: Vec<Vec<QuantizedLeaf>> = t
        .node_leaves
        .iter()
        .map(|v| v.iter().map(|l| QuantizedLeaf::from_leaf(l, &leaf_frame)).collect())
        .collect();
    let mut leaves = Vec::with_capacity(layout.total_len() as usize);
    for b in 0..layout.band_count() {
        for (i, q) in quantized.iter().enumerate() {
            if let Some(blk) = layout.block(b, i) {
                let first = blk.first_rank as usize;
                encode_block(&q[first..first + blk.count as usize], &mut leaves);
            }
        }
    }

    let radii = thickest_per_iteration(&skeleton, &iteration_table)?;
    let bodies: [(SectionKind, Vec<u8>, u32); 9] = [
        (SectionKind::NodeTable, encode_nodes(&t.nodes), t.nodes.len() as u32),
        (
            SectionKind::Materials,
            encode_materials(&t.materials),
            t.materials.leaf.len() as u32,
        ),
        // Beside the node table and materials: a client's geometry part reads all three at once.
        (
            SectionKind::SkeletonRadii,
            encode_skeleton_radii(&radii),
            radii.len() as u32,
        ),
        (SectionKind::Skeleton, skeleton, t.branches.len() as u32),
        (
            SectionKind::BarkMesh,
            encode_mesh(&t.bark_mesh, lo, hi),
            t.bark_mesh.triangle_count() as u32,
        ),
        (SectionKind::Leaves, leaves, leaf_counts.iter().sum()),
        (SectionKind::Hulls, t.hulls.bytes.clone(), t.hulls.item_count),
        (
            SectionKind::BillboardAtlases,
            t.atlases.bytes.clone(),
            t.atlases.item_count,
        ),
        (
            SectionKind::BillboardClouds,
            t.clouds.bytes.clone(),
            t.clouds.item_count,
        ),
    ];
    let mut dir = Directory {
        name: t.name.clone(),
        source: t.source,
        leaf_order: t.leaf_order,
        iterations: t.iterations,
        band_edges: t.band_edges.clone(),
        branch_count: t.branches.len() as u32,
        leaf_count: leaf_counts.iter().sum(),
        node_count: t.nodes.len() as u32,
        leaf_node_count: leaf_counts.len() as u32,
        bounds_min: lo,
        bounds_max: hi,
        leaf_width_max: leaf_frame.width_max,
        leaf_length_max: leaf_frame.length_max,
        radius_max: skel_frame.radius_max,
        iteration_table,
        sections: Vec::new(),
    };
    // The directory's length does not depend on the offsets, so encode once to size it.
    dir.sections = bodies
        .iter()
        .map(|(k, _, n)| SectionEntry {
            kind: *k,
            flags: 0,
            offset: 0,
            length: 0,
            item_count: *n,
            crc: 0,
        })
        .collect();
    let dir_len = dir.encode().len();
    let mut offset = (HEADER_LEN + dir_len) as u64;
    for (entry, (kind, body, _)) in dir.sections.iter_mut().zip(&bodies) {
        entry.offset = offset;
        entry.length = body.len() as u64;
        if *kind == SectionKind::Leaves {
            entry.flags = FLAG_BLOCK_CRC;
        } else {
            entry.crc = crc32(body);
        }
        offset += body.len() as u64;
    }
    let dir_bytes = dir.encode();
    let header = Header::current(offset, dir_bytes.len() as u32, crc32(&dir_bytes));
    let mut out = Vec::with_capacity(offset as usize);
    out.extend_from_slice(&header.encode());
    out.extend_from_slice(&dir_bytes);
    for (_, body, _) in &bodies {
        out.extend_from_slice(body);
    }
    Ok(out)
}

/// A fully decoded `.ctree` file.
#[derive(Debug, Clone)]
pub struct DecodedTree {
    /// Header.
    pub header: Header,
    /// Directory.
    pub directory: Directory,
    /// Node hierarchy.
    pub nodes: Vec<NodeRecord>,
    /// Skeleton.
    pub branches: Vec<Branch>,
    /// Materials.
    pub materials: Materials,
    /// Bark mesh.
    pub bark_mesh: TriangleMesh,
    /// Leaves of each leaf node (preorder), importance order.
    pub node_leaves: Vec<Vec<Leaf>>,
}

/// The bytes of a section, bounds checked against `bytes`.
pub fn section_bytes<'a>(bytes: &'a [u8], e: &SectionEntry) -> Result<&'a [u8], FormatError> {
    let end = e.offset.saturating_add(e.length);
    if end > bytes.len() as u64 {
        return Err(FormatError::Truncated {
            what: e.kind.name(),
            need: end,
            have: bytes.len() as u64,
        });
    }
    Ok(&bytes[e.offset as usize..end as usize])
}

/// Decodes the header and directory from a file prefix of any length ≥ their size, given the
/// real file length when known.
pub fn decode_index(prefix: &[u8], real_len: Option<u64>) -> Result<(Header, Directory), FormatError> {
    let header = Header::decode(prefix)?;
    if let Some(len) = real_len
        && len != header.file_len
    {
        return Err(FormatError::invalid(
            "file length",
            format!("header says {}, file has {len}", header.file_len),
        ));
    }
    let start = header.directory_offset as usize;
    let end = start + header.directory_len as usize;
    if prefix.len() < end {
        return Err(FormatError::Truncated {
            what: "directory",
            need: end as u64,
            have: prefix.len() as u64,
        });
    }
    let dir = Directory::decode(&prefix[start..end], header.directory_crc, header.file_len)?;
    Ok((header, dir))
}

/// A tree's node table and where its leaf blocks lie: what every reader builds after the
/// directory, before it can ask for a single leaf.
#[derive(Debug, Clone, PartialEq)]
pub struct NodeIndex {
    /// The node table.
    pub nodes: Vec<NodeRecord>,
    /// Node index of each leaf node, by leaf ordinal (preorder among leaf nodes).
    pub leaf_nodes: Vec<usize>,
    /// Leaf blocks, band-major, offsets relative to the leaves section.
    pub layout: BandLayout,
    /// The leaves section's absolute offset (0 when there is none).
    pub leaves_offset: u64,
    /// The leaves section's length in bytes (0 when there is none).
    pub leaves_len: u64,
}

/// Checks and decodes the node table `table` (the node-table section's bytes) of a tree whose
/// directory is `directory`, and lays out its leaf blocks.
pub fn decode_node_index(directory: &Directory, table: &[u8]) -> Result<NodeIndex, FormatError> {
    let e = directory
        .section(SectionKind::NodeTable)
        .ok_or_else(|| FormatError::invalid("section table", "no node table"))?;
    super::check_crc("node table", table, e.crc)?;
    let nodes = decode_nodes(table, directory.node_count, directory.branch_count)?;
    let leaf_nodes: Vec<usize> = nodes
        .iter()
        .enumerate()
        .filter(|(_, n)| n.kind == NodeKind::Leaf)
        .map(|(i, _)| i)
        .collect();
    let counts: Vec<u32> = leaf_nodes.iter().map(|&i| nodes[i].leaf_count).collect();
    let layout = BandLayout::new(&directory.band_edges, &counts);
    let (leaves_offset, leaves_len) = directory
        .section(SectionKind::Leaves)
        .map_or((0, 0), |e| (e.offset, e.length));
    Ok(NodeIndex {
        nodes,
        leaf_nodes,
        layout,
        leaves_offset,
        leaves_len,
    })
}

impl DecodedTree {
    /// Decodes a whole file, checking every section and every leaf block.
    pub fn decode(bytes: &[u8]) -> Result<Self, FormatError> {
        let (header, directory) = decode_index(bytes, Some(bytes.len() as u64))?;
        let sec = |k: SectionKind| -> Result<(&SectionEntry, &[u8]), FormatError> {
            let e = directory
                .section(k)
                .ok_or_else(|| FormatError::invalid("section table", "missing section"))?;
            Ok((e, section_bytes(bytes, e)?))
        };
        let checked = |k: SectionKind| -> Result<&[u8], FormatError> {
            let (e, b) = sec(k)?;
            super::check_crc(k.name(), b, e.crc)?;
            Ok(b)
        };
        let nodes = decode_nodes(
            checked(SectionKind::NodeTable)?,
            directory.node_count,
            directory.branch_count,
        )?;
        let materials = decode_materials(checked(SectionKind::Materials)?)?;
        let (lo, hi) = (directory.bounds_min, directory.bounds_max);
        let (_, skel) = sec(SectionKind::Skeleton)?;
        let branches = decode_skeleton(
            skel,
            &directory.iteration_table,
            &SkeletonFrame {
                lo,
                hi,
                radius_max: directory.radius_max,
            },
        )?;
        // A radii table that understates a branch would make readers leave it out: it must be
        // the skeleton's own.
        if directory.section(SectionKind::SkeletonRadii).is_some() {
            let stored = checked(SectionKind::SkeletonRadii)?;
            let own = thickest_per_iteration(skel, &directory.iteration_table)?;
            if stored != encode_skeleton_radii(&own).as_slice() {
                return Err(FormatError::invalid(
                    "skeleton radii",
                    "the table disagrees with the skeleton's radii",
                ));
            }
        }
        let bark_mesh = decode_mesh(checked(SectionKind::BarkMesh)?, lo, hi)?;

        let leaf_nodes: Vec<&NodeRecord> = nodes.iter().filter(|n| n.kind == NodeKind::Leaf).collect();
        if leaf_nodes.len() as u32 != directory.leaf_node_count {
            return Err(FormatError::invalid(
                "node table",
                "leaf node count disagrees with the directory",
            ));
        }
        let counts: Vec<u32> = leaf_nodes.iter().map(|n| n.leaf_count).collect();
        if counts.iter().map(|&c| u64::from(c)).sum::<u64>() != u64::from(directory.leaf_count) {
            return Err(FormatError::invalid(
                "node table",
                "leaf counts disagree with the directory",
            ));
        }
        let layout = BandLayout::new(&directory.band_edges, &counts);
        let (_, leaf_bytes) = sec(SectionKind::Leaves)?;
        if leaf_bytes.len() as u64 != layout.total_len() {
            return Err(FormatError::Truncated {
                what: "leaves",
                need: layout.total_len(),
                have: leaf_bytes.len() as u64,
            });
        }
        let frame = LeafFrame {
            lo,
            hi,
            width_max: directory.leaf_width_max,
            length_max: directory.leaf_length_max,
        };
        let mut node_leaves: Vec<Vec<Leaf>> = counts.iter().map(|&c| Vec::with_capacity(c as usize)).collect();
        for b in 0..layout.band_count() {
            for (i, out) in node_leaves.iter_mut().enumerate() {
                if let Some(blk) = layout.block(b, i) {
                    let bytes = &leaf_bytes[blk.offset as usize..(blk.offset + blk.len) as usize];
                    let branch = Some(leaf_nodes[i].branch).filter(|&b| b != NO_BRANCH);
                    for q in decode_block(bytes, blk.count, materials.leaf.len())? {
                        out.push(q.to_leaf(&frame, branch));
                    }
                }
            }
        }
        Ok(Self {
            header,
            directory,
            nodes,
            branches,
            materials,
            bark_mesh,
            node_leaves,
        })
    }

    /// The tree at a uniform simplification rate: each leaf node keeps its first
    /// `round(n·(1 − rate))` leaves. Leaves are returned in iteration order, as the model wants.
    pub fn to_model(&self, rate: f32) -> TreeModel {
        let mut leaves: Vec<Leaf> = self
            .node_leaves
            .iter()
            .flat_map(|v| v[..keep_count(v.len() as u32, rate) as usize].iter().copied())
            .collect();
        leaves.sort_by_key(|l| l.iteration);
        TreeModel {
            name: self.directory.name.clone(),
            branches: self.branches.clone(),
            leaves,
            bark_mesh: self.bark_mesh.clone(),
            materials: self.materials.clone(),
            iterations: self.directory.iterations,
            source: self.directory.source,
        }
    }
}

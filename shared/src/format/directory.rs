//! The directory (spec: `docs/format.md#directory`): everything a client needs to plan its
//! range requests.

use glam::Vec3;

use super::bytes::{Cursor, Writer};
use super::{FormatError, LeafOrder, MAX_BANDS, MAX_SECTIONS, check_crc};
use crate::model::ModelSource;

/// Section kinds of the section table.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum SectionKind {
    /// Node hierarchy, 56-byte records.
    NodeTable,
    /// Branch skeleton in iteration order.
    Skeleton,
    /// Band-major leaf blocks.
    Leaves,
    /// Bark and leaf materials.
    Materials,
    /// Imported bark triangles.
    BarkMesh,
    /// Crown contour hulls.
    Hulls,
    /// Multi-view billboard atlases.
    BillboardAtlases,
    /// Stochastic billboard clouds.
    BillboardClouds,
    /// Thickest branch radius of each skeleton iteration (optional, minor 4).
    SkeletonRadii,
}

impl SectionKind {
    /// Every kind, in file order.
    pub const ALL: [SectionKind; 9] = [
        Self::NodeTable,
        Self::Materials,
        Self::SkeletonRadii,
        Self::Skeleton,
        Self::BarkMesh,
        Self::Leaves,
        Self::Hulls,
        Self::BillboardAtlases,
        Self::BillboardClouds,
    ];

    /// Code in the section table.
    pub fn code(self) -> u16 {
        match self {
            Self::NodeTable => 1,
            Self::Skeleton => 2,
            Self::Leaves => 3,
            Self::Materials => 4,
            Self::BarkMesh => 5,
            Self::Hulls => 6,
            Self::BillboardAtlases => 7,
            Self::BillboardClouds => 8,
            Self::SkeletonRadii => 9,
        }
    }

    /// Inverse of [`SectionKind::code`]; `None` for kinds this reader does not know.
    pub fn from_code(code: u16) -> Option<Self> {
        Self::ALL.into_iter().find(|k| k.code() == code)
    }

    /// Lower-case name used by `inspect`.
    pub fn name(self) -> &'static str {
        match self {
            Self::NodeTable => "node_table",
            Self::Skeleton => "skeleton",
            Self::Leaves => "leaves",
            Self::Materials => "materials",
            Self::BarkMesh => "bark_mesh",
            Self::Hulls => "hulls",
            Self::BillboardAtlases => "billboard_atlases",
            Self::BillboardClouds => "billboard_clouds",
            Self::SkeletonRadii => "skeleton_radii",
        }
    }

    /// Whether a file may lack the section (kinds added by a later minor version).
    pub fn optional(self) -> bool {
        self == Self::SkeletonRadii
    }
}

/// One section table entry.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SectionEntry {
    /// Kind.
    pub kind: SectionKind,
    /// Flags (`FLAG_BLOCK_CRC`).
    pub flags: u16,
    /// Absolute offset.
    pub offset: u64,
    /// Length in bytes.
    pub length: u64,
    /// Records in the section.
    pub item_count: u32,
    /// CRC-32 of the section, or 0 with `FLAG_BLOCK_CRC`.
    pub crc: u32,
}

impl SectionEntry {
    /// Byte range `offset..offset + length`.
    pub fn range(&self) -> std::ops::Range<u64> {
        self.offset..self.offset + self.length
    }
}

/// One iteration table entry (iteration-level LOD).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct IterationEntry {
    /// Branches with iteration ≤ k.
    pub branches_end: u32,
    /// End of those branches' bytes, relative to the skeleton section.
    pub skeleton_bytes_end: u32,
    /// Leaves with iteration ≤ k.
    pub leaves_end: u32,
    /// CRC-32 of iteration k's own skeleton bytes.
    pub skeleton_crc: u32,
}

/// The iteration that created skeleton branch `branch`: the first entry `k` of `table` with
/// `branch < branches_end` (the skeleton is in iteration order). `None` past the last entry.
pub fn branch_iteration(table: &[IterationEntry], branch: u32) -> Option<u8> {
    let k = table.partition_point(|e| e.branches_end <= branch);
    (k < table.len()).then(|| u8::try_from(k).unwrap_or(u8::MAX))
}

/// Per leaf node of `nodes` (in node order), the iteration its branch was born in (0 for a
/// node without a branch or past the table): an `iterN` level keeps the nodes born by then.
pub fn leaf_node_iterations(nodes: &[super::NodeRecord], table: &[IterationEntry]) -> Vec<u8> {
    nodes
        .iter()
        .filter(|n| n.kind == super::NodeKind::Leaf)
        .map(|n| {
            if n.branch == super::NO_BRANCH {
                0
            } else {
                branch_iteration(table, n.branch).unwrap_or(0)
            }
        })
        .collect()
}

/// The decoded directory.
#[derive(Debug, Clone, PartialEq)]
pub struct Directory {
    /// Model name.
    pub name: String,
    /// Provenance.
    pub source: ModelSource,
    /// Order of leaves inside each leaf node.
    pub leaf_order: LeafOrder,
    /// L-system iterations.
    pub iterations: u8,
    /// Band edges: keep fractions × 65535, strictly increasing, last 65535.
    pub band_edges: Vec<u16>,
    /// Branches in the skeleton.
    pub branch_count: u32,
    /// Leaves in the file.
    pub leaf_count: u32,
    /// Nodes in the node table.
    pub node_count: u32,
    /// Leaf nodes among them.
    pub leaf_node_count: u32,
    /// Bounds minimum (metres).
    pub bounds_min: Vec3,
    /// Bounds maximum (metres).
    pub bounds_max: Vec3,
    /// Leaf width quantization scale.
    pub leaf_width_max: f32,
    /// Leaf length quantization scale.
    pub leaf_length_max: f32,
    /// Skeleton radius quantization scale.
    pub radius_max: f32,
    /// Iteration table, entries 0..=iterations.
    pub iteration_table: Vec<IterationEntry>,
    /// Section table, one entry per known kind, in file order.
    pub sections: Vec<SectionEntry>,
}

fn source_code(s: ModelSource) -> u8 {
    match s {
        ModelSource::LSystem => 0,
        ModelSource::Gltf => 1,
    }
}

impl Directory {
    /// The entry of a section kind. Every kind is present in a decoded directory.
    pub fn section(&self, kind: SectionKind) -> Option<&SectionEntry> {
        self.sections.iter().find(|s| s.kind == kind)
    }

    /// Encodes the directory.
    pub fn encode(&self) -> Vec<u8> {
        let mut w = Writer::default();
        w.string(&self.name);
        w.u8(source_code(self.source));
        w.u8(self.leaf_order.code());
        w.u8(self.iterations);
        w.u8(self.band_edges.len() as u8);
        for &e in &self.band_edges {
            w.u16(e);
        }
        w.u32(self.branch_count);
        w.u32(self.leaf_count);
        w.u32(self.node_count);
        w.u32(self.leaf_node_count);
        for v in self.bounds_min.to_array().into_iter().chain(self.bounds_max.to_array()) {
            w.f32(v);
        }
        w.f32(self.leaf_width_max);
        w.f32(self.leaf_length_max);
        w.f32(self.radius_max);
        w.u16(self.iteration_table.len() as u16);
        for e in &self.iteration_table {
            w.u32(e.branches_end);
            w.u32(e.skeleton_bytes_end);
            w.u32(e.leaves_end);
            w.u32(e.skeleton_crc);
        }
        w.u16(self.sections.len() as u16);
        for s in &self.sections {
            w.u16(s.kind.code());
            w.u16(s.flags);
            w.u32(0);
            w.u64(s.offset);
            w.u64(s.length);
            w.u32(s.item_count);
            w.u32(s.crc);
        }
        w.buf
    }

    /// Decodes and validates a directory, given its stored CRC and the file length.
    pub fn decode(bytes: &[u8], stored_crc: u32, file_len: u64) -> Result<Self, FormatError> {
        check_crc("directory", bytes, stored_crc)?;
        let mut c = Cursor::new(bytes, "directory");
        let name = c.string("model name")?;
        let source = match c.u8()? {
            0 => ModelSource::LSystem,
            1 => ModelSource::Gltf,
            v => return Err(FormatError::invalid("model source", v.to_string())),
        };
        let order = c.u8()?;
        let leaf_order =
            LeafOrder::from_code(order).ok_or_else(|| FormatError::invalid("leaf order", order.to_string()))?;
        let iterations = c.u8()?;
        let nbands = c.u8()? as usize;
        if nbands == 0 || nbands > MAX_BANDS {
            return Err(FormatError::invalid(
                "band count",
                format!("{nbands} not in 1..={MAX_BANDS}"),
            ));
        }
        let mut band_edges = Vec::with_capacity(nbands);
        for _ in 0..nbands {
            band_edges.push(c.u16()?);
        }
        if band_edges.windows(2).any(|w| w[0] >= w[1]) || band_edges[0] == 0 || band_edges.last() != Some(&u16::MAX) {
            return Err(FormatError::invalid(
                "band edges",
                format!("{band_edges:?} not strictly increasing to 65535"),
            ));
        }
        let branch_count = c.u32()?;
        let leaf_count = c.u32()?;
        let node_count = c.u32()?;
        let leaf_node_count = c.u32()?;
        if node_count == 0 || leaf_node_count > node_count {
            return Err(FormatError::invalid(
                "node count",
                format!("{node_count} nodes, {leaf_node_count} leaf nodes"),
            ));
        }
        let mut b = [0f32; 6];
        for v in &mut b {
            *v = c.finite_f32("bounds")?;
        }
        let bounds_min = Vec3::new(b[0], b[1], b[2]);
        let bounds_max = Vec3::new(b[3], b[4], b[5]);
        if bounds_min.cmpgt(bounds_max).any() {
            return Err(FormatError::invalid(
                "bounds",
                format!("min {bounds_min} > max {bounds_max}"),
            ));
        }
        let positive = |c: &mut Cursor, what: &'static str| -> Result<f32, FormatError> {
            let v = c.finite_f32(what)?;
            if v > 0.0 {
                Ok(v)
            } else {
                Err(FormatError::invalid(what, format!("{v} is not positive")))
            }
        };
        let leaf_width_max = positive(&mut c, "leaf width max")?;
        let leaf_length_max = positive(&mut c, "leaf length max")?;
        let radius_max = positive(&mut c, "radius max")?;
        let n_iter = c.u16()? as usize;
        if n_iter != iterations as usize + 1 {
            return Err(FormatError::invalid(
                "iteration table",
                format!("{n_iter} entries for {iterations} iterations"),
            ));
        }
        let mut iteration_table = Vec::with_capacity(n_iter);
        for _ in 0..n_iter {
            iteration_table.push(IterationEntry {
                branches_end: c.u32()?,
                skeleton_bytes_end: c.u32()?,
                leaves_end: c.u32()?,
                skeleton_crc: c.u32()?,
            });
        }
        let monotone = iteration_table.windows(2).all(|w| {
            w[0].branches_end <= w[1].branches_end
                && w[0].skeleton_bytes_end <= w[1].skeleton_bytes_end
                && w[0].leaves_end <= w[1].leaves_end
        });
        let last = iteration_table.last().copied().unwrap_or_default();
        if !monotone || last.branches_end != branch_count || last.leaves_end != leaf_count {
            return Err(FormatError::invalid(
                "iteration table",
                "not monotone or does not end at the totals",
            ));
        }
        let nsec = c.u16()? as usize;
        if nsec > MAX_SECTIONS {
            return Err(FormatError::invalid(
                "section count",
                format!("{nsec} exceeds {MAX_SECTIONS}"),
            ));
        }
        let mut sections = Vec::with_capacity(nsec);
        for _ in 0..nsec {
            let code = c.u16()?;
            let flags = c.u16()?;
            c.u32()?;
            let offset = c.u64()?;
            let length = c.u64()?;
            let item_count = c.u32()?;
            let crc = c.u32()?;
            let end = offset
                .checked_add(length)
                .ok_or_else(|| FormatError::invalid("section", "offset + length overflows"))?;
            if end > file_len {
                return Err(FormatError::invalid(
                    "section",
                    format!("section {code} ends at {end}, past file length {file_len}"),
                ));
            }
            // Unknown kinds (written by a newer minor version) are skipped.
            if let Some(kind) = SectionKind::from_code(code) {
                if sections.iter().any(|s: &SectionEntry| s.kind == kind) {
                    return Err(FormatError::invalid(
                        "section table",
                        format!("{} appears twice", kind.name()),
                    ));
                }
                sections.push(SectionEntry {
                    kind,
                    flags,
                    offset,
                    length,
                    item_count,
                    crc,
                });
            }
        }
        c.finish()?;
        for kind in SectionKind::ALL {
            if !kind.optional() && !sections.iter().any(|s| s.kind == kind) {
                return Err(FormatError::invalid(
                    "section table",
                    format!("{} is missing", kind.name()),
                ));
            }
        }
        let mut spans: Vec<_> = sections
            .iter()
            .filter(|s| s.length > 0)
            .map(SectionEntry::range)
            .collect();
        spans.sort_by_key(|r| r.start);
        if spans.windows(2).any(|w| w[0].end > w[1].start) {
            return Err(FormatError::invalid("section table", "sections overlap"));
        }
        let dir = Self {
            name,
            source,
            leaf_order,
            iterations,
            band_edges,
            branch_count,
            leaf_count,
            node_count,
            leaf_node_count,
            bounds_min,
            bounds_max,
            leaf_width_max,
            leaf_length_max,
            radius_max,
            iteration_table,
            sections,
        };
        dir.check_section_counts()?;
        Ok(dir)
    }

    fn check_section_counts(&self) -> Result<(), FormatError> {
        let sec = |k| {
            self.section(k)
                .copied()
                .ok_or_else(|| FormatError::invalid("section table", "missing section"))
        };
        let nodes = sec(SectionKind::NodeTable)?;
        if nodes.item_count != self.node_count
            || nodes.length != u64::from(self.node_count) * super::NODE_RECORD_LEN as u64
        {
            return Err(FormatError::invalid(
                "node table",
                "length or count disagrees with the node count",
            ));
        }
        let skel = sec(SectionKind::Skeleton)?;
        let last = self.iteration_table.last().map_or(0, |e| e.skeleton_bytes_end);
        if skel.item_count != self.branch_count || skel.length != u64::from(last) {
            return Err(FormatError::invalid(
                "skeleton",
                "length or count disagrees with the directory",
            ));
        }
        let leaves = sec(SectionKind::Leaves)?;
        if leaves.item_count != self.leaf_count || leaves.flags & super::FLAG_BLOCK_CRC == 0 {
            return Err(FormatError::invalid(
                "leaves",
                "count disagrees or block CRC flag missing",
            ));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn branch_iteration_finds_the_creating_iteration() {
        let e = |branches_end| IterationEntry {
            branches_end,
            ..Default::default()
        };
        // Iteration 0: branch 0; iteration 1: none; iteration 2: branches 1..4.
        let table = [e(1), e(1), e(4)];
        assert_eq!(branch_iteration(&table, 0), Some(0));
        assert_eq!(branch_iteration(&table, 1), Some(2));
        assert_eq!(branch_iteration(&table, 3), Some(2));
        assert_eq!(branch_iteration(&table, 4), None);
        assert_eq!(branch_iteration(&[], 0), None);
    }
}

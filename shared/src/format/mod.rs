//! The progressive tree format (`.ctree`), version 1.3. The spec is `docs/format.md`; each
//! section has its own module here, named as in the spec.
//!
//! Decoding never panics: every offset, length, count and checksum is checked and a bad file gives
//! a [`FormatError`].

pub mod atlas;
mod bytes;
pub mod cloud;
pub mod directory;
pub mod header;
pub mod hull;
pub mod leaf;
pub mod materials;
pub mod mesh;
pub mod node;
pub mod quant;
pub mod skeleton;
pub mod skeleton_radii;
pub mod tree;
pub mod unit;

pub use directory::{Directory, IterationEntry, SectionEntry, SectionKind, branch_iteration, leaf_node_iterations};
pub use header::Header;
pub use leaf::{BandLayout, LeafBlockRef, QuantizedLeaf};
pub use node::{NodeKind, NodeRecord};
pub use tree::{BakedTree, DecodedTree, SectionBody, encode_tree};
pub use unit::{UnitCheck, UnitContext};

/// File magic: "CNPYTRE" followed by 0x1A (stops `type` on DOS-like consoles).
pub const MAGIC: [u8; 8] = *b"CNPYTRE\x1a";
/// Major version; readers reject any other.
pub const VERSION_MAJOR: u16 = 1;
/// Minor version (1: hull and atlas sections have layouts; 2: billboard clouds have a layout;
/// 3: atlases may have an irregular views layout; 4: the optional skeleton-radii section);
/// readers accept higher minors.
pub const VERSION_MINOR: u16 = 4;
/// Fixed header length in bytes.
pub const HEADER_LEN: usize = 64;
/// Bytes a client asks for first: header, directory and (for small trees) the node table.
pub const FIRST_REQUEST_LEN: u64 = 64 * 1024;
/// Largest directory a reader accepts.
pub const MAX_DIRECTORY_LEN: u32 = 1 << 20;
/// Largest number of sections in the section table.
pub const MAX_SECTIONS: usize = 32;
/// Largest number of rate bands.
pub const MAX_BANDS: usize = 16;
/// `parent` value of the root node and of the trunk branch.
pub const NO_PARENT: u32 = u32::MAX;
/// `skeleton branch` value of a node with no skeleton branch.
pub const NO_BRANCH: u32 = u32::MAX;
/// Bytes per node record.
pub const NODE_RECORD_LEN: usize = 56;
/// Bytes per quantized leaf record.
pub const LEAF_RECORD_LEN: usize = 16;
/// Bytes of the CRC-32 trailer of every leaf block.
pub const LEAF_BLOCK_CRC_LEN: usize = 4;
/// Section flag: the section carries per-block CRCs; the table's CRC field is 0.
pub const FLAG_BLOCK_CRC: u16 = 1;

/// Order of the leaves inside each leaf node.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum LeafOrder {
    /// As grown by the L-system or as imported.
    Generation,
    /// Viewpoint mutual information, seed 004.
    Vmi,
    /// Seeded random shuffle (stochastic pruning).
    Random,
    /// Decreasing leaf area.
    Area,
}

impl LeafOrder {
    /// Byte code used in the directory.
    pub fn code(self) -> u8 {
        match self {
            Self::Generation => 0,
            Self::Vmi => 1,
            Self::Random => 2,
            Self::Area => 3,
        }
    }

    /// Inverse of [`LeafOrder::code`].
    pub fn from_code(code: u8) -> Option<Self> {
        Some(match code {
            0 => Self::Generation,
            1 => Self::Vmi,
            2 => Self::Random,
            3 => Self::Area,
            _ => return None,
        })
    }

    /// Lower-case name (`generation`, `vmi`, `random`, `area`).
    pub fn name(self) -> &'static str {
        match self {
            Self::Generation => "generation",
            Self::Vmi => "vmi",
            Self::Random => "random",
            Self::Area => "area",
        }
    }
}

/// Why a `.ctree` file (or part of one) was rejected.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FormatError {
    /// The first bytes are not [`MAGIC`].
    #[error("not a Canopy tree file (bad magic)")]
    BadMagic,
    /// A major version this reader does not know.
    #[error("unsupported format version {major}.{minor} (this reader reads {VERSION_MAJOR}.x)")]
    UnsupportedVersion {
        /// Major version found.
        major: u16,
        /// Minor version found.
        minor: u16,
    },
    /// Fewer bytes than a structure needs.
    #[error("truncated {what}: need {need} bytes, have {have}")]
    Truncated {
        /// Which structure.
        what: &'static str,
        /// Bytes needed.
        need: u64,
        /// Bytes available.
        have: u64,
    },
    /// A CRC-32 did not match.
    #[error("checksum mismatch in {what}: stored {stored:#010x}, computed {computed:#010x}")]
    ChecksumMismatch {
        /// Which structure.
        what: &'static str,
        /// CRC stored in the file.
        stored: u32,
        /// CRC of the bytes read.
        computed: u32,
    },
    /// A field holds a value the spec forbids.
    #[error("invalid {what}: {detail}")]
    Invalid {
        /// Which field.
        what: &'static str,
        /// What is wrong with it.
        detail: String,
    },
    /// Bytes left over after a structure that should fill its span exactly.
    #[error("{what} has {extra} trailing bytes")]
    TrailingBytes {
        /// Which structure.
        what: &'static str,
        /// How many bytes were not consumed.
        extra: u64,
    },
    /// The billboard-cloud table length (section kind 8) disagrees with its level and plane
    /// counts or does not fit the section.
    #[error("bad cloud table length {table_len} ({detail})")]
    CloudTableLength {
        /// Table length read from the cloud header.
        table_len: u64,
        /// What it disagrees with.
        detail: String,
    },
    /// A billboard-cloud count out of range or inconsistent (levels, planes, planes per level,
    /// a level's texture range against its planes, a level or plane index asked for).
    #[error("bad cloud counts: {0}")]
    CloudCounts(String),
    /// A billboard-cloud plane's texture range that ends past the section.
    #[error("texture of plane {plane} at {offset}+{length} lies outside the {section_len}-byte section")]
    TextureOutOfRange {
        /// Plane index (section-wide).
        plane: u32,
        /// Offset from the section start.
        offset: u64,
        /// Length.
        length: u64,
        /// Section length.
        section_len: u64,
    },
    /// A billboard-cloud plane's texture range that starts before the previous one ends (or
    /// inside the table).
    #[error("texture of plane {plane} at {offset} overlaps the bytes before it (ending at {expected})")]
    TextureOverlap {
        /// Plane index (section-wide).
        plane: u32,
        /// Its offset from the section start.
        offset: u64,
        /// Where the previous range (or the table) ended.
        expected: u64,
    },
    /// A billboard-cloud plane's texture range that leaves unused bytes before it.
    #[error("texture of plane {plane} at {offset} leaves a gap after {expected}")]
    TextureGap {
        /// Plane index (section-wide).
        plane: u32,
        /// Its offset from the section start.
        offset: u64,
        /// Where the previous range (or the table) ended.
        expected: u64,
    },
    /// A billboard-cloud texture that is not a PNG of the size its plane record gives.
    #[error("cloud texture: {0}")]
    CloudImage(String),
}

impl FormatError {
    pub(crate) fn invalid(what: &'static str, detail: impl Into<String>) -> Self {
        Self::Invalid {
            what,
            detail: detail.into(),
        }
    }
}

/// CRC-32 (IEEE) of `bytes`.
pub fn crc32(bytes: &[u8]) -> u32 {
    crc32fast::hash(bytes)
}

/// Checks `bytes` against the stored CRC-32 `stored`; `what` names the structure in the error.
pub fn check_crc(what: &'static str, bytes: &[u8], stored: u32) -> Result<(), FormatError> {
    let computed = crc32(bytes);
    if computed == stored {
        Ok(())
    } else {
        Err(FormatError::ChecksumMismatch { what, stored, computed })
    }
}

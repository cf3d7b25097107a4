//! Units: the pieces of a tree file a client fetches and keeps one by one (a skeleton iteration,
//! the bark mesh, a leaf block, a hull level, an atlas image, a cloud level), and the check each
//! must pass before it is kept. One place decides how a unit is checked, so that no reader
//! dispatches per-section checks of its own.

use super::cloud::CloudTable;
use super::leaf::decode_block;
use super::{FormatError, check_crc};

/// How a unit's bytes are checked.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum UnitCheck {
    /// CRC-32 of the whole unit (skeleton iterations, bark mesh, hull levels, atlas images).
    Crc(u32),
    /// A leaf block of `count` leaves: its own CRC and every record's fields
    /// ([`decode_block`]).
    LeafBlock {
        /// Leaves in the block.
        count: u32,
    },
    /// Every plane texture of a cloud level against its CRC ([`CloudTable::verify_level`]).
    CloudLevel(u8),
}

/// What a unit's check reads of its tree besides the unit's bytes.
#[derive(Debug, Clone, Copy)]
pub struct UnitContext<'a> {
    /// Leaf materials in the tree (a leaf record's material index must be below it).
    pub leaf_materials: usize,
    /// The tree's cloud table, when it has one.
    pub cloud: Option<&'a CloudTable>,
}

impl UnitCheck {
    /// Checks a unit's bytes.
    pub fn verify(self, bytes: &[u8], cx: UnitContext<'_>) -> Result<(), FormatError> {
        match self {
            Self::Crc(crc) => check_crc("unit", bytes, crc),
            Self::LeafBlock { count } => decode_block(bytes, count, cx.leaf_materials).map(|_| ()),
            Self::CloudLevel(level) => match cx.cloud {
                Some(c) => Ok(c.verify_level(usize::from(level), bytes)?),
                None => Err(FormatError::invalid("cloud level", "the tree has no cloud table")),
            },
        }
    }
}

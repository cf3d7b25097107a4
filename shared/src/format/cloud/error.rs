//! Why a billboard-cloud section (or one of its textures) was rejected, and the two checks
//! every part of the codec shares: a field the spec forbids, a CRC-32 that does not match.

use crate::format::{FormatError, crc32};

/// Why a billboard-cloud section (or one of its textures) was rejected.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CloudError {
    /// Fewer bytes than the structure needs.
    #[error("truncated {what}: need {need} bytes, have {have}")]
    Truncated {
        /// Which structure.
        what: &'static str,
        /// Bytes needed.
        need: u64,
        /// Bytes available.
        have: u64,
    },
    /// The table length disagrees with the counts or does not fit the section.
    #[error("bad cloud table length {table_len} ({detail})")]
    TableLength {
        /// Table length read from the header.
        table_len: u64,
        /// What it disagrees with.
        detail: String,
    },
    /// A count out of range or inconsistent (levels, planes, planes per level).
    #[error("bad cloud counts: {0}")]
    Counts(String),
    /// A texture range that ends past the section.
    #[error("texture of plane {plane} at {offset}+{length} lies outside the {section_len}-byte section")]
    OffsetOutOfRange {
        /// Plane index (section-wide).
        plane: u32,
        /// Offset from the section start.
        offset: u64,
        /// Length.
        length: u64,
        /// Section length.
        section_len: u64,
    },
    /// A texture range that starts before the previous one ends (or inside the table).
    #[error("texture of plane {plane} at {offset} overlaps the bytes before it (ending at {expected})")]
    Overlap {
        /// Plane index.
        plane: u32,
        /// Its offset.
        offset: u64,
        /// Where the previous range ended.
        expected: u64,
    },
    /// A texture range that leaves unused bytes before it.
    #[error("texture of plane {plane} at {offset} leaves a gap after {expected}")]
    Gap {
        /// Plane index.
        plane: u32,
        /// Its offset.
        offset: u64,
        /// Where the previous range ended.
        expected: u64,
    },
    /// A CRC-32 mismatch (table or texture).
    #[error("checksum mismatch in {what}: stored {stored:#010x}, computed {computed:#010x}")]
    Checksum {
        /// Which structure.
        what: &'static str,
        /// Stored CRC.
        stored: u32,
        /// CRC of the bytes.
        computed: u32,
    },
    /// A field the spec forbids (non-finite or inconsistent geometry, unknown codec or flags).
    #[error("invalid {what}: {detail}")]
    Invalid {
        /// Which field.
        what: &'static str,
        /// What is wrong.
        detail: String,
    },
    /// Bytes after the last texture.
    #[error("billboard-cloud section has {0} bytes after its last texture")]
    TrailingBytes(u64),
    /// A texture that is not a PNG of the recorded size.
    #[error("cloud texture: {0}")]
    Image(String),
}

impl From<FormatError> for CloudError {
    fn from(e: FormatError) -> Self {
        match e {
            FormatError::Truncated { what, need, have } => Self::Truncated { what, need, have },
            other => Self::Invalid {
                what: "cloud table",
                detail: other.to_string(),
            },
        }
    }
}

/// A [`CloudError::Invalid`] for field `what`.
pub(super) fn invalid(what: &'static str, detail: impl Into<String>) -> CloudError {
    CloudError::Invalid {
        what,
        detail: detail.into(),
    }
}

/// Checks `bytes` against their stored CRC-32.
pub(super) fn check(what: &'static str, bytes: &[u8], stored: u32) -> Result<(), CloudError> {
    let computed = crc32(bytes);
    if computed == stored {
        Ok(())
    } else {
        Err(CloudError::Checksum { what, stored, computed })
    }
}

//! The 64-byte file header (spec: `docs/format.md#header-64-bytes`).

use super::bytes::{Cursor, Writer};
use super::{FormatError, HEADER_LEN, MAGIC, MAX_DIRECTORY_LEN, VERSION_MAJOR, VERSION_MINOR, check_crc, crc32};

/// Decoded file header.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Header {
    /// Major version (always [`VERSION_MAJOR`] after a successful decode).
    pub version_major: u16,
    /// Minor version.
    pub version_minor: u16,
    /// Total file length in bytes.
    pub file_len: u64,
    /// Directory offset (= [`HEADER_LEN`]).
    pub directory_offset: u64,
    /// Directory length in bytes.
    pub directory_len: u32,
    /// CRC-32 of the directory bytes.
    pub directory_crc: u32,
}

impl Header {
    /// Encodes the header as 64 bytes, header CRC included.
    pub fn encode(&self) -> [u8; HEADER_LEN] {
        let mut w = Writer::default();
        w.buf.extend_from_slice(&MAGIC);
        w.u16(self.version_major);
        w.u16(self.version_minor);
        w.u32(HEADER_LEN as u32);
        w.u64(self.file_len);
        w.u64(self.directory_offset);
        w.u32(self.directory_len);
        w.u32(self.directory_crc);
        w.buf.resize(60, 0);
        let crc = crc32(&w.buf);
        w.u32(crc);
        let mut out = [0u8; HEADER_LEN];
        out.copy_from_slice(&w.buf);
        out
    }

    /// Decodes and validates the header from the first bytes of a file.
    ///
    /// Checks magic, version, header CRC, header length and that the directory lies inside the
    /// declared file length. Does not know the real file length: callers compare
    /// [`Header::file_len`] with it.
    pub fn decode(bytes: &[u8]) -> Result<Self, FormatError> {
        if bytes.len() >= MAGIC.len() && bytes[..MAGIC.len()] != MAGIC {
            return Err(FormatError::BadMagic);
        }
        let mut c = Cursor::new(bytes, "header");
        let head = c.take(HEADER_LEN)?;
        let mut c = Cursor::new(head, "header");
        c.take(MAGIC.len())?;
        let version_major = c.u16()?;
        let version_minor = c.u16()?;
        if version_major != VERSION_MAJOR {
            return Err(FormatError::UnsupportedVersion {
                major: version_major,
                minor: version_minor,
            });
        }
        check_crc(
            "header",
            &head[..60],
            u32::from_le_bytes([head[60], head[61], head[62], head[63]]),
        )?;
        let header_len = c.u32()?;
        if header_len as usize != HEADER_LEN {
            return Err(FormatError::invalid("header length", header_len.to_string()));
        }
        let file_len = c.u64()?;
        let directory_offset = c.u64()?;
        let directory_len = c.u32()?;
        let directory_crc = c.u32()?;
        if directory_offset != HEADER_LEN as u64 {
            return Err(FormatError::invalid("directory offset", directory_offset.to_string()));
        }
        if directory_len > MAX_DIRECTORY_LEN {
            return Err(FormatError::invalid(
                "directory length",
                format!("{directory_len} exceeds {MAX_DIRECTORY_LEN}"),
            ));
        }
        if directory_offset + u64::from(directory_len) > file_len {
            return Err(FormatError::invalid(
                "directory length",
                format!(
                    "directory ends at {} past file length {file_len}",
                    directory_offset + u64::from(directory_len)
                ),
            ));
        }
        Ok(Self {
            version_major,
            version_minor,
            file_len,
            directory_offset,
            directory_len,
            directory_crc,
        })
    }

    /// A header for a file written by this version.
    pub fn current(file_len: u64, directory_len: u32, directory_crc: u32) -> Self {
        Self {
            version_major: VERSION_MAJOR,
            version_minor: VERSION_MINOR,
            file_len,
            directory_offset: HEADER_LEN as u64,
            directory_len,
            directory_crc,
        }
    }
}

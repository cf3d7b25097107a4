//! Byte-range readers: `read(offset, len)` over memory and files (the client adds HTTP).
//!
//! A `.ctree` is opened with [`open_tree`]: one read of [`FIRST_REQUEST_LEN`] bytes gives the
//! header and directory, a second the node table (unless the first already held it).

use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::Path;
use std::sync::Arc;

use crate::format::directory::SectionKind;
use crate::format::leaf::BandLayout;
use crate::format::node::{NodeKind, decode_nodes};
use crate::format::tree::decode_index;
use crate::format::{Directory, FIRST_REQUEST_LEN, FormatError, Header, NodeRecord};

/// Why a read failed.
#[derive(Debug, thiserror::Error)]
pub enum ReadError {
    /// The range runs past the end of the source.
    #[error("range {offset}+{len} is past the end ({size} bytes)")]
    OutOfRange {
        /// Requested offset.
        offset: u64,
        /// Requested length.
        len: u64,
        /// Source size.
        size: u64,
    },
    /// An I/O error from the backend.
    #[error("read failed: {0}")]
    Io(#[from] std::io::Error),
    /// The bytes read are not a valid tree file.
    #[error(transparent)]
    Format(#[from] FormatError),
}

/// A source of bytes addressed by range.
pub trait RangeReader {
    /// Total size in bytes.
    fn size(&self) -> Result<u64, ReadError>;
    /// Exactly `len` bytes at `offset`; errors if the range runs past the end.
    fn read(&self, offset: u64, len: u64) -> Result<Vec<u8>, ReadError>;
}

/// An in-memory source.
#[derive(Debug, Clone)]
pub struct MemoryReader(pub Arc<[u8]>);

impl RangeReader for MemoryReader {
    fn size(&self) -> Result<u64, ReadError> {
        Ok(self.0.len() as u64)
    }
    fn read(&self, offset: u64, len: u64) -> Result<Vec<u8>, ReadError> {
        let size = self.0.len() as u64;
        match offset.checked_add(len) {
            Some(end) if end <= size => Ok(self.0[offset as usize..end as usize].to_vec()),
            _ => Err(ReadError::OutOfRange { offset, len, size }),
        }
    }
}

/// A file source using positioned reads (no shared cursor, safe to share between threads).
#[derive(Debug)]
pub struct FileReader {
    file: File,
    size: u64,
}

impl FileReader {
    /// Opens a file.
    pub fn open(path: &Path) -> Result<Self, ReadError> {
        let file = File::open(path)?;
        let size = file.metadata()?.len();
        Ok(Self { file, size })
    }
}

impl RangeReader for FileReader {
    fn size(&self) -> Result<u64, ReadError> {
        Ok(self.size)
    }
    fn read(&self, offset: u64, len: u64) -> Result<Vec<u8>, ReadError> {
        match offset.checked_add(len) {
            Some(end) if end <= self.size => {
                let mut buf = vec![0u8; len as usize];
                self.file.read_exact_at(&mut buf, offset)?;
                Ok(buf)
            }
            _ => Err(ReadError::OutOfRange {
                offset,
                len,
                size: self.size,
            }),
        }
    }
}

/// What a client knows after opening a tree: header, directory, nodes and leaf-block layout.
#[derive(Debug, Clone)]
pub struct TreeIndex {
    /// Header.
    pub header: Header,
    /// Directory.
    pub directory: Directory,
    /// Node table.
    pub nodes: Vec<NodeRecord>,
    /// Leaf-block layout.
    pub layout: BandLayout,
    /// Bytes read to build the index.
    pub bytes_read: u64,
}

/// Opens a tree: reads the first [`FIRST_REQUEST_LEN`] bytes (or the whole source if smaller),
/// then the node table if it was not in that prefix, and validates both.
pub fn open_tree(r: &dyn RangeReader) -> Result<TreeIndex, ReadError> {
    let size = r.size()?;
    let first = r.read(0, size.min(FIRST_REQUEST_LEN))?;
    let (header, directory) = decode_index(&first, Some(size))?;
    let mut bytes_read = first.len() as u64;
    let e = *directory
        .section(SectionKind::NodeTable)
        .ok_or_else(|| FormatError::invalid("section table", "no node table"))?;
    let table = if e.offset + e.length <= first.len() as u64 {
        first[e.offset as usize..(e.offset + e.length) as usize].to_vec()
    } else {
        bytes_read += e.length;
        r.read(e.offset, e.length)?
    };
    crate::format::check_crc("node table", &table, e.crc)?;
    let nodes = decode_nodes(&table, directory.node_count, directory.branch_count)?;
    let counts: Vec<u32> = nodes
        .iter()
        .filter(|n| n.kind == NodeKind::Leaf)
        .map(|n| n.leaf_count)
        .collect();
    let layout = BandLayout::new(&directory.band_edges, &counts);
    Ok(TreeIndex {
        header,
        directory,
        nodes,
        layout,
        bytes_read,
    })
}

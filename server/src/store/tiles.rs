//! Instance packs stored per tile, so that an edit writes what it changed, not the whole scene.
//!
//! A version's pack (`docs/scenes.md`, unchanged: clients read the same bytes at the same URL)
//! is kept on disk as pieces: each tile's records are a content-addressed blob
//! `scenes/<id>/t.<hash16>.ctile`, shared by every version whose tile has those exact bytes, and
//! the version writes a small pack index `scenes/<id>/v<N>.<hash16>.cpix` (the pack's header and
//! tables, then the blob of each tile in order). The server serves `v<N>.<hash16>.cpack` by
//! reading through the index ([`Parts`]): byte for byte the pack a full rebuild writes. A scene's
//! first version is also written whole (a static copy of `DATA/assets` then holds it).
//!
//! Blob lifetime: a blob is kept while a pack index under its folder names it. A publish that
//! reuses a blob and a cleanup that deletes it must not interleave, so both hold the folder's
//! [`AssetStore::blob_lock`] (a publish from before it writes until its version commits).

use std::collections::HashSet;
use std::sync::Arc;

use bytes::Bytes;

use super::Asset;
use super::assets::{AssetError, AssetStore, NAME_HASH_HEX, ReadAt, hex};
use super::pack::{PackError, Tile};
use super::pack_draft::PackDraft;
use super::scenes::{Bounds, Instance};

/// Extension of a pack index.
pub const INDEX_EXT: &str = "cpix";
/// Extension of a tile blob.
pub const TILE_EXT: &str = "ctile";
/// Name part of a tile blob's file name.
pub const TILE_NAME: &str = "t";

const INDEX_MAGIC: [u8; 8] = *b"CNPYPIDX";
const INDEX_VERSION: u32 = 1;
/// Magic, version, tile count, pack length, pack SHA-256, head length.
const INDEX_FIXED: usize = 8 + 4 + 4 + 8 + 32 + 8;
/// Per tile: the blob's hash16 (ASCII hex) and its length.
const INDEX_PER_TILE: usize = NAME_HASH_HEX + 8;

/// Why a per-tile pack could not be written or read.
#[derive(Debug, thiserror::Error)]
pub enum TileError {
    /// A pack index is malformed.
    #[error("pack index {0}: {1}")]
    Index(String, &'static str),
    /// A pack index names a tile blob the store does not hold (or holds with another length).
    #[error("pack index {index} names tile blob {tile}, which is missing or damaged")]
    MissingTile {
        /// The index.
        index: String,
        /// The blob.
        tile: String,
    },
    /// Building the pack failed.
    #[error(transparent)]
    Pack(#[from] PackError),
    /// The asset store failed.
    #[error(transparent)]
    Asset(#[from] AssetError),
}

/// A pack index, decoded.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PackIndex {
    /// Length of the whole pack.
    pub pack_len: u64,
    /// SHA-256 of the whole pack.
    pub sha256: [u8; 32],
    /// The pack's bytes before its first tile (header, model table, tile table).
    pub head: Vec<u8>,
    /// Each tile's blob: hash16 and length, in pack order.
    pub tiles: Vec<(String, u64)>,
}

fn u64_at(b: &[u8], o: usize) -> u64 {
    let mut a = [0u8; 8];
    a.copy_from_slice(&b[o..o + 8]);
    u64::from_le_bytes(a)
}

impl PackIndex {
    /// The index file's bytes.
    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(INDEX_FIXED + self.head.len() + self.tiles.len() * INDEX_PER_TILE);
        out.extend_from_slice(&INDEX_MAGIC);
        out.extend_from_slice(&INDEX_VERSION.to_le_bytes());
        out.extend_from_slice(&(self.tiles.len() as u32).to_le_bytes());
        out.extend_from_slice(&self.pack_len.to_le_bytes());
        out.extend_from_slice(&self.sha256);
        out.extend_from_slice(&(self.head.len() as u64).to_le_bytes());
        out.extend_from_slice(&self.head);
        for (h, len) in &self.tiles {
            out.extend_from_slice(h.as_bytes());
            out.extend_from_slice(&len.to_le_bytes());
        }
        out
    }

    /// Decodes an index (`name` for errors); never panics.
    pub fn decode(name: &str, b: &[u8]) -> Result<Self, TileError> {
        let bad = |why| TileError::Index(name.to_string(), why);
        if b.len() < INDEX_FIXED || b[..8] != INDEX_MAGIC {
            return Err(bad("not a pack index"));
        }
        if u32::from_le_bytes([b[8], b[9], b[10], b[11]]) != INDEX_VERSION {
            return Err(bad("unknown version"));
        }
        let count = u32::from_le_bytes([b[12], b[13], b[14], b[15]]) as usize;
        let pack_len = u64_at(b, 16);
        let mut sha256 = [0u8; 32];
        sha256.copy_from_slice(&b[24..56]);
        let head_len = usize::try_from(u64_at(b, 56)).map_err(|_| bad("head length"))?;
        let expected = count
            .checked_mul(INDEX_PER_TILE)
            .and_then(|t| t.checked_add(head_len))
            .and_then(|t| t.checked_add(INDEX_FIXED));
        if expected != Some(b.len()) {
            return Err(bad("length disagrees with its counts"));
        }
        let head = b[INDEX_FIXED..INDEX_FIXED + head_len].to_vec();
        let mut tiles = Vec::with_capacity(count);
        let mut total = head_len as u64;
        for rec in b[INDEX_FIXED + head_len..].chunks_exact(INDEX_PER_TILE) {
            let h = std::str::from_utf8(&rec[..NAME_HASH_HEX]).map_err(|_| bad("tile hash"))?;
            if !h.bytes().all(|c| c.is_ascii_digit() || (b'a'..=b'f').contains(&c)) {
                return Err(bad("tile hash"));
            }
            let len = u64_at(rec, NAME_HASH_HEX);
            total = total.checked_add(len).ok_or_else(|| bad("tile lengths"))?;
            tiles.push((h.to_string(), len));
        }
        if total != pack_len {
            return Err(bad("tile lengths do not add up to the pack length"));
        }
        Ok(Self {
            pack_len,
            sha256,
            head,
            tiles,
        })
    }
}

/// A tile blob's path under the assets folder.
pub fn tile_rel(dir: &str, hash16: &str) -> String {
    format!("{dir}/{TILE_NAME}.{hash16}.{TILE_EXT}")
}

/// A pack read through its index: the head from memory, each tile from its blob.
#[derive(Debug)]
pub struct Parts {
    head: Bytes,
    tiles: Vec<Arc<Asset>>,
    /// Offset of each tile in the pack.
    starts: Vec<u64>,
    len: u64,
}

impl Parts {
    /// The tile blobs, in pack order.
    pub fn tiles(&self) -> &[Arc<Asset>] {
        &self.tiles
    }

    /// The pack's length.
    pub fn len(&self) -> u64 {
        self.len
    }

    /// True for a pack of no bytes (never: a pack has a header).
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }
}

impl ReadAt for Parts {
    fn read_exact_at(&self, mut buf: &mut [u8], mut offset: u64) -> std::io::Result<()> {
        let past = || std::io::Error::new(std::io::ErrorKind::UnexpectedEof, "read past the end of a pack");
        if offset.checked_add(buf.len() as u64).is_none_or(|e| e > self.len) {
            return Err(past());
        }
        let head = self.head.len() as u64;
        if offset < head {
            let n = buf.len().min((head - offset) as usize);
            buf[..n].copy_from_slice(&self.head[offset as usize..offset as usize + n]);
            buf = &mut buf[n..];
            offset += n as u64;
        }
        // The tile holding `offset`, then the following ones.
        let mut k = self.starts.partition_point(|&s| s <= offset).saturating_sub(1);
        while !buf.is_empty() {
            let (t, start) = (self.tiles.get(k).ok_or_else(past)?, self.starts[k]);
            let within = offset - start;
            let n = buf.len().min((t.len - within) as usize);
            match &t.data {
                Some(d) => buf[..n].copy_from_slice(&d[within as usize..within as usize + n]),
                None => t.open()?.read_exact_at(&mut buf[..n], within)?,
            }
            buf = &mut buf[n..];
            offset += n as u64;
            k += 1;
        }
        Ok(())
    }
}

/// The [`Parts`] of an index, from the tile blobs the store holds.
pub fn parts_of(assets: &AssetStore, dir: &str, name: &str, index: &PackIndex) -> Result<Parts, TileError> {
    let mut tiles = Vec::with_capacity(index.tiles.len());
    let mut starts = Vec::with_capacity(index.tiles.len());
    let mut at = index.head.len() as u64;
    for (h, len) in &index.tiles {
        let rel = tile_rel(dir, h);
        let t = assets
            .get(&rel)
            .filter(|t| t.len == *len)
            .ok_or_else(|| TileError::MissingTile {
                index: name.to_string(),
                tile: rel,
            })?;
        starts.push(at);
        at += len;
        tiles.push(t);
    }
    Ok(Parts {
        head: Bytes::from(index.head.clone()),
        tiles,
        starts,
        len: at,
    })
}

/// Reads and decodes the index asset `a`.
pub fn read_index(a: &Asset) -> Result<PackIndex, TileError> {
    let bytes = match &a.data {
        Some(d) => d.to_vec(),
        None => std::fs::read(&a.path).map_err(|source| AssetError::Io {
            what: "reading",
            path: a.path.clone(),
            source,
        })?,
    };
    PackIndex::decode(&a.rel, &bytes)
}

/// The folder and name part (`v<N>`) of an index's path.
fn dir_and_stem(rel: &str) -> Option<(&str, &str)> {
    let (dir, file) = rel.rsplit_once('/')?;
    Some((dir, file.split('.').next()?))
}

/// Serves every pack index's pack (at start): each index found in the store whose pack is not
/// there whole becomes a pack read through its tile blobs. Indexes naming missing blobs are
/// skipped with a warning (their version's pack answers 404).
pub fn register_all(assets: &AssetStore) {
    register_in(assets, "scenes/");
}

/// [`register_all`] for the indexes under `prefix` only.
pub fn register_in(assets: &AssetStore, prefix: &str) {
    for a in assets.list(prefix) {
        if a.ext() != INDEX_EXT {
            continue;
        }
        let registered = (|| {
            let (dir, stem) = dir_and_stem(&a.rel).ok_or_else(|| TileError::Index(a.rel.clone(), "path"))?;
            let index = read_index(&a)?;
            let rel = format!("{dir}/{stem}.{}.cpack", &hex(&index.sha256)[..NAME_HASH_HEX]);
            if assets.get_indexed(&rel).is_none() {
                let parts = parts_of(assets, dir, &a.rel, &index)?;
                assets.insert_parts(&rel, &hex(&index.sha256), Arc::new(parts), a.modified);
            }
            Ok::<_, TileError>(())
        })();
        if let Err(e) = registered {
            tracing::warn!(error = %e, "a scene version's pack cannot be served");
        }
    }
}

/// What [`publish_pack`] wrote.
#[derive(Debug)]
pub struct PackPublished {
    /// The pack (served through its index, or a whole file for a first version).
    pub pack: Arc<Asset>,
    /// Its index.
    pub index: Arc<Asset>,
    /// The tile table (as the manifest repeats it).
    pub tiles: Vec<Tile>,
    /// Bytes before the first tile.
    pub tables_len: u64,
    /// Tile blobs written (the others already existed).
    pub new_tiles: usize,
}

/// Builds a version's pack and writes it per tile into `dir` ([`publish_draft`]).
pub fn publish_pack(
    assets: &AssetStore,
    dir: &str,
    stem: &str,
    bounds: &Bounds,
    list: &[Instance],
    whole: bool,
) -> Result<PackPublished, TileError> {
    let draft = PackDraft::build(0, bounds, list)?;
    publish_draft(assets, dir, stem, &draft, whole)
}

/// Writes a version's pack per tile into `dir`: the tile blobs not already there, then its index,
/// unsynced (the caller syncs `dir` before anything durable names them). With `whole`, the pack
/// is also written as one file. The caller holds `dir`'s blob lock until the version commits or
/// its files are discarded.
pub fn publish_draft(
    assets: &AssetStore,
    dir: &str,
    stem: &str,
    draft: &PackDraft,
    whole: bool,
) -> Result<PackPublished, TileError> {
    // The whole pack's hash (which the index and the manifest name) is hashed beside the tile
    // blobs' writes: on their syncs, a writer waits for the disk, not for a core.
    let (sha256, written) = std::thread::scope(|s| {
        // Without a thread to spare (the OS refused one), hashed here after the writes.
        let hashing = std::thread::Builder::new()
            .name("canopy-pack-hash".into())
            .spawn_scoped(s, || draft.pack_sha256())
            .ok();
        let written = write_tiles(assets, dir, draft);
        let sha256 = hashing
            .and_then(|h| h.join().ok())
            .unwrap_or_else(|| draft.pack_sha256());
        (sha256, written)
    });
    let (refs, new_tiles) = written?;
    let index = PackIndex {
        pack_len: draft.pack_len,
        sha256,
        head: draft.head.clone(),
        tiles: refs,
    };
    let index_asset = assets.put_unsynced(dir, stem, INDEX_EXT, &index.encode())?;
    let pack = if whole {
        assets.put_unsynced(dir, stem, "cpack", &draft.bytes())?
    } else {
        let rel = format!("{dir}/{stem}.{}.cpack", &hex(&sha256)[..NAME_HASH_HEX]);
        if let Some(a) = assets.get(&rel) {
            a
        } else {
            let parts = parts_of(assets, dir, &index_asset.rel, &index)?;
            assets.insert_parts(&rel, &hex(&sha256), Arc::new(parts), std::time::SystemTime::now())
        }
    };
    Ok(PackPublished {
        pack,
        index: index_asset,
        tiles: draft.table(),
        tables_len: draft.head.len() as u64,
        new_tiles,
    })
}

/// Writes the draft's tile blobs not already in `dir`; returns each tile's (hash16, length) in
/// pack order and how many blobs were written.
fn write_tiles(assets: &AssetStore, dir: &str, draft: &PackDraft) -> Result<(Vec<(String, u64)>, usize), TileError> {
    let mut refs = Vec::with_capacity(draft.tiles.len());
    let mut new_tiles = 0;
    for t in &draft.tiles {
        let h = hex(&t.sha256);
        let h16 = &h[..NAME_HASH_HEX];
        if assets.get(&tile_rel(dir, h16)).is_none() {
            assets.put_unsynced(dir, TILE_NAME, TILE_EXT, &t.records)?;
            new_tiles += 1;
        }
        refs.push((h16.to_string(), t.tile.length));
    }
    Ok((refs, new_tiles))
}

/// The tile blobs the pack indexes under `dir` name. `None` when an index cannot be read (then
/// nothing may be deleted).
pub fn referenced(assets: &AssetStore, dir: &str) -> Option<HashSet<String>> {
    let mut refs = Referenced::default();
    refs.read_new(&assets.list(&format!("{dir}/")), dir).then(|| {
        refs.indexes
            .iter()
            .flat_map(|(_, t)| t.iter())
            .map(|h| tile_rel(dir, &format!("{h:016x}")))
            .collect()
    })
}

/// A hash16 name as an integer (16 lowercase hex digits: what [`PackIndex::decode`] accepts).
fn hash16_value(h: &str) -> Option<u64> {
    let lower_hex = h.len() == NAME_HASH_HEX && h.bytes().all(|c| c.is_ascii_digit() || (b'a'..=b'f').contains(&c));
    lower_hex.then(|| u64::from_str_radix(h, 16).ok())?
}

/// The hash16 of a tile blob's path (`…/t.<hash16>.ctile`), as an integer.
fn tile_hash(rel: &str) -> Option<u64> {
    let h = rel
        .rsplit('/')
        .next()?
        .strip_prefix(TILE_NAME)?
        .strip_prefix('.')?
        .strip_suffix(TILE_EXT)?
        .strip_suffix('.')?;
    hash16_value(h)
}

/// The tile blobs index asset `a` names, sorted. Decoded once per asset (an index never
/// changes) while its bytes are held in memory, so the cache is bounded by the asset store's
/// memory budget (8 bytes a tile against the index's 24).
fn index_tiles(a: &Asset) -> Result<Arc<[u64]>, TileError> {
    if let Some(t) = a.index_tiles.get() {
        return Ok(t.clone());
    }
    let index = read_index(a)?;
    let mut tiles: Vec<u64> = index
        .tiles
        .iter()
        .map(|(h, _)| hash16_value(h))
        .collect::<Option<_>>()
        .ok_or_else(|| TileError::Index(a.rel.clone(), "tile hash"))?;
    tiles.sort_unstable();
    tiles.dedup();
    let tiles: Arc<[u64]> = tiles.into();
    if a.data.is_some() {
        let _ = a.index_tiles.set(tiles.clone());
    }
    Ok(tiles)
}

/// The pack indexes of a folder read so far, newest version first: a blob is looked up in the
/// newest index first, which names nearly all of them, so a cleanup costs the folder's listing,
/// not its versions × tiles.
#[derive(Default)]
struct Referenced {
    read: HashSet<String>,
    indexes: Vec<(u64, Arc<[u64]>)>,
}

impl Referenced {
    /// Reads the indexes of `dir` in `listed` not read yet; `false` when one cannot be read (then
    /// nothing may be deleted).
    fn read_new(&mut self, listed: &[Arc<Asset>], dir: &str) -> bool {
        let depth = dir.matches('/').count() + 1;
        for a in listed {
            if a.ext() != INDEX_EXT || a.rel.matches('/').count() != depth || self.read.contains(&a.rel) {
                continue;
            }
            match index_tiles(a) {
                Ok(tiles) => {
                    let version = a.name().strip_prefix('v').and_then(|v| v.parse().ok()).unwrap_or(0);
                    self.indexes.push((version, tiles));
                }
                Err(e) => {
                    tracing::warn!(error = %e, "keeping every tile blob of the folder");
                    return false;
                }
            }
            self.read.insert(a.rel.clone());
        }
        self.indexes.sort_by_key(|(v, _)| std::cmp::Reverse(*v));
        true
    }

    /// Whether asset `a` is a tile blob that no index read names.
    fn unreferenced(&self, a: &Asset) -> bool {
        a.ext() == TILE_EXT
            && tile_hash(&a.rel).is_some_and(|h| !self.indexes.iter().any(|(_, t)| t.binary_search(&h).is_ok()))
    }
}

/// Deletes the tile blobs under `dir` that no pack index there names, at most `most` of them;
/// returns (files, bytes). The caller holds `dir`'s blob lock.
pub fn drop_unreferenced(assets: &AssetStore, dir: &str, most: usize) -> (usize, u64) {
    let listed = assets.list(&format!("{dir}/"));
    let mut refs = Referenced::default();
    if !refs.read_new(&listed, dir) {
        return (0, 0);
    }
    let (mut n, mut bytes) = (0, 0);
    for a in &listed {
        if n >= most {
            break;
        }
        if !refs.unreferenced(a) {
            continue;
        }
        match assets.remove(&a.rel) {
            Ok(true) => {
                n += 1;
                bytes += a.len;
            }
            Ok(false) => {}
            Err(e) => tracing::warn!(file = %a.rel, error = %e, "could not delete an unreferenced tile blob"),
        }
    }
    (n, bytes)
}

/// [`drop_unreferenced`] without holding `dir`'s blob lock for the whole pass, so that the next
/// publish of the scene never waits behind it: the indexes are read unlocked, then each blob is
/// deleted under the lock on its own. A publish may reuse a blob the pass found unreferenced, so
/// when one has taken the lock since the indexes were read, the indexes written since are read
/// too (under the lock) before anything more is deleted.
pub fn drop_unreferenced_between(assets: &AssetStore, dir: &str, most: usize) -> (usize, u64) {
    let lock = assets.blob_lock(dir);
    let mut seen = *lock.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
    let prefix = format!("{dir}/");
    let listed = assets.list(&prefix);
    let mut refs = Referenced::default();
    if !refs.read_new(&listed, dir) {
        return (0, 0);
    }
    let (mut n, mut bytes) = (0, 0);
    for a in &listed {
        if n >= most {
            break;
        }
        if !refs.unreferenced(a) {
            continue;
        }
        let publishes = lock.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        if *publishes != seen {
            seen = *publishes;
            if !refs.read_new(&assets.list(&prefix), dir) {
                break;
            }
            if !refs.unreferenced(a) {
                continue;
            }
        }
        match assets.remove(&a.rel) {
            Ok(true) => {
                n += 1;
                bytes += a.len;
            }
            Ok(false) => {}
            Err(e) => tracing::warn!(file = %a.rel, error = %e, "could not delete an unreferenced tile blob"),
        }
    }
    (n, bytes)
}

#[cfg(test)]
#[path = "tiles_tests.rs"]
mod tests;

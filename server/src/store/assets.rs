//! The content-addressed asset store: immutable files under `DATA/assets/`, each named
//! `<name>.<hash16>.<ext>` where `hash16` is the first 16 hex digits of the SHA-256 of its bytes.
//! A file's URL is `/assets/` followed by its path relative to `DATA/assets/`, so copying that
//! folder to any static host serves the same bytes at the same paths.

use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, OnceLock, RwLock, Weak};
use std::time::SystemTime;

use axum::http::HeaderValue;
use bytes::Bytes;
use sha2::{Digest, Sha256};

/// Hex digits of the hash in a file name.
pub const NAME_HASH_HEX: usize = 16;

/// Why the asset store failed.
#[derive(Debug, thiserror::Error)]
pub enum AssetError {
    /// Filesystem error.
    #[error("{what} {path}: {source}")]
    Io {
        /// What was being done.
        what: &'static str,
        /// The path.
        path: PathBuf,
        /// The error.
        source: std::io::Error,
    },
    /// A name or folder component is not `[A-Za-z0-9_-]{1,64}`.
    #[error("invalid asset name component {0:?}: use 1 to 64 of A-Z a-z 0-9 _ -")]
    BadName(String),
}

/// Most files kept open for reuse across requests; assets beyond this are opened per request
/// (like nginx without `open_file_cache`), so the number of versions kept on disk never runs the
/// process out of file descriptors.
pub const MAX_CACHED_FILES: usize = 512;

static CACHED_FILES: AtomicUsize = AtomicUsize::new(0);

/// Default budget of asset bytes held in memory ([`AssetStore::open_with_memory`]).
pub const DEFAULT_MEMORY_BUDGET: u64 = 256 << 20;

/// Positioned reads of an asset's bytes: a file, or a pack read through its tile blobs
/// ([`super::tiles::Parts`]).
pub trait ReadAt: Send + Sync + std::fmt::Debug {
    /// Fills `buf` from `offset`, or fails (`UnexpectedEof` past the end).
    fn read_exact_at(&self, buf: &mut [u8], offset: u64) -> std::io::Result<()>;
}

impl ReadAt for File {
    fn read_exact_at(&self, buf: &mut [u8], offset: u64) -> std::io::Result<()> {
        std::os::unix::fs::FileExt::read_exact_at(self, buf, offset)
    }
}

/// One immutable asset.
#[derive(Debug)]
pub struct Asset {
    /// Path relative to the assets folder, `/`-separated (the URL after `/assets/`).
    pub rel: String,
    /// The file.
    pub path: PathBuf,
    /// Length in bytes.
    pub len: u64,
    /// SHA-256 of the bytes, lowercase hex.
    pub sha256: String,
    /// Strong entity tag: the quoted SHA-256 hex.
    pub etag: String,
    /// `Content-Type` by extension.
    pub content_type: &'static str,
    /// [`Self::etag`] as a header value, built once (responses clone it: a reference count).
    pub etag_header: HeaderValue,
    /// [`Self::content_type`] as a header value.
    pub content_type_header: HeaderValue,
    /// Modification time (picks the newest of several bakes of one model).
    pub modified: SystemTime,
    /// The whole file, when the store's memory budget had room for it: held once, shared by
    /// every response (a range is a slice of it, not a copy), dropped with the asset.
    pub data: Option<Bytes>,
    /// A pack stored per tile: read through its index, no file of its own at `path`.
    pub parts: Option<Arc<super::tiles::Parts>>,
    /// The open file, once opened, while under [`MAX_CACHED_FILES`].
    cached: OnceLock<Option<Arc<File>>>,
    /// For a pack index: the tile blobs it names, decoded once (the file never changes), so that
    /// an edit's cleanup does not decode every kept version's index again
    /// ([`super::tiles::drop_unreferenced_between`]).
    pub(crate) index_tiles: OnceLock<Arc<[u64]>>,
}

impl Asset {
    /// The file, for positioned reads: kept open after the first use while fewer than
    /// [`MAX_CACHED_FILES`] are, else opened anew. The file never changes (it is named by its
    /// hash and replaced only by rename), so a kept handle always reads the right bytes.
    pub fn open(&self) -> std::io::Result<Arc<dyn ReadAt>> {
        if let Some(p) = &self.parts {
            return Ok(p.clone());
        }
        if let Some(Some(f)) = self.cached.get() {
            return Ok(f.clone());
        }
        let f = Arc::new(File::open(&self.path)?);
        if CACHED_FILES.fetch_add(1, Ordering::Relaxed) < MAX_CACHED_FILES {
            let _ = self.cached.set(Some(f.clone()));
        } else {
            CACHED_FILES.fetch_sub(1, Ordering::Relaxed);
        }
        Ok(f)
    }

    /// The URL path: `/assets/<rel>`.
    pub fn url(&self) -> String {
        format!("/assets/{}", self.rel)
    }

    /// The name part of `<name>.<hash16>.<ext>`.
    pub fn name(&self) -> &str {
        let file = self.rel.rsplit('/').next().unwrap_or(&self.rel);
        file.split('.').next().unwrap_or(file)
    }

    /// The extension part of `<name>.<hash16>.<ext>`.
    pub fn ext(&self) -> &str {
        self.rel.rsplit('.').next().unwrap_or("")
    }
}

/// `Content-Type` for an extension.
pub fn content_type(ext: &str) -> &'static str {
    match ext {
        "json" => "application/json",
        "ctree" => "application/vnd.canopy.ctree",
        "cpack" => "application/vnd.canopy.cpack",
        "cterrain" => "application/vnd.canopy.cterrain",
        "glb" => "model/gltf-binary",
        _ => "application/octet-stream",
    }
}

/// Ordered by path, so that a folder's assets are one range ([`AssetStore::list`]): an edit's
/// cleanup lists its scene's folder without visiting every other scene's files.
type Index = BTreeMap<String, Arc<Asset>>;

/// The asset store.
#[derive(Debug)]
pub struct AssetStore {
    root: PathBuf,
    index: RwLock<Index>,
    /// Most bytes of asset files held in memory.
    memory_budget: u64,
    /// Bytes held now.
    memory_used: AtomicU64,
    /// Per folder: held by publishes that may reuse its tile blobs and by cleanups deleting them.
    blob_locks: Mutex<HashMap<String, Weak<BlobLock>>>,
    /// Other processes (server replicas) write and delete scene files in this folder too.
    shared: AtomicBool,
}

/// Folder of the cross-process folder locks, under the assets folder (never served: not a valid
/// asset name).
const LOCKS_DIR: &str = ".locks";

/// A folder's tile-blob lock, guarding how many publishes have taken it: a publish adds one, so
/// that a cleanup that works between publishes, one file at a time, sees that one came
/// ([`super::tiles::drop_unreferenced_between`]).
pub type BlobLock = Mutex<u64>;

/// SHA-256 hex of bytes.
pub fn sha256_hex(bytes: &[u8]) -> String {
    hex(&Sha256::digest(bytes))
}

/// Lowercase hex of bytes.
pub fn hex(bytes: &[u8]) -> String {
    const DIGITS: &[u8; 16] = b"0123456789abcdef";
    let mut s = String::with_capacity(bytes.len() * 2);
    for b in bytes {
        s.push(char::from(DIGITS[usize::from(b >> 4)]));
        s.push(char::from(DIGITS[usize::from(b & 15)]));
    }
    s
}

fn valid_component(s: &str) -> bool {
    !s.is_empty() && s.len() <= 64 && s.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-')
}

fn io(what: &'static str, path: &Path) -> impl FnOnce(std::io::Error) -> AssetError {
    let path = path.to_path_buf();
    move |source| AssetError::Io { what, path, source }
}

/// True for a temporary file of [`AssetStore::put`] (`.tmp-<name>-<pid>-<hash16>`) whose writer
/// is gone: its process id is not running, per `/proc` (without `/proc`, none is). Only these are
/// deleted at start, never another file.
pub(crate) fn stale_temp(file: &str) -> bool {
    let Some(rest) = file.strip_prefix(".tmp-") else {
        return false;
    };
    let mut parts = rest.rsplitn(3, '-');
    let (Some(hash), Some(pid), Some(name)) = (parts.next(), parts.next(), parts.next()) else {
        return false;
    };
    let ours = hash.len() == NAME_HASH_HEX
        && hash.bytes().all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b))
        && valid_component(name);
    let Some(pid) = pid.parse::<u32>().ok().filter(|_| ours) else {
        return false;
    };
    if pid == std::process::id() {
        return false;
    }
    if Path::new("/proc/self").exists() {
        !Path::new("/proc").join(pid.to_string()).exists()
    } else {
        false
    }
}

/// Syncs a folder, so that the renames and creations in it survive a power cut. Filesystems that
/// cannot sync a folder (`EINVAL`) are left as they are.
fn sync_dir(dir: &Path) -> Result<(), AssetError> {
    match File::open(dir).and_then(|d| d.sync_all()) {
        Err(e) if e.kind() != std::io::ErrorKind::InvalidInput => Err(io("syncing", dir)(e)),
        _ => Ok(()),
    }
}

/// `create_dir_all(dir)` (`dir` under `root`), syncing the parent of each folder it creates.
fn create_dirs_durably(root: &Path, dir: &Path) -> Result<(), AssetError> {
    if dir.is_dir() {
        return Ok(());
    }
    if let Some(parent) = dir.parent()
        && parent != root
        && parent.starts_with(root)
    {
        create_dirs_durably(root, parent)?;
    }
    match std::fs::create_dir(dir) {
        Err(e) if e.kind() != std::io::ErrorKind::AlreadyExists => return Err(io("creating", dir)(e)),
        _ => {}
    }
    sync_dir(dir.parent().unwrap_or(root))
}

impl AssetStore {
    /// Opens (creating if needed) the assets folder and indexes every correctly named file in it,
    /// checking each file's bytes against the hash in its name. Files that do not follow the
    /// naming rule or fail the check are skipped with a warning.
    pub fn open(root: &Path) -> Result<Self, AssetError> {
        Self::open_with_memory(root, DEFAULT_MEMORY_BUDGET)
    }

    /// Like [`Self::open`], holding the bytes of assets in memory (read once, at start or when
    /// written) while their total stays within `memory_budget` bytes; the rest are read from
    /// disk per request.
    pub fn open_with_memory(root: &Path, memory_budget: u64) -> Result<Self, AssetError> {
        std::fs::create_dir_all(root).map_err(io("creating", root))?;
        let store = Self {
            root: root.to_path_buf(),
            index: RwLock::new(Index::default()),
            memory_budget,
            memory_used: AtomicU64::new(0),
            blob_locks: Mutex::new(HashMap::new()),
            shared: AtomicBool::new(false),
        };
        let mut stack = vec![root.to_path_buf()];
        while let Some(dir) = stack.pop() {
            for entry in std::fs::read_dir(&dir).map_err(io("listing", &dir))? {
                let path = entry.map_err(io("listing", &dir))?.path();
                if path.is_dir() {
                    stack.push(path);
                } else if path.file_name().and_then(|n| n.to_str()).is_some_and(stale_temp) {
                    // Left by a crash between writing and renaming: never referenced.
                    match std::fs::remove_file(&path) {
                        Ok(()) => tracing::info!(file = %path.display(), "removed a stale temporary file"),
                        Err(e) => {
                            tracing::warn!(file = %path.display(), error = %e, "could not remove a stale temporary file");
                        }
                    }
                } else if let Some(rel) = store.rel_of(&path) {
                    match store.load(&rel) {
                        Ok(Some(a)) => store.insert(a),
                        Ok(None) => {
                            tracing::warn!(file = %path.display(), "skipping asset: name does not match its content hash");
                        }
                        Err(e) => tracing::warn!(error = %e, "skipping asset"),
                    }
                }
            }
        }
        super::tiles::register_all(&store);
        Ok(store)
    }

    /// The lock of folder `dir`'s tile blobs ([`super::tiles`]): a publish holds it from before
    /// it looks for a blob to reuse until its version commits, a cleanup while it deletes. It
    /// guards the count of publishes that took it ([`BlobLock`]).
    pub fn blob_lock(&self, dir: &str) -> Arc<BlobLock> {
        let mut locks = self
            .blob_locks
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        if let Some(l) = locks.get(dir).and_then(Weak::upgrade) {
            return l;
        }
        if locks.len() >= 1024 {
            locks.retain(|_, w| w.strong_count() > 0);
        }
        let l = Arc::new(Mutex::new(0));
        locks.insert(dir.to_string(), Arc::downgrade(&l));
        l
    }

    /// Indexes a pack served through its tile blobs at `rel`, unless an asset is there already;
    /// returns the asset at `rel`.
    pub(crate) fn insert_parts(
        &self,
        rel: &str,
        sha256: &str,
        parts: Arc<super::tiles::Parts>,
        modified: SystemTime,
    ) -> Arc<Asset> {
        let etag = format!("\"{sha256}\"");
        let ext = rel.rsplit('.').next().unwrap_or("");
        let content_type = content_type(ext);
        let a = Arc::new(Asset {
            rel: rel.to_string(),
            path: self.root.join(rel),
            len: parts.len(),
            data: None,
            etag_header: HeaderValue::from_str(&etag).unwrap_or_else(|_| HeaderValue::from_static("\"\"")),
            content_type_header: HeaderValue::from_static(content_type),
            etag,
            sha256: sha256.to_string(),
            content_type,
            modified,
            parts: Some(parts),
            cached: OnceLock::new(),
            index_tiles: OnceLock::new(),
        });
        let mut index = self.index.write().unwrap_or_else(std::sync::PoisonError::into_inner);
        index.entry(rel.to_string()).or_insert(a).clone()
    }

    /// The assets folder.
    pub fn root(&self) -> &Path {
        &self.root
    }

    fn rel_of(&self, path: &Path) -> Option<String> {
        let rel = path.strip_prefix(&self.root).ok()?;
        let parts: Vec<&str> = rel.iter().map(|c| c.to_str()).collect::<Option<_>>()?;
        let (file, dirs) = parts.split_last()?;
        let mut pieces = file.split('.');
        let (name, hash, ext) = (pieces.next()?, pieces.next()?, pieces.next()?);
        let ok = pieces.next().is_none()
            && dirs.iter().all(|d| valid_component(d))
            && valid_component(name)
            && hash.len() == NAME_HASH_HEX
            && hash.bytes().all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b))
            && valid_component(ext);
        ok.then(|| parts.join("/"))
    }

    /// Opens and hashes one file; `None` when its name's hash disagrees with its bytes.
    fn load(&self, rel: &str) -> Result<Option<Asset>, AssetError> {
        let path = self.root.join(rel);
        let bytes = std::fs::read(&path).map_err(io("reading", &path))?;
        let sha256 = sha256_hex(&bytes);
        let file_name = rel.rsplit('/').next().unwrap_or(rel);
        if file_name.split('.').nth(1) != Some(&sha256[..NAME_HASH_HEX]) {
            return Ok(None);
        }
        let meta = std::fs::metadata(&path).map_err(io("reading metadata of", &path))?;
        let modified = meta.modified().unwrap_or(SystemTime::UNIX_EPOCH);
        let len = bytes.len() as u64;
        Ok(Some(self.asset_of(
            rel,
            path,
            len,
            move || bytes.into(),
            sha256,
            modified,
        )))
    }

    /// The asset for a file of `len` bytes, its bytes (`data`) held in memory if the budget has room.
    fn asset_of(
        &self,
        rel: &str,
        path: PathBuf,
        len: u64,
        data: impl FnOnce() -> Bytes,
        sha256: String,
        modified: SystemTime,
    ) -> Asset {
        let held = self
            .memory_used
            .fetch_update(Ordering::Relaxed, Ordering::Relaxed, |used| {
                (used + len <= self.memory_budget).then_some(used + len)
            })
            .is_ok();
        let ext = rel.rsplit('.').next().unwrap_or("");
        let etag = format!("\"{sha256}\"");
        let content_type = content_type(ext);
        Asset {
            rel: rel.to_string(),
            path,
            len,
            data: held.then(data),
            // Hex digits and quotes: always a valid header value.
            etag_header: HeaderValue::from_str(&etag).unwrap_or_else(|_| HeaderValue::from_static("\"\"")),
            content_type_header: HeaderValue::from_static(content_type),
            etag,
            sha256,
            content_type,
            modified,
            parts: None,
            cached: OnceLock::new(),
            index_tiles: OnceLock::new(),
        }
    }

    fn insert(&self, a: Asset) {
        let mut index = self.index.write().unwrap_or_else(std::sync::PoisonError::into_inner);
        if let Some(old) = index.insert(a.rel.clone(), Arc::new(a)) {
            self.release(&old);
        }
    }

    /// Returns an asset's share of the memory budget (once it leaves the index; responses in
    /// flight may hold its bytes a little longer).
    fn release(&self, a: &Asset) {
        if a.data.is_some() {
            self.memory_used.fetch_sub(a.len, Ordering::Relaxed);
        }
    }

    /// Bytes of asset files held in memory.
    pub fn memory_used(&self) -> u64 {
        self.memory_used.load(Ordering::Relaxed)
    }

    /// The asset at `rel` (the URL path after `/assets/`). In a shared folder, a scene file
    /// another replica wrote is found on disk, and one it deleted is forgotten.
    pub fn get(&self, rel: &str) -> Option<Arc<Asset>> {
        let hit = self.get_indexed(rel);
        if !self.is_shared() || !rel.starts_with("scenes/") {
            return hit;
        }
        match hit {
            Some(a) if a.parts.is_some() || a.path.is_file() => Some(a),
            _ => self.discover(rel),
        }
    }

    /// The asset at `rel` if indexed, without looking at the disk.
    pub(crate) fn get_indexed(&self, rel: &str) -> Option<Arc<Asset>> {
        self.index
            .read()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .get(rel)
            .cloned()
    }

    /// Marks the folder as shared with other processes (server replicas on one data folder).
    pub fn set_shared(&self, shared: bool) {
        self.shared.store(shared, Ordering::Relaxed);
    }

    /// Whether other processes write and delete scene files here too.
    pub fn is_shared(&self) -> bool {
        self.shared.load(Ordering::Relaxed)
    }

    /// Looks `rel` (a scene file) up on disk: indexes it if there, forgets it if not; a pack
    /// served through its index is found by reading the folder's new indexes.
    fn discover(&self, rel: &str) -> Option<Arc<Asset>> {
        if self.rel_of(&self.root.join(rel)).as_deref() != Some(rel) {
            return None;
        }
        let stale = self
            .index
            .write()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .remove(rel);
        if let Some(old) = stale {
            self.release(&old);
        }
        if self.root.join(rel).is_file() {
            let a = self.load(rel).ok()??;
            self.insert(a);
        } else if rel.rsplit('.').next() == Some("cpack") {
            self.rescan(rel.rsplit_once('/')?.0);
        }
        self.get_indexed(rel)
    }

    /// Brings the index of folder `dir` in line with the disk (a shared folder, where other
    /// replicas write and delete): indexes new files and the packs their indexes serve, forgets
    /// files that are gone.
    pub fn rescan(&self, dir: &str) {
        let path = self.root.join(dir);
        let on_disk: std::collections::HashSet<String> = std::fs::read_dir(&path)
            .into_iter()
            .flatten()
            .flatten()
            .filter_map(|e| self.rel_of(&e.path()))
            .collect();
        let prefix = format!("{dir}/");
        let gone: Vec<Arc<Asset>> = {
            let mut index = self.index.write().unwrap_or_else(std::sync::PoisonError::into_inner);
            let gone: Vec<String> = index
                .iter()
                .filter(|(rel, a)| {
                    rel.starts_with(&prefix)
                        && !rel[prefix.len()..].contains('/')
                        && a.parts.is_none()
                        && !on_disk.contains(*rel)
                })
                .map(|(rel, _)| rel.clone())
                .collect();
            gone.iter().filter_map(|rel| index.remove(rel)).collect()
        };
        for a in &gone {
            self.release(a);
        }
        let known: Vec<String> = {
            let index = self.index.read().unwrap_or_else(std::sync::PoisonError::into_inner);
            on_disk
                .iter()
                .filter(|rel| !index.contains_key(*rel))
                .cloned()
                .collect()
        };
        for rel in known {
            match self.load(&rel) {
                Ok(Some(a)) => self.insert(a),
                Ok(None) => tracing::warn!(file = %rel, "skipping asset: name does not match its content hash"),
                Err(e) => tracing::warn!(error = %e, "skipping asset"),
            }
        }
        super::tiles::register_in(self, &prefix);
    }

    /// In a shared folder, the cross-process lock of folder `dir`'s tile blobs, held shared by a
    /// publish from before it looks for blobs to reuse until its version commits (`None` when the
    /// folder is not shared).
    pub fn folder_lock_shared(&self, dir: &str) -> Result<Option<File>, AssetError> {
        if !self.is_shared() {
            return Ok(None);
        }
        let f = self.folder_lock_file(dir)?;
        f.lock_shared().map_err(io("locking", &self.root.join(dir)))?;
        Ok(Some(f))
    }

    /// The same lock held exclusively by a sweep that deletes tile blobs, tried without waiting:
    /// `None` while a publish holds it.
    pub fn try_folder_lock_exclusive(&self, dir: &str) -> Result<Option<File>, AssetError> {
        let f = self.folder_lock_file(dir)?;
        match f.try_lock() {
            Ok(()) => Ok(Some(f)),
            Err(std::fs::TryLockError::WouldBlock) => Ok(None),
            Err(std::fs::TryLockError::Error(e)) => Err(io("locking", &self.root.join(dir))(e)),
        }
    }

    fn folder_lock_file(&self, dir: &str) -> Result<File, AssetError> {
        if !dir.split('/').all(valid_component) {
            return Err(AssetError::BadName(dir.to_string()));
        }
        let locks = self.root.join(LOCKS_DIR);
        std::fs::create_dir_all(&locks).map_err(io("creating", &locks))?;
        let path = locks.join(format!("{}.lock", dir.replace('/', "~")));
        std::fs::OpenOptions::new()
            .create(true)
            .truncate(false)
            .write(true)
            .open(&path)
            .map_err(io("opening", &path))
    }

    /// Every asset whose path starts with `prefix`, in path order.
    pub fn list(&self, prefix: &str) -> Vec<Arc<Asset>> {
        let index = self.index.read().unwrap_or_else(std::sync::PoisonError::into_inner);
        index
            .range::<str, _>((std::ops::Bound::Included(prefix), std::ops::Bound::Unbounded))
            .take_while(|(rel, _)| rel.starts_with(prefix))
            .map(|(_, a)| a.clone())
            .collect()
    }

    /// Writes `bytes` as `<dir>/<name>.<hash16>.<ext>` (atomically: temporary file, synced, then
    /// rename, then the folder synced) unless it exists already, and indexes it.
    pub fn put(&self, dir: &str, name: &str, ext: &str, bytes: &[u8]) -> Result<Arc<Asset>, AssetError> {
        let a = self.put_unsynced(dir, name, ext, bytes)?;
        self.sync_folder(dir)?;
        Ok(a)
    }

    /// Syncs the folder `dir` (relative to the assets folder): what [`Self::put_unsynced`] renamed
    /// into it survives a power cut from then on.
    pub fn sync_folder(&self, dir: &str) -> Result<(), AssetError> {
        if !dir.split('/').all(valid_component) {
            return Err(AssetError::BadName(dir.to_string()));
        }
        sync_dir(&self.root.join(dir))
    }

    /// Like [`Self::put`] without the last folder sync, so that several files written to one folder
    /// share it (a folder sync costs as much as a file's): call [`Self::sync_folder`] before
    /// anything durable refers to them.
    pub fn put_unsynced(&self, dir: &str, name: &str, ext: &str, bytes: &[u8]) -> Result<Arc<Asset>, AssetError> {
        for c in dir.split('/').chain([name, ext]) {
            if !valid_component(c) {
                return Err(AssetError::BadName(c.to_string()));
            }
        }
        let sha = sha256_hex(bytes);
        let rel = format!("{dir}/{name}.{}.{ext}", &sha[..NAME_HASH_HEX]);
        if let Some(a) = self.get(&rel) {
            return Ok(a);
        }
        let path = self.root.join(&rel);
        let parent = path.parent().unwrap_or(&self.root).to_path_buf();
        create_dirs_durably(&self.root, &parent)?;
        let tmp = parent.join(format!(".tmp-{name}-{}-{}", std::process::id(), &sha[..NAME_HASH_HEX]));
        {
            let mut f = File::create(&tmp).map_err(io("creating", &tmp))?;
            f.write_all(bytes).map_err(io("writing", &tmp))?;
            f.sync_all().map_err(io("syncing", &tmp))?;
        }
        std::fs::rename(&tmp, &path).map_err(io("renaming", &tmp))?;
        // Built from the bytes in hand: reading the file back would hash them a second time.
        let len = bytes.len() as u64;
        let a = self.asset_of(
            &rel,
            path,
            len,
            || Bytes::copy_from_slice(bytes),
            sha,
            SystemTime::now(),
        );
        self.insert(a);
        self.get(&rel).ok_or(AssetError::BadName(rel))
    }

    /// Forgets and deletes the file at `rel` (a path under the assets folder, indexed or not);
    /// false when there was none. Requests already in flight keep their open files.
    pub fn remove(&self, rel: &str) -> Result<bool, AssetError> {
        let parts: Vec<&str> = rel.split('/').collect();
        let (file, dirs) = parts.split_last().ok_or_else(|| AssetError::BadName(rel.to_string()))?;
        let file_ok = !file.is_empty()
            && file.bytes().all(|b| b.is_ascii_alphanumeric() || b"_-.".contains(&b))
            && !file.starts_with("..");
        if !(file_ok && dirs.iter().all(|d| valid_component(d))) {
            return Err(AssetError::BadName(rel.to_string()));
        }
        if let Some(old) = self
            .index
            .write()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .remove(rel)
        {
            self.release(&old);
        }
        let path = self.root.join(rel);
        match std::fs::remove_file(&path) {
            Ok(()) => Ok(true),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(false),
            Err(e) => Err(io("removing", &path)(e)),
        }
    }

    /// Forgets and deletes every asset under `dir/` (a deleted scene's files). Requests already in
    /// flight keep their open files.
    pub fn remove_dir(&self, dir: &str) -> Result<(), AssetError> {
        if !dir.split('/').all(valid_component) {
            return Err(AssetError::BadName(dir.to_string()));
        }
        let prefix = format!("{dir}/");
        self.index
            .write()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .retain(|k, a| {
                let keep = !k.starts_with(&prefix);
                if !keep {
                    self.release(a);
                }
                keep
            });
        let path = self.root.join(dir);
        match std::fs::remove_dir_all(&path) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(io("removing", &path)(e)),
            _ => Ok(()),
        }
    }

    /// The baked tree models (`trees/<name>.<hash16>.ctree`): for each name, its newest file.
    pub fn models(&self) -> HashMap<String, Arc<Asset>> {
        let mut out: HashMap<String, Arc<Asset>> = HashMap::new();
        for a in self.list("trees/") {
            if a.ext() != "ctree" || a.rel.matches('/').count() != 1 {
                continue;
            }
            let newer = out.get(a.name()).is_none_or(|b| a.modified > b.modified);
            if newer {
                out.insert(a.name().to_string(), a);
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn put_get_reopen_and_reject_mismatched_names() {
        let dir = std::env::temp_dir().join(format!("canopy-assets-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let s = AssetStore::open(&dir).expect("open");
        let a = s.put("trees", "oak", "ctree", b"hello").expect("put");
        assert_eq!(a.rel, format!("trees/oak.{}.ctree", &sha256_hex(b"hello")[..16]));
        assert_eq!(a.len, 5);
        assert_eq!(a.name(), "oak");
        assert_eq!(s.memory_used(), 5);
        assert_eq!(a.data.as_deref(), Some(&b"hello"[..]));
        // Past the memory budget, assets are still indexed, but read from disk.
        let tight = AssetStore::open_with_memory(&dir, 4).expect("open tight");
        assert!(tight.get(&a.rel).is_some_and(|a| a.data.is_none()));
        assert_eq!(tight.memory_used(), 0);
        assert!(s.put("trees", "../x", "ctree", b"x").is_err());
        // A file whose name claims another hash is not served.
        std::fs::write(dir.join("trees/fake.0123456789abcdef.ctree"), b"nope").expect("write");
        std::fs::write(dir.join("trees/notes.txt"), b"nope").expect("write");
        let s2 = AssetStore::open(&dir).expect("reopen");
        assert!(s2.get(&a.rel).is_some());
        assert!(s2.get("trees/fake.0123456789abcdef.ctree").is_none());
        assert_eq!(s2.models().keys().collect::<Vec<_>>(), vec!["oak"]);
        assert_eq!(s2.memory_used(), 5);
        s2.remove_dir("trees").expect("remove");
        assert_eq!(s2.memory_used(), 0);
        assert!(s2.get(&a.rel).is_none());
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn stale_temporary_files_are_removed_at_start_and_nothing_else() {
        let dir = std::env::temp_dir().join(format!("canopy-assets-tmp-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let scene = dir.join("scenes/demo");
        std::fs::create_dir_all(&scene).expect("mkdir");
        // No process has id 4294967295 (Linux ids stay below 2^22).
        let stale = [
            ".tmp-v232-4294967295-0123456789abcdef",
            ".tmp-my-tree-4294967295-fedcba9876543210",
        ];
        let own = format!(".tmp-v9-{}-0123456789abcdef", std::process::id());
        let keep = [
            own.as_str(),
            ".tmp-v232-4294967295-0123456789ABCDEF",
            ".tmp-v232-x-0123456789abcdef",
            ".tmp-notes",
            "tmp-v232-4294967295-0123456789abcdef",
            ".tmp-v232-4294967295-0123456789abcdef.bak",
        ];
        for f in stale.iter().chain(&keep) {
            std::fs::write(scene.join(f), b"x").expect("write");
        }
        let s = AssetStore::open(&dir).expect("open");
        for f in stale {
            assert!(!scene.join(f).exists(), "{f} is still there");
        }
        for f in keep {
            assert!(scene.join(f).exists(), "{f} was removed");
        }
        // New folders and files are published with the folders synced.
        let a = s.put("scenes/new/deeper", "v1", "cpack", b"pack").expect("put");
        assert!(dir.join(&a.rel).is_file());
        let _ = std::fs::remove_dir_all(&dir);
    }
}

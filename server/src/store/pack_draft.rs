//! A scene version's instance pack held in memory between edits, so that the version a small edit
//! makes re-encodes and re-hashes only the tiles the edit touched: the cost of an edit follows the
//! edit, not the scene (issue 23: a one-instance move on a 50,000-instance scene).
//!
//! Contract: [`PackDraft::apply`] of a version's [`Changes`] to the draft of the version before
//! gives byte for byte the pack [`pack::build`] makes from the new version's whole list (tested
//! over random edit sequences in `pack_draft_tests.rs`). When it cannot (the model set changes, a
//! change names an instance the draft does not hold, or the edit is large), it builds the draft
//! from the list instead, so a draft is never wrong, only sometimes not incremental.
//!
//! A draft knows its version's ground ([`Ground`], none for flat ground): with a terrain, a record's
//! y is the instance's stored y (its height above the ground) plus the terrain's height under it,
//! and a draft is applied in place only to a version on the same terrain file.
//!
//! Why a tile's records can be reused: an instance whose record changes has its old and new cell
//! keys marked touched; a tile whose cell (level, column, row) is unchanged and whose key range
//! holds no touched key has the same instances in the same order, and, the model table being
//! unchanged, the same bytes.

use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;

use sha2::{Digest, Sha256};

use super::pack::{self, PackError, PackInstance, Tile};
use super::scenes::{Bounds, Changes, Instance};
use crate::terrain::Ground;

/// An edit at most this many changed instance states (before and after) long is applied in
/// place; a longer one (a bulk add) rebuilds, which then costs no more than the edit's own work.
pub const INCREMENTAL_CHANGES: usize = 256;

/// One tile of a draft: its table entry (offset as in this version's pack), records and hash.
#[derive(Debug, Clone)]
pub struct DraftTile {
    /// The tile table's entry.
    pub tile: Tile,
    /// The tile's records.
    pub records: Arc<[u8]>,
    /// SHA-256 of the records (the tile blob's name is its first 16 hex digits).
    pub sha256: [u8; 32],
}

/// A version's pack, in pieces.
#[derive(Debug, Clone)]
pub struct PackDraft {
    /// The version it is the pack of.
    pub version: u64,
    bounds: [f32; 4],
    /// Model names, sorted (the pack's model table).
    names: Vec<String>,
    /// Instances per model name.
    counts: Vec<usize>,
    model_table: Vec<u8>,
    /// Instances sorted by (cell key, id), with their keys.
    keyed: Vec<(u64, PackInstance)>,
    /// Tiles in pack order.
    pub tiles: Vec<DraftTile>,
    /// The pack's bytes before the first tile.
    pub head: Vec<u8>,
    /// Length of the whole pack.
    pub pack_len: u64,
    /// The terrain its instances stand on (none: the plane y = 0).
    ground: Option<Arc<Ground>>,
}

fn instance_key(bounds: [f32; 4], i: &Instance) -> u64 {
    pack::cell_key(bounds, i.position)
}

fn pack_instance(i: &Instance, model: u16, ground: Option<&Ground>) -> PackInstance {
    PackInstance {
        id: i.id,
        model,
        position: ground.map_or(i.position, |g| g.lift(i.position)),
        rotation: i.rotation,
        scale: i.scale,
    }
}

impl PackDraft {
    /// Model names of the pack, sorted.
    pub fn names(&self) -> &[String] {
        &self.names
    }

    /// Instances in the pack.
    pub fn instance_count(&self) -> usize {
        self.keyed.len()
    }

    /// The terrain its instances stand on.
    pub fn ground(&self) -> Option<&Arc<Ground>> {
        self.ground.as_ref()
    }

    /// The draft of `version` made of `list` on flat ground, from scratch.
    pub fn build(version: u64, bounds: &Bounds, list: &[Instance]) -> Result<Self, PackError> {
        Self::build_on(version, bounds, list, None)
    }

    /// The draft of `version` made of `list` standing on `ground`, from scratch.
    pub fn build_on(
        version: u64,
        bounds: &Bounds,
        list: &[Instance],
        ground: Option<Arc<Ground>>,
    ) -> Result<Self, PackError> {
        let bounds = bounds.as_f32();
        let mut per_model = BTreeMap::<&str, usize>::new();
        for i in list {
            *per_model.entry(i.model.as_str()).or_default() += 1;
        }
        let names: Vec<String> = per_model.keys().map(|n| (*n).to_string()).collect();
        let counts: Vec<usize> = per_model.values().copied().collect();
        let model_table = pack::model_table(&names)?;
        let index: HashMap<&str, u16> = names.iter().enumerate().map(|(k, n)| (n.as_str(), k as u16)).collect();
        let mut keyed: Vec<(u64, PackInstance)> = list
            .iter()
            .map(|i| {
                (
                    instance_key(bounds, i),
                    pack_instance(i, index[i.model.as_str()], ground.as_deref()),
                )
            })
            .collect();
        keyed.sort_unstable_by_key(|(k, i)| (*k, i.id));
        let mut draft = Self {
            version,
            bounds,
            names,
            counts,
            model_table,
            keyed,
            tiles: Vec::new(),
            head: Vec::new(),
            pack_len: 0,
            ground,
        };
        draft.retile(&[], None);
        Ok(draft)
    }

    /// The draft of `version`, made by `changes` from this one (the draft of
    /// `changes.base_version`), `list` being the new version's whole list (for a rebuild), on
    /// this draft's ground.
    pub fn apply(self, version: u64, bounds: &Bounds, changes: &Changes, list: &[Instance]) -> Result<Self, PackError> {
        let ground = self.ground.clone();
        self.apply_on(version, bounds, ground, changes, list)
    }

    /// [`Self::apply`] for a version standing on `ground`: in place when it is this draft's,
    /// rebuilt otherwise.
    pub fn apply_on(
        mut self,
        version: u64,
        bounds: &Bounds,
        ground: Option<Arc<Ground>>,
        changes: &Changes,
        list: &[Instance],
    ) -> Result<Self, PackError> {
        let same_ground = match (&self.ground, &ground) {
            (None, None) => true,
            (Some(a), Some(b)) => a.same(b),
            _ => false,
        };
        if !same_ground {
            return Self::build_on(version, bounds, list, ground);
        }
        let incremental = changes.base_version == Some(self.version)
            && self.bounds == bounds.as_f32()
            && changes.before.len() + changes.after.len() <= INCREMENTAL_CHANGES
            && self.apply_in_place(changes);
        if !incremental {
            return Self::build_on(version, bounds, list, self.ground.clone());
        }
        debug_assert_eq!(self.keyed.len(), list.len());
        self.version = version;
        Ok(self)
    }

    /// Applies `changes` to the instances and the tiles; `false` (the draft then spoilt) when
    /// they cannot be applied in place.
    fn apply_in_place(&mut self, changes: &Changes) -> bool {
        let model = |names: &[String], m: &str| names.binary_search_by(|n| n.as_str().cmp(m)).ok();
        let mut counts = self.counts.clone();
        for b in &changes.before {
            match model(&self.names, &b.model) {
                Some(k) if counts[k] > 0 => counts[k] -= 1,
                _ => return false,
            }
        }
        for a in &changes.after {
            match model(&self.names, &a.model) {
                Some(k) => counts[k] += 1,
                None => return false, // a new model: the model table changes
            }
        }
        if counts.contains(&0) {
            return false; // a model left the scene
        }
        let mut touched = Vec::with_capacity(changes.before.len() + changes.after.len());
        for b in &changes.before {
            let key = instance_key(self.bounds, b);
            match self.keyed.binary_search_by(|(k, i)| (*k, i.id).cmp(&(key, b.id))) {
                Ok(at) => {
                    self.keyed.remove(at);
                }
                Err(_) => return false,
            }
            touched.push(key);
        }
        for a in &changes.after {
            let key = instance_key(self.bounds, a);
            let Some(m) = model(&self.names, &a.model) else {
                return false;
            };
            let at = self.keyed.partition_point(|(k, i)| (*k, i.id) < (key, a.id));
            self.keyed
                .insert(at, (key, pack_instance(a, m as u16, self.ground.as_deref())));
            touched.push(key);
        }
        self.counts = counts;
        touched.sort_unstable();
        touched.dedup();
        let old = std::mem::take(&mut self.tiles);
        self.retile(&touched, Some(old));
        true
    }

    /// Cuts the instances into tiles, reusing from `old` every tile no `touched` key falls in,
    /// and makes the head (the whole pack's hash is [`Self::pack_sha256`], made when published).
    fn retile(&mut self, touched: &[u64], old: Option<Vec<DraftTile>>) {
        let keys: Vec<u64> = self.keyed.iter().map(|(k, _)| *k).collect();
        let cells = pack::leaf_cells(&keys);
        let reusable: HashMap<(u8, u16, u16), DraftTile> = old
            .unwrap_or_default()
            .into_iter()
            .map(|t| ((t.tile.level, t.tile.x, t.tile.z), t))
            .collect();
        let mut offset = pack::records_start(self.model_table.len(), cells.len()) as u64;
        let mut tiles = Vec::with_capacity(cells.len());
        for c in &cells {
            let range = pack::cell_key_range(c.level, c.x, c.z);
            let clean = touched.partition_point(|k| *k < range.start) == touched.partition_point(|k| *k < range.end);
            let count = (c.end - c.start) as u32;
            let kept = reusable
                .get(&(c.level, c.x, c.z))
                .filter(|t| clean && t.tile.count == count);
            let mut t = if let Some(t) = kept {
                t.clone()
            } else {
                let mut records = Vec::with_capacity(count as usize * pack::INSTANCE_RECORD_LEN);
                for (_, i) in &self.keyed[c.start..c.end] {
                    pack::encode_record(i, &mut records);
                }
                DraftTile {
                    tile: Tile {
                        level: c.level,
                        x: c.x,
                        z: c.z,
                        count,
                        offset: 0,
                        length: records.len() as u64,
                        crc32: crc32fast::hash(&records),
                        bounds: pack::cell_bounds(self.bounds, c.level, c.x, c.z),
                    },
                    sha256: Sha256::digest(&records).into(),
                    records: records.into(),
                }
            };
            t.tile.offset = offset;
            offset += t.tile.length;
            tiles.push(t);
        }
        let table: Vec<Tile> = tiles.iter().map(|t| t.tile.clone()).collect();
        self.head = pack::encode_head(
            self.bounds,
            self.names.len(),
            &self.model_table,
            &table,
            self.keyed.len() as u32,
            offset,
        );
        self.pack_len = offset;
        self.tiles = tiles;
    }

    /// SHA-256 of the whole pack: the one part of a publish that costs the scene, not the edit
    /// (about 1 ms per 1.4 MB), so [`super::tiles::publish_draft`] runs it beside the tile
    /// blobs' writes.
    pub fn pack_sha256(&self) -> [u8; 32] {
        let mut h = Sha256::new();
        h.update(&self.head);
        for t in &self.tiles {
            h.update(&t.records);
        }
        h.finalize().into()
    }

    /// The whole pack, as one buffer.
    pub fn bytes(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(self.pack_len as usize);
        out.extend_from_slice(&self.head);
        for t in &self.tiles {
            out.extend_from_slice(&t.records);
        }
        out
    }

    /// The tile table.
    pub fn table(&self) -> Vec<Tile> {
        self.tiles.iter().map(|t| t.tile.clone()).collect()
    }
}

/// The drafts of the scenes published last, each at its committed version (a draft is put back
/// only after the store commits the version it is the pack of), bounded by the instances held.
#[derive(Debug)]
pub struct PackDrafts {
    entries: std::sync::Mutex<std::collections::VecDeque<(String, u64, PackDraft)>>,
    /// Instances held in all, at most.
    limit: usize,
}

impl Default for PackDrafts {
    fn default() -> Self {
        Self::with_limit(DRAFT_INSTANCES)
    }
}

/// Instances the drafts hold in all (about 40 bytes each in memory, plus 28 of records).
pub const DRAFT_INSTANCES: usize = 400_000;

impl PackDrafts {
    /// Drafts holding at most `limit` instances in all.
    pub fn with_limit(limit: usize) -> Self {
        Self {
            entries: std::sync::Mutex::default(),
            limit,
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, std::collections::VecDeque<(String, u64, PackDraft)>> {
        self.entries.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Takes scene `id`'s draft (of the scene made at `created_unix`), if held.
    pub fn take(&self, id: &str, created_unix: u64) -> Option<PackDraft> {
        let mut e = self.lock();
        let at = e.iter().position(|(i, c, _)| i == id && *c == created_unix)?;
        e.remove(at).map(|(_, _, d)| d)
    }

    /// Keeps scene `id`'s draft of a committed version, in place of any other of the scene.
    pub fn put(&self, id: &str, created_unix: u64, draft: PackDraft) {
        let mut e = self.lock();
        e.retain(|(i, _, _)| i != id);
        if draft.instance_count() > self.limit {
            return;
        }
        e.push_front((id.to_string(), created_unix, draft));
        let mut held = 0;
        e.retain(|(_, _, d)| {
            held += d.instance_count();
            held <= self.limit
        });
    }

    /// Drops scene `id`'s draft.
    pub fn forget(&self, id: &str) {
        self.lock().retain(|(i, _, _)| i != id);
    }
}

#[cfg(test)]
#[path = "pack_draft_tests.rs"]
mod tests;

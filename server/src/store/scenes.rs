//! Scenes: sets of tree instances over an area, their edits and versions, behind the
//! [`SceneStore`] trait (SQLite now: [`super::sqlite::SqliteStore`]; PostgreSQL later, so several
//! server processes can share one database).
//!
//! The contract every store keeps: each method is atomic; a refused call changes nothing; the
//! quotas and the retention of [`Limits`] are checked in the same transaction as the change they
//! limit (so concurrent creations cannot pass a quota together); a version commits only if the
//! scene is still at the version the edit was applied to (compare-and-swap on the version number),
//! so no version is ever written twice, whichever process writes.

use serde::{Deserialize, Serialize};

/// Most instances in one scene.
pub const MAX_INSTANCES: usize = 200_000;
/// Most operations (adds + moves + removes) in one edit batch.
pub const MAX_BATCH: usize = 10_000;
/// Largest scene extent along x or z, metres.
pub const MAX_EXTENT_M: f64 = 100_000.0;
/// Largest absolute coordinate, metres.
pub const MAX_COORD_M: f64 = 1_000_000.0;
/// Largest absolute height of an instance, metres.
pub const MAX_HEIGHT_M: f32 = 10_000.0;
/// Scale range of an instance.
pub const SCALE_RANGE: (f32, f32) = (0.01, 100.0);
/// Most scenes one store holds.
pub const MAX_SCENES: usize = 10_000;

/// Quotas and retention, enforced by the store atomically with the change they limit.
///
/// Quotas are per owner (who created the scene: a creation token, or a client address in open
/// mode); the empty owner (the server's own scenes, and scenes created before owners existed) has
/// none. Retention keeps, of each scene's versions, the current one, the pinned ones, the last
/// `keep_versions`, and those younger than `keep_secs` (0: no age rule); the rest are pruned.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limits {
    /// Most scenes one owner holds.
    pub max_scenes: u64,
    /// Most instances in one of an owner's scenes (at most [`MAX_INSTANCES`]).
    pub max_instances: usize,
    /// Most bytes the kept versions of one owner's scenes take on disk (packs and manifests).
    pub max_bytes: u64,
    /// Versions kept by count (at least 1: the current one).
    pub keep_versions: u64,
    /// Versions kept by age, seconds (0: none by age).
    pub keep_secs: u64,
    /// Most pinned versions per scene.
    pub max_pins: usize,
}

impl Default for Limits {
    fn default() -> Self {
        Self {
            max_scenes: 100,
            max_instances: MAX_INSTANCES,
            max_bytes: 2 << 30,
            keep_versions: 20,
            keep_secs: 0,
            max_pins: 16,
        }
    }
}

impl Limits {
    /// No quota (the server's own scenes); retention as given.
    pub fn unlimited(retention: &Self) -> Self {
        Self {
            max_scenes: u64::MAX,
            max_instances: MAX_INSTANCES,
            max_bytes: u64::MAX,
            ..*retention
        }
    }
}

/// A scene's ground area: `min` and `max` as `[x, z]` in metres.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Bounds {
    /// Minimum x, z.
    pub min: [f64; 2],
    /// Maximum x, z.
    pub max: [f64; 2],
}

impl Bounds {
    /// Checks the bounds are finite, ordered and not huge.
    pub fn validate(&self) -> Result<(), String> {
        let all = [self.min[0], self.min[1], self.max[0], self.max[1]];
        if !all.iter().all(|v| v.is_finite() && v.abs() <= MAX_COORD_M) {
            return Err(format!("bounds must be finite and within ±{MAX_COORD_M} m"));
        }
        for a in 0..2 {
            let extent = self.max[a] - self.min[a];
            if !(extent > 0.0 && extent <= MAX_EXTENT_M) {
                return Err(format!(
                    "bounds: max must exceed min by at most {MAX_EXTENT_M} m on both axes"
                ));
            }
        }
        Ok(())
    }

    /// True when `(x, z)` lies inside (edges included).
    pub fn contains(&self, x: f32, z: f32) -> bool {
        let (x, z) = (f64::from(x), f64::from(z));
        x >= self.min[0] && x <= self.max[0] && z >= self.min[1] && z <= self.max[1]
    }

    /// As `f32` min x, min z, max x, max z.
    pub fn as_f32(&self) -> [f32; 4] {
        [
            self.min[0] as f32,
            self.min[1] as f32,
            self.max[0] as f32,
            self.max[1] as f32,
        ]
    }

    /// Area in square metres.
    pub fn area_m2(&self) -> f64 {
        (self.max[0] - self.min[0]) * (self.max[1] - self.min[1])
    }
}

/// A tree instance.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Instance {
    /// Id, unique within the scene, never reused.
    pub id: u32,
    /// Model name (a baked tree under `/assets/trees/`).
    pub model: String,
    /// x, y, z in metres, y up.
    pub position: [f32; 3],
    /// Rotation about +y, radians.
    pub rotation: f32,
    /// Uniform scale.
    pub scale: f32,
}

/// A new instance (no id yet).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NewInstance {
    /// Model name.
    pub model: String,
    /// x, y, z in metres.
    pub position: [f32; 3],
    /// Rotation about +y, radians (default 0).
    #[serde(default)]
    pub rotation: f32,
    /// Uniform scale (default 1).
    #[serde(default = "one")]
    pub scale: f32,
}

fn one() -> f32 {
    1.0
}

/// One instance of an [`InstanceTable`]: the model as an index into its `models`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct InstanceRow {
    /// Id.
    pub id: u32,
    /// Index into [`InstanceTable::models`].
    pub model: u32,
    /// x, y, z in metres.
    pub position: [f32; 3],
    /// Rotation about +y, radians.
    pub rotation: f32,
    /// Uniform scale.
    pub scale: f32,
}

/// A scene's instances at one version, by id, read atomically with that version. Compact (28
/// bytes an instance, each model name once) so that one copy can be shared by every response
/// streaming the list, instead of a list of [`Instance`]s and its JSON per request.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct InstanceTable {
    /// The version these are the instances of.
    pub version: u64,
    /// The scene's creation time (tells a scene from a later one of the same id).
    pub created_unix: u64,
    /// The model names the rows refer to.
    pub models: Vec<String>,
    /// The instances, by id.
    pub rows: Vec<InstanceRow>,
}

/// Moves (and optionally re-rotates or re-scales) an instance.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MoveInstance {
    /// Instance id.
    pub id: u32,
    /// New position.
    pub position: [f32; 3],
    /// New rotation, if given.
    #[serde(default)]
    pub rotation: Option<f32>,
    /// New scale, if given.
    #[serde(default)]
    pub scale: Option<f32>,
}

/// One batch of instance edits, applied atomically as one new version.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EditBatch {
    /// Instances to add.
    #[serde(default)]
    pub add: Vec<NewInstance>,
    /// Instances to move.
    #[serde(default, rename = "move")]
    pub moves: Vec<MoveInstance>,
    /// Instance ids to remove.
    #[serde(default)]
    pub remove: Vec<u32>,
    /// When set, the edit applies only if the scene is still at this version (optimistic
    /// concurrency); otherwise it fails with a conflict.
    #[serde(default)]
    pub base_version: Option<u64>,
}

impl EditBatch {
    /// Operations in the batch.
    pub fn len(&self) -> usize {
        self.add.len() + self.moves.len() + self.remove.len()
    }

    /// True for an empty batch.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// A scene as listed and described (no secrets).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SceneMeta {
    /// Id (`[a-z0-9-]{1,64}`).
    pub id: String,
    /// Display name.
    pub name: String,
    /// Readable without a token.
    pub public: bool,
    /// Ground area.
    pub bounds: Bounds,
    /// Current version (1 after creation, +1 per edit).
    pub version: u64,
    /// Instances in the current version.
    pub instance_count: u64,
    /// Creation time, seconds since the Unix epoch.
    pub created_unix: u64,
}

/// What the store keeps about a scene's tokens: SHA-256 hashes only.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SceneAuth {
    /// Hash of the write token.
    pub write_hash: [u8; 32],
    /// Hash of the read token (private scenes).
    pub read_hash: Option<[u8; 32]>,
}

/// A scene to create.
#[derive(Debug, Clone)]
pub struct NewScene {
    /// Id.
    pub id: String,
    /// Name.
    pub name: String,
    /// Public or private.
    pub public: bool,
    /// Bounds.
    pub bounds: Bounds,
    /// Token hashes.
    pub auth: SceneAuth,
    /// Whose quota it counts against (empty: the server's own, no quota).
    pub owner: String,
    /// Its terrain from the first version on (the manifest's `terrain` object, JSON; its file
    /// written by the caller), or none.
    pub terrain: Option<String>,
}

/// What publishing a version wrote.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Published {
    /// The version's manifest (JSON).
    pub manifest: String,
    /// Bytes its files take.
    pub bytes: u64,
    /// Its files, as paths under the assets folder (the URL after `/assets/`).
    pub files: Vec<String>,
}

/// A version that retention removed: its files are the caller's to delete.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Pruned {
    /// Scene id.
    pub scene: String,
    /// Version.
    pub version: u64,
    /// Its files (as in [`Published::files`]).
    pub files: Vec<String>,
}

/// An applied edit: the scene at its new version, and the versions retention removed.
#[derive(Debug, Clone, PartialEq)]
pub struct Edited {
    /// The scene now.
    pub meta: SceneMeta,
    /// Versions pruned by the same transaction.
    pub pruned: Vec<Pruned>,
}

/// One kept version of a scene.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct VersionInfo {
    /// Version number.
    pub version: u64,
    /// When it was made, seconds since the Unix epoch.
    pub created_unix: u64,
    /// Bytes its files take.
    pub bytes: u64,
    /// Kept whatever the retention.
    pub pinned: bool,
}

/// A scene's current version and the files of every version it keeps (garbage collection keeps
/// these and deletes the rest).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SceneFiles {
    /// Scene id.
    pub id: String,
    /// Current version.
    pub version: u64,
    /// Files of the kept versions.
    pub files: Vec<String>,
}

/// Why a store operation failed.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// No such scene.
    #[error("scene {0:?} not found")]
    NotFound(String),
    /// The id is taken.
    #[error("scene {0:?} already exists")]
    Exists(String),
    /// The edit names instances that do not exist, or the same instance twice.
    #[error("{0}")]
    Invalid(String),
    /// `base_version` is not the current version.
    #[error("scene is at version {current}, not {expected}")]
    Conflict {
        /// Current version.
        current: u64,
        /// The version the edit was based on.
        expected: u64,
    },
    /// A limit was hit.
    #[error("{0}")]
    Limit(String),
    /// The scene does not keep this version (never made, or pruned).
    #[error("the scene has no version {0} (never made, or no longer kept)")]
    NoVersion(u64),
    /// An owner's quota was hit.
    #[error("{0}")]
    Quota(String),
    /// Publishing the new version failed.
    #[error("publishing the new version: {0}")]
    Publish(String),
    /// The database failed.
    #[error("database: {0}")]
    Database(String),
    /// The database cannot be reached (a replica that lost it answers 503 until it is back).
    #[error("the scene database is unavailable: {0}")]
    Unavailable(String),
}

/// Writes a new version's files, given its metadata and full instance list, before the store
/// commits it; returns what it wrote. If it fails, nothing is changed. If the store then does not
/// commit (a quota, a lost compare-and-swap, a database error), the files are the caller's to
/// delete (those the committed version does not name).
/// [`Changes`] says what the version changed against the one before, so that a publisher holding
/// that version's files in memory can update them instead of rebuilding them.
pub type Publish<'a> = &'a mut dyn FnMut(&SceneMeta, &[Instance], &Changes) -> Result<Published, StoreError>;

/// What a version changed against the version before it.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Changes {
    /// The version the edit was applied to (`None`: a first version).
    pub base_version: Option<u64>,
    /// The old state of every moved or removed instance.
    pub before: Vec<Instance>,
    /// The new state of every moved or added instance.
    pub after: Vec<Instance>,
    /// The scene's terrain at the new version, as the store keeps it (the manifest's `terrain`
    /// object, JSON); none: flat ground. Read by the store with the version it builds on.
    pub terrain: Option<std::sync::Arc<str>>,
}

/// Where scenes live. Every method is atomic.
pub trait SceneStore: Send + Sync + std::fmt::Debug {
    /// Creates a scene with its first version (the given instances, ids 1..=n), within the
    /// owner's quotas.
    fn create(
        &self,
        scene: &NewScene,
        instances: &[NewInstance],
        limits: &Limits,
        publish: Publish<'_>,
    ) -> Result<SceneMeta, StoreError>;
    /// Every scene, public first, by id.
    fn list(&self) -> Result<Vec<SceneMeta>, StoreError>;
    /// One scene.
    fn get(&self, id: &str) -> Result<Option<SceneMeta>, StoreError>;
    /// A scene's token hashes.
    fn auth(&self, id: &str) -> Result<Option<SceneAuth>, StoreError>;
    /// The current instances, by id.
    fn instances(&self, id: &str) -> Result<Vec<Instance>, StoreError>;
    /// The current version and its instances, read together.
    fn instance_table(&self, id: &str) -> Result<InstanceTable, StoreError>;
    /// Applies a (validated) batch as a new version, within the owner's quotas, and prunes the
    /// versions the retention no longer keeps.
    fn edit(&self, id: &str, batch: &EditBatch, limits: &Limits, publish: Publish<'_>) -> Result<Edited, StoreError>;
    /// A version's manifest (the current one for `None`).
    fn manifest(&self, id: &str, version: Option<u64>) -> Result<Option<String>, StoreError>;
    /// Deletes a scene and its versions; false if it did not exist.
    fn delete(&self, id: &str) -> Result<bool, StoreError>;
    /// The versions a scene keeps, oldest first.
    fn versions(&self, id: &str) -> Result<Vec<VersionInfo>, StoreError>;
    /// Pins (`pin`) or unpins a version (the current one for `None`), at most
    /// `limits.max_pins` per scene; returns the pinned versions.
    fn pin(&self, id: &str, version: Option<u64>, pin: bool, limits: &Limits) -> Result<Vec<u64>, StoreError>;
    /// Applies the retention to every scene at time `now_unix` (age rule, unpinned versions).
    fn prune(&self, limits: &Limits, now_unix: u64) -> Result<Vec<Pruned>, StoreError>;
    /// Every scene's current version and the files of its kept versions.
    fn files(&self) -> Result<Vec<SceneFiles>, StoreError>;
    /// The scene's flight table (seed 002's visual-redundancy table, JSON text as stored); `None`
    /// when it has none, [`StoreError::NotFound`] for an unknown scene.
    fn flight_table(&self, id: &str) -> Result<Option<String>, StoreError>;
    /// Sets (replaces) the scene's flight table: `json` is a checked table's text
    /// (`FlightTable::to_json`). A scene property: no new version; deleted with the scene.
    fn set_flight_table(&self, id: &str, json: &str) -> Result<(), StoreError>;
    /// Removes the scene's flight table; false when it had none.
    fn clear_flight_table(&self, id: &str) -> Result<bool, StoreError>;
    /// The scene's terrain (the manifest's `terrain` object, JSON text as stored); `None` when it
    /// has none, [`StoreError::NotFound`] for an unknown scene.
    fn terrain(&self, id: &str) -> Result<Option<String>, StoreError>;
    /// Sets (`Some`, replacing any) or removes (`None`) the scene's terrain and makes a new version
    /// of the same instances on it, as one edit (same locks, compare-and-swap, retention and
    /// quotas as [`Self::edit`]); `publish` gets the new terrain in [`Changes::terrain`]. Every
    /// later version keeps the terrain until it is set again.
    fn set_terrain(
        &self,
        id: &str,
        terrain: Option<&str>,
        limits: &Limits,
        publish: Publish<'_>,
    ) -> Result<Edited, StoreError>;
    /// True when other processes (server replicas) use the same database and data folder: files
    /// in flight may be theirs, so no file is swept without the grace period.
    fn shared(&self) -> bool {
        false
    }
    /// Whether the database answers (the last operation or check reached it).
    fn available(&self) -> bool {
        true
    }
    /// Calls `on_change` for every scene change other processes make (replicas on one database);
    /// a store only this process writes calls nothing.
    fn watch(&self, on_change: Box<dyn Fn(SceneChange) + Send + Sync>) {
        let _ = on_change;
    }
    /// Passes a presence payload to the other processes watching this store (they get it as
    /// [`SceneChange::Presence`]); best effort, never blocks: dropped while the database is away
    /// or behind. A store only this process uses drops it.
    fn relay_presence(&self, payload: String) {
        let _ = payload;
    }
}

/// A change another process made to a scene.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum SceneChange {
    /// A new version was committed.
    Version {
        /// Scene id.
        scene: String,
        /// The new version.
        version: u64,
    },
    /// The scene was deleted.
    Deleted {
        /// Scene id.
        scene: String,
    },
    /// Changes may have been missed (the notifications were cut off and are back): what viewers
    /// were told should be checked against the store.
    Resync,
    /// Presence another replica relayed ([`SceneStore::relay_presence`]); its format is the live
    /// module's.
    Presence {
        /// The payload as sent.
        payload: String,
    },
}

/// Checks a scene id: `[a-z0-9-]{1,64}`.
pub fn valid_scene_id(id: &str) -> bool {
    !id.is_empty()
        && id.len() <= 64
        && id
            .bytes()
            .all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b == b'-')
}

fn check_instance(what: &str, position: [f32; 3], rotation: f32, scale: f32, bounds: &Bounds) -> Result<(), String> {
    if !position.iter().all(|v| v.is_finite()) {
        return Err(format!("{what}: position must be finite"));
    }
    if !bounds.contains(position[0], position[2]) {
        return Err(format!(
            "{what}: position ({}, {}) is outside the scene bounds [{}, {}]..[{}, {}] (x, z)",
            position[0], position[2], bounds.min[0], bounds.min[1], bounds.max[0], bounds.max[1]
        ));
    }
    if position[1].abs() > MAX_HEIGHT_M {
        return Err(format!("{what}: height must be within ±{MAX_HEIGHT_M} m"));
    }
    if !rotation.is_finite() {
        return Err(format!("{what}: rotation must be finite"));
    }
    if !(scale.is_finite() && scale >= SCALE_RANGE.0 && scale <= SCALE_RANGE.1) {
        return Err(format!(
            "{what}: scale must be within [{}, {}]",
            SCALE_RANGE.0, SCALE_RANGE.1
        ));
    }
    Ok(())
}

/// Checks new instances against the bounds and the known models.
pub fn validate_new(
    instances: &[NewInstance],
    bounds: &Bounds,
    known_model: &dyn Fn(&str) -> bool,
) -> Result<(), String> {
    for (k, i) in instances.iter().enumerate() {
        let what = format!("add[{k}]");
        if !known_model(&i.model) {
            return Err(format!("{what}: unknown model {:?}", i.model));
        }
        check_instance(&what, i.position, i.rotation, i.scale, bounds)?;
    }
    Ok(())
}

/// Checks a batch's values (ids are checked by the store, which knows them).
pub fn validate_batch(batch: &EditBatch, bounds: &Bounds, known_model: &dyn Fn(&str) -> bool) -> Result<(), String> {
    if batch.is_empty() {
        return Err("empty batch: give at least one of add, move, remove".into());
    }
    if batch.len() > MAX_BATCH {
        return Err(format!(
            "batch of {} operations exceeds the limit of {MAX_BATCH}",
            batch.len()
        ));
    }
    validate_new(&batch.add, bounds, known_model)?;
    for (k, m) in batch.moves.iter().enumerate() {
        check_instance(
            &format!("move[{k}]"),
            m.position,
            m.rotation.unwrap_or(0.0),
            m.scale.unwrap_or(1.0),
            bounds,
        )?;
    }
    Ok(())
}

/// Applies a batch to an instance list (sorted by id) in place; `next_id` is the next free id.
/// Returns the next free id after it and what changed (`base_version` left `None`). Fails,
/// changing nothing, on unknown or repeated ids and on more instances than [`MAX_INSTANCES`]
/// ([`StoreError::Limit`]) or than the owner's `max_instances` ([`StoreError::Quota`]).
pub fn apply_batch(
    list: &mut Vec<Instance>,
    next_id: u32,
    batch: &EditBatch,
    max_instances: usize,
) -> Result<(u32, Changes), StoreError> {
    let find = |list: &[Instance], id: u32| list.binary_search_by_key(&id, |i| i.id).ok();
    let mut touched = std::collections::HashSet::with_capacity(batch.moves.len() + batch.remove.len());
    for &id in batch.moves.iter().map(|m| &m.id).chain(&batch.remove) {
        if find(list, id).is_none() {
            return Err(StoreError::Invalid(format!("instance {id} does not exist")));
        }
        if !touched.insert(id) {
            return Err(StoreError::Invalid(format!(
                "instance {id} appears more than once in the batch"
            )));
        }
    }
    let total = list.len() - batch.remove.len() + batch.add.len();
    if total > MAX_INSTANCES {
        return Err(StoreError::Limit(format!(
            "a scene holds at most {MAX_INSTANCES} instances; this edit would make {total}"
        )));
    }
    if total > max_instances {
        return Err(StoreError::Quota(format!(
            "quota: this owner's scenes hold at most {max_instances} instances each; this edit would make {total}"
        )));
    }
    let last_id = u32::try_from(batch.add.len())
        .ok()
        .and_then(|n| next_id.checked_add(n))
        .ok_or_else(|| StoreError::Limit("instance ids exhausted".into()))?;
    let mut changes = Changes::default();
    if !batch.remove.is_empty() {
        let removed: std::collections::HashSet<u32> = batch.remove.iter().copied().collect();
        list.retain(|i| {
            let gone = removed.contains(&i.id);
            if gone {
                changes.before.push(i.clone());
            }
            !gone
        });
    }
    for m in &batch.moves {
        if let Some(k) = find(list, m.id) {
            let i = &mut list[k];
            changes.before.push(i.clone());
            i.position = m.position;
            if let Some(r) = m.rotation {
                i.rotation = r;
            }
            if let Some(s) = m.scale {
                i.scale = s;
            }
            changes.after.push(i.clone());
        }
    }
    for (id, a) in (next_id..last_id).zip(&batch.add) {
        let i = Instance {
            id,
            model: a.model.clone(),
            position: a.position,
            rotation: a.rotation,
            scale: a.scale,
        };
        changes.after.push(i.clone());
        list.push(i);
    }
    Ok((last_id, changes))
}

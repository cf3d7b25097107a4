//! [`SceneStore`] on an embedded SQLite database (one file, one process).
//!
//! Concurrency: one writer connection behind a mutex, held only to commit (instance rows, the
//! version row, quotas, retention: milliseconds, whatever the scene's size); reads go to a small
//! pool of other connections, which in WAL mode never wait for the writer. Edits of one scene are
//! serialised by a per-scene lock; edits of different scenes read, build and write their packs in
//! parallel, outside the writer's lock, and a version commits only if its scene is still at the
//! version the edit was applied to (compare-and-swap). Durability: WAL with `synchronous = FULL`.
//! The schema is versioned (`PRAGMA user_version`), migrated forward at open (`sqlite_schema.rs`).

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, MutexGuard};

use rusqlite::{Connection, OptionalExtension, TransactionBehavior, params};

use super::scenes::{
    Bounds, EditBatch, Edited, Instance, InstanceRow, InstanceTable, Limits, MAX_INSTANCES, MAX_SCENES, NewInstance,
    NewScene, Pruned, Publish, SceneAuth, SceneFiles, SceneMeta, SceneStore, StoreError, VersionInfo, apply_batch,
};
use super::sqlite_schema::{join_files, migrate, split_files};

// `synchronous = FULL`: every commit syncs the WAL, so an acknowledged edit survives a power cut
// (NORMAL survives a crash of the process only); see docs/server.md for the cost.
const PRAGMAS: &str = "
PRAGMA journal_mode = WAL;
PRAGMA synchronous = FULL;
PRAGMA foreign_keys = ON;
PRAGMA busy_timeout = 10000;
";

/// Idle read connections kept open.
const MAX_IDLE_READERS: usize = 8;

/// Compare-and-swap attempts of one edit before it gives up with a conflict (another process
/// editing the same scene each time).
const CAS_ATTEMPTS: usize = 3;

/// SQLite scene store.
#[derive(Debug)]
pub struct SqliteStore {
    writer: Mutex<Connection>,
    /// The database file; `None` in memory, where reads share the writer.
    path: Option<PathBuf>,
    readers: Mutex<Vec<Connection>>,
    scene_locks: super::locks::SceneLocks,
    /// The instances of the scenes edited last, at their current version.
    recent: super::recent::Recent,
}

impl From<rusqlite::Error> for StoreError {
    fn from(e: rusqlite::Error) -> Self {
        StoreError::Database(e.to_string())
    }
}

pub(super) fn now_unix() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs())
}

const META_COLS: &str = "id, name, public, min_x, min_z, max_x, max_z, version, instance_count, created_unix";

fn meta_row(r: &rusqlite::Row<'_>) -> rusqlite::Result<SceneMeta> {
    Ok(SceneMeta {
        id: r.get(0)?,
        name: r.get(1)?,
        public: r.get(2)?,
        bounds: Bounds {
            min: [r.get(3)?, r.get(4)?],
            max: [r.get(5)?, r.get(6)?],
        },
        version: r.get::<_, i64>(7)? as u64,
        instance_count: r.get::<_, i64>(8)? as u64,
        created_unix: r.get::<_, i64>(9)? as u64,
    })
}

fn hash_of(v: Option<Vec<u8>>) -> Option<[u8; 32]> {
    v.and_then(|v| <[u8; 32]>::try_from(v.as_slice()).ok())
}

use super::locks::lock;

impl SqliteStore {
    /// Opens (creating if needed) the database file, migrating its schema forward.
    pub fn open(path: &Path) -> Result<Self, StoreError> {
        Self::init(Connection::open(path)?, Some(path.to_path_buf()))
    }

    /// An in-memory database (tests): reads share the writer's connection.
    pub fn in_memory() -> Result<Self, StoreError> {
        Self::init(Connection::open_in_memory()?, None)
    }

    fn init(mut conn: Connection, path: Option<PathBuf>) -> Result<Self, StoreError> {
        conn.execute_batch(PRAGMAS)?;
        migrate(&mut conn)?;
        Ok(Self {
            writer: Mutex::new(conn),
            path,
            readers: Mutex::new(Vec::new()),
            scene_locks: super::locks::SceneLocks::default(),
            recent: super::recent::Recent::default(),
        })
    }

    fn write(&self) -> MutexGuard<'_, Connection> {
        lock(&self.writer)
    }

    /// Runs `f` on a read connection, inside one read transaction (one snapshot).
    fn read<T>(&self, f: impl FnOnce(&Connection) -> Result<T, StoreError>) -> Result<T, StoreError> {
        let Some(path) = &self.path else {
            let c = self.write();
            let tx = c.unchecked_transaction()?;
            return f(&tx);
        };
        let idle = lock(&self.readers).pop();
        let conn = if let Some(c) = idle {
            c
        } else {
            let c = Connection::open(path)?;
            c.execute_batch("PRAGMA busy_timeout = 10000; PRAGMA query_only = 1;")?;
            c
        };
        let out = {
            let tx = conn.unchecked_transaction()?;
            f(&tx)
        };
        let mut idle = lock(&self.readers);
        if idle.len() < MAX_IDLE_READERS {
            idle.push(conn);
        }
        out
    }

    /// The lock that serialises changes to scene `id` in this process.
    fn scene_lock(&self, id: &str) -> Arc<Mutex<()>> {
        self.scene_locks.get(id)
    }
}

fn get_meta(c: &Connection, id: &str) -> Result<Option<SceneMeta>, StoreError> {
    c.query_row(&format!("SELECT {META_COLS} FROM scenes WHERE id = ?1"), [id], meta_row)
        .optional()
        .map_err(StoreError::from)
}

/// Position, rotation and scale of an instance row (`id, model, x, y, z, rotation, scale`).
fn placement(r: &rusqlite::Row<'_>) -> rusqlite::Result<([f32; 3], f32, f32)> {
    Ok((
        [
            r.get::<_, f64>(2)? as f32,
            r.get::<_, f64>(3)? as f32,
            r.get::<_, f64>(4)? as f32,
        ],
        r.get::<_, f64>(5)? as f32,
        r.get::<_, f64>(6)? as f32,
    ))
}

fn load_instances(c: &Connection, id: &str) -> Result<Vec<Instance>, StoreError> {
    let mut st =
        c.prepare_cached("SELECT id, model, x, y, z, rotation, scale FROM instances WHERE scene = ?1 ORDER BY id")?;
    let rows = st.query_map([id], |r| {
        let (position, rotation, scale) = placement(r)?;
        Ok(Instance {
            id: r.get::<_, i64>(0)? as u32,
            model: r.get(1)?,
            position,
            rotation,
            scale,
        })
    })?;
    rows.collect::<Result<_, _>>().map_err(StoreError::from)
}

fn insert_instance(c: &Connection, scene: &str, i: &Instance) -> Result<(), StoreError> {
    c.prepare_cached(
        "INSERT INTO instances (scene, id, model, x, y, z, rotation, scale) VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8)",
    )
    .and_then(|mut st| {
        st.execute(params![
            scene,
            i64::from(i.id),
            i.model,
            f64::from(i.position[0]),
            f64::from(i.position[1]),
            f64::from(i.position[2]),
            f64::from(i.rotation),
            f64::from(i.scale)
        ])
    })?;
    Ok(())
}

fn owner_of(c: &Connection, id: &str) -> Result<Option<(String, u32)>, StoreError> {
    c.query_row("SELECT owner, next_id FROM scenes WHERE id = ?1", [id], |r| {
        Ok((r.get(0)?, r.get::<_, i64>(1)? as u32))
    })
    .optional()
    .map_err(StoreError::from)
}

fn owner_bytes(c: &Connection, owner: &str) -> Result<u64, StoreError> {
    let n: i64 = c.query_row(
        "SELECT COALESCE(SUM(v.bytes), 0) FROM versions v JOIN scenes s ON s.id = v.scene WHERE s.owner = ?1",
        [owner],
        |r| r.get(0),
    )?;
    Ok(n.max(0) as u64)
}

fn check_bytes(c: &Connection, owner: &str, limits: &Limits) -> Result<(), StoreError> {
    if owner.is_empty() {
        return Ok(());
    }
    let used = owner_bytes(c, owner)?;
    if used > limits.max_bytes {
        return Err(StoreError::Quota(format!(
            "quota: this would keep {used} bytes of scene versions for this owner, over the limit of {}",
            limits.max_bytes
        )));
    }
    Ok(())
}

pub(super) fn max_instances(owner: &str, limits: &Limits) -> usize {
    if owner.is_empty() {
        MAX_INSTANCES
    } else {
        limits.max_instances.min(MAX_INSTANCES)
    }
}

fn insert_version(
    c: &Connection,
    id: &str,
    version: u64,
    p: &super::scenes::Published,
    now: u64,
) -> Result<(), StoreError> {
    c.execute(
        "INSERT INTO versions (scene, version, manifest, created_unix, bytes, files) VALUES (?1, ?2, ?3, ?4, ?5, ?6)",
        params![
            id,
            version as i64,
            p.manifest,
            now as i64,
            p.bytes as i64,
            join_files(&p.files)
        ],
    )?;
    Ok(())
}

/// Deletes the versions the retention no longer keeps (of scene `id`, or of every scene) and
/// returns them.
fn prune_where(c: &Connection, id: Option<&str>, limits: &Limits, now: u64) -> Result<Vec<Pruned>, StoreError> {
    let keep = limits.keep_versions.max(1) as i64;
    let age = if limits.keep_secs == 0 {
        i64::MAX
    } else {
        now.saturating_sub(limits.keep_secs) as i64
    };
    let cond = "v.pinned = 0 AND v.version < s.version AND v.version <= s.version - ?1 AND v.created_unix < ?2 \
                AND (?3 IS NULL OR s.id = ?3)";
    let gone: Vec<Pruned> = {
        let mut st = c.prepare_cached(&format!(
            "SELECT v.scene, v.version, v.files FROM versions v JOIN scenes s ON s.id = v.scene WHERE {cond}"
        ))?;
        let rows = st.query_map(params![keep, age, id], |r| {
            Ok(Pruned {
                scene: r.get(0)?,
                version: r.get::<_, i64>(1)? as u64,
                files: split_files(&r.get::<_, String>(2)?),
            })
        })?;
        rows.collect::<Result<_, _>>()?
    };
    for p in &gone {
        c.execute(
            "DELETE FROM versions WHERE scene = ?1 AND version = ?2",
            params![p.scene, p.version as i64],
        )?;
    }
    Ok(gone)
}

impl SqliteStore {
    /// [`SceneStore::edit`], and with `terrain` given, [`SceneStore::set_terrain`]: the terrain
    /// the version stands on is read from the snapshot it builds on, or is the one given, written
    /// in the version's transaction.
    fn edit_with(
        &self,
        id: &str,
        batch: &EditBatch,
        limits: &Limits,
        publish: Publish<'_>,
        terrain: super::terrains::TerrainChange<'_>,
    ) -> Result<Edited, StoreError> {
        let scene_lock = self.scene_lock(id);
        let _one_writer = lock(&scene_lock);
        let mut attempt = 0;
        loop {
            attempt += 1;
            // Read and build from one snapshot, off the writer's lock; the instances from the
            // last edit's list when it made this version.
            let (mut meta, owner, next_id, current, ground) = self.read(|c| {
                let meta = get_meta(c, id)?.ok_or_else(|| StoreError::NotFound(id.to_string()))?;
                let (owner, next_id) = owner_of(c, id)?.ok_or_else(|| StoreError::NotFound(id.to_string()))?;
                let ground = match terrain {
                    super::terrains::TerrainChange::Set(t) => t.map(Arc::from),
                    super::terrains::TerrainChange::Keep => super::terrains::sqlite_get(c, id)?.map(Arc::from),
                };
                let current = match self.recent.take(id, meta.version, meta.created_unix) {
                    Some(list) => list,
                    None => Arc::new(load_instances(c, id)?),
                };
                Ok((meta, owner, next_id, current, ground))
            })?;
            let (read_version, created) = (meta.version, meta.created_unix);
            let keep = |list| self.recent.put(id, read_version, created, list);
            if let Some(expected) = batch.base_version
                && expected != meta.version
            {
                keep(current);
                return Err(StoreError::Conflict {
                    current: meta.version,
                    expected,
                });
            }
            // Applied in place (no copy of the scene) to the list taken from `recent`: a failure
            // after this point leaves the next edit to read the list again.
            let mut list = Arc::unwrap_or_clone(current);
            let (next_id, mut changes) = match apply_batch(&mut list, next_id, batch, max_instances(&owner, limits)) {
                Ok(applied) => applied,
                Err(e) => {
                    keep(Arc::new(list));
                    return Err(e);
                }
            };
            changes.base_version = Some(meta.version);
            changes.terrain = ground;
            let base = meta.version;
            meta.version += 1;
            meta.instance_count = list.len() as u64;
            let published = publish(&meta, &list, &changes)?;
            let now = now_unix();
            let mut c = self.write();
            let tx = c.transaction_with_behavior(TransactionBehavior::Immediate)?;
            let at: Option<i64> = tx
                .query_row("SELECT version FROM scenes WHERE id = ?1", [id], |r| r.get(0))
                .optional()?;
            match at {
                None => return Err(StoreError::NotFound(id.to_string())),
                Some(v) if v as u64 != base => {
                    // Another process committed meanwhile: apply the batch again to its version.
                    if batch.base_version.is_some() || attempt >= CAS_ATTEMPTS {
                        return Err(StoreError::Conflict {
                            current: v as u64,
                            expected: base,
                        });
                    }
                    continue;
                }
                Some(_) => {}
            }
            for rid in &batch.remove {
                tx.prepare_cached("DELETE FROM instances WHERE scene = ?1 AND id = ?2")?
                    .execute(params![id, i64::from(*rid)])?;
            }
            for m in &batch.moves {
                if let Ok(k) = list.binary_search_by_key(&m.id, |i| i.id) {
                    let i = &list[k];
                    tx.prepare_cached(
                        "UPDATE instances SET x = ?3, y = ?4, z = ?5, rotation = ?6, scale = ?7 WHERE scene = ?1 AND id = ?2",
                    )?
                    .execute(params![
                        id,
                        i64::from(i.id),
                        f64::from(i.position[0]),
                        f64::from(i.position[1]),
                        f64::from(i.position[2]),
                        f64::from(i.rotation),
                        f64::from(i.scale)
                    ])?;
                }
            }
            for i in &list[list.len() - batch.add.len()..] {
                insert_instance(&tx, id, i)?;
            }
            tx.execute(
                "UPDATE scenes SET version = ?2, next_id = ?3, instance_count = ?4 WHERE id = ?1 AND version = ?5",
                params![
                    id,
                    meta.version as i64,
                    i64::from(next_id),
                    list.len() as i64,
                    base as i64
                ],
            )?;
            if let super::terrains::TerrainChange::Set(t) = terrain {
                super::terrains::sqlite_put(&tx, id, t)?;
            }
            insert_version(&tx, id, meta.version, &published, now)?;
            let pruned = prune_where(&tx, Some(id), limits, now)?;
            check_bytes(&tx, &owner, limits)?;
            tx.commit()?;
            self.recent.put(id, meta.version, meta.created_unix, Arc::new(list));
            return Ok(Edited { meta, pruned });
        }
    }
}

impl SceneStore for SqliteStore {
    fn create(
        &self,
        scene: &NewScene,
        instances: &[NewInstance],
        limits: &Limits,
        publish: Publish<'_>,
    ) -> Result<SceneMeta, StoreError> {
        let scene_lock = self.scene_lock(&scene.id);
        let _one_writer = lock(&scene_lock);
        let owner = scene.owner.as_str();
        let count_owned = |c: &Connection| -> Result<(), StoreError> {
            if owner.is_empty() {
                return Ok(());
            }
            let n: i64 = c.query_row("SELECT COUNT(*) FROM scenes WHERE owner = ?1", [owner], |r| r.get(0))?;
            if n as u64 >= limits.max_scenes {
                return Err(StoreError::Quota(format!(
                    "quota: this owner has {n} scenes, the most allowed is {}; delete one first",
                    limits.max_scenes
                )));
            }
            Ok(())
        };
        // Checked before publishing too, so that a refused creation writes no file.
        self.read(|c| {
            if get_meta(c, &scene.id)?.is_some() {
                return Err(StoreError::Exists(scene.id.clone()));
            }
            count_owned(c)
        })?;
        let batch = EditBatch {
            add: instances.to_vec(),
            ..EditBatch::default()
        };
        let mut list = Vec::with_capacity(instances.len());
        let (next_id, mut changes) = apply_batch(&mut list, 1, &batch, max_instances(owner, limits))?;
        changes.terrain = scene.terrain.as_deref().map(Arc::from);
        let now = now_unix();
        let meta = SceneMeta {
            id: scene.id.clone(),
            name: scene.name.clone(),
            public: scene.public,
            bounds: scene.bounds,
            version: 1,
            instance_count: list.len() as u64,
            created_unix: now,
        };
        let published = publish(&meta, &list, &changes)?;
        let mut c = self.write();
        let tx = c.transaction_with_behavior(TransactionBehavior::Immediate)?;
        if get_meta(&tx, &scene.id)?.is_some() {
            return Err(StoreError::Exists(scene.id.clone()));
        }
        let count: i64 = tx.query_row("SELECT COUNT(*) FROM scenes", [], |r| r.get(0))?;
        if count as usize >= MAX_SCENES {
            return Err(StoreError::Limit(format!(
                "the server holds at most {MAX_SCENES} scenes"
            )));
        }
        count_owned(&tx)?;
        tx.execute(
            "INSERT INTO scenes (id, name, public, min_x, min_z, max_x, max_z, version, next_id, instance_count, write_hash, read_hash, created_unix, owner)
             VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, 1, ?8, ?9, ?10, ?11, ?12, ?13)",
            params![
                meta.id,
                meta.name,
                meta.public,
                meta.bounds.min[0],
                meta.bounds.min[1],
                meta.bounds.max[0],
                meta.bounds.max[1],
                i64::from(next_id),
                list.len() as i64,
                scene.auth.write_hash.to_vec(),
                scene.auth.read_hash.map(|h| h.to_vec()),
                now as i64,
                owner
            ],
        )?;
        for i in &list {
            insert_instance(&tx, &meta.id, i)?;
        }
        if scene.terrain.is_some() {
            super::terrains::sqlite_put(&tx, &meta.id, scene.terrain.as_deref())?;
        }
        insert_version(&tx, &meta.id, 1, &published, now)?;
        check_bytes(&tx, owner, limits)?;
        tx.commit()?;
        self.recent.put(&meta.id, 1, now, Arc::new(list));
        Ok(meta)
    }

    fn list(&self) -> Result<Vec<SceneMeta>, StoreError> {
        self.read(|c| {
            let mut st = c.prepare_cached(&format!("SELECT {META_COLS} FROM scenes ORDER BY public DESC, id"))?;
            let rows = st.query_map([], meta_row)?;
            rows.collect::<Result<_, _>>().map_err(StoreError::from)
        })
    }

    fn get(&self, id: &str) -> Result<Option<SceneMeta>, StoreError> {
        self.read(|c| get_meta(c, id))
    }

    fn auth(&self, id: &str) -> Result<Option<SceneAuth>, StoreError> {
        let row: Option<(Vec<u8>, Option<Vec<u8>>)> = self.read(|c| {
            c.query_row("SELECT write_hash, read_hash FROM scenes WHERE id = ?1", [id], |r| {
                Ok((r.get(0)?, r.get(1)?))
            })
            .optional()
            .map_err(StoreError::from)
        })?;
        Ok(row.and_then(|(w, r)| {
            Some(SceneAuth {
                write_hash: hash_of(Some(w))?,
                read_hash: hash_of(r),
            })
        }))
    }

    fn instances(&self, id: &str) -> Result<Vec<Instance>, StoreError> {
        self.read(|c| {
            if get_meta(c, id)?.is_none() {
                return Err(StoreError::NotFound(id.to_string()));
            }
            load_instances(c, id)
        })
    }

    fn instance_table(&self, id: &str) -> Result<InstanceTable, StoreError> {
        self.read(|c| {
            let meta = get_meta(c, id)?.ok_or_else(|| StoreError::NotFound(id.to_string()))?;
            let mut st = c.prepare_cached(
                "SELECT id, model, x, y, z, rotation, scale FROM instances WHERE scene = ?1 ORDER BY id",
            )?;
            let mut rows = st.query([id])?;
            let mut table = InstanceTable {
                version: meta.version,
                created_unix: meta.created_unix,
                models: Vec::new(),
                rows: Vec::with_capacity((meta.instance_count as usize).min(MAX_INSTANCES)),
            };
            let mut index = HashMap::<String, u32>::new();
            while let Some(r) = rows.next()? {
                let name = r
                    .get_ref(1)?
                    .as_str()
                    .map_err(|e| StoreError::Database(e.to_string()))?;
                let model = if let Some(&k) = index.get(name) {
                    k
                } else {
                    let k = table.models.len() as u32;
                    table.models.push(name.to_string());
                    index.insert(name.to_string(), k);
                    k
                };
                let (position, rotation, scale) = placement(r)?;
                table.rows.push(InstanceRow {
                    id: r.get::<_, i64>(0)? as u32,
                    model,
                    position,
                    rotation,
                    scale,
                });
            }
            Ok(table)
        })
    }

    fn edit(&self, id: &str, batch: &EditBatch, limits: &Limits, publish: Publish<'_>) -> Result<Edited, StoreError> {
        self.edit_with(id, batch, limits, publish, super::terrains::TerrainChange::Keep)
    }

    fn manifest(&self, id: &str, version: Option<u64>) -> Result<Option<String>, StoreError> {
        self.read(|c| {
            let q = match version {
                Some(v) => c.query_row(
                    "SELECT manifest FROM versions WHERE scene = ?1 AND version = ?2",
                    params![id, v as i64],
                    |r| r.get(0),
                ),
                None => c.query_row(
                    "SELECT v.manifest FROM versions v JOIN scenes s ON s.id = v.scene AND s.version = v.version WHERE s.id = ?1",
                    [id],
                    |r| r.get(0),
                ),
            };
            q.optional().map_err(StoreError::from)
        })
    }

    fn delete(&self, id: &str) -> Result<bool, StoreError> {
        let scene_lock = self.scene_lock(id);
        let _one_writer = lock(&scene_lock);
        self.recent.forget(id);
        Ok(self.write().execute("DELETE FROM scenes WHERE id = ?1", [id])? > 0)
    }

    fn versions(&self, id: &str) -> Result<Vec<VersionInfo>, StoreError> {
        self.read(|c| {
            if get_meta(c, id)?.is_none() {
                return Err(StoreError::NotFound(id.to_string()));
            }
            let mut st = c.prepare_cached(
                "SELECT version, created_unix, bytes, pinned FROM versions WHERE scene = ?1 ORDER BY version",
            )?;
            let rows = st.query_map([id], |r| {
                Ok(VersionInfo {
                    version: r.get::<_, i64>(0)? as u64,
                    created_unix: r.get::<_, i64>(1)? as u64,
                    bytes: r.get::<_, i64>(2)? as u64,
                    pinned: r.get(3)?,
                })
            })?;
            rows.collect::<Result<_, _>>().map_err(StoreError::from)
        })
    }

    fn pin(&self, id: &str, version: Option<u64>, pin: bool, limits: &Limits) -> Result<Vec<u64>, StoreError> {
        let mut c = self.write();
        let tx = c.transaction_with_behavior(TransactionBehavior::Immediate)?;
        let current = get_meta(&tx, id)?
            .ok_or_else(|| StoreError::NotFound(id.to_string()))?
            .version;
        let v = version.unwrap_or(current);
        let was: Option<bool> = tx
            .query_row(
                "SELECT pinned FROM versions WHERE scene = ?1 AND version = ?2",
                params![id, v as i64],
                |r| r.get(0),
            )
            .optional()?;
        let Some(was) = was else {
            return Err(StoreError::NoVersion(v));
        };
        let pinned = |tx: &Connection| -> Result<Vec<u64>, StoreError> {
            let mut st =
                tx.prepare_cached("SELECT version FROM versions WHERE scene = ?1 AND pinned = 1 ORDER BY version")?;
            let rows = st.query_map([id], |r| Ok(r.get::<_, i64>(0)? as u64))?;
            rows.collect::<Result<_, _>>().map_err(StoreError::from)
        };
        if pin && !was && pinned(&tx)?.len() >= limits.max_pins {
            return Err(StoreError::Quota(format!(
                "quota: a scene keeps at most {} pinned versions; unpin one first",
                limits.max_pins
            )));
        }
        tx.execute(
            "UPDATE versions SET pinned = ?3 WHERE scene = ?1 AND version = ?2",
            params![id, v as i64, pin],
        )?;
        let out = pinned(&tx)?;
        tx.commit()?;
        Ok(out)
    }

    fn prune(&self, limits: &Limits, now_unix: u64) -> Result<Vec<Pruned>, StoreError> {
        let mut c = self.write();
        let tx = c.transaction_with_behavior(TransactionBehavior::Immediate)?;
        let gone = prune_where(&tx, None, limits, now_unix)?;
        tx.commit()?;
        Ok(gone)
    }

    fn files(&self) -> Result<Vec<SceneFiles>, StoreError> {
        self.read(|c| {
            let mut st = c.prepare_cached(
                "SELECT s.id, s.version, v.files FROM scenes s JOIN versions v ON v.scene = s.id ORDER BY s.id",
            )?;
            let mut rows = st.query([])?;
            let mut out: Vec<SceneFiles> = Vec::new();
            while let Some(r) = rows.next()? {
                let id: String = r.get(0)?;
                let files = split_files(&r.get::<_, String>(2)?);
                match out.last_mut() {
                    Some(last) if last.id == id => last.files.extend(files),
                    _ => out.push(SceneFiles {
                        id,
                        version: r.get::<_, i64>(1)? as u64,
                        files,
                    }),
                }
            }
            Ok(out)
        })
    }

    fn flight_table(&self, id: &str) -> Result<Option<String>, StoreError> {
        self.read(|c| super::flight_tables::sqlite_get(c, id))
    }

    fn set_flight_table(&self, id: &str, json: &str) -> Result<(), StoreError> {
        super::flight_tables::sqlite_put(&mut self.write(), id, Some(json)).map(drop)
    }

    fn clear_flight_table(&self, id: &str) -> Result<bool, StoreError> {
        super::flight_tables::sqlite_put(&mut self.write(), id, None)
    }

    fn terrain(&self, id: &str) -> Result<Option<String>, StoreError> {
        self.read(|c| super::terrains::sqlite_get(c, id))
    }

    fn set_terrain(
        &self,
        id: &str,
        terrain: Option<&str>,
        limits: &Limits,
        publish: Publish<'_>,
    ) -> Result<Edited, StoreError> {
        self.edit_with(
            id,
            &EditBatch::default(),
            limits,
            publish,
            super::terrains::TerrainChange::Set(terrain),
        )
    }
}

#[cfg(test)]
#[path = "sqlite_tests.rs"]
mod tests;

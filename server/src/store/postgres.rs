//! [`SceneStore`] on PostgreSQL: several server replicas on one database.
//!
//! Same semantics as [`super::SqliteStore`] (the store tests run against both). Concurrency: a
//! small pool of connections per replica. An edit reads and builds its version from one snapshot
//! (`REPEATABLE READ`, read-only) outside any lock, publishes its files, then commits in one
//! transaction that locks the scene's row (`SELECT … FOR UPDATE`) and writes only if the scene is
//! still at the version the edit was built from (compare-and-swap, retried on a lost race as in
//! SQLite). The row lock orders commits of one scene across replicas, and `(scene, version)` is the
//! primary key besides, so no version is ever made twice. Quota checks of one owner and scene
//! creation are serialised by transaction-scoped advisory locks (owner first, then scene row: one
//! order, no deadlock). Durability: PostgreSQL's `synchronous_commit = on` (the WAL is flushed
//! before COMMIT returns), checked at open. The schema is versioned (`canopy_schema`), migrated
//! forward at open under an advisory lock, so replicas starting together migrate once.
//!
//! A replica that cannot reach the database answers [`StoreError::Unavailable`] (HTTP 503); a
//! background thread checks the database once a second; [`SceneStore::available`] says which.

use std::collections::HashMap;
use std::io::Write;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, Weak};

use postgres::types::{FromSql, ToSql};
use postgres::{Client, IsolationLevel, Row, Transaction};

use super::locks::{SceneLocks, lock};
#[cfg(test)]
use super::postgres_conn::change_of;
use super::postgres_conn::{CONNECT_TIMEOUT, Inner, RETRY_EVERY, announce};
use super::scenes::{
    Bounds, EditBatch, Edited, Instance, InstanceRow, InstanceTable, Limits, MAX_INSTANCES, MAX_SCENES, NewInstance,
    NewScene, Pruned, Publish, Published, SceneAuth, SceneChange, SceneFiles, SceneMeta, SceneStore, StoreError,
    VersionInfo, apply_batch,
};
use super::sqlite::{max_instances, now_unix};
use super::sqlite_schema::{join_files, split_files};

/// Advisory lock keys (one namespace for the application): migration, scene creation, and the
/// base of per-owner quota locks (`hashtext(owner)` is added in SQL).
const CREATION_LOCK: i64 = 0x0063_616e_6f70_7902;
/// Namespaces of the two-key advisory locks (`(namespace, hashtext(name))`, a key space apart from
/// the one-key locks above): one owner's quota checks, and one scene's edits.
const OWNER_LOCKS: i32 = 1;
const SCENE_LOCKS: i32 = 2;

/// Compare-and-swap attempts of one edit before it gives up with a conflict.
const CAS_ATTEMPTS: usize = 3;

const META_COLS: &str = "id, name, public, min_x, min_z, max_x, max_z, version, instance_count, created_unix";

/// PostgreSQL scene store.
#[derive(Debug)]
pub struct PostgresStore {
    inner: Arc<Inner>,
    scene_locks: SceneLocks,
    /// The instances of the scenes this replica edited last, keyed by the scene row's
    /// `incarnation` (an entry serves only its exact version and incarnation, so another
    /// replica's edit, or its deletion and re-creation of the id, simply makes it miss).
    recent: super::recent::Recent,
    /// This replica's id in its change notifications (its own are not passed on).
    replica: u64,
    /// Relays this replica's presence to the others.
    presence: super::postgres_conn::PresenceSender,
}

/// Column `i` of a row, a typed error (never a panic) if the schema does not match.
pub(super) fn col<'a, T: FromSql<'a>>(r: &'a Row, i: usize) -> Result<T, StoreError> {
    r.try_get(i)
        .map_err(|e| StoreError::Database(format!("column {i}: {e}")))
}

fn meta_row(r: &Row) -> Result<SceneMeta, StoreError> {
    Ok(SceneMeta {
        id: col(r, 0)?,
        name: col(r, 1)?,
        public: col(r, 2)?,
        bounds: Bounds {
            min: [col(r, 3)?, col(r, 4)?],
            max: [col(r, 5)?, col(r, 6)?],
        },
        version: col::<i64>(r, 7)? as u64,
        instance_count: col::<i64>(r, 8)? as u64,
        created_unix: col::<i64>(r, 9)? as u64,
    })
}

/// A read-only snapshot transaction.
fn snapshot(c: &mut Client) -> Result<Transaction<'_>, StoreError> {
    Ok(c.build_transaction()
        .isolation_level(IsolationLevel::RepeatableRead)
        .read_only(true)
        .start()?)
}

fn get_meta(c: &mut Transaction<'_>, id: &str) -> Result<Option<SceneMeta>, StoreError> {
    c.query_opt(&format!("SELECT {META_COLS} FROM scenes WHERE id = $1"), &[&id])?
        .as_ref()
        .map(meta_row)
        .transpose()
}

fn placement(r: &Row) -> Result<([f32; 3], f32, f32), StoreError> {
    Ok((
        [
            col::<f64>(r, 2)? as f32,
            col::<f64>(r, 3)? as f32,
            col::<f64>(r, 4)? as f32,
        ],
        col::<f64>(r, 5)? as f32,
        col::<f64>(r, 6)? as f32,
    ))
}

/// Calls `each` with every instance row of scene `id` (`id, model, x, y, z, rotation, scale`), by
/// id, streamed rather than collected.
fn each_instance(
    c: &mut Transaction<'_>,
    id: &str,
    mut each: impl FnMut(&Row) -> Result<(), StoreError>,
) -> Result<(), StoreError> {
    use postgres::fallible_iterator::FallibleIterator;
    let mut rows = c.query_raw(
        "SELECT id, model, x, y, z, rotation, scale FROM instances WHERE scene = $1 ORDER BY id",
        [&id as &(dyn ToSql + Sync)],
    )?;
    while let Some(r) = rows.next()? {
        each(&r)?;
    }
    Ok(())
}

fn load_instances(c: &mut Transaction<'_>, id: &str) -> Result<Vec<Instance>, StoreError> {
    let mut out = Vec::new();
    each_instance(c, id, |r| {
        let (position, rotation, scale) = placement(r)?;
        out.push(Instance {
            id: col::<i64>(r, 0)? as u32,
            model: col(r, 1)?,
            position,
            rotation,
            scale,
        });
        Ok(())
    })?;
    Ok(out)
}

/// Escapes a value for COPY's text format.
fn copy_text(s: &str) -> String {
    s.replace('\\', "\\\\")
        .replace('\t', "\\t")
        .replace('\n', "\\n")
        .replace('\r', "\\r")
}

/// Inserts instances with one COPY (a 200,000-instance creation is one round trip, not 200,000).
fn insert_instances(tx: &mut Transaction<'_>, scene: &str, list: &[Instance]) -> Result<(), StoreError> {
    if list.is_empty() {
        return Ok(());
    }
    let scene = copy_text(scene);
    let mut w = tx.copy_in("COPY instances (scene, id, model, x, y, z, rotation, scale) FROM STDIN")?;
    let mut buf = Vec::with_capacity(64 * list.len().min(1 << 16));
    for i in list {
        // f64 from f32 prints the shortest text that reads back to the same f64.
        writeln!(
            buf,
            "{scene}\t{}\t{}\t{}\t{}\t{}\t{}\t{}",
            i.id,
            copy_text(&i.model),
            f64::from(i.position[0]),
            f64::from(i.position[1]),
            f64::from(i.position[2]),
            f64::from(i.rotation),
            f64::from(i.scale)
        )
        .map_err(|e| StoreError::Database(e.to_string()))?;
        if buf.len() >= 1 << 20 {
            w.write_all(&buf).map_err(|e| StoreError::Unavailable(e.to_string()))?;
            buf.clear();
        }
    }
    w.write_all(&buf).map_err(|e| StoreError::Unavailable(e.to_string()))?;
    w.finish()?;
    Ok(())
}

fn owner_lock(tx: &mut Transaction<'_>, owner: &str) -> Result<(), StoreError> {
    if !owner.is_empty() {
        tx.execute(
            "SELECT pg_advisory_xact_lock($1, hashtext($2))",
            &[&OWNER_LOCKS, &owner],
        )?;
    }
    Ok(())
}

fn count_owned(tx: &mut Transaction<'_>, owner: &str, limits: &Limits) -> Result<(), StoreError> {
    if owner.is_empty() {
        return Ok(());
    }
    let n: i64 = col(
        &tx.query_one("SELECT COUNT(*) FROM scenes WHERE owner = $1", &[&owner])?,
        0,
    )?;
    if n as u64 >= limits.max_scenes {
        return Err(StoreError::Quota(format!(
            "quota: this owner has {n} scenes, the most allowed is {}; delete one first",
            limits.max_scenes
        )));
    }
    Ok(())
}

fn check_bytes(tx: &mut Transaction<'_>, owner: &str, limits: &Limits) -> Result<(), StoreError> {
    if owner.is_empty() {
        return Ok(());
    }
    let used: i64 = col(
        &tx.query_one(
            "SELECT COALESCE(SUM(v.bytes), 0)::BIGINT FROM versions v JOIN scenes s ON s.id = v.scene \
             WHERE s.owner = $1",
            &[&owner],
        )?,
        0,
    )?;
    let used = used.max(0) as u64;
    if used > limits.max_bytes {
        return Err(StoreError::Quota(format!(
            "quota: this would keep {used} bytes of scene versions for this owner, over the limit of {}",
            limits.max_bytes
        )));
    }
    Ok(())
}

fn insert_version(tx: &mut Transaction<'_>, id: &str, version: u64, p: &Published, now: u64) -> Result<(), StoreError> {
    tx.execute(
        "INSERT INTO versions (scene, version, manifest, created_unix, bytes, files) VALUES ($1, $2, $3, $4, $5, $6)",
        &[
            &id,
            &(version as i64),
            &p.manifest,
            &(now as i64),
            &(p.bytes as i64),
            &join_files(&p.files),
        ],
    )?;
    Ok(())
}

/// Deletes the versions the retention no longer keeps (of scene `id`, or of every scene) and
/// returns them.
fn prune_where(
    tx: &mut Transaction<'_>,
    id: Option<&str>,
    limits: &Limits,
    now: u64,
) -> Result<Vec<Pruned>, StoreError> {
    let keep = limits.keep_versions.max(1) as i64;
    let age = if limits.keep_secs == 0 {
        i64::MAX
    } else {
        now.saturating_sub(limits.keep_secs) as i64
    };
    let rows = tx.query(
        "DELETE FROM versions v USING scenes s WHERE s.id = v.scene AND NOT v.pinned AND v.version < s.version \
         AND v.version <= s.version - $1 AND v.created_unix < $2 AND ($3::TEXT IS NULL OR s.id = $3) \
         RETURNING v.scene, v.version, v.files",
        &[&keep, &age, &id],
    )?;
    let mut out = rows
        .iter()
        .map(|r| {
            Ok(Pruned {
                scene: col(r, 0)?,
                version: col::<i64>(r, 1)? as u64,
                files: split_files(&col::<String>(r, 2)?),
            })
        })
        .collect::<Result<Vec<_>, StoreError>>()?;
    out.sort_by(|a, b| (&a.scene, a.version).cmp(&(&b.scene, b.version)));
    Ok(out)
}

impl PostgresStore {
    /// A store on the database at `url` (`postgres://user@host:port/db`). Connects and migrates
    /// now if it can; if the database cannot be reached, the store starts unavailable and a
    /// background thread retries once a second. A URL that does not parse is an error.
    pub fn open(url: &str) -> Result<Self, StoreError> {
        let mut config: postgres::Config = url
            .parse()
            .map_err(|e| StoreError::Database(format!("database URL: {e}")))?;
        if config.get_connect_timeout().is_none() {
            config.connect_timeout(CONNECT_TIMEOUT);
        }
        config.application_name("canopy-server");
        let inner = Arc::new(Inner {
            config,
            idle: Mutex::new(Vec::new()),
            migrated: AtomicBool::new(false),
            available: AtomicBool::new(false),
        });
        match inner.ensure_migrated() {
            Ok(()) => {}
            Err(StoreError::Unavailable(e)) => {
                tracing::warn!(error = %e, "scene database unreachable at start; retrying every second");
            }
            Err(e) => return Err(e),
        }
        let weak: Weak<Inner> = Arc::downgrade(&inner);
        std::thread::Builder::new()
            .name("postgres-check".into())
            .spawn(move || {
                // Also while available, so that `/healthz` notices a lost database without traffic.
                while let Some(inner) = weak.upgrade() {
                    inner.check();
                    drop(inner);
                    std::thread::sleep(RETRY_EVERY);
                }
            })
            .map_err(|e| StoreError::Database(format!("starting the database check: {e}")))?;
        let mut raw = [0u8; 8];
        getrandom::fill(&mut raw).map_err(|e| StoreError::Database(format!("replica id: {e}")))?;
        let replica = u64::from_le_bytes(raw);
        let presence = super::postgres_conn::PresenceSender::start(Arc::downgrade(&inner), replica)
            .map_err(|e| StoreError::Database(format!("starting the presence relay: {e}")))?;
        Ok(Self {
            inner,
            scene_locks: SceneLocks::default(),
            recent: super::recent::Recent::default(),
            replica,
            presence,
        })
    }

    fn read<T>(&self, f: impl FnOnce(&mut Transaction<'_>) -> Result<T, StoreError>) -> Result<T, StoreError> {
        self.inner.with(|c| {
            let mut tx = snapshot(c)?;
            let out = f(&mut tx)?;
            tx.commit()?;
            Ok(out)
        })
    }

    fn write<T>(&self, f: impl FnOnce(&mut Transaction<'_>) -> Result<T, StoreError>) -> Result<T, StoreError> {
        self.inner.with(|c| {
            let mut tx = c.transaction()?;
            let out = f(&mut tx)?;
            tx.commit()?;
            Ok(out)
        })
    }
}

impl SceneStore for PostgresStore {
    fn create(
        &self,
        scene: &NewScene,
        instances: &[NewInstance],
        limits: &Limits,
        publish: Publish<'_>,
    ) -> Result<SceneMeta, StoreError> {
        let scene_lock = self.scene_locks.get(&scene.id);
        let _one_writer = lock(&scene_lock);
        let owner = scene.owner.as_str();
        // Checked before publishing too, so that a refused creation writes no file.
        self.read(|tx| {
            if get_meta(tx, &scene.id)?.is_some() {
                return Err(StoreError::Exists(scene.id.clone()));
            }
            count_owned(tx, owner, limits)
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
        let incarnation = self.write(|tx| {
            owner_lock(tx, owner)?;
            tx.execute("SELECT pg_advisory_xact_lock($1)", &[&CREATION_LOCK])?;
            if get_meta(tx, &scene.id)?.is_some() {
                return Err(StoreError::Exists(scene.id.clone()));
            }
            let count: i64 = col(&tx.query_one("SELECT COUNT(*) FROM scenes", &[])?, 0)?;
            if count as usize >= MAX_SCENES {
                return Err(StoreError::Limit(format!(
                    "the server holds at most {MAX_SCENES} scenes"
                )));
            }
            count_owned(tx, owner, limits)?;
            let read_hash = scene.auth.read_hash.map(|h| h.to_vec());
            let made = tx.query_one(
                "INSERT INTO scenes (id, name, public, min_x, min_z, max_x, max_z, version, next_id, instance_count, \
                 write_hash, read_hash, created_unix, owner) VALUES ($1, $2, $3, $4, $5, $6, $7, 1, $8, $9, $10, $11, $12, $13) \
                 RETURNING incarnation",
                &[
                    &meta.id,
                    &meta.name,
                    &meta.public,
                    &meta.bounds.min[0],
                    &meta.bounds.min[1],
                    &meta.bounds.max[0],
                    &meta.bounds.max[1],
                    &i64::from(next_id),
                    &(list.len() as i64),
                    &scene.auth.write_hash.as_slice(),
                    &read_hash,
                    &(now as i64),
                    &owner,
                ],
            )?;
            insert_instances(tx, &meta.id, &list)?;
            if scene.terrain.is_some() {
                super::terrains::postgres_put(tx, &meta.id, scene.terrain.as_deref())?;
            }
            insert_version(tx, &meta.id, 1, &published, now)?;
            check_bytes(tx, owner, limits)?;
            Ok(col::<i64>(&made, 0)? as u64)
        })?;
        self.recent.put(&meta.id, 1, incarnation, Arc::new(list));
        Ok(meta)
    }

    fn list(&self) -> Result<Vec<SceneMeta>, StoreError> {
        self.read(|tx| {
            tx.query(&format!("SELECT {META_COLS} FROM scenes ORDER BY public DESC, id"), &[])?
                .iter()
                .map(meta_row)
                .collect()
        })
    }

    fn get(&self, id: &str) -> Result<Option<SceneMeta>, StoreError> {
        self.read(|tx| get_meta(tx, id))
    }

    fn auth(&self, id: &str) -> Result<Option<SceneAuth>, StoreError> {
        let row = self.read(|tx| {
            tx.query_opt("SELECT write_hash, read_hash FROM scenes WHERE id = $1", &[&id])?
                .map(|r| Ok::<_, StoreError>((col::<Vec<u8>>(&r, 0)?, col::<Option<Vec<u8>>>(&r, 1)?)))
                .transpose()
        })?;
        Ok(row.and_then(|(w, r)| {
            Some(SceneAuth {
                write_hash: <[u8; 32]>::try_from(w.as_slice()).ok()?,
                read_hash: r.and_then(|r| <[u8; 32]>::try_from(r.as_slice()).ok()),
            })
        }))
    }

    fn instances(&self, id: &str) -> Result<Vec<Instance>, StoreError> {
        self.read(|tx| {
            if get_meta(tx, id)?.is_none() {
                return Err(StoreError::NotFound(id.to_string()));
            }
            load_instances(tx, id)
        })
    }

    fn instance_table(&self, id: &str) -> Result<InstanceTable, StoreError> {
        self.read(|tx| {
            let meta = get_meta(tx, id)?.ok_or_else(|| StoreError::NotFound(id.to_string()))?;
            let mut table = InstanceTable {
                version: meta.version,
                created_unix: meta.created_unix,
                models: Vec::new(),
                rows: Vec::with_capacity((meta.instance_count as usize).min(MAX_INSTANCES)),
            };
            let mut index = HashMap::<String, u32>::new();
            each_instance(tx, id, |r| {
                let name: &str = col(r, 1)?;
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
                    id: col::<i64>(r, 0)? as u32,
                    model,
                    position,
                    rotation,
                    scale,
                });
                Ok(())
            })?;
            Ok(table)
        })
    }

    fn edit(&self, id: &str, batch: &EditBatch, limits: &Limits, publish: Publish<'_>) -> Result<Edited, StoreError> {
        self.edit_held(id, batch, limits, publish, super::terrains::TerrainChange::Keep)
    }

    fn manifest(&self, id: &str, version: Option<u64>) -> Result<Option<String>, StoreError> {
        self.read(|tx| {
            let row = match version {
                Some(v) => tx.query_opt(
                    "SELECT manifest FROM versions WHERE scene = $1 AND version = $2",
                    &[&id, &(v as i64)],
                )?,
                None => tx.query_opt(
                    "SELECT v.manifest FROM versions v JOIN scenes s ON s.id = v.scene AND s.version = v.version \
                     WHERE s.id = $1",
                    &[&id],
                )?,
            };
            row.map(|r| col(&r, 0)).transpose()
        })
    }

    fn delete(&self, id: &str) -> Result<bool, StoreError> {
        let scene_lock = self.scene_locks.get(id);
        let _one_writer = lock(&scene_lock);
        self.recent.forget(id);
        self.write(|tx| {
            let gone = tx.execute("DELETE FROM scenes WHERE id = $1", &[&id])? > 0;
            if gone {
                announce(tx, self.replica, id, None)?;
            }
            Ok(gone)
        })
    }

    fn versions(&self, id: &str) -> Result<Vec<VersionInfo>, StoreError> {
        self.read(|tx| {
            if get_meta(tx, id)?.is_none() {
                return Err(StoreError::NotFound(id.to_string()));
            }
            tx.query(
                "SELECT version, created_unix, bytes, pinned FROM versions WHERE scene = $1 ORDER BY version",
                &[&id],
            )?
            .iter()
            .map(|r| {
                Ok(VersionInfo {
                    version: col::<i64>(r, 0)? as u64,
                    created_unix: col::<i64>(r, 1)? as u64,
                    bytes: col::<i64>(r, 2)? as u64,
                    pinned: col(r, 3)?,
                })
            })
            .collect()
        })
    }

    fn pin(&self, id: &str, version: Option<u64>, pin: bool, limits: &Limits) -> Result<Vec<u64>, StoreError> {
        self.write(|tx| {
            let current = tx
                .query_opt("SELECT version FROM scenes WHERE id = $1 FOR UPDATE", &[&id])?
                .ok_or_else(|| StoreError::NotFound(id.to_string()))?;
            let v = version.unwrap_or(col::<i64>(&current, 0)? as u64);
            let Some(was) = tx.query_opt(
                "SELECT pinned FROM versions WHERE scene = $1 AND version = $2",
                &[&id, &(v as i64)],
            )?
            else {
                return Err(StoreError::NoVersion(v));
            };
            let was: bool = col(&was, 0)?;
            let pinned = |tx: &mut Transaction<'_>| -> Result<Vec<u64>, StoreError> {
                tx.query(
                    "SELECT version FROM versions WHERE scene = $1 AND pinned ORDER BY version",
                    &[&id],
                )?
                .iter()
                .map(|r| Ok(col::<i64>(r, 0)? as u64))
                .collect()
            };
            if pin && !was && pinned(tx)?.len() >= limits.max_pins {
                return Err(StoreError::Quota(format!(
                    "quota: a scene keeps at most {} pinned versions; unpin one first",
                    limits.max_pins
                )));
            }
            tx.execute(
                "UPDATE versions SET pinned = $3 WHERE scene = $1 AND version = $2",
                &[&id, &(v as i64), &pin],
            )?;
            pinned(tx)
        })
    }

    fn prune(&self, limits: &Limits, now_unix: u64) -> Result<Vec<Pruned>, StoreError> {
        self.write(|tx| prune_where(tx, None, limits, now_unix))
    }

    fn files(&self) -> Result<Vec<SceneFiles>, StoreError> {
        self.read(|tx| {
            let rows = tx.query(
                "SELECT s.id, s.version, v.files FROM scenes s JOIN versions v ON v.scene = s.id ORDER BY s.id",
                &[],
            )?;
            let mut out: Vec<SceneFiles> = Vec::new();
            for r in &rows {
                let id: String = col(r, 0)?;
                let files = split_files(col(r, 2)?);
                match out.last_mut() {
                    Some(last) if last.id == id => last.files.extend(files),
                    _ => out.push(SceneFiles {
                        id,
                        version: col::<i64>(r, 1)? as u64,
                        files,
                    }),
                }
            }
            Ok(out)
        })
    }

    fn flight_table(&self, id: &str) -> Result<Option<String>, StoreError> {
        self.read(|tx| super::flight_tables::postgres_get(tx, id))
    }

    fn set_flight_table(&self, id: &str, json: &str) -> Result<(), StoreError> {
        self.write(|tx| super::flight_tables::postgres_put(tx, id, Some(json)).map(drop))
    }

    fn clear_flight_table(&self, id: &str) -> Result<bool, StoreError> {
        self.write(|tx| super::flight_tables::postgres_put(tx, id, None))
    }

    fn terrain(&self, id: &str) -> Result<Option<String>, StoreError> {
        self.read(|tx| super::terrains::postgres_get(tx, id))
    }

    fn set_terrain(
        &self,
        id: &str,
        terrain: Option<&str>,
        limits: &Limits,
        publish: Publish<'_>,
    ) -> Result<Edited, StoreError> {
        self.edit_held(
            id,
            &EditBatch::default(),
            limits,
            publish,
            super::terrains::TerrainChange::Set(terrain),
        )
    }

    fn shared(&self) -> bool {
        true
    }

    fn available(&self) -> bool {
        self.inner.available.load(Ordering::Relaxed)
    }

    /// Listens on its own connection (re-established once a second while the database is away)
    /// until the store is dropped. Changes made while no connection listened are not replayed:
    /// a viewer learns the current version from the manifest when it next asks.
    fn watch(&self, on_change: Box<dyn Fn(SceneChange) + Send + Sync>) {
        let spawned = super::postgres_conn::listen(Arc::downgrade(&self.inner), self.replica, on_change);
        if let Err(e) = spawned {
            tracing::error!(error = %e, "cannot listen for other replicas' scene changes");
        }
    }

    fn relay_presence(&self, payload: String) {
        self.presence.send(payload);
    }
}

#[path = "postgres_edit.rs"]
mod edit;

#[cfg(test)]
#[path = "postgres_tests.rs"]
mod tests;

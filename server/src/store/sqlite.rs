//! [`SceneStore`] on an embedded SQLite database (one file, one process).

use std::path::Path;
use std::sync::Mutex;

use rusqlite::{Connection, OptionalExtension, params};

use super::scenes::Bounds;
use super::scenes::{
    EditBatch, Instance, InstanceRow, InstanceTable, MAX_INSTANCES, MAX_SCENES, NewInstance, NewScene, Publish,
    SceneAuth, SceneMeta, SceneStore, StoreError, apply_batch,
};

// `synchronous = FULL`: every commit syncs the WAL, so an acknowledged edit survives a power cut
// (NORMAL survives a crash of the process only); see docs/server.md for the cost.
const SCHEMA: &str = "
PRAGMA journal_mode = WAL;
PRAGMA synchronous = FULL;
PRAGMA foreign_keys = ON;
CREATE TABLE IF NOT EXISTS scenes (
    id TEXT PRIMARY KEY,
    name TEXT NOT NULL,
    public INTEGER NOT NULL,
    min_x REAL NOT NULL, min_z REAL NOT NULL, max_x REAL NOT NULL, max_z REAL NOT NULL,
    version INTEGER NOT NULL,
    next_id INTEGER NOT NULL,
    instance_count INTEGER NOT NULL,
    write_hash BLOB NOT NULL,
    read_hash BLOB,
    created_unix INTEGER NOT NULL
);
CREATE TABLE IF NOT EXISTS instances (
    scene TEXT NOT NULL REFERENCES scenes(id) ON DELETE CASCADE,
    id INTEGER NOT NULL,
    model TEXT NOT NULL,
    x REAL NOT NULL, y REAL NOT NULL, z REAL NOT NULL,
    rotation REAL NOT NULL,
    scale REAL NOT NULL,
    PRIMARY KEY (scene, id)
) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS versions (
    scene TEXT NOT NULL REFERENCES scenes(id) ON DELETE CASCADE,
    version INTEGER NOT NULL,
    manifest TEXT NOT NULL,
    created_unix INTEGER NOT NULL,
    PRIMARY KEY (scene, version)
) WITHOUT ROWID;
";

/// SQLite scene store.
#[derive(Debug)]
pub struct SqliteStore {
    conn: Mutex<Connection>,
}

impl From<rusqlite::Error> for StoreError {
    fn from(e: rusqlite::Error) -> Self {
        StoreError::Database(e.to_string())
    }
}

fn now_unix() -> u64 {
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

impl SqliteStore {
    /// Opens (creating if needed) the database file.
    pub fn open(path: &Path) -> Result<Self, StoreError> {
        Self::init(Connection::open(path)?)
    }

    /// An in-memory database (tests).
    pub fn in_memory() -> Result<Self, StoreError> {
        Self::init(Connection::open_in_memory()?)
    }

    fn init(conn: Connection) -> Result<Self, StoreError> {
        conn.execute_batch(SCHEMA)?;
        Ok(Self { conn: Mutex::new(conn) })
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Connection> {
        self.conn.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
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

impl SceneStore for SqliteStore {
    fn create(
        &self,
        scene: &NewScene,
        instances: &[NewInstance],
        publish: Publish<'_>,
    ) -> Result<SceneMeta, StoreError> {
        let mut c = self.lock();
        let tx = c.transaction()?;
        if get_meta(&tx, &scene.id)?.is_some() {
            return Err(StoreError::Exists(scene.id.clone()));
        }
        let count: i64 = tx.query_row("SELECT COUNT(*) FROM scenes", [], |r| r.get(0))?;
        if count as usize >= MAX_SCENES {
            return Err(StoreError::Limit(format!(
                "the server holds at most {MAX_SCENES} scenes"
            )));
        }
        let batch = EditBatch {
            add: instances.to_vec(),
            ..EditBatch::default()
        };
        let (list, next_id) = apply_batch(&[], 1, &batch)?;
        let meta = SceneMeta {
            id: scene.id.clone(),
            name: scene.name.clone(),
            public: scene.public,
            bounds: scene.bounds,
            version: 1,
            instance_count: list.len() as u64,
            created_unix: now_unix(),
        };
        tx.execute(
            "INSERT INTO scenes (id, name, public, min_x, min_z, max_x, max_z, version, next_id, instance_count, write_hash, read_hash, created_unix)
             VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, 1, ?8, ?9, ?10, ?11, ?12)",
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
                meta.created_unix as i64
            ],
        )
        ?;
        for i in &list {
            insert_instance(&tx, &meta.id, i)?;
        }
        let manifest = publish(&meta, &list)?;
        tx.execute(
            "INSERT INTO versions (scene, version, manifest, created_unix) VALUES (?1, 1, ?2, ?3)",
            params![meta.id, manifest, meta.created_unix as i64],
        )?;
        tx.commit()?;
        Ok(meta)
    }

    fn list(&self) -> Result<Vec<SceneMeta>, StoreError> {
        let c = self.lock();
        let mut st = c.prepare(&format!("SELECT {META_COLS} FROM scenes ORDER BY public DESC, id"))?;
        let rows = st.query_map([], meta_row)?;
        rows.collect::<Result<_, _>>().map_err(StoreError::from)
    }

    fn get(&self, id: &str) -> Result<Option<SceneMeta>, StoreError> {
        get_meta(&self.lock(), id)
    }

    fn auth(&self, id: &str) -> Result<Option<SceneAuth>, StoreError> {
        let c = self.lock();
        let row: Option<(Vec<u8>, Option<Vec<u8>>)> = c
            .query_row("SELECT write_hash, read_hash FROM scenes WHERE id = ?1", [id], |r| {
                Ok((r.get(0)?, r.get(1)?))
            })
            .optional()?;
        Ok(row.and_then(|(w, r)| {
            Some(SceneAuth {
                write_hash: hash_of(Some(w))?,
                read_hash: hash_of(r),
            })
        }))
    }

    fn instances(&self, id: &str) -> Result<Vec<Instance>, StoreError> {
        let c = self.lock();
        if get_meta(&c, id)?.is_none() {
            return Err(StoreError::NotFound(id.to_string()));
        }
        load_instances(&c, id)
    }

    fn instance_table(&self, id: &str) -> Result<InstanceTable, StoreError> {
        let c = self.lock();
        let meta = get_meta(&c, id)?.ok_or_else(|| StoreError::NotFound(id.to_string()))?;
        let mut st =
            c.prepare_cached("SELECT id, model, x, y, z, rotation, scale FROM instances WHERE scene = ?1 ORDER BY id")?;
        let mut rows = st.query([id])?;
        let mut table = InstanceTable {
            version: meta.version,
            created_unix: meta.created_unix,
            models: Vec::new(),
            rows: Vec::with_capacity((meta.instance_count as usize).min(MAX_INSTANCES)),
        };
        let mut index = std::collections::HashMap::<String, u32>::new();
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
    }

    fn edit(&self, id: &str, batch: &EditBatch, publish: Publish<'_>) -> Result<SceneMeta, StoreError> {
        let mut c = self.lock();
        let tx = c.transaction()?;
        let mut meta = get_meta(&tx, id)?.ok_or_else(|| StoreError::NotFound(id.to_string()))?;
        if let Some(expected) = batch.base_version
            && expected != meta.version
        {
            return Err(StoreError::Conflict {
                current: meta.version,
                expected,
            });
        }
        let next_id: i64 = tx.query_row("SELECT next_id FROM scenes WHERE id = ?1", [id], |r| r.get(0))?;
        let current = load_instances(&tx, id)?;
        let (list, next_id) = apply_batch(&current, next_id as u32, batch)?;
        for rid in &batch.remove {
            tx.execute(
                "DELETE FROM instances WHERE scene = ?1 AND id = ?2",
                params![id, i64::from(*rid)],
            )?;
        }
        for m in &batch.moves {
            if let Ok(k) = list.binary_search_by_key(&m.id, |i| i.id) {
                let i = &list[k];
                tx.execute(
                    "UPDATE instances SET x = ?3, y = ?4, z = ?5, rotation = ?6, scale = ?7 WHERE scene = ?1 AND id = ?2",
                    params![
                        id,
                        i64::from(i.id),
                        f64::from(i.position[0]),
                        f64::from(i.position[1]),
                        f64::from(i.position[2]),
                        f64::from(i.rotation),
                        f64::from(i.scale)
                    ],
                )
                ?;
            }
        }
        for i in &list[list.len() - batch.add.len()..] {
            insert_instance(&tx, id, i)?;
        }
        meta.version += 1;
        meta.instance_count = list.len() as u64;
        tx.execute(
            "UPDATE scenes SET version = ?2, next_id = ?3, instance_count = ?4 WHERE id = ?1",
            params![id, meta.version as i64, i64::from(next_id), list.len() as i64],
        )?;
        let manifest = publish(&meta, &list)?;
        tx.execute(
            "INSERT INTO versions (scene, version, manifest, created_unix) VALUES (?1, ?2, ?3, ?4)",
            params![id, meta.version as i64, manifest, now_unix() as i64],
        )?;
        tx.commit()?;
        Ok(meta)
    }

    fn manifest(&self, id: &str, version: Option<u64>) -> Result<Option<String>, StoreError> {
        let c = self.lock();
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
    }

    fn delete(&self, id: &str) -> Result<bool, StoreError> {
        let c = self.lock();
        Ok(c.execute("DELETE FROM scenes WHERE id = ?1", [id])? > 0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::scenes::MoveInstance;

    fn new_scene(id: &str) -> NewScene {
        NewScene {
            id: id.into(),
            name: "Test".into(),
            public: true,
            bounds: Bounds {
                min: [0.0, 0.0],
                max: [100.0, 100.0],
            },
            auth: SceneAuth {
                write_hash: [7; 32],
                read_hash: None,
            },
        }
    }

    fn add(x: f32) -> NewInstance {
        NewInstance {
            model: "oak".into(),
            position: [x, 0.0, 1.0],
            rotation: 0.0,
            scale: 1.0,
        }
    }

    #[test]
    fn create_edit_version_and_failed_publish_changes_nothing() {
        let s = SqliteStore::in_memory().expect("db");
        let mut ok = |m: &SceneMeta, l: &[Instance]| Ok(format!("{{\"v\":{},\"n\":{}}}", m.version, l.len()));
        let m = s
            .create(&new_scene("a"), &[add(1.0), add(2.0)], &mut ok)
            .expect("create");
        assert_eq!((m.version, m.instance_count), (1, 2));
        assert!(matches!(
            s.create(&new_scene("a"), &[], &mut ok),
            Err(StoreError::Exists(_))
        ));
        let batch = EditBatch {
            add: vec![add(3.0)],
            moves: vec![MoveInstance {
                id: 1,
                position: [9.0, 0.0, 9.0],
                rotation: Some(1.0),
                scale: None,
            }],
            remove: vec![2],
            base_version: Some(1),
        };
        let m = s.edit("a", &batch, &mut ok).expect("edit");
        assert_eq!((m.version, m.instance_count), (2, 2));
        let list = s.instances("a").expect("instances");
        assert_eq!(list.iter().map(|i| i.id).collect::<Vec<_>>(), vec![1, 3]);
        assert_eq!(list[0].position, [9.0, 0.0, 9.0]);
        assert_eq!(list[0].rotation, 1.0);
        assert_eq!(s.manifest("a", None).expect("m").as_deref(), Some("{\"v\":2,\"n\":2}"));
        assert_eq!(
            s.manifest("a", Some(1)).expect("m").as_deref(),
            Some("{\"v\":1,\"n\":2}")
        );
        // Stale base version, unknown id, duplicate id, failing publish: all change nothing.
        assert!(matches!(
            s.edit("a", &batch, &mut ok),
            Err(StoreError::Conflict {
                current: 2,
                expected: 1
            })
        ));
        let bad = EditBatch {
            remove: vec![2],
            ..EditBatch::default()
        };
        assert!(matches!(s.edit("a", &bad, &mut ok), Err(StoreError::Invalid(_))));
        let dup = EditBatch {
            remove: vec![1, 1],
            ..EditBatch::default()
        };
        assert!(matches!(s.edit("a", &dup, &mut ok), Err(StoreError::Invalid(_))));
        let mut fail = |_: &SceneMeta, _: &[Instance]| Err(StoreError::Publish("disk full".into()));
        let good = EditBatch {
            remove: vec![1],
            ..EditBatch::default()
        };
        assert!(s.edit("a", &good, &mut fail).is_err());
        assert_eq!(
            s.get("a").expect("get").map(|m| (m.version, m.instance_count)),
            Some((2, 2))
        );
        assert_eq!(s.instances("a").expect("instances").len(), 2);
        let t = s.instance_table("a").expect("table");
        assert_eq!((t.version, t.models.clone()), (2, vec!["oak".to_string()]));
        assert_eq!(
            t.rows.iter().map(|r| (r.id, r.model)).collect::<Vec<_>>(),
            vec![(1, 0), (3, 0)]
        );
        assert_eq!(t.rows[0].position, [9.0, 0.0, 9.0]);
        assert!(matches!(s.instance_table("zz"), Err(StoreError::NotFound(_))));
        assert_eq!(s.auth("a").expect("auth").map(|a| a.write_hash), Some([7; 32]));
        assert!(s.delete("a").expect("delete"));
        assert!(!s.delete("a").expect("delete"));
        assert!(s.get("a").expect("get").is_none());
        assert!(s.manifest("a", Some(1)).expect("m").is_none());
    }
}

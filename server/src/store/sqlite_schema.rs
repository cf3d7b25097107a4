//! The SQLite store's schema: its migrations, run forward at open (`PRAGMA user_version` counts
//! those that ran), and how a version row lists its files. The statements are in
//! [`super::sqlite`].

use rusqlite::{Connection, params};

use super::scenes::StoreError;

/// Schema migrations, in order: the database's `user_version` is how many have run.
pub(super) const MIGRATIONS: &[&str] = &[
    "
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
",
    // Owners (quotas), and per version its files, their bytes and a pin (retention). Rows from
    // before get their files and bytes from their manifests (`backfill_files`).
    "
ALTER TABLE scenes ADD COLUMN owner TEXT NOT NULL DEFAULT '';
CREATE INDEX scenes_owner ON scenes(owner);
ALTER TABLE versions ADD COLUMN bytes INTEGER NOT NULL DEFAULT 0;
ALTER TABLE versions ADD COLUMN pinned INTEGER NOT NULL DEFAULT 0;
ALTER TABLE versions ADD COLUMN files TEXT NOT NULL DEFAULT '';
",
    // Seed 002's flight table, a scene property (not versioned): one row per scene that has one,
    // deleted with the scene. A table of its own, so that an edit's UPDATE of the scene row does
    // not rewrite it (SQLite rewrites a whole row, overflow pages included).
    "
CREATE TABLE flight_tables (
    scene TEXT PRIMARY KEY REFERENCES scenes(id) ON DELETE CASCADE,
    json TEXT NOT NULL
);
",
    // A scene's terrain (the manifest's `terrain` object): one row per scene that has one, deleted
    // with the scene; written with the version that sets it (`terrains.rs`).
    "
CREATE TABLE terrains (
    scene TEXT PRIMARY KEY REFERENCES scenes(id) ON DELETE CASCADE,
    json TEXT NOT NULL
);
",
];

pub(super) fn join_files(files: &[String]) -> String {
    files.join("\n")
}

pub(super) fn split_files(s: &str) -> Vec<String> {
    s.lines().filter(|l| !l.is_empty()).map(String::from).collect()
}

/// A version's files and bytes, from its manifest (rows written before versions recorded them).
fn files_of_manifest(scene: &str, version: i64, manifest: &str) -> (Vec<String>, i64) {
    let v: serde_json::Value = serde_json::from_str(manifest).unwrap_or_default();
    let mut files = vec![format!(
        "scenes/{scene}/v{version}.{}.json",
        &super::assets::sha256_hex(manifest.as_bytes())[..super::assets::NAME_HASH_HEX]
    )];
    if let Some(p) = v["pack"]["url"].as_str().and_then(|u| u.strip_prefix("/assets/")) {
        files.push(p.to_string());
    }
    let bytes = v["pack"]["size"].as_i64().unwrap_or(0) + manifest.len() as i64;
    (files, bytes)
}

pub(super) fn migrate(conn: &mut Connection) -> Result<(), StoreError> {
    let done: usize = conn.query_row("PRAGMA user_version", [], |r| r.get::<_, i64>(0))? as usize;
    if done > MIGRATIONS.len() {
        return Err(StoreError::Database(format!(
            "the database has schema version {done}; this server knows up to {}",
            MIGRATIONS.len()
        )));
    }
    for (k, sql) in MIGRATIONS.iter().enumerate().skip(done) {
        let tx = conn.transaction()?;
        tx.execute_batch(sql)?;
        if k == 1 {
            backfill_files(&tx)?;
        }
        tx.pragma_update(None, "user_version", (k + 1) as i64)?;
        tx.commit()?;
        tracing::info!(schema_version = k + 1, "scene database migrated");
    }
    Ok(())
}

fn backfill_files(tx: &Connection) -> Result<(), StoreError> {
    let rows: Vec<(String, i64, String)> = {
        let mut st = tx.prepare("SELECT scene, version, manifest FROM versions")?;
        let r = st.query_map([], |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?)))?;
        r.collect::<Result<_, _>>()?
    };
    for (scene, version, manifest) in rows {
        let (files, bytes) = files_of_manifest(&scene, version, &manifest);
        tx.execute(
            "UPDATE versions SET files = ?3, bytes = ?4 WHERE scene = ?1 AND version = ?2",
            params![scene, version, join_files(&files), bytes],
        )?;
    }
    Ok(())
}

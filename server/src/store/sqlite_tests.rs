//! Tests of the SQLite scene store: the store contract (`contract_tests.rs`) on SQLite, and the
//! schema migration.

use super::*;
use crate::store::contract_tests as contract;
use crate::store::scenes::Changes;
use crate::store::sqlite_schema::MIGRATIONS;

fn temp_db(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("canopy-sqlite-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("mkdir");
    dir.join("canopy.db")
}

#[test]
fn create_edit_version_and_failed_publish_changes_nothing() {
    contract::create_edit_version_and_failed_publish_changes_nothing(&SqliteStore::in_memory().expect("db"));
}

#[test]
fn quotas_per_owner_refuse_and_change_nothing() {
    contract::quotas_per_owner_refuse_and_change_nothing(&SqliteStore::in_memory().expect("db"));
}

#[test]
fn retention_keeps_the_last_versions_the_pinned_and_the_current() {
    contract::retention_keeps_the_last_versions_the_pinned_and_the_current(&SqliteStore::in_memory().expect("db"));
}

#[test]
fn reads_do_not_wait_for_a_publish_in_progress() {
    let db = temp_db("readers");
    let s: Arc<dyn SceneStore> = Arc::new(SqliteStore::open(&db).expect("open"));
    contract::reads_do_not_wait_for_a_publish_in_progress(&s);
    let _ = std::fs::remove_dir_all(db.parent().expect("dir"));
}

#[test]
fn a_version_commits_only_over_the_version_it_was_built_from() {
    let db = temp_db("cas");
    let s1 = SqliteStore::open(&db).expect("open");
    let s2 = SqliteStore::open(&db).expect("open");
    contract::a_version_commits_only_over_the_version_it_was_built_from(&s1, &s2);
    let _ = std::fs::remove_dir_all(db.parent().expect("dir"));
}

#[test]
fn a_flight_table_is_a_scene_property_gone_with_the_scene() {
    contract::a_flight_table_is_a_scene_property_gone_with_the_scene(&SqliteStore::in_memory().expect("db"));
}

#[test]
fn a_flight_table_survives_a_restart() {
    let db = temp_db("flight-table");
    contract::a_flight_table_survives_a_restart(&|| Box::new(SqliteStore::open(&db).expect("open")));
    let _ = std::fs::remove_dir_all(db.parent().expect("dir"));
}

#[test]
fn a_terrain_is_set_with_a_version_and_kept_by_later_edits() {
    contract::a_terrain_is_set_with_a_version_and_kept_by_later_edits(&SqliteStore::in_memory().expect("db"));
}

#[test]
fn a_terrain_survives_a_restart() {
    let db = temp_db("terrain");
    contract::a_terrain_survives_a_restart(&|| Box::new(SqliteStore::open(&db).expect("open")));
    let _ = std::fs::remove_dir_all(db.parent().expect("dir"));
}

#[test]
fn a_database_from_before_terrains_is_migrated() {
    let db = temp_db("migrate-terrain");
    {
        let mut c = Connection::open(&db).expect("open");
        let tx = c.transaction().expect("tx");
        for sql in &MIGRATIONS[..3] {
            tx.execute_batch(sql).expect("old schema");
        }
        tx.pragma_update(None, "user_version", 3).expect("version");
        tx.execute_batch(
            "INSERT INTO scenes (id, name, public, min_x, min_z, max_x, max_z, version, next_id, instance_count, \
             write_hash, created_unix) VALUES ('old', 'Old', 1, 0, 0, 10, 10, 1, 1, 0, x'00', 5);",
        )
        .expect("old rows");
        tx.commit().expect("commit");
    }
    let s = SqliteStore::open(&db).expect("migrated");
    assert_eq!(s.terrain("old").expect("terrains' table"), None);
    let mut ok = |m: &SceneMeta, l: &[Instance], _: &Changes| contract::published(m, l);
    s.set_terrain("old", Some(&contract::terrain_json(1)), &Limits::default(), &mut ok)
        .expect("set");
    assert!(s.terrain("old").expect("get").is_some());
    let _ = std::fs::remove_dir_all(db.parent().expect("dir"));
}

#[test]
fn a_database_from_before_owners_and_retention_is_migrated() {
    let db = temp_db("migrate");
    {
        let c = Connection::open(&db).expect("open");
        c.execute_batch(MIGRATIONS[0]).expect("old schema");
        c.execute_batch(
            "INSERT INTO scenes VALUES ('old', 'Old', 1, 0, 0, 10, 10, 1, 1, 0, x'00', NULL, 5);
             INSERT INTO versions VALUES ('old', 1, '{\"pack\":{\"url\":\"/assets/scenes/old/v1.0123456789abcdef.cpack\",\"size\":700}}', 5);",
        )
        .expect("old rows");
    }
    let s = SqliteStore::open(&db).expect("migrated");
    let f = s.files().expect("files");
    assert_eq!(f[0].files.len(), 2);
    assert_eq!(f[0].files[1], "scenes/old/v1.0123456789abcdef.cpack");
    assert!(f[0].files[0].starts_with("scenes/old/v1.") && f[0].files[0].rsplit('.').next() == Some("json"));
    let v = s.versions("old").expect("versions");
    assert!(v[0].bytes > 700, "{v:?}");
    // The flight tables' table is there, and the old scene has none.
    assert_eq!(s.flight_table("old").expect("flight table"), None);
    s.set_flight_table("old", &contract::flight_table_json(1))
        .expect("set a flight table");
    drop(s);
    // Reopening runs nothing twice.
    let s = SqliteStore::open(&db).expect("reopened");
    assert_eq!(s.versions("old").expect("versions").len(), 1);
    assert!(s.flight_table("old").expect("flight table").is_some());
    let c = Connection::open(&db).expect("open");
    let schema: i64 = c
        .query_row("PRAGMA user_version", [], |r| r.get(0))
        .expect("user_version");
    assert_eq!(schema, MIGRATIONS.len() as i64);
    let _ = std::fs::remove_dir_all(db.parent().expect("dir"));
}

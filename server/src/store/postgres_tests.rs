//! Tests of the PostgreSQL scene store: the store contract (`contract_tests.rs`) on PostgreSQL,
//! two replicas editing one scene under contention, the schema migration, and a database that is
//! not there.
//!
//! They need a PostgreSQL server: `CANOPY_TEST_POSTGRES=postgres://USER@HOST:PORT/DB` (a role that
//! may create databases; `.ci/run` starts a throwaway cluster and sets it). Each test makes its own
//! database. Without the variable they are skipped, except under CI, where they fail.

use std::sync::Arc;
use std::time::Duration;

use postgres::NoTls;

use super::*;
use crate::store::contract_tests as contract;
use crate::store::scenes::Changes;

/// A fresh database for test `name`, as a URL; `None` (skipped) without a server outside CI.
fn fresh_database(name: &str) -> Option<String> {
    let Ok(url) = std::env::var("CANOPY_TEST_POSTGRES") else {
        assert!(
            std::env::var_os("CI").is_none(),
            "CANOPY_TEST_POSTGRES is not set: CI must run the PostgreSQL store tests (.ci/run starts a server)"
        );
        eprintln!("skipped: CANOPY_TEST_POSTGRES is not set");
        return None;
    };
    let db = format!("canopy_test_{name}");
    let mut admin = postgres::Client::connect(&url, NoTls).expect("connecting to CANOPY_TEST_POSTGRES");
    for sql in [
        format!("DROP DATABASE IF EXISTS {db} WITH (FORCE)"),
        format!("CREATE DATABASE {db}"),
    ] {
        admin.batch_execute(&sql).expect("creating the test database");
    }
    let (base, _) = url
        .rsplit_once('/')
        .expect("CANOPY_TEST_POSTGRES is postgres://USER@HOST:PORT/DB");
    Some(format!("{base}/{db}"))
}

fn open(url: &str) -> PostgresStore {
    PostgresStore::open(url).expect("open")
}

#[test]
fn create_edit_version_and_failed_publish_changes_nothing() {
    let Some(url) = fresh_database("create_edit") else {
        return;
    };
    contract::create_edit_version_and_failed_publish_changes_nothing(&open(&url));
}

#[test]
fn quotas_per_owner_refuse_and_change_nothing() {
    let Some(url) = fresh_database("quotas") else { return };
    contract::quotas_per_owner_refuse_and_change_nothing(&open(&url));
}

#[test]
fn retention_keeps_the_last_versions_the_pinned_and_the_current() {
    let Some(url) = fresh_database("retention") else { return };
    contract::retention_keeps_the_last_versions_the_pinned_and_the_current(&open(&url));
}

#[test]
fn reads_do_not_wait_for_a_publish_in_progress() {
    let Some(url) = fresh_database("readers") else { return };
    let s: Arc<dyn SceneStore> = Arc::new(open(&url));
    contract::reads_do_not_wait_for_a_publish_in_progress(&s);
}

#[test]
fn a_flight_table_is_a_scene_property_gone_with_the_scene() {
    let Some(url) = fresh_database("flight_table") else {
        return;
    };
    contract::a_flight_table_is_a_scene_property_gone_with_the_scene(&open(&url));
}

#[test]
fn a_flight_table_survives_a_restart() {
    let Some(url) = fresh_database("flight_table_restart") else {
        return;
    };
    contract::a_flight_table_survives_a_restart(&|| Box::new(open(&url)));
}

#[test]
fn a_terrain_is_set_with_a_version_and_kept_by_later_edits() {
    let Some(url) = fresh_database("terrain") else {
        return;
    };
    contract::a_terrain_is_set_with_a_version_and_kept_by_later_edits(&open(&url));
}

#[test]
fn a_terrain_survives_a_restart() {
    let Some(url) = fresh_database("terrain_restart") else {
        return;
    };
    contract::a_terrain_survives_a_restart(&|| Box::new(open(&url)));
}

#[test]
fn a_terrain_set_on_one_replica_is_built_on_by_the_others_edits() {
    let Some(url) = fresh_database("terrain_replicas") else {
        return;
    };
    let (s1, s2) = (open(&url), open(&url));
    let mut ok = |m: &SceneMeta, l: &[Instance], _: &Changes| contract::published(m, l);
    s1.create(&contract::new_scene("a", ""), &[], &Limits::default(), &mut ok)
        .expect("create");
    // Replica 2 edits first, so that its cached list is of version 2.
    s2.edit("a", &contract::one_add(), &Limits::default(), &mut ok)
        .expect("edit");
    let t = contract::terrain_json(3);
    let e = s1.set_terrain("a", Some(&t), &Limits::default(), &mut ok).expect("set");
    assert_eq!(e.meta.version, 3);
    let mut seen = None;
    let mut keep = |m: &SceneMeta, l: &[Instance], ch: &Changes| {
        seen = ch.terrain.as_deref().map(String::from);
        contract::published(m, l)
    };
    let e = s2
        .edit("a", &contract::one_add(), &Limits::default(), &mut keep)
        .expect("edit");
    assert_eq!((e.meta.version, seen.as_deref()), (4, Some(t.as_str())));
    assert!(s2.delete("a").expect("delete"));
    assert!(matches!(s1.terrain("a"), Err(StoreError::NotFound(_))));
}

#[test]
fn a_flight_table_set_on_one_replica_is_read_on_the_other_and_deleted_with_the_scene_there() {
    let Some(url) = fresh_database("flight_table_replicas") else {
        return;
    };
    let (s1, s2) = (open(&url), open(&url));
    let mut ok = |m: &SceneMeta, l: &[Instance], _: &Changes| contract::published(m, l);
    s1.create(&contract::new_scene("a", ""), &[], &Limits::default(), &mut ok)
        .expect("create");
    let t = contract::flight_table_json(2);
    s1.set_flight_table("a", &t).expect("set");
    assert_eq!(s2.flight_table("a").expect("get").as_deref(), Some(t.as_str()));
    assert!(s2.delete("a").expect("delete"));
    assert!(matches!(s1.flight_table("a"), Err(StoreError::NotFound(_))));
    assert!(matches!(s1.set_flight_table("a", &t), Err(StoreError::NotFound(_))));
}

#[test]
fn edits_of_one_scene_on_two_replicas_wait_for_each_other_instead_of_conflicting() {
    let Some(url) = fresh_database("serialised") else {
        return;
    };
    let (s1, s2) = (Arc::new(open(&url)), Arc::new(open(&url)));
    let l = Limits::default();
    let mut ok = |m: &SceneMeta, l: &[Instance], _: &Changes| contract::published(m, l);
    s1.create(&contract::new_scene("a", "o"), &[], &l, &mut ok).expect("a");
    let (started_tx, started) = std::sync::mpsc::channel();
    let (release_tx, release) = std::sync::mpsc::channel::<()>();
    let first = {
        let s1 = s1.clone();
        std::thread::spawn(move || {
            let mut slow = |m: &SceneMeta, l: &[Instance], _: &Changes| {
                let _ = started_tx.send(());
                let _ = release.recv();
                contract::published(m, l)
            };
            s1.edit("a", &contract::one_add(), &Limits::default(), &mut slow)
                .map(|e| e.meta.version)
        })
    };
    started.recv().expect("publishing");
    let done = Arc::new(AtomicBool::new(false));
    let second = {
        let (s2, done) = (s2.clone(), done.clone());
        std::thread::spawn(move || {
            let v = s2
                .edit("a", &contract::one_add(), &Limits::default(), &mut |m, l, _| {
                    contract::published(m, l)
                })
                .map(|e| e.meta.version);
            done.store(true, Ordering::SeqCst);
            v
        })
    };
    std::thread::sleep(Duration::from_millis(300));
    assert!(
        !done.load(Ordering::SeqCst),
        "the second replica's edit waits for the first"
    );
    // Reads do not wait.
    assert_eq!(s2.get("a").expect("get").map(|m| m.version), Some(1));
    release_tx.send(()).expect("release");
    assert_eq!(first.join().expect("join").expect("first edit"), 2);
    assert_eq!(second.join().expect("join").expect("second edit, no conflict"), 3);
    // With a base version, the later edit is the client's conflict, refused before publishing.
    let based = EditBatch {
        base_version: Some(2),
        ..contract::one_add()
    };
    assert!(matches!(
        s2.edit("a", &based, &l, &mut ok),
        Err(StoreError::Conflict {
            current: 3,
            expected: 2
        })
    ));
}

#[test]
fn two_replicas_editing_one_scene_lose_no_acknowledged_edit_and_make_no_version_twice() {
    let Some(url) = fresh_database("contention") else {
        return;
    };
    let replicas = [Arc::new(open(&url)), Arc::new(open(&url))];
    let l = Limits::default();
    let mut ok = |m: &SceneMeta, l: &[Instance], _: &Changes| contract::published(m, l);
    replicas[0]
        .create(&contract::new_scene("a", ""), &[], &l, &mut ok)
        .expect("create");
    // Two writers on each replica: the replica's scene lock orders its own, the row lock and the
    // compare-and-swap the two replicas'.
    let writers: Vec<_> = (0..4)
        .map(|k| {
            let s = replicas[k % 2].clone();
            std::thread::spawn(move || {
                let (mut acked, mut conflicts) = (Vec::new(), 0);
                for n in 0..12 {
                    let batch = EditBatch {
                        add: vec![contract::add((k * 100 + n) as f32 * 0.1)],
                        ..EditBatch::default()
                    };
                    match s.edit("a", &batch, &Limits::default(), &mut |m, l, _| {
                        contract::published(m, l)
                    }) {
                        Ok(e) => acked.push((e.meta.version, (k * 100 + n) as f32 * 0.1)),
                        Err(StoreError::Conflict { .. }) => conflicts += 1,
                        Err(e) => panic!("edit: {e}"),
                    }
                }
                (acked, conflicts)
            })
        })
        .collect();
    let mut acked = Vec::new();
    let mut conflicts = 0;
    for w in writers {
        let (a, c) = w.join().expect("writer");
        acked.extend(a);
        conflicts += c;
    }
    let mut versions: Vec<u64> = acked.iter().map(|a| a.0).collect();
    versions.sort_unstable();
    let n = versions.len() as u64;
    assert_eq!(
        versions,
        (2..=n + 1).collect::<Vec<_>>(),
        "each acknowledged edit its own version"
    );
    let list = replicas[1].instances("a").expect("instances");
    assert_eq!(list.len() as u64, n, "{conflicts} conflicts");
    for (_, x) in &acked {
        assert!(
            list.iter().any(|i| i.position[0] == *x),
            "acknowledged edit at x = {x} kept"
        );
    }
    assert_eq!(replicas[1].get("a").expect("get").map(|m| m.version), Some(n + 1));
    assert_eq!(
        (n, conflicts),
        (48, 0),
        "every edit commits: replicas wait for each other"
    );
}

#[test]
fn migration_runs_once_and_a_newer_schema_is_refused() {
    let Some(url) = fresh_database("migration") else { return };
    let s = open(&url);
    let mut ok = |m: &SceneMeta, l: &[Instance], _: &Changes| contract::published(m, l);
    s.create(
        &contract::new_scene("a", ""),
        &[contract::add(1.0)],
        &Limits::default(),
        &mut ok,
    )
    .expect("create");
    drop(s);
    let s = open(&url);
    assert_eq!(s.instances("a").expect("kept").len(), 1);
    let mut c = postgres::Client::connect(&url, NoTls).expect("connect");
    let schema: i32 = c
        .query_one("SELECT version FROM canopy_schema", &[])
        .expect("schema")
        .get(0);
    assert_eq!(schema as usize, super::super::postgres_conn::MIGRATIONS.len());
    c.execute("UPDATE canopy_schema SET version = 99", &[]).expect("bump");
    let err = PostgresStore::open(&url).expect_err("newer schema");
    assert!(err.to_string().contains("schema version 99"), "{err}");
}

#[test]
fn a_database_from_before_flight_tables_is_migrated() {
    let Some(url) = fresh_database("migration_flight") else {
        return;
    };
    let migrations = super::super::postgres_conn::MIGRATIONS;
    let mut c = postgres::Client::connect(&url, NoTls).expect("connect");
    for sql in &migrations[..2] {
        c.batch_execute(sql).expect("old schema");
    }
    c.batch_execute(
        "CREATE TABLE canopy_schema (version INTEGER NOT NULL); INSERT INTO canopy_schema VALUES (2);
         INSERT INTO scenes (id, name, public, min_x, min_z, max_x, max_z, version, next_id, instance_count, \
         write_hash, created_unix) VALUES ('old', 'Old', TRUE, 0, 0, 10, 10, 1, 1, 0, '\\x00', 5);",
    )
    .expect("old rows");
    let s = open(&url);
    assert_eq!(s.flight_table("old").expect("migrated"), None);
    s.set_flight_table("old", &contract::flight_table_json(1)).expect("set");
    assert!(s.flight_table("old").expect("get").is_some());
    // And so from before terrains (migration 4).
    assert_eq!(s.terrain("old").expect("migrated"), None);
}

#[test]
fn a_database_that_is_not_there_is_unavailable_not_a_panic_or_a_failed_start() {
    // A port nothing listens on (bound, then closed).
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("port")
        .port();
    let s = PostgresStore::open(&format!("postgres://canopy@127.0.0.1:{port}/canopy")).expect("starts");
    assert!(!s.available());
    assert!(
        matches!(s.get("a"), Err(StoreError::Unavailable(_))),
        "{:?}",
        s.get("a")
    );
    assert!(matches!(s.list(), Err(StoreError::Unavailable(_))));
    assert!(matches!(s.flight_table("a"), Err(StoreError::Unavailable(_))));
    assert!(matches!(s.set_flight_table("a", "{}"), Err(StoreError::Unavailable(_))));
    assert!(matches!(s.clear_flight_table("a"), Err(StoreError::Unavailable(_))));
    assert!(matches!(s.terrain("a"), Err(StoreError::Unavailable(_))));
    assert!(matches!(
        PostgresStore::open("postgres://[bad"),
        Err(StoreError::Database(_))
    ));
}

#[test]
fn change_notifications_skip_the_replicas_own_and_malformed_ones() {
    let own = 7;
    assert_eq!(
        change_of(r#"{"replica":"8","scene":"a","version":3}"#, own),
        Some(SceneChange::Version {
            scene: "a".into(),
            version: 3
        })
    );
    assert_eq!(
        change_of(r#"{"replica":"8","scene":"a","version":null}"#, own),
        Some(SceneChange::Deleted { scene: "a".into() })
    );
    assert_eq!(change_of(r#"{"replica":"7","scene":"a","version":3}"#, own), None);
    for bad in [
        "",
        "{",
        "[]",
        r#"{"replica":8,"scene":"a"}"#,
        r#"{"replica":"x","scene":"a"}"#,
        r#"{"replica":"8"}"#,
    ] {
        assert_eq!(change_of(bad, own), None, "{bad}");
    }
}

#[test]
fn concurrent_creation_on_two_replicas_keeps_the_owner_quota_and_ids_unique() {
    let Some(url) = fresh_database("creation") else {
        return;
    };
    let replicas = [Arc::new(open(&url)), Arc::new(open(&url))];
    let l = Limits {
        max_scenes: 5,
        ..Limits::default()
    };
    // Eight creators, four per replica, each trying 3 scenes of one owner: ids s0..s11, two
    // creators per id (one on each replica).
    let creators: Vec<_> = (0..8)
        .map(|k| {
            let s = replicas[k % 2].clone();
            std::thread::spawn(move || {
                let mut made = Vec::new();
                for n in 0..3 {
                    let id = format!("s{}", (k / 2) * 3 + n);
                    let mut ok = |m: &SceneMeta, l: &[Instance], _: &Changes| contract::published(m, l);
                    match s.create(&contract::new_scene(&id, "alice"), &[], &l, &mut ok) {
                        Ok(_) => made.push(id),
                        Err(StoreError::Quota(_) | StoreError::Exists(_)) => {}
                        Err(e) => panic!("create {id}: {e}"),
                    }
                }
                made
            })
        })
        .collect();
    let mut made: Vec<String> = creators.into_iter().flat_map(|c| c.join().expect("creator")).collect();
    made.sort();
    let before = made.len();
    made.dedup();
    assert_eq!(made.len(), before, "an id created twice: {made:?}");
    assert_eq!(made.len(), 5, "exactly the quota: {made:?}");
    let listed: Vec<String> = replicas[1].list().expect("list").into_iter().map(|m| m.id).collect();
    assert_eq!(listed.len(), 5, "{listed:?}");
}

#[test]
fn presence_payloads_carry_their_replica_and_skip_its_own() {
    use super::super::postgres_conn::presence_of;
    assert_eq!(
        presence_of("8 {\"scene\":\"a\"}", 7),
        Some(SceneChange::Presence {
            payload: "{\"scene\":\"a\"}".into()
        })
    );
    assert_eq!(presence_of("7 {}", 7), None);
    for bad in ["", "8", "x {}", "-1 {}"] {
        assert_eq!(presence_of(bad, 7), None, "{bad}");
    }
}

#[test]
fn presence_relayed_by_one_replica_reaches_the_other_only() {
    let Some(url) = fresh_database("presence") else {
        return;
    };
    let (s1, s2) = (open(&url), open(&url));
    let (tx1, rx1) = std::sync::mpsc::channel();
    let (tx2, rx2) = std::sync::mpsc::channel();
    s1.watch(Box::new(move |c| drop(tx1.send(c))));
    s2.watch(Box::new(move |c| drop(tx2.send(c))));
    // The listeners connect on their own threads: relay until the other replica hears.
    let t0 = std::time::Instant::now();
    let heard = loop {
        s1.relay_presence("hello".into());
        if let Ok(c) = rx2.recv_timeout(Duration::from_millis(100)) {
            break c;
        }
        assert!(t0.elapsed() < Duration::from_secs(10), "never relayed");
    };
    assert_eq!(
        heard,
        SceneChange::Presence {
            payload: "hello".into()
        }
    );
    std::thread::sleep(Duration::from_millis(200));
    assert!(rx1.try_iter().next().is_none(), "a replica hears its own presence");
}

#[test]
fn a_scene_deleted_and_made_again_on_another_replica_is_not_built_from_the_old_list() {
    let Some(url) = fresh_database("incarnation") else {
        return;
    };
    let (s1, s2) = (open(&url), open(&url));
    let l = Limits::default();
    let mut ok = |m: &SceneMeta, l: &[Instance], _: &Changes| contract::published(m, l);
    s1.create(&contract::new_scene("a", ""), &[contract::add(1.0)], &l, &mut ok)
        .expect("create");
    s1.edit("a", &contract::one_add(), &l, &mut ok)
        .expect("edit: s1 keeps version 2's list");
    // Within the same second: same id, same created second, same version number.
    assert!(s2.delete("a").expect("delete"));
    s2.create(&contract::new_scene("a", ""), &[contract::add(50.0)], &l, &mut ok)
        .expect("again");
    s2.edit("a", &contract::one_add(), &l, &mut ok).expect("to version 2");
    let e = s1.edit("a", &contract::one_add(), &l, &mut ok).expect("edit on s1");
    assert_eq!((e.meta.version, e.meta.instance_count), (3, 3));
    let xs: Vec<f32> = s1.instances("a").expect("list").iter().map(|i| i.position[0]).collect();
    assert_eq!(xs, vec![50.0, 5.0, 5.0], "built from the new scene's rows");
}

#[test]
fn a_listener_cut_off_listens_again_and_asks_for_a_resync() {
    let Some(url) = fresh_database("resync") else {
        return;
    };
    let store = open(&url);
    let (tx, rx) = std::sync::mpsc::channel();
    store.watch(Box::new(move |c| drop(tx.send(c))));
    let mut admin = postgres::Client::connect(&url, NoTls).expect("admin connection");
    let listeners = "SELECT pid FROM pg_stat_activity WHERE datname = current_database() \
                     AND query LIKE 'LISTEN%' AND pid <> pg_backend_pid()";
    let t0 = std::time::Instant::now();
    while admin.query(listeners, &[]).expect("activity").is_empty() {
        assert!(t0.elapsed() < Duration::from_secs(10), "the listener never connected");
        std::thread::sleep(Duration::from_millis(50));
    }
    // Connecting the first time asks for nothing: there was nothing to miss.
    assert!(rx.recv_timeout(Duration::from_millis(300)).is_err());
    let cut = admin
        .execute(
            &format!("SELECT pg_terminate_backend(pid) FROM ({listeners}) AS l"),
            &[],
        )
        .expect("terminate");
    assert_eq!(cut, 1);
    let heard = rx
        .recv_timeout(Duration::from_secs(5))
        .expect("a resync after listening again");
    assert_eq!(heard, SceneChange::Resync);
}

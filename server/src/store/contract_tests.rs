//! The scene store's contract, as test bodies every backend runs (`sqlite_tests.rs`,
//! `postgres_tests.rs`): versions, refusals that change nothing, quotas, retention, pins, reads
//! beside a writer, compare-and-swap between two processes, the per-scene flight table, and the
//! scene's terrain (versioned).

use std::sync::Arc;

use super::scenes::{
    Bounds, Changes, EditBatch, Instance, Limits, MoveInstance, NewInstance, NewScene, Published, SceneAuth, SceneMeta,
    SceneStore, StoreError,
};

/// Seconds since the epoch.
pub fn now_unix() -> u64 {
    super::sqlite::now_unix()
}

pub fn new_scene(id: &str, owner: &str) -> NewScene {
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
        owner: owner.into(),
        terrain: None,
    }
}

pub fn add(x: f32) -> NewInstance {
    NewInstance {
        model: "oak".into(),
        position: [x, 0.0, 1.0],
        rotation: 0.0,
        scale: 1.0,
    }
}

#[allow(clippy::unnecessary_wraps)] // the shape of a `Publish`
pub fn published(m: &SceneMeta, l: &[Instance]) -> Result<Published, StoreError> {
    let manifest = format!("{{\"v\":{},\"n\":{}}}", m.version, l.len());
    Ok(Published {
        bytes: 100 + 28 * l.len() as u64,
        files: vec![format!("scenes/{}/v{}.x.cpack", m.id, m.version)],
        manifest,
    })
}

pub fn one_add() -> EditBatch {
    EditBatch {
        add: vec![add(5.0)],
        ..EditBatch::default()
    }
}

pub fn create_edit_version_and_failed_publish_changes_nothing(s: &dyn SceneStore) {
    let l = Limits::default();
    let mut ok = |m: &SceneMeta, l: &[Instance], _: &Changes| published(m, l);
    let m = s
        .create(&new_scene("a", ""), &[add(1.0), add(2.0)], &l, &mut ok)
        .expect("create");
    assert_eq!((m.version, m.instance_count), (1, 2));
    assert!(matches!(
        s.create(&new_scene("a", ""), &[], &l, &mut ok),
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
    let m = s.edit("a", &batch, &l, &mut ok).expect("edit").meta;
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
        s.edit("a", &batch, &l, &mut ok),
        Err(StoreError::Conflict {
            current: 2,
            expected: 1
        })
    ));
    let bad = EditBatch {
        remove: vec![2],
        ..EditBatch::default()
    };
    assert!(matches!(s.edit("a", &bad, &l, &mut ok), Err(StoreError::Invalid(_))));
    let dup = EditBatch {
        remove: vec![1, 1],
        ..EditBatch::default()
    };
    assert!(matches!(s.edit("a", &dup, &l, &mut ok), Err(StoreError::Invalid(_))));
    let mut fail = |_: &SceneMeta, _: &[Instance], _: &Changes| Err(StoreError::Publish("disk full".into()));
    let good = EditBatch {
        remove: vec![1],
        ..EditBatch::default()
    };
    assert!(s.edit("a", &good, &l, &mut fail).is_err());
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

pub fn quotas_per_owner_refuse_and_change_nothing(s: &dyn SceneStore) {
    let l = Limits {
        max_scenes: 2,
        max_instances: 3,
        max_bytes: 1_000,
        ..Limits::default()
    };
    let mut ok = |m: &SceneMeta, l: &[Instance], _: &Changes| published(m, l);
    s.create(&new_scene("a", "alice"), &[add(1.0)], &l, &mut ok).expect("a");
    s.create(&new_scene("b", "alice"), &[], &l, &mut ok).expect("b");
    let mut calls = 0;
    let mut counted = |m: &SceneMeta, l: &[Instance], _: &Changes| {
        calls += 1;
        published(m, l)
    };
    assert!(matches!(
        s.create(&new_scene("c", "alice"), &[], &l, &mut counted),
        Err(StoreError::Quota(_))
    ));
    assert_eq!(calls, 0, "a creation over the scene quota publishes nothing");
    // Another owner, and the server's own scenes, are not alice's quota.
    s.create(&new_scene("c", "bob"), &[], &l, &mut ok).expect("bob");
    s.create(&new_scene("d", ""), &vec![add(1.0); 5], &l, &mut ok)
        .expect("no quota for the server's own scenes");
    // Instances per scene.
    let three = EditBatch {
        add: vec![add(2.0), add(3.0), add(4.0)],
        ..EditBatch::default()
    };
    assert!(matches!(s.edit("a", &three, &l, &mut ok), Err(StoreError::Quota(_))));
    assert_eq!(s.get("a").expect("get").map(|m| m.version), Some(1));
    // Bytes: each version of "a" takes 100 + 28 n; alice holds 128 + 100 now.
    let l2 = Limits { max_bytes: 400, ..l };
    let e = s.edit("a", &one_add(), &l2, &mut ok).expect("within the bytes quota");
    assert_eq!(e.meta.version, 2);
    assert!(matches!(
        s.edit("a", &one_add(), &l2, &mut ok),
        Err(StoreError::Quota(_))
    ));
    assert_eq!(s.get("a").expect("get").map(|m| m.version), Some(2));
    // Retention frees bytes: keeping one version, the same edit fits.
    let l3 = Limits { keep_versions: 1, ..l2 };
    let e = s.edit("a", &one_add(), &l3, &mut ok).expect("after pruning");
    assert_eq!(e.pruned.iter().map(|p| p.version).collect::<Vec<_>>(), vec![1, 2]);
    assert_eq!(e.pruned[0].files, vec!["scenes/a/v1.x.cpack".to_string()]);
}

pub fn retention_keeps_the_last_versions_the_pinned_and_the_current(s: &dyn SceneStore) {
    let l = Limits {
        keep_versions: 3,
        ..Limits::default()
    };
    let mut ok = |m: &SceneMeta, l: &[Instance], _: &Changes| published(m, l);
    s.create(&new_scene("a", "o"), &[], &l, &mut ok).expect("create");
    assert_eq!(s.pin("a", None, true, &l).expect("pin v1"), vec![1]);
    let mut gone = Vec::new();
    for _ in 0..9 {
        gone.extend(s.edit("a", &one_add(), &l, &mut ok).expect("edit").pruned);
    }
    // Versions 1..=10; kept: 1 (pinned), 8, 9, 10.
    let kept: Vec<u64> = s.versions("a").expect("versions").iter().map(|v| v.version).collect();
    assert_eq!(kept, vec![1, 8, 9, 10]);
    assert_eq!(
        gone.iter().map(|p| p.version).collect::<Vec<_>>(),
        (2..=7).collect::<Vec<_>>()
    );
    assert!(s.manifest("a", Some(5)).expect("m").is_none());
    assert!(matches!(s.pin("a", Some(5), true, &l), Err(StoreError::NoVersion(5))));
    // Unpinned, version 1 goes at the next prune; the age rule keeps young versions.
    assert_eq!(s.pin("a", Some(1), false, &l).expect("unpin"), Vec::<u64>::new());
    let by_age = Limits {
        keep_versions: 1,
        keep_secs: 3600,
        ..l
    };
    assert!(
        s.prune(&by_age, now_unix()).expect("prune").is_empty(),
        "all younger than an hour"
    );
    let p = s.prune(&by_age, now_unix() + 7200).expect("prune");
    assert_eq!(p.iter().map(|p| p.version).collect::<Vec<_>>(), vec![1, 8, 9]);
    let files = s.files().expect("files");
    assert_eq!(files.len(), 1);
    assert_eq!(
        (files[0].version, files[0].files.clone()),
        (10, vec!["scenes/a/v10.x.cpack".to_string()])
    );
    // Pins are bounded.
    let few = Limits { max_pins: 1, ..l };
    s.pin("a", None, true, &few).expect("pin");
    s.pin("a", None, true, &few).expect("pinning twice is one pin");
    s.edit("a", &one_add(), &l, &mut ok).expect("edit");
    assert!(matches!(s.pin("a", None, true, &few), Err(StoreError::Quota(_))));
    assert!(matches!(s.pin("zz", None, true, &few), Err(StoreError::NotFound(_))));
}

pub fn reads_do_not_wait_for_a_publish_in_progress(s: &Arc<dyn SceneStore>) {
    let l = Limits::default();
    let mut ok = |m: &SceneMeta, l: &[Instance], _: &Changes| published(m, l);
    s.create(&new_scene("a", "o"), &[add(1.0)], &l, &mut ok).expect("a");
    s.create(&new_scene("b", "o"), &[add(1.0)], &l, &mut ok).expect("b");
    let (started_tx, started) = std::sync::mpsc::channel();
    let (release_tx, release) = std::sync::mpsc::channel::<()>();
    let writer = {
        let s = s.clone();
        std::thread::spawn(move || {
            let mut slow = |m: &SceneMeta, l: &[Instance], _: &Changes| {
                let _ = started_tx.send(());
                let _ = release.recv();
                published(m, l)
            };
            s.edit("a", &one_add(), &Limits::default(), &mut slow)
                .map(|e| e.meta.version)
        })
    };
    started.recv().expect("publishing");
    // While scene a's new version is being written, b (and a's old version) read and edit.
    assert_eq!(s.get("a").expect("get").map(|m| m.version), Some(1));
    assert_eq!(s.instance_table("b").expect("table").rows.len(), 1);
    assert_eq!(s.edit("b", &one_add(), &l, &mut ok).expect("edit b").meta.version, 2);
    release_tx.send(()).expect("release");
    assert_eq!(writer.join().expect("join").expect("edit a"), 2);
    assert_eq!(s.get("a").expect("get").map(|m| m.instance_count), Some(2));
}

/// `s1` and `s2` are two stores on one database, standing for two processes (replicas): the
/// in-process scene lock cannot order them.
pub fn a_version_commits_only_over_the_version_it_was_built_from(s1: &dyn SceneStore, s2: &dyn SceneStore) {
    let l = Limits::default();
    let mut ok = |m: &SceneMeta, l: &[Instance], _: &Changes| published(m, l);
    s1.create(&new_scene("a", "o"), &[], &l, &mut ok).expect("a");
    let mut raced = false;
    let mut racing = |m: &SceneMeta, l: &[Instance], _: &Changes| {
        if !raced {
            raced = true;
            s2.edit("a", &one_add(), &Limits::default(), &mut |m, l, _| published(m, l))
                .expect("the other process");
        }
        published(m, l)
    };
    let e = s1
        .edit("a", &one_add(), &l, &mut racing)
        .expect("retried over version 2");
    assert_eq!((e.meta.version, e.meta.instance_count), (3, 2));
    assert_eq!(
        s1.instances("a")
            .expect("list")
            .iter()
            .map(|i| i.id)
            .collect::<Vec<_>>(),
        vec![1, 2]
    );
    let v: Vec<u64> = s1.versions("a").expect("v").iter().map(|v| v.version).collect();
    assert_eq!(v, vec![1, 2, 3]);
    // With a base version, a lost race is the client's conflict.
    let mut raced = false;
    let mut racing = |m: &SceneMeta, l: &[Instance], _: &Changes| {
        if !raced {
            raced = true;
            s2.edit("a", &one_add(), &Limits::default(), &mut |m, l, _| published(m, l))
                .expect("the other process");
        }
        published(m, l)
    };
    let based = EditBatch {
        base_version: Some(3),
        ..one_add()
    };
    assert!(matches!(
        s1.edit("a", &based, &l, &mut racing),
        Err(StoreError::Conflict {
            current: 4,
            expected: 3
        })
    ));
}

/// A checked flight table's text, as the HTTP layer stores it; `top` is its last cell.
pub fn flight_table_json(top: u8) -> String {
    let v = serde_json::json!({
        "format": "canopy-flight-table", "format_version": 1, "dh_m": 20.0, "dv_mps": 10.0,
        "offsets": [[0, 0, 1], [0, 1, top]],
        "policy": {"sigma_m": [100.0, 250.0, 500.0, 1000.0], "field_deg": 120.0, "threat_time_s": 2.0},
        "method": {"metric": "ssim", "threshold": 0.95, "width": 480, "height": 270, "fps": 30.0, "viewpoints": 2}
    });
    canopy_shared::flight_table::FlightTable::parse(v.to_string().as_bytes())
        .and_then(|t| Ok(t.to_json()?))
        .expect("a valid table")
}

pub fn a_flight_table_is_a_scene_property_gone_with_the_scene(s: &dyn SceneStore) {
    let l = Limits::default();
    let mut ok = |m: &SceneMeta, l: &[Instance], _: &Changes| published(m, l);
    s.create(&new_scene("a", "o"), &[add(1.0)], &l, &mut ok).expect("a");
    s.create(&new_scene("b", "o"), &[], &l, &mut ok).expect("b");
    let (t1, t2) = (flight_table_json(2), flight_table_json(3));
    assert_eq!(s.flight_table("a").expect("get"), None, "none before one is set");
    s.set_flight_table("a", &t1).expect("set");
    assert_eq!(s.flight_table("a").expect("get").as_deref(), Some(t1.as_str()));
    assert_eq!(s.flight_table("b").expect("get"), None, "per scene");
    // Not versioned: the scene is still at version 1, with one version kept.
    assert_eq!(s.get("a").expect("get").map(|m| m.version), Some(1));
    assert_eq!(s.versions("a").expect("versions").len(), 1);
    s.set_flight_table("a", &t2).expect("replace");
    assert_eq!(s.flight_table("a").expect("get").as_deref(), Some(t2.as_str()));
    // An edit (a new version) keeps it.
    s.edit("a", &one_add(), &l, &mut ok).expect("edit");
    assert_eq!(s.flight_table("a").expect("get").as_deref(), Some(t2.as_str()));
    assert!(s.clear_flight_table("a").expect("clear"));
    assert_eq!(s.flight_table("a").expect("get"), None);
    assert!(!s.clear_flight_table("a").expect("clearing none"));
    // An unknown scene is not found, and setting a table does not make it.
    assert!(matches!(s.flight_table("zz"), Err(StoreError::NotFound(_))));
    assert!(matches!(s.set_flight_table("zz", &t1), Err(StoreError::NotFound(_))));
    assert!(matches!(s.clear_flight_table("zz"), Err(StoreError::NotFound(_))));
    assert!(s.get("zz").expect("get").is_none());
    // Gone with the scene: the same id made again has none.
    s.set_flight_table("a", &t1).expect("set");
    s.set_flight_table("b", &t2).expect("set b");
    assert!(s.delete("a").expect("delete"));
    assert!(matches!(s.flight_table("a"), Err(StoreError::NotFound(_))));
    s.create(&new_scene("a", "o"), &[], &l, &mut ok).expect("a again");
    assert_eq!(s.flight_table("a").expect("get"), None, "a new scene of the same id");
    assert_eq!(s.flight_table("b").expect("get").as_deref(), Some(t2.as_str()));
}

/// `open` opens a store on the same database each time (a restart between the calls).
pub fn a_flight_table_survives_a_restart(open: &dyn Fn() -> Box<dyn SceneStore>) {
    let t = flight_table_json(4);
    {
        let s = open();
        let mut ok = |m: &SceneMeta, l: &[Instance], _: &Changes| published(m, l);
        s.create(&new_scene("a", ""), &[], &Limits::default(), &mut ok)
            .expect("create");
        s.set_flight_table("a", &t).expect("set");
    }
    let s = open();
    assert_eq!(s.flight_table("a").expect("get").as_deref(), Some(t.as_str()));
}

/// A terrain's stored text (the store keeps it as given); `k` tells two apart.
pub fn terrain_json(k: u32) -> String {
    format!("{{\"url\":\"/assets/scenes/a/terrain.{k:016x}.cterrain\"}}")
}

/// A publisher that records each version's terrain as the store passed it, and fails while
/// `fail` is set.
fn recording<'a>(
    seen: &'a std::cell::RefCell<Vec<(u64, Option<String>)>>,
    fail: &'a std::cell::Cell<bool>,
) -> impl FnMut(&SceneMeta, &[Instance], &Changes) -> Result<Published, StoreError> + 'a {
    move |m, l, ch| {
        seen.borrow_mut()
            .push((m.version, ch.terrain.as_deref().map(String::from)));
        if fail.get() {
            return Err(StoreError::Publish("disk full".into()));
        }
        published(m, l)
    }
}

pub fn a_terrain_is_set_with_a_version_and_kept_by_later_edits(s: &dyn SceneStore) {
    let l = Limits::default();
    let (seen, fail) = (std::cell::RefCell::new(Vec::new()), std::cell::Cell::new(false));
    let mut publish = recording(&seen, &fail);
    let (t1, t2) = (terrain_json(1), terrain_json(2));
    s.create(&new_scene("a", "o"), &[add(1.0), add(2.0)], &l, &mut publish)
        .expect("a");
    assert_eq!(s.terrain("a").expect("get"), None, "none before one is set");
    // Setting it is a version of the same instances, published on it.
    let e = s.set_terrain("a", Some(&t1), &l, &mut publish).expect("set");
    assert_eq!((e.meta.version, e.meta.instance_count), (2, 2));
    assert_eq!(s.terrain("a").expect("get").as_deref(), Some(t1.as_str()));
    assert_eq!(s.instances("a").expect("instances").len(), 2);
    assert!(s.manifest("a", Some(2)).expect("v2").is_some());
    // An edit builds on it.
    s.edit("a", &one_add(), &l, &mut publish).expect("edit");
    // A refused publish changes nothing.
    fail.set(true);
    assert!(matches!(
        s.set_terrain("a", Some(&t2), &l, &mut publish),
        Err(StoreError::Publish(_))
    ));
    fail.set(false);
    assert_eq!(s.terrain("a").expect("get").as_deref(), Some(t1.as_str()));
    assert_eq!(s.get("a").expect("get").map(|m| m.version), Some(3));
    // Removed: a version on flat ground, and edits after it too.
    let e = s.set_terrain("a", None, &l, &mut publish).expect("clear");
    assert_eq!(e.meta.version, 4);
    assert_eq!(s.terrain("a").expect("get"), None);
    s.edit("a", &one_add(), &l, &mut publish).expect("edit");
    let some = |v: &str| Some(v.to_string());
    assert_eq!(
        *seen.borrow(),
        vec![
            (1, None),
            (2, some(&t1)),
            (3, some(&t1)),
            (4, some(&t2)),
            (4, None),
            (5, None)
        ]
    );
    // From the first version on; an unknown scene is not found; gone with the scene.
    seen.borrow_mut().clear();
    let b = NewScene {
        terrain: Some(t2.clone()),
        ..new_scene("b", "o")
    };
    s.create(&b, &[], &l, &mut publish).expect("b");
    assert_eq!(*seen.borrow(), vec![(1, some(&t2))]);
    assert_eq!(s.terrain("b").expect("get").as_deref(), Some(t2.as_str()));
    assert!(matches!(s.terrain("zz"), Err(StoreError::NotFound(_))));
    assert!(matches!(
        s.set_terrain("zz", Some(&t1), &l, &mut publish),
        Err(StoreError::NotFound(_))
    ));
    assert!(s.delete("b").expect("delete"));
    assert!(matches!(s.terrain("b"), Err(StoreError::NotFound(_))));
    s.create(&new_scene("b", "o"), &[], &l, &mut publish).expect("b again");
    assert_eq!(s.terrain("b").expect("get"), None, "a new scene of the same id");
}

/// `open` opens a store on the same database each time (a restart between the calls).
pub fn a_terrain_survives_a_restart(open: &dyn Fn() -> Box<dyn SceneStore>) {
    let t = terrain_json(7);
    {
        let s = open();
        let mut ok = |m: &SceneMeta, l: &[Instance], _: &Changes| published(m, l);
        s.create(&new_scene("a", ""), &[add(1.0)], &Limits::default(), &mut ok)
            .expect("create");
        s.set_terrain("a", Some(&t), &Limits::default(), &mut ok).expect("set");
    }
    let s = open();
    assert_eq!(s.terrain("a").expect("get").as_deref(), Some(t.as_str()));
    let mut seen = None;
    let mut keep = |m: &SceneMeta, l: &[Instance], ch: &Changes| {
        seen = ch.terrain.as_deref().map(String::from);
        published(m, l)
    };
    s.edit("a", &one_add(), &Limits::default(), &mut keep).expect("edit");
    assert_eq!(seen.as_deref(), Some(t.as_str()), "read back for the next version");
}

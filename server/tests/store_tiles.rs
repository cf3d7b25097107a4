//! Packs stored per tile (issue 23): an edit writes what it changed, not the scene; what a client
//! reads after edits is a full rebuild byte for byte; garbage collection keeps shared tile blobs;
//! a data folder from before (whole packs only) still opens and edits. On a real data folder
//! (SQLite file in WAL mode, assets on disk), bounded (a 50,000-instance scene).

use std::collections::{BTreeSet, HashSet};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use axum::body::Body;
use axum::http::{Request, StatusCode};
use canopy_server::demo::{bake_and_store, synthetic_model};
use canopy_server::http::scenes::{CreateScene, apply_edit, create_scene};
use canopy_server::http::{AppState, HttpConfig, router};
use canopy_server::store::scenes::{
    Bounds, EditBatch, Instance, Limits, MoveInstance, NewInstance, NewScene, Published, SceneAuth,
};
use canopy_server::store::{AssetStore, SqliteStore, gc, pack, tiles};
use canopy_shared::manifest::{MANIFEST_FORMAT, MANIFEST_VERSION, Manifest, ManifestBounds, ManifestPack};
use tower::ServiceExt;

struct Data {
    dir: PathBuf,
}

impl Drop for Data {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

impl Data {
    fn new(name: &str) -> Self {
        let dir = std::env::temp_dir().join(format!("canopy-store-tiles-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        Self { dir }
    }

    fn open(&self, limits: Limits) -> AppState {
        let assets = Arc::new(AssetStore::open(&self.dir.join("assets")).expect("assets"));
        let scenes = Arc::new(SqliteStore::open(&self.dir.join("canopy.db")).expect("db"));
        AppState::new(
            assets,
            scenes,
            HttpConfig {
                limits,
                ..HttpConfig::default()
            },
        )
        .0
    }
}

fn bounds() -> Bounds {
    Bounds {
        min: [-1000.0, -1000.0],
        max: [1000.0, 1000.0],
    }
}

fn spread(model: &str, from: u32, n: u32) -> Vec<NewInstance> {
    (from..from + n)
        .map(|k| {
            let k = f64::from(k);
            NewInstance {
                model: model.to_string(),
                position: [
                    ((k * 0.618_034).fract() * 1900.0 - 950.0) as f32,
                    0.0,
                    ((k * 0.414_214).fract() * 1900.0 - 950.0) as f32,
                ],
                rotation: 0.5,
                scale: 1.0,
            }
        })
        .collect()
}

/// A public scene of `n` instances (creation, then batches of 10,000 adds).
fn big_scene(state: &AppState, id: &str, model: &str, n: u32) {
    let first = n.min(10_000);
    create_scene(
        state,
        &CreateScene {
            id: Some(id.into()),
            name: id.into(),
            public: true,
            bounds: bounds(),
            instances: spread(model, 0, first),
        },
    )
    .expect("create");
    let limits = state.inner.config.limits;
    let mut at = first;
    while at < n {
        let k = (n - at).min(10_000);
        let add = EditBatch {
            add: spread(model, at, k),
            ..EditBatch::default()
        };
        apply_edit(state, id, &add, &limits).expect("add");
        at += k;
    }
}

fn move_one(state: &AppState, id: &str, which: u32, to: [f32; 3]) {
    let mv = EditBatch {
        moves: vec![MoveInstance {
            id: which,
            position: to,
            rotation: None,
            scale: None,
        }],
        ..EditBatch::default()
    };
    apply_edit(state, id, &mv, &state.inner.config.limits).expect("move");
}

/// Bytes this process has handed to `write` and friends (`/proc/self/io` `wchar`).
fn written() -> Option<u64> {
    let io = std::fs::read_to_string("/proc/self/io").ok()?;
    io.lines().find_map(|l| l.strip_prefix("wchar: ")?.trim().parse().ok())
}

fn files(dir: &Path) -> Vec<(PathBuf, u64)> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).into_iter().flatten().flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else {
                out.push((p.clone(), e.metadata().map_or(0, |m| m.len())));
            }
        }
    }
    out
}

/// The whole asset at `url`, through the router (as a client gets it).
async fn get(state: &AppState, url: &str, range: Option<&str>) -> (StatusCode, Vec<u8>) {
    let mut req = Request::builder().uri(url).header("host", "x");
    if let Some(r) = range {
        req = req.header("range", r);
    }
    let resp = router(state.clone())
        .oneshot(req.body(Body::empty()).expect("req"))
        .await
        .expect("infallible");
    let status = resp.status();
    let body = axum::body::to_bytes(resp.into_body(), usize::MAX).await.expect("body");
    (status, body.to_vec())
}

fn manifest(state: &AppState, id: &str, version: Option<u64>) -> Manifest {
    let text = state.inner.scenes.manifest(id, version).expect("db").expect("manifest");
    Manifest::parse(text.as_bytes()).expect("valid manifest")
}

/// What a full rebuild of the current instances writes.
fn rebuild(state: &AppState, id: &str) -> Vec<u8> {
    let list = state.inner.scenes.instances(id).expect("instances");
    let names: Vec<String> = list
        .iter()
        .map(|i| i.model.clone())
        .collect::<BTreeSet<_>>()
        .into_iter()
        .collect();
    let pis: Vec<pack::PackInstance> = list
        .iter()
        .map(|i| pack::PackInstance {
            id: i.id,
            model: names.binary_search(&i.model).expect("model") as u16,
            position: i.position,
            rotation: i.rotation,
            scale: i.scale,
        })
        .collect();
    pack::build(bounds().as_f32(), &names, &pis).expect("build").0
}

#[test]
fn a_one_instance_edit_writes_its_tiles_and_the_index_not_the_scene() {
    let data = Data::new("bytes");
    let state = data.open(Limits::default());
    let model = bake_and_store(&state, &synthetic_model(0)).expect("bake");
    big_scene(&state, "big", &model, 50_000);
    let pack_len = manifest(&state, "big", None).pack.size;
    let before: HashSet<PathBuf> = files(&data.dir).into_iter().map(|(p, _)| p).collect();
    let w0 = written();
    move_one(&state, "big", 17, [5.0, 0.0, 5.0]);
    let w1 = written();
    let new_files: u64 = files(&data.dir.join("assets"))
        .into_iter()
        .filter(|(p, _)| !before.contains(p))
        .map(|(_, n)| n)
        .sum();
    let m = manifest(&state, "big", None);
    let tiles = m.tiles.len() as u64;
    eprintln!(
        "pack {pack_len} B, {tiles} tiles; one move: new asset files {new_files} B, all writes {:?} B",
        w0.zip(w1).map(|(a, b)| b - a)
    );
    // The touched tiles, the index (32 + 24 B per tile, the pack's head) and the manifest
    // (about 130 B per tile): a tenth of the pack, not the pack.
    assert!(
        new_files < pack_len / 8,
        "{new_files} B of new files for a {pack_len} B pack"
    );
    if let (Some(a), Some(b)) = (w0, w1) {
        // Plus the database: the version row (the manifest again) and its WAL pages.
        assert!(b - a < pack_len / 4, "{} B written for a {pack_len} B pack", b - a);
    }
}

#[tokio::test]
async fn after_edits_a_client_reads_a_full_rebuild_byte_for_byte() {
    let data = Data::new("rebuild");
    let state = data.open(Limits::default());
    let models: Vec<String> = (0..2)
        .map(|k| bake_and_store(&state, &synthetic_model(k)).expect("bake"))
        .collect();
    big_scene(&state, "s", &models[0], 12_000);
    let limits = state.inner.config.limits;
    let edits = [
        EditBatch {
            moves: vec![MoveInstance {
                id: 3,
                position: [-999.0, 1.0, 999.0],
                rotation: Some(2.0),
                scale: Some(1.5),
            }],
            ..EditBatch::default()
        },
        EditBatch {
            remove: (100..400).collect(),
            ..EditBatch::default()
        },
        EditBatch {
            add: spread(&models[1], 90_000, 700),
            ..EditBatch::default()
        },
        EditBatch {
            remove: (1..=12_000).filter(|k| k % 7 == 0 && !(100..400).contains(k)).collect(),
            ..EditBatch::default()
        },
    ];
    for e in &edits {
        apply_edit(&state, "s", e, &limits).expect("edit");
        let m = manifest(&state, "s", None);
        let (status, body) = get(&state, &m.pack.url, None).await;
        assert_eq!(status, StatusCode::OK);
        assert_eq!(body.len() as u64, m.pack.size);
        assert!(
            body == rebuild(&state, "s"),
            "version {}: not a full rebuild",
            m.version
        );
        let decoded = pack::decode(&body).expect("decodes");
        assert_eq!(decoded.tiles, m.tiles);
        assert_eq!(canopy_server::store::assets::sha256_hex(&body), m.pack.sha256);
        // A client's tile ranges, several in one request, come back checked.
        let t = &m.tiles[m.tiles.len() / 2];
        let (status, one) = get(
            &state,
            &m.pack.url,
            Some(&format!("bytes={}-{}", t.offset, t.offset + t.length - 1)),
        )
        .await;
        assert_eq!(status, StatusCode::PARTIAL_CONTENT);
        pack::decode_tile_records(&one, t.crc32, m.models.len()).expect("tile checks");
    }
    // After a restart, the same bytes.
    let m = manifest(&state, "s", None);
    let want = rebuild(&state, "s");
    drop(state);
    let state = data.open(Limits::default());
    assert!(get(&state, &m.pack.url, None).await.1 == want);
}

#[tokio::test]
async fn retention_and_sweeps_keep_shared_tiles_and_delete_the_rest() {
    let data = Data::new("gc");
    let limits = Limits {
        keep_versions: 2,
        ..Limits::default()
    };
    let state = data.open(limits);
    let model = bake_and_store(&state, &synthetic_model(0)).expect("bake");
    big_scene(&state, "g", &model, 8_000);
    for k in 0..6u16 {
        move_one(&state, "g", 1 + u32::from(k) * 501, [f32::from(k), 0.0, -3.0]);
    }
    let assets = state.inner.assets.clone();
    let check = |state: &AppState| {
        let kept = state.inner.scenes.versions("g").expect("versions");
        assert_eq!(kept.len(), 2, "the last 2, the current one among them");
        let named = tiles::referenced(&state.inner.assets, "scenes/g").expect("indexes readable");
        let on_disk: HashSet<String> = std::fs::read_dir(data.dir.join("assets/scenes/g"))
            .expect("ls")
            .flatten()
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .filter(|n| Path::new(n).extension().is_some_and(|e| e == "ctile"))
            .map(|n| format!("scenes/g/{n}"))
            .collect();
        assert_eq!(on_disk, named, "exactly the tiles kept indexes name");
        kept
    };
    let kept = check(&state);
    // The blob written by a publish that never committed, and a stray one: nothing names them.
    let stray = assets.put("scenes/g", "t", "ctile", &[0u8; 28]).expect("stray");
    let swept = gc::sweep(&assets, state.inner.scenes.as_ref(), Duration::from_mins(10)).expect("sweep");
    assert_eq!(
        swept.files, 1,
        "unreferenced blobs need no grace under the folder's lock"
    );
    assert!(assets.get(&stray.rel).is_none());
    check(&state);
    for v in &kept {
        let m = manifest(&state, "g", Some(v.version));
        let (status, body) = get(&state, &m.pack.url, None).await;
        assert_eq!(status, StatusCode::OK, "version {}", v.version);
        pack::decode(&body).expect("kept versions stay whole");
    }
    // And after a restart with a start-up collection.
    drop(state);
    let state = data.open(limits);
    gc::collect(
        &state.inner.assets,
        state.inner.scenes.as_ref(),
        &limits,
        u64::MAX / 2,
        Duration::ZERO,
    )
    .expect("gc");
    check(&state);
}

/// A version written the way the server did before packs were stored per tile: the whole pack
/// and the manifest, nothing else.
fn old_publish(assets: &AssetStore, meta: &canopy_server::store::scenes::SceneMeta, list: &[Instance]) -> Published {
    let names: Vec<String> = list
        .iter()
        .map(|i| i.model.clone())
        .collect::<BTreeSet<_>>()
        .into_iter()
        .collect();
    let pis: Vec<pack::PackInstance> = list
        .iter()
        .map(|i| pack::PackInstance {
            id: i.id,
            model: names.binary_search(&i.model).expect("model") as u16,
            position: i.position,
            rotation: i.rotation,
            scale: i.scale,
        })
        .collect();
    let (bytes, tiles) = pack::build(meta.bounds.as_f32(), &names, &pis).expect("build");
    let dir = format!("scenes/{}", meta.id);
    let p = assets
        .put(&dir, &format!("v{}", meta.version), "cpack", &bytes)
        .expect("pack");
    let models = names
        .iter()
        .map(|n| {
            let a = &assets.models()[n];
            canopy_shared::manifest::ManifestModel {
                name: n.clone(),
                url: a.url(),
                sha256: a.sha256.clone(),
                size: a.len,
                // Written before the server made discrete LOD files.
                levels: Vec::new(),
            }
        })
        .collect();
    let m = Manifest {
        format: MANIFEST_FORMAT.into(),
        format_version: MANIFEST_VERSION,
        scene: meta.id.clone(),
        name: meta.name.clone(),
        version: meta.version,
        bounds: ManifestBounds {
            min: meta.bounds.min,
            max: meta.bounds.max,
        },
        instance_count: list.len() as u64,
        models,
        pack: ManifestPack {
            url: p.url(),
            sha256: p.sha256.clone(),
            size: p.len,
            tables_len: tiles.first().map_or(bytes.len() as u64, |t| t.offset),
        },
        tiles,
        terrain: None,
    };
    let text = m.to_json().expect("json");
    let j = assets
        .put(&dir, &format!("v{}", meta.version), "json", text.as_bytes())
        .expect("manifest");
    Published {
        bytes: p.len + j.len,
        files: vec![p.rel.clone(), j.rel.clone()],
        manifest: text,
    }
}

#[tokio::test]
async fn a_data_folder_of_whole_packs_opens_serves_and_edits() {
    let data = Data::new("old");
    let limits = Limits {
        keep_versions: 1,
        ..Limits::default()
    };
    let model;
    let old_url;
    {
        let state = data.open(limits);
        model = bake_and_store(&state, &synthetic_model(0)).expect("bake");
        let assets = state.inner.assets.clone();
        let store = state.inner.scenes.clone();
        let scene = NewScene {
            id: "old".into(),
            name: "Old".into(),
            public: true,
            bounds: bounds(),
            auth: SceneAuth {
                write_hash: [1; 32],
                read_hash: None,
            },
            owner: String::new(),
            terrain: None,
        };
        store
            .create(&scene, &spread(&model, 0, 3_000), &limits, &mut |m, l, _| {
                Ok(old_publish(&assets, m, l))
            })
            .expect("old create");
        let add = EditBatch {
            add: spread(&model, 5_000, 10),
            ..EditBatch::default()
        };
        let e = store
            .edit("old", &add, &limits, &mut |m, l, _| Ok(old_publish(&assets, m, l)))
            .expect("old edit");
        gc::remove_files(&assets, &e.pruned);
        old_url = manifest(&state, "old", None).pack.url;
    }
    // Reopened by this server: the old version is served as it was, then edited per tile.
    let state = data.open(limits);
    let (status, body) = get(&state, &old_url, None).await;
    assert_eq!(status, StatusCode::OK);
    assert!(body == rebuild(&state, "old"));
    move_one(&state, "old", 2, [1.0, 0.0, 1.0]);
    let m = manifest(&state, "old", None);
    assert_ne!(m.pack.url, old_url);
    let (status, body) = get(&state, &m.pack.url, None).await;
    assert_eq!(status, StatusCode::OK);
    assert!(
        body == rebuild(&state, "old"),
        "the first edit writes every tile, then reads whole"
    );
    // The old version was pruned with its whole pack.
    assert_eq!(get(&state, &old_url, None).await.0, StatusCode::NOT_FOUND);
    assert!(
        !data
            .dir
            .join("assets")
            .join(old_url.trim_start_matches("/assets/"))
            .exists()
    );
    move_one(&state, "old", 3, [2.0, 0.0, 1.0]);
    let m = manifest(&state, "old", None);
    assert!(get(&state, &m.pack.url, None).await.1 == rebuild(&state, "old"));
}

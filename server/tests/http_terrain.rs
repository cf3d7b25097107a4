//! In-process tests of a scene's terrain through the API (`PUT`, `GET` and `DELETE
//! /api/scenes/{id}/terrain`): each change a new version whose pack places the instances on the
//! terrain (stored y above the ground) and whose manifest names it, kept by later edits; `.cterrain`,
//! PNG and GeoTIFF uploads; refusals that change nothing (content type, bad files, a heightmap of
//! the wrong size or depth, tokens, bounds, body size); read access as the manifest's; the edit
//! rate limit; retention and the sweep with a terrain file shared between versions; the hilly demo;
//! and a database that is away.

use std::io::Cursor;
use std::path::PathBuf;
use std::sync::Arc;

use axum::body::Body;
use axum::http::{HeaderMap, Request, StatusCode};
use canopy_server::demo::{self, DemoConfig, DemoModels, bake_and_store, synthetic_model};
use canopy_server::http::quota::Rate;
use canopy_server::http::{AppState, HttpConfig, router};
use canopy_server::store::scenes::Limits;
use canopy_server::store::{AssetStore, PostgresStore, SceneStore, SqliteStore, gc};
use canopy_shared::manifest::Manifest;
use canopy_shared::terrain::Heightfield;
use image::ImageEncoder;
use serde_json::{Value, json};
use tower::ServiceExt;

struct Fixture {
    app: axum::Router,
    state: AppState,
    dir: PathBuf,
    model: String,
}

impl Drop for Fixture {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("canopy-http-terrain-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

fn fixture_with(name: &str, config: HttpConfig) -> Fixture {
    let dir = temp_dir(name);
    let assets = Arc::new(AssetStore::open(&dir).expect("asset store"));
    let scenes = Arc::new(SqliteStore::in_memory().expect("db"));
    let (state, _stop) = AppState::new(assets, scenes, config);
    let model = bake_and_store(&state, &synthetic_model(0)).expect("bake");
    Fixture {
        app: router(state.clone()),
        state,
        dir,
        model,
    }
}

fn fixture(name: &str) -> Fixture {
    fixture_with(name, HttpConfig::default())
}

struct Reply {
    status: StatusCode,
    headers: HeaderMap,
    body: Vec<u8>,
}

impl Reply {
    fn json(&self) -> Value {
        serde_json::from_slice(&self.body).unwrap_or(Value::Null)
    }

    fn error(&self) -> String {
        self.json()["error"].as_str().unwrap_or_default().to_string()
    }
}

/// A request with a bearer token (when given), extra headers and a body.
async fn send(
    app: &axum::Router,
    method: &str,
    uri: &str,
    token: Option<&str>,
    headers: &[(&str, &str)],
    body: Option<Vec<u8>>,
) -> Reply {
    let mut req = Request::builder().method(method).uri(uri);
    if let Some(t) = token {
        req = req.header("authorization", format!("Bearer {t}"));
    }
    for (k, v) in headers {
        req = req.header(*k, *v);
    }
    let req = req.body(body.map_or_else(Body::empty, Body::from)).expect("request");
    let resp = app.clone().oneshot(req).await.expect("infallible");
    let (parts, body) = resp.into_parts();
    let body = axum::body::to_bytes(body, usize::MAX).await.expect("body").to_vec();
    Reply {
        status: parts.status,
        headers: parts.headers,
        body,
    }
}

const PATH: &str = "/api/scenes/grove/terrain";
const OCTET: (&str, &str) = ("content-type", "application/octet-stream");

/// Creates scene `grove` over ±100 m with instances at (x, y, z) = (10, 0, 20) and (-50, 2, 30);
/// returns its write token and (private scenes) read token.
async fn create(f: &Fixture, public: bool) -> (String, Option<String>) {
    let body = json!({
        "name": "Grove", "id": "grove", "public": public,
        "bounds": {"min": [-100.0, -100.0], "max": [100.0, 100.0]},
        "instances": [
            {"model": f.model, "position": [10.0, 0.0, 20.0]},
            {"model": f.model, "position": [-50.0, 2.0, 30.0]}
        ]
    });
    let r = send(
        &f.app,
        "POST",
        "/api/scenes",
        None,
        &[("content-type", "application/json")],
        Some(body.to_string().into_bytes()),
    )
    .await;
    assert_eq!(r.status, StatusCode::CREATED, "{}", r.json());
    let v = r.json();
    (
        v["write_token"].as_str().expect("write token").to_string(),
        v["read_token"].as_str().map(String::from),
    )
}

/// A terrain over the scene: a slope along x with a bump.
fn field(cell: f64) -> Heightfield {
    let n = (200.0 / cell) as u32 + 1;
    let h: Vec<f32> = (0..n)
        .flat_map(|j| (0..n).map(move |i| (i, j)))
        .map(|(i, j)| 0.2 * i as f32 * cell as f32 + 5.0 * ((j as f32) * 0.3).sin())
        .collect();
    Heightfield::new([-100.0, -100.0], cell, [n, n], &h).expect("field")
}

async fn manifest(f: &Fixture) -> Manifest {
    let r = send(&f.app, "GET", "/api/scenes/grove/manifest", None, &[], None).await;
    assert_eq!(r.status, StatusCode::OK);
    Manifest::parse(&r.body).expect("a valid manifest")
}

/// The version's pack instances' positions, by id.
async fn placed(f: &Fixture, m: &Manifest) -> Vec<(u32, [f32; 3])> {
    let r = send(&f.app, "GET", &m.pack.url, None, &[], None).await;
    assert_eq!(r.status, StatusCode::OK);
    let pack = canopy_shared::pack::decode(&r.body).expect("pack");
    let mut out: Vec<(u32, [f32; 3])> = pack.instances.iter().map(|i| (i.id, i.position)).collect();
    out.sort_by_key(|(id, _)| *id);
    out
}

#[tokio::test]
async fn a_terrain_makes_versions_whose_instances_stand_on_it_until_removed() {
    let f = fixture("round-trip");
    let (write, _) = create(&f, true).await;
    let flat = manifest(&f).await;
    assert!(flat.terrain.is_none());
    let flat_pack = placed(&f, &flat).await;
    assert_eq!(flat_pack, vec![(1, [10.0, 0.0, 20.0]), (2, [-50.0, 2.0, 30.0])]);
    let r = send(&f.app, "GET", PATH, None, &[], None).await;
    assert_eq!(r.status, StatusCode::NOT_FOUND);
    assert!(r.error().contains("has no terrain"), "{}", r.error());

    let t = field(4.0);
    let r = send(&f.app, "PUT", PATH, Some(&write), &[OCTET], Some(t.encode())).await;
    assert_eq!(r.status, StatusCode::OK, "{}", r.error());
    let put = r.body.clone();
    let r = send(&f.app, "GET", PATH, None, &[], None).await;
    assert_eq!((r.status, &r.body), (StatusCode::OK, &put), "GET answers what PUT did");
    assert_eq!(
        r.headers.get("cache-control").and_then(|v| v.to_str().ok()),
        Some("no-cache")
    );

    // Version 2: the same instances, each at the terrain's height plus its stored y.
    let m = manifest(&f).await;
    assert_eq!(m.version, 2);
    let terrain = m.terrain.clone().expect("the manifest names the terrain");
    assert_eq!(serde_json::to_vec(&terrain).expect("json"), put);
    assert_eq!(terrain.grid, t.grid);
    let file = send(&f.app, "GET", &terrain.url, None, &[("range", "bytes=0-63")], None).await;
    assert_eq!(file.status, StatusCode::PARTIAL_CONTENT, "the file is served by range");
    let whole = send(&f.app, "GET", &terrain.url, None, &[], None).await;
    assert_eq!(whole.body.len() as u64, terrain.size);
    assert_eq!(Heightfield::decode(&whole.body).expect("decodes"), t);
    let on = placed(&f, &m).await;
    assert_eq!(on[0].1, [10.0, t.height_at(10.0, 20.0), 20.0]);
    assert_eq!(on[1].1, [-50.0, t.height_at(-50.0, 30.0) + 2.0, 30.0]);
    assert!(on[0].1[1] > 15.0, "a real lift: {:?}", on[0].1);
    // The stored instances keep their heights above the ground.
    let list = send(&f.app, "GET", "/api/scenes/grove/instances", None, &[], None).await;
    assert_eq!(list.json()["instances"][1]["position"], json!([-50.0, 2.0, 30.0]));

    // An edit keeps the terrain: a moved instance stands at its new place.
    let batch = json!({"move": [{"id": 1, "position": [60.0, 1.0, -40.0]}]}).to_string();
    let r = send(
        &f.app,
        "POST",
        "/api/scenes/grove/instances",
        Some(&write),
        &[("content-type", "application/json")],
        Some(batch.into_bytes()),
    )
    .await;
    assert_eq!(r.status, StatusCode::OK, "{}", r.error());
    let m3 = manifest(&f).await;
    assert_eq!((m3.version, m3.terrain.as_ref()), (3, Some(&terrain)));
    let on = placed(&f, &m3).await;
    assert_eq!(on[0].1, [60.0, t.height_at(60.0, -40.0) + 1.0, -40.0]);
    assert_eq!(on[1].1, [-50.0, t.height_at(-50.0, 30.0) + 2.0, 30.0]);

    // Removed: version 4 on flat ground, byte for byte the pack of a scene that never had one.
    let r = send(&f.app, "DELETE", PATH, Some(&write), &[], None).await;
    assert_eq!(r.status, StatusCode::NO_CONTENT);
    let m4 = manifest(&f).await;
    assert_eq!((m4.version, m4.terrain.is_none()), (4, true));
    assert_eq!(
        placed(&f, &m4).await,
        vec![(1, [60.0, 1.0, -40.0]), (2, [-50.0, 2.0, 30.0])]
    );
    let r = send(&f.app, "GET", PATH, None, &[], None).await;
    assert_eq!(r.status, StatusCode::NOT_FOUND);
    // Removing none makes no version.
    let r = send(&f.app, "DELETE", PATH, Some(&write), &[], None).await;
    assert_eq!(r.status, StatusCode::NO_CONTENT);
    assert_eq!(manifest(&f).await.version, 4);
    // The old versions keep theirs.
    let r = send(&f.app, "GET", "/api/scenes/grove/manifest?version=2", None, &[], None).await;
    assert_eq!(Manifest::parse(&r.body).expect("v2").terrain.as_ref(), Some(&terrain));

    // An unknown scene is a different 404.
    for (method, body) in [("GET", None), ("PUT", Some(t.encode())), ("DELETE", None)] {
        let r = send(&f.app, method, "/api/scenes/nope/terrain", Some(&write), &[OCTET], body).await;
        assert_eq!(r.status, StatusCode::NOT_FOUND, "{method}");
        assert!(r.error().contains("not found"), "{method}: {}", r.error());
    }
}

fn png16(w: u32, h: u32, f: impl Fn(u32, u32) -> u16) -> Vec<u8> {
    let bytes: Vec<u8> = (0..h)
        .flat_map(|j| (0..w).map(move |i| (i, j)))
        .flat_map(|(i, j)| f(i, j).to_ne_bytes())
        .collect();
    let mut out = Vec::new();
    image::codecs::png::PngEncoder::new(&mut out)
        .write_image(&bytes, w, h, image::ExtendedColorType::L16)
        .expect("png");
    out
}

fn tiff_f32(w: u32, h: u32, scale: f64) -> Vec<u8> {
    let data: Vec<f32> = (0..w * h).map(|k| 300.0 + (k % w) as f32).collect();
    let mut out = Vec::new();
    {
        let mut enc = tiff::encoder::TiffEncoder::new(Cursor::new(&mut out)).expect("encoder");
        let mut img = enc
            .new_image::<tiff::encoder::colortype::Gray32Float>(w, h)
            .expect("image");
        img.encoder()
            .write_tag(tiff::tags::Tag::ModelPixelScaleTag, &[scale, scale, 0.0][..])
            .expect("tag");
        img.write_data(&data).expect("data");
    }
    out
}

#[tokio::test]
async fn png_and_geotiff_heightmaps_are_imported_with_the_query() {
    let f = fixture("images");
    let (write, _) = create(&f, true).await;
    let png = png16(51, 41, |i, _| (i * 1000) as u16);
    let r = send(
        &f.app,
        "PUT",
        &format!("{PATH}?cell=4&heights=-5%3A60.535&samples=51,41"),
        Some(&write),
        &[("content-type", "image/png")],
        Some(png),
    )
    .await;
    assert_eq!(r.status, StatusCode::OK, "{}", r.error());
    let g = &r.json()["grid"];
    assert_eq!((g["samples"].clone(), g["cell"].clone()), (json!([51, 41]), json!(4.0)));
    assert_eq!(g["origin"], json!([-100.0, -80.0]), "centred by default");
    let m = manifest(&f).await;
    let t = m.terrain.as_ref().expect("terrain");
    assert!((t.tiles[0].min_height + 5.0).abs() < 1e-3, "{:?}", t.tiles[0]);

    let r = send(
        &f.app,
        "PUT",
        &format!("{PATH}?origin=-90,-90"),
        Some(&write),
        &[("content-type", "image/tiff")],
        Some(tiff_f32(40, 30, 5.0)),
    )
    .await;
    assert_eq!(r.status, StatusCode::OK, "{}", r.error());
    let g = &r.json()["grid"];
    assert_eq!(
        (g["samples"].clone(), g["cell"].clone(), g["origin"].clone()),
        (json!([40, 30]), json!(5.0), json!([-90.0, -90.0]))
    );
    assert_eq!(manifest(&f).await.version, 3);
}

#[tokio::test]
async fn refused_uploads_and_tokens_change_nothing() {
    let f = fixture("refused");
    let (write, _) = create(&f, true).await;
    let good = field(4.0).encode();
    let put = |q: &str, token: Option<&str>, ct: &'static str, body: Vec<u8>| {
        let (app, uri, token) = (f.app.clone(), format!("{PATH}{q}"), token.map(String::from));
        async move { send(&app, "PUT", &uri, token.as_deref(), &[("content-type", ct)], Some(body)).await }
    };
    let check = |r: &Reply, status: StatusCode, words: &str| {
        assert_eq!(r.status, status, "{}", r.error());
        assert!(r.error().contains(words), "{:?} lacks {words:?}", r.error());
    };
    let r = put("", None, "application/octet-stream", good.clone()).await;
    check(&r, StatusCode::UNAUTHORIZED, "write token");
    let r = put("", Some("0123"), "application/octet-stream", good.clone()).await;
    check(&r, StatusCode::FORBIDDEN, "write token");
    let r = put("", Some(&write), "application/json", good.clone()).await;
    check(&r, StatusCode::UNSUPPORTED_MEDIA_TYPE, "image/png");
    let r = put(
        "",
        Some(&write),
        "application/octet-stream",
        good[..good.len() - 5].to_vec(),
    )
    .await;
    check(&r, StatusCode::BAD_REQUEST, "terrain");
    let r = put("", Some(&write), "application/octet-stream", b"not a terrain".to_vec()).await;
    check(&r, StatusCode::BAD_REQUEST, "not a valid terrain");
    let r = put("?samples=10,10", Some(&write), "application/octet-stream", good.clone()).await;
    check(&r, StatusCode::BAD_REQUEST, "expected 10 × 10");
    let r = put("?cell=2", Some(&write), "application/octet-stream", good.clone()).await;
    check(&r, StatusCode::BAD_REQUEST, "carries its own grid");
    let r = put("?colour=red", Some(&write), "application/octet-stream", good.clone()).await;
    check(&r, StatusCode::BAD_REQUEST, "unknown query parameter");
    // Heightmaps of the wrong size or depth.
    let png = png16(20, 20, |i, j| (i + j) as u16);
    let r = put(
        "?cell=4&heights=0:10&samples=21,20",
        Some(&write),
        "image/png",
        png.clone(),
    )
    .await;
    check(&r, StatusCode::BAD_REQUEST, "20 × 20 samples, expected 21 × 20");
    let r = put("?cell=4", Some(&write), "image/png", png.clone()).await;
    check(&r, StatusCode::BAD_REQUEST, "heights=MIN:MAX");
    let mut gray8 = Vec::new();
    image::codecs::png::PngEncoder::new(&mut gray8)
        .write_image(&[9; 64], 8, 8, image::ExtendedColorType::L8)
        .expect("png");
    let r = put("?cell=4&heights=0:10", Some(&write), "image/png", gray8).await;
    check(&r, StatusCode::BAD_REQUEST, "8-bit grayscale");
    let r = put(
        "?cell=4&heights=0:10",
        Some(&write),
        "image/png",
        png[..png.len() / 2].to_vec(),
    )
    .await;
    check(&r, StatusCode::BAD_REQUEST, "PNG");
    let r = put("", Some(&write), "image/tiff", tiff_f32(8, 8, 0.0001)).await;
    check(&r, StatusCode::BAD_REQUEST, "degrees");
    // Outside the scene.
    let far = Heightfield::new([5000.0, 5000.0], 1.0, [2, 2], &[0.0; 4])
        .expect("far")
        .encode();
    let r = put("", Some(&write), "application/octet-stream", far).await;
    check(&r, StatusCode::UNPROCESSABLE_ENTITY, "origin=X,Z");
    // Over the upload bound, by the declared length, before the body is read.
    let r = send(
        &f.app,
        "PUT",
        PATH,
        Some(&write),
        &[OCTET, ("content-length", "70000000")],
        Some(vec![0; 16]),
    )
    .await;
    assert_eq!(r.status, StatusCode::PAYLOAD_TOO_LARGE, "{}", r.error());
    // Nothing changed.
    assert_eq!(manifest(&f).await.version, 1);
    let r = send(&f.app, "GET", PATH, None, &[], None).await;
    assert_eq!(r.status, StatusCode::NOT_FOUND);
    // Another route keeps the 4 MiB bound; a terrain past it is taken.
    let big = field(0.125).encode();
    assert!(big.len() > 4 << 20, "{} bytes", big.len());
    let r = send(&f.app, "PUT", PATH, Some(&write), &[OCTET], Some(big)).await;
    assert_eq!(r.status, StatusCode::OK, "{}", r.error());
    let r = send(
        &f.app,
        "PUT",
        "/api/scenes/grove/flight-table",
        Some(&write),
        &[("content-type", "application/json")],
        Some(vec![b' '; (4 << 20) + 1]),
    )
    .await;
    assert_eq!(r.status, StatusCode::PAYLOAD_TOO_LARGE);
}

#[tokio::test]
async fn a_private_scenes_terrain_is_read_as_its_manifest_is() {
    let f = fixture("private");
    let (write, read) = create(&f, false).await;
    let read = read.expect("read token");
    let r = send(&f.app, "PUT", PATH, Some(&write), &[OCTET], Some(field(10.0).encode())).await;
    assert_eq!(r.status, StatusCode::OK, "{}", r.error());
    for (token, want) in [
        (None, StatusCode::UNAUTHORIZED),
        (Some("nope"), StatusCode::FORBIDDEN),
        (Some(read.as_str()), StatusCode::OK),
        (Some(write.as_str()), StatusCode::OK),
    ] {
        let r = send(&f.app, "GET", PATH, token, &[], None).await;
        assert_eq!(r.status, want, "{token:?}");
    }
    // Reading is not writing.
    let r = send(&f.app, "DELETE", PATH, Some(&read), &[], None).await;
    assert_eq!(r.status, StatusCode::FORBIDDEN);
}

#[tokio::test]
async fn terrain_changes_spend_the_scenes_edits() {
    let config = HttpConfig {
        edit_rate: Rate {
            per_s: 0.001,
            burst: 2.0,
        },
        ..HttpConfig::default()
    };
    let f = fixture_with("rate", config);
    let (write, _) = create(&f, true).await;
    let r = send(&f.app, "PUT", PATH, Some(&write), &[OCTET], Some(field(10.0).encode())).await;
    assert_eq!(r.status, StatusCode::OK, "{}", r.error());
    let r = send(&f.app, "DELETE", PATH, Some(&write), &[], None).await;
    assert_eq!(r.status, StatusCode::NO_CONTENT);
    let r = send(&f.app, "PUT", PATH, Some(&write), &[OCTET], Some(field(10.0).encode())).await;
    assert_eq!(r.status, StatusCode::TOO_MANY_REQUESTS, "{}", r.error());
    assert!(r.headers.get("retry-after").is_some());
}

#[tokio::test]
async fn retention_keeps_a_shared_terrain_file_and_the_sweep_drops_it_once_unnamed() {
    let config = HttpConfig {
        limits: Limits {
            keep_versions: 1,
            ..Limits::default()
        },
        ..HttpConfig::default()
    };
    let f = fixture_with("retention", config);
    let (write, _) = create(&f, true).await;
    let r = send(&f.app, "PUT", PATH, Some(&write), &[OCTET], Some(field(5.0).encode())).await;
    assert_eq!(r.status, StatusCode::OK, "{}", r.error());
    let url = r.json()["url"].as_str().expect("url").to_string();
    let on_disk = f.dir.join(url.trim_start_matches("/assets/"));
    // Edits prune the version that set it; later versions still name (and serve) it.
    for k in 0..3 {
        let batch = json!({"move": [{"id": 1, "position": [k as f32, 0.0, 0.0]}]}).to_string();
        let r = send(
            &f.app,
            "POST",
            "/api/scenes/grove/instances",
            Some(&write),
            &[("content-type", "application/json")],
            Some(batch.into_bytes()),
        )
        .await;
        assert_eq!(r.status, StatusCode::OK, "{}", r.error());
    }
    let versions = send(&f.app, "GET", "/api/scenes/grove/versions", None, &[], None).await;
    assert_eq!(versions.json()["versions"].as_array().map(Vec::len), Some(1));
    assert!(on_disk.is_file(), "pruning a version keeps the shared terrain file");
    gc::sweep(
        &f.state.inner.assets,
        f.state.inner.scenes.as_ref(),
        std::time::Duration::ZERO,
    )
    .expect("sweep");
    assert!(on_disk.is_file(), "a named terrain is not swept");
    assert_eq!(send(&f.app, "GET", &url, None, &[], None).await.status, StatusCode::OK);
    // Removed, and the versions that named it pruned: the sweep deletes it.
    let r = send(&f.app, "DELETE", PATH, Some(&write), &[], None).await;
    assert_eq!(r.status, StatusCode::NO_CONTENT);
    assert!(
        on_disk.is_file(),
        "the version that named it is pruned, its file left to the sweep"
    );
    gc::sweep(
        &f.state.inner.assets,
        f.state.inner.scenes.as_ref(),
        std::time::Duration::ZERO,
    )
    .expect("sweep");
    assert!(!on_disk.exists());
}

#[tokio::test]
async fn the_hills_demo_stands_on_its_terrain_and_the_flat_demo_stays_flat() {
    let f = fixture("hills");
    let cfg = DemoConfig {
        models: DemoModels::Synthetic(2),
        trees: 300,
        ..DemoConfig::default()
    };
    let st = f.state.clone();
    let t0 = std::time::Instant::now();
    let (flat, hills) = tokio::task::spawn_blocking(move || {
        let flat = demo::ensure_demo(&st, &cfg, &mut |_, _, _| {}).expect("demo");
        let (t_demo, t1) = (t0.elapsed(), std::time::Instant::now());
        let hills = demo::ensure_hills(&st, &cfg, &mut |_, _, _| {}).expect("hills");
        eprintln!("demo {t_demo:?}, hills {:?}", t1.elapsed());
        assert!(
            !demo::ensure_hills(&st, &cfg, &mut |_, _, _| {}).expect("again"),
            "made once"
        );
        (flat, hills)
    })
    .await
    .expect("join");
    assert!(flat && hills);
    let get = |id: &str| {
        let app = f.app.clone();
        let uri = format!("/api/scenes/{id}/manifest");
        async move { Manifest::parse(&send(&app, "GET", &uri, None, &[], None).await.body).expect("manifest") }
    };
    let (d, h) = (get("demo").await, get("hills").await);
    assert!(d.terrain.is_none(), "the flat demo has no terrain");
    assert_eq!((h.version, h.instance_count, d.bounds), (1, 300, h.bounds));
    assert_eq!(d.models, h.models, "the same models");
    let t = h
        .terrain
        .as_ref()
        .expect("hills stands on a terrain from its first version");
    let file = send(&f.app, "GET", &t.url, None, &[], None).await;
    let field = Heightfield::decode(&file.body).expect("terrain");
    let lo = t.tiles.iter().map(|t| t.min_height).fold(f32::INFINITY, f32::min);
    let hi = t.tiles.iter().map(|t| t.max_height).fold(f32::NEG_INFINITY, f32::max);
    assert!((hi - lo - 75.0).abs() < 0.1, "relief {}", hi - lo);
    let r = send(&f.app, "GET", &h.pack.url, None, &[], None).await;
    let pack = canopy_shared::pack::decode(&r.body).expect("pack");
    for i in &pack.instances {
        let ground = field.height_at(i.position[0], i.position[2]);
        assert!(
            (i.position[1] - ground).abs() < 1e-4,
            "instance {} at {:?}",
            i.id,
            i.position
        );
    }
    // Its first version is a static copy too, terrain included.
    assert!(f.dir.join(t.url.trim_start_matches("/assets/")).is_file());
    let copy = std::fs::read_dir(f.dir.join("scenes/hills"))
        .expect("folder")
        .flatten()
        .map(|e| e.path())
        .find(|p| p.extension().is_some_and(|e| e == "json"))
        .expect("the first version's manifest file");
    let copy = Manifest::parse(&std::fs::read(copy).expect("read")).expect("manifest");
    assert_eq!(copy.terrain.as_ref(), Some(t));
    // The flat demo's placement does not depend on the hills' (its own seed).
    let r = send(&f.app, "GET", &d.pack.url, None, &[], None).await;
    let flat_pack = canopy_shared::pack::decode(&r.body).expect("pack");
    assert!(flat_pack.instances.iter().all(|i| i.position[1] == 0.0));
}

/// Not a `tokio::test`: the PostgreSQL driver (blocking) opens outside any runtime, as `serve`
/// does.
#[test]
fn a_database_that_is_away_answers_503_with_retry_after() {
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("port")
        .port();
    let scenes = PostgresStore::open(&format!("postgres://canopy@127.0.0.1:{port}/canopy")).expect("starts");
    assert!(!scenes.available());
    let dir = temp_dir("away");
    let assets = Arc::new(AssetStore::open(&dir).expect("asset store"));
    let (state, _stop) = AppState::new(assets, Arc::new(scenes), HttpConfig::default());
    let app = router(state);
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("runtime");
    for (method, body) in [("GET", None), ("PUT", Some(field(10.0).encode())), ("DELETE", None)] {
        let r = rt.block_on(send(&app, method, PATH, Some("token"), &[OCTET], body));
        assert_eq!(r.status, StatusCode::SERVICE_UNAVAILABLE, "{method}: {}", r.error());
        assert_eq!(
            r.headers.get("retry-after").and_then(|v| v.to_str().ok()),
            Some("1"),
            "{method}"
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}

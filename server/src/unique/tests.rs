//! The unique forest on a tiny species and a bake without stand-ins: cheap enough to grow and
//! bake 300 models in seconds.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use canopy_shared::format::LeafOrder;

use super::*;
use crate::http::{AppState, HttpConfig};
use crate::store::{AssetStore, SqliteStore};

/// A tiny species (a handful of leaves) whose age, shoot length and leaf size vary.
const TINY: &str = r#"
name = "tiny"
seed = 3
iterations = 3
axiom = "A(1)"
productions = ["A(x) -> F(x*ls, 0.02) [+(40) F(x*0.5, 0.01) L(lw, 0.05)] [-(40) F(x*0.5, 0.01) L(lw, 0.05)] A(x*0.8)"]

[constants]
N = 3
ls = 1.0
lw = 0.04

[variation]
iterations = [2, 4]
iterations_constant = "N"

[variation.constants]
ls = [0.6, 1.4]
lw = [0.02, 0.06]
"#;

fn scratch(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("canopy-unique-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap_or_else(|e| panic!("{}: {e}", d.display()));
    d
}

fn species_dir(root: &Path, text: &str) -> PathBuf {
    let dir = root.join("species");
    std::fs::create_dir_all(&dir).unwrap_or_else(|e| panic!("{e}"));
    std::fs::write(dir.join("tiny.toml"), text).unwrap_or_else(|e| panic!("{e}"));
    dir
}

fn state(root: &Path) -> AppState {
    let assets = Arc::new(AssetStore::open(&root.join("assets")).unwrap_or_else(|e| panic!("{e}")));
    let scenes = Arc::new(SqliteStore::open(&root.join("canopy.db")).unwrap_or_else(|e| panic!("{e}")));
    AppState::new(assets, scenes, HttpConfig::default()).0
}

/// No stand-ins, random order: the bake of a tiny tree in about a millisecond.
fn quick() -> BakeOptions {
    BakeOptions {
        order: LeafOrder::Random,
        atlas: None,
        hull: None,
        cloud: None,
        ..BakeOptions::default()
    }
}

fn config(dir: PathBuf, models: usize) -> UniqueConfig {
    UniqueConfig {
        species_dir: dir,
        models,
        workers: 2,
        bake: quick(),
        ..UniqueConfig::default()
    }
}

#[test]
fn variants_are_deterministic_and_distinct() {
    let root = scratch("variants");
    let cfg = config(species_dir(&root, TINY), 300);
    let a = variants(&cfg).unwrap_or_else(|e| panic!("{e}"));
    let b = variants(&cfg).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(a, b);
    let keys: std::collections::BTreeSet<String> = a.iter().map(|s| model_key(s, &cfg.bake)).collect();
    assert_eq!(keys.len(), 300, "every variant its own content key");
    // The key follows the bake options too.
    assert_ne!(model_key(&a[0], &cfg.bake), model_key(&a[0], &BakeOptions::default()));
    let _ = std::fs::remove_dir_all(&root);
}

#[test]
fn three_hundred_distinct_models_baked_once_then_reused() {
    let root = scratch("bake");
    let cfg = config(species_dir(&root, TINY), 300);
    let st = state(&root.join("data"));
    let specs = variants(&cfg).unwrap_or_else(|e| panic!("{e}"));
    let calls = AtomicU64::new(0);
    let last = AtomicU64::new(0);
    let progress = |_: &str, done: u64, total: u64| {
        assert_eq!(total, 300);
        calls.fetch_add(1, Ordering::Relaxed);
        last.fetch_max(done, Ordering::Relaxed);
    };
    let first = bake_variants(&st, &specs, &cfg.bake, 2, &progress).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!((first.baked, first.reused, first.workers), (300, 0, 2));
    assert_eq!(last.load(Ordering::Relaxed), 300);
    assert!(calls.load(Ordering::Relaxed) >= 300);
    // 300 distinct files: distinct names and distinct contents.
    let models = st.inner.assets.models();
    let files: std::collections::BTreeSet<String> = first
        .names
        .iter()
        .map(|n| models.get(n).map(|a| a.sha256.clone()).unwrap_or_default())
        .collect();
    assert_eq!(files.len(), 300);
    assert!(!files.contains(""));
    // A second run (a restart: a new store over the same folder) bakes nothing.
    let st2 = state(&root.join("data"));
    let second = bake_variants(&st2, &specs, &cfg.bake, 2, &no_progress).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!((second.baked, second.reused), (0, 300));
    assert_eq!(second.names, first.names);
    // Adding models bakes only the new ones.
    let more = variants(&config(cfg.species_dir.clone(), 310)).unwrap_or_else(|e| panic!("{e}"));
    let third = bake_variants(&st2, &more, &cfg.bake, 1, &no_progress).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!((third.baked, third.reused), (10, 300));
    let _ = std::fs::remove_dir_all(&root);
}

#[test]
fn the_scene_places_each_model_once_and_the_demo_leaves_them_alone() {
    let root = scratch("scene");
    let cfg = config(species_dir(&root, TINY), 40);
    let st = state(&root.join("data"));
    let r = ensure_unique(&st, &cfg, &no_progress).unwrap_or_else(|e| panic!("{e}"));
    assert!(r.created);
    assert_eq!(r.bake.as_ref().map(|b| b.baked), Some(40));
    let again = ensure_unique(&st, &cfg, &no_progress).unwrap_or_else(|e| panic!("{e}"));
    assert!(!again.created && again.bake.is_none());
    let names = r.bake.map(|b| b.names).unwrap_or_default();
    let inst = place(&cfg, &names).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(inst, place(&cfg, &names).unwrap_or_else(|e| panic!("{e}")));
    let used: std::collections::BTreeSet<&str> = inst.iter().map(|i| i.model.as_str()).collect();
    assert_eq!(used.len(), 40);
    let b = bounds(&cfg);
    assert!(inst.iter().all(|i| b.contains(i.position[0], i.position[2])));
    assert!(names.iter().all(|n| is_unique_model(n)));
    // The demo places only models that are not the unique forest's (here one stored beside
    // them, so that it bakes nothing).
    let synthetic = crate::demo::synthetic_model(0);
    let (baked, _) = crate::bake::bake_model(&synthetic, &quick()).unwrap_or_else(|e| panic!("{e}"));
    let bytes = canopy_shared::format::encode_tree(&baked).unwrap_or_else(|e| panic!("{e}"));
    st.inner
        .assets
        .put("trees", "synthetic-0", "ctree", &bytes)
        .unwrap_or_else(|e| panic!("{e}"));
    let demo = crate::demo::DemoConfig {
        models: crate::demo::DemoModels::Synthetic(1),
        trees: 50,
        width_m: 200.0,
        depth_m: 200.0,
        ..crate::demo::DemoConfig::default()
    };
    assert!(crate::demo::ensure_demo(&st, &demo, &mut |_, _, _| {}).unwrap_or_else(|e| panic!("{e}")));
    let placed = st
        .inner
        .scenes
        .instances(crate::demo::DEMO_ID)
        .unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(placed.len(), 50);
    assert!(placed.iter().all(|i| i.model == "synthetic-0"));
    let _ = std::fs::remove_dir_all(&root);
}

#[test]
fn bad_parameters_give_clear_errors() {
    let root = scratch("bad");
    let bad = TINY.replace("ls = [0.6, 1.4]", "ls = [1.4, 0.6]");
    let e = variants(&config(species_dir(&root, &bad), 4))
        .err()
        .map(|e| e.to_string());
    let e = e.unwrap_or_default();
    assert!(e.contains("variation.constants.ls") && e.contains("min ≤ max"), "{e}");
    let unknown = TINY.replace("lw = [0.02, 0.06]", "leafw = [0.02, 0.06]");
    let e = variants(&config(species_dir(&root, &unknown), 4))
        .err()
        .map(|e| e.to_string());
    assert!(e.unwrap_or_default().contains("variation.constants.leafw"));
    let e = variants(&config(species_dir(&root, TINY), 0))
        .err()
        .map(|e| e.to_string());
    assert!(e.unwrap_or_default().contains("at least 1 model"));
    let st = state(&root.join("data"));
    let specs = variants(&config(species_dir(&root, TINY), 2)).unwrap_or_else(|e| panic!("{e}"));
    let e = bake_variants(&st, &specs, &quick(), 0, &no_progress)
        .err()
        .map(|e| e.to_string());
    assert!(e.unwrap_or_default().contains("at least 1 bake thread"));
    // A variant that cannot grow (a division by its drawn shoot length, 0) names itself.
    let zero = TINY
        .replace("F(x*ls, 0.02)", "F(x/ls, 0.02)")
        .replace("ls = [0.6, 1.4]", "ls = [0.0, 0.0]");
    let specs = variants(&config(species_dir(&root, &zero), 2)).unwrap_or_else(|e| panic!("{e}"));
    let e = bake_variants(&st, &specs, &quick(), 1, &no_progress)
        .err()
        .map(|e| e.to_string());
    let e = e.unwrap_or_default();
    assert!(e.contains("tiny-000") || e.contains("tiny-001"), "{e}");
    let _ = std::fs::remove_dir_all(&root);
}

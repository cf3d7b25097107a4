//! The discrete LOD files (`discrete_files`): written with each bake and named by the exact model
//! file they come from, made at start for models baked without them, listed in a published
//! manifest, valid GLB files whose geometry levels shrink and whose billboard level holds the
//! model's own crossed-quad images; a corrupt model file is an error, not a panic, and does not
//! stop the other models.

use std::path::PathBuf;
use std::sync::Arc;

use canopy_server::bake::{BakeOptions, bake_model};
use canopy_server::demo::{bake_and_store, synthetic_model};
use canopy_server::discrete_files::{ensure_level_files, level_files, manifest_levels};
use canopy_server::http::{AppState, HttpConfig};
use canopy_server::store::{AssetStore, SqliteStore};
use canopy_shared::discrete::LEVEL_COUNT;
use canopy_shared::format::atlas::{AtlasLayoutKind, AtlasTable};
use canopy_shared::format::directory::SectionKind;
use canopy_shared::format::tree::{DecodedTree, section_bytes};
use serde_json::Value;

struct Dir(PathBuf);

impl Drop for Dir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

fn temp(name: &str) -> Dir {
    let dir = std::env::temp_dir().join(format!("canopy-levels-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    Dir(dir)
}

/// The GLB's JSON chunk and BIN chunk, after checking the container.
fn glb(bytes: &[u8]) -> (Value, Vec<u8>) {
    assert_eq!(&bytes[..4], b"glTF");
    assert_eq!(u32::from_le_bytes(bytes[4..8].try_into().expect("4")), 2);
    assert_eq!(
        u32::from_le_bytes(bytes[8..12].try_into().expect("4")) as usize,
        bytes.len()
    );
    let json_len = u32::from_le_bytes(bytes[12..16].try_into().expect("4")) as usize;
    assert_eq!(&bytes[16..20], b"JSON");
    let json: Value = serde_json::from_slice(&bytes[20..20 + json_len]).expect("JSON chunk");
    let bin = if bytes.len() > 20 + json_len {
        let at = 20 + json_len;
        let n = u32::from_le_bytes(bytes[at..at + 4].try_into().expect("4")) as usize;
        assert_eq!(&bytes[at + 4..at + 8], b"BIN\0");
        bytes[at + 8..at + 8 + n].to_vec()
    } else {
        Vec::new()
    };
    (json, bin)
}

fn ctree_of(seed: u64) -> Vec<u8> {
    let (baked, _) = bake_model(&synthetic_model(seed), &BakeOptions::default()).expect("bake");
    canopy_shared::format::encode_tree(&baked).expect("encode")
}

#[test]
fn levels_are_glb_files_that_shrink_and_end_with_the_models_billboard() {
    let ctree = ctree_of(0);
    let files = level_files(&ctree).expect("levels");
    assert_eq!(files.len(), LEVEL_COUNT);
    for (k, f) in files.iter().enumerate().take(LEVEL_COUNT - 1) {
        let (json, _) = glb(f);
        let required: Vec<&str> = json["extensionsRequired"]
            .as_array()
            .map(|a| a.iter().filter_map(Value::as_str).collect())
            .unwrap_or_default();
        assert!(required.contains(&"EXT_meshopt_compression"), "level {k}: {required:?}");
        assert!(required.contains(&"KHR_mesh_quantization"), "level {k}: {required:?}");
    }
    assert!(
        files[0].len() > files[1].len() && files[1].len() > files[2].len(),
        "{:?}",
        files.iter().map(Vec::len).collect::<Vec<_>>()
    );
    // The billboard: two quads, each textured with the crossed-quad frame's own PNG bytes.
    let tree = DecodedTree::decode(&ctree).expect("decode");
    let e = *tree.directory.section(SectionKind::BillboardAtlases).expect("atlas");
    let section = section_bytes(&ctree, &e).expect("section");
    let table = AtlasTable::decode(section, e.length).expect("table");
    let layout = table
        .layouts
        .iter()
        .find(|l| l.kind == AtlasLayoutKind::CrossedQuads)
        .expect("crossed quads");
    let (json, bin) = glb(&files[LEVEL_COUNT - 1]);
    let images = json["images"].as_array().expect("images");
    assert_eq!(images.len() as u32, layout.frame_count());
    for (k, img) in images.iter().enumerate() {
        assert_eq!(img["mimeType"], "image/png");
        let view = &json["bufferViews"][img["bufferView"].as_u64().expect("view") as usize];
        let (o, n) = (
            view["byteOffset"].as_u64().expect("o") as usize,
            view["byteLength"].as_u64().expect("n") as usize,
        );
        let want = table
            .image_bytes(section, layout.first_frame + k as u32, 0)
            .expect("image")
            .expect("present");
        assert_eq!(&bin[o..o + n], want, "frame {k}");
    }
}

#[test]
fn a_bake_writes_them_and_a_published_manifest_names_them() {
    let dir = temp("bake");
    let assets = Arc::new(AssetStore::open(&dir.0).expect("assets"));
    let (state, _stop) = AppState::new(
        assets.clone(),
        Arc::new(SqliteStore::in_memory().expect("db")),
        HttpConfig::default(),
    );
    let name = bake_and_store(&state, &synthetic_model(0)).expect("bake");
    let models = assets.models();
    let levels = manifest_levels(&assets, &models).remove(&name).expect("model");
    assert_eq!(levels.len(), LEVEL_COUNT);
    for l in &levels {
        let rel = l.url.strip_prefix("/assets/").expect("asset URL");
        let a = assets.get(rel).expect("stored");
        assert_eq!((a.len, &a.sha256), (l.size, &l.sha256));
        assert_eq!(a.content_type, "model/gltf-binary");
    }
    // Nothing left to do at the next start.
    let again = ensure_level_files(&assets, &|_, _| {}).expect("ensure");
    assert_eq!((again.written, again.failed.len()), (0, 0));
}

#[test]
fn models_baked_without_levels_get_them_and_never_take_another_files() {
    let dir = temp("ensure");
    let assets = AssetStore::open(&dir.0).expect("assets");
    let first = assets.put("trees", "oak", "ctree", &ctree_of(1)).expect("put");
    assert!(manifest_levels(&assets, &assets.models())["oak"].is_empty());
    let r = ensure_level_files(&assets, &|_, _| {}).expect("ensure");
    assert_eq!((r.written, r.failed.len()), (1, 0));
    let before = manifest_levels(&assets, &assets.models())["oak"].clone();
    assert_eq!(before.len(), LEVEL_COUNT);
    // The same model baked again (another file under the same name, newer): the old file's
    // levels are not its levels.
    std::thread::sleep(std::time::Duration::from_millis(20));
    let second = assets.put("trees", "oak", "ctree", &ctree_of(2)).expect("put");
    assert_ne!(first.sha256, second.sha256);
    assert_eq!(assets.models()["oak"].sha256, second.sha256);
    assert!(manifest_levels(&assets, &assets.models())["oak"].is_empty());
    ensure_level_files(&assets, &|_, _| {}).expect("ensure");
    let after = manifest_levels(&assets, &assets.models())["oak"].clone();
    assert_eq!(after.len(), LEVEL_COUNT);
    assert!(after.iter().zip(&before).all(|(a, b)| a.url != b.url));
    // Reopened, the store finds the same files.
    drop(assets);
    let reopened = AssetStore::open(&dir.0).expect("reopen");
    assert_eq!(manifest_levels(&reopened, &reopened.models())["oak"], after);
}

#[test]
fn a_corrupt_model_file_is_an_error_and_the_others_still_get_levels() {
    assert!(level_files(b"not a tree").is_err());
    let mut truncated = ctree_of(3);
    truncated.truncate(truncated.len() / 2);
    assert!(level_files(&truncated).is_err());
    let dir = temp("corrupt");
    let assets = AssetStore::open(&dir.0).expect("assets");
    assets.put("trees", "broken", "ctree", &truncated).expect("put");
    assets.put("trees", "good", "ctree", &ctree_of(4)).expect("put");
    let r = ensure_level_files(&assets, &|_, _| {}).expect("ensure");
    assert_eq!(r.written, 1);
    assert_eq!(r.failed.len(), 1);
    assert_eq!(r.failed[0].0, "broken");
    let all = manifest_levels(&assets, &assets.models());
    assert!(all["broken"].is_empty());
    assert_eq!(all["good"].len(), LEVEL_COUNT);
}

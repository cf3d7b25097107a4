use super::*;
use crate::store::assets::AssetStore;

fn temp(name: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("canopy-tiles-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

fn bounds() -> Bounds {
    Bounds {
        min: [-500.0, -500.0],
        max: [500.0, 500.0],
    }
}

/// `n` instances spread over the bounds (deterministic).
fn grove(n: u32) -> Vec<Instance> {
    (1..=n)
        .map(|id| {
            let k = f64::from(id);
            Instance {
                id,
                model: models()[(id % 2) as usize].clone(),
                position: [
                    ((k * 0.618_034).fract() * 999.0 - 499.5) as f32,
                    0.0,
                    ((k * 0.414_214).fract() * 999.0 - 499.5) as f32,
                ],
                rotation: k as f32,
                scale: 1.0,
            }
        })
        .collect()
}

fn read_all(a: &Asset) -> Vec<u8> {
    let mut out = vec![0; a.len as usize];
    a.open().expect("open").read_exact_at(&mut out, 0).expect("read");
    out
}

fn models() -> Vec<String> {
    vec!["a".into(), "b".into()]
}

/// The pack a full build makes of `list`.
fn build(list: &[Instance]) -> (Vec<u8>, Vec<crate::store::pack::Tile>) {
    let pis: Vec<crate::store::pack::PackInstance> = list
        .iter()
        .map(|i| crate::store::pack::PackInstance {
            id: i.id,
            model: u16::from(i.model == "b"),
            position: i.position,
            rotation: i.rotation,
            scale: i.scale,
        })
        .collect();
    crate::store::pack::build(bounds().as_f32(), &models(), &pis).expect("build")
}

#[test]
fn a_pack_per_tile_reads_as_the_whole_pack_and_an_edit_writes_only_its_tiles() {
    let dir = temp("publish");
    let assets = AssetStore::open(&dir).expect("assets");
    let mut list = grove(20_000);
    let v1 = publish_pack(&assets, "scenes/s", "v1", &bounds(), &list, true).expect("v1");
    let (whole, tiles) = build(&list);
    assert!(v1.pack.parts.is_none(), "a first version is written whole");
    assert_eq!(read_all(&v1.pack), whole);
    assert_eq!(v1.new_tiles, tiles.len());
    // Move one instance: one or two tiles change, the index is new, everything else is shared.
    list[100].position = [3.0, 0.0, 4.0];
    let v2 = publish_pack(&assets, "scenes/s", "v2", &bounds(), &list, false).expect("v2");
    let (whole2, tiles2) = build(&list);
    assert!(v2.pack.parts.is_some());
    assert_eq!(v2.tiles, tiles2);
    assert_eq!(read_all(&v2.pack), whole2, "byte for byte a full rebuild");
    assert_eq!(v2.pack.sha256, crate::store::assets::sha256_hex(&whole2));
    assert!((1..=2).contains(&v2.new_tiles), "{} new tiles", v2.new_tiles);
    // Reads across the head and tile boundaries.
    let p = v2.pack.open().expect("open");
    for (at, n) in [
        (0, 10),
        (v2.tables_len - 3, 40),
        (whole2.len() as u64 - 29, 29),
        (1000, 70_000),
    ] {
        let mut b = vec![0; n];
        p.read_exact_at(&mut b, at).expect("range");
        assert_eq!(b, whole2[at as usize..at as usize + n]);
    }
    let mut past = vec![0; 2];
    assert!(p.read_exact_at(&mut past, whole2.len() as u64 - 1).is_err());
    // After a restart the pack is served through its index again.
    drop(assets);
    let again = AssetStore::open(&dir).expect("reopen");
    let a = again.get(&v2.pack.rel).expect("registered");
    assert_eq!(read_all(&a), whole2);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn unreferenced_tiles_go_shared_ones_stay() {
    let dir = temp("gc");
    let assets = AssetStore::open(&dir).expect("assets");
    let mut list = grove(5_000);
    let v1 = publish_pack(&assets, "scenes/s", "v1", &bounds(), &list, false).expect("v1");
    list[7].position = [-400.0, 0.0, 400.0];
    let v2 = publish_pack(&assets, "scenes/s", "v2", &bounds(), &list, false).expect("v2");
    let tiles = |a: &AssetStore| a.list("scenes/s/").into_iter().filter(|a| a.ext() == TILE_EXT).count();
    let before = tiles(&assets);
    assert_eq!(
        drop_unreferenced(&assets, "scenes/s", usize::MAX),
        (0, 0),
        "both indexes name their tiles"
    );
    // Version 1 pruned: only the tiles it alone named go.
    assets.remove(&v1.index.rel).expect("rm index");
    assets.remove(&v1.pack.rel).expect("rm pack");
    let (gone, _) = drop_unreferenced(&assets, "scenes/s", usize::MAX);
    assert!((1..=2).contains(&gone), "{gone}");
    assert_eq!(tiles(&assets), before - gone);
    let whole = build(&list).0;
    assert_eq!(read_all(&v2.pack), whole, "version 2 still whole");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_cleanup_keeps_the_tiles_of_every_kept_version_not_only_the_newest() {
    let dir = temp("gc-kept");
    let assets = AssetStore::open(&dir).expect("assets");
    let mut list = grove(5_000);
    // v9, v10, v11 (v10 sorts before v9 as text): the tile v10 alone names must stay.
    publish_pack(&assets, "scenes/s", "v9", &bounds(), &list, false).expect("v9");
    list[7].position = [-400.0, 0.0, 400.0];
    let v10 = publish_pack(&assets, "scenes/s", "v10", &bounds(), &list, false).expect("v10");
    list[7].position = [400.0, 0.0, -400.0];
    publish_pack(&assets, "scenes/s", "v11", &bounds(), &list, false).expect("v11");
    let tiles = |a: &AssetStore| a.list("scenes/s/").into_iter().filter(|a| a.ext() == TILE_EXT).count();
    let before = tiles(&assets);
    assert_eq!(drop_unreferenced_between(&assets, "scenes/s", usize::MAX), (0, 0));
    assert_eq!(
        read_all(&v10.pack),
        build(&{
            let mut l = list.clone();
            l[7].position = [-400.0, 0.0, 400.0];
            l
        })
        .0
    );
    // v10 pruned: the tiles only it named go, once each.
    assets.remove(&v10.index.rel).expect("rm index");
    assets.remove(&v10.pack.rel).expect("rm pack");
    let (gone, _) = drop_unreferenced_between(&assets, "scenes/s", usize::MAX);
    assert!((1..=2).contains(&gone), "{gone}");
    assert_eq!(tiles(&assets), before - gone);
    assert_eq!(drop_unreferenced_between(&assets, "scenes/s", usize::MAX), (0, 0));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn indexes_that_are_damaged_are_refused_never_a_panic() {
    let index = PackIndex {
        pack_len: 64 + 56,
        sha256: [7; 32],
        head: vec![1; 64],
        tiles: vec![("0123456789abcdef".into(), 28), ("fedcba9876543210".into(), 28)],
    };
    let b = index.encode();
    assert_eq!(PackIndex::decode("x", &b).expect("round trip"), index);
    for n in 0..b.len() {
        assert!(PackIndex::decode("x", &b[..n]).is_err(), "truncated at {n}");
    }
    let mut bad = b.clone();
    bad[0] = b'X';
    assert!(PackIndex::decode("x", &bad).is_err());
    let mut bad = b.clone();
    bad[16] ^= 1;
    assert!(PackIndex::decode("x", &bad).is_err(), "lengths must add up");
    let mut bad = b;
    let at = INDEX_FIXED + 64;
    bad[at] = b'G';
    assert!(PackIndex::decode("x", &bad).is_err(), "hash must be hex");
}

#[test]
fn a_cleanup_between_publishes_never_deletes_a_blob_a_publish_reuses() {
    let dir = temp("between");
    let assets = Arc::new(AssetStore::open(&dir).expect("assets"));
    let mut list = grove(3_000);
    let mut last = publish_pack(&assets, "scenes/s", "v1", &bounds(), &list, false).expect("v1");
    let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let cleaner = {
        let (assets, stop) = (assets.clone(), stop.clone());
        std::thread::spawn(move || {
            let mut deleted = 0;
            while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                deleted += drop_unreferenced_between(&assets, "scenes/s", usize::MAX).0;
            }
            deleted
        })
    };
    for v in 2..120 {
        // One instance back and forth: each version reuses the blobs of the version two before,
        // which the removal of that version's index has just left unreferenced.
        let lock = assets.blob_lock("scenes/s");
        let mut publishes = lock.lock().expect("lock");
        *publishes += 1;
        list[5].position = if v % 2 == 0 {
            [-300.0, 0.0, 250.0]
        } else {
            [200.0, 0.0, -350.0]
        };
        let next = publish_pack(&assets, "scenes/s", &format!("v{v}"), &bounds(), &list, false).expect("publish");
        drop(publishes);
        // Time for a pass that began before this publish to delete what it reused.
        std::thread::sleep(std::time::Duration::from_millis(2));
        // On disk, not only in memory: a restart must find every blob the index names.
        for (h, _) in &read_index(&next.index).expect("index").tiles {
            assert!(
                dir.join(tile_rel("scenes/s", h)).exists(),
                "version {v}: blob {h} deleted"
            );
        }
        assets.remove(&last.index.rel).expect("prune");
        last = next;
    }
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    let deleted = cleaner.join().expect("cleaner");
    assert!(deleted > 0, "the cleaner deleted nothing: the test proves nothing");
    assert_eq!(read_all(&last.pack), build(&list).0);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_tile_blob_path_gives_its_hash() {
    assert_eq!(
        tile_hash(&tile_rel("scenes/s", "0123456789abcdef")),
        Some(0x0123_4567_89ab_cdef)
    );
    assert_eq!(tile_hash(&tile_rel("scenes/s", "0123456789ABCDEF")), None);
    assert_eq!(tile_hash(&tile_rel("scenes/s", "0123456789abcde")), None);
    assert_eq!(tile_hash(&tile_rel("scenes/s", "+123456789abcdef")), None);
    assert_eq!(tile_hash("scenes/s/v3.0123456789abcdef.cpix"), None);
    assert_eq!(tile_hash("scenes/s/t.ctile"), None);
}

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
fn grove(n: u32) -> Vec<PackInstance> {
    (1..=n)
        .map(|id| {
            let k = f64::from(id);
            PackInstance {
                id,
                model: (id % 2) as u16,
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

#[test]
fn a_pack_per_tile_reads_as_the_whole_pack_and_an_edit_writes_only_its_tiles() {
    let dir = temp("publish");
    let assets = AssetStore::open(&dir).expect("assets");
    let mut list = grove(20_000);
    let v1 = publish_pack(&assets, "scenes/s", "v1", &bounds(), &models(), &list, true).expect("v1");
    let (whole, tiles) = pack::build(bounds().as_f32(), &models(), &list).expect("build");
    assert!(v1.pack.parts.is_none(), "a first version is written whole");
    assert_eq!(read_all(&v1.pack), whole);
    assert_eq!(v1.new_tiles, tiles.len());
    // Move one instance: one or two tiles change, the index is new, everything else is shared.
    list[100].position = [3.0, 0.0, 4.0];
    let v2 = publish_pack(&assets, "scenes/s", "v2", &bounds(), &models(), &list, false).expect("v2");
    let (whole2, tiles2) = pack::build(bounds().as_f32(), &models(), &list).expect("build");
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
    let v1 = publish_pack(&assets, "scenes/s", "v1", &bounds(), &models(), &list, false).expect("v1");
    list[7].position = [-400.0, 0.0, 400.0];
    let v2 = publish_pack(&assets, "scenes/s", "v2", &bounds(), &models(), &list, false).expect("v2");
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
    let whole = pack::build(bounds().as_f32(), &models(), &list).expect("build").0;
    assert_eq!(read_all(&v2.pack), whole, "version 2 still whole");
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

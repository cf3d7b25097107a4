use proptest::prelude::*;

use super::*;

fn bounds() -> Bounds {
    Bounds {
        min: [-100.0, -100.0],
        max: [100.0, 100.0],
    }
}

fn inst(id: u32, model: &str, x: f32, z: f32) -> Instance {
    Instance {
        id,
        model: model.into(),
        position: [x, 0.5, z],
        rotation: id as f32 * 0.1,
        scale: 1.0,
    }
}

/// The full build of `list` (sorted by id, as the store keeps it).
fn reference(list: &[Instance]) -> (Vec<u8>, Vec<Tile>) {
    reference_on(list, None)
}

/// The full build of `list` standing on `ground`.
fn reference_on(list: &[Instance], ground: Option<&Ground>) -> (Vec<u8>, Vec<Tile>) {
    let names: Vec<String> = list
        .iter()
        .map(|i| i.model.clone())
        .collect::<std::collections::BTreeSet<_>>()
        .into_iter()
        .collect();
    let pis: Vec<PackInstance> = list
        .iter()
        .map(|i| pack_instance(i, names.binary_search(&i.model).expect("name") as u16, ground))
        .collect();
    pack::build(bounds().as_f32(), &names, &pis).expect("build")
}

fn check(draft: &PackDraft, list: &[Instance]) {
    let (bytes, tiles) = reference_on(list, draft.ground().map(|g| &**g));
    assert_eq!(draft.table(), tiles);
    assert_eq!(draft.bytes(), bytes, "byte for byte the full build");
    assert_eq!(draft.pack_sha256(), <[u8; 32]>::from(Sha256::digest(&bytes)));
    assert_eq!(draft.pack_len, bytes.len() as u64);
    for t in &draft.tiles {
        assert_eq!(t.sha256, <[u8; 32]>::from(Sha256::digest(&t.records)));
    }
}

/// One edit: (kind 0 move / 1 remove / 2 add, which instance, x, z, model).
type Op = (u8, usize, f32, f32, u8);

/// Applies `ops` to `list` as the store does and returns the changes.
fn edit(list: &mut Vec<Instance>, next_id: &mut u32, ops: &[Op], base: u64) -> Changes {
    let mut ch = Changes {
        base_version: Some(base),
        ..Changes::default()
    };
    let mut seen = std::collections::HashSet::new();
    for &(kind, which, x, z, model) in ops {
        let name = ["a", "b", "c"][usize::from(model % 3)];
        match kind % 3 {
            0 | 1 if !list.is_empty() => {
                let k = which % list.len();
                if !seen.insert(list[k].id) {
                    continue;
                }
                ch.before.push(list[k].clone());
                if kind % 3 == 0 {
                    list[k].position = [x, 0.5, z];
                    ch.after.push(list[k].clone());
                } else {
                    list.remove(k);
                }
            }
            _ => {
                let i = inst(*next_id, name, x, z);
                *next_id += 1;
                seen.insert(i.id);
                ch.after.push(i.clone());
                list.push(i);
            }
        }
    }
    ch
}

#[test]
fn a_move_re_encodes_only_its_tiles() {
    let mut list: Vec<Instance> = (1..=3000)
        .map(|id| {
            let k = f64::from(id);
            let x = ((k * 0.618_034).fract() * 199.0 - 99.5) as f32;
            let z = ((k * 0.414_214).fract() * 199.0 - 99.5) as f32;
            inst(id, if id % 2 == 0 { "a" } else { "b" }, x, z)
        })
        .collect();
    let d1 = PackDraft::build(1, &bounds(), &list).expect("build");
    check(&d1, &list);
    assert!(d1.tiles.len() > 8, "{} tiles", d1.tiles.len());
    let mut next = 3001;
    let ch = edit(&mut list, &mut next, &[(0, 10, 3.0, 4.0, 0)], 1);
    let before: Vec<Arc<[u8]>> = d1.tiles.iter().map(|t| t.records.clone()).collect();
    let d2 = d1.apply(2, &bounds(), &ch, &list).expect("apply");
    check(&d2, &list);
    let shared = d2
        .tiles
        .iter()
        .filter(|t| before.iter().any(|b| Arc::ptr_eq(b, &t.records)))
        .count();
    assert!(
        shared + 2 >= d2.tiles.len(),
        "{shared} of {} tiles reused",
        d2.tiles.len()
    );
}

#[test]
fn a_new_model_or_a_wrong_base_rebuilds() {
    let mut list: Vec<Instance> = (1..=50).map(|id| inst(id, "a", id as f32, 0.0)).collect();
    let d = PackDraft::build(1, &bounds(), &list).expect("build");
    let mut next = 51;
    let ch = edit(&mut list, &mut next, &[(2, 0, 1.0, 1.0, 1)], 1);
    let d = d.apply(2, &bounds(), &ch, &list).expect("apply");
    check(&d, &list);
    assert_eq!(d.names(), ["a".to_string(), "b".to_string()]);
    // Changes against version 5 given to the draft of version 2: rebuilt from the list.
    let ch = edit(&mut list, &mut next, &[(0, 3, -50.0, 20.0, 0)], 5);
    let d = d.apply(6, &bounds(), &ch, &list).expect("apply");
    check(&d, &list);
    assert_eq!(d.version, 6);
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]
    #[test]
    fn every_edit_sequence_gives_the_full_build(
        start in prop::collection::vec((-100.0f32..100.0, -100.0f32..100.0, 0u8..3), 0..700),
        edits in prop::collection::vec(
            prop::collection::vec((0u8..3, 0usize..1000, -100.0f32..100.0, -100.0f32..100.0, 0u8..3), 1..6),
            1..8,
        ),
    ) {
        // Clustered positions, so tiles split and merge as instances come and go.
        let mut list: Vec<Instance> = start
            .iter()
            .enumerate()
            .map(|(k, &(x, z, m))| inst(k as u32 + 1, ["a", "b", "c"][usize::from(m)], x * 0.1, z * 0.1))
            .collect();
        let mut next = list.len() as u32 + 1;
        let mut draft = PackDraft::build(1, &bounds(), &list).expect("build");
        for (v, ops) in edits.iter().enumerate() {
            let ch = edit(&mut list, &mut next, ops, v as u64 + 1);
            draft = draft.apply(v as u64 + 2, &bounds(), &ch, &list).expect("apply");
            check(&draft, &list);
        }
    }
}

#[test]
fn drafts_hold_only_what_was_put_and_are_bounded() {
    let d = |n: u32| {
        PackDraft::build(
            1,
            &bounds(),
            &(1..=n).map(|id| inst(id, "a", 0.0, 0.0)).collect::<Vec<_>>(),
        )
    };
    let drafts = PackDrafts::with_limit(100);
    drafts.put("s", 7, d(10).expect("d"));
    assert!(drafts.take("s", 8).is_none(), "another scene of the same id");
    assert!(drafts.take("s", 7).is_some());
    assert!(drafts.take("s", 7).is_none(), "taken");
    drafts.put("s", 7, d(10).expect("d"));
    drafts.put("t", 7, d(95).expect("d"));
    assert!(drafts.take("s", 7).is_none(), "the oldest goes past the bound");
    drafts.forget("t");
    assert!(drafts.take("t", 7).is_none());
}

/// A ground: a slope along x (`rise` metres per metre), named by `sha`.
fn slope(rise: f32, sha: &str) -> Arc<Ground> {
    let field = canopy_shared::terrain::Heightfield::new(
        [-100.0, -100.0],
        50.0,
        [5, 5],
        &(0..25).map(|k| rise * 50.0 * (k % 5) as f32).collect::<Vec<_>>(),
    )
    .expect("field");
    Arc::new(Ground {
        terrain: canopy_shared::manifest::ManifestTerrain {
            url: format!("/assets/scenes/s/terrain.{sha}.cterrain"),
            sha256: sha.into(),
            size: 0,
            grid: field.grid,
            tiles: Vec::new(),
        },
        field,
    })
}

#[test]
fn a_draft_on_a_terrain_lifts_its_records_and_is_rebuilt_for_another_ground() {
    let mut list: Vec<Instance> = (1..=300)
        .map(|id| {
            inst(
                id,
                ["a", "b"][id as usize % 2],
                (id as f32 * 7.3) % 190.0 - 95.0,
                (id as f32 * 3.1) % 190.0 - 95.0,
            )
        })
        .collect();
    let g = slope(0.25, "g");
    let d = PackDraft::build_on(1, &bounds(), &list, Some(g.clone())).expect("build");
    check(&d, &list);
    let p = pack::decode(&d.bytes()).expect("pack");
    for i in &p.instances {
        let want = 0.25 * (i.position[0] + 100.0) + 0.5;
        assert!((i.position[1] - want).abs() < 1e-3, "{:?}", i.position);
    }
    // In place on the same ground (another Arc of the same file) …
    let mut next = 301;
    let ch = edit(
        &mut list,
        &mut next,
        &[(0, 3, 40.0, -20.0, 0), (2, 0, 10.0, 10.0, 1)],
        1,
    );
    let d = d
        .apply_on(2, &bounds(), Some(slope(0.25, "g")), &ch, &list)
        .expect("apply");
    check(&d, &list);
    // … rebuilt on another, and on flat ground, where it is the plain build byte for byte.
    let ch = edit(&mut list, &mut next, &[(1, 5, 0.0, 0.0, 0)], 2);
    let d = d
        .apply_on(3, &bounds(), Some(slope(-0.1, "h")), &ch, &list)
        .expect("apply");
    assert_eq!(d.ground().map(|g| g.terrain.sha256.as_str()), Some("h"));
    check(&d, &list);
    let ch = edit(&mut list, &mut next, &[(0, 7, 1.0, 1.0, 0)], 3);
    let d = d.apply_on(4, &bounds(), None, &ch, &list).expect("apply");
    assert!(d.ground().is_none());
    assert_eq!(d.bytes(), reference(&list).0);
    assert_eq!(d.bytes(), PackDraft::build(4, &bounds(), &list).expect("build").bytes());
}

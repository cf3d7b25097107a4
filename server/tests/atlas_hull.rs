//! Billboard atlases and crown hulls: whole-file round trip through `encode_tree`, a client's
//! range-fetch path, and (ignored) the per-species measurements of benchmarks/log.md.
#![allow(clippy::unwrap_used)]

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use canopy_server::bake::atlas::{AtlasOptions, LatLongOptions, bake_atlases};
use canopy_server::bake::hull::{HullOptions, bake_hulls};
use canopy_server::bake::{BakeOptions, bake_model};
use canopy_server::import_gltf::import_gltf;
use canopy_shared::format::atlas::{AtlasTable, decode_png_frame, hemi_oct_blend};
use canopy_shared::format::hull::{HullTable, decode_hulls};
use canopy_shared::format::tree::section_bytes;
use canopy_shared::format::{DecodedTree, LeafOrder, SectionKind, encode_tree};
use canopy_shared::model::TreeModel;
use glam::Vec3;

const FIXTURES: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../../shared/fixtures/trees");
const SPECIES: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../assets/species");

fn fixture(name: &str) -> Option<TreeModel> {
    let p = Path::new(FIXTURES).join(name);
    if !p.is_file() {
        assert!(std::env::var_os("CI").is_none(), "fixture {} missing", p.display());
        println!("SKIP: fixture {} is missing", p.display());
        return None;
    }
    Some(import_gltf(&p).unwrap())
}

#[test]
fn sections_round_trip_through_a_whole_file() {
    let Some(model) = fixture("kenney_tree_oak_fall.glb") else {
        return;
    };
    let aopts = AtlasOptions {
        resolutions: vec![32, 16],
        lat_long: Some(LatLongOptions {
            azimuth_step_deg: 60.0,
            ..LatLongOptions::default()
        }),
        hemi_oct_side: Some(4),
        crossed_quads: true,
        ..AtlasOptions::default()
    };
    let (atlases, arep) = bake_atlases(&model, &aopts).unwrap();
    let hopts = HullOptions {
        iou_views: 4,
        iou_size: 32,
        ..HullOptions::default()
    };
    let (hulls, hrep) = bake_hulls(&model, &hopts).unwrap();
    let bopts = BakeOptions {
        order: LeafOrder::Generation,
        ..BakeOptions::default()
    };
    let (mut baked, _) = bake_model(&model, &bopts).unwrap();
    baked.atlases = atlases.clone();
    baked.hulls = hulls.clone();
    let file = encode_tree(&baked).unwrap();
    let decoded = DecodedTree::decode(&file).unwrap();

    // Hulls: table by prefix, then each level by its own range.
    let he = *decoded.directory.section(SectionKind::Hulls).unwrap();
    assert_eq!(he.item_count, 3);
    let hs = section_bytes(&file, &he).unwrap();
    let table_len = HullTable::peek_table_len(hs).unwrap() as usize;
    let ht = HullTable::decode(&hs[..table_len], he.length).unwrap();
    for (k, lvl) in ht.levels.iter().enumerate() {
        let start = (he.offset + u64::from(lvl.offset)) as usize;
        let m = ht.decode_level(k, &file[start..start + lvl.length as usize]).unwrap();
        assert_eq!(m.triangle_count(), hrep.levels[k].triangles);
        assert_eq!(m.method, hrep.levels[k].method);
        assert!(m.triangle_count() <= hopts.budgets[k] as usize);
    }
    assert_eq!(decode_hulls(hs).unwrap().1.len(), 3);

    // Atlases: table by prefix, one frame by range, PNG decodes at the stored size.
    let ae = *decoded.directory.section(SectionKind::BillboardAtlases).unwrap();
    let s = section_bytes(&file, &ae).unwrap();
    let tl = AtlasTable::peek_table_len(s).unwrap() as usize;
    assert_eq!(tl, arep.table_bytes);
    let at = AtlasTable::decode(&s[..tl], ae.length).unwrap();
    assert_eq!(at.frames.len() as u32, ae.item_count);
    let hemi = at.layouts[1];
    let w = hemi_oct_blend(Vec3::new(0.3, 0.8, 0.1), u32::from(hemi.cols));
    let frame = hemi.first_frame + w.iter().max_by(|a, b| a.1.total_cmp(&b.1)).unwrap().0;
    for (r, &side) in at.resolutions.iter().enumerate() {
        let e = at.image(frame, r).unwrap();
        let start = (ae.offset + u64::from(e.offset)) as usize;
        let bytes = AtlasTable::verify_image(&e, &file[start..start + e.length as usize]).unwrap();
        let img = decode_png_frame(bytes, side).unwrap();
        assert!(img.pixels().any(|p| p[3] > 0));
    }
    let stored: usize = arep.layouts.iter().map(|l| l.stored).sum();
    assert_eq!(stored, at.frames.iter().filter(|f| f.is_present()).count());
}

/// Species specs and fixtures to measure: `(name, model, grow/import seconds)`.
fn measured_models() -> Vec<(String, TreeModel, f64)> {
    let mut out = Vec::new();
    let mut specs: Vec<PathBuf> = std::fs::read_dir(SPECIES)
        .map(|d| d.filter_map(|e| e.ok().map(|e| e.path())).collect())
        .unwrap_or_default();
    specs.retain(|p| p.extension().is_some_and(|e| e == "toml"));
    specs.sort();
    for p in specs {
        let t = Instant::now();
        let spec = canopy_server::species::SpeciesSpec::load(&p).unwrap();
        let model = canopy_server::species::grow(&spec, &canopy_server::lsystem::Limits::default()).unwrap();
        out.push((spec.name.clone(), model, t.elapsed().as_secs_f64()));
    }
    for f in ["kenney_tree_oak_fall.glb", "tfs_tree.glb", "tfs_detailedTree.glb"] {
        let t = Instant::now();
        if let Some(m) = fixture(f) {
            out.push((f.to_owned(), m, t.elapsed().as_secs_f64()));
        }
    }
    out
}

/// Prints the per-species table of benchmarks/log.md. Run in release:
/// `cargo test --release -p canopy-server --test atlas_hull -- --ignored --nocapture`.
#[test]
#[ignore = "measurement; run in release"]
fn measure_atlases_and_hulls() {
    let mut atlas_table = String::from(
        "| model | leaves | layout | frames (stored) | bytes 128² | bytes 64² | total KiB | mean B/frame 128² / 64² | seconds |\n|---|---:|---|---:|---:|---:|---:|---:|---:|\n",
    );
    let mut hull_table = String::from(
        "| model | feature pts (kept) | recon tris (closed) | budget | tris | method | closed | IoU | hull s |\n|---|---:|---:|---:|---:|---|---|---:|---:|\n",
    );
    let mut totals = String::new();
    for (name, model, grow_s) in measured_models() {
        let (ab, ar) = bake_atlases(&model, &AtlasOptions::default()).unwrap();
        let (hb, hr) = bake_hulls(&model, &HullOptions::default()).unwrap();
        for l in &ar.layouts {
            let mean = |k: usize| l.bytes_per_resolution[k] / l.stored.max(1);
            writeln!(
                atlas_table,
                "| {name} | {} | {} | {} ({}) | {} | {} | {:.1} | {} / {} | {:.2} |",
                model.leaves.len(),
                l.name,
                l.frames,
                l.stored,
                l.bytes_per_resolution[0],
                l.bytes_per_resolution[1],
                l.bytes() as f64 / 1024.0,
                mean(0),
                mean(1),
                l.seconds
            )
            .unwrap();
        }
        for l in &hr.levels {
            writeln!(
                hull_table,
                "| {name} | {} ({}) | {} ({}) | {} | {} | {} | {} | {:.3} | {:.2} |",
                hr.feature_points,
                hr.kept_points,
                hr.reconstructed_triangles,
                if hr.reconstructed_closed { "yes" } else { "no" },
                l.budget,
                l.triangles,
                l.method.name(),
                if l.closed { "yes" } else { "no" },
                l.iou,
                hr.seconds
            )
            .unwrap();
        }
        writeln!(
            totals,
            "{name}: grow/import {grow_s:.2} s, atlases {:.2} s ({} B section, {} B table), hulls {:.2} s ({} B section), atlases + hulls {:.2} s",
            ar.seconds,
            ab.bytes.len(),
            ar.table_bytes,
            hr.seconds,
            hb.bytes.len(),
            ar.seconds + hr.seconds
        )
        .unwrap();
        println!("done {name}");
    }
    println!("\n{atlas_table}\n{hull_table}\n{totals}");
}

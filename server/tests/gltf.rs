//! glTF import/export: real fixtures, round trips, synthetic edge cases, corrupt inputs.
#![allow(clippy::unwrap_used, clippy::too_many_lines)]

use std::path::{Path, PathBuf};

use canopy_server::export_gltf::{export_glb, export_glb_to};
use canopy_server::import_gltf::{ImportError, import_gltf, import_gltf_report, import_gltf_slice};
use canopy_shared::model::{Branch, Leaf, Materials, ModelSource, SkeletonPoint, TreeModel, TriangleMesh};
use glam::Vec3;
use serde_json::{Value, json};

const FIXTURES: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../../shared/fixtures/trees");

/// The fixture `.glb` files, or `None` (skip) when the folder is missing outside CI.
fn fixtures() -> Option<Vec<PathBuf>> {
    let dir = Path::new(FIXTURES);
    if !dir.is_dir() {
        assert!(
            std::env::var_os("CI").is_none(),
            "fixture folder {FIXTURES} is missing (CI is set, so this is a failure)"
        );
        println!("SKIP: fixture folder {FIXTURES} is missing");
        return None;
    }
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "glb"))
        .collect();
    files.sort();
    assert!(!files.is_empty(), "no .glb files in {FIXTURES}");
    Some(files)
}

fn stem(p: &Path) -> String {
    p.file_stem().unwrap().to_string_lossy().into_owned()
}

fn check_leaf(l: &Leaf) {
    assert!(l.center.is_finite());
    assert!((l.normal.length() - 1.0).abs() < 1e-3, "normal {}", l.normal);
    assert!((l.axis.length() - 1.0).abs() < 1e-3, "axis {}", l.axis);
    assert!(l.axis.dot(l.normal).abs() < 1e-3, "axis not perpendicular to normal");
    assert!(l.width > 0.0 && l.length > 0.0);
    assert_eq!(l.branch, None);
    assert_eq!(l.iteration, 0);
}

#[test]
fn fixtures_import_with_sensible_counts() {
    let Some(files) = fixtures() else { return };
    for path in files {
        let name = stem(&path);
        let bytes = std::fs::read(&path).unwrap();
        let report = import_gltf_report(&bytes, &name, path.parent()).unwrap();
        let m = &report.model;
        println!(
            "{name}: bark {} triangles / {} vertices, {} leaves ({} quads, {} per-triangle, {} degenerate dropped), \
             bark colour {:?} texture {:?}, leaf materials {:?}, renormalised normals {}, warnings {:?}",
            m.bark_mesh.triangle_count(),
            m.bark_mesh.positions.len(),
            m.leaves.len(),
            report.stats.leaf_quads,
            report.stats.leaf_triangles,
            report.stats.degenerate_leaf_triangles,
            m.materials.bark_color,
            m.materials.bark_texture,
            m.materials.leaf,
            report.stats.renormalized_normals,
            report.warnings,
        );
        m.check_invariants().unwrap();
        assert_eq!(m.source, ModelSource::Gltf);
        assert_eq!(m.iterations, 0);
        assert!(m.branches.is_empty());
        assert!(!m.materials.leaf.is_empty());
        assert!(m.bark_mesh.triangle_count() > 0, "{name}: no bark");
        assert!(!m.leaves.is_empty(), "{name}: no leaves");
        assert_eq!(m.bark_mesh.normals.len(), m.bark_mesh.positions.len());
        for n in &m.bark_mesh.normals {
            assert!((n.length() - 1.0).abs() < 1e-3, "{name}: bark normal {n}");
        }
        for l in &m.leaves {
            check_leaf(l);
        }
        // Base at the origin: bark min y = 0, bark xz bounds centred.
        let (lo, hi) = m.bark_mesh.positions.iter().fold(
            (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
            |(lo, hi), &p| (lo.min(p), hi.max(p)),
        );
        assert!(lo.y.abs() < 1e-4, "{name}: base at y {}", lo.y);
        assert!((lo.x + hi.x).abs() < 1e-3 && (lo.z + hi.z).abs() < 1e-3);
        let (_, all_hi) = m.bounds().unwrap();
        assert!(all_hi.y > 0.5, "{name}: tree is only {} tall", all_hi.y);

        // The same through the path API.
        let via_path = import_gltf(&path).unwrap();
        assert_eq!(via_path.leaves.len(), m.leaves.len());
        assert_eq!(via_path.name, name);

        match name.as_str() {
            "tfs_detailedTree" => {
                assert_eq!(m.leaves.len(), 640);
                assert_eq!(report.stats.leaf_quads, 640);
                assert_eq!(m.bark_mesh.triangle_count(), 3698);
                assert!(report.stats.renormalized_normals >= 288);
                assert_eq!(m.materials.leaf.len(), 1);
                assert_eq!(m.materials.leaf[0].texture.as_deref(), Some("elm leaf"));
                assert_eq!(m.materials.bark_texture.as_deref(), Some("bark04"));
                // 0.12 scale on an ~88-unit model, Z-up rotated to Y-up: ~10.6 m tall.
                assert!((all_hi.y - 11.0).abs() < 2.0, "height {}", all_hi.y);
            }
            "tfs_tree" => {
                assert_eq!(m.bark_mesh.triangle_count(), 170);
                assert_eq!(m.leaves.len() + report.stats.degenerate_leaf_triangles, 400);
                assert!(m.leaves.len() > 350);
            }
            _ => {
                // Kenney: low-poly blobs, one leaf per (non-degenerate) triangle; one "leafs*"
                // material; the non-root scene node must be imported exactly once.
                assert_eq!(report.stats.leaf_quads + report.stats.leaf_triangles, m.leaves.len());
                assert_eq!(m.materials.leaf.len(), 1);
                assert_eq!(report.stats.leaf_primitives, 1);
            }
        }
    }
}

#[test]
fn kenney_non_root_scene_node_imported_once() {
    let Some(files) = fixtures() else { return };
    // The folder is there (`fixtures` checked it): a missing file is a failure, CI or not.
    let path = files
        .iter()
        .find(|p| stem(p) == "kenney_tree_default_fall")
        .expect("kenney_tree_default_fall.glb in the fixture folder");
    let bytes = std::fs::read(path).unwrap();
    let m = import_gltf_slice(&bytes, "k", None).unwrap();
    // woodBirch primitive: 564 indices = 188 triangles; leafsFall: 120 indices = 40 triangles.
    assert_eq!(m.bark_mesh.triangle_count(), 188);
    assert!(m.leaves.len() <= 40 && m.leaves.len() > 30);
    assert!(m.bark_mesh.positions.len() <= 384);
}

fn accessor_count(doc: &gltf::Document, index: usize) -> usize {
    doc.accessors().nth(index).unwrap().count()
}

#[test]
fn fixtures_round_trip_through_glb() {
    let Some(files) = fixtures() else { return };
    for path in files {
        let name = stem(&path);
        let model = import_gltf(&path).unwrap();
        let glb = export_glb(&model, 1.0).unwrap();
        let parsed = gltf::Gltf::from_slice(&glb).unwrap();
        let doc = &parsed.document;
        let mesh = doc.meshes().next().unwrap();
        let prims: Vec<_> = mesh.primitives().collect();
        let bark = &prims[0];
        let pos = bark.get(&gltf::Semantic::Positions).unwrap();
        assert_eq!(pos.count(), model.bark_mesh.positions.len());
        assert_eq!(
            accessor_count(doc, bark.indices().unwrap().index()),
            model.bark_mesh.indices.len()
        );
        let leaf_vertices: usize = prims[1..]
            .iter()
            .map(|p| p.get(&gltf::Semantic::Positions).unwrap().count())
            .sum();
        assert_eq!(leaf_vertices, 4 * model.leaves.len());
        for p in &prims[1..] {
            assert_eq!(p.material().alpha_mode(), gltf::material::AlphaMode::Mask);
            assert!(p.material().double_sided());
            assert!(p.get(&gltf::Semantic::TexCoords(0)).is_some());
            let n = p.get(&gltf::Semantic::Positions).unwrap().count();
            assert_eq!(accessor_count(doc, p.indices().unwrap().index()), n / 4 * 6);
        }
        let back = import_gltf_slice(&glb, &name, None).unwrap();
        println!(
            "{name}: round trip {} -> {} leaves, {} -> {} bark triangles, {} bytes",
            model.leaves.len(),
            back.leaves.len(),
            model.bark_mesh.triangle_count(),
            back.bark_mesh.triangle_count(),
            glb.len()
        );
        assert_eq!(back.leaves.len(), model.leaves.len(), "{name}");
        assert_eq!(back.bark_mesh.triangle_count(), model.bark_mesh.triangle_count());
        assert_eq!(back.materials.leaf.len(), model.materials.leaf.len());
        for (a, b) in model.leaves.iter().zip(&back.leaves) {
            let tol = 1e-3 * (1.0 + a.length.max(a.width));
            assert!(a.center.distance(b.center) < 1e-3 * (1.0 + a.center.length()), "{name}");
            assert!((a.width - b.width).abs() < tol && (a.length - b.length).abs() < tol);
            assert!(a.axis.dot(b.axis) > 0.999, "{name}: axis {} vs {}", a.axis, b.axis);
            assert!(a.normal.dot(b.normal) > 0.999);
        }
        for (a, b) in model.materials.leaf.iter().zip(&back.materials.leaf) {
            for k in 0..4 {
                assert!((a.color[k].clamp(0.0, 1.0) - b.color[k]).abs() < 1e-6);
            }
        }
    }
}

#[test]
fn truncated_and_corrupted_fixtures_never_panic() {
    let Some(files) = fixtures() else { return };
    let mut rng = 0x9E37_79B9_7F4A_7C15_u64;
    let mut next = move || {
        rng ^= rng << 13;
        rng ^= rng >> 7;
        rng ^= rng << 17;
        rng
    };
    for path in &files {
        let bytes = std::fs::read(path).unwrap();
        // Truncations: every length for small files, ~400 lengths for big ones.
        let step = (bytes.len() / 400).max(1);
        let mut lengths: Vec<usize> = (0..bytes.len()).step_by(step).collect();
        lengths.extend([1, 11, 12, 19, 20, 21, bytes.len() - 1]);
        for len in lengths {
            let r = import_gltf_slice(&bytes[..len], "t", None);
            assert!(r.is_err(), "{}: truncation to {len} bytes imported", path.display());
        }
        // Random byte flips: any result but a panic.
        for _ in 0..150 {
            let mut b = bytes.clone();
            for _ in 0..=(next() % 8) {
                let i = (next() % b.len() as u64) as usize;
                b[i] = next() as u8;
            }
            let _ = import_gltf_slice(&b, "t", None);
        }
    }
    // Random bytes, with and without a GLB header.
    for n in 0..300 {
        let len = (next() % 2048) as usize;
        let mut b: Vec<u8> = (0..len).map(|_| next() as u8).collect();
        if n % 2 == 0 && b.len() >= 12 {
            b[..4].copy_from_slice(b"glTF");
            b[4..8].copy_from_slice(&2u32.to_le_bytes());
            let declared = (next() % 4096) as u32;
            b[8..12].copy_from_slice(&declared.to_le_bytes());
        }
        assert!(import_gltf_slice(&b, "r", None).is_err());
    }
}

// ---------------------------------------------------------------------------------------------
// Synthetic files

fn base64(data: &[u8]) -> String {
    const A: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut s = String::new();
    for c in data.chunks(3) {
        let n =
            (u32::from(c[0]) << 16) | (u32::from(*c.get(1).unwrap_or(&0)) << 8) | u32::from(*c.get(2).unwrap_or(&0));
        for k in 0..4 {
            if k <= c.len() {
                s.push(A[((n >> (18 - 6 * k)) & 63) as usize] as char);
            } else {
                s.push('=');
            }
        }
    }
    s
}

fn f32s(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|f| f.to_le_bytes()).collect()
}

/// A glTF JSON document with one base64 buffer.
fn doc_with_buffer(buffer: &[u8], rest: &Value) -> Vec<u8> {
    let mut doc = json!({
        "asset": { "version": "2.0" },
        "buffers": [{
            "byteLength": buffer.len(),
            "uri": format!("data:application/octet-stream;base64,{}", base64(buffer)),
        }],
    });
    for (k, v) in rest.as_object().unwrap() {
        doc[k] = v.clone();
    }
    serde_json::to_vec(&doc).unwrap()
}

/// Interleaved leaf quad (position, normal, uv; stride 32), u8 indices, MASK material, plus a
/// non-indexed bark triangle strip without normals.
fn synthetic() -> (Vec<u8>, Value) {
    // Quad in the XY plane, 0.2 wide (x) and 0.6 long (y), centre (1, 2, 0); v along +Y.
    let quad = [
        ([0.9, 1.7, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0]),
        ([1.1, 1.7, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0]),
        ([1.1, 2.3, 0.0], [0.0, 0.0, 1.0], [1.0, 1.0]),
        ([0.9, 2.3, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0]),
    ];
    let mut buf = Vec::new();
    for (p, n, uv) in quad {
        buf.extend(f32s(&p));
        buf.extend(f32s(&n));
        buf.extend(f32s(&uv));
    }
    let idx_off = buf.len(); // 128
    buf.extend([0u8, 1, 2, 0, 2, 3, 0, 0]);
    let strip_off = buf.len(); // 136
    // A 1 m tall, 0.2 wide vertical strip at the origin (4 vertices, 2 triangles).
    buf.extend(f32s(&[-0.1, 0.0, 0.0, 0.1, 0.0, 0.0, -0.1, 1.0, 0.0, 0.1, 1.0, 0.0]));
    let rest = json!({
        "bufferViews": [
            { "buffer": 0, "byteOffset": 0, "byteLength": 128, "byteStride": 32 },
            { "buffer": 0, "byteOffset": idx_off, "byteLength": 6 },
            { "buffer": 0, "byteOffset": strip_off, "byteLength": 48 },
        ],
        "accessors": [
            { "bufferView": 0, "byteOffset": 0, "componentType": 5126, "count": 4, "type": "VEC3" },
            { "bufferView": 0, "byteOffset": 12, "componentType": 5126, "count": 4, "type": "VEC3" },
            { "bufferView": 0, "byteOffset": 24, "componentType": 5126, "count": 4, "type": "VEC2" },
            { "bufferView": 1, "componentType": 5121, "count": 6, "type": "SCALAR" },
            { "bufferView": 2, "componentType": 5126, "count": 4, "type": "VEC3" },
        ],
        "materials": [
            { "name": "Material.001", "alphaMode": "MASK",
              "pbrMetallicRoughness": { "baseColorFactor": [0.1, 0.5, 0.2, 1.0] } },
            { "name": "Material.002",
              "pbrMetallicRoughness": { "baseColorFactor": [0.4, 0.3, 0.2, 1.0] } },
        ],
        "meshes": [
            { "primitives": [
                { "attributes": { "POSITION": 0, "NORMAL": 1, "TEXCOORD_0": 2 }, "indices": 3, "material": 0 },
                { "attributes": { "POSITION": 4 }, "mode": 5, "material": 1 },
                { "attributes": { "POSITION": 4 }, "mode": 1 },
            ] },
        ],
        "nodes": [
            { "children": [1], "translation": [5.0, 0.0, 0.0] },
            { "mesh": 0, "matrix": [1,0,0,0, 0,1,0,0, 0,0,1,0, 0,3,0,1] },
        ],
        "scenes": [{ "nodes": [0, 1] }],
    });
    (buf, rest)
}

#[test]
fn synthetic_interleaved_u8_strip_lines_hierarchy() {
    let (buf, rest) = synthetic();
    let bytes = doc_with_buffer(&buf, &rest);
    let report = import_gltf_report(&bytes, "synthetic", None).unwrap();
    let m = &report.model;
    println!("warnings: {:?}", report.warnings);
    // The line primitive is skipped with a warning; the node listed twice is imported once.
    assert_eq!(report.stats.skipped_primitives, 1);
    assert!(report.warnings.iter().any(|w| w.contains("Lines")));
    assert!(report.warnings.iter().any(|w| w.contains("no default scene")));
    assert_eq!(m.bark_mesh.triangle_count(), 2);
    assert_eq!(m.leaves.len(), 1);
    assert_eq!(report.stats.computed_normals, 4);
    for n in &m.bark_mesh.normals {
        assert!((n.z.abs() - 1.0).abs() < 1e-5);
    }
    // World = translate(5,0,0) * translate(0,3,0); base of the bark strip at (5, 3, 0) moves to
    // the origin, so the leaf centre (1,2,0) + (5,3,0) - (5,3,0) = (1, 2, 0).
    let l = m.leaves[0];
    check_leaf(&l);
    assert!(l.center.distance(Vec3::new(1.0, 2.0, 0.0)) < 1e-5, "{}", l.center);
    assert!((l.width - 0.2).abs() < 1e-5 && (l.length - 0.6).abs() < 1e-5);
    assert!(l.axis.dot(Vec3::Y) > 0.9999);
    assert!(l.normal.dot(Vec3::Z) > 0.9999);
    assert_eq!(m.materials.leaf[0].color, [0.1, 0.5, 0.2, 1.0]);
    assert_eq!(m.materials.bark_color, [0.4, 0.3, 0.2, 1.0]);
}

#[test]
fn synthetic_sparse_accessor_and_external_buffer() {
    let (buf, mut rest) = synthetic();
    // Sparse: move strip vertex 3 to x = 0.3 using u16 indices and values in a new view.
    let mut buf = buf;
    let sparse_off = buf.len(); // 184
    buf.extend(3u16.to_le_bytes());
    buf.extend([0, 0]);
    buf.extend(f32s(&[0.3, 1.0, 0.0]));
    rest["bufferViews"]
        .as_array_mut()
        .unwrap()
        .push(json!({ "buffer": 0, "byteOffset": sparse_off, "byteLength": 16 }));
    rest["accessors"][4]["sparse"] = json!({
        "count": 1,
        "indices": { "bufferView": 3, "componentType": 5123 },
        "values": { "bufferView": 3, "byteOffset": 4 },
    });
    // External buffer next to the document.
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("gltf_external");
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("tree data.bin"), &buf).unwrap();
    let mut doc = json!({ "asset": { "version": "2.0" }, "scene": 0,
        "buffers": [{ "byteLength": buf.len(), "uri": "tree%20data.bin" }] });
    for (k, v) in rest.as_object().unwrap() {
        doc[k] = v.clone();
    }
    std::fs::write(dir.join("tree.gltf"), serde_json::to_vec(&doc).unwrap()).unwrap();
    let m = import_gltf(&dir.join("tree.gltf")).unwrap();
    let max_x = m.bark_mesh.positions.iter().map(|p| p.x).fold(f32::MIN, f32::max);
    let min_x = m.bark_mesh.positions.iter().map(|p| p.x).fold(f32::MAX, f32::min);
    assert!((max_x - min_x - 0.4).abs() < 1e-5, "sparse value not applied");
    // Without a base folder the external buffer is a typed error.
    let bytes = serde_json::to_vec(&doc).unwrap();
    assert!(matches!(
        import_gltf_slice(&bytes, "x", None),
        Err(ImportError::Buffer { .. })
    ));
    // Escaping the folder is refused.
    doc["buffers"][0]["uri"] = json!("../gltf_external/tree%20data.bin");
    let bytes = serde_json::to_vec(&doc).unwrap();
    assert!(matches!(
        import_gltf_slice(&bytes, "x", Some(&dir)),
        Err(ImportError::Buffer { .. })
    ));
}

#[test]
fn leaf_detection_by_shape_and_names() {
    // 20 small disjoint quads under a neutral material name: the shape rule makes them leaves.
    let mut pos = Vec::new();
    let mut idx: Vec<u32> = Vec::new();
    for i in 0..20u32 {
        let c = Vec3::new(i as f32, (i % 3) as f32, 0.0);
        for d in [[-0.05, -0.1], [0.05, -0.1], [0.05, 0.1], [-0.05, 0.1]] {
            pos.extend((c + Vec3::new(d[0], d[1], 0.0)).to_array());
        }
        let b = 4 * i;
        idx.extend([b, b + 1, b + 2, b, b + 2, b + 3]);
    }
    let mut buf = f32s(&pos);
    let ioff = buf.len();
    buf.extend(idx.iter().flat_map(|i| i.to_le_bytes()));
    let rest = json!({
        "bufferViews": [
            { "buffer": 0, "byteLength": ioff },
            { "buffer": 0, "byteOffset": ioff, "byteLength": idx.len() * 4 },
        ],
        "accessors": [
            { "bufferView": 0, "componentType": 5126, "count": 80, "type": "VEC3" },
            { "bufferView": 1, "componentType": 5125, "count": idx.len(), "type": "SCALAR" },
        ],
        "materials": [{ "name": "Material" }],
        "meshes": [{ "name": "Plane", "primitives": [{ "attributes": { "POSITION": 0 }, "indices": 1, "material": 0 }] }],
        "nodes": [{ "mesh": 0 }],
        "scenes": [{ "nodes": [0] }],
        "scene": 0,
    });
    let m = import_gltf_slice(&doc_with_buffer(&buf, &rest), "shape", None).unwrap();
    assert_eq!(m.leaves.len(), 20);
    assert!(m.bark_mesh.positions.is_empty());
    for l in &m.leaves {
        check_leaf(l);
        // No uvs: axis along the longest side (the 0.2 side along Y).
        assert!(l.axis.dot(Vec3::Y).abs() > 0.9999);
        assert!((l.length - 0.2).abs() < 1e-5 && (l.width - 0.1).abs() < 1e-5);
    }
    // A bark material name overrides the shape rule.
    let mut named = rest.clone();
    named["materials"][0]["name"] = json!("OakBark");
    let m = import_gltf_slice(&doc_with_buffer(&buf, &named), "bark", None).unwrap();
    assert!(m.leaves.is_empty());
    assert_eq!(m.bark_mesh.triangle_count(), 40);
    // A node named "foliage" makes a primitive leaves even when the shape would not.
    let mut named = rest.clone();
    named["accessors"][1]["count"] = json!(6);
    named["nodes"][0]["name"] = json!("Foliage_01");
    let m = import_gltf_slice(&doc_with_buffer(&buf, &named), "one", None).unwrap();
    assert_eq!(m.leaves.len(), 1);
    // Two quads that share corner positions (welded) but not indices stay two leaves.
    let mut touching = rest;
    let shared: Vec<f32> = [
        [0.0, 0.0, 0.0],
        [0.1, 0.0, 0.0],
        [0.1, 0.2, 0.0],
        [0.0, 0.2, 0.0],
        [0.1, 0.0, 0.0],
        [0.2, 0.0, 0.0],
        [0.2, 0.2, 0.0],
        [0.1, 0.2, 0.0],
    ]
    .concat();
    let mut buf = f32s(&shared);
    let ioff = buf.len();
    let idx: [u32; 12] = [0, 1, 2, 0, 2, 3, 4, 5, 6, 4, 6, 7];
    buf.extend(idx.iter().flat_map(|i| i.to_le_bytes()));
    touching["bufferViews"][0]["byteLength"] = json!(ioff);
    touching["bufferViews"][1] = json!({ "buffer": 0, "byteOffset": ioff, "byteLength": 48 });
    touching["accessors"][0]["count"] = json!(8);
    touching["accessors"][1]["count"] = json!(12);
    touching["materials"][0]["name"] = json!("leaves");
    let m = import_gltf_slice(&doc_with_buffer(&buf, &touching), "touch", None).unwrap();
    assert_eq!(m.leaves.len(), 2);
}

#[test]
fn corrupt_json_gives_typed_errors() {
    let (buf, rest) = synthetic();
    let run = |f: &dyn Fn(&mut Value)| {
        let mut r = rest.clone();
        f(&mut r);
        import_gltf_slice(&doc_with_buffer(&buf, &r), "c", None)
    };
    let e = run(&|r| r["meshes"][0]["primitives"][0]["attributes"]["POSITION"] = json!(99));
    assert!(
        matches!(e, Err(ImportError::InvalidReference { kind: "accessor", .. })),
        "{e:?}"
    );
    let e = run(&|r| r["accessors"][0]["bufferView"] = json!(42));
    assert!(
        matches!(e, Err(ImportError::InvalidReference { kind: "bufferView", .. })),
        "{e:?}"
    );
    let e = run(&|r| r["bufferViews"][0]["buffer"] = json!(7));
    assert!(
        matches!(e, Err(ImportError::InvalidReference { kind: "buffer", .. })),
        "{e:?}"
    );
    let e = run(&|r| r["accessors"][0]["count"] = json!(4_000_000_000_u64));
    assert!(matches!(e, Err(ImportError::AccessorOutOfBounds { .. })), "{e:?}");
    let e = run(&|r| r["accessors"][4]["count"] = json!(u64::MAX));
    assert!(e.is_err(), "{e:?}");
    let e = run(&|r| {
        r["accessors"][4].as_object_mut().unwrap().remove("bufferView");
        r["accessors"][4]["count"] = json!(4_000_000_000_u64);
    });
    assert!(matches!(e, Err(ImportError::AccessorOutOfBounds { .. })), "{e:?}");
    let e = run(&|r| r["bufferViews"][0]["byteLength"] = json!(100_000));
    assert!(matches!(e, Err(ImportError::AccessorOutOfBounds { .. })), "{e:?}");
    let e = run(&|r| r["bufferViews"][0]["byteStride"] = json!(4));
    assert!(matches!(e, Err(ImportError::BadAccessor { .. })), "{e:?}");
    let e = run(&|r| r["accessors"][0]["type"] = json!("VEC2"));
    assert!(matches!(e, Err(ImportError::BadAccessor { .. })), "{e:?}");
    let e = run(&|r| r["accessors"][3]["componentType"] = json!(5126));
    assert!(matches!(e, Err(ImportError::BadAccessor { .. })), "{e:?}");
    let e = run(&|r| {
        r["nodes"][1]["matrix"] = json!([1e30, 0, 0, 0, 0, 1e30, 0, 0, 0, 0, 1e30, 0, 0, 0, 0, 1e30]);
    });
    assert!(
        e.is_ok() || matches!(e, Err(ImportError::NonFinitePosition { .. })),
        "{e:?}"
    );
    let e = run(&|r| {
        r["nodes"][1]["matrix"] = json!([3e38, 0, 0, 0, 0, 3e38, 0, 0, 0, 0, 3e38, 0, 0, 0, 0, 1]);
    });
    assert!(matches!(e, Err(ImportError::NonFinitePosition { .. })), "{e:?}");
    // Cycles in the node graph and dangling children do not hang or panic.
    let e = run(&|r| {
        r["nodes"][1]["children"] = json!([0, 1, 77]);
    });
    assert!(e.is_ok(), "{e:?}");
    // A node referring to a missing mesh is skipped; with nothing left there is no geometry.
    let e = run(&|r| r["nodes"][1]["mesh"] = json!(5));
    assert!(matches!(e, Err(ImportError::NoGeometry)), "{e:?}");
    let e = run(&|r| {
        r["buffers"] = json!([{ "byteLength": 10, "uri": "data:application/octet-stream;base64,@@@" }]);
    });
    assert!(matches!(e, Err(ImportError::Buffer { .. })), "{e:?}");
    let e = run(&|r| r["asset"]["version"] = json!("1.0"));
    assert!(matches!(e, Err(ImportError::Unsupported(_))), "{e:?}");
    // Out-of-range vertex index.
    let mut b = buf.clone();
    b[128] = 9;
    let e = import_gltf_slice(&doc_with_buffer(&b, &rest), "c", None);
    assert!(matches!(e, Err(ImportError::IndexOutOfRange { index: 9, .. })), "{e:?}");
    // NaN position.
    let mut b = buf.clone();
    b[0..4].copy_from_slice(&f32::NAN.to_le_bytes());
    let e = import_gltf_slice(&doc_with_buffer(&b, &rest), "c", None);
    assert!(matches!(e, Err(ImportError::NonFinitePosition { .. })), "{e:?}");
    // Not glTF at all.
    assert!(matches!(
        import_gltf_slice(b"hello", "c", None),
        Err(ImportError::NotGltf(_))
    ));
    assert!(matches!(
        import_gltf_slice(b"", "c", None),
        Err(ImportError::NotGltf(_))
    ));
    assert!(matches!(
        import_gltf_slice(b"{\"x\": 1}", "c", None),
        Err(ImportError::Json(_))
    ));
    assert!(matches!(
        import_gltf_slice(b"{\"asset\":{\"version\":\"2.0\"}}", "c", None),
        Err(ImportError::NoGeometry)
    ));
    assert!(matches!(
        import_gltf(Path::new("/nonexistent/tree.glb")),
        Err(ImportError::Io { .. })
    ));
}

#[test]
fn glb_container_errors() {
    let (buf, rest) = synthetic();
    let json_bytes = doc_with_buffer(&buf, &rest);
    let glb = |json_len: u32, total: u32, body: &[u8]| {
        let mut v = b"glTF".to_vec();
        v.extend(2u32.to_le_bytes());
        v.extend(total.to_le_bytes());
        v.extend(json_len.to_le_bytes());
        v.extend(b"JSON");
        v.extend(body);
        v
    };
    let n = json_bytes.len() as u32;
    let ok = glb(n, 20 + n, &json_bytes);
    assert!(import_gltf_slice(&ok, "g", None).is_ok());
    assert!(matches!(
        import_gltf_slice(&glb(n, 20 + n + 100, &json_bytes), "g", None),
        Err(ImportError::TruncatedGlb(_))
    ));
    assert!(matches!(
        import_gltf_slice(&glb(n + 100, 20 + n, &json_bytes), "g", None),
        Err(ImportError::TruncatedGlb(_))
    ));
    assert!(matches!(
        import_gltf_slice(&glb(n, 3, &json_bytes), "g", None),
        Err(ImportError::MalformedGlb(_))
    ));
    let mut v1 = ok.clone();
    v1[4] = 1;
    assert!(matches!(
        import_gltf_slice(&v1, "g", None),
        Err(ImportError::MalformedGlb(_))
    ));
    // Buffer 0 without uri but no BIN chunk.
    let mut doc: Value = serde_json::from_slice(&json_bytes).unwrap();
    doc["buffers"][0].as_object_mut().unwrap().remove("uri");
    let j = serde_json::to_vec(&doc).unwrap();
    let nj = j.len() as u32;
    assert!(matches!(
        import_gltf_slice(&glb(nj, 20 + nj, &j), "g", None),
        Err(ImportError::Buffer { .. })
    ));
}

// ---------------------------------------------------------------------------------------------
// Export of skeleton models

fn lsystem_like() -> TreeModel {
    let trunk = Branch {
        points: (0..5)
            .map(|i| SkeletonPoint {
                position: Vec3::new(0.05 * (i as f32).sin(), i as f32, 0.0),
                radius: 0.2 - 0.03 * i as f32,
            })
            .collect(),
        parent: None,
        level: 1,
        iteration: 0,
    };
    let side = Branch {
        points: vec![
            SkeletonPoint {
                position: Vec3::new(0.0, 2.0, 0.0),
                radius: 0.08,
            },
            SkeletonPoint {
                position: Vec3::new(1.0, 2.8, 0.3),
                radius: 0.02,
            },
        ],
        parent: Some(0),
        level: 2,
        iteration: 1,
    };
    let leaves = (0..30)
        .map(|i| {
            let a = i as f32 * 0.7;
            Leaf {
                center: Vec3::new(a.cos(), 3.0 + 0.03 * i as f32, a.sin()),
                normal: Vec3::new(a.cos(), 0.5, a.sin()).normalize(),
                axis: Vec3::new(-a.sin(), 0.0, a.cos()),
                width: 0.05,
                length: 0.12,
                branch: Some(1),
                iteration: 1,
                material: u8::from(i % 3 == 0),
            }
        })
        .collect();
    let mut materials = Materials::default();
    materials.leaf.push(materials.leaf[0].clone());
    materials.leaf[1].color = [0.8, 0.6, 0.1, 1.0];
    TreeModel {
        name: "demo".into(),
        branches: vec![trunk, side],
        leaves,
        bark_mesh: TriangleMesh::default(),
        materials,
        iterations: 1,
        source: ModelSource::LSystem,
    }
}

#[test]
fn skeleton_model_exports_valid_glb() {
    let mut model = lsystem_like();
    // Orthonormalise leaf frames as the L-system would.
    for l in &mut model.leaves {
        l.axis = (l.axis - l.normal * l.axis.dot(l.normal)).normalize();
    }
    let glb = export_glb(&model, 1.5).unwrap();
    assert_eq!(&glb[..4], b"glTF");
    assert_eq!(u32::from_le_bytes(glb[8..12].try_into().unwrap()) as usize, glb.len());
    assert_eq!(glb.len() % 4, 0);
    let parsed = gltf::Gltf::from_slice(&glb).unwrap();
    let mesh = parsed.document.meshes().next().unwrap();
    let prims: Vec<_> = mesh.primitives().collect();
    assert_eq!(prims.len(), 3);
    let bark_vertices = prims[0].get(&gltf::Semantic::Positions).unwrap().count();
    assert_eq!(bark_vertices, (5 + 2) * 8);
    let pos = prims[1].get(&gltf::Semantic::Positions).unwrap();
    assert_eq!(pos.count(), 4 * 20);
    assert_eq!(prims[2].get(&gltf::Semantic::Positions).unwrap().count(), 4 * 10);
    // min/max present (validation requires it) and containing the 1.5x leaf.
    let bounds = pos.min().unwrap();
    assert_eq!(bounds.as_array().unwrap().len(), 3);

    let back = import_gltf_slice(&glb, "demo", None).unwrap();
    assert_eq!(back.leaves.len(), model.leaves.len());
    assert_eq!(back.materials.leaf.len(), 2);
    assert_eq!(back.leaves.iter().filter(|l| l.material == 1).count(), 10);
    // Leaf size carries the 1.5 enlargement.
    for l in &back.leaves {
        assert!((l.width - 0.075).abs() < 1e-4 && (l.length - 0.18).abs() < 1e-4);
    }

    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR"));
    let path = dir.join("demo_export.glb");
    export_glb_to(&path, &model, 1.0).unwrap();
    assert_eq!(import_gltf(&path).unwrap().leaves.len(), 30);

    // Empty model: still a valid file.
    let empty = TreeModel {
        branches: vec![],
        leaves: vec![],
        ..model.clone()
    };
    let glb = export_glb(&empty, 1.0).unwrap();
    gltf::Gltf::from_slice(&glb).unwrap();
    assert!(matches!(
        import_gltf_slice(&glb, "e", None),
        Err(ImportError::NoGeometry)
    ));
    // Non-finite input is a typed error.
    let mut bad = model.clone();
    bad.leaves[0].center.x = f32::NAN;
    assert!(export_glb(&bad, 1.0).is_err());
    assert!(export_glb(&model, f32::INFINITY).is_err());
    let mut bad = model;
    bad.bark_mesh.positions = vec![Vec3::ZERO];
    bad.bark_mesh.indices = vec![0, 0, 1];
    assert!(export_glb(&bad, 1.0).is_err());
}

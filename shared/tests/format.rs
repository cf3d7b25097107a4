//! Round-trip and corrupt-input tests of the `.ctree` format.

use canopy_shared::format::directory::SectionKind;
use canopy_shared::format::leaf::{DEFAULT_BAND_EDGES, decode_block};
use canopy_shared::format::tree::{decode_index, decode_node_index, section_bytes};
use canopy_shared::format::{
    BakedTree, DecodedTree, FIRST_REQUEST_LEN, FormatError, HEADER_LEN, LeafOrder, NO_BRANCH, NO_PARENT, NodeKind,
    NodeRecord, SectionBody, encode_tree,
};
use canopy_shared::model::{Branch, Leaf, LeafMaterial, Materials, ModelSource, SkeletonPoint, TriangleMesh};
use glam::Vec3;
use proptest::prelude::*;

fn node(parent: u32, kind: NodeKind, level: u8, branch: u32, leaves: u32, end: u32) -> NodeRecord {
    NodeRecord {
        parent,
        subtree_end: end,
        kind,
        branch_level: level,
        sphere_layer: 1 + (end % 3) as u8,
        branch,
        leaf_count: leaves,
        growth_direction: Vec3::Y,
        length: 2.0,
        sphere_center: Vec3::new(0.0, 2.0, 0.0),
        sphere_radius: 3.0,
        leaf_density: leaves as f32 / 2.0,
    }
}

/// A small tree: trunk + 2 branches (iterations 0, 1, 2), three leaf nodes of 1, 37 and 100 leaves.
fn sample() -> BakedTree {
    let p = |x: f32, y: f32, z: f32, r: f32| SkeletonPoint {
        position: Vec3::new(x, y, z),
        radius: r,
    };
    let branches = vec![
        Branch {
            points: vec![p(0.0, 0.0, 0.0, 0.2), p(0.0, 4.0, 0.0, 0.1)],
            parent: None,
            level: 1,
            iteration: 0,
        },
        Branch {
            points: vec![p(0.0, 2.0, 0.0, 0.08), p(1.5, 3.0, 0.2, 0.03), p(2.0, 3.5, 0.4, 0.01)],
            parent: Some(0),
            level: 2,
            iteration: 1,
        },
        Branch {
            points: vec![p(0.0, 3.0, 0.0, 0.06), p(-1.0, 4.0, -0.5, 0.02)],
            parent: Some(0),
            level: 2,
            iteration: 2,
        },
    ];
    let mk = |n: usize, branch: u32, iteration: u8| -> Vec<Leaf> {
        (0..n)
            .map(|i| {
                let t = i as f32 / n.max(1) as f32;
                let normal = Vec3::new(t.sin(), 0.5, t.cos()).normalize();
                let axis = normal.any_orthonormal_vector();
                Leaf {
                    center: Vec3::new(t * 2.0 - 1.0, 2.0 + t * 2.0, (t * 9.0).sin()),
                    normal,
                    axis,
                    width: 0.03 + 0.02 * t,
                    length: 0.06 + 0.03 * t,
                    branch: Some(branch),
                    iteration,
                    material: (i % 2) as u8,
                }
            })
            .collect()
    };
    let nodes = vec![
        node(NO_PARENT, NodeKind::Branch, 1, 0, 0, 6),
        node(0, NodeKind::Leaf, 1, 0, 1, 2),
        node(0, NodeKind::Branch, 2, 1, 0, 4),
        node(2, NodeKind::Leaf, 2, 1, 37, 4),
        node(0, NodeKind::Branch, 2, 2, 0, 6),
        node(4, NodeKind::Leaf, 2, 2, 100, 6),
    ];
    BakedTree {
        name: "sample".into(),
        source: ModelSource::LSystem,
        leaf_order: LeafOrder::Random,
        iterations: 2,
        band_edges: DEFAULT_BAND_EDGES.to_vec(),
        branches,
        materials: Materials {
            bark_color: [0.3, 0.2, 0.1, 1.0],
            bark_texture: Some("bark.png".into()),
            leaf: vec![
                LeafMaterial {
                    color: [0.1, 0.5, 0.1, 1.0],
                    texture: Some("leaf.png".into()),
                },
                LeafMaterial {
                    color: [0.2, 0.6, 0.1, 1.0],
                    texture: None,
                },
            ],
        },
        bark_mesh: TriangleMesh {
            positions: vec![Vec3::ZERO, Vec3::X, Vec3::Y],
            normals: vec![Vec3::Z; 3],
            indices: vec![0, 1, 2],
        },
        nodes,
        node_leaves: vec![mk(1, 0, 0), mk(37, 1, 1), mk(100, 2, 2)],
        hulls: SectionBody::default(),
        atlases: SectionBody::default(),
        clouds: SectionBody::default(),
    }
}

#[test]
fn round_trip_within_error_bounds() {
    let t = sample();
    let bytes = encode_tree(&t).expect("encode");
    let d = DecodedTree::decode(&bytes).expect("decode");
    assert_eq!(d.directory.name, "sample");
    assert_eq!(d.directory.leaf_order, LeafOrder::Random);
    assert_eq!(d.nodes, t.nodes);
    assert_eq!(d.materials, t.materials);
    assert_eq!(d.branches.len(), 3);
    let ext = d.directory.bounds_max - d.directory.bounds_min;
    let tol = ext.max_element() / 131_070.0 + 1e-5;
    for (a, b) in t.branches.iter().zip(&d.branches) {
        assert_eq!((a.parent, a.level, a.iteration), (b.parent, b.level, b.iteration));
        for (p, q) in a.points.iter().zip(&b.points) {
            assert!(
                p.position.distance(q.position) <= tol * 1.8,
                "{} vs {}",
                p.position,
                q.position
            );
            assert!((p.radius - q.radius).abs() <= 0.2 / 131_070.0 + 1e-6);
        }
    }
    for (a, b) in t.node_leaves.iter().zip(&d.node_leaves) {
        assert_eq!(a.len(), b.len());
        for (l, m) in a.iter().zip(b) {
            assert!(l.center.distance(m.center) <= tol * 1.8);
            assert!(l.normal.angle_between(m.normal).to_degrees() < 0.3);
            assert!(l.axis.angle_between(m.axis).to_degrees() < 0.3);
            assert!((l.width - m.width).abs() < 1e-5 && (l.length - m.length).abs() < 1e-5);
            assert_eq!((l.iteration, l.material, l.branch), (m.iteration, m.material, m.branch));
        }
    }
    assert_eq!(d.bark_mesh.indices, vec![0, 1, 2]);
    // Encoding is deterministic.
    assert_eq!(encode_tree(&t).expect("encode"), bytes);
}

#[test]
fn uniform_rate_is_one_contiguous_range_and_blocks_verify() {
    let t = sample();
    let bytes = encode_tree(&t).expect("encode");
    let idx = open_index(&bytes);
    let leaves = *idx.directory.section(SectionKind::Leaves).expect("leaves");
    let section = section_bytes(&bytes, &leaves).expect("section");
    let mut covered = 0;
    for b in 0..idx.layout.band_count() {
        // Bands 0..=b form one contiguous range starting at the section start.
        let r = idx.layout.band_range(b);
        assert_eq!(r.start, covered);
        covered = r.end;
        for i in 0..3 {
            if let Some(blk) = idx.layout.block(b, i) {
                let q = decode_block(
                    &section[blk.offset as usize..(blk.offset + blk.len) as usize],
                    blk.count,
                    2,
                )
                .expect("block");
                assert_eq!(q.len() as u32, blk.count);
            }
        }
    }
    assert_eq!(covered, section.len() as u64);
}

/// Header, directory and node index as a client builds them: from the first
/// [`FIRST_REQUEST_LEN`] bytes, then the node table.
struct Opened {
    directory: canopy_shared::format::Directory,
    nodes: Vec<canopy_shared::format::NodeRecord>,
    layout: canopy_shared::format::BandLayout,
}

fn open_index(bytes: &[u8]) -> Opened {
    let first = &bytes[..bytes.len().min(FIRST_REQUEST_LEN as usize)];
    let (_, directory) = decode_index(first, Some(bytes.len() as u64)).expect("index");
    let e = *directory.section(SectionKind::NodeTable).expect("node table");
    let table = section_bytes(bytes, &e).expect("node table bytes");
    let idx = decode_node_index(&directory, table).expect("node index");
    Opened {
        directory,
        nodes: idx.nodes,
        layout: idx.layout,
    }
}

#[test]
fn first_request_holds_header_and_directory() {
    let bytes = encode_tree(&sample()).expect("encode");
    assert!(bytes.len() as u64 <= FIRST_REQUEST_LEN, "the sample is a small file");
    let idx = open_index(&bytes);
    assert_eq!(idx.nodes.len(), 6);
    assert_eq!(
        idx.layout.leaf_counts().len(),
        idx.nodes.iter().filter(|n| n.kind == NodeKind::Leaf).count()
    );
    // A flipped node-table byte is refused by its CRC.
    let (_, directory) = decode_index(&bytes, Some(bytes.len() as u64)).expect("index");
    let e = *directory.section(SectionKind::NodeTable).expect("node table");
    let mut table = section_bytes(&bytes, &e).expect("node table bytes").to_vec();
    table[0] ^= 1;
    assert!(matches!(
        decode_node_index(&directory, &table),
        Err(FormatError::ChecksumMismatch { .. })
    ));
}

#[test]
fn every_truncation_is_rejected() {
    let bytes = encode_tree(&sample()).expect("encode");
    for len in 0..bytes.len() {
        assert!(
            DecodedTree::decode(&bytes[..len]).is_err(),
            "truncated to {len} accepted"
        );
    }
}

#[test]
fn every_single_byte_flip_is_rejected() {
    let bytes = encode_tree(&sample()).expect("encode");
    for i in 0..bytes.len() {
        let mut b = bytes.clone();
        b[i] ^= 0x5A;
        assert!(DecodedTree::decode(&b).is_err(), "flip at {i} accepted");
    }
}

#[test]
fn over_long_and_wrong_version_are_rejected() {
    let mut bytes = encode_tree(&sample()).expect("encode");
    let mut long = bytes.clone();
    long.extend_from_slice(&[0; 7]);
    assert!(matches!(
        DecodedTree::decode(&long),
        Err(FormatError::Invalid {
            what: "file length",
            ..
        })
    ));
    bytes[8] = 2;
    assert!(matches!(
        DecodedTree::decode(&bytes),
        Err(FormatError::UnsupportedVersion { major: 2, .. })
    ));
    bytes[0] = b'X';
    assert_eq!(DecodedTree::decode(&bytes).err(), Some(FormatError::BadMagic));
    assert!(DecodedTree::decode(&[]).is_err());
    assert!(DecodedTree::decode(&[0u8; HEADER_LEN]).is_err());
}

#[test]
fn inconsistent_input_is_not_encoded() {
    let mut t = sample();
    t.node_leaves.pop();
    assert!(encode_tree(&t).is_err());
    let mut t = sample();
    t.node_leaves[1][0].center.x = f32::NAN;
    assert!(encode_tree(&t).is_err());
    let mut t = sample();
    t.branches.swap(1, 2);
    assert!(encode_tree(&t).is_err());
    let mut t = sample();
    t.nodes[5].branch = NO_BRANCH;
    assert!(encode_tree(&t).is_ok(), "nodes without skeleton branches are legal");
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 256, ..ProptestConfig::default() })]
    #[test]
    fn random_bytes_never_panic(data in proptest::collection::vec(any::<u8>(), 0..2048)) {
        let _ = DecodedTree::decode(&data);
    }

    #[test]
    fn random_edits_never_panic(edits in proptest::collection::vec((any::<usize>(), any::<u8>()), 1..8)) {
        let mut bytes = encode_tree(&sample()).expect("encode");
        for (i, v) in edits {
            let n = bytes.len();
            bytes[i % n] = v;
        }
        let _ = DecodedTree::decode(&bytes);
    }
}

//! CPU rasterizer throughput: triangles per second for a 300k-leaf cloud (600k triangles).
//!
//! `cargo bench -p canopy-shared --bench raster -- --warm-up-time 1 --measurement-time 3`

use std::hint::black_box;

use canopy_shared::raster::{
    ABuffer, Camera, RasterMesh, RenderOptions, Scene, Texture, TreeMeshOptions, render, tree_materials,
};
use canopy_shared::{Leaf, Materials, ModelSource, TreeModel, TriangleMesh};
use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use glam::Vec3;

const LEAVES: usize = 300_000;
const CROWN_RADIUS: f32 = 5.0;

/// A crown-like random leaf cloud: leaves uniform in a sphere of radius 5 m, 5 × 8 cm blades.
fn leaf_cloud(n: usize) -> TreeModel {
    let mut s = 0x2545_f491_4f6c_dd1d_u64;
    let mut rnd = move || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        (s >> 40) as f32 / (1u64 << 24) as f32 * 2.0 - 1.0
    };
    let mut leaves = Vec::with_capacity(n);
    while leaves.len() < n {
        let c = Vec3::new(rnd(), rnd(), rnd());
        if c.length_squared() > 1.0 {
            continue;
        }
        let normal = Vec3::new(rnd(), rnd(), rnd()).normalize_or(Vec3::Y);
        leaves.push(Leaf {
            center: c * CROWN_RADIUS + Vec3::Y * 6.0,
            normal,
            axis: normal.any_orthonormal_vector(),
            width: 0.05,
            length: 0.08,
            branch: None,
            iteration: 0,
            material: 0,
        });
    }
    TreeModel {
        name: "cloud".into(),
        branches: vec![],
        leaves,
        bark_mesh: TriangleMesh::default(),
        materials: Materials::default(),
        iterations: 0,
        source: ModelSource::LSystem,
    }
}

fn bench(c: &mut Criterion) {
    let model = leaf_cloud(LEAVES);
    let mesh = RasterMesh::from_tree(&model, &TreeMeshOptions::default());
    let textures = [Texture::procedural_leaf(32)];
    let materials = tree_materials(&model, &[Some(0)]);
    let scene = Scene::single(&mesh, &materials, &textures);
    let tris = mesh.triangle_count() as u64;
    let centre = Vec3::Y * 6.0;
    let cam = Camera::orbit_perspective(centre, CROWN_RADIUS * 1.05, Vec3::new(0.3, 0.2, 1.0), 0.7);

    // One-off figures for benchmarks/log.md: coverage and A-buffer size.
    if let (Ok(f), Ok(ab)) = (
        render(&scene, &cam, 512, 512, &RenderOptions::default()),
        ABuffer::render(&scene, &cam, 256, 256),
    ) {
        let covered = f.coverage().iter().filter(|&&b| b).count();
        let ab_covered = (0..256 * 256).filter(|&p| !ab.fragments(p).is_empty()).count();
        eprintln!(
            "scene: {tris} triangles; 512² coverage {covered} px; A-buffer 256²: {} fragments \
             over {ab_covered} covered px ({:.1} per covered px), {:.1} MiB, {} items",
            ab.fragment_count(),
            ab.fragment_count() as f64 / ab_covered.max(1) as f64,
            ab.memory_bytes() as f64 / (1024.0 * 1024.0),
            ab.items().len()
        );
    }

    let mut g = c.benchmark_group("raster");
    g.sample_size(10);
    g.throughput(Throughput::Elements(tris));
    g.bench_function("render_512_color_depth_item_600k_tris", |b| {
        b.iter(|| render(black_box(&scene), &cam, 512, 512, &RenderOptions::default()));
    });
    let no_shade = RenderOptions {
        shade: false,
        ..RenderOptions::default()
    };
    g.bench_function("render_512_depth_item_600k_tris", |b| {
        b.iter(|| render(black_box(&scene), &cam, 512, 512, &no_shade));
    });
    g.bench_function("abuffer_256_600k_tris", |b| {
        b.iter(|| ABuffer::render(black_box(&scene), &cam, 256, 256));
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);

//! VMI leaf order: the incremental A-buffer method against the paper's literal method
//! (re-render every view for every candidate after every removal), on one real leaf node.
//!
//! `cargo bench -p canopy-server --bench vmi`

use std::path::Path;

use canopy_server::bake::hierarchy;
use canopy_server::bake::vmi::{VmiOptions, vmi_order, vmi_order_exact};
use canopy_server::lsystem::Limits;
use canopy_server::species::{SpeciesSpec, grow};
use canopy_shared::format::NodeKind;
use criterion::{Criterion, criterion_group, criterion_main};

fn bench(c: &mut Criterion) {
    let spec_path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../assets/species/small_shrub.toml");
    let spec = SpeciesSpec::load(&spec_path).expect("spec");
    let model = grow(&spec, &Limits::default()).expect("grow");
    let h = hierarchy::build(&model, hierarchy::TARGET_LEAVES_PER_NODE);
    // The first leaf node with at least 32 leaves, cut to 32 so the literal method stays feasible.
    let (k, node) = h
        .nodes
        .iter()
        .filter(|n| n.kind == NodeKind::Leaf)
        .enumerate()
        .find(|(k, _)| h.node_leaves[*k].len() >= 32)
        .expect("a node of 32 leaves");
    let leaves: Vec<u32> = h.node_leaves[k][..32].to_vec();
    let mut node = *node;
    node.leaf_count = 32;
    // The literal method ranks the node alone, so the incremental one does too here.
    let opts = VmiOptions {
        context_resolution: 0,
        ..VmiOptions::default()
    };
    let mut g = c.benchmark_group("vmi_32_leaves_32_views");
    g.sample_size(10);
    g.bench_function("incremental_abuffer", |b| {
        b.iter(|| {
            let mut lists = vec![leaves.clone()];
            vmi_order(&model, std::slice::from_ref(&node), &mut lists, &opts).expect("vmi");
            lists
        });
    });
    g.bench_function("rerender_every_candidate", |b| {
        b.iter(|| vmi_order_exact(&model, &leaves, node.sphere_center, node.sphere_radius, &opts).expect("exact"));
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);

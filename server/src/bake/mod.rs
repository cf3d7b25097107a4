//! The bake: tree model in, `.ctree` out. Stages: load (grow or import), hierarchy, leaf order,
//! billboard atlases, crown hulls, billboard clouds, encode.

pub mod atlas;
pub mod cloud;
pub mod hierarchy;
pub mod hull;
pub mod order;
pub mod surface;
pub mod views;
pub mod vmi;

use std::path::Path;
use std::time::Instant;

use canopy_shared::format::leaf::DEFAULT_BAND_EDGES;
use canopy_shared::format::{BakedTree, LeafOrder, SectionBody};
use canopy_shared::model::TreeModel;

pub use hierarchy::{Hierarchy, TARGET_LEAVES_PER_NODE};

/// Options of a bake.
#[derive(Debug, Clone)]
pub struct BakeOptions {
    /// Leaf order inside nodes.
    pub order: LeafOrder,
    /// Seed of the random order.
    pub seed: u64,
    /// Mean leaf-node size the hierarchy aims for.
    pub target_leaves_per_node: usize,
    /// Rate band edges.
    pub band_edges: Vec<u16>,
    /// VMI parameters (used when `order` is VMI).
    pub vmi: vmi::VmiOptions,
    /// Billboard atlases; `None` skips them.
    pub atlas: Option<atlas::AtlasOptions>,
    /// Crown hulls; `None` skips them.
    pub hull: Option<hull::HullOptions>,
    /// Billboard clouds; `None` skips them.
    pub cloud: Option<cloud::CloudOptions>,
}

impl Default for BakeOptions {
    fn default() -> Self {
        Self {
            order: LeafOrder::Vmi,
            seed: 1,
            target_leaves_per_node: TARGET_LEAVES_PER_NODE,
            band_edges: DEFAULT_BAND_EDGES.to_vec(),
            vmi: vmi::VmiOptions::default(),
            atlas: Some(atlas::AtlasOptions::default()),
            hull: Some(hull::HullOptions::default()),
            cloud: Some(cloud::CloudOptions::default()),
        }
    }
}

/// Why a bake failed.
#[derive(Debug, thiserror::Error)]
pub enum BakeError {
    /// The input's extension is neither `.toml` nor `.glb`/`.gltf`.
    #[error("cannot bake {0}: expected a species spec (.toml) or a glTF file (.glb, .gltf)")]
    UnknownInput(String),
    /// The species spec is invalid.
    #[error(transparent)]
    Species(#[from] crate::species::SpeciesError),
    /// The L-system failed (for example a cap was hit).
    #[error(transparent)]
    LSystem(#[from] crate::lsystem::LSystemError),
    /// The glTF import failed.
    #[error(transparent)]
    Import(#[from] crate::import_gltf::ImportError),
    /// The leaf order could not be built.
    #[error(transparent)]
    Order(#[from] order::OrderError),
    /// The billboard atlases failed.
    #[error(transparent)]
    Atlas(#[from] atlas::AtlasError),
    /// The crown hulls failed.
    #[error(transparent)]
    Hull(#[from] hull::HullError),
    /// The billboard clouds failed.
    #[error(transparent)]
    Cloud(#[from] cloud::CloudBakeError),
    /// Rendering for the VMI order or a billboard failed.
    #[error(transparent)]
    Raster(#[from] canopy_shared::raster::RasterError),
    /// The model could not be encoded.
    #[error(transparent)]
    Format(#[from] canopy_shared::format::FormatError),
}

/// What kind of input a path names.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum InputKind {
    /// A species spec (`.toml`).
    Species,
    /// A glTF file (`.glb` or `.gltf`).
    Gltf,
}

/// Classifies an input path by extension.
pub fn input_kind(path: &Path) -> Result<InputKind, BakeError> {
    match path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
        .as_deref()
    {
        Some("toml") => Ok(InputKind::Species),
        Some("glb" | "gltf") => Ok(InputKind::Gltf),
        _ => Err(BakeError::UnknownInput(path.display().to_string())),
    }
}

/// What a bake produced besides the file: the hierarchy, stage reports and stage times.
#[derive(Debug, Clone)]
pub struct BakeReport {
    /// The node hierarchy (leaf lists in the written order).
    pub hierarchy: Hierarchy,
    /// Atlas figures, if baked.
    pub atlas: Option<atlas::AtlasReport>,
    /// Hull figures, if baked.
    pub hull: Option<hull::HullReport>,
    /// Billboard-cloud figures, if baked.
    pub cloud: Option<cloud::CloudReport>,
    /// Seconds per stage: hierarchy, leaf order, atlases, hulls, clouds.
    pub seconds: StageSeconds,
}

/// Wall-clock seconds of each bake stage.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct StageSeconds {
    /// Node hierarchy.
    pub hierarchy: f64,
    /// Leaf order (VMI or a baseline).
    pub order: f64,
    /// Billboard atlases.
    pub atlases: f64,
    /// Crown hulls.
    pub hulls: f64,
    /// Billboard clouds.
    pub clouds: f64,
}

/// Turns a model into what the encoder writes: builds the hierarchy, orders the leaves, bakes the
/// billboard atlases, the crown hulls and the billboard clouds.
pub fn bake_model(model: &TreeModel, opts: &BakeOptions) -> Result<(BakedTree, BakeReport), BakeError> {
    let mut seconds = StageSeconds::default();
    let t = Instant::now();
    let mut h = hierarchy::build(model, opts.target_leaves_per_node);
    seconds.hierarchy = t.elapsed().as_secs_f64();
    let t = Instant::now();
    if opts.order == LeafOrder::Vmi {
        vmi::vmi_order(model, &h.nodes, &mut h.node_leaves, &opts.vmi)?;
    } else {
        order::order_leaves(model, &mut h.node_leaves, opts.order, opts.seed)?;
    }
    seconds.order = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let (atlases, atlas_report) = match &opts.atlas {
        Some(o) => {
            let (body, r) = atlas::bake_atlases(model, o)?;
            (body, Some(r))
        }
        None => (SectionBody::default(), None),
    };
    seconds.atlases = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let (hulls, hull_report) = match &opts.hull {
        Some(o) => {
            let (body, r) = hull::bake_hulls(model, o)?;
            (body, Some(r))
        }
        None => (SectionBody::default(), None),
    };
    seconds.hulls = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let (clouds, cloud_report) = match &opts.cloud {
        Some(o) => {
            let (body, r) = cloud::bake_clouds(model, o)?;
            (body, Some(r))
        }
        None => (SectionBody::default(), None),
    };
    seconds.clouds = t.elapsed().as_secs_f64();
    let node_leaves = h
        .node_leaves
        .iter()
        .map(|v| v.iter().map(|&i| model.leaves[i as usize]).collect())
        .collect();
    let baked = BakedTree {
        name: model.name.clone(),
        source: model.source,
        leaf_order: opts.order,
        iterations: model.iterations,
        band_edges: opts.band_edges.clone(),
        branches: model.branches.clone(),
        materials: model.materials.clone(),
        bark_mesh: model.bark_mesh.clone(),
        nodes: h.nodes.clone(),
        node_leaves,
        hulls,
        atlases,
        clouds,
    };
    Ok((
        baked,
        BakeReport {
            hierarchy: h,
            atlas: atlas_report,
            hull: hull_report,
            cloud: cloud_report,
            seconds,
        },
    ))
}

//! The unique forest: a second built-in scene, `unique`, in which every tree is its own model.
//!
//! The models are variants of the species specs ([`SpeciesSpec::variant`]: each its own seed and
//! parameters drawn from the species' `[variation]` ranges: age, shoot lengths, vigour, leaf
//! sizes), dealt round-robin over the species, baked in parallel and incrementally
//! ([`bake::bake_variants`]), then placed once each by Poisson-disk sampling over the scene's
//! area (as the demo places its trees), so no two trees share a model.
//!
//! Conventions: positions in metres on the ground plane `[x, z]`, centred on the origin, y up
//! (trees stand on y = 0); rotation about +y in radians; scale 1 (the variation is in the models).

pub mod bake;

use std::path::PathBuf;

use canopy_shared::rng::SplitMix64;

use crate::bake::BakeOptions;
use crate::demo::{DemoConfig, DemoError, DemoModels, create_public_scene, positions};
use crate::http::AppState;
use crate::species::SpeciesSpec;
use crate::store::scenes::{Bounds, NewInstance};

pub use bake::{BakeSummary, UNIQUE_BAKE_VERSION, bake_variants, model_key, stored_name};

/// The unique forest's scene id.
pub const UNIQUE_ID: &str = "unique";

/// Prefix of every unique-forest model name (`unique-<variant>-<key>`); the demo leaves such
/// models alone.
pub const MODEL_PREFIX: &str = "unique-";

/// Whether a stored model name belongs to the unique forest.
pub fn is_unique_model(name: &str) -> bool {
    name.starts_with(MODEL_PREFIX)
}

/// The unique forest's settings.
#[derive(Debug, Clone)]
pub struct UniqueConfig {
    /// Folder of species specs (`*.toml`); each contributes variants.
    pub species_dir: PathBuf,
    /// Species names to use; empty for all.
    pub only: Vec<String>,
    /// Distinct models (variants), dealt round-robin over the species.
    pub models: usize,
    /// Bake threads (at least 1).
    pub workers: usize,
    /// Extent along x, metres.
    pub width_m: f64,
    /// Extent along z, metres.
    pub depth_m: f64,
    /// Placement seed.
    pub seed: u64,
    /// Bake options of every model (part of each model's content key).
    pub bake: BakeOptions,
}

impl Default for UniqueConfig {
    fn default() -> Self {
        Self {
            species_dir: PathBuf::from("assets/species"),
            only: Vec::new(),
            models: 300,
            workers: std::thread::available_parallelism().map_or(1, usize::from),
            width_m: 1000.0,
            depth_m: 1000.0,
            seed: 11,
            bake: bake_options(),
        }
    }
}

/// The unique forest's bake: the default one with 16 VMI views per node ranked alone (no
/// whole-tree context) and no latitude–longitude atlas (the default ladder draws the
/// hemi-octahedral one; the discrete baseline the crossed quads): about half the default's CPU
/// time, which keeps a bake of hundreds of models within minutes on 2 cores.
pub fn bake_options() -> BakeOptions {
    let mut o = BakeOptions::default();
    o.vmi.views = 16;
    o.vmi.context_resolution = 0;
    if let Some(a) = o.atlas.as_mut() {
        a.lat_long = None;
    }
    o
}

/// Why the unique forest could not be made.
#[derive(Debug, thiserror::Error)]
pub enum UniqueError {
    /// A setting out of range.
    #[error("unique forest: {0}")]
    Config(String),
    /// A species spec, its variation, or a variant's growth, bake or storage failed.
    #[error(transparent)]
    Demo(#[from] DemoError),
    /// A variant failed; names it.
    #[error("unique forest: variant {name}: {source}")]
    Variant {
        /// The variant's name.
        name: String,
        /// What failed.
        #[source]
        source: Box<DemoError>,
    },
    /// The bake's thread pool could not start.
    #[error("unique forest: starting {0} bake threads: {1}")]
    Threads(usize, String),
}

/// The variant specs of the forest: variant `k` of species `k mod S` for `k` in `0..models`
/// (species sorted by file name), each validated. Deterministic.
pub fn variants(cfg: &UniqueConfig) -> Result<Vec<SpeciesSpec>, UniqueError> {
    if cfg.models == 0 {
        return Err(UniqueError::Config("needs at least 1 model".into()));
    }
    let specs: Vec<SpeciesSpec> = SpeciesSpec::load_dir(&cfg.species_dir)
        .map_err(DemoError::from)?
        .into_iter()
        .filter(|s| cfg.only.is_empty() || cfg.only.iter().any(|o| o == &s.name))
        .collect();
    if specs.is_empty() {
        return Err(
            DemoError::NoSpecies(format!("{} holds no matching species specs", cfg.species_dir.display())).into(),
        );
    }
    (0..cfg.models)
        .map(|k| {
            let spec = &specs[k % specs.len()];
            spec.variant((k / specs.len()) as u64)
                .map_err(|e| UniqueError::Variant {
                    name: format!("{}-{:03}", spec.name, k / specs.len()),
                    source: Box::new(e.into()),
                })
        })
        .collect()
}

/// The scene's bounds.
pub fn bounds(cfg: &UniqueConfig) -> Bounds {
    Bounds {
        min: [-cfg.width_m / 2.0, -cfg.depth_m / 2.0],
        max: [cfg.width_m / 2.0, cfg.depth_m / 2.0],
    }
}

/// One tree per model: Poisson-disk positions (as the demo's), model `k` at the `k`-th, random
/// rotation, scale 1.
pub fn place(cfg: &UniqueConfig, models: &[String]) -> Result<Vec<NewInstance>, UniqueError> {
    let demo = DemoConfig {
        models: DemoModels::Synthetic(0),
        trees: models.len(),
        width_m: cfg.width_m,
        depth_m: cfg.depth_m,
        seed: cfg.seed,
        photo_views: None,
    };
    let mut rng = SplitMix64::new(cfg.seed);
    let pts = positions(&demo, &mut rng)?;
    let (ox, oz) = (cfg.width_m / 2.0, cfg.depth_m / 2.0);
    Ok(pts
        .iter()
        .zip(models)
        .map(|(p, m)| NewInstance {
            model: m.clone(),
            position: [(p[0] - ox) as f32, 0.0, (p[1] - oz) as f32],
            rotation: rng.uniform(0.0, std::f64::consts::TAU) as f32,
            scale: 1.0,
        })
        .collect())
}

/// What [`ensure_unique`] did.
#[derive(Debug, Clone)]
pub struct UniqueReport {
    /// Whether the scene was created now (false: it existed; nothing was baked).
    pub created: bool,
    /// The bake, when the scene was created now.
    pub bake: Option<BakeSummary>,
}

/// Makes sure the scene `unique` exists: when it does not, bakes the variants not baked yet
/// (`cfg.workers` threads; `progress` gets `("bake unique models", done, total)`) and creates
/// it.
pub fn ensure_unique(
    state: &AppState,
    cfg: &UniqueConfig,
    progress: &(dyn Fn(&str, u64, u64) + Sync),
) -> Result<UniqueReport, UniqueError> {
    if state
        .inner
        .scenes
        .get(UNIQUE_ID)
        .map_err(|e| DemoError::Scene(e.to_string()))?
        .is_some()
    {
        return Ok(UniqueReport {
            created: false,
            bake: None,
        });
    }
    let specs = variants(cfg)?;
    let summary = bake_variants(state, &specs, &cfg.bake, cfg.workers, progress)?;
    let instances = place(cfg, &summary.names)?;
    create_public_scene(state, UNIQUE_ID, "Unique forest", bounds(cfg), &instances)?;
    tracing::info!(
        trees = instances.len(),
        baked = summary.baked,
        reused = summary.reused,
        seconds = summary.seconds,
        "unique forest created"
    );
    Ok(UniqueReport {
        created: true,
        bake: Some(summary),
    })
}

/// Progress callback that ignores everything (tests, quiet runs).
pub fn no_progress(_: &str, _: u64, _: u64) {}

#[cfg(test)]
mod tests;

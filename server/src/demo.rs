//! The built-in demo: on first start with an empty data folder, bake the built-in species and
//! create the public scene `demo`, a forest of Poisson-disk placed trees (several species, varied
//! rotation and scale) over at least a square kilometre on flat ground, and the public scene
//! `hills`: the same models and placement rules over the same bounds (its own seed), standing on a
//! generated DEM-like terrain (`terrain::generate`, 75 m of relief) from its first version on.

use std::path::PathBuf;

use canopy_shared::model::{Branch, Leaf, Materials, ModelSource, SkeletonPoint, TreeModel, TriangleMesh};
use canopy_shared::rng::SplitMix64;
use glam::Vec3;

use crate::bake::{BakeOptions, bake_model};
use crate::http::AppState;
use crate::http::scenes::{ApiError, CreateScene, create_scene_on};
use crate::lsystem::Limits;
use crate::species::{self, SpeciesSpec};
use crate::store::scenes::{Bounds, EditBatch, MAX_BATCH, NewInstance};

/// The demo scene's id.
pub const DEMO_ID: &str = "demo";

/// The hilly demo scene's id.
pub const HILLS_ID: &str = "hills";

/// The hilly demo's seed: its placement's and its terrain's.
pub const HILLS_SEED: u64 = 3;

/// Most terrain samples along a side of the hilly demo: past `1024 × 4 m`, the cell grows.
const HILLS_MAX_SIDE_CELLS: f64 = 1024.0;

/// Where the demo's tree models come from.
#[derive(Debug, Clone)]
pub enum DemoModels {
    /// Grow and bake every species spec (`*.toml`) in a folder whose name passes the filter
    /// (all when the filter is empty).
    Species {
        /// The folder (the repository's `assets/species`).
        dir: PathBuf,
        /// Species names to use; empty for all.
        only: Vec<String>,
    },
    /// `n` small built-in synthetic trees (tests, and a machine without the species folder).
    Synthetic(usize),
}

/// The demo's settings.
#[derive(Debug, Clone)]
pub struct DemoConfig {
    /// Model source.
    pub models: DemoModels,
    /// Trees to place.
    pub trees: usize,
    /// Extent along x, metres.
    pub width_m: f64,
    /// Extent along z, metres.
    pub depth_m: f64,
    /// Placement seed.
    pub seed: u64,
    /// Also bake this many irregular atlas views per model (a generated photographer's set,
    /// seed 001; the ladder rung `views`).
    pub photo_views: Option<usize>,
}

impl Default for DemoConfig {
    fn default() -> Self {
        Self {
            models: DemoModels::Species {
                dir: PathBuf::from("assets/species"),
                only: Vec::new(),
            },
            trees: 2500,
            width_m: 1100.0,
            depth_m: 1000.0,
            seed: 7,
            photo_views: None,
        }
    }
}

/// Why the demo could not be made.
#[derive(Debug, thiserror::Error)]
pub enum DemoError {
    /// No usable species.
    #[error("no species to bake: {0}")]
    NoSpecies(String),
    /// A species failed to load.
    #[error(transparent)]
    Species(#[from] crate::species::SpeciesError),
    /// A species failed to grow.
    #[error(transparent)]
    LSystem(#[from] crate::lsystem::LSystemError),
    /// The bake failed.
    #[error(transparent)]
    Bake(#[from] crate::bake::BakeError),
    /// The encoder failed.
    #[error(transparent)]
    Format(#[from] canopy_shared::format::FormatError),
    /// Writing an asset failed.
    #[error(transparent)]
    Asset(#[from] crate::store::AssetError),
    /// A model's discrete LOD files could not be made.
    #[error("discrete LOD files: {0}")]
    Levels(#[from] crate::discrete_files::LevelError),
    /// Creating the scene failed.
    #[error("creating the demo scene: {0}")]
    Scene(String),
    /// Too many trees for the area and limits.
    #[error("{0}")]
    Config(String),
    /// The hilly demo's terrain could not be made or written.
    #[error("the hills scene's terrain: {0}")]
    Terrain(String),
}

impl From<ApiError> for DemoError {
    fn from(e: ApiError) -> Self {
        Self::Scene(e.message)
    }
}

/// Progress of the demo build: `(stage, done, total)`.
pub type Progress<'a> = &'a mut dyn FnMut(&str, u64, u64);

/// Bridson's Poisson-disk sampling over `[0, w] × [0, d]`: points at least `r` apart, grown from
/// a random seed point until no more fit. O(n).
pub fn poisson_disk(w: f64, d: f64, r: f64, rng: &mut SplitMix64) -> Vec<[f64; 2]> {
    const K: usize = 30;
    let cell = r / std::f64::consts::SQRT_2;
    let (gw, gd) = ((w / cell).ceil() as usize + 1, (d / cell).ceil() as usize + 1);
    let mut grid = vec![u32::MAX; gw * gd];
    let mut pts: Vec<[f64; 2]> = Vec::new();
    let mut active = Vec::new();
    let gi = |p: [f64; 2]| ((p[0] / cell) as usize).min(gw - 1) + ((p[1] / cell) as usize).min(gd - 1) * gw;
    let first = [rng.uniform(0.0, w), rng.uniform(0.0, d)];
    grid[gi(first)] = 0;
    pts.push(first);
    active.push(0usize);
    while !active.is_empty() {
        let k = (rng.next_u64() % active.len() as u64) as usize;
        let p = pts[active[k]];
        let mut placed = false;
        for _ in 0..K {
            let a = rng.uniform(0.0, std::f64::consts::TAU);
            let rad = rng.uniform(r, 2.0 * r);
            let q = [p[0] + rad * a.cos(), p[1] + rad * a.sin()];
            if !(0.0..=w).contains(&q[0]) || !(0.0..=d).contains(&q[1]) {
                continue;
            }
            let (cx, cz) = ((q[0] / cell) as usize, (q[1] / cell) as usize);
            let mut ok = true;
            'near: for z in cz.saturating_sub(2)..=(cz + 2).min(gd - 1) {
                for x in cx.saturating_sub(2)..=(cx + 2).min(gw - 1) {
                    let j = grid[x + z * gw];
                    if j != u32::MAX {
                        let o = pts[j as usize];
                        if (o[0] - q[0]).powi(2) + (o[1] - q[1]).powi(2) < r * r {
                            ok = false;
                            break 'near;
                        }
                    }
                }
            }
            if ok {
                grid[gi(q)] = pts.len() as u32;
                active.push(pts.len());
                pts.push(q);
                placed = true;
                break;
            }
        }
        if !placed {
            active.swap_remove(k);
        }
    }
    pts
}

/// `cfg.trees` Poisson-disk positions over the config's area, in metres from its south-west
/// corner, in random order: the radius shrinks until enough fit, then a random subset is kept
/// (which stays Poisson-disk). Draws from `rng`.
pub fn positions(cfg: &DemoConfig, rng: &mut SplitMix64) -> Result<Vec<[f64; 2]>, DemoError> {
    let area = cfg.width_m * cfg.depth_m;
    let mut r = (area / (cfg.trees.max(1) as f64 * 1.4)).sqrt();
    let mut pts = Vec::new();
    for _ in 0..40 {
        pts = poisson_disk(cfg.width_m, cfg.depth_m, r, rng);
        if pts.len() >= cfg.trees {
            break;
        }
        r *= 0.9;
    }
    if pts.len() < cfg.trees {
        return Err(DemoError::Config(format!(
            "cannot fit {} trees in {} m²",
            cfg.trees, area
        )));
    }
    // Partial Fisher-Yates: a uniform random subset.
    for i in 0..cfg.trees {
        let j = i + (rng.next_u64() % (pts.len() - i) as u64) as usize;
        pts.swap(i, j);
    }
    pts.truncate(cfg.trees);
    Ok(pts)
}

/// Places `cfg.trees` instances of `models`, centred on the origin: [`positions`], random
/// species, rotation and scale in [0.7, 1.3].
pub fn place(cfg: &DemoConfig, models: &[String]) -> Result<Vec<NewInstance>, DemoError> {
    if models.is_empty() {
        return Err(DemoError::NoSpecies("no models to place".into()));
    }
    let mut rng = SplitMix64::new(cfg.seed);
    let pts = positions(cfg, &mut rng)?;
    let (ox, oz) = (cfg.width_m / 2.0, cfg.depth_m / 2.0);
    Ok(pts
        .iter()
        .map(|p| NewInstance {
            model: models[(rng.next_u64() % models.len() as u64) as usize].clone(),
            position: [(p[0] - ox) as f32, 0.0, (p[1] - oz) as f32],
            rotation: rng.uniform(0.0, std::f64::consts::TAU) as f32,
            scale: rng.uniform(0.7, 1.3) as f32,
        })
        .collect())
}

/// The demo scene's bounds for a config.
pub fn bounds(cfg: &DemoConfig) -> Bounds {
    Bounds {
        min: [-cfg.width_m / 2.0, -cfg.depth_m / 2.0],
        max: [cfg.width_m / 2.0, cfg.depth_m / 2.0],
    }
}

/// A small synthetic tree (a trunk, `6 + seed % 4` side branches, leaves along them): enough
/// structure for the bake, cheap to make. Name `synthetic-<seed>`.
pub fn synthetic_model(seed: u64) -> TreeModel {
    let mut rng = SplitMix64::new(seed.wrapping_add(0x5EED));
    let height = rng.uniform(6.0, 14.0) as f32;
    let trunk = Branch {
        points: (0..=4)
            .map(|k| SkeletonPoint {
                position: Vec3::new(0.0, height * k as f32 / 4.0, 0.0),
                radius: 0.25 * (1.0 - k as f32 / 5.0),
            })
            .collect(),
        parent: None,
        level: 1,
        iteration: 0,
    };
    let mut branches = vec![trunk];
    let mut leaves = Vec::new();
    let n = 6 + (seed % 4) as usize;
    for b in 0..n {
        let y = height * (0.35 + 0.6 * b as f32 / n as f32);
        let a = rng.uniform(0.0, std::f64::consts::TAU) as f32;
        let dir = Vec3::new(a.cos(), 0.4, a.sin()).normalize();
        let len = height * 0.3 * (1.0 - b as f32 / (n as f32 + 2.0));
        let base = Vec3::new(0.0, y, 0.0);
        let idx = branches.len() as u32;
        branches.push(Branch {
            points: vec![
                SkeletonPoint {
                    position: base,
                    radius: 0.06,
                },
                SkeletonPoint {
                    position: base + dir * len,
                    radius: 0.01,
                },
            ],
            parent: Some(0),
            level: 2,
            iteration: 1,
        });
        for k in 0..24 {
            let t = (k as f32 + 0.5) / 24.0;
            let side = if k % 2 == 0 { 1.0 } else { -1.0 };
            let across = dir.cross(Vec3::Y).normalize_or_zero() * side * 0.15;
            leaves.push(Leaf {
                center: base + dir * (len * t) + across,
                normal: Vec3::Y,
                axis: (dir + across).normalize_or_zero(),
                width: 0.08,
                length: 0.16,
                branch: Some(idx),
                iteration: 1,
                material: 0,
            });
        }
    }
    TreeModel {
        name: format!("synthetic-{seed}"),
        branches,
        leaves,
        bark_mesh: TriangleMesh::default(),
        materials: Materials::default(),
        iterations: 1,
        source: ModelSource::LSystem,
    }
}

/// Bakes a model and stores it as `trees/<name>.<hash16>.ctree`; returns the model name.
pub fn bake_and_store(state: &AppState, model: &TreeModel) -> Result<String, DemoError> {
    bake_and_store_with(state, model, &BakeOptions::default())
}

/// [`bake_and_store`] with these bake options.
pub fn bake_and_store_with(state: &AppState, model: &TreeModel, opts: &BakeOptions) -> Result<String, DemoError> {
    let (baked, _) = bake_model(model, opts)?;
    let bytes = canopy_shared::format::encode_tree(&baked)?;
    let name: String = model
        .name
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '_' {
                c
            } else {
                '-'
            }
        })
        .collect();
    let ctree = state.inner.assets.put("trees", &name, "ctree", &bytes)?;
    crate::discrete_files::store_level_files(&state.inner.assets, &ctree)?;
    state.inner.assets.sync_folder("trees")?;
    Ok(name)
}

fn bake_models(state: &AppState, cfg: &DemoConfig, progress: Progress<'_>) -> Result<Vec<String>, DemoError> {
    let mut opts = BakeOptions::default();
    if let (Some(a), Some(n)) = (opts.atlas.as_mut(), cfg.photo_views) {
        a.views = Some(crate::bake::views::photo_views(n, cfg.seed));
    }
    let opts = &opts;
    match &cfg.models {
        DemoModels::Synthetic(n) => {
            let mut names = Vec::new();
            for k in 0..*n {
                progress("bake synthetic trees", k as u64, *n as u64);
                names.push(bake_and_store_with(state, &synthetic_model(k as u64), opts)?);
            }
            Ok(names)
        }
        DemoModels::Species { dir, only } => {
            let specs: Vec<SpeciesSpec> = SpeciesSpec::load_dir(dir)?
                .into_iter()
                .filter(|s| only.is_empty() || only.iter().any(|o| o == &s.name))
                .collect();
            if specs.is_empty() {
                return Err(DemoError::NoSpecies(format!(
                    "{} holds no matching species specs",
                    dir.display()
                )));
            }
            let total = specs.len() as u64;
            let mut names = Vec::new();
            for (k, spec) in specs.iter().enumerate() {
                progress(&format!("grow and bake {}", spec.name), k as u64, total);
                let model = species::grow_with_progress(spec, spec.iterations, &Limits::default(), &mut |_, _| {})?;
                names.push(bake_and_store_with(state, &model, opts)?);
            }
            Ok(names)
        }
    }
}

/// Makes sure the demo scene exists: when it does not, bakes the models (unless baked models
/// already exist) and creates it. Returns `true` when it was created now.
pub fn ensure_demo(state: &AppState, cfg: &DemoConfig, progress: Progress<'_>) -> Result<bool, DemoError> {
    if exists(state, DEMO_ID)? {
        return Ok(false);
    }
    let models = demo_models(state, cfg, progress)?;
    progress("place trees", 0, 1);
    let instances = place(cfg, &models)?;
    create_public_scene(state, DEMO_ID, "Demo forest", bounds(cfg), &instances)?;
    progress("place trees", 1, 1);
    tracing::info!(trees = instances.len(), models = models.len(), "demo scene created");
    Ok(true)
}

fn exists(state: &AppState, id: &str) -> Result<bool, DemoError> {
    Ok(state
        .inner
        .scenes
        .get(id)
        .map_err(|e| DemoError::Scene(e.to_string()))?
        .is_some())
}

/// The demo's models: the baked ones (but the unique forest's, which are its own), or, with none
/// baked yet, those [`bake_models`] bakes now.
fn demo_models(state: &AppState, cfg: &DemoConfig, progress: Progress<'_>) -> Result<Vec<String>, DemoError> {
    let mut models: Vec<String> = state
        .inner
        .assets
        .models()
        .into_keys()
        .filter(|name| !crate::unique::is_unique_model(name))
        .collect();
    models.sort();
    if models.is_empty() {
        models = bake_models(state, cfg, progress)?;
    }
    Ok(models)
}

/// The hilly demo's terrain over a config's bounds: [`HILLS_SEED`], the demo relief, 4 m cells
/// (larger past 1024 cells a side).
pub fn hills_terrain(cfg: &DemoConfig) -> Result<canopy_shared::terrain::Heightfield, DemoError> {
    use crate::terrain::generate::{DEMO_CELL_M, DEMO_RELIEF_M};
    let b = bounds(cfg);
    let cell = DEMO_CELL_M.max(cfg.width_m.max(cfg.depth_m) / HILLS_MAX_SIDE_CELLS);
    crate::terrain::generate(
        [b.min[0], b.min[1], b.max[0], b.max[1]],
        cell,
        DEMO_RELIEF_M,
        HILLS_SEED,
    )
    .map_err(|e| DemoError::Terrain(e.to_string()))
}

/// Makes sure the hilly demo scene exists ([`HILLS_ID`]: the demo's models and placement rules
/// with [`HILLS_SEED`], on [`hills_terrain`]); returns `true` when it was created now.
pub fn ensure_hills(state: &AppState, cfg: &DemoConfig, progress: Progress<'_>) -> Result<bool, DemoError> {
    if exists(state, HILLS_ID)? {
        return Ok(false);
    }
    let models = demo_models(state, cfg, progress)?;
    progress("hills: terrain and trees", 0, 1);
    let field = hills_terrain(cfg)?;
    let ground = crate::terrain::ground::store(&state.inner.assets, HILLS_ID, field)
        .map_err(|e| DemoError::Terrain(e.to_string()))?;
    let [lo, hi] = ground.height_range();
    let instances = place(
        &DemoConfig {
            seed: HILLS_SEED,
            ..cfg.clone()
        },
        &models,
    )?;
    let ground = std::sync::Arc::new(ground);
    create_public_scene_on(
        state,
        HILLS_ID,
        "Demo forest on hills",
        bounds(cfg),
        &instances,
        Some(&ground),
    )?;
    progress("hills: terrain and trees", 1, 1);
    tracing::info!(trees = instances.len(), relief_m = hi - lo, "hills scene created");
    Ok(true)
}

/// Creates the public scene `id` with `instances` (in batches of at most [`MAX_BATCH`]) and keeps
/// its write token beside the database as `DATA/<id>-write-token`, so the operator may edit it.
pub fn create_public_scene(
    state: &AppState,
    id: &str,
    name: &str,
    bounds: Bounds,
    instances: &[NewInstance],
) -> Result<(), DemoError> {
    create_public_scene_on(state, id, name, bounds, instances, None)
}

/// [`create_public_scene`] standing on `terrain` (its file stored under the scene's folder).
pub fn create_public_scene_on(
    state: &AppState,
    id: &str,
    name: &str,
    bounds: Bounds,
    instances: &[NewInstance],
    terrain: Option<&std::sync::Arc<crate::terrain::Ground>>,
) -> Result<(), DemoError> {
    let first = instances.len().min(MAX_BATCH);
    let req = CreateScene {
        id: Some(id.into()),
        name: name.into(),
        public: true,
        bounds,
        instances: instances[..first].to_vec(),
    };
    let (_, write, _) = create_scene_on(state, &req, terrain)?;
    for chunk in instances[first..].chunks(MAX_BATCH) {
        let batch = EditBatch {
            add: chunk.to_vec(),
            ..EditBatch::default()
        };
        let limits = crate::store::scenes::Limits::unlimited(&state.inner.config.limits);
        crate::http::scenes::apply_edit(state, id, &batch, &limits)?;
    }
    let token_path = state
        .inner
        .assets
        .root()
        .parent()
        .map(|p| p.join(format!("{id}-write-token")));
    if let Some(p) = token_path
        && let Err(e) = std::fs::write(&p, format!("{write}\n"))
    {
        tracing::warn!(error = %e, "could not save the {id} scene's write token");
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn poisson_points_keep_their_distance_and_fill_a_square_km() {
        let cfg = DemoConfig {
            models: DemoModels::Synthetic(3),
            ..DemoConfig::default()
        };
        assert!(cfg.width_m * cfg.depth_m >= 1e6);
        let names: Vec<String> = (0..3).map(|k| format!("m{k}")).collect();
        let inst = place(&cfg, &names).expect("place");
        assert_eq!(inst.len(), cfg.trees);
        assert!(inst.len() >= 2000);
        let b = bounds(&cfg);
        let mut min_d2 = f32::INFINITY;
        // Grid-free O(n²) check on a sample keeps the test fast.
        for (i, a) in inst.iter().enumerate().take(300) {
            assert!(b.contains(a.position[0], a.position[2]));
            for c in &inst[i + 1..] {
                let d2 = (a.position[0] - c.position[0]).powi(2) + (a.position[2] - c.position[2]).powi(2);
                min_d2 = min_d2.min(d2);
            }
        }
        assert!(min_d2.sqrt() > 5.0, "trees {} m apart", min_d2.sqrt());
        for m in &names {
            assert!(inst.iter().any(|i| &i.model == m));
        }
        let scales: Vec<f32> = inst.iter().map(|i| i.scale).collect();
        assert!(scales.iter().all(|s| (0.7..=1.3).contains(s)));
        assert!(scales.iter().any(|&s| s < 0.8) && scales.iter().any(|&s| s > 1.2));
        // The spread covers the area: every quadrant holds trees.
        for (sx, sz) in [(-1.0, -1.0), (1.0, -1.0), (-1.0, 1.0), (1.0, 1.0)] {
            assert!(
                inst.iter()
                    .any(|i| i.position[0] * sx > 100.0 && i.position[2] * sz > 100.0)
            );
        }
    }

    #[test]
    fn synthetic_models_are_valid() {
        for s in 0..3 {
            let m = synthetic_model(s);
            m.check_invariants().expect("invariants");
            assert!(m.leaves.len() >= 100);
        }
    }
}

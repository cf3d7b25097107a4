//! The unique forest's bake: every variant grown and baked once, in parallel on a bounded pool of
//! threads, and kept across starts.
//!
//! Incremental by a content key: [`model_key`] hashes what determines the file (the variant's
//! whole spec, the bake options, [`UNIQUE_BAKE_VERSION`] and the format version), and the stored
//! model's name carries it ([`stored_name`]), so a model whose name is already in the asset store
//! is not baked again, and a change of any input gives a new name (the old file stays until the
//! store's garbage collection). The asset store writes each file atomically, so an interrupted
//! bake leaves only whole models behind.

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

use rayon::prelude::*;

use super::{MODEL_PREFIX, UniqueError};
use crate::bake::{BakeOptions, bake_model};
use crate::demo::DemoError;
use crate::http::AppState;
use crate::lsystem::Limits;
use crate::species::{self, SpeciesSpec};

/// Bumped when the bake changes what it writes for the same inputs, so that every unique model
/// is baked again.
pub const UNIQUE_BAKE_VERSION: u32 = 1;

/// Hex digits of the content key kept in a model's name.
const KEY_HEX: usize = 12;

/// The content key of a variant baked with `opts`: SHA-256 (hex) over the bake version, the
/// `.ctree` format version, the spec (JSON) and the options.
pub fn model_key(spec: &SpeciesSpec, opts: &BakeOptions) -> String {
    let spec_json = serde_json::to_string(spec).unwrap_or_else(|_| format!("{spec:?}"));
    let text = format!(
        "canopy-unique/{UNIQUE_BAKE_VERSION}\nformat {}.{}\n{spec_json}\n{opts:?}",
        canopy_shared::format::VERSION_MAJOR,
        canopy_shared::format::VERSION_MINOR
    );
    crate::store::assets::sha256_hex(text.as_bytes())
}

/// The stored model name of a variant: `unique-<variant name>-<key prefix>`, with characters the
/// asset store does not take in names replaced by `-`.
pub fn stored_name(spec: &SpeciesSpec, key: &str) -> String {
    let clean: String = spec
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
    format!("{MODEL_PREFIX}{clean}-{}", &key[..KEY_HEX.min(key.len())])
}

/// What [`bake_variants`] did.
#[derive(Debug, Clone, PartialEq)]
pub struct BakeSummary {
    /// Stored model names, one per variant, in the variants' order.
    pub names: Vec<String>,
    /// Models baked now.
    pub baked: usize,
    /// Models found already baked (same key).
    pub reused: usize,
    /// Wall time of the whole bake, seconds.
    pub seconds: f64,
    /// Threads used.
    pub workers: usize,
}

/// Bakes every variant whose model is not stored yet with `opts`, on `workers` threads (each bake's own
/// parallel stages share the same pool), and stores it under [`stored_name`]. `progress` is
/// called with `("bake unique models", done, total)` as models finish, from any thread.
pub fn bake_variants(
    state: &AppState,
    specs: &[SpeciesSpec],
    opts: &BakeOptions,
    workers: usize,
    progress: &(dyn Fn(&str, u64, u64) + Sync),
) -> Result<BakeSummary, UniqueError> {
    if workers == 0 {
        return Err(UniqueError::Config("needs at least 1 bake thread".into()));
    }
    let t0 = Instant::now();
    let names: Vec<String> = specs.iter().map(|s| stored_name(s, &model_key(s, opts))).collect();
    let stored = state.inner.assets.models();
    let todo: Vec<usize> = (0..specs.len()).filter(|&k| !stored.contains_key(&names[k])).collect();
    let total = specs.len() as u64;
    let done = AtomicU64::new((specs.len() - todo.len()) as u64);
    progress("bake unique models", done.load(Ordering::Relaxed), total);
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(workers)
        .thread_name(|k| format!("unique-bake-{k}"))
        .build()
        .map_err(|e| UniqueError::Threads(workers, e.to_string()))?;
    pool.install(|| {
        todo.par_iter().try_for_each(|&k| {
            bake_one(state, &specs[k], &names[k], opts).map_err(|e| UniqueError::Variant {
                name: specs[k].name.clone(),
                source: Box::new(e),
            })?;
            let d = done.fetch_add(1, Ordering::Relaxed) + 1;
            progress("bake unique models", d, total);
            Ok::<(), UniqueError>(())
        })
    })?;
    state.inner.assets.sync_folder("trees").map_err(DemoError::from)?;
    Ok(BakeSummary {
        names,
        baked: todo.len(),
        reused: specs.len() - todo.len(),
        seconds: t0.elapsed().as_secs_f64(),
        workers,
    })
}

fn bake_one(state: &AppState, spec: &SpeciesSpec, name: &str, opts: &BakeOptions) -> Result<(), DemoError> {
    let model = species::grow(spec, &Limits::default())?;
    let (baked, _) = bake_model(&model, opts)?;
    let bytes = canopy_shared::format::encode_tree(&baked)?;
    let ctree = state.inner.assets.put_unsynced("trees", name, "ctree", &bytes)?;
    crate::discrete_files::store_level_files(&state.inner.assets, &ctree)?;
    Ok(())
}

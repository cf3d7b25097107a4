//! `serve --unique`: the unique forest's flags, and its bake at start with a progress bar and a
//! report of the time it took.

use std::path::Path;

use anyhow::{Context, Result};
use canopy_server::http::AppState;
use canopy_server::unique::{self, UniqueConfig};
use indicatif::{ProgressBar, ProgressStyle};

/// Flags of the unique forest (scene `unique`).
#[derive(clap::Args, Debug)]
pub struct UniqueArgs {
    /// Also create the scene `unique`: a forest in which every tree is its own model (variants
    /// of the species with their own seeds and parameters), baked once and kept across starts.
    #[arg(long, env = "CANOPY_UNIQUE")]
    unique: bool,
    /// Distinct models (and trees) in the unique forest (at least 1).
    #[arg(long, env = "CANOPY_UNIQUE_MODELS", default_value_t = UniqueConfig::default().models as u64,
          value_parser = clap::value_parser!(u64).range(1..=100_000))]
    unique_models: u64,
    /// Unique-forest extent along x and along z, metres.
    #[arg(long, env = "CANOPY_UNIQUE_SIDE_M", default_value_t = UniqueConfig::default().width_m,
          value_parser = crate::serve_cmd::parse_extent)]
    unique_side_m: f64,
    /// Threads that bake the unique forest's models (default: one per core).
    #[arg(long, env = "CANOPY_BAKE_WORKERS", value_parser = clap::value_parser!(u64).range(1..=256))]
    bake_workers: Option<u64>,
}

/// Creates the unique forest when asked and it does not exist yet, baking what is missing.
pub fn ensure(state: &AppState, args: &UniqueArgs, species: &Path) -> Result<()> {
    if !args.unique {
        return Ok(());
    }
    let cfg = UniqueConfig {
        species_dir: species.to_path_buf(),
        models: args.unique_models as usize,
        width_m: args.unique_side_m,
        depth_m: args.unique_side_m,
        workers: args
            .bake_workers
            .map_or(UniqueConfig::default().workers, |w| w as usize),
        ..UniqueConfig::default()
    };
    let pb = ProgressBar::new(cfg.models as u64);
    pb.set_style(
        ProgressStyle::with_template("{spinner} [{elapsed_precise}] {bar:30} {pos}/{len} {msg} ({eta})")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let report = unique::ensure_unique(state, &cfg, &|stage, done, total| {
        pb.set_length(total);
        pb.set_position(done);
        pb.set_message(stage.to_string());
    })
    .context("creating the unique forest")?;
    pb.finish_and_clear();
    if let Some(b) = &report.bake {
        // Scripts and benchmarks read this line.
        println!(
            "unique forest: {} models ({} baked, {} reused) in {:.1} s on {} threads",
            b.names.len(),
            b.baked,
            b.reused,
            b.seconds,
            b.workers
        );
    }
    Ok(())
}

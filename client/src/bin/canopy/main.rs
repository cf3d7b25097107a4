//! `canopy`: the Canopy client. Streams a scene's trees by byte range with level of detail,
//! headless (`fly`, `load`), or prints what a single tree file needs (`plan`).

mod cli;
mod demo_cmd;
mod eval_cmd;
mod fly_cmd;
mod load_cmd;
mod redundancy_cmd;
mod view_app;
mod view_cmd;

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use canopy_client::net::file::FileSource;
use canopy_client::plan::uniform_range;
use canopy_client::stream::open_tree;
use canopy_shared::format::leaf::keep_count;
use clap::{Parser, Subcommand};
use serde_json::json;

/// Canopy client: streams forests by byte range with level of detail.
#[derive(Parser, Debug)]
#[command(version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Print the byte ranges of a .ctree that a client at a uniform simplification rate fetches.
    Plan {
        /// The .ctree file.
        file: PathBuf,
        /// Simplification rate in [0, 1]: 0 draws every leaf, 0.9 the first 10 % of each node.
        #[arg(long, default_value_t = 0.5)]
        rate: f32,
        /// Print JSON.
        #[arg(long)]
        json: bool,
    },
    /// Fly a camera path through a scene without a window and report, per frame, the bytes and
    /// requests it took, the cache, and what was drawn.
    Fly(fly_cmd::FlyCli),
    /// Load-test a server: many simulated viewers, each with its own camera path and cache.
    Load(load_cmd::LoadArgs),
    /// Chart transfer against visual quality: render what the client draws along a path with the
    /// CPU rasterizer against the full-detail scene, for Canopy and the alternatives.
    Eval(eval_cmd::EvalArgs),
    /// Open the viewer (egui, wgpu) on a scene, or render one view offscreen (`--screenshot`).
    View(Box<view_cmd::ViewCmdArgs>),
    /// Seed 002's visual-redundancy pre-pass: for each flight-height and speed band, how many
    /// levels the low-flight policy may raise before SSIM under one frame's motion drops below
    /// MOS 4's 0.95; writes the flight table and, with `--publish`, stores it with the scene.
    Redundancy(Box<redundancy_cmd::RedundancyArgs>),
    /// The main job on the built-in demo: start the server, fly the flyover headless, chart
    /// transfer against quality, print where the charts are.
    Demo(demo_cmd::DemoArgs),
}

fn main() -> Result<()> {
    match Cli::parse().command {
        Command::Plan { file, rate, json } => plan(&file, rate, json),
        Command::Fly(a) => runtime()?.block_on(fly_cmd::fly_clocked(a)),
        Command::Load(a) => runtime()?.block_on(load_cmd::run(a)),
        Command::Eval(a) => runtime()?.block_on(eval_cmd::run(a)),
        Command::Demo(a) => runtime()?.block_on(demo_cmd::run(a)),
        Command::View(a) => runtime()?.block_on(view_cmd::run(*a)),
        Command::Redundancy(a) => runtime()?.block_on(redundancy_cmd::run(*a)),
    }
}

/// The client's runtime: two workers (the machines it is measured on have two cores).
fn runtime() -> Result<tokio::runtime::Runtime> {
    Ok(tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?)
}

fn plan(file: &Path, rate: f32, json: bool) -> Result<()> {
    let size = std::fs::metadata(file)
        .with_context(|| format!("opening {}", file.display()))?
        .len();
    let (Some(dir), Some(name)) = (file.parent(), file.file_name().and_then(|n| n.to_str())) else {
        bail!("{} is not a file path", file.display());
    };
    let src = FileSource::new(if dir.as_os_str().is_empty() {
        Path::new(".")
    } else {
        dir
    });
    let idx = runtime()?
        .block_on(open_tree(&src, &format!("/{name}"), size))
        .map_err(|e| anyhow::anyhow!("reading {}: {e}", file.display()))?;
    let counts = idx.layout.leaf_counts();
    let drawn: u64 = counts.iter().map(|&n| u64::from(keep_count(n, rate))).sum();
    let range = uniform_range(&idx.layout, idx.leaves_offset, rate);
    let fetched: u64 = range
        .as_ref()
        .map_or(0, |r| r.blocks.iter().map(|b| u64::from(b.count)).sum());
    let bands = range
        .as_ref()
        .and_then(|r| r.blocks.iter().map(|b| b.band).max())
        .map_or(0, |b| b + 1);
    let report = json!({
        "file": file.display().to_string(),
        "rate": rate,
        "index_bytes": idx.bytes_read,
        "bands": bands,
        "leaves_drawn": drawn,
        "leaves_fetched": fetched,
        "leaf_range": range.map(|r| json!({"start": r.start, "end": r.end, "bytes": r.end - r.start})),
        "file_bytes": size,
    });
    if json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        println!("{report:#}");
    }
    Ok(())
}

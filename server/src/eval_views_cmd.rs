//! `canopy-server eval-views`: the command line of [`canopy_server::eval_views`].

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use canopy_server::eval_views::{self, BANDS_DEG, ViewEvalOptions};
use indicatif::{ProgressBar, ProgressStyle};

/// Compare seed 001's billboard lookups at the same frame count on a .ctree: its lat-long grid
/// (four-point nearest), the hemi-octahedral grid, and irregular view sets (an even one and a
/// photographer's set with a gap) looked up by spherical Delaunay triangulation: silhouette
/// IoU of the picked frame against the tree from arbitrary directions, angle to the picked
/// frame, lookup time.
#[derive(Debug, clap::Args)]
pub struct EvalViewsArgs {
    /// The .ctree file (its full model is rendered; the atlas section is not used).
    file: PathBuf,
    /// Frames per set (the lat-long grid is 12 × 4 = 48 whatever this is).
    #[arg(long, default_value_t = 48)]
    frames: usize,
    /// Query directions, uniform over the upper hemisphere.
    #[arg(long, default_value_t = 200)]
    queries: usize,
    /// Image side in pixels.
    #[arg(long, default_value_t = 96)]
    resolution: u32,
    /// Seed of the queries and the photo set.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Print JSON.
    #[arg(long)]
    json: bool,
}

pub fn run(a: &EvalViewsArgs) -> Result<()> {
    if !(3..=16_384).contains(&a.frames) || a.queries == 0 || !(16..=1024).contains(&a.resolution) {
        bail!("--frames must be 3..=16384, --queries at least 1, --resolution 16..=1024");
    }
    let bytes = std::fs::read(&a.file).with_context(|| format!("reading {}", a.file.display()))?;
    let tree =
        canopy_shared::format::DecodedTree::decode(&bytes).with_context(|| format!("decoding {}", a.file.display()))?;
    let opts = ViewEvalOptions {
        frames: a.frames,
        queries: a.queries,
        resolution: a.resolution,
        seed: a.seed,
    };
    let pb = if a.json {
        ProgressBar::hidden()
    } else {
        ProgressBar::new(eval_views::render_count(&opts))
    };
    pb.set_style(
        ProgressStyle::with_template("{spinner} [{elapsed_precise}] {bar:30} {pos}/{len} renders")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let r = eval_views::eval_views(&tree, &opts, &|| pb.inc(1))
        .with_context(|| format!("evaluating the view lookups of {}", a.file.display()))?;
    pb.finish_and_clear();
    if a.json {
        println!("{}", serde_json::to_string_pretty(&r)?);
        return Ok(());
    }
    let bands: Vec<String> = BANDS_DEG
        .iter()
        .zip(&r.queries_by_band)
        .map(|((lo, hi), n)| format!("{lo:.0}–{hi:.0}° ({n})"))
        .collect();
    println!(
        "{}: {} queries at {} px; IoU by elevation band {}",
        r.name,
        r.queries,
        r.resolution,
        bands.join(", ")
    );
    println!(
        "  {:<52} {:>6} {:>8} {:>7} {:>20} {:>9} {:>8} {:>9}",
        "set, lookup", "frames", "IoU", "p10", "IoU by band", "angle°", "max°", "ns/query"
    );
    for row in &r.rows {
        let by: Vec<String> = row.iou_by_band.iter().map(|x| format!("{x:.3}")).collect();
        println!(
            "  {:<52} {:>6} {:>8.3} {:>7.3} {:>20} {:>9.1} {:>8.1} {:>9.0}",
            row.name,
            row.frames,
            row.iou_mean,
            row.iou_p10,
            by.join(" "),
            row.angle_mean_deg,
            row.angle_max_deg,
            row.lookup_ns
        );
    }
    println!(
        "photo set: {:.0} % of the queries outside every Delaunay triangle; seed 001's triangle-vertex rule picks a farther frame than the nearest for {:.1} %",
        100.0 * r.photo_outside_share,
        100.0 * r.photo_rule_miss_share
    );
    Ok(())
}

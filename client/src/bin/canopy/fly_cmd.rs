//! `canopy fly`: the client frame loop along a camera path, without a window.

use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, Result};
use canopy_client::cache::CacheStats;
use canopy_client::net::RangeSource;
use canopy_client::net::file::FileSource;
use canopy_client::net::http::{HttpSource, RangeMode};
use canopy_client::paths::{FRAME_DT, PathKind, camera_at};
use canopy_client::scene::Manifest;
use canopy_client::stream::{FrameReport, Streamer};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use serde_json::json;

use crate::cli::{
    SceneArgs, SceneLocation, ViewArgs, fetch_manifest, http_options, locate, peak_rss_bytes, percentile,
    stream_options,
};

#[derive(Args, Debug)]
pub struct FlyArgs {
    #[command(flatten)]
    pub scene: SceneArgs,
    #[command(flatten)]
    pub view: ViewArgs,
    /// Print one JSON document (summary and per-frame reports) instead of text.
    #[arg(long)]
    pub json: bool,
}

/// One frame of `fly --json`: the streamer's report, and the block cache's own counters for
/// the frame (differences of [`CacheStats`] before and after it).
#[derive(Debug, serde::Serialize)]
struct FlyFrame<'a> {
    #[serde(flatten)]
    report: &'a FrameReport,
    /// Lookups that found their block this frame.
    cache_hits: u64,
    /// Lookups that did not.
    cache_misses: u64,
    /// Blocks evicted this frame to stay within the budget.
    cache_evictions: u64,
    /// Blocks inserted this frame (replacements included).
    cache_insertions: u64,
    /// Inserts refused this frame (a block larger than the whole budget).
    cache_rejections: u64,
}

impl<'a> FlyFrame<'a> {
    fn new(report: &'a FrameReport, before: CacheStats, after: CacheStats) -> Self {
        Self {
            report,
            cache_hits: after.hits - before.hits,
            cache_misses: after.misses - before.misses,
            cache_evictions: after.evictions - before.evictions,
            cache_insertions: after.insertions - before.insertions,
            cache_rejections: after.rejections - before.rejections,
        }
    }
}

/// Per-run totals of a fly-through.
#[derive(Debug, serde::Serialize)]
struct FlySummary {
    scene: String,
    version: u64,
    path: PathKind,
    frames: u32,
    full_detail: bool,
    range_mode: RangeMode,
    bytes: u64,
    requests: u64,
    retries: u64,
    failures: u64,
    corrupt_blocks: u64,
    /// Every model file whole plus the whole pack: what a client without LOD downloads.
    full_download_bytes: u64,
    /// `full_download_bytes / bytes`.
    saving_vs_full_download: f64,
    /// The `--cache-mb` budget, bytes (the cache's own use is `cache_peak_bytes` and, per frame,
    /// `cache_bytes`).
    cache_budget_bytes: u64,
    cache_peak_bytes: u64,
    cache_hit_rate: f64,
    /// Blocks the cache evicted over the run to stay within its budget.
    cache_evictions: u64,
    /// Blocks inserted into the cache over the run (replacements included).
    cache_insertions: u64,
    /// Inserts the cache refused over the run (a block larger than the whole budget).
    cache_rejections: u64,
    peak_rss_bytes: u64,
    mean_triangles: f64,
    mean_full_triangles: f64,
    triangle_share: f64,
    plan_ms_p50: f64,
    plan_ms_p95: f64,
    plan_ms_max: f64,
    seconds: f64,
}

pub async fn fly(a: FlyArgs) -> Result<()> {
    let opts = stream_options(&a.view)?;
    match locate(&a.scene)? {
        SceneLocation::Http {
            api_origin,
            manifest_path,
            assets_origin,
        } => {
            let (manifest, manifest_bytes) = fetch_manifest(&api_origin, &manifest_path, &a.scene).await?;
            let src = Arc::new(HttpSource::new(&assets_origin, http_options(&a.scene))?);
            run_fly(Streamer::with_manifest(src, manifest, opts), &a, manifest_bytes).await
        }
        SceneLocation::Files { root, manifest_path } => {
            let src = Arc::new(FileSource::new(root));
            let bytes = src.get(&manifest_path).await?;
            let manifest = Manifest::parse(&bytes).context("reading the manifest")?;
            run_fly(Streamer::with_manifest(src, manifest, opts), &a, 0).await
        }
    }
}

async fn run_fly<S: RangeSource>(mut s: Streamer<S>, a: &FlyArgs, manifest_bytes: u64) -> Result<()> {
    let m = s.manifest().clone();
    let bounds = m.bounds.as_f32();
    let bar = ProgressBar::new(u64::from(a.view.frames));
    bar.set_style(
        ProgressStyle::with_template("{spinner} fly {pos}/{len} frames [{bar:30}] {msg} ({eta})")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let start = Instant::now();
    let mut frames: Vec<FrameReport> = Vec::with_capacity(a.view.frames as usize);
    let mut total = 0u64;
    let mut cache_peak = 0u64;
    let cs0 = s.cache_stats();
    // The cache's counters after each frame.
    let mut cache_after: Vec<CacheStats> = Vec::with_capacity(a.view.frames as usize);
    for f in 0..a.view.frames {
        let cam = camera_at(a.view.path, bounds, f as f32 * FRAME_DT);
        let r = s.frame(&cam, FRAME_DT).await;
        total += r.bytes;
        cache_peak = cache_peak.max(r.cache_bytes);
        bar.set_message(format!("{:.1} MB", total as f64 / 1e6));
        bar.inc(1);
        frames.push(r);
        cache_after.push(s.cache_stats());
    }
    bar.finish_and_clear();
    let net = s.source().stats().snapshot();
    let cs = s.cache_stats();
    let mut plan: Vec<f64> = frames.iter().map(|f| f.plan_ms).collect();
    plan.sort_by(f64::total_cmp);
    let n = frames.len().max(1) as f64;
    let mean_tris = frames.iter().map(|f| f.triangles as f64).sum::<f64>() / n;
    let mean_full = frames.iter().map(|f| f.full_triangles as f64).sum::<f64>() / n;
    let bytes = net.bytes + manifest_bytes;
    let summary = FlySummary {
        scene: m.scene.clone(),
        version: m.version,
        path: a.view.path,
        frames: a.view.frames,
        full_detail: a.view.full_detail,
        range_mode: a.scene.range_mode,
        bytes,
        requests: net.requests,
        retries: net.retries,
        failures: net.failures,
        corrupt_blocks: s.corrupt_blocks(),
        full_download_bytes: m.full_download_bytes(),
        saving_vs_full_download: m.full_download_bytes() as f64 / bytes.max(1) as f64,
        cache_budget_bytes: a.view.cache_mb << 20,
        cache_peak_bytes: cache_peak,
        cache_hit_rate: cs.hits as f64 / (cs.hits + cs.misses).max(1) as f64,
        cache_evictions: cs.evictions - cs0.evictions,
        cache_insertions: cs.insertions - cs0.insertions,
        cache_rejections: cs.rejections - cs0.rejections,
        peak_rss_bytes: peak_rss_bytes(),
        mean_triangles: mean_tris,
        mean_full_triangles: mean_full,
        triangle_share: if mean_full > 0.0 { mean_tris / mean_full } else { 0.0 },
        plan_ms_p50: percentile(&plan, 0.5),
        plan_ms_p95: percentile(&plan, 0.95),
        plan_ms_max: plan.last().copied().unwrap_or(0.0),
        seconds: start.elapsed().as_secs_f64(),
    };
    if a.json {
        let frames: Vec<FlyFrame<'_>> = frames
            .iter()
            .zip(&cache_after)
            .scan(cs0, |before, (r, &after)| {
                let f = FlyFrame::new(r, *before, after);
                *before = after;
                Some(f)
            })
            .collect();
        println!(
            "{}",
            serde_json::to_string_pretty(&json!({"summary": summary, "frames": frames}))?
        );
    } else {
        println!(
            "{} v{}: {} frames of {:?} in {:.1} s",
            summary.scene, summary.version, summary.frames, summary.path, summary.seconds
        );
        println!(
            "fetched {:.2} MB in {} requests ({} retries, {} failed, {} corrupt blocks dropped)",
            summary.bytes as f64 / 1e6,
            summary.requests,
            summary.retries,
            summary.failures,
            summary.corrupt_blocks
        );
        println!(
            "full download would be {:.2} MB: {:.1}x less transferred",
            summary.full_download_bytes as f64 / 1e6,
            summary.saving_vs_full_download
        );
        println!(
            "drawn triangles: {:.0} per frame, {:.1} % of full detail ({:.0})",
            summary.mean_triangles,
            100.0 * summary.triangle_share,
            summary.mean_full_triangles
        );
        println!(
            "cache peak {:.1} MB of {} MiB, hit rate {:.3}; peak RSS {:.1} MB; plan p50 {:.2} ms, p95 {:.2} ms",
            summary.cache_peak_bytes as f64 / 1e6,
            a.view.cache_mb,
            summary.cache_hit_rate,
            summary.peak_rss_bytes as f64 / 1e6,
            summary.plan_ms_p50,
            summary.plan_ms_p95
        );
    }
    Ok(())
}

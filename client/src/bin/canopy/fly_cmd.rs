//! `canopy fly`: the client frame loop along a camera path, without a window.

use std::future::Future;
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, Result};
use canopy_client::cache::CacheStats;
use canopy_client::net::RangeSource;
use canopy_client::net::file::FileSource;
use canopy_client::net::http::{HttpSource, RangeMode};
use canopy_client::net::link::{LinkCounters, LinkModel, LinkSim, request_wire_bytes, response_wire_bytes};
use canopy_client::net::linked::LinkedSource;
use canopy_client::paths::PathKind;
use canopy_client::scene::Manifest;
use canopy_client::stream::{FrameReport, StreamOptions, Streamer};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use serde_json::json;

use crate::cli::{
    LinkArgs, SceneArgs, SceneLocation, ViewArgs, fetch_manifest, http_options, locate, path_ground, peak_rss_bytes,
    percentile, resolve_flight_table, stream_options,
};

#[derive(Args, Debug)]
pub struct FlyArgs {
    #[command(flatten)]
    pub scene: SceneArgs,
    #[command(flatten)]
    pub view: ViewArgs,
    #[command(flatten)]
    pub link: LinkArgs,
    /// Stop once the stream has settled (30 frames in a row with every visible tree drawn and
    /// nothing in flight or waiting), at most `--frames` frames.
    #[arg(long)]
    pub until_settled: bool,
    /// Print one JSON document (summary and per-frame reports) instead of text.
    #[arg(long)]
    pub json: bool,
}

/// `canopy fly`'s own command line: [`FlyArgs`] (which `canopy demo` builds too) and the
/// clock.
#[derive(Args, Debug)]
pub struct FlyCli {
    #[command(flatten)]
    pub fly: FlyArgs,
    /// Pace frames by the wall clock over the real network instead of a modelled link on the
    /// virtual clock: frame f is drawn `f × --frame-time` seconds after streaming starts, from
    /// whatever has arrived by then, as a window does. The link is whatever lies between client
    /// and server (a shaped one: `tests/tests/client_shaped.rs`); figures then depend on the
    /// network and on how loaded the machine is. Use `--max-in-flight 6` to match the model's
    /// connections.
    #[arg(long, conflicts_with = "link")]
    pub wall_clock: bool,
}

/// Frames in a row with nothing pending that make a stream settled (cesium's definition).
pub const SETTLED_FRAMES: u32 = 30;

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
    /// Wire bytes the link has delivered up to the end of the frame's interval (modelled links
    /// only).
    link_wire_bytes: Option<f64>,
    /// Inserts refused this frame (a block larger than the whole budget).
    cache_rejections: u64,
}

impl<'a> FlyFrame<'a> {
    fn new(report: &'a FrameReport, before: CacheStats, after: CacheStats, link_wire_bytes: Option<f64>) -> Self {
        Self {
            report,
            link_wire_bytes,
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
    /// The link (`--link`) and the clock.
    link: String,
    frame_time_s: f64,
    speed_mps: f32,
    /// Time to fetch the manifest, before streaming starts (modelled on the link, or measured on
    /// the wall clock); the times below include it.
    manifest_s: f64,
    /// Time to the first frame with every visible tree drawn (at least as a stand-in), seconds.
    first_complete_s: Option<f64>,
    /// Time to settled: the first of 30 frames in a row complete with nothing pending.
    settled_s: Option<f64>,
    /// Modelled time to download the manifest, the pack and every model file whole on the
    /// same link (6 connections): the baseline without LOD. `None` on the wall clock.
    whole_download_s: Option<f64>,
    /// The same baseline as a glTF viewer gets it: the manifest, the pack and every model's
    /// finest discrete LOD file (a quantized, meshopt-compressed `.glb`) whole. `None` on the
    /// wall clock, or when the manifest names no level files.
    whole_glb_download_s: Option<f64>,
    /// Body bytes taken in up to the first complete frame.
    bytes_to_first_complete: Option<u64>,
    /// Wire bytes the link delivered (headers included) and its use while work was pending
    /// (modelled links only).
    link_wire_bytes: Option<f64>,
    link_utilisation: Option<f64>,
    /// Frame time (wall) while loading: frames with something pending.
    loading_frame_ms_p50: f64,
    loading_frame_ms_p95: f64,
    /// The clock at the end of the run (virtual, or wall since streaming started).
    end_s: f64,
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
    /// Seed 002's redundancy offsets the run flew with (`--flight-policy` and a scene table or
    /// `--flight-table`), rows by height band, columns by speed band.
    flight_table_offsets: Option<Vec<Vec<u8>>>,
    seconds: f64,
}

/// How a run's frames are paced: the clock the streamer and the transport share.
trait FlyClock {
    /// Moves the clock to `t` seconds after streaming started: the virtual link's clock runs to
    /// `t` (what arrives by then is drawn next), the wall clock is slept to.
    fn advance_to(&self, t: f64) -> impl Future<Output = ()>;
    /// The clock, seconds since streaming started.
    fn now(&self) -> f64;
    /// The modelled link's counters; `None` on the real network.
    fn link(&self) -> Option<LinkCounters>;
}

impl<S: RangeSource> FlyClock for Arc<LinkedSource<S>> {
    fn advance_to(&self, t: f64) -> impl Future<Output = ()> {
        LinkedSource::advance_to(self, t)
    }
    fn now(&self) -> f64 {
        LinkedSource::now(self)
    }
    fn link(&self) -> Option<LinkCounters> {
        Some(self.counters())
    }
}

/// The wall clock from the instant streaming started.
struct WallClock(tokio::time::Instant);

impl FlyClock for WallClock {
    fn advance_to(&self, t: f64) -> impl Future<Output = ()> {
        tokio::time::sleep_until(self.0 + std::time::Duration::from_secs_f64(t.max(0.0)))
    }
    fn now(&self) -> f64 {
        self.0.elapsed().as_secs_f64()
    }
    fn link(&self) -> Option<LinkCounters> {
        None
    }
}

/// `canopy fly` on the virtual clock (what `canopy demo` runs).
pub async fn fly(a: FlyArgs) -> Result<()> {
    fly_clocked(FlyCli {
        fly: a,
        wall_clock: false,
    })
    .await
}

/// `canopy fly` on the clock its command line asks for.
pub async fn fly_clocked(cli: FlyCli) -> Result<()> {
    let a = &cli.fly;
    let mut opts = stream_options(&a.view)?;
    let t0 = Instant::now();
    let loc = locate(&a.scene)?;
    resolve_flight_table(&mut opts, &a.view, &loc, &a.scene).await?;
    let (src, manifest, manifest_bytes) = match loc {
        SceneLocation::Http {
            api_origin,
            manifest_path,
            assets_origin,
        } => {
            let (manifest, manifest_bytes) = fetch_manifest(&api_origin, &manifest_path, &a.scene).await?;
            let src = HttpSource::new(&assets_origin, http_options(&a.scene))?;
            (Source::Http(src), manifest, manifest_bytes)
        }
        SceneLocation::Files { root, manifest_path } => {
            let src = FileSource::new(root);
            let bytes = src.get(&manifest_path).await?;
            let manifest = Manifest::parse(&bytes).context("reading the manifest")?;
            (Source::Files(src), manifest, bytes.len() as u64)
        }
    };
    let manifest_wall_s = t0.elapsed().as_secs_f64();
    let ground = match &src {
        Source::Http(s) => path_ground(s, &manifest).await?,
        Source::Files(s) => path_ground(s, &manifest).await?,
    };
    let run = Run {
        a,
        manifest_bytes,
        ground,
    };
    match (src, cli.wall_clock) {
        (Source::Http(src), false) => run_virtual(src, manifest, opts, run).await,
        (Source::Files(src), false) => run_virtual(src, manifest, opts, run).await,
        (Source::Http(src), true) => run_wall(src, manifest, opts, run, manifest_wall_s).await,
        (Source::Files(src), true) => run_wall(src, manifest, opts, run, manifest_wall_s).await,
    }
}

/// What a run flies: its arguments, the manifest's size, the ground under its path.
struct Run<'a> {
    a: &'a FlyArgs,
    manifest_bytes: u64,
    ground: Option<canopy_shared::terrain::Heightfield>,
}

/// Where the scene's bytes come from.
enum Source {
    Http(HttpSource),
    Files(FileSource),
}

/// Modelled time to fetch whole bodies of `sizes` bytes on `link` from a cold start, all asked
/// for at once (at most the link's connections in transfer): when the last one has arrived.
fn download_time(link: &LinkModel, sizes: impl IntoIterator<Item = u64>) -> f64 {
    let mut sim = LinkSim::new(link.clone());
    for (k, b) in sizes.into_iter().enumerate() {
        sim.submit(request_wire_bytes(0), response_wire_bytes(b, 1), k as u64);
    }
    sim.advance(1e7).last().map_or(0.0, |d| d.1)
}

/// The run on the modelled link's virtual clock.
async fn run_virtual<S: RangeSource>(inner: S, manifest: Manifest, opts: StreamOptions, run: Run<'_>) -> Result<()> {
    let (a, manifest_bytes) = (run.a, run.manifest_bytes);
    let link = &a.link.link;
    let src = Arc::new(LinkedSource::new(inner, link.clone()));
    let s = Streamer::with_manifest(Arc::clone(&src), manifest, opts);
    let m = s.manifest();
    let manifest_s = download_time(link, [manifest_bytes]);
    // The baseline without LOD: the manifest, then the pack and every model file whole, largest
    // first (a glTF viewer's downloads; what it draws first is the first whole file).
    let mut files: Vec<u64> = m.models.iter().map(|x| x.size).chain([m.pack.size]).collect();
    files.sort_unstable_by(|a, b| b.cmp(a));
    let whole_download_s = manifest_s + download_time(link, files);
    let glb: Option<Vec<u64>> = m
        .models
        .iter()
        .map(|x| x.levels.first().map(|l| l.size))
        .chain([Some(m.pack.size)])
        .collect();
    let whole_glb_download_s = glb.map(|mut g| {
        g.sort_unstable_by(|a, b| b.cmp(a));
        manifest_s + download_time(link, g)
    });
    let timing = Timing {
        label: link.to_string(),
        manifest_s,
        whole_download_s: Some(whole_download_s),
        whole_glb_download_s,
    };
    run_fly(s, &src, timing, run).await
}

/// The run on the wall clock over the real network.
async fn run_wall<S: RangeSource>(
    src: S,
    manifest: Manifest,
    opts: StreamOptions,
    run: Run<'_>,
    manifest_s: f64,
) -> Result<()> {
    let s = Streamer::with_manifest(Arc::new(src), manifest, opts);
    let clock = WallClock(tokio::time::Instant::now());
    let timing = Timing {
        label: "wall clock (the real network)".to_string(),
        manifest_s,
        whole_download_s: None,
        whole_glb_download_s: None,
    };
    run_fly(s, &clock, timing, run).await
}

/// What a run knows of its clock before it starts.
struct Timing {
    /// The link, or the wall clock.
    label: String,
    /// Time to fetch the manifest, seconds.
    manifest_s: f64,
    /// The whole-file baseline, seconds (modelled links only).
    whole_download_s: Option<f64>,
    /// The same with every model's level-0 `.glb` in place of its `.ctree`.
    whole_glb_download_s: Option<f64>,
}

async fn run_fly<R: RangeSource>(
    mut s: Streamer<R>,
    clock: &impl FlyClock,
    timing: Timing,
    run: Run<'_>,
) -> Result<()> {
    let (a, manifest_bytes, ground) = (run.a, run.manifest_bytes, run.ground);
    let m = s.manifest().clone();
    let bounds = m.bounds.as_f32();
    let dt = a.view.frame_time;
    let manifest_s = timing.manifest_s;
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
    // The cache's counters and the link's delivered bytes after each frame.
    let mut cache_after: Vec<CacheStats> = Vec::with_capacity(a.view.frames as usize);
    let mut wire_after: Vec<Option<f64>> = Vec::with_capacity(a.view.frames as usize);
    let (mut first_complete, mut settled, mut bytes_to_first) = (None, None, None);
    let (mut run, mut run_start, mut arrived) = (0u32, 0.0, 0u64);
    for f in 0..a.view.frames {
        let cam = a.view.camera(bounds, f, ground.as_ref());
        // The clock moves to the next frame's time: what arrives by then is drawn next. The
        // report is charged for the requests and bytes of both (as `Streamer::frame_until`).
        let net0 = s.source().stats().snapshot();
        let mut r = s.frame(&cam, dt as f32);
        clock.advance_to(f64::from(f + 1) * dt).await;
        let net1 = s.source().stats().snapshot();
        r.bytes = net1.bytes - net0.bytes;
        r.requests = net1.requests - net0.requests;
        r.retries = net1.retries - net0.retries;
        r.failures = net1.failures - net0.failures;
        total += r.bytes;
        arrived += r.bytes_arrived;
        cache_peak = cache_peak.max(r.cache_bytes);
        if r.complete && first_complete.is_none() {
            first_complete = Some(manifest_s + r.time_s);
            bytes_to_first = Some(arrived + manifest_bytes);
        }
        if r.complete && r.is_idle() {
            if run == 0 {
                run_start = r.time_s;
            }
            run += 1;
            if run >= SETTLED_FRAMES && settled.is_none() {
                settled = Some(manifest_s + run_start);
            }
        } else {
            run = 0;
        }
        bar.set_message(format!("{:.1} MB, t {:.1} s", total as f64 / 1e6, r.time_s));
        bar.inc(1);
        frames.push(r);
        cache_after.push(s.cache_stats());
        wire_after.push(clock.link().map(|c| c.wire_bytes));
        if a.until_settled && settled.is_some() {
            break;
        }
    }
    bar.finish_and_clear();
    let net = s.source().stats().snapshot();
    let cs = s.cache_stats();
    let mut loading_ms: Vec<f64> = frames.iter().filter(|f| !f.is_idle()).map(|f| f.frame_ms).collect();
    loading_ms.sort_by(f64::total_cmp);
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
        frames: frames.len() as u32,
        full_detail: a.view.full_detail,
        range_mode: a.scene.range_mode,
        link: timing.label,
        frame_time_s: dt,
        speed_mps: a.view.speed.unwrap_or_else(|| a.view.path.speed()),
        manifest_s,
        first_complete_s: first_complete,
        settled_s: settled,
        whole_download_s: timing.whole_download_s,
        whole_glb_download_s: timing.whole_glb_download_s,
        bytes_to_first_complete: bytes_to_first,
        link_wire_bytes: clock.link().map(|c| c.wire_bytes),
        link_utilisation: clock.link().map(|c| c.utilisation()),
        loading_frame_ms_p50: percentile(&loading_ms, 0.5),
        loading_frame_ms_p95: percentile(&loading_ms, 0.95),
        end_s: clock.now(),
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
        flight_table_offsets: s
            .options()
            .flight
            .as_ref()
            .and_then(|f| f.redundancy.as_ref())
            .map(|t| t.offsets.clone()),
        seconds: start.elapsed().as_secs_f64(),
    };
    if a.json {
        let frames: Vec<FlyFrame<'_>> = frames
            .iter()
            .zip(cache_after.iter().zip(&wire_after))
            .scan(cs0, |before, (r, (&after, &wire))| {
                let f = FlyFrame::new(r, *before, after, wire);
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
        let secs = |x: Option<f64>| x.map_or_else(|| "not reached".to_string(), |t| format!("{t:.2} s"));
        let modelled = match (summary.whole_download_s, summary.link_utilisation) {
            (Some(whole), Some(used)) => {
                let glb = summary
                    .whole_glb_download_s
                    .map_or(String::new(), |g| format!(" (as meshopt .glb: {g:.1} s)"));
                format!(
                    "; every file whole: {whole:.1} s{glb}; link busy {:.0} % while loading",
                    100.0 * used
                )
            }
            _ => String::new(),
        };
        println!(
            "link {}: first complete frame {}, settled {} (manifest {:.2} s){modelled}",
            summary.link,
            secs(summary.first_complete_s),
            secs(summary.settled_s),
            summary.manifest_s,
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

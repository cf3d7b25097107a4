//! `canopy load`: many simulated viewers against a Canopy server on this machine.
//!
//! Each viewer has its own [`HttpSource`] (own connection pool, own counters) and its own
//! [`Streamer`] (own block cache), flies its own camera path (the four [`PathKind`]s in turn,
//! each viewer starting [`PATH_OFFSET_S`] seconds of path time after the previous one) and runs
//! frames back to back, or at `--fps`, until the duration has elapsed. The manifest is fetched
//! once and cloned into every viewer.
//!
//! The measurement window is exactly `--duration`: at its end a frame still waiting on the
//! network is dropped (its requests in flight are not counted). Requests, bytes, retries and
//! failures come from the viewers' sources; latency percentiles merge every source's
//! [`LatencyHistogram`]. A sampler reads the sources every second for the time series charted
//! under `--out`.
//!
//! Only loopback servers are accepted (127.0.0.0/8, `localhost`, `[::1]`): this is a tool to
//! load one's own server, not someone else's.

use std::fmt::Write as _;
use std::net::IpAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use anyhow::{Context, Result, bail};
use canopy_client::cache::CacheStats;
use canopy_client::lod::LodParams;
use canopy_client::lod::projection::{DEFAULT_LADDER_SPEC, SWITCH_BLEND_BAND};
use canopy_client::net::http::{HttpSource, RangeMode};
use canopy_client::net::{LatencyHistogram, NetCounters, RangeSource};
use canopy_client::paths::{FRAME_DT, PathKind, camera_at};
use canopy_client::scene::Manifest;
use canopy_client::stream::{StreamOptions, Streamer};
use canopy_shared::chart::{LineChart, Series, write_line_chart};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use reqwest::Url;
use serde::Serialize;
use tokio::task::JoinHandle;
use tokio::time::{Instant, MissedTickBehavior};

use crate::cli::{SceneArgs, SceneLocation, ViewArgs, http_options, locate, peak_rss_bytes, stream_options};

/// Most simulated viewers.
pub const MAX_CLIENTS: u32 = 1000;
/// Longest run, seconds.
pub const MAX_DURATION_S: u64 = 600;
/// Highest `--fps`.
pub const MAX_FPS: f64 = 240.0;
/// Path time between the starts of consecutive viewers, seconds.
pub const PATH_OFFSET_S: f64 = 7.3;
/// The camera paths, given to viewers in turn.
const KINDS: [PathKind; 4] = [PathKind::Orbit, PathKind::Flyover, PathKind::Walk, PathKind::Lowflight];
/// Failed-model reasons kept for the report.
const FAILED_MODEL_EXAMPLES: usize = 5;

/// Options of `canopy load`.
///
/// URL must be a scene on an HTTP server of this machine (`http://127.0.0.1:PORT/api/scenes/ID`,
/// `localhost` or `[::1]`); so must `--assets-base`. Other hosts are refused, and so are manifest
/// files (the file backend has no server to load).
#[derive(Args, Debug)]
#[command(after_help = "Only loopback servers are accepted: 127.0.0.0/8, localhost, [::1]. \
    Manifest files (the file backend) are refused: there is no server to load.\n\
    Every viewer uses its own connection pool of up to --max-in-flight connections, so \
    CLIENTS x MAX_IN_FLIGHT sockets may be open at once (mind `ulimit -n`).")]
pub struct LoadArgs {
    #[command(flatten)]
    pub scene: SceneArgs,
    /// Simulated viewers (1 to 1000), each with its own connection pool, cache and camera path
    /// (orbit, flyover, walk, lowflight in turn, each starting 7.3 s of path further along).
    #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u32).range(1..=i64::from(MAX_CLIENTS)))]
    pub clients: u32,
    /// Length of the run, seconds (1 to 600); frames still waiting at the end are dropped.
    #[arg(long, default_value_t = 30, value_parser = clap::value_parser!(u64).range(1..=MAX_DURATION_S))]
    pub duration: u64,
    /// Frames per second of each viewer (0 to 240); 0 runs frames back to back. Paced viewers
    /// move along their path at 1/FPS s per frame, unpaced ones at 1/30 s per frame.
    #[arg(long, default_value_t = 0.0, value_parser = parse_fps)]
    pub fps: f64,
    /// Block cache budget of each viewer, MiB.
    #[arg(long, default_value_t = 64)]
    pub cache_mb: u64,
    /// View distance, metres: farther trees are neither fetched nor drawn.
    #[arg(long, default_value_t = 1500.0)]
    pub view_distance: f32,
    /// Folder for the report: `load.json` and charts of requests/s and MB/s over time
    /// (`requests.png`/`.svg`, `throughput.png`/`.svg`).
    #[arg(long, default_value = "load-report")]
    pub out: PathBuf,
    /// Print the report as one JSON object (the same as `load.json`) instead of text.
    #[arg(long)]
    pub json: bool,
}

fn parse_fps(s: &str) -> Result<f64, String> {
    let v: f64 = s.trim().parse().map_err(|e| format!("{s:?} is not a number: {e}"))?;
    if !(0.0..=MAX_FPS).contains(&v) {
        return Err(format!("{v} is outside 0..={MAX_FPS}"));
    }
    Ok(v)
}

/// Checks the bounds again (clap enforces them on the command line; this guards other callers).
fn check_bounds(a: &LoadArgs) -> Result<()> {
    if !(1..=MAX_CLIENTS).contains(&a.clients) {
        bail!("--clients {} is outside 1..={MAX_CLIENTS}", a.clients);
    }
    if !(1..=MAX_DURATION_S).contains(&a.duration) {
        bail!("--duration {} is outside 1..={MAX_DURATION_S} seconds", a.duration);
    }
    if !(0.0..=MAX_FPS).contains(&a.fps) {
        bail!("--fps {} is outside 0..={MAX_FPS}", a.fps);
    }
    if !(a.view_distance.is_finite() && a.view_distance > 0.0) {
        bail!(
            "--view-distance {} must be a positive number of metres",
            a.view_distance
        );
    }
    Ok(())
}

/// Whether `url`'s host is a loopback address (127.0.0.0/8, `::1`, an IPv4-mapped loopback) or
/// `localhost`. The URL is read with the parser the HTTP client uses, so what is checked is what
/// would be connected to.
pub fn is_loopback_url(url: &str) -> bool {
    let Ok(u) = Url::parse(url) else {
        return false;
    };
    if !matches!(u.scheme(), "http" | "https") {
        return false;
    }
    // The parser normalises IPv4 forms (`127.1`, `0x7f.0.0.1`) and brackets IPv6 literals.
    let Some(host) = u.host_str() else {
        return false;
    };
    if let Ok(ip) = host.trim_start_matches('[').trim_end_matches(']').parse::<IpAddr>() {
        return match ip {
            IpAddr::V4(v4) => v4.is_loopback(),
            IpAddr::V6(v6) => v6.is_loopback() || v6.to_ipv4_mapped().is_some_and(|v4| v4.is_loopback()),
        };
    }
    host.strip_suffix('.').unwrap_or(host).eq_ignore_ascii_case("localhost")
}

/// Where the viewers go: API origin, manifest path, assets origin. Refuses manifest files and
/// any host that is not loopback.
fn resolve(scene: &SceneArgs) -> Result<(String, String, String)> {
    let is_http = |u: &str| u.starts_with("http://") || u.starts_with("https://");
    if !is_http(&scene.url) {
        bail!(
            "canopy load needs a server: {:?} is not an http(s) URL (manifest files are refused; \
             use `canopy fly` for the file backend)",
            scene.url
        );
    }
    let mut given = vec![scene.url.as_str()];
    given.extend(scene.assets_base.as_deref());
    for u in given {
        if !is_loopback_url(u) {
            bail!("canopy load only runs against this machine: {u:?} is not on 127.0.0.0/8, localhost or [::1]");
        }
    }
    match locate(scene)? {
        SceneLocation::Http {
            api_origin,
            manifest_path,
            assets_origin,
        } => {
            // The sources request `origin + path`: check those exact strings too.
            for (origin, path) in [(&api_origin, manifest_path.as_str()), (&assets_origin, "/assets/")] {
                let full = format!("{origin}{path}");
                if !is_loopback_url(&full) {
                    bail!("canopy load only runs against this machine: {full:?} is not on loopback");
                }
            }
            Ok((api_origin, manifest_path, assets_origin))
        }
        SceneLocation::Files { .. } => bail!("canopy load needs a server, not a manifest file"),
    }
}

/// Camera path and starting path time (seconds) of viewer `i`.
pub fn viewer_path(i: u32) -> (PathKind, f64) {
    (KINDS[i as usize % KINDS.len()], f64::from(i) * PATH_OFFSET_S)
}

/// What a viewer task hands back.
#[derive(Debug, Default)]
struct ViewerOutcome {
    frames: u64,
    /// A frame was dropped at the deadline.
    cut_off: bool,
    frame_ms_sum: f64,
    cache: CacheStats,
    corrupt_blocks: u64,
    failed_models: Vec<(String, String)>,
}

/// One running viewer.
struct Viewer {
    source: Arc<HttpSource>,
    task: JoinHandle<ViewerOutcome>,
}

/// Runs frames of `streamer` along `kind` from path time `t0` until `deadline`.
async fn run_viewer(
    mut streamer: Streamer<HttpSource>,
    kind: PathKind,
    t0: f64,
    bounds: [f32; 4],
    fps: f64,
    deadline: Instant,
) -> ViewerOutcome {
    let period = (fps > 0.0).then(|| Duration::from_secs_f64(1.0 / fps));
    let dt = period.map_or(f64::from(FRAME_DT), |p| p.as_secs_f64());
    let mut out = ViewerOutcome::default();
    let mut next = Instant::now();
    while Instant::now() < deadline {
        let cam = camera_at(kind, bounds, (t0 + out.frames as f64 * dt) as f32);
        if let Ok(r) = tokio::time::timeout_at(deadline, streamer.frame(&cam, dt as f32)).await {
            out.frames += 1;
            out.frame_ms_sum += r.frame_ms;
        } else {
            out.cut_off = true;
            break;
        }
        match period {
            Some(p) => {
                next += p;
                let now = Instant::now();
                if next > now {
                    tokio::time::sleep_until(next.min(deadline)).await;
                } else {
                    // Behind schedule: start the next frame now rather than bursting.
                    next = now;
                }
            }
            // A frame served from the cache never waits: let the sampler and the others run.
            None => tokio::task::yield_now().await,
        }
    }
    out.cache = streamer.cache_stats();
    out.corrupt_blocks = streamer.corrupt_blocks();
    out.failed_models = streamer.failed_models();
    out
}

/// One second of the time series.
#[derive(Debug, Clone, Copy, Serialize)]
struct Sample {
    /// Seconds since the start.
    seconds: f64,
    requests_per_s: f64,
    mb_per_s: f64,
}

/// Latency of every request of every viewer, send to last body byte (bucket upper edges, ±9 %).
#[derive(Debug, Serialize)]
struct LatencyReport {
    samples: u64,
    p50_ms: f64,
    p95_ms: f64,
    p99_ms: f64,
    max_ms: f64,
}

/// The report printed and written to `load.json`.
#[derive(Debug, Serialize)]
struct LoadReport {
    url: String,
    scene: String,
    version: u64,
    clients: u32,
    duration_s: u64,
    /// Start to the last viewer stopping.
    elapsed_s: f64,
    /// Frames per second per viewer; 0 = back to back.
    fps: f64,
    cache_mb: u64,
    view_distance: f32,
    range_mode: RangeMode,
    max_in_flight: usize,
    /// Manifest bytes, fetched once before the run (not counted below).
    manifest_bytes: u64,
    requests: u64,
    requests_per_s: f64,
    /// Highest one-second rate of the timeline.
    requests_per_s_peak: f64,
    bytes: u64,
    bytes_per_s: f64,
    /// Highest one-second rate of the timeline, bytes/s.
    bytes_per_s_peak: f64,
    latency: LatencyReport,
    /// `failed_fetches + corrupt_blocks + failed_models + viewers_lost`.
    errors: u64,
    /// Fetches that failed after every retry.
    failed_fetches: u64,
    corrupt_blocks: u64,
    /// Models a viewer could not open (summed over viewers).
    failed_models: u64,
    /// A few `name: reason` of failed models.
    failed_model_examples: Vec<String>,
    /// Viewer tasks that panicked (their cache counters are lost; their network counters are not).
    viewers_lost: u64,
    retries: u64,
    /// Block look-ups that found the block (every block drawn, every frame).
    cache_hits: u64,
    /// Block look-ups that did not.
    cache_misses: u64,
    /// Blocks fetched and offered to the cache (insertions and refusals).
    cache_blocks_fetched: u64,
    /// `hits / (hits + max(misses, blocks fetched))`: the share of block uses served without
    /// the network.
    cache_hit_rate: f64,
    frames: u64,
    frames_per_viewer_mean: f64,
    frames_per_viewer_min: u64,
    frames_per_viewer_max: u64,
    /// Viewers whose last frame was dropped at the deadline.
    frames_cut_off: u64,
    frame_ms_mean: f64,
    /// Most requests in flight at once in any one viewer.
    peak_in_flight_per_viewer: u64,
    peak_rss_bytes: u64,
    timeline: Vec<Sample>,
    /// Chart files written.
    charts: Vec<String>,
}

fn totals(viewers: &[Viewer]) -> NetCounters {
    let mut t = NetCounters::default();
    for v in viewers {
        let s = v.source.stats().snapshot();
        t.requests += s.requests;
        t.bytes += s.bytes;
        t.retries += s.retries;
        t.failures += s.failures;
        t.peak_in_flight = t.peak_in_flight.max(s.peak_in_flight);
    }
    t
}

/// Soft limit on open files of this process, if known.
fn open_files_limit() -> Option<u64> {
    let s = std::fs::read_to_string("/proc/self/limits").ok()?;
    let line = s.lines().find(|l| l.starts_with("Max open files"))?;
    line.split_whitespace().nth(3)?.parse().ok()
}

/// Runs the load test.
pub async fn run(a: LoadArgs) -> Result<()> {
    check_bounds(&a)?;
    let (api_origin, manifest_path, assets_origin) = resolve(&a.scene)?;
    let hopts = http_options(&a.scene);
    let need_fds = u64::from(a.clients) * hopts.max_in_flight as u64 + 64;
    if let Some(limit) = open_files_limit().filter(|&l| l < need_fds) {
        eprintln!(
            "warning: {} clients x {} in flight may need {need_fds} open files; the limit is {limit} (ulimit -n)",
            a.clients, hopts.max_in_flight
        );
    }

    let api = HttpSource::new(&api_origin, hopts.clone())?;
    let manifest_bytes = api
        .get(&manifest_path)
        .await
        .with_context(|| format!("fetching the manifest {api_origin}{manifest_path}"))?;
    let manifest = Manifest::parse(&manifest_bytes).context("reading the manifest")?;
    let b = manifest.bounds;
    let bounds = [b.min[0], b.min[1], b.max[0], b.max[1]];
    let opts = view_options(&a)?;

    let start = Instant::now();
    let deadline = start + Duration::from_secs(a.duration);
    let mut viewers = Vec::with_capacity(a.clients as usize);
    for i in 0..a.clients {
        let source = Arc::new(HttpSource::new(&assets_origin, hopts.clone())?);
        let streamer = Streamer::with_manifest(Arc::clone(&source), manifest.clone(), opts.clone());
        let (kind, t0) = viewer_path(i);
        let task = tokio::spawn(run_viewer(streamer, kind, t0, bounds, a.fps, deadline));
        viewers.push(Viewer { source, task });
    }

    let bar = ProgressBar::new(a.duration);
    bar.set_style(
        ProgressStyle::with_template("{spinner} load {pos}/{len} s [{bar:30}] {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let timeline = sample(&viewers, start, a.duration, &bar).await;
    bar.finish_and_clear();

    let mut outcomes = Vec::with_capacity(viewers.len());
    let mut lost = 0u64;
    for v in &mut viewers {
        match (&mut v.task).await {
            Ok(o) => outcomes.push(o),
            Err(e) => {
                lost += 1;
                eprintln!("a viewer task failed: {e}");
            }
        }
    }
    let elapsed = start.elapsed().as_secs_f64();
    let net = totals(&viewers);
    let latency = LatencyHistogram::default();
    for v in &viewers {
        latency.merge(&v.source.stats().latency);
    }

    let mut report = summarize(
        &a,
        &manifest,
        manifest_bytes.len() as u64,
        &outcomes,
        lost,
        &net,
        &latency,
    );
    report.elapsed_s = elapsed;
    report.requests_per_s = net.requests as f64 / elapsed.max(1e-9);
    report.bytes_per_s = net.bytes as f64 / elapsed.max(1e-9);
    report.requests_per_s_peak = timeline.iter().map(|s| s.requests_per_s).fold(0.0, f64::max);
    report.bytes_per_s_peak = timeline.iter().map(|s| s.mb_per_s * 1e6).fold(0.0, f64::max);
    report.timeline = timeline;

    let written = write_outputs(&a.out, &mut report);
    if a.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print!("{}", text_report(&report));
    }
    let written = written?;
    for p in &written {
        eprintln!("wrote {}", p.display());
    }
    if lost > 0 {
        bail!("{lost} viewer task(s) failed");
    }
    Ok(())
}

/// Stream options of every viewer (planned on its own task: the viewers already share the
/// cores).
fn view_options(a: &LoadArgs) -> Result<StreamOptions> {
    stream_options(&ViewArgs {
        path: PathKind::Orbit,
        frames: 0,
        width: 1280,
        height: 720,
        fov_deg: 60.0,
        view_distance: a.view_distance,
        cache_mb: a.cache_mb,
        frame_budget_kb: 0,
        full_detail: false,
        ladder: DEFAULT_LADDER_SPEC.into(),
        cloud_blend: SWITCH_BLEND_BAND,
        lod_near: LodParams::default().near,
        lod_far: LodParams::default().far,
        leaf_pixels: None,
        no_leaf_pixels_enlarge: false,
        lod_weights: LodParams::default().weights.to_vec(),
        flight_policy: false,
        no_plan_pool: true,
    })
}

/// Reads the viewers' counters every second until `duration` seconds have passed.
async fn sample(viewers: &[Viewer], start: Instant, duration: u64, bar: &ProgressBar) -> Vec<Sample> {
    let mut tick = tokio::time::interval_at(start + Duration::from_secs(1), Duration::from_secs(1));
    tick.set_missed_tick_behavior(MissedTickBehavior::Delay);
    let mut timeline = Vec::with_capacity(duration as usize);
    let (mut prev_t, mut prev) = (start, NetCounters::default());
    for k in 1..=duration {
        tick.tick().await;
        let now = Instant::now();
        let cur = totals(viewers);
        let dt = (now - prev_t).as_secs_f64().max(1e-3);
        let s = Sample {
            seconds: (now - start).as_secs_f64(),
            requests_per_s: (cur.requests - prev.requests) as f64 / dt,
            mb_per_s: (cur.bytes - prev.bytes) as f64 / dt / 1e6,
        };
        timeline.push(s);
        bar.set_position(k);
        bar.set_message(format!("{:.0} req/s, {:.1} MB/s", s.requests_per_s, s.mb_per_s));
        (prev_t, prev) = (now, cur);
    }
    timeline
}

/// Totals over the viewers (rates and the timeline are filled in by the caller).
fn summarize(
    a: &LoadArgs,
    m: &Manifest,
    manifest_bytes: u64,
    outcomes: &[ViewerOutcome],
    lost: u64,
    net: &NetCounters,
    latency: &LatencyHistogram,
) -> LoadReport {
    let hits: u64 = outcomes.iter().map(|o| o.cache.hits).sum();
    let misses: u64 = outcomes.iter().map(|o| o.cache.misses).sum();
    let fetched: u64 = outcomes.iter().map(|o| o.cache.insertions + o.cache.rejections).sum();
    let frames: u64 = outcomes.iter().map(|o| o.frames).sum();
    let corrupt: u64 = outcomes.iter().map(|o| o.corrupt_blocks).sum();
    let failed_models: u64 = outcomes.iter().map(|o| o.failed_models.len() as u64).sum();
    let mut examples: Vec<String> = outcomes
        .iter()
        .flat_map(|o| o.failed_models.iter().map(|(n, e)| format!("{n}: {e}")))
        .collect();
    examples.sort();
    examples.dedup();
    examples.truncate(FAILED_MODEL_EXAMPLES);
    let frame_ms: f64 = outcomes.iter().map(|o| o.frame_ms_sum).sum();
    LoadReport {
        url: a.scene.url.clone(),
        scene: m.scene.clone(),
        version: m.version,
        clients: a.clients,
        duration_s: a.duration,
        elapsed_s: 0.0,
        fps: a.fps,
        cache_mb: a.cache_mb,
        view_distance: a.view_distance,
        range_mode: a.scene.range_mode,
        max_in_flight: a.scene.max_in_flight.max(1),
        manifest_bytes,
        requests: net.requests,
        requests_per_s: 0.0,
        requests_per_s_peak: 0.0,
        bytes: net.bytes,
        bytes_per_s: 0.0,
        bytes_per_s_peak: 0.0,
        latency: LatencyReport {
            samples: latency.count(),
            p50_ms: latency.quantile_ms(0.5),
            p95_ms: latency.quantile_ms(0.95),
            p99_ms: latency.quantile_ms(0.99),
            max_ms: latency.quantile_ms(1.0),
        },
        errors: net.failures + corrupt + failed_models + lost,
        failed_fetches: net.failures,
        corrupt_blocks: corrupt,
        failed_models,
        failed_model_examples: examples,
        viewers_lost: lost,
        retries: net.retries,
        cache_hits: hits,
        cache_misses: misses,
        cache_blocks_fetched: fetched,
        cache_hit_rate: hit_rate(hits, misses, fetched),
        frames,
        frames_per_viewer_mean: frames as f64 / outcomes.len().max(1) as f64,
        frames_per_viewer_min: outcomes.iter().map(|o| o.frames).min().unwrap_or(0),
        frames_per_viewer_max: outcomes.iter().map(|o| o.frames).max().unwrap_or(0),
        frames_cut_off: outcomes.iter().filter(|o| o.cut_off).count() as u64,
        frame_ms_mean: frame_ms / frames.max(1) as f64,
        peak_in_flight_per_viewer: net.peak_in_flight,
        peak_rss_bytes: peak_rss_bytes(),
        timeline: Vec::new(),
        charts: Vec::new(),
    }
}

/// Share of block uses served from the cache. The streamer plans with `contains`, which counts
/// nothing, so a block that had to be fetched may never show as a miss: the blocks fetched stand
/// in for the misses when they are more.
fn hit_rate(hits: u64, misses: u64, fetched: u64) -> f64 {
    let misses = misses.max(fetched);
    hits as f64 / (hits + misses).max(1) as f64
}

/// Writes the charts and `load.json` under `dir`; records the chart paths in the report.
fn write_outputs(dir: &Path, report: &mut LoadReport) -> Result<Vec<PathBuf>> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let mut written = Vec::new();
    let title_r = format!("{} clients: requests per second", report.clients);
    let title_b = format!("{} clients: throughput", report.clients);
    let charts = [
        (
            "requests",
            title_r.as_str(),
            "requests/s",
            "requests/s",
            report
                .timeline
                .iter()
                .map(|s| (s.seconds, s.requests_per_s))
                .collect::<Vec<_>>(),
        ),
        (
            "throughput",
            title_b.as_str(),
            "MB/s",
            "MB/s",
            report.timeline.iter().map(|s| (s.seconds, s.mb_per_s)).collect(),
        ),
    ];
    for (stem, title, y_label, name, points) in charts {
        let series = [Series {
            name: name.into(),
            points,
        }];
        let files = write_line_chart(
            &dir.join(stem),
            &LineChart {
                title,
                x_label: "seconds",
                y_label,
                series: &series,
                log_x: false,
            },
        )?;
        report.charts.extend(files.iter().map(|p| p.display().to_string()));
        written.extend(files);
    }
    let json = dir.join("load.json");
    let text = serde_json::to_string_pretty(&*report)?;
    std::fs::write(&json, text + "\n").with_context(|| format!("writing {}", json.display()))?;
    written.push(json);
    Ok(written)
}

fn text_report(r: &LoadReport) -> String {
    let mut s = String::new();
    let fps = if r.fps > 0.0 {
        format!("{} fps each", r.fps)
    } else {
        "frames back to back".into()
    };
    let _ = writeln!(
        s,
        "{} v{}: {} clients for {} s ({:.2} s measured), {fps}, cache {} MiB each",
        r.scene, r.version, r.clients, r.duration_s, r.elapsed_s, r.cache_mb
    );
    let _ = writeln!(
        s,
        "requests: {} ({:.1}/s, peak {:.0}/s); bytes: {:.2} MB ({:.2} MB/s, peak {:.2} MB/s)",
        r.requests,
        r.requests_per_s,
        r.requests_per_s_peak,
        r.bytes as f64 / 1e6,
        r.bytes_per_s / 1e6,
        r.bytes_per_s_peak / 1e6
    );
    let l = &r.latency;
    let _ = writeln!(
        s,
        "latency ({} requests): p50 {:.2} ms, p95 {:.2} ms, p99 {:.2} ms, max {:.2} ms",
        l.samples, l.p50_ms, l.p95_ms, l.p99_ms, l.max_ms
    );
    let _ = writeln!(
        s,
        "errors: {} ({} failed fetches, {} corrupt blocks, {} failed models, {} viewers lost); {} retries",
        r.errors, r.failed_fetches, r.corrupt_blocks, r.failed_models, r.viewers_lost, r.retries
    );
    for e in &r.failed_model_examples {
        let _ = writeln!(s, "  failed model {e}");
    }
    let _ = writeln!(
        s,
        "cache hit rate {:.4} ({} block uses from the cache, {} blocks fetched, {} misses counted)",
        r.cache_hit_rate, r.cache_hits, r.cache_blocks_fetched, r.cache_misses
    );
    let _ = writeln!(
        s,
        "frames per viewer: mean {:.1}, min {}, max {} ({:.1} ms mean frame; {} cut off at the end)",
        r.frames_per_viewer_mean, r.frames_per_viewer_min, r.frames_per_viewer_max, r.frame_ms_mean, r.frames_cut_off
    );
    let _ = writeln!(
        s,
        "peak in flight per viewer {}; peak RSS {:.1} MB",
        r.peak_in_flight_per_viewer,
        r.peak_rss_bytes as f64 / 1e6
    );
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser, Debug)]
    struct T {
        #[command(flatten)]
        a: LoadArgs,
    }

    fn parse(extra: &[&str]) -> Result<LoadArgs, clap::Error> {
        let mut v = vec!["t", "http://127.0.0.1:8080/api/scenes/demo"];
        v.extend_from_slice(extra);
        T::try_parse_from(v).map(|t| t.a)
    }

    #[test]
    fn loopback_hosts_only() {
        for u in [
            "http://127.0.0.1:18090/api/scenes/demo",
            "http://127.3.4.5/",
            "http://localhost:8080/api/scenes/demo",
            "http://LOCALHOST./x",
            "http://[::1]:8080/api/scenes/demo",
            "https://127.0.0.1",
            "http://user@127.0.0.1:80/",
        ] {
            assert!(is_loopback_url(u), "{u}");
        }
        for u in [
            "http://10.0.0.1/api/scenes/demo",
            "http://192.168.1.1:8080/",
            "http://example.com/",
            "http://localhost.example.com/",
            "http://127.0.0.1.example.com/",
            "http://127.0.0.1@example.com/",
            "http://example.com#@127.0.0.1/",
            "http://[::2]/",
            "ftp://127.0.0.1/",
            "not a url",
        ] {
            assert!(!is_loopback_url(u), "{u}");
        }
    }

    #[test]
    fn resolve_refuses_remote_hosts_and_files() {
        let scene = |url: &str, assets: Option<&str>| {
            let mut a = parse(&[]).expect("parses").scene;
            a.url = url.into();
            a.assets_base = assets.map(Into::into);
            a
        };
        let (api, path, assets) = resolve(&scene("http://127.0.0.1:18090/api/scenes/demo", None)).expect("loopback");
        assert_eq!(api, "http://127.0.0.1:18090");
        assert_eq!(path, "/api/scenes/demo/manifest");
        assert_eq!(assets, api);
        let (_, _, assets) =
            resolve(&scene("http://localhost:1/api/scenes/demo", Some("http://[::1]:9000"))).expect("loopback CDN");
        assert_eq!(assets, "http://[::1]:9000");
        for (url, assets) in [
            ("http://10.0.0.1/api/scenes/demo", None),
            ("http://127.0.0.1/api/scenes/demo", Some("http://example.com")),
            ("http://example.com#@127.0.0.1/api/scenes/demo", None),
            ("/tmp/data/assets/scenes/demo/v1.json", None),
        ] {
            let e = resolve(&scene(url, assets)).expect_err(url);
            assert!(e.to_string().contains("canopy load"), "{e}");
        }
    }

    #[test]
    fn argument_bounds() {
        let a = parse(&[]).expect("defaults");
        assert_eq!((a.clients, a.duration, a.fps, a.cache_mb), (8, 30, 0.0, 64));
        assert_eq!(a.out, PathBuf::from("load-report"));
        check_bounds(&a).expect("defaults are in bounds");
        for ok in [
            &["--clients", "1"][..],
            &["--clients", "1000"],
            &["--duration", "1"],
            &["--duration", "600"],
            &["--fps", "0"],
            &["--fps", "240"],
        ] {
            let a = parse(ok).unwrap_or_else(|e| panic!("{ok:?}: {e}"));
            check_bounds(&a).expect("in bounds");
        }
        for bad in [
            &["--clients", "0"][..],
            &["--clients", "1001"],
            &["--duration", "0"],
            &["--duration", "601"],
            &["--fps", "-1"],
            &["--fps", "241"],
            &["--fps", "NaN"],
        ] {
            assert!(parse(bad).is_err(), "{bad:?} accepted");
        }
        let mut a = parse(&[]).expect("defaults");
        a.clients = 1001;
        assert!(check_bounds(&a).is_err());
        a.clients = 4;
        a.duration = 0;
        assert!(check_bounds(&a).is_err());
        a.duration = 10;
        a.view_distance = f32::NAN;
        assert!(check_bounds(&a).is_err());
    }

    #[test]
    fn viewers_spread_over_paths_and_time() {
        let kinds: Vec<PathKind> = (0..8).map(|i| viewer_path(i).0).collect();
        assert_eq!(&kinds[..4], &KINDS);
        assert_eq!(&kinds[4..], &KINDS);
        assert_eq!(viewer_path(0).1, 0.0);
        assert!((viewer_path(3).1 - 21.9).abs() < 1e-9);
        assert_eq!(viewer_path(5), viewer_path(5));
    }

    #[test]
    fn text_report_mentions_every_figure() {
        let m = Manifest {
            format: "canopy-scene".into(),
            format_version: 1,
            scene: "demo".into(),
            version: 3,
            bounds: canopy_client::scene::ManifestBounds {
                min: [0.0, 0.0],
                max: [1.0, 1.0],
            },
            instance_count: 0,
            models: vec![],
            pack: canopy_client::scene::ManifestPack {
                url: "/assets/p".into(),
                size: 0,
                tables_len: 0,
            },
            tiles: vec![],
        };
        let a = parse(&["--clients", "2", "--duration", "5"]).expect("args");
        let outcomes = [
            ViewerOutcome {
                frames: 10,
                cache: CacheStats {
                    hits: 3,
                    misses: 1,
                    ..CacheStats::default()
                },
                failed_models: vec![("oak".into(), "bad".into())],
                ..ViewerOutcome::default()
            },
            ViewerOutcome {
                frames: 4,
                cut_off: true,
                ..ViewerOutcome::default()
            },
        ];
        let net = NetCounters {
            requests: 20,
            bytes: 2_000_000,
            retries: 1,
            failures: 2,
            peak_in_flight: 3,
        };
        let h = LatencyHistogram::default();
        h.record(Duration::from_millis(2));
        let r = summarize(&a, &m, 100, &outcomes, 0, &net, &h);
        assert_eq!(r.errors, 3);
        assert_eq!(
            (
                r.frames,
                r.frames_per_viewer_min,
                r.frames_per_viewer_max,
                r.frames_cut_off
            ),
            (14, 4, 10, 1)
        );
        assert!((r.cache_hit_rate - 0.75).abs() < 1e-12);
        assert_eq!(hit_rate(0, 0, 0), 0.0);
        assert!(
            (hit_rate(9, 0, 1) - 0.9).abs() < 1e-12,
            "fetched blocks count as misses"
        );
        assert!((hit_rate(9, 1, 0) - 0.9).abs() < 1e-12);
        assert!(r.latency.p50_ms >= 2.0 && r.latency.p50_ms <= 2.2);
        let t = text_report(&r);
        for want in [
            "2 clients",
            "requests: 20",
            "p99",
            "errors: 3",
            "hit rate 0.7500",
            "failed model oak: bad",
        ] {
            assert!(t.contains(want), "{want:?} missing from\n{t}");
        }
    }
}

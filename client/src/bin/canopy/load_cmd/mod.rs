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
//!
//! Code layout: the arguments, the loopback checks and the run itself are here; the simulated
//! viewers (camera paths, frame loop, the per-second sampler) are in `viewers`; the report
//! (totals, `load.json`, charts, text) is in `report`.

mod report;
mod viewers;

use std::net::IpAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use anyhow::{Context, Result, bail};
use canopy_client::lod::LodParams;
use canopy_client::lod::projection::{DEFAULT_LADDER_SPEC, SWITCH_BLEND_BAND};
use canopy_client::net::http::HttpSource;
use canopy_client::net::{LatencyHistogram, RangeSource};
use canopy_client::paths::PathKind;
use canopy_client::scene::Manifest;
use canopy_client::stream::{StreamOptions, Streamer};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use reqwest::Url;
use tokio::time::Instant;

use crate::cli::{SceneArgs, SceneLocation, ViewArgs, http_options, locate, stream_options};
use report::{summarize, text_report, write_outputs};
use viewers::{Viewer, run_viewer, sample, totals, viewer_path};

/// Most simulated viewers.
pub const MAX_CLIENTS: u32 = 1000;
/// Longest run, seconds.
pub const MAX_DURATION_S: u64 = 600;
/// Highest `--fps`.
pub const MAX_FPS: f64 = 240.0;
/// Path time between the starts of consecutive viewers, seconds.
pub const PATH_OFFSET_S: f64 = 7.3;

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
    let bounds = manifest.bounds.as_f32();
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
        frame_time: f64::from(canopy_client::paths::FRAME_DT),
        speed: None,
        eye_height: None,
        full_detail: false,
        ladder: DEFAULT_LADDER_SPEC.into(),
        cloud_blend: SWITCH_BLEND_BAND,
        lod_near: LodParams::default().near,
        lod_far: LodParams::default().far,
        leaf_pixels: None,
        no_leaf_pixels_enlarge: false,
        lod_weights: LodParams::default().weights.to_vec(),
        no_switch_control: false,
        flight_policy: false,
        flight_table: None,
        no_flight_table: false,
        no_plan_pool: true,
        no_terrain_culling: false,
    })
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

    pub(super) fn parse(extra: &[&str]) -> Result<LoadArgs, clap::Error> {
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
}

//! `canopy redundancy`: seed 002's visual-redundancy pre-pass over a scene
//! ([`canopy_client::eval::redundancy`] says how a cell is scored), written as a flight table
//! and, with `--publish`, stored with the scene on its server.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use canopy_client::eval::redundancy::{blend_views, motion_eyes, search_offsets, viewpoints};
use canopy_client::eval::{BACKGROUND, LeafChoice};
use canopy_client::eval::{EvalScene, RenderMode, View, render_view};
use canopy_client::lod::FlightParams;
use canopy_client::net::RangeSource;
use canopy_client::net::file::FileSource;
use canopy_client::net::http::HttpSource;
use canopy_client::net::link::LinkModel;
use canopy_client::net::linked::LinkedSource;
use canopy_client::scene::Manifest;
use canopy_client::stream::{Camera, DrawnTree, StreamOptions, Streamer};
use canopy_shared::flight_table::{FLIGHT_TABLE_FORMAT, FLIGHT_TABLE_VERSION, FlightTable, FlightTableMethod};
use canopy_shared::metrics::ssim_maps_rgba;
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use serde::Serialize;

use crate::cli::{SceneArgs, SceneLocation, ViewArgs, fetch_manifest, flight_table_path, http_options, locate};
use crate::eval_cmd::load_models;

/// Frames a settled view must hold still (idle, the same draws) before it is scored.
const SETTLE_FRAMES: u32 = 3;
/// Most frames a view is given to settle.
const MAX_SETTLE_FRAMES: u32 = 600;

/// Options of `canopy redundancy`.
#[derive(Args, Debug)]
pub struct RedundancyArgs {
    #[command(flatten)]
    pub scene: SceneArgs,
    /// The viewport, ladder and LOD settings the policy draws with (`--width`, `--height`, `--ladder`
    /// …); the path options are not used.
    #[command(flatten)]
    pub view: ViewArgs,
    /// Highest flight height, metres (seed 002: 1,000).
    #[arg(long, default_value_t = 1000.0)]
    pub h_max: f32,
    /// Height band ΔH, metres (seed 002: 20).
    #[arg(long, default_value_t = 20.0)]
    pub dh: f32,
    /// Highest speed, m/s (seed 002: 80).
    #[arg(long, default_value_t = 80.0)]
    pub v_max: f32,
    /// Speed band Δv, m/s (seed 002: 10).
    #[arg(long, default_value_t = 10.0)]
    pub dv: f32,
    /// SSIM a raised frame must keep against the unraised one under the same motion: 0.95 is
    /// MOS 4 on Zinner et al.'s (2010) SSIM-to-MOS mapping.
    #[arg(long, default_value_t = 0.95)]
    pub threshold: f64,
    /// Frames per second: one frame's motion is v / fps metres.
    #[arg(long, default_value_t = 30.0)]
    pub fps: f32,
    /// Viewpoints per height band (a cell passes only if all do).
    #[arg(long, default_value_t = 2)]
    pub viewpoints: usize,
    /// Where to write the table (JSON).
    #[arg(long, default_value = "flight-table.json")]
    pub out: PathBuf,
    /// Also store the table with the scene on its server (`PUT …/flight-table`), which needs the
    /// scene's write token (`--write-token` or `CANOPY_WRITE_TOKEN`).
    #[arg(long)]
    pub publish: bool,
    /// The scene's write token, for `--publish`.
    #[arg(long, env = "CANOPY_WRITE_TOKEN", hide_env_values = true)]
    pub write_token: Option<String>,
    /// Print the table and the run's figures as JSON.
    #[arg(long)]
    pub json: bool,
}

/// What the run printed with `--json`.
#[derive(Debug, Serialize)]
struct Summary {
    table: FlightTable,
    /// Cells scored.
    cells: usize,
    /// Offsets tried (each a settle per viewpoint and, unless its draws equal the offset
    /// below's, a render).
    offsets_tried: u64,
    /// Renders made (sub-frames included).
    renders: u64,
    /// Lowest SSIM that passed and highest that failed, over the run.
    lowest_pass_ssim: Option<f64>,
    highest_fail_ssim: Option<f64>,
    wall_s: f64,
    out: String,
    published: Option<String>,
}

fn check(a: &RedundancyArgs) -> Result<(usize, usize)> {
    let ok = |x: f32| x.is_finite() && x > 0.0;
    if !(ok(a.h_max) && ok(a.dh) && ok(a.v_max) && ok(a.dv) && ok(a.fps)) {
        bail!("--h-max, --dh, --v-max, --dv and --fps must be finite and positive");
    }
    if !(a.threshold.is_finite() && (0.0..=1.0).contains(&a.threshold)) {
        bail!("--threshold is an SSIM in [0, 1]");
    }
    if !(1..=64).contains(&a.viewpoints) {
        bail!("--viewpoints must be 1..=64");
    }
    let rows = (a.h_max / a.dh).ceil() as usize;
    let cols = (a.v_max / a.dv).ceil() as usize;
    let max = canopy_shared::flight_table::MAX_BANDS;
    if rows > max || cols > max {
        bail!("{rows} height bands × {cols} speed bands: at most {max} a side");
    }
    if a.publish && a.write_token.is_none() {
        bail!("--publish needs the scene's write token (--write-token or CANOPY_WRITE_TOKEN)");
    }
    Ok((rows, cols))
}

pub async fn run(a: RedundancyArgs) -> Result<()> {
    let (rows, cols) = check(&a)?;
    let opts = crate::cli::stream_options(&a.view)?;
    let loc = locate(&a.scene)?;
    if a.publish
        && !matches!(&loc, SceneLocation::Http { manifest_path, .. } if flight_table_path(manifest_path).is_some())
    {
        bail!("--publish needs the scene's API URL (http://HOST/api/scenes/ID)");
    }
    let table = match &loc {
        SceneLocation::Http {
            api_origin,
            manifest_path,
            assets_origin,
        } => {
            let (m, _) = fetch_manifest(api_origin, manifest_path, &a.scene).await?;
            let mk = || Ok(HttpSource::new(assets_origin, http_options(&a.scene))?);
            prepass(&mk, m, opts, &a, rows, cols).await?
        }
        SceneLocation::Files { root, manifest_path } => {
            let src = FileSource::new(root);
            let m = Manifest::parse(&src.get(manifest_path).await?).context("reading the manifest")?;
            let mk = || Ok(FileSource::new(root));
            prepass(&mk, m, opts, &a, rows, cols).await?
        }
    };
    let mut summary = table;
    let text = summary.table.to_json()?;
    std::fs::write(&a.out, &text).with_context(|| format!("writing {}", a.out.display()))?;
    if a.publish
        && let SceneLocation::Http {
            api_origin,
            manifest_path,
            ..
        } = &loc
        && let Some(path) = flight_table_path(manifest_path)
    {
        let url = format!("{api_origin}{path}");
        publish(&url, a.write_token.as_deref().unwrap_or_default(), &text).await?;
        summary.published = Some(url);
    }
    summary.out = a.out.display().to_string();
    if a.json {
        println!("{}", serde_json::to_string_pretty(&summary)?);
    } else {
        print_table(&summary);
    }
    Ok(())
}

async fn publish(url: &str, token: &str, text: &str) -> Result<()> {
    let resp = reqwest::Client::new()
        .put(url)
        .bearer_auth(token)
        .header(reqwest::header::CONTENT_TYPE, "application/json")
        .body(text.to_string())
        .send()
        .await
        .with_context(|| format!("storing the table at {url}"))?;
    let status = resp.status();
    if !status.is_success() {
        let body = resp.text().await.unwrap_or_default();
        bail!("storing the table at {url}: HTTP {status}: {}", body.trim());
    }
    Ok(())
}

fn print_table(s: &Summary) {
    let t = &s.table;
    println!(
        "flight table: {} height bands of {} m × {} speed bands of {} m/s, {} viewpoints each, SSIM ≥ {} under one frame's motion at {} fps ({}×{})",
        t.offsets.len(),
        t.dh_m,
        t.offsets.first().map_or(0, Vec::len),
        t.dv_mps,
        t.method.viewpoints,
        t.method.threshold,
        t.method.fps,
        t.method.width,
        t.method.height
    );
    let header: Vec<String> = (0..t.offsets.first().map_or(0, Vec::len))
        .map(|c| format!("{:>4.0}", c as f32 * t.dv_mps))
        .collect();
    println!("  H \\ v m/s {}", header.join(""));
    for (h, row) in t.offsets.iter().enumerate() {
        let cells: Vec<String> = row.iter().map(|o| format!("{o:>4}")).collect();
        println!("  {:>8.0} {}", h as f32 * t.dh_m, cells.join(""));
    }
    println!(
        "{} cells, {} offsets tried, {} renders in {:.1} s; wrote {}{}",
        s.cells,
        s.offsets_tried,
        s.renders,
        s.wall_s,
        s.out,
        s.published
            .as_ref()
            .map_or(String::new(), |u| format!(", stored at {u}"))
    );
}

/// The policy with every cell raised by `k`: a one-cell table.
fn raised(policy: &FlightParams, k: u8, method: &FlightTableMethod) -> FlightParams {
    FlightParams {
        redundancy: Some(FlightTable {
            format: FLIGHT_TABLE_FORMAT.into(),
            format_version: FLIGHT_TABLE_VERSION,
            dh_m: 1.0,
            dv_mps: 1.0,
            offsets: vec![vec![k]],
            policy: policy.policy(),
            method: method.clone(),
        }),
        ..policy.clone()
    }
}

/// Runs `st` at `cam` with speed `speed` until it is idle and draws the same for
/// [`SETTLE_FRAMES`] frames (or [`MAX_SETTLE_FRAMES`] pass); returns what it draws.
async fn settle<S: RangeSource>(
    st: &mut Streamer<LinkedSource<S>>,
    cam: &Camera,
    speed: f32,
    dt: f32,
) -> Vec<DrawnTree> {
    st.set_flight_speed(Some(speed));
    let mut last: Vec<DrawnTree> = Vec::new();
    let mut still = 0;
    for _ in 0..MAX_SETTLE_FRAMES {
        let t_next = st.now() + f64::from(dt);
        let r = st.frame_until(cam, dt, t_next).await;
        if r.is_idle() && st.drawn() == last.as_slice() {
            still += 1;
            if still >= SETTLE_FRAMES {
                break;
            }
        } else {
            still = 0;
            last = st.drawn().to_vec();
        }
    }
    st.drawn().to_vec()
}

/// Counters of the run.
#[derive(Default)]
struct Counts {
    tried: u64,
    renders: u64,
    lowest_pass: Option<f64>,
    highest_fail: Option<f64>,
}

/// Colour SSIM over the pixels either frame draws a tree on (sky and ground would dilute it);
/// 1 where neither draws one.
fn trees_ssim(reference: &View, v: &View) -> Result<f64> {
    let (_, maps) = ssim_maps_rgba(&reference.color, &v.color, v.width, v.height, BACKGROUND)?;
    let mask: Vec<bool> = reference
        .covered
        .iter()
        .zip(&v.covered)
        .map(|(a, b)| *a || *b)
        .collect();
    Ok(maps.masked(&mask).unwrap_or(1.0))
}

/// One frame under motion: the renders of `trees` from each of [`motion_eyes`], blended.
fn blurred(
    scene: &mut EvalScene,
    trees: &[DrawnTree],
    cam: &Camera,
    speed: f32,
    fps: f32,
    opts: &StreamOptions,
    counts: &mut Counts,
) -> Result<View> {
    let vp = &opts.viewport;
    let mode = RenderMode::AsDrawn {
        choice: LeafChoice::Prefix,
        enlarge: false,
    };
    let mut views = Vec::new();
    for eye in motion_eyes(cam, speed, fps) {
        let c = Camera { eye, ..*cam };
        views.push(render_view(scene, trees, mode, &c, vp, vp.width, vp.height)?);
        counts.renders += 1;
    }
    blend_views(&views).context("blending the sub-frames")
}

async fn prepass<S: RangeSource>(
    mk: &impl Fn() -> Result<S>,
    m: Manifest,
    opts: StreamOptions,
    a: &RedundancyArgs,
    rows: usize,
    cols: usize,
) -> Result<Summary> {
    let t0 = Instant::now();
    let policy = opts.flight.clone().unwrap_or_else(FlightParams::standard);
    let levels = policy.sigma.len().min(usize::from(u8::MAX)) as u8;
    let method = FlightTableMethod {
        metric: "ssim-trees".into(),
        threshold: a.threshold,
        width: opts.viewport.width,
        height: opts.viewport.height,
        fps: a.fps,
        viewpoints: a.viewpoints as u32,
        ladder: a.view.ladder.clone(),
    };
    // One streamer per offset, each on its own instant link, kept across cells (its cache too).
    let mut streamers = Vec::with_capacity(usize::from(levels) + 1);
    for k in 0..=levels {
        let o = StreamOptions {
            flight: Some(raised(&policy, k, &method)),
            ..opts.clone()
        };
        let src = Arc::new(LinkedSource::new(mk()?, LinkModel::loopback()));
        streamers.push(Streamer::with_manifest(src, m.clone(), o));
    }
    let ref_src = mk()?;
    let mut scene = EvalScene::new(m.models.len());
    let bounds = m.bounds.as_f32();
    let dt = 1.0 / a.fps;
    let pb = if a.json {
        ProgressBar::hidden()
    } else {
        ProgressBar::new((rows * cols) as u64)
    };
    pb.set_style(
        ProgressStyle::with_template("{spinner} [{elapsed_precise}] {bar:30} {pos}/{len} cells {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let mut counts = Counts::default();
    // The cell being scored: its viewpoints, their reference frames, and the last offset's
    // draws and verdict (an offset that draws the same as the one below shares its verdict).
    let mut cell: Option<(usize, usize)> = None;
    let mut cams: Vec<Camera> = Vec::new();
    let mut refs: Vec<View> = Vec::new();
    let mut below: (Vec<Vec<DrawnTree>>, bool) = (Vec::new(), true);
    let offsets = search_offsets(rows, cols, levels, async |h, c, k| -> Result<bool> {
        let height = (h as f32 + 0.5) * a.dh;
        let speed = c as f32 * a.dv;
        if cell != Some((h, c)) {
            if cell.is_some() {
                pb.inc(1);
            }
            cell = Some((h, c));
            pb.set_message(format!("H {height:.0} m, v {speed:.0} m/s"));
            cams = viewpoints(bounds, a.viewpoints, height);
            refs.clear();
            let mut lists = Vec::new();
            for cam in &cams {
                let trees = settle(&mut streamers[0], cam, speed, dt).await;
                load_models(&ref_src, &m, &mut scene, &trees).await?;
                refs.push(blurred(&mut scene, &trees, cam, speed, a.fps, &opts, &mut counts)?);
                lists.push(trees);
            }
            below = (lists, true);
        }
        counts.tried += 1;
        let mut lists = Vec::with_capacity(cams.len());
        for cam in &cams {
            lists.push(settle(&mut streamers[usize::from(k)], cam, speed, dt).await);
        }
        if lists == below.0 {
            return Ok(below.1);
        }
        let mut pass = true;
        for ((cam, trees), reference) in cams.iter().zip(&lists).zip(&refs) {
            load_models(&ref_src, &m, &mut scene, trees).await?;
            let v = blurred(&mut scene, trees, cam, speed, a.fps, &opts, &mut counts)?;
            let ssim = trees_ssim(reference, &v)?;
            if ssim >= a.threshold {
                counts.lowest_pass = Some(counts.lowest_pass.map_or(ssim, |x: f64| x.min(ssim)));
            } else {
                counts.highest_fail = Some(counts.highest_fail.map_or(ssim, |x: f64| x.max(ssim)));
                pass = false;
                break;
            }
        }
        below = (lists, pass);
        Ok(pass)
    })
    .await?;
    pb.finish_and_clear();
    let table = FlightTable {
        format: FLIGHT_TABLE_FORMAT.into(),
        format_version: FLIGHT_TABLE_VERSION,
        dh_m: a.dh,
        dv_mps: a.dv,
        offsets,
        policy: policy.policy(),
        method,
    };
    table.check().context("the computed table")?;
    Ok(Summary {
        table,
        cells: rows * cols,
        offsets_tried: counts.tried,
        renders: counts.renders,
        lowest_pass_ssim: counts.lowest_pass,
        highest_fail_ssim: counts.highest_fail,
        wall_s: t0.elapsed().as_secs_f64(),
        out: String::new(),
        published: None,
    })
}

//! `canopy view`: the egui viewer, or one offscreen screenshot (`--screenshot`).

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use canopy_client::eval::{EvalScene, LeafChoice, RenderMode, quality, render_view};
use canopy_client::net::RangeSource;
use canopy_client::net::file::FileSource;
use canopy_client::net::http::HttpSource;
use canopy_client::net::link::LinkModel;
use canopy_client::net::linked::LinkedSource;
use canopy_client::scene::Manifest;
use canopy_client::stream::{Camera, StreamOptions, Streamer};
use canopy_client::view::gpu::{Renderer, Target, headless_device};
use canopy_client::view::upload::{GpuScene, ViewOptions, frame_camera};
use clap::Args;
use glam::Vec3;
use indicatif::{ProgressBar, ProgressStyle};
use serde_json::json;

use crate::cli::{
    SceneArgs, SceneLocation, ViewArgs, fetch_manifest, http_options, locate, resolve_flight_table, stream_options,
};

#[derive(Args, Debug)]
#[allow(clippy::struct_excessive_bools)] // Independent command-line switches.
pub struct ViewCmdArgs {
    #[command(flatten)]
    pub scene: SceneArgs,
    #[command(flatten)]
    pub view: ViewArgs,
    /// Render offscreen (no window) once streaming for the view has settled, write this PNG and
    /// exit.
    #[arg(long)]
    pub screenshot: Option<PathBuf>,
    /// Camera for `--screenshot` (and the window's start): `x,y,z,yaw,pitch`, metres and
    /// degrees (yaw 0 looks along −Z, positive yaw turns towards +X; pitch positive up).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub camera: Option<Vec<f32>>,
    /// With `--screenshot`: stream frames until one fetches nothing (at most `--frames`), then
    /// render. Without it, one frame is streamed.
    #[arg(long)]
    pub wait_idle: bool,
    /// With `--screenshot`: also render the same drawn state with the shared CPU rasterizer to
    /// this PNG (model files fetched whole for it) and report the SSIM between the two.
    #[arg(long)]
    pub reference: Option<PathBuf>,
    /// Seed 004 enlargement of the leaves of simplified nodes.
    #[arg(long)]
    pub enlarge: bool,
    /// Colour trees by representation.
    #[arg(long)]
    pub color_by_lod: bool,
    /// No ground plane.
    #[arg(long)]
    pub no_ground: bool,
    /// Print a JSON report (screenshot and bench modes).
    #[arg(long)]
    pub json: bool,
    /// Window mode: after this many seconds, once streaming has settled (at most 60 s later),
    /// save the window (side panel included) to `--capture` and close (smoke tests under a
    /// virtual display).
    #[arg(long, requires = "capture")]
    pub capture_after: Option<f64>,
    /// Window mode: where `--capture-after` writes the window's pixels (PNG).
    #[arg(long)]
    pub capture: Option<PathBuf>,
    /// Frame-time benchmark, offscreen: fly `--path` for this many frames, streaming, uploading
    /// and rendering each, with LOD and then at full detail, and report GPU frame times.
    #[arg(long)]
    pub bench_frames: Option<u32>,
    /// With `--bench-frames`: the LOD run only, without the full-detail baseline (which takes
    /// most of the time on a CPU rasterizer).
    #[arg(long, requires = "bench_frames")]
    pub bench_lod_only: bool,
}

/// `--camera x,y,z,yaw,pitch` (metres, degrees).
pub fn parse_camera(c: &[f32]) -> Result<Camera> {
    let [x, y, z, yaw, pitch]: [f32; 5] = c
        .try_into()
        .map_err(|_| anyhow::anyhow!("--camera takes 5 numbers x,y,z,yaw,pitch; got {}", c.len()))?;
    if !c.iter().all(|v| v.is_finite()) {
        bail!("--camera values must be finite");
    }
    Ok(Camera {
        eye: Vec3::new(x, y, z),
        yaw: yaw.to_radians(),
        pitch: pitch.clamp(-89.9, 89.9).to_radians(),
    })
}

/// The camera from `--camera`, or a view over the scene's centre from its south edge.
pub fn start_camera(a: &ViewCmdArgs, m: &Manifest) -> Result<Camera> {
    if let Some(c) = &a.camera {
        return parse_camera(c);
    }
    let [min_x, _, max_x, max_z] = m.bounds.as_f32();
    Ok(Camera {
        eye: Vec3::new(0.5 * (min_x + max_x), 30.0, max_z + 20.0),
        yaw: 0.0,
        pitch: -10f32.to_radians(),
    })
}

pub async fn run(a: ViewCmdArgs) -> Result<()> {
    let mut opts = stream_options(&a.view)?;
    // Bad camera values fail before any network traffic.
    if let Some(c) = &a.camera {
        parse_camera(c)?;
    }
    let loc = locate(&a.scene)?;
    resolve_flight_table(&mut opts, &a.view, &loc, &a.scene).await?;
    match loc {
        SceneLocation::Http {
            api_origin,
            manifest_path,
            assets_origin,
        } => {
            let (m, _) = fetch_manifest(&api_origin, &manifest_path, &a.scene).await?;
            let src = Arc::new(HttpSource::new(&assets_origin, http_options(&a.scene))?);
            dispatch(src, m, opts, a, Some(api_origin)).await
        }
        SceneLocation::Files { root, manifest_path } => {
            let src = Arc::new(FileSource::new(&root));
            let m = Manifest::parse(&src.get(&manifest_path).await?).context("reading the manifest")?;
            dispatch(src, m, opts, a, None).await
        }
    }
}

async fn dispatch<S: RangeSource + 'static>(
    src: Arc<S>,
    m: Manifest,
    opts: StreamOptions,
    a: ViewCmdArgs,
    api_origin: Option<String>,
) -> Result<()> {
    if a.screenshot.is_some() {
        screenshot(src, m, opts, &a).await
    } else if let Some(n) = a.bench_frames {
        bench(src, m, opts, &a, n).await
    } else {
        // A played path flies over the ground, as headless runs do.
        let ground = crate::cli::path_ground(src.as_ref(), &m).await?;
        crate::view_app::open(src, m, opts, &a, api_origin, ground)
    }
}

async fn screenshot<S: RangeSource>(src: Arc<S>, m: Manifest, opts: StreamOptions, a: &ViewCmdArgs) -> Result<()> {
    let Some(out) = &a.screenshot else {
        bail!("no --screenshot path")
    };
    let cam = start_camera(a, &m)?;
    let vp = opts.viewport;
    // Headless: on the virtual clock, over no link.
    let link = Arc::new(LinkedSource::new(Arc::clone(&src), LinkModel::loopback()));
    let mut s = Streamer::with_manifest(link, m.clone(), opts);
    let limit = if a.wait_idle { a.view.frames.max(1) } else { 1 };
    let bar = ProgressBar::new(u64::from(limit));
    bar.set_style(
        ProgressStyle::with_template("{spinner} streaming the view {pos}/{len} frames {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let mut frames = 0u32;
    let mut bytes = 0u64;
    let mut settled = false;
    while frames < limit {
        // dt 0: the camera stands still, so switch control does not hold rates back.
        let r = s
            .frame_until(&cam, 0.0, f64::from(frames + 1) * a.view.frame_time)
            .await;
        frames += 1;
        bytes += r.bytes;
        bar.inc(1);
        bar.set_message(format!("{:.1} MB", bytes as f64 / 1e6));
        if r.complete && r.is_idle() && r.bytes == 0 {
            settled = true;
            break;
        }
    }
    bar.finish_and_clear();
    let (device, queue, adapter) = headless_device()?;
    let t0 = Instant::now();
    let mut renderer = Renderer::new(&device, &queue);
    let mut gpu = GpuScene::new(&device, m.models.len());
    let view_opts = ViewOptions {
        enlarge: a.enlarge,
        color_by_lod: a.color_by_lod,
        ground: !a.no_ground,
    };
    let (plan, stats) = gpu.prepare(&device, &queue, &renderer, &s, &cam, &vp, &view_opts);
    let target = Target::new(&device, vp.width, vp.height);
    renderer.render(&device, &queue, &target, &frame_camera(&cam, &vp), &gpu.draws(&plan));
    let rgba = Renderer::read_back(&device, &queue, &target)?;
    let render_ms = t0.elapsed().as_secs_f64() * 1e3;
    let img = image::RgbaImage::from_raw(vp.width, vp.height, rgba).context("read-back size")?;
    img.save(out).with_context(|| format!("writing {}", out.display()))?;
    let mut ssim = None;
    if let Some(ref_path) = &a.reference {
        let mut scene = EvalScene::new(m.models.len());
        crate::eval_cmd::load_models(src.as_ref(), &m, &mut scene, s.drawn()).await?;
        let mode = RenderMode::AsDrawn {
            choice: LeafChoice::Prefix,
            enlarge: a.enlarge,
        };
        let cpu = render_view(&mut scene, s.drawn(), mode, &cam, &vp, vp.width, vp.height)?;
        let cpu_img = image::RgbaImage::from_raw(vp.width, vp.height, cpu.color.iter().flatten().copied().collect())
            .context("reference size")?;
        cpu_img
            .save(ref_path)
            .with_context(|| format!("writing {}", ref_path.display()))?;
        // The GPU image as a View, to compare with the same metric as `eval`.
        let gpu_view = canopy_client::eval::View {
            width: vp.width,
            height: vp.height,
            color: img.pixels().map(|p| p.0).collect(),
            covered: img.pixels().map(|p| p.0[3] > 0).collect(),
            triangles: stats.triangles,
        };
        ssim = Some(quality(&cpu, &gpu_view)?.ssim);
    }
    let report = json!({
        "screenshot": out.display().to_string(),
        "adapter": adapter,
        "camera": {"eye": cam.eye.to_array(), "yaw_deg": cam.yaw.to_degrees(), "pitch_deg": cam.pitch.to_degrees()},
        "width": vp.width,
        "height": vp.height,
        "frames_streamed": frames,
        "settled": settled,
        "bytes": bytes,
        "draw": stats,
        "render_ms": render_ms,
        "reference": a.reference.as_ref().map(|p| p.display().to_string()),
        "ssim_vs_cpu": ssim,
    });
    if a.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        println!(
            "{} ({}x{}, {} frames streamed, {:.2} MB, {}): {} leaves, {} triangles on {adapter}",
            out.display(),
            vp.width,
            vp.height,
            frames,
            bytes as f64 / 1e6,
            if settled { "settled" } else { "not settled" },
            stats.leaves,
            stats.triangles
        );
        if let Some(v) = ssim {
            println!("SSIM against the CPU rasterizer's render of the same state: {v:.4}");
        }
    }
    Ok(())
}

/// Frame times of one bench run.
#[derive(Debug, serde::Serialize)]
struct BenchRun {
    lod: bool,
    frames: u32,
    /// Upload and render, waiting for the GPU, milliseconds (streaming excluded).
    gpu_ms_p50: f64,
    gpu_ms_p95: f64,
    fps_p50: f64,
    mean_leaves: f64,
    mean_triangles: f64,
    mean_instances: f64,
    bytes: u64,
}

async fn bench<S: RangeSource>(src: Arc<S>, m: Manifest, opts: StreamOptions, a: &ViewCmdArgs, n: u32) -> Result<()> {
    let (device, queue, adapter) = headless_device()?;
    let vp = opts.viewport;
    let bounds = m.bounds.as_f32();
    let ground = crate::cli::path_ground(src.as_ref(), &m).await?;
    let view_opts = ViewOptions {
        enlarge: a.enlarge,
        color_by_lod: a.color_by_lod,
        ground: !a.no_ground,
    };
    let mut runs = Vec::new();
    let passes: &[bool] = if a.bench_lod_only { &[true] } else { &[true, false] };
    for &lod in passes {
        let o = StreamOptions {
            lod_enabled: lod,
            ..opts.clone()
        };
        let link = Arc::new(LinkedSource::new(Arc::clone(&src), LinkModel::loopback()));
        let mut s = Streamer::with_manifest(link, m.clone(), o);
        let mut renderer = Renderer::new(&device, &queue);
        let mut gpu = GpuScene::new(&device, m.models.len());
        let target = Target::new(&device, vp.width, vp.height);
        let bar = ProgressBar::new(u64::from(n));
        bar.set_style(
            ProgressStyle::with_template(&format!(
                "{{spinner}} bench ({}) {{pos}}/{{len}} frames [{{bar:30}}] {{msg}}",
                if lod { "LOD" } else { "full detail" }
            ))
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        let mut times = Vec::with_capacity(n as usize);
        let (mut leaves, mut tris, mut inst, mut bytes) = (0u64, 0u64, 0u64, 0u64);
        for f in 0..n {
            let cam = a.view.camera(bounds, f, ground.as_ref());
            let r = s
                .frame_until(&cam, a.view.frame_time as f32, f64::from(f + 1) * a.view.frame_time)
                .await;
            bytes += r.bytes;
            let t0 = Instant::now();
            let (plan, stats) = gpu.prepare(&device, &queue, &renderer, &s, &cam, &vp, &view_opts);
            renderer.render(&device, &queue, &target, &frame_camera(&cam, &vp), &gpu.draws(&plan));
            device
                .poll(wgpu::PollType::wait_indefinitely())
                .map_err(|e| anyhow::anyhow!("GPU wait: {e}"))?;
            times.push(t0.elapsed().as_secs_f64() * 1e3);
            leaves += stats.leaves;
            tris += stats.triangles;
            inst += stats.instances;
            bar.inc(1);
            bar.set_message(format!("{:.1} ms", times.last().copied().unwrap_or(0.0)));
        }
        bar.finish_and_clear();
        times.sort_by(f64::total_cmp);
        let p50 = crate::cli::percentile(&times, 0.5);
        let k = f64::from(n.max(1));
        runs.push(BenchRun {
            lod,
            frames: n,
            gpu_ms_p50: p50,
            gpu_ms_p95: crate::cli::percentile(&times, 0.95),
            fps_p50: if p50 > 0.0 { 1e3 / p50 } else { 0.0 },
            mean_leaves: leaves as f64 / k,
            mean_triangles: tris as f64 / k,
            mean_instances: inst as f64 / k,
            bytes,
        });
    }
    let speedup = runs.get(1).map(|full| full.gpu_ms_p50 / runs[0].gpu_ms_p50.max(1e-9));
    if a.json {
        println!(
            "{}",
            serde_json::to_string_pretty(&json!({
                "adapter": adapter,
                "scene": m.scene,
                "trees": m.instance_count,
                "path": a.view.path,
                "width": vp.width,
                "height": vp.height,
                "runs": runs,
                "full_detail_over_lod_frame_time": speedup,
            }))?
        );
    } else {
        println!(
            "{adapter}, {}x{}, {:?} path, {} frames",
            vp.width, vp.height, a.view.path, n
        );
        for r in &runs {
            println!(
                "{}: frame p50 {:.2} ms ({:.1} fps), p95 {:.2} ms; {:.0} leaves, {:.0} triangles per frame",
                if r.lod { "LOD        " } else { "full detail" },
                r.gpu_ms_p50,
                r.fps_p50,
                r.gpu_ms_p95,
                r.mean_leaves,
                r.mean_triangles
            );
        }
        if let Some(x) = speedup {
            println!("LOD frames are {x:.2}x faster than full detail");
        }
    }
    Ok(())
}

//! `canopy demo`: the main job on the built-in demo, in one command. Starts `canopy-server`
//! (building it first when run through `cargo run` and it is missing), waits until the demo
//! forest is baked and served, flies the flyover headless against it, streams the start view with
//! every eval method on its own modelled slow4g link (prints Canopy's, the discrete files' and the
//! whole files' first complete frame and time to Q; a report charts SSIM over time for all), scores what the client drew along the flyover against full detail (SSIM,
//! FLIP, per distance band) in one HTML report with charts and image strips, prints where they
//! are, and stops the server.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use canopy_client::lod::LodParams;
use canopy_client::lod::projection::SWITCH_BLEND_BAND;
use canopy_client::net::link::LinkModel;
use clap::Args;

use crate::cli::{LinkArgs, SceneArgs, ViewArgs};
use crate::eval_cmd::{EvalArgs, run as run_eval};
use crate::fly_cmd::{FlyArgs, fly};
use canopy_client::net::http::RangeMode;
use canopy_client::paths::PathKind;

/// Options of `canopy demo`.
#[derive(Args, Debug)]
pub struct DemoArgs {
    /// Server data folder (baked on first start, reused later).
    #[arg(long, default_value = "data")]
    pub data: PathBuf,
    /// Address of the server (a server already answering there is used as it is).
    #[arg(long, default_value = "127.0.0.1:8080")]
    pub addr: String,
    /// Folder for the evaluation's report (report.html), CSV, JSON, charts and image strips.
    #[arg(long, default_value = "demo-report")]
    pub out: PathBuf,
    /// Frames of the flyover the evaluation streams (30 per second).
    #[arg(long, default_value_t = 91)]
    pub eval_frames: u32,
    /// Frames of those the evaluation renders and scores, evenly spaced (at least 1).
    #[arg(long, default_value_t = DEMO_EVAL_SAMPLES, value_parser = clap::value_parser!(u32).range(1..))]
    pub eval_samples: u32,
    /// Keep the server running after the report (Ctrl-C stops it).
    #[arg(long)]
    pub keep_serving: bool,
    /// Do not open the viewer afterwards (it opens when a display is available: `DISPLAY` or
    /// `WAYLAND_DISPLAY` set).
    #[arg(long)]
    pub no_view: bool,
    /// Longest wait for the server's first start (it bakes every species), seconds.
    #[arg(long, default_value_t = 900)]
    pub startup_timeout_s: u64,
    /// Seconds of the slow-link comparison on the virtual clock (long enough for the discrete
    /// files and the whole-file downloads to settle at the start view: about 200 s on slow4g).
    #[arg(long, default_value_t = 220, value_parser = clap::value_parser!(u32).range(1..=3600))]
    pub slow_link_seconds: u32,
}

/// Kills the server when the demo ends, however it ends.
struct ServerGuard(Option<Child>);

impl Drop for ServerGuard {
    fn drop(&mut self) {
        if let Some(c) = &mut self.0 {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

fn server_binary() -> Result<PathBuf> {
    let exe = std::env::current_exe().context("locating this executable")?;
    let dir = exe.parent().context("executable has no folder")?.to_path_buf();
    let path = dir.join("canopy-server");
    if path.is_file() {
        return Ok(path);
    }
    // Under `cargo run` the CARGO variable names cargo: build the server in the same profile.
    let Some(cargo) = std::env::var_os("CARGO") else {
        bail!(
            "{} is missing: build it with `cargo build --release --bin canopy-server`",
            path.display()
        );
    };
    let release = dir.file_name().is_some_and(|n| n == "release");
    eprintln!("building canopy-server ({})", if release { "release" } else { "debug" });
    let mut cmd = Command::new(cargo);
    // `--bin` rather than `-p`: cargo then resolves features for the whole workspace, as the
    // `cargo run --bin canopy` that started this did, and reuses every dependency it built.
    cmd.args(["build", "--bin", "canopy-server"]);
    // From the workspace root, wherever `cargo run` was started.
    if let Some(root) = Path::new(env!("CARGO_MANIFEST_DIR")).parent() {
        cmd.current_dir(root);
    }
    if release {
        cmd.arg("--release");
    }
    let status = cmd.status().context("running cargo build")?;
    if !status.success() || !path.is_file() {
        bail!("building canopy-server failed");
    }
    Ok(path)
}

async fn healthy(client: &reqwest::Client, addr: &str) -> bool {
    client
        .get(format!("http://{addr}/healthz"))
        .send()
        .await
        .is_ok_and(|r| r.status().is_success())
}

/// Runs the demo.
pub async fn run(a: DemoArgs) -> Result<()> {
    let client = reqwest::Client::builder().timeout(Duration::from_secs(2)).build()?;
    let mut guard = ServerGuard(None);
    if healthy(&client, &a.addr).await {
        eprintln!("using the server already running at http://{}", a.addr);
    } else {
        let bin = server_binary()?;
        eprintln!(
            "starting {} serve --data {} --addr {} (the first start grows and bakes every species: 1-2 minutes)",
            bin.display(),
            a.data.display(),
            a.addr
        );
        let child = Command::new(&bin)
            .args(["serve", "--data"])
            .arg(&a.data)
            .args(["--addr", &a.addr])
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .spawn()
            .with_context(|| format!("starting {}", bin.display()))?;
        guard.0 = Some(child);
        let t0 = Instant::now();
        loop {
            if healthy(&client, &a.addr).await {
                break;
            }
            if let Some(c) = guard.0.as_mut()
                && let Some(status) = c.try_wait()?
            {
                bail!("canopy-server exited during start-up ({status}); see its messages above");
            }
            if t0.elapsed() > Duration::from_secs(a.startup_timeout_s) {
                bail!("canopy-server did not answer /healthz within {} s", a.startup_timeout_s);
            }
            tokio::time::sleep(Duration::from_millis(500)).await;
        }
        eprintln!("server ready after {:.0} s", t0.elapsed().as_secs_f64());
    }
    let scene = scene_args(&a.addr);
    let view = |frames: u32, width: u32, height: u32, far: f32, ladder: &str| ViewArgs {
        path: PathKind::Flyover,
        frames,
        width,
        height,
        fov_deg: 60.0,
        view_distance: far,
        cache_mb: 256,
        frame_budget_kb: 0,
        frame_time: f64::from(canopy_client::paths::FRAME_DT),
        speed: None,
        eye_height: None,
        full_detail: false,
        ladder: ladder.into(),
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
        no_plan_pool: false,
        no_terrain_culling: false,
    };
    println!("== fly: the flyover, 300 frames, 1280x720, default LOD");
    fly(FlyArgs {
        scene: scene.clone(),
        view: view(
            300,
            1280,
            720,
            1500.0,
            canopy_client::lod::projection::DEFAULT_LADDER_SPEC,
        ),
        link: LinkArgs {
            link: LinkModel::loopback(),
        },
        until_settled: false,
        json: false,
    })
    .await?;
    println!();
    println!("== fly on a slow link: slow4g (1.6 Mbit/s down, 150 ms), camera held at the flyover's start");
    let mut held = view(
        1800,
        1280,
        720,
        1500.0,
        canopy_client::lod::projection::DEFAULT_LADDER_SPEC,
    );
    held.speed = Some(0.0);
    fly(FlyArgs {
        scene: scene.clone(),
        view: held,
        link: LinkArgs {
            link: LinkModel::preset("slow4g").context("the slow4g preset")?,
        },
        until_settled: true,
        json: false,
    })
    .await?;
    println!();
    slow_link_eval(&scene, &a, &view).await?;
    println!();
    // Samples at every-th frame from `every` on: as many as asked that fit in the frames.
    let every = (a.eval_frames.saturating_sub(1) / a.eval_samples).max(1);
    println!(
        "== eval: {} frames of the flyover, {} of them rendered at 480x270 (view distance 250 m) and scored \
         against full detail",
        a.eval_frames,
        (a.eval_frames.saturating_sub(1) / every).max(1)
    );
    run_eval(EvalArgs {
        scene: scene.clone(),
        view: view(a.eval_frames, 480, 270, 250.0, DEMO_EVAL_LADDER),
        link: LinkArgs {
            link: LinkModel::loopback(),
        },
        every,
        sample_at: Vec::new(),
        enlarge: false,
        out: a.out.clone(),
        save_images: false,
        json: false,
        detail_scales: Vec::new(),
        ladders: Vec::new(),
        strips_dir: None,
        strip_methods: vec!["canopy".into(), "discrete".into()],
    })
    .await?;
    println!();
    println!(
        "report (table, charts, image strips; open in a browser): {}",
        a.out.join("report.html").display()
    );
    println!(
        "slow-link report (SSIM over time for every method): {}",
        a.out.join(SLOW_LINK_REPORT).join("report.html").display()
    );
    let display = ["DISPLAY", "WAYLAND_DISPLAY"]
        .iter()
        .any(|k| std::env::var_os(k).is_some_and(|v| !v.is_empty()));
    if display && !a.no_view {
        println!("== view: opening the viewer on the demo (close the window to finish)");
        crate::view_cmd::run(crate::view_cmd::ViewCmdArgs {
            scene: scene_args(&a.addr),
            view: view(
                300,
                1280,
                720,
                1500.0,
                canopy_client::lod::projection::DEFAULT_LADDER_SPEC,
            ),
            screenshot: None,
            camera: None,
            wait_idle: false,
            reference: None,
            enlarge: false,
            color_by_lod: false,
            no_ground: false,
            json: false,
            capture_after: None,
            capture: None,
            bench_frames: None,
            bench_lod_only: false,
        })
        .await?;
    }
    if a.keep_serving
        && let Some(c) = guard.0.as_mut()
    {
        println!("serving the demo at http://{} until Ctrl-C", a.addr);
        let _ = tokio::signal::ctrl_c().await;
        let _ = c.kill();
    }
    Ok(())
}

/// Folder of the slow-link comparison's report, inside the demo's `--out`.
const SLOW_LINK_REPORT: &str = "slow4g";

/// When the slow-link comparison scores a frame, seconds: dense while the first stand-ins and
/// levels arrive, sparse while the whole files come.
const SLOW_LINK_SAMPLES_S: [f64; 22] = [
    0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0, 15.0, 20.0, 30.0, 45.0, 60.0, 90.0, 120.0, 150.0, 180.0,
    200.0, 220.0,
];

/// Issue 20's comparison on one link: every method streams the flyover's start view, camera
/// held, over its own modelled slow4g link; prints each one's first complete frame and time to
/// Q beside its bytes, and writes a report whose chart is SSIM over time for every method.
async fn slow_link_eval(
    scene: &SceneArgs,
    a: &DemoArgs,
    view: &impl Fn(u32, u32, u32, f32, &str) -> ViewArgs,
) -> Result<()> {
    let fps = (1.0 / canopy_client::paths::FRAME_DT).round() as u32;
    let frames = a.slow_link_seconds.max(1) * fps + 1;
    let sample_at: Vec<f64> = SLOW_LINK_SAMPLES_S
        .into_iter()
        .filter(|&t| t <= f64::from(a.slow_link_seconds))
        .collect();
    println!(
        "== slow link: every method on its own slow4g link, camera held at the flyover's start, {} s on the \
         virtual clock, {} frames scored at 480x270 (view distance 250 m), from 0.5 s apart to 30 s apart",
        a.slow_link_seconds,
        sample_at.len()
    );
    let mut held = view(frames, 480, 270, 250.0, DEMO_EVAL_LADDER);
    held.speed = Some(0.0);
    let out = a.out.join(SLOW_LINK_REPORT);
    run_eval(EvalArgs {
        scene: scene.clone(),
        view: held,
        link: LinkArgs {
            link: LinkModel::preset("slow4g").context("the slow4g preset")?,
        },
        every: fps,
        sample_at,
        enlarge: false,
        out: out.clone(),
        save_images: false,
        json: false,
        detail_scales: Vec::new(),
        ladders: Vec::new(),
        strips_dir: None,
        strip_methods: vec!["canopy".into(), "discrete".into(), "whole-glb".into()],
    })
    .await?;
    let summary: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("summary.json")).context("reading the slow-link summary")?)
            .context("parsing the slow-link summary")?;
    let q = summary["quality_target"].as_f64();
    println!();
    println!(
        "slow4g, camera held: Q = {} (0.01 under the lower of Canopy's and the discrete files' final SSIM)",
        q.map_or("-".into(), |q| format!("{q:.3}"))
    );
    println!(
        "{:<12} {:>15} {:>10} {:>12} {:>10}",
        "method", "first complete", "to Q", "bytes", "SSIM end"
    );
    let secs = |v: &serde_json::Value| v.as_f64().map_or("-".to_string(), |t| format!("{t:.1} s"));
    for name in ["canopy", "discrete", "whole-glb", "whole-ctree"] {
        let Some(m) = summary["methods"]
            .as_array()
            .and_then(|ms| ms.iter().find(|m| m["method"] == name))
        else {
            continue;
        };
        let last = summary["samples"]
            .as_array()
            .and_then(|ss| ss.iter().rfind(|s| s["method"] == name))
            .and_then(|s| s["ssim"].as_f64());
        println!(
            "{:<12} {:>15} {:>10} {:>12} {:>10}",
            name,
            secs(&m["time_to_complete"]),
            secs(&m["time_to_quality_target"]),
            m["bytes"].as_u64().unwrap_or(0),
            last.map_or("-".into(), |v| format!("{v:.3}"))
        );
    }
    println!("(time to Q is that of a scored frame; first complete is per frame)");
    Ok(())
}

fn scene_args(addr: &str) -> SceneArgs {
    SceneArgs {
        url: format!("http://{addr}/api/scenes/demo"),
        assets_base: None,
        range_mode: RangeMode::Auto,
        max_in_flight: 16,
        retries: 4,
    }
}

/// Frames the demo's evaluation scores: enough for its charts to be curves (issue 21).
pub const DEMO_EVAL_SAMPLES: u32 = 8;

/// The evaluation's ladder in the demo: the default ladder (`geometry:150,hemioct:0` at
/// 1280 × 720) with its switch height scaled to the evaluation's 270 rows (150 · 270/720 = 56
/// px), so that each tree is drawn as the viewer draws it. (Until 2026-12-05 it was
/// `geometry:15,hull0:8,hemioct:0`, whose hulls showed in the report as green lumps.)
pub const DEMO_EVAL_LADDER: &str = "geometry:56,hemioct:0";

//! Per-frame planning cost of the streaming client on 40,000-tree demo scenes (seed 002's tree
//! count), without a network.
//!
//! Two layouts of the same 40,000 trees:
//! - `plan_40k`: the demo's own 1.1 km × 1.0 km, 91 times denser than seed 002's forest (one tree
//!   per 27 m²; 23,000–30,000 trees in view), the hardest case;
//! - `plan_40k_10km`: seed 002's 10 km × 10 km (one tree per 2,500 m²; 700–800 in view with the
//!   default 60° field and 1,500 m view distance).
//!
//! Each scene is the server's own demo (`canopy-server serve --demo-trees 40000`, plus
//! `--demo-width-m 10000 --demo-depth-m 10000` for the second: the four baked species,
//! Poisson-disk placed instances), read from its data folder through [`FileSource`]: the client
//! crate does not depend on the server crate, so the bench makes each folder once by running the
//! server binary (built by cargo on first use) and keeps it under the target folder (the second
//! reuses the first's baked trees when they exist). `CANOPY_PLAN_DATA=DIR` and
//! `CANOPY_PLAN_DATA_10KM=DIR` use existing data folders instead.
//!
//! What is measured: the streamer is first flown along the path for [`WARM_FRAMES`] frames
//! (tiles loaded, models opened, the blocks the path needs cached), then every measured
//! iteration is the *next* frame of the same path (the camera keeps moving; it never repeats a
//! pose within a run). `plan` benches report the frame's `plan_ms` (LOD and range planning, the
//! figure `canopy fly` reports); `frame` benches the whole frame (planning, fetching what is
//! still missing from files, and the draw count); `stage/{select,schedule,resolve}` bench the
//! frame's CPU stages one at a time ([`StageTimes`]).

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::Arc;
use std::time::Duration;

use canopy_client::net::RangeSource;
use canopy_client::net::file::FileSource;
use canopy_client::net::link::LinkModel;
use canopy_client::net::linked::LinkedSource;
use canopy_client::paths::{FRAME_DT, PathKind, camera_at};
use canopy_client::scene::Manifest;
use canopy_client::stream::{StageTimes, StreamOptions, Streamer};
use criterion::{Criterion, criterion_group, criterion_main};

/// Trees in the benched scenes (seed 002's tree count).
const TREES: &str = "40000";

/// One benched scene: 40,000 trees over an extent.
struct Layout {
    /// Criterion group name.
    group: &'static str,
    /// Environment variable naming an existing data folder.
    env: &'static str,
    /// Default data folder under the target folder.
    folder: &'static str,
    /// Extent, metres (x, z).
    extent: [f32; 2],
    /// Paths benched.
    paths: &'static [PathKind],
}

const LAYOUTS: [Layout; 2] = [
    Layout {
        group: "plan_40k",
        env: "CANOPY_PLAN_DATA",
        folder: "plan-bench-data",
        extent: [1100.0, 1000.0],
        paths: &[PathKind::Flyover, PathKind::Orbit],
    },
    Layout {
        group: "plan_40k_10km",
        env: "CANOPY_PLAN_DATA_10KM",
        folder: "plan-bench-data-10km",
        extent: [10_000.0, 10_000.0],
        paths: &[PathKind::Flyover, PathKind::Orbit, PathKind::Lowflight],
    },
];
/// Frames flown before measuring (10 s of the path at 30 frames per second).
const WARM_FRAMES: u32 = 300;

fn target_dir() -> PathBuf {
    // target/release/deps/plan-<hash> → target
    let exe = std::env::current_exe().expect("current exe");
    exe.ancestors().nth(3).expect("target folder").to_path_buf()
}

fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// The newest manifest (`vN.<hash>.json`) of the demo scene in a data folder.
fn newest_manifest(data: &Path) -> Option<PathBuf> {
    let dir = data.join("assets/scenes/demo");
    std::fs::read_dir(dir)
        .ok()?
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|e| e == "json"))
        .filter_map(|p| {
            let name = p.file_name()?.to_str()?;
            let v: u64 = name.strip_prefix('v')?.split('.').next()?.parse().ok()?;
            Some((v, p))
        })
        .max_by_key(|(v, _)| *v)
        .map(|(_, p)| p)
}

/// Copies the baked trees of another layout's data folder, so the server does not bake them
/// again (it bakes only when `assets/trees` is empty).
fn reuse_trees(data: &Path) {
    let dst = data.join("assets/trees");
    for l in &LAYOUTS {
        let src = target_dir().join(l.folder).join("assets/trees");
        let Ok(dir) = std::fs::read_dir(&src) else { continue };
        if src == dst {
            continue;
        }
        std::fs::create_dir_all(&dst).expect("create trees folder");
        for e in dir.filter_map(Result::ok) {
            std::fs::copy(e.path(), dst.join(e.file_name())).expect("copy a baked tree");
        }
        return;
    }
}

/// Makes the layout's demo in `data` by starting the real server once (it bakes on first start
/// and prints its address when ready), then stops it.
fn bake_demo(data: &Path, layout: &Layout) {
    let status = Command::new(std::env::var("CARGO").unwrap_or_else(|_| "cargo".into()))
        .current_dir(workspace_root())
        .args(["build", "--release", "--quiet", "-p", "canopy-server"])
        .status()
        .expect("run cargo build");
    assert!(status.success(), "building canopy-server failed");
    reuse_trees(data);
    let server = target_dir().join("release/canopy-server");
    eprintln!("making the {} demo in {} (once)", layout.group, data.display());
    let [w, d] = layout.extent.map(|m| m.to_string());
    let mut child = Command::new(server)
        .current_dir(workspace_root())
        .args(["serve", "--addr", "127.0.0.1:0", "--demo-trees", TREES])
        .args(["--demo-width-m", &w, "--demo-depth-m", &d, "--data"])
        .arg(data)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("start canopy-server");
    let out = child.stdout.take().expect("stdout");
    let ready = std::io::BufRead::lines(std::io::BufReader::new(out))
        .map_while(Result::ok)
        .any(|l| l.contains("listening on"));
    let _ = child.kill();
    let _ = child.wait();
    assert!(ready, "canopy-server exited before the demo was ready");
}

/// The data folder and the manifest to bench.
fn scene(layout: &Layout) -> (PathBuf, Manifest) {
    let data = std::env::var_os(layout.env).map_or_else(|| target_dir().join(layout.folder), PathBuf::from);
    let manifest = newest_manifest(&data).unwrap_or_else(|| {
        bake_demo(&data, layout);
        newest_manifest(&data).expect("the demo's manifest")
    });
    let m = Manifest::parse(&std::fs::read(&manifest).expect("read manifest")).expect("manifest");
    let [min_x, min_z, max_x, max_z] = m.bounds.as_f32();
    let extent = [max_x - min_x, max_z - min_z];
    assert!(
        m.instance_count == 40_000 && extent == layout.extent,
        "{} is not the 40,000-tree demo over {:?} m (it has {} trees over {extent:?} m)",
        manifest.display(),
        layout.extent,
        m.instance_count
    );
    (data, m)
}

fn bench(c: &mut Criterion) {
    let rt = tokio::runtime::Builder::new_current_thread().build().expect("runtime");
    // Frames spawn their transfers on it; they run while `advance_to` waits for them.
    let _runtime = rt.enter();
    for layout in &LAYOUTS {
        let (data, manifest) = scene(layout);
        let bounds = manifest.bounds.as_f32();
        let mut g = c.benchmark_group(layout.group);
        g.sample_size(10)
            .warm_up_time(Duration::from_secs(1))
            .measurement_time(Duration::from_secs(8));
        for &path in layout.paths {
            // On the virtual clock over no link: what a frame asks for arrives by the next.
            let src = Arc::new(LinkedSource::new(FileSource::new(&data), LinkModel::loopback()));
            let mut s = Streamer::with_manifest(Arc::clone(&src), manifest.clone(), StreamOptions::default());
            let mut f = 0u32;
            let mut next = |s: &mut Streamer<LinkedSource<FileSource>>| {
                let cam = camera_at(path, bounds, f as f32 * FRAME_DT);
                f += 1;
                let r = s.frame(&cam, FRAME_DT);
                rt.block_on(src.advance_to(f64::from(f) * f64::from(FRAME_DT)));
                r
            };
            let mut most_visible = 0;
            for _ in 0..WARM_FRAMES {
                most_visible = most_visible.max(next(&mut s).visible);
            }
            eprintln!(
                "{} {path:?}: {} instances loaded, up to {most_visible} visible during warm-up, {:.1} MB fetched",
                layout.group,
                manifest.instance_count,
                s.source().stats().snapshot().bytes as f64 / 1e6
            );
            let name = format!("{path:?}").to_lowercase();
            g.bench_function(format!("plan/{name}"), |b| {
                b.iter_custom(|iters| {
                    (0..iters)
                        .map(|_| Duration::from_secs_f64(next(&mut s).plan_ms / 1e3))
                        .sum()
                });
            });
            g.bench_function(format!("frame/{name}"), |b| {
                b.iter_custom(|iters| {
                    (0..iters)
                        .map(|_| Duration::from_secs_f64(next(&mut s).frame_ms / 1e3))
                        .sum()
                });
            });
            // The frame's CPU stages one by one (`Streamer::stage_times`).
            type Stage = fn(&StageTimes) -> f64;
            let stages: [(&str, Stage); 3] = [
                ("select", |t| t.select_ms),
                ("schedule", |t| t.schedule_ms),
                ("resolve", |t| t.resolve_ms),
            ];
            for (stage, ms) in stages {
                g.bench_function(format!("stage/{stage}/{name}"), |b| {
                    b.iter_custom(|iters| {
                        (0..iters)
                            .map(|_| {
                                next(&mut s);
                                Duration::from_secs_f64(ms(&s.stage_times()) / 1e3)
                            })
                            .sum()
                    });
                });
            }
        }
        g.finish();
    }
}

criterion_group!(benches, bench);
criterion_main!(benches);

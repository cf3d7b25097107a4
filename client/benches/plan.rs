//! Per-frame planning cost of the streaming client on the 40,000-tree demo scene, without a
//! network.
//!
//! The scene is the server's own demo (`canopy-server serve --demo-trees 40000`: the four baked
//! species, 40,000 Poisson-disk placed instances), read from its data folder through
//! [`FileSource`]: the client crate does not depend on the server crate, so the bench makes that
//! folder once by running the server binary (built by cargo on first use) and keeps it under the
//! target folder. `CANOPY_PLAN_DATA=DIR` uses an existing data folder instead.
//!
//! What is measured: the streamer is first flown along the path for [`WARM_FRAMES`] frames
//! (tiles loaded, models opened, the blocks the path needs cached), then every measured
//! iteration is the *next* frame of the same path (the camera keeps moving; it never repeats a
//! pose within a run). `plan` benches report the frame's `plan_ms` (LOD and range planning, the
//! figure `canopy fly` reports); `frame` benches the whole frame (planning, fetching what is
//! still missing from files, and the draw count).

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::Arc;
use std::time::Duration;

use canopy_client::net::RangeSource;
use canopy_client::net::file::FileSource;
use canopy_client::paths::{FRAME_DT, PathKind, camera_at};
use canopy_client::scene::Manifest;
use canopy_client::stream::{StreamOptions, Streamer};
use criterion::{Criterion, criterion_group, criterion_main};

/// Trees in the benched scene (seed 002's scene size).
const TREES: &str = "40000";
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

/// Bakes the demo into `data` by starting the real server once (it bakes on first start and
/// prints its address when ready), then stops it.
fn bake_demo(data: &Path) {
    let status = Command::new(std::env::var("CARGO").unwrap_or_else(|_| "cargo".into()))
        .current_dir(workspace_root())
        .args(["build", "--release", "--quiet", "-p", "canopy-server"])
        .status()
        .expect("run cargo build");
    assert!(status.success(), "building canopy-server failed");
    let server = target_dir().join("release/canopy-server");
    eprintln!("baking the {TREES}-tree demo into {} (once)", data.display());
    let mut child = Command::new(server)
        .current_dir(workspace_root())
        .args(["serve", "--addr", "127.0.0.1:0", "--demo-trees", TREES, "--data"])
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
fn scene() -> (PathBuf, Manifest) {
    let data = std::env::var_os("CANOPY_PLAN_DATA").map_or_else(|| target_dir().join("plan-bench-data"), PathBuf::from);
    let manifest = newest_manifest(&data).unwrap_or_else(|| {
        bake_demo(&data);
        newest_manifest(&data).expect("the demo's manifest")
    });
    let m = Manifest::parse(&std::fs::read(&manifest).expect("read manifest")).expect("manifest");
    assert_eq!(
        m.instance_count,
        40_000,
        "{} is not the 40,000-tree demo",
        manifest.display()
    );
    (data, m)
}

fn bench(c: &mut Criterion) {
    let rt = tokio::runtime::Builder::new_current_thread().build().expect("runtime");
    let (data, manifest) = scene();
    let bounds = [
        manifest.bounds.min[0],
        manifest.bounds.min[1],
        manifest.bounds.max[0],
        manifest.bounds.max[1],
    ];
    let mut g = c.benchmark_group("plan_40k");
    g.sample_size(10)
        .warm_up_time(Duration::from_secs(1))
        .measurement_time(Duration::from_secs(8));
    for path in [PathKind::Flyover, PathKind::Orbit] {
        let src = Arc::new(FileSource::new(&data));
        let mut s = Streamer::with_manifest(src, manifest.clone(), StreamOptions::default());
        let mut f = 0u32;
        let mut next = |s: &mut Streamer<FileSource>| {
            let cam = camera_at(path, bounds, f as f32 * FRAME_DT);
            f += 1;
            rt.block_on(s.frame(&cam, FRAME_DT))
        };
        let mut most_visible = 0;
        for _ in 0..WARM_FRAMES {
            most_visible = most_visible.max(next(&mut s).visible);
        }
        eprintln!(
            "{path:?}: {} instances loaded, up to {most_visible} visible during warm-up, {:.1} MB fetched",
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
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);

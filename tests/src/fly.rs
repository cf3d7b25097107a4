//! Running `canopy fly` from tests: bounded in time, its JSON report parsed and checked.

use std::io::Read;
use std::path::Path;
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

use serde_json::Value;

use crate::faults::{FaultProxy, Seen, parse_range_spec};
use crate::net::{Server, http};
use crate::{client, server, workspace_root};

/// A small synthetic demo (400 trees of 2 models), quick to serve.
pub const SMALL_DEMO: &[&str] = &["--demo-synthetic", "2", "--demo-trees", "400"];
/// Path and frames of most runs: a walk through the trees (geometry, hulls and billboards).
pub const PATH: &str = "walk";
/// Frames of most runs.
pub const FRAMES: &str = "90";
/// Longest one `canopy` run may take before the test fails.
pub const RUN_LIMIT: Duration = Duration::from_secs(90);

/// Runs a command with a time limit; kills it and panics when it runs over.
pub fn run_bounded(cmd: &mut Command, limit: Duration) -> Output {
    let mut child = cmd
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn canopy");
    let mut out = child.stdout.take().expect("stdout");
    let mut err = child.stderr.take().expect("stderr");
    let t_out = std::thread::spawn(move || {
        let mut b = Vec::new();
        let _ = out.read_to_end(&mut b);
        b
    });
    let t_err = std::thread::spawn(move || {
        let mut b = Vec::new();
        let _ = err.read_to_end(&mut b);
        b
    });
    let t0 = Instant::now();
    let status = loop {
        if let Some(s) = child.try_wait().expect("wait for canopy") {
            break s;
        }
        if t0.elapsed() > limit {
            let _ = child.kill();
            let _ = child.wait();
            let stderr = t_err.join().unwrap_or_default();
            panic!(
                "{cmd:?} ran over {limit:?}; stderr:\n{}",
                String::from_utf8_lossy(&stderr)
            );
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    Output {
        status,
        stdout: t_out.join().unwrap_or_default(),
        stderr: t_err.join().unwrap_or_default(),
    }
}

/// `canopy fly URL --json ARGS…` (path and frames from ARGS, else [`PATH`] and [`FRAMES`]).
pub fn fly_output(url: &str, args: &[&str]) -> Output {
    fly_output_env(url, args, &[])
}

/// [`fly_output`] with environment variables set.
pub fn fly_output_env(url: &str, args: &[&str], env: &[(&str, &str)]) -> Output {
    let mut cmd = Command::new(client());
    cmd.envs(env.iter().copied());
    cmd.args(["fly", url, "--json"]);
    if !args.contains(&"--path") {
        cmd.args(["--path", PATH]);
    }
    if !args.contains(&"--frames") {
        cmd.args(["--frames", FRAMES]);
    }
    cmd.args(args);
    run_bounded(&mut cmd, RUN_LIMIT)
}

/// A finished fly-through.
#[derive(Debug)]
pub struct Fly {
    /// The report's `summary`.
    pub summary: Value,
    /// The report's `frames`.
    pub frames: Vec<Value>,
}

impl Fly {
    /// An unsigned summary field.
    pub fn sum(&self, k: &str) -> u64 {
        self.summary[k]
            .as_u64()
            .unwrap_or_else(|| panic!("summary.{k} is not an unsigned integer: {}", self.summary))
    }

    /// An unsigned field of every frame.
    pub fn per_frame(&self, k: &str) -> Vec<u64> {
        self.frames
            .iter()
            .map(|f| {
                f[k].as_u64()
                    .unwrap_or_else(|| panic!("frame.{k} is not an unsigned integer: {f}"))
            })
            .collect()
    }

    /// What each frame drew: leaves, triangles, and trees by representation.
    pub fn drawn(&self) -> Vec<[u64; 6]> {
        self.frames
            .iter()
            .map(|f| {
                let g = |k: &str| f[k].as_u64().unwrap_or_else(|| panic!("frame.{k}: {f}"));
                [
                    g("leaves"),
                    g("triangles"),
                    g("geometry_trees"),
                    g("hull_trees"),
                    g("billboard_trees"),
                    g("pending_trees"),
                ]
            })
            .collect()
    }

    /// Frames that drew at least one tree (any representation).
    pub fn drawing_frames(&self) -> usize {
        self.drawn().iter().filter(|d| d[2] + d[3] + d[4] > 0).count()
    }
}

/// Runs `canopy fly` and checks that it succeeds with a well-formed JSON report.
pub fn fly(url: &str, args: &[&str]) -> Fly {
    fly_env(url, args, &[])
}

/// [`fly`] with environment variables set.
pub fn fly_env(url: &str, args: &[&str], env: &[(&str, &str)]) -> Fly {
    let out = fly_output_env(url, args, env);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        out.status.success(),
        "canopy fly {url} {args:?} failed ({}):\n{stderr}",
        out.status
    );
    assert!(!stderr.contains("panicked"), "canopy fly {args:?} panicked:\n{stderr}");
    let json: Value = serde_json::from_slice(&out.stdout).unwrap_or_else(|e| {
        panic!(
            "canopy fly {args:?} printed no JSON ({e}):\n{}",
            String::from_utf8_lossy(&out.stdout)
        )
    });
    let frames = json["frames"].as_array().expect("frames array").clone();
    let want: usize = args
        .iter()
        .position(|a| *a == "--frames")
        .and_then(|i| args.get(i + 1))
        .unwrap_or(&FRAMES)
        .parse()
        .expect("frame count");
    assert_eq!(frames.len(), want, "one report per frame");
    Fly {
        summary: json["summary"].clone(),
        frames,
    }
}

/// The demo scene's URL on `s`.
pub fn scene_url(s: &Server) -> String {
    format!("http://{}/api/scenes/demo", s.addr)
}

/// Checks that a `canopy` run (`what`) failed without a panic; returns its stderr.
pub fn failed(out: &Output, what: &str) -> String {
    let stderr = String::from_utf8_lossy(&out.stderr).to_string();
    assert!(!out.status.success(), "{what} succeeded");
    assert!(!stderr.contains("panicked"), "{what} panicked:\n{stderr}");
    stderr
}

/// Runs `canopy fly URL` expecting failure; returns stderr.
pub fn fly_fails(url: &str, args: &[&str]) -> String {
    let out = fly_output(url, args);
    let stderr = failed(&out, &format!("canopy fly {url}"));
    assert!(out.stdout.is_empty() || !String::from_utf8_lossy(&out.stdout).contains("\"summary\""));
    stderr
}

/// The sections of a model file (`canopy-server inspect --json`): kind and byte range.
pub fn sections(file: &Path) -> Vec<(String, (u64, u64))> {
    let out = run_bounded(Command::new(server()).arg("inspect").arg("--json").arg(file), RUN_LIMIT);
    assert!(
        out.status.success(),
        "canopy-server inspect {}: {}",
        file.display(),
        String::from_utf8_lossy(&out.stderr)
    );
    let v: Value = serde_json::from_slice(&out.stdout).expect("inspect JSON");
    v["sections"]
        .as_array()
        .expect("sections")
        .iter()
        .map(|s| {
            let off = s["offset"].as_u64().expect("offset");
            let kind = s["kind"].as_str().expect("kind").to_string();
            (kind, (off, off + s["bytes"].as_u64().expect("bytes")))
        })
        .collect()
}

/// A model's sections: kind and byte range.
pub type Sections = Vec<(String, (u64, u64))>;

/// An atlas image of a model file: its frame, resolution index (0 the largest side) and byte
/// range in the file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct AtlasImage {
    pub frame: u64,
    pub resolution: u64,
    pub range: (u64, u64),
}

/// Every atlas image of a model file (`canopy-server inspect --json`).
pub fn atlas_images(file: &Path) -> Vec<AtlasImage> {
    let out = run_bounded(Command::new(server()).arg("inspect").arg("--json").arg(file), RUN_LIMIT);
    assert!(out.status.success(), "canopy-server inspect {}", file.display());
    let v: Value = serde_json::from_slice(&out.stdout).expect("inspect JSON");
    v["atlas"]["images"]
        .as_array()
        .expect("atlas images")
        .iter()
        .map(|i| {
            let n = |k: &str| i[k].as_u64().unwrap_or_else(|| panic!("atlas image {k}"));
            let r = &i["range"];
            AtlasImage {
                frame: n("frame"),
                resolution: n("resolution"),
                range: (r[0].as_u64().expect("start"), r[1].as_u64().expect("end")),
            }
        })
        .collect()
}

/// The crossed-quad stand-in of a model file: the `crossed` layout's two frames at the coarsest
/// resolution, the first unit the client fetches for every model (`None`: no such layout).
/// Returns the frames and the byte span from the first image's start to the last one's end.
pub fn crossed_stand_in(file: &Path) -> Option<(Vec<u64>, (u64, u64))> {
    let out = run_bounded(Command::new(server()).arg("inspect").arg("--json").arg(file), RUN_LIMIT);
    assert!(out.status.success(), "canopy-server inspect {}", file.display());
    let v: Value = serde_json::from_slice(&out.stdout).expect("inspect JSON");
    let l = v["atlas"]["layouts"]
        .as_array()?
        .iter()
        .find(|l| l["layout"] == "crossed")?;
    let first = l["first_frame"].as_u64()?;
    let coarsest = v["atlas"]["resolutions"].as_array()?.len().checked_sub(1)? as u64;
    let frames = vec![first, first + 1];
    let images: Vec<AtlasImage> = atlas_images(file)
        .into_iter()
        .filter(|i| frames.contains(&i.frame) && i.resolution == coarsest)
        .collect();
    let start = images.iter().map(|i| i.range.0).min()?;
    let end = images.iter().map(|i| i.range.1).max()?;
    Some((frames, (start, end)))
}

/// The byte range of section `kind` among `secs`.
pub fn section_of(secs: &[(String, (u64, u64))], kind: &str) -> (u64, u64) {
    secs.iter()
        .find_map(|(k, r)| (k == kind).then_some(*r))
        .unwrap_or_else(|| panic!("no {kind} section"))
}

/// Every model of the demo: its URL and its sections.
pub fn model_sections(s: &Server) -> Vec<(String, Sections)> {
    let manifest = http(s.addr, "GET", "/api/scenes/demo/manifest", &[], None).json();
    manifest["models"]
        .as_array()
        .expect("models")
        .iter()
        .map(|m| {
            let url = m["url"].as_str().expect("url").to_string();
            let file = s.data.join(url.trim_start_matches('/'));
            (url, sections(&file))
        })
        .collect()
}

/// The leaves section of every model of the demo: URL and byte range.
pub fn leaf_sections(s: &Server) -> Vec<(String, (u64, u64))> {
    model_sections(s)
        .into_iter()
        .map(|(url, secs)| {
            let r = secs
                .iter()
                .find(|(k, _)| k == "leaves")
                .map(|(_, r)| *r)
                .expect("a leaves section");
            (url, r)
        })
        .collect()
}

/// Bytes of `[a, b)` covered by the ranges the proxy saw for `target` (each byte once).
pub fn covered(proxy: &FaultProxy, target: &str, r: (u64, u64)) -> u64 {
    covered_after(proxy, target, r, 0)
}

/// Every range the proxy saw for `target` after its first `skip` requests, clipped to `[a, b)`
/// (`(start, end)`, end exclusive, empty ones left out), as often as it was asked for.
pub fn spans_after(proxy: &FaultProxy, target: &str, (a, b): (u64, u64), skip: usize) -> Vec<(u64, u64)> {
    proxy
        .seen()
        .iter()
        .filter(|s| s.target == target)
        .skip(skip)
        .filter_map(|s| s.range.as_deref().map(parse_range_spec))
        .flatten()
        .map(|(first, last)| (first.max(a), (last + 1).min(b)))
        .filter(|(x, y)| x < y)
        .collect()
}

/// [`covered`], leaving out the first `skip` requests for `target`.
pub fn covered_after(proxy: &FaultProxy, target: &str, (a, b): (u64, u64), skip: usize) -> u64 {
    let mut spans = spans_after(proxy, target, (a, b), skip);
    spans.sort_unstable();
    let (mut total, mut end) = (0, a);
    for (x, y) in spans {
        let x = x.max(end);
        if y > x {
            total += y - x;
            end = y;
        }
    }
    total
}

/// Checks that every byte the proxy flipped was asked for again later: the client dropped the
/// corrupt data (a client that kept it would not fetch it again).
pub fn every_flip_refetched(proxy: &FaultProxy, bad: &Fly, mode: &str) -> usize {
    let flips = proxy.flips();
    assert!(!flips.is_empty(), "{mode}: the proxy flipped nothing");
    for f in &flips {
        assert!(
            proxy.refetched(f.seq, &f.target, f.offset),
            "{mode}: byte {} of {} was corrupted in response {} but never fetched again \
             (corrupt_blocks {}, retries {})",
            f.offset,
            f.target,
            f.seq,
            bad.sum("corrupt_blocks"),
            bad.sum("retries")
        );
    }
    assert_eq!(bad.sum("failures"), 0, "{mode}: {}", bad.summary);
    flips.len()
}

/// A server whose demo is 100 maples: large trees (a 5 MB file, of it 1.4 MB of leaves, 290,000
/// of them), where what a run fetches and draws depends on the LOD in ways the synthetic demo's
/// small trees (whole files smaller than the opening read) cannot show. Baking the maple takes
/// about 15 s, so each test that needs it checks several things on one server.
pub fn maple_server(dir: &Path) -> Server {
    let species = workspace_root().join("assets/species");
    Server::start(
        &dir.join("data"),
        &[
            "--species",
            species.to_str().expect("UTF-8 path"),
            "--demo-species",
            "maple",
            "--demo-trees",
            "100",
        ],
    )
}

/// Whether a request the proxy saw asked for more than one range.
pub fn multi_range(r: &Seen) -> bool {
    r.range.as_deref().is_some_and(|h| parse_range_spec(h).len() > 1)
}

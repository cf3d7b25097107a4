//! End-to-end test of what `canopy eval` shows a person (issue 21): FLIP and per-band scores in
//! its JSON, the resolution it scored at, image strips of its sampled frames and an HTML report
//! that links them, against the real `canopy-server` on loopback.

use std::process::{Command, Stdio};

use canopy_e2e::net::Server;
use canopy_e2e::{client, run_ok, scratch};
use serde_json::Value;

const SMALL_DEMO: &[&str] = &["--demo-synthetic", "2", "--demo-trees", "400"];

#[test]
fn eval_writes_flip_bands_strips_and_a_report_that_links_them() {
    let dir = scratch("eval-report");
    let s = Server::start(&dir.join("data"), SMALL_DEMO);
    let out_dir = dir.join("eval");
    let strips_dir = dir.join("strips");
    let url = format!("http://{}/api/scenes/demo", s.addr);
    let out = run_ok(
        Command::new(client())
            .args(["eval", &url, "--path", "walk", "--frames", "13", "--every", "6"])
            .args([
                "--width",
                "160",
                "--height",
                "90",
                "--json",
                "--strip-methods",
                "canopy,discrete",
            ])
            .arg("--out")
            .arg(&out_dir)
            .arg("--strips-dir")
            .arg(&strips_dir)
            .stdin(Stdio::null()),
    );
    let summary: Value = serde_json::from_slice(&out.stdout).expect("eval --json prints JSON");
    // 160 × 90 is below the viewer's 1280 × 720, and the summary says so.
    let res = &summary["resolution"];
    assert_eq!(
        (res["width"].as_u64(), res["height"].as_u64()),
        (Some(160), Some(90)),
        "{res}"
    );
    assert_eq!(res["reduced"], true);
    assert!(res["note"].as_str().is_some_and(|n| n.contains("160x90")), "{res}");
    let method = |name: &str| {
        summary["methods"]
            .as_array()
            .and_then(|m| m.iter().find(|m| m["method"] == name))
            .unwrap_or_else(|| panic!("no {name} in {summary}"))
            .clone()
    };
    // Full detail is the reference: no FLIP error anywhere, in any band it has.
    let full = method("full");
    assert_eq!(full["mean_flip"].as_f64(), Some(0.0), "{full}");
    let canopy = method("canopy");
    let flip = canopy["mean_flip"].as_f64().expect("mean_flip");
    assert!(flip > 0.0 && flip < 1.0, "{canopy}");
    let bands = canopy["bands"].as_array().expect("bands");
    let names: Vec<&str> = bands.iter().filter_map(|b| b["band"].as_str()).collect();
    assert_eq!(names, ["near", "mid", "far"]);
    // The bands' pixels are trees: together at most the image, and some tree is seen.
    let share: f64 = bands.iter().filter_map(|b| b["mean_pixel_share"].as_f64()).sum();
    assert!(share > 0.0 && share <= 3.0, "{bands:?}");
    // Two sampled frames (6 and 12), two methods with strips: four PNGs, three panels wide.
    let strips: Vec<String> = summary["strips"]
        .as_array()
        .expect("strips")
        .iter()
        .filter_map(|p| p.as_str().map(String::from))
        .collect();
    assert_eq!(strips.len(), 4, "{strips:?}");
    for p in &strips {
        let img = image::open(p).unwrap_or_else(|e| panic!("{p}: {e}"));
        assert_eq!((img.width(), img.height()), (3 * 160 + 2 * 4, 90), "{p}");
        assert!(p.starts_with(&strips_dir.display().to_string()), "{p}");
    }
    // The report exists and every image it shows is there (strips outside `--out` are linked by
    // their own path, which `join` keeps).
    let report = summary["report"].as_str().expect("report path");
    let html = std::fs::read_to_string(report).expect("report.html");
    let srcs: Vec<&str> = html
        .split("<img src=\"")
        .skip(1)
        .filter_map(|rest| rest.split('"').next())
        .collect();
    assert_eq!(srcs.len(), 4, "{srcs:?}");
    for src in &srcs {
        assert!(
            out_dir.join(src).is_file(),
            "report links {src}, not in {}",
            out_dir.display()
        );
    }
    assert!(
        html.contains("<svg") && html.contains("mid FLIP"),
        "charts or table missing"
    );
    // A strip of a method that is not run is refused before anything is fetched.
    let bad = Command::new(client())
        .args(["eval", &url, "--strip-methods", "canopy,nope", "--out"])
        .arg(dir.join("bad"))
        .stdin(Stdio::null())
        .output()
        .expect("run canopy eval");
    let err = String::from_utf8_lossy(&bad.stderr);
    assert!(!bad.status.success() && err.contains("--strip-methods"), "{err}");
}

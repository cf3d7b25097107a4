//! End-to-end tests of streaming over a modelled link: `canopy fly --link` against the real
//! `canopy-server` on loopback, on the virtual clock (`client/src/net/linked.rs`).

use std::process::Command;

use canopy_e2e::net::Server;
use canopy_e2e::{client, run_ok, scratch, workspace_root};
use serde_json::Value;

/// Synthetic trees, as the other client tests use.
const SMALL_DEMO: &[&str] = &["--demo-synthetic", "2", "--demo-trees", "400"];

/// `canopy fly URL ARGS --json`: (summary, frames).
fn fly(url: &str, args: &[&str]) -> (Value, Vec<Value>) {
    let out = run_ok(Command::new(client()).arg("fly").arg(url).args(args).arg("--json"));
    let json: Value = serde_json::from_slice(&out.stdout).expect("fly --json prints JSON");
    let frames = json["frames"].as_array().expect("frames").clone();
    (json["summary"].clone(), frames)
}

fn num(v: &Value, k: &str) -> f64 {
    v[k].as_f64().unwrap_or_else(|| panic!("{k} is not a number: {v}"))
}

#[test]
fn a_slow_link_draws_stand_ins_first_deterministically_and_long_before_the_whole_files() {
    let dir = scratch("client-link-slow");
    let s = Server::start(&dir.join("data"), SMALL_DEMO);
    let url = format!("http://{}/api/scenes/demo", s.addr);
    let args = [
        "--link",
        "3g-slow",
        "--speed",
        "0",
        "--frames",
        "900",
        "--until-settled",
    ];
    let (a, frames) = fly(&url, &args);
    let (b, _) = fly(&url, &args);
    // The virtual clock: the same run twice gives the same times and bytes.
    for k in ["first_complete_s", "settled_s", "bytes", "link_wire_bytes"] {
        assert_eq!(a[k], b[k], "{k} differs between two runs of the same path and link");
    }
    let first = num(&a, "first_complete_s");
    let settled = num(&a, "settled_s");
    let whole = num(&a, "whole_download_s");
    assert!(
        first < settled && first < whole / 2.0,
        "first complete frame {first} s, settled {settled} s, every file whole {whole} s"
    );
    // The same baseline with each model's level-0 .glb, modelled on the same link after the
    // manifest. (This scene's synthetic models are tiny meshes: their .glb files are smaller
    // than the .ctree files with their atlases, so no order against `first` is implied.)
    let whole_glb = num(&a, "whole_glb_download_s");
    assert!(whole_glb > num(&a, "manifest_s") && whole_glb.is_finite(), "{a}");
    // Nothing arrives before a round trip (400 ms) after the manifest.
    assert!(first > num(&a, "manifest_s") + 0.4, "{a}");
    // At the first complete frame every visible tree is drawn, as a stand-in where its geometry
    // is still on its way.
    let f = frames
        .iter()
        .find(|f| f["complete"].as_bool() == Some(true))
        .expect("a complete frame");
    assert_eq!(f["pending_trees"], 0);
    assert!(num(f, "visible") > 0.0);
    // The stand-in is each model's crossed-quad billboard. A hull is drawn only where the
    // opening's reads happened to carry it (these models' sections are tiny) and only until
    // the crossed quads arrive: the default ladder has no hull rung.
    assert!(
        frames.iter().any(|f| num(f, "stand_in_trees") > 0.0),
        "no crossed-quad stand-in drawn"
    );
    let last = frames.last().expect("frames");
    assert_eq!(last["hull_trees"], 0, "{last}");
    for f in &frames {
        // Only a tree drawn as its stand-in can be waiting for its leaves.
        assert!(num(f, "geometry_waiting") <= num(f, "stand_in_trees"), "{f}");
    }
    let u = num(&a, "link_utilisation");
    assert!(u > 0.3 && u <= 1.0 + 1e-9, "link use {u}");
}

#[test]
fn a_bandwidth_drop_lowers_the_detail_and_recovery_raises_it() {
    // A grown species (small shrubs, 2.5 MB a file): the flyover keeps asking for more.
    let dir = scratch("client-link-drop");
    let species = workspace_root().join("assets/species");
    let s = Server::start(
        &dir.join("data"),
        &[
            "--species",
            species.to_str().expect("UTF-8 path"),
            "--demo-species",
            "small_shrub",
            "--demo-trees",
            "200",
        ],
    );
    let url = format!("http://{}/api/scenes/demo", s.addr);
    // 8 Mbit/s, 40 kbit/s from 1 s to 10 s, 8 Mbit/s again.
    let (_, frames) = fly(
        &url,
        &["--link", "8,40@1=0.04;10=8", "--path", "flyover", "--frames", "600"],
    );
    let level = |from: f64, to: f64, pick: fn(f64, f64) -> f64| {
        frames
            .iter()
            .filter(|f| (from..to).contains(&num(f, "time_s")))
            .map(|f| num(f, "detail"))
            .fold(f64::NAN, pick)
    };
    let low = level(1.0, 10.0, f64::min);
    let after = level(15.0, 20.0, f64::max);
    assert!(
        low < 0.6,
        "the detail stayed at {low} or above while the link carried 40 kbit/s"
    );
    assert!(
        after > 0.9,
        "the detail did not come back after the link recovered: {low} then {after}"
    );
    // An instant link never lowers it.
    let (_, fast) = fly(&url, &["--path", "flyover", "--frames", "300"]);
    assert!(fast.iter().all(|f| num(f, "detail") == 1.0));
}

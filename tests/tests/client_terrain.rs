//! The terrain end to end: the server's `hills` scene (the demo's models on a generated terrain)
//! is streamed with its terrain tiles fetched by range; trees the hills hide are neither drawn
//! nor fetched for, and none of them shows in the full-detail reference (the culling is
//! conservative); the flat demo is untouched.

use canopy_e2e::fly::*;
use canopy_e2e::net::Server;
use canopy_e2e::{client, scratch};
use serde_json::Value;

fn hills_url(s: &Server) -> String {
    format!("http://{}/api/scenes/hills", s.addr)
}

fn fly(url: &str, args: &[&str]) -> Value {
    let out = fly_output(url, args);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    serde_json::from_slice(&out.stdout).expect("fly JSON")
}

fn frames(v: &Value) -> &Vec<Value> {
    v["frames"].as_array().expect("frames")
}

fn sum(v: &Value, key: &str) -> u64 {
    frames(v).iter().map(|f| f[key].as_u64().unwrap_or(0)).sum()
}

#[test]
fn hills_hide_trees_which_are_then_not_fetched() {
    let dir = scratch("client-terrain");
    let s = Server::start(&dir.join("data"), SMALL_DEMO);
    let url = hills_url(&s);
    let args = ["--path", "walk", "--frames", "40", "--width", "480", "--height", "270"];
    let culled = fly(&url, &args);
    let mut all = args.to_vec();
    all.push("--no-terrain-culling");
    let kept = fly(&url, &all);

    assert!(sum(&culled, "terrain_culled") > 0, "the walk sees no hidden tree");
    assert_eq!(sum(&kept, "terrain_culled"), 0);
    // The terrain's tiles came by range, nearest first, and are all held by the end.
    let last = frames(&culled).last().expect("a frame");
    assert!(last["terrain_tiles"].as_u64().unwrap_or(0) > 0, "{last}");
    assert_eq!(last["terrain_loading"], 0);
    // Same camera, same instances: a culled tree is one the run without culling saw.
    for (a, b) in frames(&culled).iter().zip(frames(&kept)) {
        if a["tiles_loading"] == 0 && b["tiles_loading"] == 0 && a["instances_loaded"] == b["instances_loaded"] {
            let (va, ca, vb) = (
                a["visible"].as_u64(),
                a["terrain_culled"].as_u64(),
                b["visible"].as_u64(),
            );
            assert_eq!(va.zip(ca).map(|(v, c)| v + c), vb, "frame {}", a["frame"]);
        }
    }
    let (bytes_culled, bytes_kept) = (sum(&culled, "bytes"), sum(&kept, "bytes"));
    assert!(
        bytes_culled <= bytes_kept,
        "culling fetched more: {bytes_culled} against {bytes_kept}"
    );

    // The flat demo has no terrain and culls nothing.
    let flat = fly(&scene_url(&s), &args);
    assert_eq!(sum(&flat, "terrain_culled"), 0);
    assert_eq!(sum(&flat, "terrain_tiles"), 0);
}

#[test]
fn no_tree_the_hills_hide_shows_in_the_reference() {
    let dir = scratch("client-terrain-eval");
    let s = Server::start(&dir.join("data"), SMALL_DEMO);
    let out_dir = dir.join("eval");
    let mut cmd = std::process::Command::new(client());
    cmd.arg("eval")
        .arg(hills_url(&s))
        .args([
            "--path", "walk", "--frames", "24", "--every", "6", "--width", "320", "--height", "180",
        ])
        .args(["--json", "--out"])
        .arg(&out_dir);
    let out = run_bounded(&mut cmd, RUN_LIMIT);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let v: Value = serde_json::from_slice(&out.stdout).expect("eval JSON");
    let t = &v["terrain_culling"];
    assert!(t["frames_checked"].as_u64().unwrap_or(0) >= 3, "{t}");
    assert!(t["mean_culled"].as_f64().unwrap_or(0.0) > 0.0, "nothing culled: {t}");
    assert_eq!(t["culled_seen_in_reference"], 0, "a culled tree shows: {t}");
    assert_eq!(t["culled_seen_pixels"], 0, "{t}");
}

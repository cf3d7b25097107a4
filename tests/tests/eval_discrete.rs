//! End-to-end test of the discrete-files baseline as real files (issue 20, item 6): the server
//! writes each model's level files and the manifest names them; each is served whole as a GLB of
//! the size and hash listed; `canopy eval`'s `discrete` method downloads them, and its bytes are
//! exactly the sizes of files it fetched, on loopback and on a modelled link, where they take
//! the link's time.

use std::collections::BTreeSet;
use std::process::{Command, Stdio};

use canopy_e2e::net::{Server, http};
use canopy_e2e::{client, run_ok, scratch};
use serde_json::Value;

const SMALL_DEMO: &[&str] = &["--demo-synthetic", "2", "--demo-trees", "400"];

/// Every sum of a subset of `sizes`.
fn subset_sums(sizes: &[u64]) -> BTreeSet<u64> {
    let mut sums = BTreeSet::from([0u64]);
    for &s in sizes {
        let more: Vec<u64> = sums.iter().map(|x| x + s).collect();
        sums.extend(more);
    }
    sums
}

fn eval(url: &str, out: &std::path::Path, extra: &[&str]) -> Value {
    let o = run_ok(
        Command::new(client())
            .args(["eval", url, "--path", "walk", "--frames", "31", "--every", "15"])
            .args(["--width", "160", "--height", "90", "--json", "--out"])
            .arg(out)
            .args(extra)
            .stdin(Stdio::null()),
    );
    serde_json::from_slice(&o.stdout).expect("eval --json prints JSON")
}

fn method(summary: &Value, name: &str) -> Value {
    summary["methods"]
        .as_array()
        .and_then(|m| m.iter().find(|m| m["method"] == name))
        .unwrap_or_else(|| panic!("no {name} in {summary}"))
        .clone()
}

#[test]
fn discrete_files_are_served_whole_and_eval_downloads_exactly_them() {
    let dir = scratch("eval-discrete");
    let s = Server::start(&dir.join("data"), SMALL_DEMO);
    let m = http(s.addr, "GET", "/api/scenes/demo/manifest", &[], None).json();
    let models = m["models"].as_array().expect("models");
    assert_eq!(models.len(), 2, "{m}");
    let mut all_sizes = Vec::new();
    let mut finest = Vec::new();
    let ctrees: Vec<u64> = models.iter().map(|x| x["size"].as_u64().expect("size")).collect();
    for model in models {
        let levels = model["levels"]
            .as_array()
            .unwrap_or_else(|| panic!("no levels: {model}"));
        assert_eq!(levels.len(), 4, "{model}");
        for (k, l) in levels.iter().enumerate() {
            let url = l["url"].as_str().expect("url");
            let r = http(s.addr, "GET", url, &[], None);
            assert_eq!(r.status, 200, "{url}");
            assert_eq!(r.header("content-type"), Some("model/gltf-binary"), "{url}");
            assert_eq!(Some(r.body.len() as u64), l["size"].as_u64(), "{url}");
            assert_eq!(&r.body[..4], b"glTF", "{url}");
            // The name carries the model file's own hash prefix.
            let sha = model["sha256"].as_str().expect("sha");
            assert!(url.contains(&format!("-lod{k}-{}", &sha[..16])), "{url}");
            all_sizes.push(r.body.len() as u64);
            if k == 0 {
                finest.push(r.body.len() as u64);
            }
        }
    }
    let url = format!("http://{}/api/scenes/demo", s.addr);
    for (label, extra) in [("loopback", &[][..]), ("dash5", &["--link", "dash5"][..])] {
        let summary = eval(&url, &dir.join(label), extra);
        let d = &summary["discrete_files"];
        assert_eq!(d["models_without_levels"], 0, "{label}: {d}");
        assert_eq!(d["failures"], 0, "{label}: {d}");
        let requests = d["requests"].as_u64().expect("requests");
        assert!(requests > 0, "{label}: {d}");
        let bytes = method(&summary, "discrete")["bytes"].as_u64().expect("bytes");
        // What arrived is whole files: a sum of some of the listed sizes, and not nothing.
        assert!(bytes > 0, "{label}");
        assert!(
            subset_sums(&all_sizes).contains(&bytes),
            "{label}: {bytes} B is no sum of {all_sizes:?}"
        );
        // The whole-.glb baseline: the finest level of every model a full-detail frame drew.
        let whole = summary["whole_glb_bytes"].as_u64().expect("whole_glb_bytes");
        assert!(
            whole > 0 && subset_sums(&finest).contains(&whole),
            "{label}: {whole} of {finest:?}"
        );
        // The whole-file methods download whole files and draw full detail once they are in.
        for (name, sizes) in [("whole-glb", &finest), ("whole-ctree", &ctrees)] {
            let w = method(&summary, name);
            let b = w["bytes"].as_u64().expect("bytes");
            assert!(subset_sums(sizes).contains(&b), "{label} {name}: {b} B of {sizes:?}");
            if label == "loopback" {
                assert!(b > 0, "{label} {name}");
                assert!(
                    w["time_to_complete"].as_f64().is_some(),
                    "{label} {name}: never complete"
                );
                assert!(
                    w["mean_ssim"].as_f64().is_some_and(|x| x > 0.999),
                    "{label} {name}: {w}"
                );
            }
        }
        if label == "loopback" {
            // On an instant link every file a frame asks for is there by the next: none left.
            assert_eq!(d["pending_at_end"], 0, "{label}: {d}");
        }
    }
}

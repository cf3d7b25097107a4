//! End-to-end: `canopy-server serve --unique` on a tiny species (3 models, seconds in a debug
//! build): the scene `unique` places each model once, a restart over the same assets bakes
//! nothing, and a bad `[variation]` stops the server with an error naming the key.

use std::collections::BTreeSet;
use std::path::Path;
use std::process::Command;

use canopy_e2e::net::{Server, http};
use canopy_e2e::scratch;

const TINY: &str = r#"
name = "tiny"
seed = 3
iterations = 3
axiom = "A(1)"
productions = ["A(x) -> F(x*ls, 0.02) [+(40) F(x*0.5, 0.01) L(lw, 0.05)] [-(40) F(x*0.5, 0.01) L(lw, 0.05)] A(x*0.8)"]

[constants]
N = 3
ls = 1.0
lw = 0.04

[variation]
iterations = [2, 4]
iterations_constant = "N"

[variation.constants]
ls = [0.6, 1.4]
lw = [0.02, 0.06]
"#;

fn species(dir: &Path, text: &str) -> String {
    let d = dir.join("species");
    std::fs::create_dir_all(&d).expect("species dir");
    std::fs::write(d.join("tiny.toml"), text).expect("spec");
    d.display().to_string()
}

fn args(species: &str) -> Vec<&str> {
    vec![
        "--no-demo",
        "--unique",
        "--unique-models",
        "3",
        "--unique-side-m",
        "200",
        "--bake-workers",
        "2",
        "--species",
        species,
        "--log-format",
        "json",
    ]
}

/// `(baked, reused)` of the last bake in the server's log (JSON lines; the printed report goes
/// to stdout, which the harness reads for the address).
fn last_bake(log: &Path) -> Option<(u64, u64)> {
    let text = std::fs::read_to_string(log).unwrap_or_default();
    text.lines()
        .rev()
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .find(|v| v["message"] == "unique forest created")
        .and_then(|v| Some((v["fields"]["baked"].as_u64()?, v["fields"]["reused"].as_u64()?)))
}

#[test]
fn unique_forest_is_served_and_its_bake_is_reused() {
    let dir = scratch("unique-forest");
    let sp = species(&dir, TINY);
    let data = dir.join("data");
    let s = Server::start(&data, &args(&sp));
    let m = http(s.addr, "GET", "/api/scenes/unique/manifest", &[], None).json();
    let models: BTreeSet<String> = m["models"]
        .as_array()
        .expect("models")
        .iter()
        .map(|x| x["name"].as_str().expect("name").to_string())
        .collect();
    assert_eq!(models.len(), 3, "{m}");
    assert!(models.iter().all(|n| n.starts_with("unique-tiny-")), "{models:?}");
    let list = http(s.addr, "GET", "/api/scenes", &[], None).json();
    let unique = list["scenes"]
        .as_array()
        .and_then(|a| a.iter().find(|x| x["id"] == "unique"))
        .cloned()
        .expect("scene unique listed");
    assert_eq!(unique["instance_count"], 3);
    let log = data.with_extension("log");
    assert_eq!(last_bake(&log), Some((3, 0)));
    assert_eq!(s.stop().code(), Some(0));

    // Without the scene (a new database) but with the assets: the models are reused.
    std::fs::remove_file(data.join("canopy.db")).expect("remove the database");
    let s = Server::start(&data, &args(&sp));
    assert_eq!(last_bake(&log), Some((0, 3)));
    let m2 = http(s.addr, "GET", "/api/scenes/unique/manifest", &[], None).json();
    let again: BTreeSet<String> = m2["models"]
        .as_array()
        .expect("models")
        .iter()
        .map(|x| x["name"].as_str().expect("name").to_string())
        .collect();
    assert_eq!(again, models);
    drop(s);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_bad_variation_stops_the_server_with_the_key_named() {
    let dir = scratch("unique-bad");
    let sp = species(&dir, &TINY.replace("lw = [0.02, 0.06]", "lw = [0.06, 0.02]"));
    let out = Command::new(canopy_e2e::server())
        .arg("serve")
        .arg("--data")
        .arg(dir.join("data"))
        .args(["--addr", "127.0.0.1:0"])
        .args(args(&sp))
        .output()
        .expect("run canopy-server");
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("variation.constants.lw"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}

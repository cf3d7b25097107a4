//! Seed 002's visual-redundancy table end to end: `canopy redundancy` computes it over the real
//! server's demo, stores it with the scene (`PUT …/flight-table`), the server serves it back,
//! and `canopy fly --flight-policy` flies with it; bad tables and tokens are refused clearly.

use std::process::Command;

use canopy_e2e::fly::*;
use canopy_e2e::net::{Server, http};
use canopy_e2e::{client, scratch};
use serde_json::Value;

/// The pre-pass over a 2 × 2 grid at a small size (cheap enough for CI).
const GRID: &[&str] = &[
    "--h-max",
    "40",
    "--dh",
    "20",
    "--v-max",
    "20",
    "--dv",
    "10",
    "--width",
    "160",
    "--height",
    "90",
    "--viewpoints",
    "1",
];

fn redundancy(url: &str, args: &[&str]) -> std::process::Output {
    let mut cmd = Command::new(client());
    cmd.arg("redundancy").arg(url).args(GRID).args(args);
    run_bounded(&mut cmd, RUN_LIMIT)
}

#[test]
fn a_computed_table_is_stored_with_the_scene_and_flown_with() {
    let dir = scratch("client-redundancy");
    let s = Server::start(&dir.join("data"), SMALL_DEMO);
    let url = scene_url(&s);
    let policy = ["--flight-policy", "--frames", "10"];

    // No table yet: the policy alone, and it says so.
    let before = fly_output(&url, &policy);
    assert!(before.status.success(), "{}", String::from_utf8_lossy(&before.stderr));
    assert!(
        String::from_utf8_lossy(&before.stderr).contains("no flight table"),
        "{}",
        String::from_utf8_lossy(&before.stderr)
    );
    let v: Value = serde_json::from_slice(&before.stdout).expect("fly JSON");
    assert!(v["summary"]["flight_table_offsets"].is_null(), "{}", v["summary"]);

    // The pre-pass, published with the demo's write token.
    let token = std::fs::read_to_string(s.data.join("demo-write-token")).expect("the demo's write token");
    let out_file = dir.join("table.json");
    let out_arg = out_file.to_str().expect("utf-8 path");
    let out = redundancy(
        &url,
        &["--out", out_arg, "--publish", "--write-token", token.trim(), "--json"],
    );
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let run: Value = serde_json::from_slice(&out.stdout).expect("redundancy JSON");
    let offsets = run["table"]["offsets"].clone();
    assert_eq!(offsets.as_array().map(Vec::len), Some(2), "{run}");
    assert!(
        offsets
            .as_array()
            .into_iter()
            .flatten()
            .all(|r| r.as_array().map(Vec::len) == Some(2))
    );
    assert!(run["renders"].as_u64().unwrap_or(0) > 0, "nothing rendered: {run}");
    assert_eq!(run["table"]["method"]["metric"], "ssim-trees");
    let file: Value = serde_json::from_slice(&std::fs::read(&out_file).expect("table file")).expect("JSON");
    assert_eq!(file, run["table"]);

    // The server serves exactly what was stored.
    let got = http(s.addr, "GET", "/api/scenes/demo/flight-table", &[], None);
    assert_eq!(got.status, 200, "{}", String::from_utf8_lossy(&got.body));
    assert_eq!(got.json(), run["table"]);

    // And the policy flies with it.
    let after = fly(&url, &policy);
    assert_eq!(after.summary["flight_table_offsets"], offsets, "{}", after.summary);
    // `--no-flight-table` flies the policy alone.
    let alone = fly(&url, &["--flight-policy", "--no-flight-table", "--frames", "10"]);
    assert!(alone.summary["flight_table_offsets"].is_null());
}

#[test]
fn bad_tables_and_tokens_are_refused_with_clear_errors() {
    let dir = scratch("client-redundancy-bad");
    let s = Server::start(&dir.join("data"), SMALL_DEMO);
    let url = scene_url(&s);

    // A wrong write token: the server's 403, and nothing stored.
    let out = redundancy(
        &url,
        &[
            "--out",
            dir.join("t.json").to_str().expect("utf-8 path"),
            "--publish",
            "--write-token",
            "nope",
        ],
    );
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("403") && err.contains("flight-table"), "{err}");
    assert!(!err.contains("panicked"), "{err}");
    assert_eq!(
        http(s.addr, "GET", "/api/scenes/demo/flight-table", &[], None).status,
        404
    );

    // --publish without a token, and bad grids, fail before any work.
    for args in [
        vec!["--publish"],
        vec!["--dh", "0"],
        vec!["--v-max", "-5"],
        vec!["--threshold", "1.5"],
        vec!["--viewpoints", "0"],
    ] {
        let mut cmd = Command::new(client());
        cmd.arg("redundancy")
            .arg(&url)
            .args(&args)
            .env_remove("CANOPY_WRITE_TOKEN");
        let out = run_bounded(&mut cmd, RUN_LIMIT);
        assert!(!out.status.success(), "{args:?} accepted");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains("--") && !err.contains("panicked"), "{args:?}: {err}");
    }

    // A table file that fails its checks: a ragged table, one past the policy's levels.
    for (name, offsets) in [("ragged", "[[0, 0], [0]]"), ("past", "[[9]]")] {
        let file = dir.join(format!("{name}.json"));
        std::fs::write(
            &file,
            format!(
                r#"{{"format":"canopy-flight-table","format_version":1,"dh_m":20,"dv_mps":10,"offsets":{offsets},
                "policy":{{"sigma_m":[100,250,500,1000],"field_deg":120,"threat_time_s":2}},
                "method":{{"metric":"ssim","threshold":0.95,"width":1,"height":1,"fps":30,"viewpoints":1}}}}"#
            ),
        )
        .expect("write");
        let out = fly_output(
            &url,
            &["--flight-table", file.to_str().expect("utf-8 path"), "--frames", "2"],
        );
        assert!(!out.status.success(), "{name} accepted");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            err.contains("flight table") && err.contains("inconsistent"),
            "{name}: {err}"
        );
        assert!(!err.contains("panicked"), "{err}");
    }
}

//! End to end: the real `canopy-server` binary bakes every species and fixture, inspects and
//! exports them, and rejects bad input with a clear error and a non-zero exit.

use std::process::Command;

use canopy_e2e::{client, run_ok, scratch, server, shared_dir, workspace_root};
use serde_json::Value;

const ALL_SECTIONS: [&str; 9] = [
    "node_table",
    "materials",
    "skeleton_radii",
    "skeleton",
    "bark_mesh",
    "leaves",
    "hulls",
    "billboard_atlases",
    "billboard_clouds",
];

fn json(out: &std::process::Output) -> Value {
    serde_json::from_slice(&out.stdout)
        .unwrap_or_else(|e| panic!("bad JSON ({e}): {}", String::from_utf8_lossy(&out.stdout)))
}

fn inspect(file: &std::path::Path) -> Value {
    json(&run_ok(Command::new(server()).arg("inspect").arg(file).arg("--json")))
}

fn check_sections(report: &Value) {
    let kinds: Vec<&str> = report["sections"]
        .as_array()
        .expect("sections")
        .iter()
        .filter_map(|s| s["kind"].as_str())
        .collect();
    assert_eq!(kinds, ALL_SECTIONS);
    assert!(report["first_request_bytes"].as_u64().expect("first request") <= 65_536);
}

#[test]
fn every_species_bakes_and_the_largest_has_290k_leaves() {
    let out = scratch("species");
    let species = workspace_root().join("assets/species");
    // Area order keeps this debug-build test fast; the VMI order has its own test below.
    let reports = json(&run_ok(
        Command::new(server())
            .arg("bake")
            .arg(&species)
            .arg("-o")
            .arg(&out)
            .args(["--order", "area", "--no-atlases", "--no-hulls", "--json"]),
    ));
    let reports = reports.as_array().expect("one report per species");
    assert!(reports.len() >= 4, "at least four species");
    let max_leaves = reports.iter().filter_map(|r| r["leaves"].as_u64()).max().unwrap_or(0);
    assert!(max_leaves >= 290_000, "largest species has {max_leaves} leaves");
    let min_leaves = reports.iter().filter_map(|r| r["leaves"].as_u64()).min().unwrap_or(0);
    assert!(min_leaves >= 1_000, "smallest species has {min_leaves} leaves");
    for r in reports {
        let file = std::path::PathBuf::from(r["output"].as_str().expect("output"));
        let i = inspect(&file);
        check_sections(&i);
        assert_eq!(i["leaves"], r["leaves"]);
        assert!(
            i["branches"].as_u64().expect("branches") > 10,
            "an L-system tree has a skeleton"
        );
        let levels = i["branches_by_level"].as_array().expect("levels");
        assert!(levels.len() >= 3, "{}: branch levels {levels:?}", r["name"]);
    }
}

#[test]
fn vmi_is_the_default_order_and_the_directory_names_it() {
    let out = scratch("vmi");
    let spec = workspace_root().join("assets/species/small_shrub.toml");
    let r = json(&run_ok(
        Command::new(server())
            .arg("bake")
            .arg(&spec)
            .arg("-o")
            .arg(&out)
            .arg("--json"),
    ));
    assert_eq!(r["order"], "vmi");
    let i = inspect(std::path::Path::new(r["output"].as_str().expect("output")));
    assert_eq!(i["leaf_order"], "vmi");
    // The default bake fills the hull and atlas sections.
    for kind in ["hulls", "billboard_atlases"] {
        let s = i["sections"]
            .as_array()
            .expect("sections")
            .iter()
            .find(|s| s["kind"] == kind)
            .expect(kind);
        assert!(s["bytes"].as_u64().expect("bytes") > 0, "{kind} is empty");
        assert!(s["items"].as_u64().expect("items") > 0, "{kind} has no items");
    }
    let levels = r["hulls"]["levels"].as_array().expect("hull levels");
    assert_eq!(levels.len(), 3);
    let layouts = r["atlases"]["layouts"].as_array().expect("atlas layouts");
    assert_eq!(layouts.len(), 3);
}

#[test]
fn every_fixture_imports_bakes_inspects_and_exports() {
    let Some(shared) = shared_dir() else { return };
    let out = scratch("fixtures");
    let mut n = 0;
    for entry in std::fs::read_dir(shared.join("fixtures/trees")).expect("fixtures") {
        let path = entry.expect("entry").path();
        if path.extension().is_none_or(|e| e != "glb") {
            continue;
        }
        n += 1;
        let r = json(&run_ok(
            Command::new(server())
                .arg("bake")
                .arg(&path)
                .arg("-o")
                .arg(&out)
                .arg("--json"),
        ));
        let leaves = r["leaves"].as_u64().expect("leaves");
        assert!(leaves >= 20, "{}: {leaves} leaves", path.display());
        let file = std::path::PathBuf::from(r["output"].as_str().expect("output"));
        let i = inspect(&file);
        check_sections(&i);
        assert!(i["leaf_nodes"].as_u64().expect("leaf nodes") >= 1);
        let glb = out.join("export.glb");
        run_ok(
            Command::new(server())
                .arg("export")
                .arg(&file)
                .arg("-o")
                .arg(&glb)
                .args(["--rate", "0.5", "--enlarge"]),
        );
        let bytes = std::fs::read(&glb).expect("glb");
        assert_eq!(&bytes[..4], b"glTF");
        let plan = json(&run_ok(
            Command::new(client())
                .arg("plan")
                .arg(&file)
                .args(["--rate", "0.5", "--json"]),
        ));
        let count = |k: &str| {
            plan[k]
                .as_u64()
                .unwrap_or_else(|| panic!("{}: plan.{k} is not a count: {plan}", path.display()))
        };
        let (fetched, drawn) = (count("leaves_fetched"), count("leaves_drawn"));
        assert!(
            drawn > 0 && fetched >= drawn,
            "{}: rate 0.5 draws {drawn} leaves of {fetched} fetched",
            path.display()
        );
    }
    assert_eq!(n, 7, "seven fixture files");
}

#[test]
fn bad_input_fails_with_a_clear_message() {
    let out = scratch("bad");
    // A truncated glb.
    let glb = out.join("broken.glb");
    std::fs::write(&glb, b"glTF\x02\x00\x00\x00\xff\xff\x00\x00").expect("write");
    let o = Command::new(server())
        .arg("bake")
        .arg(&glb)
        .arg("-o")
        .arg(&out)
        .output()
        .expect("run");
    assert!(!o.status.success());
    assert!(
        String::from_utf8_lossy(&o.stderr).contains("broken.glb"),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
    // A grammar that explodes must stop at the module cap, quickly.
    let spec = out.join("explode.toml");
    std::fs::write(&spec, EXPLODING).expect("write");
    let o = Command::new(server())
        .arg("bake")
        .arg(&spec)
        .arg("-o")
        .arg(&out)
        .output()
        .expect("run");
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr).to_lowercase();
    assert!(err.contains("module cap of 8000000"), "{err}");
    // The cap is configurable from the command line.
    let o = Command::new(server())
        .arg("bake")
        .arg(&spec)
        .arg("-o")
        .arg(&out)
        .args(["--max-modules", "1000"])
        .output()
        .expect("run");
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr).to_lowercase();
    assert!(err.contains("module cap of 1000 "), "{err}");
    // A corrupt .ctree.
    let bad = out.join("bad.ctree");
    std::fs::write(&bad, b"CNPYTRE\x1a garbage").expect("write");
    let o = Command::new(server()).arg("inspect").arg(&bad).output().expect("run");
    assert!(!o.status.success());
    assert!(
        String::from_utf8_lossy(&o.stderr).contains("truncated"),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
    // An unknown input kind.
    let o = Command::new(server())
        .arg("bake")
        .arg(out.join("x.obj"))
        .output()
        .expect("run");
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("expected a species spec"));
}

const EXPLODING: &str = r#"
name = "explode"
seed = 1
iterations = 60
axiom = "A"
productions = ["A -> A A"]
"#;

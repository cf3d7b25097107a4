//! Helpers for end-to-end tests: locate (and if needed build) the real binaries, find the
//! repository and `../shared`.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::Mutex;

/// Serializes `cargo build` calls from parallel tests.
static BUILD: Mutex<()> = Mutex::new(());

/// The workspace root.
pub fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// The shared folder beside the checkout (`../shared`). When it is missing, panics if `CI` is set
/// (tests that need it must fail there, not skip) and returns `None` otherwise.
pub fn shared_dir() -> Option<PathBuf> {
    let dir = workspace_root().join("../shared");
    if dir.is_dir() {
        return Some(dir);
    }
    assert!(
        std::env::var_os("CI").is_none(),
        "../shared is missing at {} and CI is set",
        dir.display()
    );
    eprintln!("skipping: ../shared is missing at {}", dir.display());
    None
}

/// Path of a workspace binary in this test's profile directory, built on first use if missing.
pub fn bin(package: &str, name: &str) -> PathBuf {
    let exe = std::env::current_exe().expect("current exe");
    // target/<profile>/deps/<test> -> target/<profile>/<name>
    let profile_dir = exe.parent().and_then(Path::parent).expect("profile dir").to_path_buf();
    let path = profile_dir.join(name);
    let _guard = BUILD.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
    let release = profile_dir.file_name().is_some_and(|n| n == "release");
    // Always ask cargo: it is a no-op when the binary is fresh, and rebuilds a stale one.
    let mut cmd = Command::new(env!("CARGO"));
    cmd.current_dir(workspace_root())
        .args(["build", "--quiet", "-p", package, "--bin", name]);
    if release {
        cmd.arg("--release");
    }
    let status = cmd.status().expect("run cargo build");
    assert!(status.success(), "cargo build of {name} failed");
    assert!(path.is_file(), "{} missing after build", path.display());
    path
}

/// The server binary.
pub fn server() -> PathBuf {
    bin("canopy-server", "canopy-server")
}

/// The client binary.
pub fn client() -> PathBuf {
    bin("canopy-client", "canopy")
}

/// Runs a command and returns its output, panicking with stderr when it fails.
pub fn run_ok(cmd: &mut Command) -> Output {
    let out = cmd.output().expect("spawn");
    assert!(
        out.status.success(),
        "{cmd:?} failed ({}):\n{}",
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// A fresh scratch directory under the target directory.
pub fn scratch(name: &str) -> PathBuf {
    let dir = workspace_root()
        .join("target/e2e-scratch")
        .join(format!("{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("scratch dir");
    dir
}

pub mod faults;
pub mod net;

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

/// Path of a workspace binary in this test's profile directory, built first if it is stale.
///
/// The binaries are built by `cargo test --no-run --workspace`, the build that
/// `cargo nextest run --workspace` (the README's test command) has just done: each package with
/// integration tests gets its binaries built there, with the workspace's unified features. A
/// `cargo build -p <package>` would resolve features for that package alone and compile a second
/// copy of most dependencies (5 minutes for the client on 2 cores), so it is not used. Run alone
/// (`cargo nextest run -p canopy-e2e`), the first test builds every workspace test target here.
pub fn bin(name: &str) -> PathBuf {
    let exe = std::env::current_exe().expect("current exe");
    // target/<profile>/deps/<test> -> target/<profile>/<name>
    let profile_dir = exe.parent().and_then(Path::parent).expect("profile dir").to_path_buf();
    let path = profile_dir.join(name);
    // Serializes builds from tests in this process; cargo's own lock serializes processes.
    let _guard = BUILD.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
    let release = profile_dir.file_name().is_some_and(|n| n == "release");
    // Always ask cargo: it is a no-op when everything is fresh, and rebuilds a stale binary.
    let mut cmd = Command::new(env!("CARGO"));
    cmd.current_dir(workspace_root())
        .args(["test", "--no-run", "--quiet", "--workspace"]);
    if release {
        cmd.arg("--release");
    }
    let status = cmd.status().expect("run cargo test --no-run");
    assert!(status.success(), "building the workspace's binaries failed");
    assert!(path.is_file(), "{} missing after the build", path.display());
    path
}

/// The server binary.
pub fn server() -> PathBuf {
    bin("canopy-server")
}

/// The client binary.
pub fn client() -> PathBuf {
    bin("canopy")
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
pub mod fly;
pub mod net;

//! The `canopy` binary's command line: help, and clear errors (never a panic) for bad input that
//! needs no server. Streaming against a real server is tested in `tests/` (canopy-e2e).
//!
//! Being an integration test of this package also makes `cargo nextest run --workspace` build the
//! `canopy` binary with the workspace's features, which the end-to-end tests then run.

use std::path::PathBuf;
use std::process::{Command, Output};

fn canopy(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_canopy"))
        .args(args)
        .output()
        .expect("spawn canopy")
}

/// A scratch folder under the target directory, unique to this process, removed on drop.
struct Scratch(PathBuf);

impl Scratch {
    fn new() -> Self {
        let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join(format!("cli-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("scratch dir");
        Self(dir)
    }

    fn file(&self, name: &str, bytes: &[u8]) -> PathBuf {
        let path = self.0.join(name);
        std::fs::write(&path, bytes).expect("write scratch file");
        path
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// Asserts that the command failed with a message containing every `needle`, and did not panic.
fn assert_clear_failure(out: &Output, needles: &[&str]) {
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "expected a failure, got success:\n{err}");
    assert!(!err.contains("panicked"), "panicked instead of an error:\n{err}");
    for needle in needles {
        assert!(err.contains(needle), "no {needle:?} in the error:\n{err}");
    }
}

#[test]
fn help_lists_every_command() {
    let out = canopy(&["--help"]);
    assert!(out.status.success());
    let help = String::from_utf8_lossy(&out.stdout);
    for command in ["plan", "fly", "load", "eval", "view", "demo"] {
        assert!(
            help.lines().any(|l| l.trim_start().starts_with(command)),
            "{command} missing from --help:\n{help}"
        );
    }
}

#[test]
fn plan_of_a_missing_file_names_it() {
    let missing = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("no-such-tree.ctree");
    let out = canopy(&["plan", missing.to_str().expect("utf-8 path")]);
    assert_clear_failure(&out, &["opening", "no-such-tree.ctree"]);
}

#[test]
fn plan_of_a_file_that_is_not_a_tree_fails_cleanly() {
    let scratch = Scratch::new();
    for (name, bytes) in [
        ("empty.ctree", &b""[..]),
        ("text.ctree", b"this is not a Canopy tree file, only some text"),
        ("zeros.ctree", &[0u8; 4096][..]),
    ] {
        let path = scratch.file(name, bytes);
        let out = canopy(&["plan", path.to_str().expect("utf-8 path")]);
        assert_clear_failure(&out, &["reading", name]);
    }
}

#[test]
fn bad_arguments_are_rejected_by_the_parser() {
    let out = canopy(&["plan", "x.ctree", "--rate", "half"]);
    assert_clear_failure(&out, &["--rate"]);
    let out = canopy(&["fly"]);
    assert_clear_failure(&out, &["Usage"]);
    let out = canopy(&["no-such-command"]);
    assert_clear_failure(&out, &["no-such-command"]);
}

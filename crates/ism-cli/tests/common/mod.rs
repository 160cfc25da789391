//! Helpers shared by the CLI's end-to-end tests (a test file includes them with `mod common;`).
// Each test binary uses a different subset.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// The `ism` binary under test.
pub fn ism() -> Command {
    Command::new(env!("CARGO_BIN_EXE_ism"))
}

/// A file under `spec/examples/`.
pub fn example(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../spec/examples")
        .join(name)
}

/// The one JSON object a `--json` command prints.
pub fn json(stdout: &[u8]) -> serde_json::Value {
    serde_json::from_slice(stdout).expect("--json prints one JSON object")
}

/// Asserts the exit status, showing what the command printed when it differs.
#[track_caller]
pub fn assert_status(out: &Output, code: i32) {
    assert_eq!(
        out.status.code(),
        Some(code),
        "stderr: {}\nstdout: {}",
        String::from_utf8_lossy(&out.stderr),
        String::from_utf8_lossy(&out.stdout)
    );
}

/// Asserts that `ism validate MODEL` exits 0.
#[track_caller]
pub fn assert_validates(model: &Path) {
    let check = ism().arg("validate").arg(model).output().unwrap();
    assert_status(&check, 0);
}

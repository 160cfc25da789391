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

/// A pseudo-terminal: `(controller, terminal)`. Give `terminal` to a child as standard output or
/// error and the child sees a terminal there; what it writes can be read from `controller`.
#[cfg(unix)]
pub fn pseudo_terminal() -> (std::fs::File, std::fs::File) {
    use rustix::pty::{grantpt, openpt, ptsname, unlockpt, OpenptFlags};
    use std::os::unix::ffi::OsStrExt;
    let controller = openpt(OpenptFlags::RDWR | OpenptFlags::NOCTTY).expect("openpt");
    grantpt(&controller).expect("grantpt");
    unlockpt(&controller).expect("unlockpt");
    let name = ptsname(&controller, Vec::new()).expect("ptsname");
    let terminal = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .open(std::ffi::OsStr::from_bytes(name.as_bytes()))
        .expect("open the terminal side");
    (std::fs::File::from(controller), terminal)
}

/// Asserts exit status 2 and that standard error contains every one of `words`; returns stderr.
#[track_caller]
pub fn assert_refused_with(out: &Output, words: &[&str]) -> String {
    assert_status(out, 2);
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    for w in words {
        assert!(stderr.contains(w), "{w:?} not in: {stderr}");
    }
    stderr
}

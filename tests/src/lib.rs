//! Shared helpers of the workspace-level tests: where the repository, the spec and the `ism` binary are.
#![deny(missing_docs)]

use std::path::PathBuf;

pub mod fuzz;

/// The repository's README, whose Rust example is compiled as a doctest here (`no_run`: its paths
/// are relative to the repository root, and doctests run in `tests/`).
#[doc = include_str!("../../README.md")]
#[cfg(doctest)]
pub struct ReadmeExample;

/// The repository root.
pub fn repo_root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("tests/ sits in the repository")
        .to_path_buf()
}

/// `spec/` in the repository.
pub fn spec_dir() -> PathBuf {
    repo_root().join("spec")
}

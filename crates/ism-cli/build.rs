//! Links the `ism` binary as a position-dependent executable (non-PIE).
//!
//! A PIE binary is relocated by the dynamic loader at every start: the `ism` binary's ~19,800
//! relative relocations make it read the whole relocation table and copy every page of
//! `.data.rel.ro` and the GOT, ~100 of the 256 page faults and 0.26 M of the 1.0 M instructions of
//! `ism --version`, ~0.2 ms of CPU per run (issue 19, session 25: `ism --version` 1.58 → 1.35 ms,
//! best of 200, and a small export's CPU is a few ms). A non-PIE link resolves them at link time.
//! Packed relative relocations (`-z pack-relative-relocs`, still PIE) only shrink the table: 244
//! faults, 1.50 ms. The price is that the executable's own code is not placed at a random address
//! (shared libraries, heap and stack still are).
//!
//! Only the binaries of this crate are affected (`rustc-link-arg-bins`): the libraries, and the
//! Python extension module that links them, stay position-independent.
fn main() {
    let os = std::env::var("CARGO_CFG_TARGET_OS").unwrap_or_default();
    let env = std::env::var("CARGO_CFG_TARGET_ENV").unwrap_or_default();
    // GNU toolchains on Linux (gcc or clang as the linker driver) take `-no-pie`; other targets
    // keep their default.
    if os == "linux" && env == "gnu" {
        println!("cargo:rustc-link-arg-bins=-no-pie");
    }
    println!("cargo:rerun-if-changed=build.rs");
}

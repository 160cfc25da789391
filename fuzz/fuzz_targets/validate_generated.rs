//! The validator on structurally valid models generated from the bytes (Kuhn-grid complexes with
//! arbitrary stages): never a panic, and never VALID where an exact evaluation finds det DY <= 0
//! at a sampled dyadic point (property in `ism_conformance::fuzz::validate_generated`).
#![no_main]
libfuzzer_sys::fuzz_target!(|data: &[u8]| ism_conformance::fuzz::validate_generated(data));

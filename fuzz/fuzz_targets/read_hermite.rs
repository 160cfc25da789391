//! `ism fit --hermite`'s handles file on arbitrary bytes: parse, base model, and a short fit of
//! small inputs (property in `ism_conformance::fuzz::read_hermite`).
#![no_main]
libfuzzer_sys::fuzz_target!(|data: &[u8]| ism_conformance::fuzz::read_hermite(data));

//! The structured decoder (spec §7.4.3) behind a valid container, so the fuzzer explores the
//! `Records` sections (masks over the complex's faces, lattice points) rather than the checksum:
//! arbitrary payloads must give Ok or a typed error, never a panic or an allocation beyond what
//! the bytes justify; every reader gives the same result; what reads is re-encoded canonically to
//! the same model (`ism_conformance::fuzz::read_structured`).
#![no_main]

libfuzzer_sys::fuzz_target!(|payload: &[u8]| {
    ism_conformance::fuzz::read_structured(payload);
});

//! The compressed encoding (spec §7.4.2) behind a valid container: the first byte picks whether the
//! rest is a compressed payload as it is (the length, the xz framing, bombs, bytes after the
//! stream) or a compact payload compressed by the target, whose read must equal the `.ismc`
//! read of the same payload (`ism_conformance::fuzz::read_compressed`). Never a panic or an
//! allocation beyond the limits.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    ism_conformance::fuzz::read_compressed(data);
});

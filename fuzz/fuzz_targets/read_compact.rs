//! The compact binary decoder (spec §7.4.1) behind a valid container, so the fuzzer explores the
//! varint decoding rather than the checksum: arbitrary payloads must give Ok or a typed error, never
//! a panic or a huge allocation; every reader gives the same result
//! (`ism_conformance::fuzz::readers_agree`); what reads is re-encoded to the same model.
#![no_main]
use ism_format::{io, Encoding, FORMAT_VERSION};

libfuzzer_sys::fuzz_target!(|payload: &[u8]| {
    let mut bytes = io::header(Encoding::Compact, FORMAT_VERSION, payload).to_vec();
    bytes.extend_from_slice(payload);
    ism_conformance::fuzz::readers_agree(&bytes);
    if let Ok(doc) = io::from_slice(&bytes) {
        let again =
            io::to_vec(&doc.model, Encoding::Compact, Default::default()).expect("re-encode");
        assert_eq!(io::from_slice(&again).expect("re-read").model, doc.model);
        // Canonical (minimal varints only): a payload that reads is the one the writer writes.
        assert_eq!(&again[io::HEADER_LEN..], payload, "not canonical");
    }
});

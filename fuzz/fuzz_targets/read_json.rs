//! The json decoder behind a valid container, so the fuzzer explores the decoder rather than the
//! checksum: arbitrary payloads must give Ok or a typed error, never a panic or a huge allocation;
//! every reader gives the same result (`ism_conformance::fuzz::readers_agree`).
#![no_main]
use ism_format::{io, Encoding, FORMAT_VERSION};

libfuzzer_sys::fuzz_target!(|payload: &[u8]| {
    let mut bytes = io::header(Encoding::Json, FORMAT_VERSION, payload).to_vec();
    bytes.extend_from_slice(payload);
    ism_conformance::fuzz::readers_agree(&bytes);
    if let Ok(doc) = io::from_slice(&bytes) {
        let again = io::to_vec(&doc.model, Encoding::Json, Default::default()).expect("re-encode");
        assert_eq!(io::from_slice(&again).expect("re-read").model, doc.model);
    }
});

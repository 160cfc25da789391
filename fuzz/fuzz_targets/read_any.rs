//! Whole reader with content sniffing: arbitrary bytes must give Ok or a typed error, never a panic;
//! every reader gives the same result (`ism_conformance::fuzz::readers_agree`).
#![no_main]
libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    ism_conformance::fuzz::readers_agree(data);
    if let Ok(doc) = ism_format::io::from_slice(data) {
        // Whatever reads must write and read back to the same model.
        let bytes = ism_format::io::to_vec(&doc.model, doc.encoding, Default::default())
            .expect("re-encode");
        let again = ism_format::io::from_slice(&bytes).expect("re-read");
        // A writer writes its own version (spec §8.1); nothing else may change.
        let expected = ism_format::Model {
            version: ism_format::FORMAT_VERSION.to_string(),
            ..doc.model
        };
        assert_eq!(again.model, expected);
    }
});

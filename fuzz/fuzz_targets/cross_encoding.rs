//! Cross-encoding round trips (spec §7.7): whatever reads — in any encoding, structure unchecked so
//! the fuzzer reaches odd models — is written in each encoding, read back equal, and written again to
//! the same bytes; the canonical bytes do not depend on the encoding the model came from. Models
//! with a non-finite number are refused by every writer with the rule a reader reports.
#![no_main]
use ism_format::io::{self, ReadOptions, WriteOptions};
use ism_format::{Encoding, Model};

fn unchecked() -> ReadOptions {
    ReadOptions {
        check_structure: false,
        ..ReadOptions::default()
    }
}

/// The model as a writer writes it back: its own version (spec §8.1).
fn as_written(model: &Model) -> Model {
    Model {
        version: ism_format::FORMAT_VERSION.to_string(),
        ..model.clone()
    }
}

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let Ok(doc) = io::from_slice_with(data, &unchecked()) else {
        return;
    };
    let expected = as_written(&doc.model);
    let mut canonical = Vec::new();
    for encoding in Encoding::ALL {
        match io::to_vec(&doc.model, encoding, WriteOptions::default()) {
            Ok(bytes) => {
                let again =
                    io::from_slice_with(&bytes, &unchecked()).expect("a written file reads");
                let binary = |m: &Model| io::encode_payload(m, Encoding::Binary, false).unwrap();
                assert_eq!(
                    binary(&again.model),
                    binary(&expected),
                    "{encoding:?} changed the model"
                );
                let rewritten =
                    io::to_vec(&again.model, encoding, WriteOptions::default()).unwrap();
                assert_eq!(rewritten, bytes, "{encoding:?} is not canonical");
                canonical.push(bytes);
            }
            Err(e) => {
                // Only a reader-level problem may stop a writer, and then in every encoding.
                assert!(io::check_writable(&doc.model).is_err(), "{encoding:?}: {e}");
                assert!(
                    canonical.is_empty(),
                    "{encoding:?} refused what another wrote: {e}"
                );
            }
        }
    }
    // From each written file, every encoding's bytes are the same as from the original.
    for bytes in &canonical {
        let model = io::from_slice_with(bytes, &unchecked()).unwrap().model;
        for (encoding, expected) in Encoding::ALL.into_iter().zip(&canonical) {
            assert_eq!(
                &io::to_vec(&model, encoding, WriteOptions::default()).unwrap(),
                expected
            );
        }
    }
});

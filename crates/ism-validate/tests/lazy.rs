//! The validator indexes a model lazily (face tables only when a layer asks for them): its reports
//! must equal those of the eagerly indexed model (`validate_indexed` on `IndexedModel::new`, every
//! table built before any layer runs) on every spec vector and example, with theorems on and off
//! (off sends every simplex through the face-table lookups) and with the quality layer. The truth
//! is the eager path, whose tables are checked against brute force in ism-format; the vectors'
//! expected issues are checked by the conformance suite.

use std::path::PathBuf;

use ism_format::{io, IndexedModel};
use ism_validate::{validate, validate_indexed, Options, Report};

fn spec_models() -> Vec<PathBuf> {
    let spec = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../spec");
    let mut out = Vec::new();
    for dir in ["vectors/validate", "examples"] {
        for entry in std::fs::read_dir(spec.join(dir)).expect("spec directory") {
            let path = entry.expect("entry").path();
            if path.to_string_lossy().ends_with(".ism.json") {
                out.push(path);
            }
        }
    }
    out.sort();
    out
}

fn without_timing(mut report: Report) -> Report {
    report.timing = Default::default();
    report
}

#[test]
fn lazy_and_eager_indexes_give_the_same_reports() {
    let models = spec_models();
    assert!(models.len() >= 20, "{models:?}");
    let read = io::ReadOptions {
        check_structure: false,
        ..io::ReadOptions::default()
    };
    let mut indexed = 0;
    for path in &models {
        let model = io::read_with(std::fs::File::open(path).expect("file"), &read)
            .expect("readable")
            .model;
        for (theorems, quality) in [(true, false), (false, false), (true, true)] {
            let options = Options {
                theorems,
                quality,
                max_pieces: 4096,
                ..Options::default()
            };
            let lazy = without_timing(validate(&model, &options));
            match IndexedModel::new(model.clone()) {
                Ok(eager) => {
                    indexed += 1;
                    let eager = without_timing(validate_indexed(&eager, &options));
                    assert_eq!(lazy, eager, "{} {options:?}", path.display());
                }
                // Not indexable either way: the structural layer's report (not lazy at all).
                Err(_) => assert!(
                    IndexedModel::new_lazy_or_model(model.clone()).is_err(),
                    "{}",
                    path.display()
                ),
            }
        }
    }
    assert!(indexed >= 3 * 15, "{indexed}");
}

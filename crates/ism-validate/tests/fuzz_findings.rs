//! Regressions found by the `validate_generated` fuzz target (fuzz/, issue 18): each input that
//! made the validator panic or misjudge, as a model (the inputs themselves are replayed by
//! `tests/tests/fuzz_corpora.rs`).

use ism_format::{io, Model};
use ism_validate::{validate, Options, Verdict};

fn example(name: &str) -> Model {
    let path = format!("{}/../../spec/examples/{name}", env!("CARGO_MANIFEST_DIR"));
    io::read_path(path).expect("example reads").model
}

/// `--no-theorems` on a monotonic stage indexed the (empty) face-record table and panicked; only
/// the §4 theorem certifies a monotonic map, so without it the stage is undetermined, never valid.
#[test]
fn monotonic_stage_without_theorems_is_undetermined_not_a_panic() {
    let model = example("monotonic.ism.json");
    let report = validate(
        &model,
        &Options {
            theorems: false,
            ..Options::default()
        },
    );
    assert_eq!(report.verdict, Verdict::Undetermined);
    assert!(report
        .stages
        .iter()
        .all(|s| s.undetermined == model.num_simplices()));
    assert_eq!(
        validate(&model, &Options::default()).verdict,
        Verdict::Valid
    );
}

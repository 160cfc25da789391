//! The progress hook: a validation reports its positivity phase in simplices, and a hook
//! cancelled at its first report stops the run before the work is done.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

use ism_format::progress::{Cancelled, Progress};
use ism_validate::{validate_with_progress, Options, Verdict, POSITIVITY_PHASE};

type Seen = Arc<Mutex<Vec<(String, u64, u64)>>>;

/// A hook recording every step; with `cancel`, it cancels itself at its first report.
fn recording(cancel: bool) -> (Progress, Seen) {
    let flag = Arc::new(AtomicBool::new(false));
    let seen: Seen = Arc::default();
    let (f, s) = (flag.clone(), seen.clone());
    let p = Progress::new(move |st| {
        s.lock()
            .unwrap()
            .push((st.phase.to_string(), st.done, st.total));
        if cancel {
            f.store(true, Ordering::Relaxed);
        }
    })
    .with_cancel(flag);
    (p, seen)
}

#[test]
fn positivity_is_counted_to_the_end_and_a_cancel_stops_it() {
    // 3 stratified stages on a Kuhn grid: every simplex of every stage is decided numerically
    // when the theorems are off.
    let model = ism_examples::large_stratified_model(1500);
    let ns = model.num_simplices() as u64;
    let options = Options {
        theorems: false,
        threads: 2,
        ..Options::default()
    };

    // Uncancelled (with the theorems, quick): each stage's phase starts at 0 and ends at ns.
    let (p, seen) = recording(false);
    let report = validate_with_progress(
        &model,
        &Options {
            threads: 2,
            ..Options::default()
        },
        &p,
    )
    .unwrap();
    assert_eq!(report.verdict, Verdict::Valid);
    let seen = seen.lock().unwrap().clone();
    let phase: Vec<_> = seen.iter().filter(|s| s.0 == POSITIVITY_PHASE).collect();
    assert!(phase.iter().all(|s| s.2 == ns));
    assert_eq!(
        phase.iter().filter(|s| s.1 == 0).count(),
        model.stages.len()
    );
    assert_eq!(
        phase.iter().filter(|s| s.1 == ns).count(),
        model.stages.len()
    );

    // Cancelled at the first report (the first stage's start): no simplex is decided after it.
    let (p, seen) = recording(true);
    assert!(matches!(
        validate_with_progress(&model, &options, &p),
        Err(Cancelled)
    ));
    let seen = seen.lock().unwrap().clone();
    assert_eq!(seen[0], (POSITIVITY_PHASE.to_string(), 0, ns));
    assert!(seen.iter().all(|s| s.1 < ns), "{seen:?}");
    assert_eq!(seen.len(), 1, "only the first stage started: {seen:?}");
}

#[test]
fn a_cancelled_file_validation_is_an_error() {
    let model = ism_examples::large_stratified_model(100);
    let bytes =
        ism_examples::named::example_bytes(&model, ism_format::Encoding::Binary).expect("encodes");
    let (p, _) = recording(true);
    let r = ism_validate::validate_bytes_with_progress(&bytes, &Options::default(), &p);
    assert!(matches!(r, Err(ism_validate::Error::Cancelled(Cancelled))));
}

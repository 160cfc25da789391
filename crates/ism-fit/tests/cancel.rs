//! The progress hook of fitting and smoothing: steps reported as the work goes, and a hook
//! cancelled at its first report stops the call at once (no further step is reported).

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

use ism_fit::smooth::{smooth_with_progress, SmoothOptions, PHASE};
use ism_fit::{fit, FitError, FitOptions, Preset, Progress};

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

fn circle_options() -> (ism_fit::Expression, FitOptions) {
    let preset = Preset::find("circle").unwrap();
    let mut options = FitOptions::new(preset.domain);
    options.resolution = 6;
    (preset.expression().unwrap(), options)
}

#[test]
fn a_fit_reports_its_phases_and_stops_at_the_first_step_when_cancelled() {
    let (g, options) = circle_options();
    let (p, seen) = recording(false);
    let fitted = fit(&g, &options, &p).unwrap();
    let seen = seen.lock().unwrap().clone();
    let phases: Vec<&str> = seen.iter().map(|s| s.0.as_str()).collect();
    assert_eq!(phases.first(), Some(&"topology"));
    assert!(phases.contains(&"optimize") && phases.contains(&"refine"));
    assert_eq!(phases.last(), Some(&"report"));
    assert_eq!(
        seen.last().map(|s| (s.1, s.2)),
        Some((
            fitted.complex.num_cells() as u64,
            options.max_simplices as u64
        ))
    );

    let (p, seen) = recording(true);
    assert!(matches!(fit(&g, &options, &p), Err(FitError::Cancelled(_))));
    assert_eq!(seen.lock().unwrap().len(), 1);
}

#[test]
fn smoothing_counts_its_faces_and_stops_when_cancelled() {
    let (g, options) = circle_options();
    let model = fit(&g, &options, &Progress::none())
        .unwrap()
        .to_model("circle");
    let smooth_options = SmoothOptions {
        iterations: 2,
        ..SmoothOptions::default()
    };
    let (p, seen) = recording(false);
    let s = smooth_with_progress(&model, &smooth_options, &p).unwrap();
    let seen = seen.lock().unwrap().clone();
    let free = s.report.free_faces as u64;
    assert!(free > 0);
    // One phase per sweep, each from 0 to every free face.
    assert_eq!(seen.iter().filter(|x| x.0 == PHASE && x.1 == 0).count(), 2);
    assert!(seen.iter().all(|x| x.0 == PHASE && x.2 == free));

    let (p, seen) = recording(true);
    let r = smooth_with_progress(&model, &smooth_options, &p);
    assert!(matches!(r, Err(ism_fit::hermite::EditError::Cancelled(_))));
    assert_eq!(seen.lock().unwrap().len(), 1);
}

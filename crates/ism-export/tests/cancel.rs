//! The progress hook of extraction and volume export: phases counted to the end, and a hook
//! cancelled at its first report stops the work before it is done. The library `export` call
//! writes what `ism export` writes.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

use ism_export::export::{build, export_path, ExportOptions, Exported};
use ism_export::extract::phase;
use ism_format::progress::Progress;

type Seen = Arc<Mutex<Vec<(String, u64, u64)>>>;

/// A hook recording every step; with `cancel`, it cancels itself at its first counted report.
fn recording(cancel: bool) -> (Progress, Seen) {
    let flag = Arc::new(AtomicBool::new(false));
    let seen: Seen = Arc::default();
    let (f, s) = (flag.clone(), seen.clone());
    let p = Progress::new(move |st| {
        s.lock()
            .unwrap()
            .push((st.phase.to_string(), st.done, st.total));
        if cancel && st.total > 0 {
            f.store(true, Ordering::Relaxed);
        }
    })
    .with_cancel(flag);
    (p, seen)
}

fn sphere() -> ism_format::IndexedModel {
    ism_format::IndexedModel::new(ism_examples::large_stratified_model(3000)).unwrap()
}

#[test]
fn extraction_counts_facets_then_patches_and_stops_when_cancelled() {
    let model = sphere();
    let options = ExportOptions::default();
    let (p, seen) = recording(false);
    let Exported::Surface { extract, .. } = build(&model, &options, &p).unwrap() else {
        panic!("a surface");
    };
    let crossed = extract.unwrap().crossed_simplices as u64;
    let seen = seen.lock().unwrap().clone();
    let patches: Vec<_> = seen.iter().filter(|s| s.0 == phase::PATCHES).collect();
    assert_eq!(patches.first().map(|s| (s.1, s.2)), Some((0, crossed)));
    assert_eq!(patches.last().map(|s| (s.1, s.2)), Some((crossed, crossed)));
    let facets: Vec<_> = seen.iter().filter(|s| s.0 == phase::FACETS).collect();
    let nf = facets[0].2;
    assert!(nf > 0 && facets.last().unwrap().1 == nf);

    // Cancelled at the facets phase's start: no facet is refined, no patch phase begins.
    let (p, seen) = recording(true);
    let r = build(&model, &options, &p);
    assert!(matches!(r, Err(ism_export::Error::Cancelled(_))), "{r:?}");
    let seen = seen.lock().unwrap().clone();
    let counted: Vec<_> = seen.iter().filter(|s| s.2 > 0).collect();
    assert_eq!(counted.len(), 1, "{seen:?}");
    assert_eq!((counted[0].0.as_str(), counted[0].1), (phase::FACETS, 0));
}

#[test]
fn a_cancelled_volume_export_stops_and_writes_nothing() {
    let model = ism_format::IndexedModel::new(ism_examples::large_stratified_model(200)).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("v.vtu");
    let options = ExportOptions {
        volume: true,
        ..ExportOptions::default()
    };
    let (p, seen) = recording(true);
    let r = export_path(&model, &out, &options, &p);
    assert!(matches!(r, Err(ism_export::Error::Cancelled(_))), "{r:?}");
    assert!(!out.exists());
    let seen = seen.lock().unwrap().clone();
    let counted: Vec<_> = seen.iter().filter(|s| s.2 > 0).collect();
    // The first candidate's first phase: its screen on the crossed simplices when those are at
    // most a quarter of all (`SCREENED`), else its fit on every simplex.
    assert_eq!(counted.len(), 1, "{seen:?}");
    let crossed = (0..model.num_simplices())
        .filter(|&s| {
            model
                .simplex(s)
                .iter()
                .any(|&v| model.values[v as usize] < model.level)
                && model
                    .simplex(s)
                    .iter()
                    .any(|&v| model.values[v as usize] >= model.level)
        })
        .count() as u64;
    let expected = if crossed * 4 <= model.num_simplices() as u64 {
        (ism_export::volume::SCREEN_PHASE, 0, crossed)
    } else {
        (ism_export::volume::PHASE, 0, model.num_simplices() as u64)
    };
    assert_eq!(
        (counted[0].0.as_str(), counted[0].1, counted[0].2),
        expected
    );

    // Uncancelled, the same call writes the file and the phase reaches every simplex.
    let (p, seen) = recording(false);
    let (built, _) = export_path(&model, &out, &options, &p).unwrap();
    assert!(matches!(built, Exported::Volume { .. }));
    assert!(out.exists());
    let seen = seen.lock().unwrap().clone();
    let ns = model.num_simplices() as u64;
    assert!(seen
        .iter()
        .any(|s| s.0 == ism_export::volume::PHASE && s.1 == ns));
}

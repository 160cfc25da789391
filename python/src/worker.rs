//! Long calls off the interpreter's thread: the GIL is released, Ctrl-C is honoured, an optional
//! progress callback runs on the caller's thread.
//!
//! Each long call runs on a worker thread while the calling thread waits with the GIL released,
//! waking every [`POLL`] to run Python's signal handlers (`PyErr_CheckSignals`) and the progress
//! callback. The job gets the libraries' progress hook ([`Control::hook`], an
//! [`ism_format::Progress`] sharing this call's cancel flag). On `KeyboardInterrupt` (or an
//! exception from the callback) the flag is set, the library call returns `Cancelled` at its
//! next unit of work (a simplex, a patch, a face, a block of rows, a fit step), and the caller
//! waits for the worker to end before raising: no work continues in the background.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc;
use std::sync::Arc;
use std::time::Duration;

use pyo3::prelude::*;

/// How often the waiting thread wakes to check signals (Ctrl-C answers within this time).
const POLL: Duration = Duration::from_millis(50);

enum Msg<T> {
    Progress(Report),
    Done(std::thread::Result<T>),
}

/// A progress report: rows done (sampling, queries; the callback gets `(done, total)`), a fit's
/// step (the callback gets `(phase, simplices, worst)`) or another library step (the callback
/// gets `(phase, done, total)`; total 0 when not counted).
enum Report {
    Rows(u64),
    Fit(String, u64, f64),
    Step(String, u64, u64),
}

/// What a job sees: the cancel flag and a way to report progress.
#[derive(Clone)]
pub(crate) struct Control {
    cancel: Arc<AtomicBool>,
    progress: mpsc::Sender<Msg<()>>,
}

impl Control {
    /// Whether the caller asked to stop.
    pub(crate) fn cancelled(&self) -> bool {
        self.cancel.load(Ordering::Relaxed)
    }

    /// Reports `done` units of work (rows); the caller's callback gets `(done, total)`.
    pub(crate) fn report(&self, done: u64) {
        let _ = self.progress.send(Msg::Progress(Report::Rows(done)));
    }

    /// The libraries' hook for this call: cancelled with it; each step reaches the caller's
    /// callback as `(phase, done, total)`.
    pub(crate) fn hook(&self) -> ism_format::Progress {
        let tx = self.progress.clone();
        ism_format::Progress::new(move |s| {
            let _ = tx.send(Msg::Progress(Report::Step(
                s.phase.to_string(),
                s.done,
                s.total,
            )));
        })
        .with_cancel(self.cancel.clone())
    }

    /// As [`Control::hook`] for `ism_fit::fit`, whose steps reach the callback as
    /// `(phase, simplices, worst)`.
    pub(crate) fn fit_hook(&self) -> ism_format::Progress {
        let tx = self.progress.clone();
        ism_format::Progress::new(move |s| {
            let _ = tx.send(Msg::Progress(Report::Fit(
                s.phase.to_string(),
                s.done,
                s.worst,
            )));
        })
        .with_cancel(self.cancel.clone())
    }
}

/// Runs `job` on a worker thread (with `threads` rayon workers when nonzero) and waits for it as
/// described in the module documentation. A panic in the job becomes `ism.InternalError`; after a
/// cancel the job's result is dropped and the pending exception raised.
pub(crate) fn run<T: Send + 'static>(
    py: Python<'_>,
    threads: usize,
    progress: Option<(&Bound<'_, PyAny>, u64)>,
    job: impl FnOnce(&Control) -> T + Send + 'static,
) -> PyResult<T> {
    let (tx, rx) = mpsc::channel::<Msg<T>>();
    let (ptx, prx) = mpsc::channel::<Msg<()>>();
    let control = Control {
        cancel: Arc::new(AtomicBool::new(false)),
        progress: ptx,
    };
    let cancel = control.cancel.clone();
    name_global_pool();
    let pool = if threads > 0 {
        Some(
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .thread_name(|i| format!("ism-pool-{i}"))
                .build()
                .map_err(|e| {
                    pyo3::exceptions::PyRuntimeError::new_err(format!(
                        "cannot start {threads} worker threads: {e}"
                    ))
                })?,
        )
    } else {
        None
    };
    let handle = std::thread::Builder::new()
        .name("ism-worker".into())
        .spawn(move || {
            let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| match &pool {
                Some(pool) => pool.install(|| job(&control)),
                None => job(&control),
            }));
            let _ = tx.send(Msg::Done(result));
        })
        .map_err(|e| {
            pyo3::exceptions::PyRuntimeError::new_err(format!("cannot start a thread: {e}"))
        })?;
    let mut handle = Some(handle);

    let mut pending: Option<PyErr> = None;
    // A `Receiver` is `Send` but not `Sync`: it moves into the GIL-free closure and back.
    let mut rx = Some(rx);
    loop {
        let (back, msg) = py.allow_threads(|| {
            let r = rx
                .take()
                .expect("the receiver is put back after every wait");
            let msg = r.recv_timeout(POLL);
            (r, msg)
        });
        rx = Some(back);
        if matches!(msg, Ok(Msg::Done(_))) {
            // The worker sent its last message: wait for it to end, so that no thread of this
            // call outlives it.
            if let Some(h) = handle.take() {
                let _ = py.allow_threads(|| h.join());
            }
        }
        // Progress first: every report that arrived, newest last.
        while let Ok(Msg::Progress(report)) = prx.try_recv() {
            if let (Some((callback, total)), None) = (&progress, &pending) {
                let called = match report {
                    Report::Rows(done) => callback.call1((done, *total)),
                    Report::Fit(phase, simplices, worst) => {
                        callback.call1((phase, simplices, worst))
                    }
                    Report::Step(phase, done, total) => callback.call1((phase, done, total)),
                };
                if let Err(e) = called {
                    cancel.store(true, Ordering::Relaxed);
                    pending = Some(e);
                }
            }
        }
        match msg {
            Ok(Msg::Done(Ok(value))) => {
                return match pending {
                    Some(e) => Err(e),
                    None => Ok(value),
                }
            }
            Ok(Msg::Done(Err(payload))) => return Err(crate::errors::panic_error(py, &*payload)),
            Ok(Msg::Progress(_)) => {}
            Err(mpsc::RecvTimeoutError::Timeout) => {
                if pending.is_none() {
                    if let Err(e) = py.check_signals() {
                        cancel.store(true, Ordering::Relaxed);
                        pending = Some(e);
                    }
                }
            }
            Err(mpsc::RecvTimeoutError::Disconnected) => {
                return Err(pyo3::exceptions::PyRuntimeError::new_err(
                    "the ISM worker thread ended without a result",
                ))
            }
        }
    }
}

/// Names rayon's global pool's threads. The pool is created lazily by the first thread that uses
/// it, and a Linux thread inherits its creator's name: created from an `ism-worker` thread, its
/// long-lived threads would carry that name and look like workers left behind by a call.
fn name_global_pool() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        // An error means the pool already exists (another library built it): nothing to name.
        let _ = rayon::ThreadPoolBuilder::new()
            .thread_name(|i| format!("ism-rayon-{i}"))
            .build_global();
    });
}

//! Long calls off the interpreter's thread: the GIL is released, Ctrl-C is honoured, an optional
//! progress callback runs on the caller's thread.
//!
//! The libraries have no cancellation hook. So each long call runs on a worker thread while the
//! calling thread waits with the GIL released, waking every [`POLL`] to run Python's signal
//! handlers (`PyErr_CheckSignals`) and the progress callback. On `KeyboardInterrupt` (or an
//! exception from the callback) the cancel flag is set and:
//! - jobs that stream through a sink (sampling, queries) see the flag at their next block of rows
//!   and stop; the caller waits for that, so no work continues;
//! - other jobs (validation, extraction, fitting) cannot be stopped: the exception is raised at
//!   once and the worker finishes in the background, its result dropped.

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

/// A progress report: rows done (sampling, queries; the callback gets `(done, total)`) or a fit's
/// phase (the callback gets `(phase, simplices, worst)`).
enum Report {
    Rows(u64),
    Phase(&'static str, usize, f64),
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

    /// Reports a fit's phase; the caller's callback gets `(phase, simplices, worst)`.
    pub(crate) fn report_phase(&self, phase: &'static str, simplices: usize, worst: f64) {
        let _ = self
            .progress
            .send(Msg::Progress(Report::Phase(phase, simplices, worst)));
    }
}

/// Whether a job stops when cancelled (see the module documentation).
#[derive(Clone, Copy, PartialEq, Eq)]
pub(crate) enum Stop {
    /// The job polls [`Control::cancelled`]: wait for it to return.
    Polls,
    /// The job cannot be stopped: return at once, let it finish in the background.
    Detach,
}

/// Runs `job` on a worker thread (with `threads` rayon workers when nonzero) and waits for it as
/// described in the module documentation. A panic in the job becomes `ism.InternalError`.
pub(crate) fn run<T: Send + 'static>(
    py: Python<'_>,
    threads: usize,
    stop: Stop,
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
    let pool = if threads > 0 {
        Some(
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
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
    std::thread::Builder::new()
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
        // Progress first: every report that arrived, newest last.
        while let Ok(Msg::Progress(report)) = prx.try_recv() {
            if let (Some((callback, total)), None) = (&progress, &pending) {
                let called = match report {
                    Report::Rows(done) => callback.call1((done, *total)),
                    Report::Phase(phase, simplices, worst) => {
                        callback.call1((phase, simplices, worst))
                    }
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
                if stop == Stop::Detach {
                    if let Some(e) = pending.take() {
                        return Err(e);
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

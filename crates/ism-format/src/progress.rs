//! The progress and cancel hook of long calls: one type for every library (validation,
//! extraction, export, fitting, smoothing, sampling) and every front end (the CLI's progress
//! display, the Python package's callbacks and Ctrl-C).
//!
//! A [`Progress`] carries an optional callback, which receives a [`Step`] now and then (from
//! worker threads, in no particular order within a phase), and an optional cancel flag. A long
//! call polls [`Progress::check`] between units of work and returns [`Cancelled`] (wrapped in its
//! own error type) soon after the flag is set: the work really stops, nothing runs on in the
//! background. [`Progress::none`] (the default) reports nothing and is never cancelled.
//!
//! It lives in the lowest crate because every library above uses it; it knows nothing of files.
//!
//! ```
//! use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
//! use std::sync::Arc;
//! use ism_format::progress::{Cancelled, Progress};
//!
//! // A callback that counts reports, and a flag the caller (e.g. a Ctrl-C handler) can set.
//! let reports = Arc::new(AtomicU64::new(0));
//! let seen = reports.clone();
//! let flag = Arc::new(AtomicBool::new(false));
//! let progress = Progress::new(move |_step| {
//!     seen.fetch_add(1, Ordering::Relaxed);
//! })
//! .with_cancel(flag.clone());
//!
//! let counter = progress.phase("items", 10);
//! counter.add(10);
//! assert!(reports.load(Ordering::Relaxed) >= 2); // the phase's start and its end
//! assert_eq!(progress.check(), Ok(()));
//! flag.store(true, Ordering::Relaxed);
//! assert_eq!(progress.check(), Err(Cancelled));
//! ```

use std::fmt;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;

/// One report of a long call.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Step<'a> {
    /// What is being done: a phase name the call documents.
    pub phase: &'a str,
    /// Units of the phase done so far (rows, simplices, patches, sweeps; the call says which).
    pub done: u64,
    /// Units of the phase in all; 0 when not known in advance.
    pub total: u64,
    /// The largest error so far, for phases that measure one (fits); NaN otherwise.
    pub worst: f64,
}

/// A long call stopped because its [`Progress`] was cancelled.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
#[error("cancelled")]
pub struct Cancelled;

type Callback = dyn Fn(&Step<'_>) + Send + Sync;

/// A long call's hook: an optional progress callback and an optional cancel flag (see the module
/// documentation). Cheap to clone (two reference counts).
#[derive(Clone, Default)]
pub struct Progress {
    callback: Option<Arc<Callback>>,
    cancel: Option<Arc<AtomicBool>>,
}

impl fmt::Debug for Progress {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Progress")
            .field("callback", &self.callback.is_some())
            .field("cancelled", &self.is_cancelled())
            .finish()
    }
}

/// Units between two reports of a [`Counter`]: often enough for a display, rare enough to cost
/// nothing next to the unit's own work.
pub const REPORT_STRIDE: u64 = 64;

impl Progress {
    /// No reports, never cancelled.
    pub fn none() -> Progress {
        Progress::default()
    }

    /// Reports every [`Step`] to `callback` (called from worker threads; keep it quick).
    pub fn new(callback: impl Fn(&Step<'_>) + Send + Sync + 'static) -> Progress {
        Progress {
            callback: Some(Arc::new(callback)),
            cancel: None,
        }
    }

    /// The same hook, cancelled when `flag` is set.
    pub fn with_cancel(mut self, flag: Arc<AtomicBool>) -> Progress {
        self.cancel = Some(flag);
        self
    }

    /// Whether the caller asked the call to stop.
    pub fn is_cancelled(&self) -> bool {
        self.cancel
            .as_ref()
            .is_some_and(|c| c.load(Ordering::Relaxed))
    }

    /// `Err(Cancelled)` once the caller asked the call to stop.
    ///
    /// # Errors
    /// [`Cancelled`] when the cancel flag is set.
    pub fn check(&self) -> Result<(), Cancelled> {
        if self.is_cancelled() {
            Err(Cancelled)
        } else {
            Ok(())
        }
    }

    /// Passes `step` to the callback, if any.
    pub fn report(&self, step: &Step<'_>) {
        if let Some(cb) = &self.callback {
            cb(step);
        }
    }

    /// Reports `(phase, done, total)` with no error measure.
    pub fn report_count(&self, phase: &str, done: u64, total: u64) {
        self.report(&Step {
            phase,
            done,
            total,
            worst: f64::NAN,
        });
    }

    /// Starts a counted phase of `total` units (reports `done = 0` now); the counter reports
    /// every [`REPORT_STRIDE`]-th unit and the last.
    pub fn phase<'a>(&'a self, name: &'a str, total: u64) -> Counter<'a> {
        self.report_count(name, 0, total);
        Counter {
            progress: self,
            name,
            total,
            done: AtomicU64::new(0),
        }
    }
}

/// Counts finished units of one phase from any thread (see [`Progress::phase`]).
#[derive(Debug)]
pub struct Counter<'a> {
    progress: &'a Progress,
    name: &'a str,
    total: u64,
    done: AtomicU64,
}

impl Counter<'_> {
    /// Adds `units` finished units; reports when a multiple of [`REPORT_STRIDE`] is crossed or
    /// the total is reached.
    pub fn add(&self, units: u64) {
        let before = self.done.fetch_add(units, Ordering::Relaxed);
        let after = before + units;
        if after / REPORT_STRIDE != before / REPORT_STRIDE || after == self.total {
            self.progress.report_count(self.name, after, self.total);
        }
    }

    /// Whether the caller asked the call to stop (as [`Progress::is_cancelled`]).
    pub fn is_cancelled(&self) -> bool {
        self.progress.is_cancelled()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Mutex;

    #[test]
    fn counter_reports_start_strides_and_end() {
        let steps = Arc::new(Mutex::new(Vec::new()));
        let s = steps.clone();
        let p = Progress::new(move |st| s.lock().unwrap().push((st.phase.to_string(), st.done)));
        let c = p.phase("x", 130);
        for _ in 0..130 {
            c.add(1);
        }
        let got = steps.lock().unwrap().clone();
        let want: Vec<(String, u64)> = [0, 64, 128, 130]
            .iter()
            .map(|&d| ("x".to_string(), d))
            .collect();
        assert_eq!(got, want);
    }

    #[test]
    fn none_is_never_cancelled_and_flag_cancels() {
        assert_eq!(Progress::none().check(), Ok(()));
        let flag = Arc::new(AtomicBool::new(false));
        let p = Progress::none().with_cancel(flag.clone());
        assert!(!p.is_cancelled());
        flag.store(true, Ordering::Relaxed);
        assert!(p.is_cancelled());
        assert_eq!(p.clone().check(), Err(Cancelled));
    }
}

//! Progress on standard error: each phase named, the elapsed time, and a count where the work is
//! counted — never an estimate of the time left (a phase's rate is not known in advance, and an
//! early rate extrapolated over a later phase misleads). Shown only on a terminal and without `-q`.

use std::io::IsTerminal;
use std::time::Duration;

use indicatif::{ProgressBar, ProgressStyle};

/// A progress display, or nothing (not a terminal, or `-q`).
pub(crate) struct Progress {
    bar: Option<ProgressBar>,
}

impl Progress {
    /// A spinner that keeps turning while a phase runs (so a long library call without callbacks
    /// still shows life).
    pub(crate) fn new(quiet: bool) -> Progress {
        if quiet || !std::io::stderr().is_terminal() {
            return Progress { bar: None };
        }
        let bar = ProgressBar::new_spinner();
        bar.set_style(spinner_style());
        bar.enable_steady_tick(Duration::from_millis(120));
        Progress { bar: Some(bar) }
    }

    /// Starts the phase `name` (e.g. "reading model.ismb").
    pub(crate) fn phase(&self, name: impl Into<String>) {
        if let Some(bar) = &self.bar {
            bar.set_style(spinner_style());
            bar.set_message(name.into());
            // Past the rate limit: a phase shorter than the refresh interval is still named.
            bar.force_draw();
        }
    }

    /// Starts a counted phase of `total` `unit`s (e.g. "points"); returns a handle whose
    /// [`Counter::set`] may be called from worker threads.
    pub(crate) fn counted(&self, name: &str, total: u64, unit: &str) -> Counter {
        if let Some(bar) = &self.bar {
            // Position first, then the new style, then the length: a redraw between the calls
            // never shows the previous phase's count against the new total.
            bar.set_position(0);
            let template =
                format!("{{spinner}} {name} {{bar:30}} {{pos}}/{{len}} {unit} [{{elapsed}}]");
            if let Ok(style) = ProgressStyle::with_template(&template) {
                bar.set_style(style);
            }
            bar.set_length(total);
            bar.force_draw();
        }
        Counter {
            bar: self.bar.clone(),
        }
    }

    /// Runs `f` (which prints) with the display hidden, then shows it again.
    pub(crate) fn suspend<R>(&self, f: impl FnOnce() -> R) -> R {
        match &self.bar {
            Some(bar) => bar.suspend(f),
            None => f(),
        }
    }

    /// Removes the display (before the command prints its results).
    pub(crate) fn finish(&self) {
        if let Some(bar) = &self.bar {
            bar.finish_and_clear();
        }
    }
}

impl Drop for Progress {
    fn drop(&mut self) {
        self.finish();
    }
}

/// The count of a [`Progress::counted`] phase.
#[derive(Clone)]
pub(crate) struct Counter {
    bar: Option<ProgressBar>,
}

impl Counter {
    /// `done` units so far.
    pub(crate) fn set(&self, done: u64) {
        if let Some(bar) = &self.bar {
            bar.set_position(done);
        }
    }
}

fn spinner_style() -> ProgressStyle {
    ProgressStyle::with_template("{spinner} {msg} [{elapsed}]")
        .unwrap_or_else(|_| ProgressStyle::default_spinner())
}

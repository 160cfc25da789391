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
            show_phase(bar, name);
        }
    }

    /// Starts a counted phase of `total` `unit`s (e.g. "points"); returns a handle whose
    /// [`Counter::set`] may be called from worker threads.
    pub(crate) fn counted(&self, name: &str, total: u64, unit: &str) -> Counter {
        if let Some(bar) = &self.bar {
            show_counted(bar, name, total, unit);
        }
        Counter {
            bar: self.bar.clone(),
        }
    }

    /// The libraries' progress hook showing on this display: an uncounted step (`total` 0) names
    /// its phase, a counted one gets a bar labelled with the phase and `unit(phase)` (restarted
    /// at each step with `done` 0, the start of a phase).
    pub(crate) fn hook(&self, unit: fn(&str) -> &'static str) -> ism_format::Progress {
        let Some(bar) = self.bar.clone() else {
            return ism_format::Progress::none();
        };
        // The phase shown (name and total): a new one restyles the display.
        let current: std::sync::Mutex<(String, u64)> = std::sync::Mutex::new((String::new(), 0));
        ism_format::Progress::new(move |step| {
            let mut cur = current.lock().unwrap_or_else(|e| e.into_inner());
            if cur.0 != step.phase || cur.1 != step.total || step.done == 0 {
                *cur = (step.phase.to_string(), step.total);
                if step.total == 0 {
                    show_phase(&bar, step.phase);
                } else {
                    show_counted(&bar, step.phase, step.total, unit(step.phase));
                }
            }
            if step.total > 0 {
                bar.set_position(step.done);
            }
        })
    }

    /// The libraries' progress hook showing each step as the phase `message(step)`.
    pub(crate) fn message_hook(
        &self,
        message: impl Fn(&ism_format::progress::Step<'_>) -> String + Send + Sync + 'static,
    ) -> ism_format::Progress {
        let Some(bar) = self.bar.clone() else {
            return ism_format::Progress::none();
        };
        ism_format::Progress::new(move |step| show_phase(&bar, message(step)))
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

fn show_phase(bar: &ProgressBar, name: impl Into<String>) {
    bar.set_style(spinner_style());
    bar.set_message(name.into());
    // Past the rate limit: a phase shorter than the refresh interval is still named.
    bar.force_draw();
}

fn show_counted(bar: &ProgressBar, name: &str, total: u64, unit: &str) {
    // Position first, then the new style, then the length: a redraw between the calls never
    // shows the previous phase's count against the new total.
    bar.set_position(0);
    let template = format!("{{spinner}} {name} {{bar:30}} {{pos}}/{{len}} {unit} [{{elapsed}}]");
    if let Ok(style) = ProgressStyle::with_template(&template) {
        bar.set_style(style);
    }
    bar.set_length(total);
    bar.force_draw();
}

fn spinner_style() -> ProgressStyle {
    ProgressStyle::with_template("{spinner} {msg} [{elapsed}]")
        .unwrap_or_else(|_| ProgressStyle::default_spinner())
}

//! The crate's error type.

use std::path::PathBuf;

use crate::rules::{Diagnostic, Location, Rule};

/// Why reading or writing an ISM failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    /// The operating system refused a read or write.
    #[error("I/O error{}: {error}", path.as_ref().map(|p| format!(" on {}", p.display())).unwrap_or_default())]
    Io {
        /// The file, when known.
        path: Option<PathBuf>,
        /// The underlying error.
        error: std::io::Error,
    },
    /// The bytes break a requirement of the container or encoding (spec §7).
    #[error("{0}")]
    Format(Box<Diagnostic>),
    /// The decoded model breaks structural requirements (spec §2–5); all errors found are listed.
    #[error("{} structural error(s); first: {}", .0.len(), .0.first().map(|d| d.to_string()).unwrap_or_default())]
    Structure(Vec<Diagnostic>),
    /// The model was read without its face records' control points and weights
    /// ([`crate::io::ReadOptions::keep_record_numbers`] off, for summaries such as `ism info`), so it
    /// cannot be written or indexed.
    #[error("stage {stage}'s face records were read without their control points and weights (ReadOptions::keep_record_numbers); read the file again keeping them to {action} it")]
    NumbersNotKept {
        /// The first such stage.
        stage: usize,
        /// What was asked: "write" or "index".
        action: &'static str,
    },
}

impl Error {
    pub(crate) fn format(rule: Rule, location: Location, message: impl Into<String>) -> Error {
        Error::Format(Box::new(Diagnostic::new(rule, location, message)))
    }

    /// [`Error::NumbersNotKept`] for the first stage of `model` whose table was read without its
    /// numbers, if any.
    pub(crate) fn unless_numbers_kept(model: &crate::Model, action: &'static str) -> Result<()> {
        match model.stages.iter().position(|s| !s.faces.numbers_kept()) {
            Some(stage) => Err(Error::NumbersNotKept { stage, action }),
            None => Ok(()),
        }
    }

    pub(crate) fn io(path: Option<PathBuf>, source: std::io::Error) -> Error {
        Error::Io {
            path,
            error: source,
        }
    }

    /// The diagnostics this error carries (empty for I/O errors).
    pub fn diagnostics(&self) -> &[Diagnostic] {
        match self {
            Error::Io { .. } | Error::NumbersNotKept { .. } => &[],
            Error::Format(d) => std::slice::from_ref(d),
            Error::Structure(list) => list,
        }
    }

    /// The first rule violated, if any.
    pub fn rule(&self) -> Option<Rule> {
        self.diagnostics().first().map(|d| d.rule)
    }
}

/// Shorthand for this crate's results.
pub type Result<T, E = Error> = std::result::Result<T, E>;

/// An error and its causes as one line, outermost first, joined by `": "` — how the `ism` CLI
/// and the Python package print every error.
///
/// The workspace's error types follow the Rust API guidelines' rule for wrapped errors: a variant
/// that carries a cause returns it from [`std::error::Error::source`] and does not repeat it in its
/// own message, so printing only `{err}` shows the outermost context and printing the chain shows
/// each cause exactly once.
///
/// ```
/// use ism_format::ErrorChain;
///
/// #[derive(Debug, thiserror::Error)]
/// #[error("cannot write out.obj")]
/// struct Write(#[source] std::io::Error);
///
/// let err = Write(std::io::Error::other("disk full"));
/// assert_eq!(err.to_string(), "cannot write out.obj");
/// assert_eq!(ErrorChain(&err).to_string(), "cannot write out.obj: disk full");
/// ```
///
/// This crate's own [`Error`] carries no cause: its I/O variant names the operating system's
/// error in its message, so its chain is its message.
#[derive(Clone, Copy)]
pub struct ErrorChain<'a>(pub &'a (dyn std::error::Error + 'static));

impl std::fmt::Display for ErrorChain<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}", self.0)?;
        let mut cause = self.0.source();
        while let Some(c) = cause {
            write!(f, ": {c}")?;
            cause = c.source();
        }
        Ok(())
    }
}

impl std::fmt::Debug for ErrorChain<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        std::fmt::Display::fmt(self, f)
    }
}

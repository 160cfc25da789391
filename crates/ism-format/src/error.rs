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
}

impl Error {
    pub(crate) fn format(rule: Rule, location: Location, message: impl Into<String>) -> Error {
        Error::Format(Box::new(Diagnostic::new(rule, location, message)))
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
            Error::Io { .. } => &[],
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

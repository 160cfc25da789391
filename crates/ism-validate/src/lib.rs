//! The ISM validator: structure, invariance and certified positivity of every stage.
//!
//! [`validate`] runs the layers of `spec/validation.md` on a [`Model`] and returns a [`Report`] —
//! the same data `ism validate --json` prints:
//!
//! 1. **Structure** (ISM-1xx): the reader's checks of `ism_format::structure`, plus non-manifold
//!    vertices and edges (ISM-150, warnings).
//! 2. **Invariance** (ISM-201..204): stored control points in their open faces, positive weights,
//!    increasing monotonic coefficients.
//! 3. **Positivity** (ISM-301/302): `det DX > 0` on every closed top simplex for every stage — by a
//!    named theorem when one applies, otherwise by Bernstein coefficients with rigorous rounding
//!    bounds and adaptive subdivision. Each element is valid (with its certificate), invalid (with a
//!    witness point and `det` value) or undetermined (never counted as valid).
//! 4. **Quality** (ISM-401..403, with [`Options::quality`]): C¹ residual of rational stages, normal
//!    jumps of the shape across facets, range of `det DX`.
//!
//! ```
//! use ism_format::builder::{ModelBuilder, StageBuilder};
//! use ism_validate::{validate, Options, Verdict};
//!
//! let square = |stage| {
//!     ModelBuilder::new(2)
//!         .vertex(&[0.0, 0.0], -1.0)
//!         .vertex(&[1.0, 0.0], 1.0)
//!         .vertex(&[1.0, 1.0], 1.0)
//!         .vertex(&[0.0, 1.0], 1.0)
//!         .simplex(&[0, 1, 2])
//!         .simplex(&[0, 2, 3])
//!         .stage(stage)
//!         .build_unchecked()
//! };
//! // A quadratic stage bending the diagonal: certified by Mello & Velho 2009 Prop. 5.6.
//! let report = validate(&square(StageBuilder::bezier(2).face(&[0, 2], &[0.6, 0.4], &[]).build()), &Options::default());
//! assert_eq!(report.verdict, Verdict::Valid);
//! assert_eq!(report.stages[0].certificates["Mello & Velho 2009 Prop. 5.6: adjusted quadratic"], 2);
//!
//! // A quartic stage whose edge points cross over (Mello & Velho 2009 Fig. 2): det DX < 0 somewhere, with a witness.
//! let folded = StageBuilder::bezier(4).face(&[0, 2], &[0.1, 0.9, 0.5, 0.5, 0.9, 0.1], &[]).build();
//! let report = validate(&square(folded), &Options::default());
//! assert_eq!(report.verdict, Verdict::Invalid);
//! let message = &report.issues.messages[0];
//! assert_eq!(message.code, "ISM-301");
//! assert!(message.witness.as_ref().unwrap().det <= 0.0);
//! ```
#![deny(missing_docs)]

pub mod certify;
pub mod exact;
pub mod invariance;
pub mod net;
pub mod positivity;
pub mod quality;
pub mod report;
pub mod theorem;
pub mod topology;
pub mod twofold;

#[cfg(test)]
mod test_support;

use std::path::Path;
use std::time::Instant;

use ism_format::progress::{Cancelled, Progress};
use ism_format::{io, IndexedModel, Model, Rule, Severity};

pub use certify::{Budget, Certificate, Decision, DenseNet, DetKernel, DEFAULT_MAX_PIECES};
pub use report::{
    Message, NormalJumps, QualityStats, Report, StageReport, Verdict, Witness, REPORT_VERSION,
};

/// Default cap on the messages a report lists (all are counted).
pub const DEFAULT_MAX_ISSUES: usize = 100;

/// Settings of a validation run.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Options {
    /// Most messages listed in the report (all are counted).
    pub max_issues: usize,
    /// Worker threads; 0 uses rayon's global pool (all cores).
    pub threads: usize,
    /// Floating-point pieces per element of the positivity certificate (the exact path gets a
    /// sixteenth as many; see [`Budget`]).
    pub max_pieces: usize,
    /// Run the quality layer.
    pub quality: bool,
    /// Use theorems where they apply (off: certify every touched simplex numerically).
    pub theorems: bool,
    /// Resource limits of the read, for the functions that read ([`validate_path`],
    /// [`validate_bytes`] and their `_with_progress` forms): a file past one is unreadable
    /// (ISM-007, naming the payload or the member). A service validating files from
    /// anyone lowers them; the defaults refuse nothing a readable file can hold.
    pub limits: io::Limits,
}

impl Default for Options {
    fn default() -> Self {
        Options {
            max_issues: DEFAULT_MAX_ISSUES,
            threads: 0,
            max_pieces: DEFAULT_MAX_PIECES,
            quality: false,
            theorems: true,
            limits: io::Limits::default(),
        }
    }
}

/// Why a file could not be validated at all.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    /// The file could not be read.
    #[error("cannot read {}", path.display())]
    Io {
        /// The file.
        path: std::path::PathBuf,
        /// The operating system's error.
        source: std::io::Error,
    },
    /// The file is not a readable ISM (I/O, container or encoding; spec ISM-0xx).
    #[error("unreadable")]
    Read(#[from] ism_format::Error),
    /// The caller cancelled the run through its [`Progress`].
    #[error(transparent)]
    Cancelled(#[from] Cancelled),
    /// The worker pool could not be started.
    #[error("cannot start {threads} worker threads: {message}")]
    Threads {
        /// Threads asked for.
        threads: usize,
        /// The pool builder's error.
        message: String,
    },
}

/// Validates a model in memory (indexing a copy of it; [`validate_indexed`] shares an indexed
/// model instead).
pub fn validate(model: &Model, options: &Options) -> Report {
    uncancelled(validate_with_progress(model, options, &Progress::none()))
}

/// Validates a structurally checked, indexed model (no copy).
pub fn validate_indexed(model: &IndexedModel, options: &Options) -> Report {
    uncancelled(validate_indexed_with_progress(
        model,
        options,
        &Progress::none(),
    ))
}

/// The phase [`validate_with_progress`] reports per stage, counted in simplices.
pub const POSITIVITY_PHASE: &str = "certifying the positivity of det DX";

/// [`validate`] with a progress and cancel hook: the positivity layer reports
/// [`POSITIVITY_PHASE`] per stage, and a cancelled hook stops the run within one simplex per
/// worker thread (and between layers).
///
/// # Errors
/// [`Cancelled`] when `progress` was cancelled.
pub fn validate_with_progress(
    model: &Model,
    options: &Options,
    progress: &Progress,
) -> Result<Report, Cancelled> {
    in_pool(options, || validate_owned(model.clone(), options, progress))
}

/// [`validate_indexed`] with a progress and cancel hook (see [`validate_with_progress`]).
///
/// # Errors
/// [`Cancelled`] when `progress` was cancelled.
pub fn validate_indexed_with_progress(
    model: &IndexedModel,
    options: &Options,
    progress: &Progress,
) -> Result<Report, Cancelled> {
    in_pool(options, || run(model, Some(model), options, progress))
}

/// The report of a run that had no cancel flag.
fn uncancelled(r: Result<Report, Cancelled>) -> Report {
    match r {
        Ok(report) => report,
        Err(Cancelled) => unreachable!("Progress::none() is never cancelled"),
    }
}

/// Indexes `model` (the structural check runs once) and validates it; a model that cannot be
/// indexed gets the structural layer's report.
fn validate_owned(
    model: Model,
    options: &Options,
    progress: &Progress,
) -> Result<Report, Cancelled> {
    // The face tables are built only if a layer needs them (a stage not decided by a theorem
    // from its records alone, or the quality layer).
    match IndexedModel::new_lazy_or_model(model) {
        Ok(indexed) => run(&indexed, Some(&indexed), options, progress),
        Err((model, _)) => run(&model, None, options, progress),
    }
}

fn in_pool<T: Send>(options: &Options, job: impl FnOnce() -> T + Send) -> T {
    if options.threads == 0 {
        return job();
    }
    match rayon::ThreadPoolBuilder::new()
        .num_threads(options.threads)
        .build()
    {
        Ok(pool) => pool.install(job),
        // Falling back to the global pool only changes speed, never the result.
        Err(_) => job(),
    }
}

/// Reads and validates a file (any encoding). Structural problems are reported, not returned as
/// errors; only unreadable input is an error.
///
/// # Errors
/// [`Error::Io`] when the file cannot be read, [`Error::Read`] when its bytes are not a readable
/// ISM container or encoding.
pub fn validate_path(path: impl AsRef<Path>, options: &Options) -> Result<Report, Error> {
    validate_path_with_progress(path, options, &Progress::none())
}

/// [`validate_path`] with a progress and cancel hook (see [`validate_with_progress`]).
///
/// # Errors
/// As [`validate_path`]; [`Error::Cancelled`] when `progress` was cancelled.
pub fn validate_path_with_progress(
    path: impl AsRef<Path>,
    options: &Options,
    progress: &Progress,
) -> Result<Report, Error> {
    let path = path.as_ref();
    let file = std::fs::File::open(path).map_err(|source| Error::Io {
        path: path.to_path_buf(),
        source,
    })?;
    // Streamed: a binary file is decoded as it arrives, never held whole beside its model.
    let read = io::ReadOptions {
        check_structure: false,
        limits: options.limits,
        ..io::ReadOptions::default()
    };
    let doc = io::read_with(file, &read).map_err(|e| match e {
        // An operating-system error stays one, naming the path (as when the file was read whole).
        ism_format::Error::Io { error, .. } => Error::Io {
            path: path.to_path_buf(),
            source: error,
        },
        other => Error::Read(other),
    })?;
    let mut report = validate_document(doc, options, progress)?;
    if let Some(file) = &mut report.file {
        file.path = path.display().to_string();
    }
    Ok(report)
}

/// Reads and validates bytes (any encoding); see [`validate_path`].
///
/// # Errors
/// [`Error::Read`] when the bytes are not a readable ISM.
pub fn validate_bytes(bytes: &[u8], options: &Options) -> Result<Report, Error> {
    validate_bytes_with_progress(bytes, options, &Progress::none())
}

/// [`validate_bytes`] with a progress and cancel hook (see [`validate_with_progress`]).
///
/// # Errors
/// As [`validate_bytes`]; [`Error::Cancelled`] when `progress` was cancelled.
pub fn validate_bytes_with_progress(
    bytes: &[u8],
    options: &Options,
    progress: &Progress,
) -> Result<Report, Error> {
    let read = io::ReadOptions {
        check_structure: false,
        limits: options.limits,
        ..io::ReadOptions::default()
    };
    let doc = io::from_slice_with(bytes, &read)?;
    validate_document(doc, options, progress)
}

/// Validates a decoded (not yet structurally checked) document.
fn validate_document(
    doc: io::Document,
    options: &Options,
    progress: &Progress,
) -> Result<Report, Error> {
    let (encoding, byte_len) = (doc.encoding, doc.byte_len);
    let mut report = in_pool(options, || validate_owned(doc.model, options, progress))?;
    report.file = Some(report::FileInfo {
        path: String::new(),
        encoding: encoding.name().to_string(),
        bytes: byte_len,
    });
    Ok(report)
}

/// The four layers; `indexed` is the model's index when it passed the structural check (then the
/// check is not repeated), `None` when it did not.
fn run(
    model: &Model,
    indexed: Option<&IndexedModel>,
    options: &Options,
    progress: &Progress,
) -> Result<Report, Cancelled> {
    let mut out = report::Collector::new(options.max_issues);
    let mut timing = report::Timing::default();
    let mut stages = Vec::new();

    // Layer 1.
    let t = Instant::now();
    let structural = match indexed {
        Some(ix) => ix.diagnostics().to_vec(),
        None => ism_format::structure::check(model, usize::MAX),
    };
    let structure_ok =
        indexed.is_some() && !structural.iter().any(|d| d.severity == Severity::Error);
    let indexable = !structural.iter().any(|d| {
        matches!(
            d.rule,
            Rule::Dimension
                | Rule::VertexArray
                | Rule::SimplexArray
                | Rule::IndexRange
                | Rule::RepeatedIndex
        )
    });
    for d in structural {
        out.push(d.into());
    }
    if indexable {
        let found = match indexed {
            // Without structural errors, the stars alone decide (no face tables needed).
            Some(ix) if structure_ok => topology::non_manifold_stars(ix),
            Some(ix) => topology::non_manifold_indexed(ix),
            None => topology::non_manifold(model),
        };
        for m in found {
            out.push(m);
        }
    }
    timing.structure = t.elapsed().as_secs_f64();
    progress.check()?;

    // Layer 2, per stage.
    let t = Instant::now();
    let mut stage_ok = vec![structure_ok; model.stages.len()];
    if structure_ok {
        for (k, ok) in stage_ok.iter_mut().enumerate() {
            let found = invariance::check_stage(model, k);
            *ok = found.is_empty();
            for m in found {
                out.push(m);
            }
        }
    }
    timing.invariance = t.elapsed().as_secs_f64();
    progress.check()?;

    // Layer 3.
    let t = Instant::now();
    let popts = positivity::PositivityOptions {
        budget: certify::Budget::new(options.max_pieces),
        theorems: options.theorems,
    };
    let mut positivity_messages = Vec::new();
    let mut quality_stats = report::QualityStats::default();
    for (k, stage) in model.stages.iter().enumerate() {
        if !stage_ok[k] {
            stages.push(StageReport {
                index: k,
                kind: stage.kind.as_str().to_string(),
                degree: stage.degree,
                direction: positivity::direction_name(stage.direction).to_string(),
                status: "skipped".into(),
                skipped_because: Some(
                    if structure_ok {
                        "invariance errors in this stage"
                    } else {
                        "structural errors"
                    }
                    .into(),
                ),
                ..StageReport::default()
            });
            continue;
        }
        let Some(ix) = indexed else {
            unreachable!("stage_ok implies structure_ok, which implies an index")
        };
        let outcome = positivity::check_stage_with_progress(ix, k, popts, progress)?;
        stages.push(outcome.report);
        positivity_messages.extend(outcome.messages);
    }
    for m in positivity_messages {
        out.push(m);
    }
    timing.positivity = t.elapsed().as_secs_f64();
    progress.check()?;

    // Layer 4.
    if let (true, Some(ix)) = (options.quality && structure_ok, indexed) {
        let t = Instant::now();
        let (found, stats) = quality::check(ix, &mut stages, &stage_ok);
        quality_stats = stats;
        for m in found {
            out.push(m);
        }
        timing.quality = t.elapsed().as_secs_f64();
    }

    let issues = out.finish();
    let verdict = if issues.num_errors == 0 {
        Verdict::Valid
    } else if issues.counts.iter().all(|(code, &c)| {
        c == 0
            || code == Rule::Undetermined.id()
            || Rule::from_id(code).is_none_or(|r| r.severity() != Severity::Error)
    }) {
        Verdict::Undetermined
    } else {
        Verdict::Invalid
    };
    Ok(Report {
        report_version: REPORT_VERSION.to_string(),
        validator: format!("ism-validate {}", env!("CARGO_PKG_VERSION")),
        file: None,
        model: report::ModelInfo {
            dimension: model.dimension,
            vertices: model.num_vertices(),
            simplices: model.num_simplices(),
            stages: model.stages.len(),
        },
        verdict,
        issues,
        stages,
        piece_budget: options.max_pieces,
        timing,
        quality: quality_stats,
    })
}

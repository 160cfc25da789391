//! Arguments shared by several subcommands, and value parsers that name what they expect (clap puts
//! the argument's name in front: `invalid value '0' for '--tolerance <T>': must be …`).

use std::path::Path;

/// `-j/--threads N`, the same spelling on every command that runs in parallel.
#[derive(clap::Args, Clone, Copy, Debug)]
pub(crate) struct Threads {
    /// Worker threads (0 or absent: all cores).
    #[arg(short = 'j', long = "threads", value_name = "N")]
    pub(crate) threads: Option<usize>,
}

impl Threads {
    /// The count to hand to rayon (0: all cores).
    pub(crate) fn count(self) -> usize {
        self.threads.unwrap_or(0)
    }

    /// Sizes rayon's global pool (used by the libraries' parallel loops).
    pub(crate) fn install(self) -> anyhow::Result<()> {
        self.build_global(false)
    }

    /// Sizes rayon's global pool as [`Threads::install`] does, the calling thread being one of
    /// its threads: parallel loops then start on this thread instead of being handed to a worker
    /// and waited for, and `-j 1` starts no thread at all. For a small model (the spec examples)
    /// that is a measurable share of the whole process: `ism export`'s handoffs of `-j 1` through a
    /// separate worker cost ~100 futex and ~35 `sched_yield` calls, and that worker's malloc arena
    /// ~170 `mprotect` calls (`strace -f -c`, sphere example at 1e-3; issue 19, session 24). Only
    /// for a command none of whose library calls uses `rayon::spawn`, which the calling thread
    /// would not pick up unless it waits in a join.
    pub(crate) fn install_on_calling_thread(self) -> anyhow::Result<()> {
        self.build_global(true)
    }

    fn build_global(self, use_current_thread: bool) -> anyhow::Result<()> {
        if let Some(t) = self.threads.filter(|&t| t > 0) {
            let mut builder = rayon::ThreadPoolBuilder::new().num_threads(t);
            if use_current_thread {
                builder = builder.use_current_thread();
            }
            builder
                .build_global()
                .map_err(|e| anyhow::anyhow!("cannot start {t} worker threads: {e}"))?;
        }
        Ok(())
    }
}

/// `--max-payload-bytes`, `--max-vertices`, `--max-simplices`: the limits that apply to a mesh of
/// another format as well as to a model ([`ism_format::io::Limits`]; `ism import` takes only these,
/// a mesh having no stages).
#[derive(clap::Args, Clone, Copy, Debug, Default)]
#[command(next_help_heading = "Resource limits (refuse a file past one)")]
pub(crate) struct MeshLimits {
    /// Largest payload, in bytes [default: 8 GiB]
    #[arg(long, value_name = "BYTES")]
    pub(crate) max_payload_bytes: Option<u64>,
    /// Most vertices [default: 2^32 - 1]
    #[arg(long, value_name = "N")]
    pub(crate) max_vertices: Option<u64>,
    /// Most top simplices [default: 2^32 - 1]
    #[arg(long, value_name = "N")]
    pub(crate) max_simplices: Option<u64>,
}

impl MeshLimits {
    /// The limits: each given flag, the library's default for the others.
    pub(crate) fn limits(self) -> ism_format::io::Limits {
        let d = ism_format::io::Limits::default();
        ism_format::io::Limits {
            max_payload_bytes: self.max_payload_bytes.unwrap_or(d.max_payload_bytes),
            max_vertices: self.max_vertices.unwrap_or(d.max_vertices),
            max_simplices: self.max_simplices.unwrap_or(d.max_simplices),
            ..d
        }
    }
}

/// [`MeshLimits`] plus `--max-stages` and `--max-records`: the reader's resource limits
/// ([`ism_format::io::Limits`]), the same spelling on every command that reads a model. A pipeline
/// validating files from anyone caps what one file may cost; a file past a limit is unreadable
/// (exit 2, ISM-007 naming the payload or the member). Absent: the library's defaults, which
/// refuse nothing a readable file can hold.
#[derive(clap::Args, Clone, Copy, Debug, Default)]
#[command(next_help_heading = "Resource limits (refuse a file past one)")]
pub(crate) struct ReadLimits {
    #[command(flatten)]
    mesh: MeshLimits,
    /// Most stages [default: no limit]
    #[arg(long, value_name = "N")]
    max_stages: Option<u64>,
    /// Most face records and vertex maps over all stages [default: no limit]
    #[arg(long, value_name = "N")]
    max_records: Option<u64>,
}

impl ReadLimits {
    /// The limits: each given flag, the library's default for the others.
    pub(crate) fn limits(self) -> ism_format::io::Limits {
        let d = self.mesh.limits();
        ism_format::io::Limits {
            max_stages: self.max_stages.unwrap_or(d.max_stages),
            max_records: self.max_records.unwrap_or(d.max_records),
            ..d
        }
    }

    /// The reader's options: these limits, the library's defaults otherwise.
    fn options(self) -> ism_format::io::ReadOptions {
        ism_format::io::ReadOptions {
            limits: self.limits(),
            ..ism_format::io::ReadOptions::default()
        }
    }

    /// Reads and checks `path` within the limits; errors as [`cannot_read_model`].
    pub(crate) fn read(self, path: &Path) -> anyhow::Result<ism_format::Document> {
        ism_format::io::read_path_with(path, &self.options())
            .map_err(|e| cannot_read_model(path, e))
    }

    /// Reads a model within the limits and indexes it: the structural check runs once and its
    /// topology is kept for the evaluator (no copy of the model, no second check).
    pub(crate) fn read_indexed(
        self,
        path: &Path,
    ) -> anyhow::Result<ism_format::io::IndexedDocument> {
        ism_format::io::read_path_indexed_with(path, &self.options())
            .map_err(|e| cannot_read_model(path, e))
    }

    /// [`ReadLimits::read_indexed`] for a caller that looks up few face records or none (`ism
    /// export`): the same check and errors, the face tables built on first use
    /// ([`ism_format::io::read_path_indexed_lazily_with`]).
    pub(crate) fn read_indexed_lazily(
        self,
        path: &Path,
    ) -> anyhow::Result<ism_format::io::IndexedDocument> {
        ism_format::io::read_path_indexed_lazily_with(path, &self.options())
            .map_err(|e| cannot_read_model(path, e))
    }
}

fn number(s: &str) -> Result<f64, String> {
    s.trim()
        .parse::<f64>()
        .map_err(|_| format!("expected a number, found {s:?}"))
}

/// A finite number `> 0`.
pub(crate) fn positive(s: &str) -> Result<f64, String> {
    let x = number(s)?;
    if x.is_finite() && x > 0.0 {
        Ok(x)
    } else {
        Err(format!("must be a positive number, found {s}"))
    }
}

/// A finite number `≥ 0`.
pub(crate) fn non_negative(s: &str) -> Result<f64, String> {
    let x = number(s)?;
    if x.is_finite() && x >= 0.0 {
        Ok(x)
    } else {
        Err(format!("must be a number ≥ 0, found {s}"))
    }
}

/// `fit --resolution`: grid cells along the longest side, 1 to 512.
pub(crate) fn resolution(s: &str) -> Result<usize, String> {
    match s.trim().parse::<usize>() {
        Ok(r) if (1..=512).contains(&r) => Ok(r),
        _ => Err(format!("must be a whole number from 1 to 512, found {s}")),
    }
}

/// The operating system's reason for a failed write of `path`, without the temporary file's name
/// that `tempfile` puts in its messages (the caller names the destination once).
pub(crate) fn os_message(path: &Path, e: &std::io::Error) -> String {
    if let Some(code) = e.raw_os_error() {
        return std::io::Error::from_raw_os_error(code).to_string();
    }
    match e.kind() {
        // Our own writers' failures (`io::Error::other`) carry their message.
        std::io::ErrorKind::Other => e.to_string(),
        std::io::ErrorKind::NotFound => match path.parent() {
            Some(dir) if !dir.as_os_str().is_empty() && !dir.is_dir() => {
                format!("the directory {} does not exist", dir.display())
            }
            _ => e.kind().to_string(),
        },
        kind => kind.to_string(),
    }
}

/// `cannot write PATH: REASON` for an error of [`ism_format::io::write_atomic`].
pub(crate) fn cannot_write(path: &Path, e: &std::io::Error) -> anyhow::Error {
    anyhow::anyhow!("cannot write {}: {}", path.display(), os_message(path, e))
}

/// As [`cannot_write`] for an error of [`ism_format::io::write_path`]: an I/O failure shows only
/// the operating system's reason; an encoding failure keeps its own message.
pub(crate) fn cannot_write_model(path: &Path, e: ism_format::Error) -> anyhow::Error {
    match &e {
        ism_format::Error::Io { error, .. } => cannot_write(path, error),
        _ => anyhow::Error::new(e).context(format!("cannot write {}", path.display())),
    }
}

/// `cannot read PATH: REASON` for an error of [`ism_format::io::read_path`], naming the path once.
pub(crate) fn cannot_read_model(path: &Path, e: ism_format::Error) -> anyhow::Error {
    match &e {
        ism_format::Error::Io { error, .. } => {
            anyhow::anyhow!(
                "cannot read {}: {}",
                path.display(),
                os_message(path, error)
            )
        }
        _ => anyhow::Error::new(e).context(format!("cannot read {}", path.display())),
    }
}

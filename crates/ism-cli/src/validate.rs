//! `ism validate`: structure, invariance and certified positivity; glue over `ism-validate`.

use std::path::PathBuf;
use std::process::ExitCode;

use ism_format::ErrorChain;
use ism_validate::{Options, Report, Verdict};

const AFTER_HELP: &str = "\
Examples:
  ism validate spec/examples/*.ism.json
  ism validate --json model.ismb > report.json
  ism validate --quality --max-pieces 1000000 -j 1 model.ism.json
  ism validate --max-issues 500 model.ism.json     (list up to 500 messages)

Each element (stage × top simplex) is certified valid by a theorem or by Bernstein coefficients of
det DX with subdivision (floating point with proven rounding bounds, then exact integer arithmetic
where that cannot decide), rejected with a witness point proven by exact evaluation, or left
undetermined when the piece budget runs out (never counted valid).
Rules are defined in spec/validation.md; --json prints the report of spec/schema/report.schema.json
(one report per file; several files give a JSON array).

Exit status:
  0  every file valid
  1  some file invalid or undetermined
  2  some file unreadable, or bad arguments";

/// Arguments of `ism validate`.
#[derive(clap::Args)]
#[command(after_help = AFTER_HELP)]
pub struct Args {
    /// Model files (any encoding; detected from content).
    #[arg(required = true)]
    files: Vec<PathBuf>,
    /// Print the machine-readable report (JSON) instead of the summary.
    #[arg(long)]
    json: bool,
    /// Most messages listed per file (all are counted) [default: 20 in the text summary, 100 with
    /// --json].
    #[arg(long)]
    max_issues: Option<usize>,
    #[command(flatten)]
    threads: crate::args::Threads,
    /// No progress display.
    #[arg(long, short)]
    quiet: bool,
    /// Pieces per element for the positivity certificate's subdivision (floating point; the exact
    /// fallback gets a sixteenth as many). Undetermined only means this budget ran out.
    #[arg(long, default_value_t = ism_validate::DEFAULT_MAX_PIECES, value_parser = parse_pieces)]
    max_pieces: usize,
    /// Also report quality: C¹ residuals of rational stages, normal jumps, det DX range.
    #[arg(long)]
    quality: bool,
    /// Certify every element numerically even where a theorem applies.
    #[arg(long)]
    no_theorems: bool,
    #[command(flatten)]
    limits: crate::args::ReadLimits,
}

/// A piece budget: a positive whole number of at most 2^32 (bounds memory and time per element).
fn parse_pieces(text: &str) -> Result<usize, String> {
    match text.parse::<usize>() {
        Ok(n) if (1..=1 << 32).contains(&n) => Ok(n),
        _ => Err(format!(
            "expected a whole number of pieces from 1 to {}",
            1u64 << 32
        )),
    }
}

/// Messages the text summary lists when --max-issues is not given.
const TEXT_MAX_ISSUES: usize = 20;

fn print_summary(path: &std::path::Path, report: &Report, listed: usize) {
    let verdict = match report.verdict {
        Verdict::Valid => "VALID",
        Verdict::Invalid => "INVALID",
        Verdict::Undetermined => "UNDETERMINED",
    };
    println!(
        "{}: {verdict} — {} error(s), {} warning(s), {} info(s); {} simplices, {} stage(s)",
        path.display(),
        report.issues.num_errors,
        report.issues.num_warnings,
        report.issues.num_infos,
        report.model.simplices,
        report.model.stages
    );
    if !report.issues.counts.is_empty() {
        // Worst rules first: severity, then count.
        let mut counts: Vec<(&String, &usize)> = report.issues.counts.iter().collect();
        let severity = |code: &str| {
            ism_format::Rule::from_id(code)
                .map(|r| r.severity())
                .unwrap_or(ism_format::Severity::Info)
        };
        counts.sort_by(|a, b| {
            severity(b.0)
                .cmp(&severity(a.0))
                .then(b.1.cmp(a.1))
                .then(a.0.cmp(b.0))
        });
        for (code, count) in counts {
            let title = ism_format::Rule::from_id(code)
                .map(|r| r.title())
                .unwrap_or("");
            println!("  {code} ×{count}  {title}");
        }
    }
    for st in &report.stages {
        let certs: Vec<String> = st
            .certificates
            .iter()
            .map(|(k, v)| format!("{v} by {k}"))
            .collect();
        println!(
            "  stage {} ({} degree {}, {}): {} — {} valid, {} invalid, {} undetermined{}",
            st.index,
            st.kind,
            st.degree,
            st.direction,
            st.skipped_because
                .as_deref()
                .map(|r| format!("skipped: {r}"))
                .unwrap_or_else(|| st.status.clone()),
            st.valid,
            st.invalid,
            st.undetermined,
            if certs.is_empty() {
                String::new()
            } else {
                format!(" [{}]", certs.join("; "))
            }
        );
    }
    // Messages are already ordered errors first; show the first `listed`.
    let shown = report.issues.messages.len().min(listed);
    for m in &report.issues.messages[..shown] {
        println!(
            "  {} {:?} ({}): {}",
            m.code, m.severity, m.location, m.message
        );
    }
    let total = report.issues.num_errors + report.issues.num_warnings + report.issues.num_infos;
    if total > shown {
        println!(
            "  … {} more not listed (counted above; raise --max-issues to list them)",
            total - shown
        );
    }
}

pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    // The report keeps at least the default number of messages, so `--json` does not lose any
    // to the shorter text listing.
    let listed = args.max_issues.unwrap_or(if args.json {
        ism_validate::DEFAULT_MAX_ISSUES
    } else {
        TEXT_MAX_ISSUES
    });
    let options = Options {
        max_issues: args.max_issues.unwrap_or(ism_validate::DEFAULT_MAX_ISSUES),
        threads: args.threads.count(),
        max_pieces: args.max_pieces,
        quality: args.quality,
        theorems: !args.no_theorems,
        limits: args.limits.limits(),
    };
    let progress = crate::progress::Progress::new(args.quiet);
    // The positivity layer reports per stage, counted in simplices.
    let hook = progress.hook(|_| "simplices");
    let mut worst = 0u8;
    let mut reports = Vec::new();
    for path in &args.files {
        progress.phase(format!(
            "validating {}: structure, invariance, positivity certificates",
            path.display()
        ));
        match ism_validate::validate_path_with_progress(path, &options, &hook) {
            Ok(report) => {
                if report.verdict != Verdict::Valid {
                    worst = worst.max(1);
                }
                if args.json {
                    reports.push(serde_json::to_value(&report)?);
                } else {
                    progress.suspend(|| print_summary(path, &report, listed));
                }
            }
            Err(err) => {
                worst = 2;
                progress.suspend(|| eprintln!("error: {}: {}", path.display(), ErrorChain(&err)));
                if args.json {
                    reports.push(serde_json::json!({
                        "file": { "path": path.display().to_string() },
                        "verdict": "unreadable",
                        "error": ErrorChain(&err).to_string(),
                    }));
                }
            }
        }
    }
    progress.finish();
    if args.json {
        let out = if reports.len() == 1 {
            reports.pop().expect("one report")
        } else {
            serde_json::Value::Array(reports)
        };
        println!("{}", serde_json::to_string_pretty(&out)?);
    }
    Ok(ExitCode::from(worst))
}

//! Golden CLI tests (wasm-tools' `BLESS=1` style): every `ism` subcommand's human and `--json`
//! output on the bundled examples, compared byte for byte with a file under `tests/golden/`, so a
//! changed message is a reviewed diff.
//!
//! `tests/golden/cases.txt` lists the cases, one a line: `NAME: ARGS [&& ARGS …]`, each `ARGS` one
//! `ism` run (split on whitespace). Commands run in the repository root (paths print as given) in
//! order; `$TMP` is a scratch directory of the case, so a case can read back what it wrote.
//! `tests/golden/NAME.txt` holds, per command, the command line, its exit status, standard output
//! and standard error. `BLESS=1 cargo test -p ism-cli --test golden` rewrites the expected files
//! (and deletes those of cases no longer listed); review the diff before committing.
//!
//! What legitimately varies between runs is replaced by the minimal filter [`normalize`], and
//! nothing else: the scratch directory's path, elapsed times, and this build's version after the
//! names of its own components. Thread counts are never printed, and the outputs do not depend on
//! them (`golden_outputs_do_not_depend_on_the_thread_count` in this file checks one case per
//! parallel command with one worker and with the default).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::LazyLock;

use libtest_mimic::{Arguments, Failed, Trial};
use regex::Regex;

/// The repository root, where commands run.
fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn golden_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/golden")
}

/// One case of `cases.txt`.
struct Case {
    name: String,
    commands: Vec<Vec<String>>,
}

fn cases() -> Vec<Case> {
    let text = std::fs::read_to_string(golden_dir().join("cases.txt")).expect("cases.txt");
    let mut out: Vec<Case> = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let (name, rest) = line
            .split_once(':')
            .unwrap_or_else(|| panic!("cases.txt line {}: expected `NAME: ARGS`", i + 1));
        let name = name.trim().to_string();
        assert!(
            !name.is_empty()
                && name
                    .chars()
                    .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_'),
            "cases.txt line {}: bad case name {name:?}",
            i + 1
        );
        assert!(
            out.iter().all(|c| c.name != name),
            "cases.txt line {}: case {name} given twice",
            i + 1
        );
        let commands = rest
            .split("&&")
            .map(|c| c.split_whitespace().map(str::to_string).collect())
            .collect();
        out.push(Case { name, commands });
    }
    out
}

/// Components of this workspace whose name a command prints with the build's version.
const OWN_COMPONENTS: &str = "ism|ism-validate|ism-fit|ism-export|ism-format|ism-sample|ism-cli";

/// The documented filter: (1) the case's scratch directory becomes `$TMP`; (2) elapsed times
/// become `<elapsed>` — a decimal number followed by ` s` in text, the value of a JSON member whose
/// key ends in `seconds`, and the `"timing"` object of the validation report; (3) this build's
/// version after the name of one of its own components becomes `<version>` (a version inside an
/// input file, e.g. an example's generator, is kept).
fn normalize(text: &str, tmp: &Path) -> String {
    static SECONDS_TEXT: LazyLock<Regex> = LazyLock::new(|| Regex::new(r"\b\d+\.\d+ s\b").unwrap());
    static SECONDS_JSON: LazyLock<Regex> = LazyLock::new(|| {
        Regex::new(r#"("[A-Za-z_]*(?:seconds|Seconds)"\s*:\s*)-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?"#)
            .unwrap()
    });
    static TIMING_JSON: LazyLock<Regex> =
        LazyLock::new(|| Regex::new(r#"("timing"\s*:\s*)\{[^{}]*\}"#).unwrap());
    static VERSION: LazyLock<Regex> = LazyLock::new(|| {
        Regex::new(&format!(
            r"\b({OWN_COMPONENTS}) {}\b",
            regex::escape(env!("CARGO_PKG_VERSION"))
        ))
        .unwrap()
    });
    let text = text.replace(&tmp.display().to_string(), "$TMP");
    let text = SECONDS_TEXT.replace_all(&text, "<elapsed> s");
    let text = SECONDS_JSON.replace_all(&text, "${1}<elapsed>");
    let text = TIMING_JSON.replace_all(&text, "${1}<elapsed>");
    VERSION.replace_all(&text, "${1} <version>").into_owned()
}

/// Runs a case's commands and renders what they printed (normalized).
fn render(case: &Case, threads: Option<&str>) -> String {
    let tmp = tempfile::tempdir().expect("scratch directory");
    let mut out = String::new();
    for args in &case.commands {
        let args: Vec<String> = args
            .iter()
            .map(|a| a.replace("$TMP", &tmp.path().display().to_string()))
            .collect();
        let mut command = Command::new(env!("CARGO_BIN_EXE_ism"));
        command
            .args(&args)
            .current_dir(root())
            .stdin(Stdio::null())
            .env_remove("RAYON_NUM_THREADS");
        if let Some(t) = threads {
            command.env("RAYON_NUM_THREADS", t);
        }
        let output = command.output().expect("run ism");
        let status = match output.status.code() {
            Some(code) => format!("exit {code}"),
            None => format!("killed: {:?}", output.status),
        };
        // The scratch path in the arguments turns back into `$TMP` in the filter.
        writeln!(out, "$ ism {}", args.join(" ")).unwrap();
        writeln!(out, "{status}").unwrap();
        for (label, bytes) in [("stdout", &output.stdout), ("stderr", &output.stderr)] {
            if bytes.is_empty() {
                continue;
            }
            writeln!(out, "--- {label}").unwrap();
            out.push_str(&String::from_utf8_lossy(bytes));
            if !bytes.ends_with(b"\n") {
                out.push_str("\n[no newline at the end]\n");
            }
        }
        out.push('\n');
    }
    normalize(&out, tmp.path())
}

fn blessing() -> bool {
    std::env::var_os("BLESS").is_some_and(|v| !v.is_empty() && v != "0")
}

/// Compares one case with its expected file, or rewrites the file when blessing.
fn check(case: &Case) -> Result<(), Failed> {
    let actual = render(case, None);
    let path = golden_dir().join(format!("{}.txt", case.name));
    if blessing() {
        std::fs::write(&path, &actual).map_err(|e| format!("{}: {e}", path.display()))?;
        return Ok(());
    }
    let expected = std::fs::read_to_string(&path).map_err(|e| {
        format!(
            "{}: {e} (run `BLESS=1 cargo test -p ism-cli --test golden` to create it)",
            path.display()
        )
    })?;
    if actual == expected {
        return Ok(());
    }
    Err(format!(
        "output differs from {} (rerun with BLESS=1 to accept it, then review the diff):\n{}",
        path.display(),
        diff(&expected, &actual)
    )
    .into())
}

/// A line diff of expected and actual (`-` expected, `+` actual), enough to review a failure.
fn diff(expected: &str, actual: &str) -> String {
    let (e, a): (Vec<&str>, Vec<&str>) = (expected.lines().collect(), actual.lines().collect());
    // Longest common subsequence table; the files are small.
    let mut lcs = vec![vec![0usize; a.len() + 1]; e.len() + 1];
    for i in (0..e.len()).rev() {
        for j in (0..a.len()).rev() {
            lcs[i][j] = if e[i] == a[j] {
                lcs[i + 1][j + 1] + 1
            } else {
                lcs[i + 1][j].max(lcs[i][j + 1])
            };
        }
    }
    let (mut i, mut j, mut out) = (0, 0, String::new());
    while i < e.len() || j < a.len() {
        if i < e.len() && j < a.len() && e[i] == a[j] {
            i += 1;
            j += 1;
        } else if i < e.len() && (j == a.len() || lcs[i + 1][j] >= lcs[i][j + 1]) {
            writeln!(out, "-{}", e[i]).unwrap();
            i += 1;
        } else {
            writeln!(out, "+{}", a[j]).unwrap();
            j += 1;
        }
    }
    out
}

/// Expected files of cases no longer listed: an error (or deleted when blessing).
fn stale(cases: &[Case]) -> Result<(), Failed> {
    let mut stale = Vec::new();
    for entry in std::fs::read_dir(golden_dir()).map_err(|e| e.to_string())? {
        let path = entry.map_err(|e| e.to_string())?.path();
        let Some(name) = path
            .file_name()
            .and_then(|n| n.to_str())
            .and_then(|n| n.strip_suffix(".txt"))
        else {
            continue;
        };
        if name != "cases" && cases.iter().all(|c| c.name != name) {
            if blessing() {
                std::fs::remove_file(&path).map_err(|e| e.to_string())?;
            } else {
                stale.push(path.display().to_string());
            }
        }
    }
    if stale.is_empty() {
        Ok(())
    } else {
        Err(format!("expected files of no case in cases.txt: {stale:?}").into())
    }
}

/// Cases whose commands run in parallel, rendered with one worker thread: the output must equal
/// the default's (and so the expected file).
const THREAD_CASES: &[&str] = &[
    "validate-torus-quality",
    "export-sphere-obj",
    "sample-sphere-volume",
    "fit-preset-circle",
    "smooth-circle-curved",
];

fn main() {
    let args = Arguments::from_args();
    let all = cases();
    let mut trials: Vec<Trial> = Vec::new();
    for case in cases() {
        trials.push(Trial::test(case.name.clone(), move || check(&case)));
    }
    trials.push(Trial::test("golden_files_belong_to_cases", move || {
        stale(&all)
    }));
    trials.push(Trial::test(
        "golden_outputs_do_not_depend_on_the_thread_count",
        || {
            let all = cases();
            for name in THREAD_CASES {
                let case = all
                    .iter()
                    .find(|c| c.name == *name)
                    .ok_or_else(|| format!("no case {name} in cases.txt"))?;
                let (one, default) = (render(case, Some("1")), render(case, None));
                if one != default {
                    return Err(format!(
                        "{name}: one worker (-) vs the default (+):\n{}",
                        diff(&one, &default)
                    )
                    .into());
                }
            }
            Ok(())
        },
    ));
    libtest_mimic::run(&args, trials).exit();
}

//! CPU time of this process, shared by the benchmark examples (included with `#[path]`; a
//! folder without `main.rs` is not an example of its own).

/// CPU seconds of every live thread of this process so far (`/proc/self/task/*/schedstat`,
/// nanoseconds on a CPU): the same measure as Python's `time.process_time()`, which the peers'
/// scripts use. A thread that exits while the folder is read is skipped; NaN when the folder
/// cannot be read at all (not Linux), so no ratio is ever computed from a missing figure.
pub fn cpu() -> f64 {
    let Ok(tasks) = std::fs::read_dir("/proc/self/task") else {
        return f64::NAN;
    };
    tasks
        .filter_map(|t| {
            let text = std::fs::read_to_string(t.ok()?.path().join("schedstat")).ok()?;
            text.split_whitespace().next()?.parse::<u64>().ok()
        })
        .sum::<u64>() as f64
        * 1e-9
}

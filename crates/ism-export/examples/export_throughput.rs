//! The exporter's throughput in process: `ism export MODEL out.obj --tolerance T -j 1` as library
//! calls (read the file, the lazy index, [`build`], the OBJ written to memory), repeated `REPS`
//! times on one thread — the work the CLI does without the process around it (loading the binary,
//! arguments, the file system), i.e. what a caller of the library pays per export (the Python
//! package and the Blender add-on call it in process). Prints one JSON line: triangles, CPU
//! seconds per export (user + system of the whole process over all repetitions, from
//! `/proc/self/stat`: Linux only), triangles per CPU-second, and the best wall time of each part.
//! Run through `tools/bench_export_throughput.py`, which prints it beside the whole `ism export`
//! process.
//!
//! `cargo run --release -p ism-export --example export_throughput -- MODEL TOLERANCE REPS`

use std::time::Instant;

use ism_export::export::{build, ExportOptions, Exported};
use ism_export::format::ExportFormat;
use ism_format::io::{read_path_indexed_lazily_with, ReadOptions};
use ism_format::progress::Progress;

/// The clock ticks per second of `/proc/self/stat`'s CPU fields (`USER_HZ`): 100 on every Linux
/// architecture the kernel's ABI defines for user space.
const USER_HZ: f64 = 100.0;

/// User + system CPU seconds of this process so far (every thread), from `/proc/self/stat`.
fn process_cpu_seconds() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").expect("/proc/self/stat (Linux)");
    // Fields after the command name, which is in parentheses and may hold spaces: state is
    // field 3, utime field 14 and stime field 15 of proc(5).
    let rest = &stat[stat.rfind(')').expect("proc(5) format") + 2..];
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let ticks = |i: usize| fields[i].parse::<u64>().expect("proc(5) format") as f64;
    (ticks(11) + ticks(12)) / USER_HZ
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let usage = "usage: export_throughput MODEL TOLERANCE REPS";
    let [path, tolerance, reps] = &args[..] else {
        panic!("{usage}")
    };
    let tolerance: f64 = tolerance.parse().expect(usage);
    let reps: usize = reps.parse().expect(usage);
    assert!(reps > 0, "{usage}");
    // As `ism export -j 1`: one thread, the calling one (no worker to hand the work to).
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .use_current_thread()
        .build()
        .expect("thread pool");
    // As the CLI's `export` reads: the lazy index (face tables built on first use).
    let read_options = ReadOptions::default();
    let options = ExportOptions {
        tolerance,
        ..ExportOptions::default()
    };
    let mut triangles = 0;
    let mut bytes = 0;
    let mut best = [f64::INFINITY; 3];
    let cpu_before = process_cpu_seconds();
    pool.install(|| {
        for _ in 0..reps {
            let t0 = Instant::now();
            let model = read_path_indexed_lazily_with(path, &read_options)
                .expect("a readable, structurally valid model")
                .model;
            let t1 = Instant::now();
            let built = build(&model, &options, &Progress::none()).expect("an exportable model");
            let t2 = Instant::now();
            let mut out = Vec::new();
            built
                .write(ExportFormat::Obj, None, &mut out)
                .expect("writing to memory");
            let t3 = Instant::now();
            let Exported::Surface { mesh, .. } = &built else {
                unreachable!("a surface export")
            };
            triangles = mesh.num_cells();
            bytes = out.len();
            for (b, t) in best.iter_mut().zip([t1 - t0, t2 - t1, t3 - t2]) {
                *b = b.min(t.as_secs_f64());
            }
        }
    });
    let cpu = (process_cpu_seconds() - cpu_before) / reps as f64;
    println!(
        r#"{{"model":{path:?},"tolerance":{tolerance},"reps":{reps},"triangles":{triangles},"obj_bytes":{bytes},"cpu_seconds_per_export":{cpu:.6},"triangles_per_cpu_second":{:.0},"best_wall_seconds":{{"read_and_index":{:.6},"extract":{:.6},"write":{:.6}}}}}"#,
        triangles as f64 / cpu,
        best[0],
        best[1],
        best[2]
    );
}

//! Wall and CPU time of each phase of `ism validate` on a file, with 1, 2, … threads alternating in
//! one run: where the time goes and which phases scale (issue 12: 1 → 2 threads on the 1 M-tet
//! model).
//!
//! ```text
//! cargo run --release -p ism-validate --example validate_phases -- FILE [ROUNDS] [THREADS…]
//! ```
//!
//! Phases: `read` (decode, no structural check), `index` (structural check + vertex incidence, the
//! validator's `IndexedModel::new_lazy_or_model`: face tables only if a layer asks), `manifold`
//! (ISM-150 stars, `topology::non_manifold_stars`), `invariance`, `positivity`, `drop`
//! (freeing the model), then `calibration` (a compute-bound loop, not in the totals: what any loop
//! can gain from more threads on the machine at that moment). CPU is the sum over the process's threads of their time on a CPU
//! (`/proc/self/task/*/schedstat`), so a phase that scales keeps its CPU and halves its wall time.

use std::time::Instant;

use ism_format::{io, IndexedModel};
use ism_validate::{certify, invariance, positivity, topology};
use rayon::prelude::*;

#[path = "support/cpu.rs"]
mod support;
use support::cpu;

/// The 1-minute load average.
fn load() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .ok()
        .and_then(|s| s.split_whitespace().next().map(str::to_string))
        .unwrap_or_default()
}

struct Clock {
    phases: Vec<(&'static str, f64, f64)>,
    wall: Instant,
    cpu: f64,
}

impl Clock {
    fn new() -> Clock {
        Clock {
            phases: Vec::new(),
            wall: Instant::now(),
            cpu: cpu(),
        }
    }
    fn lap(&mut self, name: &'static str) {
        let (w, c) = (Instant::now(), cpu());
        self.phases
            .push((name, (w - self.wall).as_secs_f64(), c - self.cpu));
        self.wall = Instant::now();
        self.cpu = cpu();
    }
}

fn round(path: &str) -> Result<Clock, Box<dyn std::error::Error + Send + Sync>> {
    let mut clock = Clock::new();
    let read = io::ReadOptions {
        check_structure: false,
        ..io::ReadOptions::default()
    };
    let doc = io::read_with(std::fs::File::open(path)?, &read)?;
    clock.lap("read");
    let indexed = IndexedModel::new_lazy_or_model(doc.model).map_err(|(_, e)| e)?;
    clock.lap("index");
    let found = topology::non_manifold_stars(&indexed);
    clock.lap("manifold");
    let mut messages = found.len();
    for k in 0..indexed.stages.len() {
        messages += invariance::check_stage(&indexed, k).len();
    }
    clock.lap("invariance");
    let options = positivity::PositivityOptions {
        budget: certify::Budget::new(ism_validate::DEFAULT_MAX_PIECES),
        theorems: true,
    };
    for k in 0..indexed.stages.len() {
        messages += positivity::check_stage(&indexed, k, options).messages.len();
    }
    clock.lap("positivity");
    drop(indexed);
    clock.lap("drop");
    // Calibration: a compute-bound loop with no memory traffic, the most any loop can gain from
    // more threads on this machine at this moment.
    let x: f64 = (0..40_000_000u64)
        .into_par_iter()
        .map(|i| (i as f64).sqrt().sin())
        .sum();
    clock.lap("calibration");
    std::hint::black_box(x);
    if messages != 0 {
        eprintln!("{messages} messages");
    }
    Ok(clock)
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let path = args
        .first()
        .ok_or("usage: validate_phases FILE [ROUNDS] [THREADS…]")?;
    let rounds: usize = args.get(1).map_or(Ok(2), |a| a.parse())?;
    let mut threads: Vec<usize> = args[2.min(args.len())..]
        .iter()
        .map(|a| a.parse())
        .collect::<Result<_, _>>()?;
    if threads.is_empty() {
        threads = vec![1, 2];
    }
    let pools: Vec<rayon::ThreadPool> = threads
        .iter()
        .map(|&t| rayon::ThreadPoolBuilder::new().num_threads(t).build())
        .collect::<Result<_, _>>()?;
    for r in 0..rounds {
        for (pool, &t) in pools.iter().zip(&threads) {
            let before = load();
            let clock = pool.install(|| round(path)).map_err(|e| e.to_string())?;
            let (wall, cpu): (f64, f64) = clock
                .phases
                .iter()
                .filter(|p| p.0 != "calibration")
                .fold((0.0, 0.0), |(w, c), p| (w + p.1, c + p.2));
            let phases: Vec<String> = clock
                .phases
                .iter()
                .map(|(name, w, c)| format!("\"{name}\":[{w:.3},{c:.3}]"))
                .collect();
            println!(
                "{{\"round\":{r},\"threads\":{t},\"load\":\"{before}\",\"wall_s\":{wall:.3},\"cpu_s\":{cpu:.3},\"phases_wall_cpu\":{{{}}}}}",
                phases.join(",")
            );
        }
    }
    Ok(())
}

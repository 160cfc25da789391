//! Certifies a batch of dense control nets and reports the throughput: the Rust side of
//! `tools/bench_gmsh.py`, which writes the nets and runs Gmsh on the same elements.
//!
//! Input file: one JSON header line `{"n": 3, "degree": 3, "rational": false, "count": N}`, then
//! `N · C(d + n, n) · 4` little-endian f64 (barycentric control points in canonical order, 4
//! coordinates each, unused ones 0), then, for rational nets, `N · C(d + n, n)` weights.
//! Output: a JSON line with counts and timing on stdout; one verdict byte per element
//! (`1` valid, `0` invalid, `2` undetermined) in the file given as the second argument.
//!
//! ```text
//! cargo run --release -p ism-validate --example certify_nets -- nets.bin verdicts.bin --threads 1 [--max-pieces P]
//! ```

use std::io::{BufRead, Read};
use std::time::Instant;

use ism_format::multi_index;
use ism_validate::{Budget, Certificate, DenseNet, DetKernel};
use rayon::prelude::*;

#[derive(serde::Deserialize)]
struct Header {
    n: usize,
    degree: u32,
    rational: bool,
    count: usize,
}

// CPU time around the certification pass alone: the same measure as Gmsh's
// `time.process_time()` around its call.
#[path = "support/cpu.rs"]
mod support;
use support::cpu;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let input = args
        .get(1)
        .ok_or("usage: certify_nets NETS VERDICTS [--threads T] [--repeat R] [--max-pieces P]")?;
    let output = args.get(2).ok_or("missing VERDICTS path")?;
    let flag = |name: &str| {
        args.iter()
            .position(|a| a == name)
            .and_then(|i| args.get(i + 1))
            .map(|v| v.parse::<usize>())
    };
    let threads = flag("--threads").transpose()?.unwrap_or(0);
    let budget = flag("--max-pieces")
        .transpose()?
        .map_or_else(Budget::default, Budget::new);
    // `--repeat 0` only loads: the benchmark subtracts its CPU time to time certification alone.
    let repeat = flag("--repeat").transpose()?.unwrap_or(1);

    let mut reader = std::io::BufReader::new(std::fs::File::open(input)?);
    let mut line = String::new();
    reader.read_line(&mut line)?;
    let header: Header = serde_json::from_str(&line)?;
    let per = multi_index::count(header.n + 1, header.degree);
    let mut bytes = Vec::new();
    reader.read_to_end(&mut bytes)?;
    let floats: Vec<f64> = bytes
        .chunks_exact(8)
        .map(|c| f64::from_le_bytes(c.try_into().expect("8 bytes")))
        .collect();
    let points_len = header.count * per * 4;
    if floats.len()
        != points_len
            + if header.rational {
                header.count * per
            } else {
                0
            }
    {
        return Err(format!("{} numbers; header announces {}", floats.len(), points_len).into());
    }
    let nets: Vec<DenseNet> = (0..header.count)
        .map(|e| DenseNet {
            n: header.n,
            degree: header.degree,
            points: floats[e * per * 4..(e + 1) * per * 4]
                .chunks_exact(4)
                .map(|c| [c[0], c[1], c[2], c[3]])
                .collect(),
            weights: if header.rational {
                floats[points_len + e * per..points_len + (e + 1) * per].to_vec()
            } else {
                Vec::new()
            },
        })
        .collect();
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()?;
    let kernel = DetKernel::new(header.n, header.degree, header.rational);
    let mut verdicts: Vec<(u8, usize)> = Vec::new();
    let mut best = f64::INFINITY;
    let mut best_cpu = f64::INFINITY;
    for _ in 0..repeat {
        let cpu0 = cpu();
        let start = Instant::now();
        verdicts = pool.install(|| {
            nets.par_iter()
                .map(|net| match kernel.certify(net, budget) {
                    Certificate::Positive {
                        pieces,
                        exact: true,
                        ..
                    } => (3u8, pieces),
                    Certificate::Positive { pieces, .. } => (1u8, pieces),
                    Certificate::NonPositive { .. } => (0u8, 0),
                    Certificate::Undetermined { pieces, .. } => (2u8, pieces),
                })
                .collect::<Vec<(u8, usize)>>()
        });
        best = best.min(start.elapsed().as_secs_f64());
        // A NaN (no schedstat) is dropped by `min`, leaving ∞, which is written as null.
        best_cpu = best_cpu.min(cpu() - cpu0);
    }
    let pieces: usize = verdicts.iter().filter(|v| v.0 % 2 == 1).map(|v| v.1).sum();
    // 3 marks a positive decided by the exact path; the file says 1 (valid) for both.
    let exact_valid = verdicts.iter().filter(|v| v.0 == 3).count();
    let verdicts: Vec<u8> = verdicts
        .into_iter()
        .map(|v| if v.0 == 3 { 1 } else { v.0 })
        .collect();
    ism_format::io::write_atomic(std::path::Path::new(output), |w| {
        std::io::Write::write_all(w, &verdicts)
    })?;
    let count = |v: u8| verdicts.iter().filter(|&&x| x == v).count();
    println!(
        "{}",
        serde_json::json!({
            "count": header.count,
            "threads": pool.current_num_threads(),
            "seconds": if repeat == 0 { 0.0 } else { best },
            "per_second": if repeat == 0 { 0.0 } else { header.count as f64 / best },
            // CPU time of the process (all threads) around one pass, best of --repeat; null when
            // /proc/self/task/*/schedstat cannot be read.
            "cpu_seconds": best_cpu.is_finite().then_some(best_cpu),
            "valid": count(1),
            "invalid": count(0),
            "undetermined": count(2),
            "mean_pieces_per_valid": pieces as f64 / count(1).max(1) as f64,
            "exact_valid": exact_valid,
        })
    );
    Ok(())
}

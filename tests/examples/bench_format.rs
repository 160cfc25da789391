//! Read/write throughput of the five encodings on a large stratified model (issue 2 benchmark).
//! Driven by `tools/bench_format.sh`, which also runs the meshio peer and records peak memory.
//!
//! `bench_format make DIR [TETS] [--binary-only]`  build the model, write it in every encoding (or
//!                                 only the binary one; timed), and dump the raw
//!                                 tetrahedra/points/values as .npy for the peer.
//! `bench_format read FILE [--no-check | --indexed] [--repeat K]`  read a file (timed; best of K;
//!                                 `--indexed` also builds the IndexedModel).
//! `bench_format write FILE OUT [--repeat K]`  read FILE unchecked, then write it to OUT in the
//!                                 encoding OUT's name suggests (timed, best of K; peak RSS of the
//!                                 write phase alone, from the kernel's high-water mark reset
//!                                 before it).

use std::io::Write;
use std::path::Path;
use std::time::Instant;

use ism_format::io::{self, ReadOptions, WriteOptions};
use ism_format::Encoding;

fn npy(path: &Path, descr: &str, shape: &[usize], data: &[u8]) -> std::io::Result<()> {
    let dims: Vec<String> = shape.iter().map(|d| d.to_string()).collect();
    let mut header = format!(
        "{{'descr': '{descr}', 'fortran_order': False, 'shape': ({},), }}",
        dims.join(", ")
    );
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut f = std::io::BufWriter::new(std::fs::File::create(path)?);
    f.write_all(b"\x93NUMPY\x01\x00")?;
    f.write_all(&(header.len() as u16).to_le_bytes())?;
    f.write_all(header.as_bytes())?;
    f.write_all(data)?;
    f.flush()
}

fn make(dir: &Path, tets: usize, binary_only: bool) -> Result<(), Box<dyn std::error::Error>> {
    std::fs::create_dir_all(dir)?;
    let t = Instant::now();
    let model = ism_examples::large_stratified_model(tets);
    eprintln!(
        "model: {} tets, {} vertices, {} face records, built in {:.2}s",
        model.num_simplices(),
        model.num_vertices(),
        model.stages.iter().map(|s| s.faces.len()).sum::<usize>(),
        t.elapsed().as_secs_f64()
    );
    let encodings: &[Encoding] = if binary_only {
        &[Encoding::Binary]
    } else {
        &Encoding::ALL
    };
    for &enc in encodings {
        let path = dir.join(format!("large.{}", enc.extension()));
        let mut best = f64::INFINITY;
        let mut bytes = 0;
        for _ in 0..3 {
            let t = Instant::now();
            io::write_path(&model, &path, Some(enc), WriteOptions::default())?;
            best = best.min(t.elapsed().as_secs_f64());
            bytes = std::fs::metadata(&path)?.len();
        }
        println!("{{\"op\":\"write\",\"encoding\":\"{}\",\"bytes\":{bytes},\"seconds\":{best:.4},\"simplices\":{}}}",
            enc.name(), model.num_simplices());
    }
    let f64s = |xs: &[f64]| xs.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>();
    npy(
        &dir.join("points.npy"),
        "<f8",
        &[model.num_vertices(), 3],
        &f64s(&model.vertices),
    )?;
    npy(
        &dir.join("values.npy"),
        "<f8",
        &[model.num_vertices()],
        &f64s(&model.values),
    )?;
    let ids: Vec<u8> = model
        .simplices
        .iter()
        .flat_map(|x| (*x as i64).to_le_bytes())
        .collect();
    npy(
        &dir.join("tets.npy"),
        "<i8",
        &[model.num_simplices(), 4],
        &ids,
    )?;
    Ok(())
}

/// CPU seconds (user + system) of this process so far.
fn cpu_seconds() -> f64 {
    // /proc/self/stat fields 14 and 15: utime and stime in clock ticks (100 per second on Linux).
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let after = stat.rsplit_once(')').map_or("", |(_, rest)| rest);
    let fields: Vec<&str> = after.split_whitespace().collect();
    let tick = |i: usize| {
        fields
            .get(i)
            .and_then(|x| x.parse::<f64>().ok())
            .unwrap_or(0.0)
    };
    (tick(11) + tick(12)) / 100.0
}

/// `mode`: "checked", "unchecked" or "indexed" (checked, keeping the index).
fn read(file: &Path, mode: &str, repeat: usize) -> Result<(), Box<dyn std::error::Error>> {
    let options = ReadOptions {
        check_structure: mode == "checked",
        ..ReadOptions::default()
    };
    let mut best = f64::INFINITY;
    let mut best_cpu = f64::INFINITY;
    let mut out = None;
    for _ in 0..repeat {
        drop(out.take());
        let (t, c) = (Instant::now(), cpu_seconds());
        let f = std::fs::File::open(file)?;
        // No BufReader: the reader streams binary payloads through its own window.
        let d = io::read_with(f, &options)?;
        let summary = if mode == "indexed" {
            let indexed = ism_format::IndexedModel::new(d.model)?;
            (
                d.encoding,
                d.byte_len,
                indexed.num_simplices(),
                Some(indexed),
            )
        } else {
            (d.encoding, d.byte_len, d.model.num_simplices(), None)
        };
        let (wall, cpu) = (t.elapsed().as_secs_f64(), cpu_seconds() - c);
        if std::env::var_os("BENCH_EACH").is_some() {
            eprintln!("read: {wall:.4} s, {cpu:.2} CPU-s");
        }
        best = best.min(wall);
        best_cpu = best_cpu.min(cpu);
        out = Some(summary);
    }
    let (encoding, bytes, simplices, _) = out.expect("repeat ≥ 1");
    println!("{{\"op\":\"read\",\"encoding\":\"{}\",\"mode\":\"{mode}\",\"bytes\":{bytes},\"seconds\":{best:.4},\"cpu_seconds\":{best_cpu:.2},\"simplices\":{simplices}}}",
        encoding.name());
    Ok(())
}

/// A line of /proc/self/status in KiB (`VmHWM`, `VmRSS`), 0 where unavailable.
fn status_kib(key: &str) -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .unwrap_or_default()
        .lines()
        .find_map(|l| l.strip_prefix(key)?.strip_prefix(':'))
        .and_then(|v| v.split_whitespace().next()?.parse().ok())
        .unwrap_or(0)
}

fn write(file: &Path, out: &Path, repeat: usize) -> Result<(), Box<dyn std::error::Error>> {
    let options = ReadOptions {
        check_structure: false,
        ..ReadOptions::default()
    };
    let model = io::read_with(std::fs::File::open(file)?, &options)?.model;
    let encoding =
        Encoding::from_path(out).ok_or("OUT needs an .ismb, .ism.msgpack or .ism.json name")?;
    let resident = status_kib("VmRSS");
    // Linux: writing 5 to clear_refs resets the peak RSS, so VmHWM below is the write's own peak.
    let reset = std::fs::write("/proc/self/clear_refs", "5").is_ok();
    let (mut best, mut best_cpu) = (f64::INFINITY, f64::INFINITY);
    for _ in 0..repeat {
        let (t, c) = (Instant::now(), cpu_seconds());
        io::write_path(&model, out, Some(encoding), WriteOptions::default())?;
        best = best.min(t.elapsed().as_secs_f64());
        best_cpu = best_cpu.min(cpu_seconds() - c);
    }
    let bytes = std::fs::metadata(out)?.len();
    println!("{{\"op\":\"write\",\"encoding\":\"{}\",\"bytes\":{bytes},\"seconds\":{best:.4},\"cpu_seconds\":{best_cpu:.2},\"model_rss_kib\":{resident},\"write_peak_rss_kib\":{},\"peak_reset\":{reset}}}",
        encoding.name(), status_kib("VmHWM"));
    Ok(())
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    match args.first().map(String::as_str) {
        Some("make") => make(
            Path::new(&args[1]),
            args.get(2)
                .map(|s| s.parse())
                .transpose()?
                .unwrap_or(1_000_000),
            args.iter().any(|a| a == "--binary-only"),
        ),
        Some("read") => {
            let mode = if args.iter().any(|a| a == "--no-check") {
                "unchecked"
            } else if args.iter().any(|a| a == "--indexed") {
                "indexed"
            } else {
                "checked"
            };
            let repeat = args
                .iter()
                .position(|a| a == "--repeat")
                .and_then(|i| args.get(i + 1))
                .map(|s| s.parse())
                .transpose()?
                .unwrap_or(3);
            read(Path::new(&args[1]), mode, repeat)
        }
        Some("write") if args.len() >= 3 => {
            let repeat = args
                .iter()
                .position(|a| a == "--repeat")
                .and_then(|i| args.get(i + 1))
                .map(|s| s.parse())
                .transpose()?
                .unwrap_or(3);
            write(Path::new(&args[1]), Path::new(&args[2]), repeat)
        }
        _ => Err(
            "usage: bench_format make DIR [TETS] [--binary-only] | read FILE [--no-check | --indexed] [--repeat K] | write FILE OUT [--repeat K]"
                .into(),
        ),
    }
}

//! `ism-make-examples`: (re)writes `spec/examples/` and, with `--vectors`, `spec/vectors/reader/`
//! and `spec/vectors/writer/`.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::Parser;

const AFTER_HELP: &str = "\
Examples:
  cargo run -p ism-examples --bin ism-make-examples                 # rewrite spec/examples/
  cargo run -p ism-examples --bin ism-make-examples -- --vectors    # also spec/vectors/{reader,writer}/
  ism-make-examples --examples-dir /tmp/ex --no-examples --vectors --vectors-dir /tmp/vec
  ism-make-examples --no-examples --large 1000000 /tmp/large.ismb   # benchmark model (any encoding)

Output is deterministic: running it twice gives identical bytes.
Exit status: 0 when every file was written, 2 on a write error or a vector that does not fail as intended.";

/// Writes the ISM example models (five encodings each) and the reader test vectors.
#[derive(Parser)]
#[command(name = "ism-make-examples", version, about, after_help = AFTER_HELP)]
struct Args {
    /// Directory of the examples.
    #[arg(long, default_value = "spec/examples")]
    examples_dir: PathBuf,
    /// Skip the examples.
    #[arg(long)]
    no_examples: bool,
    /// Also write the reader test vectors.
    #[arg(long)]
    vectors: bool,
    /// Directory of the reader test vectors.
    #[arg(long, default_value = "spec/vectors/reader")]
    vectors_dir: PathBuf,
    /// Directory of the writer test vectors.
    #[arg(long, default_value = "spec/vectors/writer")]
    writer_vectors_dir: PathBuf,
    /// Also write `large_stratified_model(TETS)` to FILE (encoding from the extension: .ism.json,
    /// .ism.msgpack, .ismb, .ismc, .ismz).
    #[arg(long, num_args = 2, value_names = ["TETS", "FILE"])]
    large: Option<Vec<String>>,
}

fn main() -> ExitCode {
    let args = Args::parse();
    match run(&args) {
        Ok(count) => {
            eprintln!("wrote {count} files");
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("ism-make-examples: {e:#}");
            ExitCode::from(2)
        }
    }
}

fn run(args: &Args) -> anyhow::Result<usize> {
    let mut count = 0;
    if !args.no_examples {
        std::fs::create_dir_all(&args.examples_dir)?;
        count += ism_examples::named::write_examples(&args.examples_dir)?.len();
    }
    if args.vectors {
        count += ism_examples::vectors::write_reader_vectors(&args.vectors_dir)
            .map_err(anyhow::Error::msg)?
            .len();
        count += ism_examples::writer_vectors::write_writer_vectors(&args.writer_vectors_dir)
            .map_err(anyhow::Error::msg)?
            .len();
    }
    if let Some(large) = &args.large {
        let tets: usize = large[0]
            .parse()
            .map_err(|e| anyhow::anyhow!("TETS {:?}: {e}", large[0]))?;
        let path = PathBuf::from(&large[1]);
        let started = std::time::Instant::now();
        let model = ism_examples::large_stratified_model(tets);
        let built = started.elapsed();
        ism_format::io::write_path(&model, &path, None, ism_format::io::WriteOptions::default())?;
        eprintln!(
            "{}: {} tetrahedra, {} face records; built in {:.2?}, written in {:.2?}",
            path.display(),
            model.num_simplices(),
            model.stages.iter().map(|s| s.faces.len()).sum::<usize>(),
            built,
            started.elapsed() - built
        );
        count += 1;
    }
    Ok(count)
}

//! `ism info`: a summary of a model, for people and (`--json`) for scripts.

use std::path::PathBuf;
use std::process::ExitCode;

use ism_format::io::{self, Document};
use serde::Serialize;

const AFTER_HELP: &str = "\
Examples:
  ism info spec/examples/sphere.ism.json
  ism info --json model.ismb | jq .stages

Exit status, as `ism validate`'s:
  0  the file reads and the model is well-formed
  1  the file decodes but the model breaks a structural rule (ISM-1xx); the errors are listed
  2  the file cannot be read: container, encoding or I/O (the error names the rule, e.g. ISM-003)";

/// Arguments of `ism info`.
#[derive(clap::Args)]
#[command(after_help = AFTER_HELP)]
pub struct Args {
    /// The model file (any encoding; detected from content).
    file: PathBuf,
    /// Print the summary as JSON.
    #[arg(long)]
    json: bool,
    /// No progress display.
    #[arg(long, short)]
    quiet: bool,
    #[command(flatten)]
    limits: crate::args::ReadLimits,
}

#[derive(Serialize)]
struct StageSummary {
    index: usize,
    kind: &'static str,
    degree: u32,
    direction: &'static str,
    name: Option<String>,
    face_records: usize,
    vertex_maps: usize,
    stored_numbers: usize,
    degrees_of_freedom: usize,
}

#[derive(Serialize)]
struct Summary {
    file: String,
    encoding: &'static str,
    version: String,
    container: Option<io::ContainerInfo>,
    checksum: &'static str,
    bytes: u64,
    name: Option<String>,
    generator: Option<String>,
    dimension: u8,
    vertices: usize,
    simplices: usize,
    /// Faces of K by dimension: vertices, edges, triangles, (tetrahedra).
    faces_by_dimension: Vec<usize>,
    level: f64,
    inside_vertices: usize,
    bounding_box: Vec<[f64; 2]>,
    stages: Vec<StageSummary>,
    extensions_used: Vec<String>,
}

/// Reads the file and runs the structural check, which counts the faces of each dimension on the
/// way (nothing is indexed beyond what the check needs: `info` is as cheap as a checked read).
fn read_counting_faces(
    path: &std::path::Path,
    limits: ism_format::io::Limits,
) -> ism_format::Result<(Document, Vec<usize>)> {
    // The summary needs the records' lengths, not their numbers: a binary file's control points
    // and weights are tested (finite) as they are decoded, and not kept (the model's largest part).
    let unchecked = io::ReadOptions {
        check_structure: false,
        keep_record_numbers: false,
        limits,
        ..io::ReadOptions::default()
    };
    let doc = io::read_path_with(path, &unchecked)?;
    let (diagnostics, counts) = ism_format::structure::check_counting_faces(
        &doc.model,
        ism_format::structure::DEFAULT_MAX_DIAGNOSTICS,
    );
    let errors: Vec<_> = diagnostics
        .into_iter()
        .filter(|d| d.severity == ism_format::Severity::Error)
        .collect();
    match counts {
        Some(counts) if errors.is_empty() => Ok((doc, counts)),
        _ => Err(ism_format::Error::Structure(errors)),
    }
}

/// Free numbers of a stage's face records: per record, its points less one coordinate per point
/// (they sum to 1), plus its weights. A table whose records all have the same lengths (as every
/// strata builder writes) is counted from those lengths, without visiting its millions of records.
fn record_freedom(faces: &ism_format::FaceTable) -> usize {
    let free = |face: usize, points: usize, weights: usize| points - points / face.max(1) + weights;
    match faces.uniform_lengths() {
        Some([face, points, weights]) => faces.len() * free(face, points, weights),
        // From the lengths: a table read without its numbers keeps them.
        None => (0..faces.len())
            .filter_map(|r| faces.lengths(r))
            .map(|[face, points, weights]| free(face, points, weights))
            .sum(),
    }
}

fn summarize(path: &std::path::Path, doc: &Document, faces: &[usize]) -> Summary {
    let model: &ism_format::Model = &doc.model;
    let n = model.dim();
    let mut bbox = vec![[f64::INFINITY, f64::NEG_INFINITY]; n];
    for v in model.vertices.chunks_exact(n) {
        for (b, &x) in bbox.iter_mut().zip(v) {
            b[0] = b[0].min(x);
            b[1] = b[1].max(x);
        }
    }
    let stages = model
        .stages
        .iter()
        .enumerate()
        .map(|(index, s)| StageSummary {
            index,
            kind: s.kind.as_str(),
            degree: s.degree,
            direction: match s.direction {
                ism_format::Direction::Implicit => "implicit",
                ism_format::Direction::Parametric => "parametric",
            },
            name: s.name.clone(),
            face_records: s.faces.len(),
            vertex_maps: s.vertex_maps.len(),
            stored_numbers: s.parameter_count(),
            // A control point on a k-face has k free coordinates (they sum to 1); weights are free
            // up to the per-face scale only for whole-face records, so count them all.
            degrees_of_freedom: record_freedom(&s.faces)
                + s.vertex_maps
                    .iter()
                    .map(|m| m.coefficients.len().saturating_sub(1))
                    .sum::<usize>(),
        })
        .collect();
    Summary {
        file: path.display().to_string(),
        encoding: doc.encoding.name(),
        version: model.version.clone(),
        container: doc.container,
        checksum: if doc.container.is_some() {
            "verified (CRC-32)"
        } else {
            "none (plain JSON)"
        },
        bytes: doc.byte_len,
        name: model.metadata.name.clone(),
        generator: model.metadata.generator.clone(),
        dimension: model.dimension,
        vertices: model.num_vertices(),
        simplices: model.num_simplices(),
        // Vertices: every vertex of the file (an unused one is only a warning).
        faces_by_dimension: std::iter::once(model.num_vertices())
            .chain(faces.iter().skip(1).copied())
            .collect(),
        level: model.level,
        inside_vertices: model.values.iter().filter(|&&v| v < model.level).count(),
        bounding_box: bbox,
        stages,
        extensions_used: model.extensions_used.clone(),
    }
}

pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let progress = crate::progress::Progress::new(args.quiet);
    progress.phase(format!("reading {}", args.file.display()));
    let (doc, faces) = match read_counting_faces(&args.file, args.limits.limits()) {
        Ok(doc) => doc,
        Err(ism_format::Error::Structure(errors)) => {
            progress.finish();
            eprintln!(
                "{}: the file decodes, but the model breaks {} structural rule(s) \
                 (spec/ism-format.md §9):",
                args.file.display(),
                errors.len()
            );
            for d in errors.iter().take(10) {
                eprintln!("  {d}");
            }
            if errors.len() > 10 {
                eprintln!(
                    "  … {} more; `ism validate` lists them all",
                    errors.len() - 10
                );
            }
            return Ok(ExitCode::from(1));
        }
        Err(e) => return Err(crate::args::cannot_read_model(&args.file, e)),
    };
    progress.phase("summarizing");
    let s = summarize(&args.file, &doc, &faces);
    progress.finish();
    if args.json {
        println!("{}", serde_json::to_string_pretty(&s)?);
        return Ok(ExitCode::SUCCESS);
    }
    println!("{}", s.file);
    println!(
        "  format      ISM {} ({}, {} bytes, checksum {})",
        s.version, s.encoding, s.bytes, s.checksum
    );
    if let Some(name) = &s.name {
        println!("  name        {name}");
    }
    if let Some(g) = &s.generator {
        println!("  generator   {g}");
    }
    let names = ["vertices", "edges", "triangles", "tetrahedra"];
    let faces: Vec<String> = s
        .faces_by_dimension
        .iter()
        .zip(names)
        .map(|(c, n)| format!("{c} {n}"))
        .collect();
    println!("  dimension   {}", s.dimension);
    println!(
        "  complex     {} top simplices; faces: {}",
        s.simplices,
        faces.join(", ")
    );
    println!(
        "  values      level {}, {} of {} vertices inside (f < level)",
        s.level, s.inside_vertices, s.vertices
    );
    let bbox: Vec<String> = s
        .bounding_box
        .iter()
        .map(|b| format!("[{}, {}]", b[0], b[1]))
        .collect();
    println!("  bbox        {}", bbox.join(" × "));
    if s.stages.is_empty() {
        println!("  stages      none (linear isocomplex)");
    }
    for st in &s.stages {
        let detail = if st.kind == "monotonic" {
            format!("{} vertex maps", st.vertex_maps)
        } else {
            format!("{} face records", st.face_records)
        };
        println!(
            "  stage {}     {} degree {} ({}), {detail}, {} stored numbers, {} degrees of freedom{}",
            st.index,
            st.kind,
            st.degree,
            st.direction,
            st.stored_numbers,
            st.degrees_of_freedom,
            st.name.as_ref().map(|n| format!(" — {n}")).unwrap_or_default()
        );
    }
    Ok(ExitCode::SUCCESS)
}

#[cfg(test)]
mod tests {
    use super::record_freedom;
    use ism_format::FaceTable;

    #[test]
    fn free_numbers_of_uniform_and_ragged_tables() {
        let mut table = FaceTable::new();
        assert_eq!(record_freedom(&table), 0);
        // Edge records of two points (2 coordinates each, one free) and two weights: 2 + 2 each.
        for r in 0..3 {
            table.push(&[r, r + 1], &[0.3, 0.7, 0.6, 0.4], &[1.0, 2.0]);
        }
        assert!(table.uniform_lengths().is_some());
        assert_eq!(record_freedom(&table), 12);
        // A triangle record of one point (3 coordinates, 2 free) and one weight: 3 more.
        table.push(&[0, 1, 2], &[0.2, 0.3, 0.5], &[1.5]);
        assert!(table.uniform_lengths().is_none());
        assert_eq!(record_freedom(&table), 15);
    }
}

//! `ism fit --hermite HANDLES`: free-form modeling from Hermite data (glue over
//! `ism_fit::hermite`). The handles file format is in `spec/hermite.md`.

use std::path::Path;
use std::process::ExitCode;

use anyhow::Context;
use ism_fit::hermite::{fit_hermite, HermiteData};
use ism_format::io;

/// Help text for `--hermite` (shown by `ism fit --help`).
pub const HELP: &str = "\
A JSON handles file (spec/hermite.md, schema spec/schema/hermite.schema.json): either a complex
(\"dimension\", flat \"vertices\", flat \"simplices\", nonzero \"values\", optional \"level\") or
\"model\": a path (relative to the file) of an .ism model to edit, with optional \"vertices\" /
\"values\" overrides; and \"handles\": per sign-changing edge {\"edge\": [a, b], \"t\": 0.4 | \"point\":
[x, y(, z)], \"normal\": [nx, ny(, nz)]} (t runs from a to b; the normal points outside, towards
larger values). Optional \"alpha\" (weight of the normal term, default 1) and \"iterations\"
(default 8), and \"adjustValues\": true to rescale |f(v)| (signs kept) so that every crossing
comes within reach of its edge map. Each crossing is met by its edge's control point (exactly when in reach of the
quadratic edge map), the normals by optimizing the other solitary points; the report gives
per-handle position and angle errors, and the written model is validated.";

/// Runs the Hermite fit. Exit 0 when the output validates, 1 when it does not, 2 (as an error)
/// for unreadable input or a failed write.
pub fn run(
    handles: &Path,
    output: Option<&Path>,
    svg: Option<&Path>,
    json: bool,
) -> anyhow::Result<ExitCode> {
    let output = output.context("missing --output")?;
    let text = std::fs::read_to_string(handles)
        .with_context(|| format!("cannot read {}", handles.display()))?;
    let data = HermiteData::from_json(&text).with_context(|| handles.display().to_string())?;
    let base = match &data.model {
        Some(rel) => {
            let path = handles.parent().unwrap_or(Path::new(".")).join(rel);
            let doc = io::read_path(&path)
                .with_context(|| format!("cannot read the model {}", path.display()))?;
            Some(doc.model)
        }
        None => None,
    };
    let model = data.base_model(base)?;
    if svg.is_some() && model.dim() != 2 {
        anyhow::bail!("--svg draws 2D models only; this one is {}D", model.dim());
    }
    let fitted = fit_hermite(&model, &data.handles, &data.options())?;
    io::write_path(&fitted.model, output, None, io::WriteOptions::default())
        .map_err(|e| crate::args::cannot_write_model(output, e))?;
    let r = &fitted.report;
    let verdict = ism_validate::validate(&fitted.model, &ism_validate::Options::default()).verdict;
    let simplices = fitted.model.num_simplices();
    if let Some(svg) = svg {
        let title = format!(
            "Hermite fit: {} handles, angle error max {:.2}° (before {:.2}°)",
            r.handles.len(),
            r.max_angle_after,
            r.max_angle_before
        );
        // The model is not needed after the picture: indexed by value, not copied (the error
        // is the one the picture's evaluator reported when it indexed a copy).
        let indexed = ism_format::IndexedModel::for_evaluation(fitted.model)
            .map_err(|e| ism_fit::FitError::Eval(e.into()))?;
        let picture = ism_fit::svg::picture(&indexed, &title)?;
        io::write_atomic(svg, |w| std::io::Write::write_all(w, picture.as_bytes()))
            .map_err(|e| crate::args::cannot_write(svg, &e))?;
    }
    let valid = verdict == ism_validate::Verdict::Valid;
    if json {
        let handles: Vec<_> = r
            .handles
            .iter()
            .map(|h| {
                serde_json::json!({
                    "edge": h.edge,
                    "target": h.target,
                    "achieved": h.achieved,
                    "positionError": h.position_error,
                    "angleBefore": h.angle_before,
                    "angleAfter": h.angle_after,
                })
            })
            .collect();
        let value = serde_json::json!({
            "handles": handles,
            "maxPositionError": r.max_position_error,
            "maxAngleBefore": r.max_angle_before,
            "maxAngleAfter": r.max_angle_after,
            "meanAngleBefore": r.mean_angle_before,
            "meanAngleAfter": r.mean_angle_after,
            "objectiveBefore": r.objective_before,
            "objectiveAfter": r.objective_after,
            "freeFaces": r.free_faces,
            "blockAdded": r.block_added,
            "valuesAdjusted": r.values_adjusted,
            "simplices": simplices,
            "verdict": verdict.as_str(),
            "seconds": r.seconds,
        });
        println!("{value}");
    } else {
        println!("wrote {}", output.display());
        println!(
            "  handles          {} on {} simplices, {} free control points optimized",
            r.handles.len(),
            simplices,
            r.free_faces
        );
        println!("  position error   max {:.3e}", r.max_position_error);
        println!(
            "  angle error      max {:.3}° mean {:.3}° (after placing the crossings: max {:.3}° mean {:.3}°)",
            r.max_angle_after, r.mean_angle_after, r.max_angle_before, r.mean_angle_before
        );
        println!(
            "  objective        {:.4e} -> {:.4e} in {:.2} s",
            r.objective_before, r.objective_after, r.seconds
        );
        for (i, h) in r.handles.iter().enumerate() {
            if h.position_error > 1e-9 {
                println!(
                    "  handle {i} (edge {:?}): crossing out of reach of the edge map, off by {:.3e} (see adjustValues)",
                    h.edge, h.position_error
                );
            }
        }
        println!("  validate         {}", verdict.as_str());
    }
    Ok(if valid {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(1)
    })
}

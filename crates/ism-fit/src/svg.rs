//! SVG pictures of 2D models in the spirit of the papers' figures: the complex, the vertex signs,
//! the linear isocontour, the control points of the stages, and the curved shape.

use std::fmt::Write as _;

use ism_format::IndexedModel;

use crate::isocontour::{patch_samples, Bary};

/// Picture size in pixels (the longer side).
const SIZE: f64 = 800.0;

/// Draws a 2D model. Returns the SVG text.
///
/// Takes the indexed model: the evaluator shares its index (no copy of the model) and the edges
/// of the complex are its topology's edge table.
///
/// # Errors
/// The kernel's error when the model does not evaluate; [`crate::FitError::Options`] when it is
/// not 2D.
pub fn picture(model: &IndexedModel, title: &str) -> Result<String, crate::FitError> {
    if model.dim() != 2 {
        return Err(crate::FitError::Options(
            "pictures are drawn for 2D models only".into(),
        ));
    }
    let eval = ism_geom::ModelEval::from_indexed(model).map_err(crate::FitError::Eval)?;
    let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
    for v in model.vertices.chunks_exact(2) {
        for k in 0..2 {
            lo[k] = lo[k].min(v[k]);
            hi[k] = hi[k].max(v[k]);
        }
    }
    let span = (hi[0] - lo[0]).max(hi[1] - lo[1]).max(f64::MIN_POSITIVE);
    let margin = 20.0;
    let scale = (SIZE - 2.0 * margin) / span;
    let width = (hi[0] - lo[0]) * scale + 2.0 * margin;
    let height = (hi[1] - lo[1]) * scale + 2.0 * margin + 24.0;
    // y grows downwards in SVG.
    let xy = |p: &[f64]| {
        (
            (p[0] - lo[0]) * scale + margin,
            (hi[1] - p[1]) * scale + margin + 24.0,
        )
    };
    let mut out = String::new();
    let _ = writeln!(
        out,
        r#"<svg xmlns="http://www.w3.org/2000/svg" width="{width:.0}" height="{height:.0}" viewBox="0 0 {width:.1} {height:.1}">"#
    );
    let _ = writeln!(out, r#"<rect width="100%" height="100%" fill="white"/>"#);
    let _ = writeln!(
        out,
        r#"<text x="{margin}" y="18" font-family="sans-serif" font-size="14">{}</text>"#,
        escape(title)
    );
    // Edges of the complex, each once, in increasing order of their sorted ids.
    let _ = write!(
        out,
        r##"<path fill="none" stroke="#bbbbbb" stroke-width="0.6" d=""##
    );
    for edge in model.topology().face_vertices(1).chunks_exact(2) {
        let (a, b) = (edge[0], edge[1]);
        let (x0, y0) = xy(model.vertex(a as usize));
        let (x1, y1) = xy(model.vertex(b as usize));
        let _ = write!(out, "M{x0:.2} {y0:.2}L{x1:.2} {y1:.2}");
    }
    let _ = writeln!(out, r#""/>"#);
    // Linear isocontour (dashed) and the curve (solid).
    let mut linear = String::new();
    let mut curve = String::new();
    for s in 0..model.num_simplices() {
        let Some(patch) = eval.patch(s) else { continue };
        let corners: Vec<Bary> = patch.corners.iter().map(|c| c.u).collect();
        let a = eval.point(s, &corners[0]);
        let b = eval.point(s, &corners[1]);
        let (x0, y0) = xy(&a);
        let (x1, y1) = xy(&b);
        let _ = write!(linear, "M{x0:.2} {y0:.2}L{x1:.2} {y1:.2}");
        for (i, u) in patch_samples(&corners, 24).iter().enumerate() {
            let p = eval.param_point(s, u).p;
            let (x, y) = xy(&p);
            let _ = write!(curve, "{}{x:.2} {y:.2}", if i == 0 { "M" } else { "L" });
        }
    }
    let _ = writeln!(
        out,
        r##"<path fill="none" stroke="#6a8fd0" stroke-width="1" stroke-dasharray="4 3" d="{linear}"/>"##
    );
    let _ = writeln!(
        out,
        r##"<path fill="none" stroke="#c0392b" stroke-width="2" d="{curve}"/>"##
    );
    // Control points: each face record's points at Σ b_i v_i.
    for stage in &model.stages {
        for rec in &stage.faces {
            let k = rec.face.len();
            for b in rec.points.chunks_exact(k) {
                let mut p = [0.0; 2];
                for (i, &v) in rec.face.iter().enumerate() {
                    let q = model.vertex(v as usize);
                    p[0] += b[i] * q[0];
                    p[1] += b[i] * q[1];
                }
                let (x, y) = xy(&p);
                let color = if k == 2 { "#27ae60" } else { "#8e44ad" };
                let _ = writeln!(
                    out,
                    r#"<circle cx="{x:.2}" cy="{y:.2}" r="2.2" fill="{color}"/>"#
                );
            }
        }
    }
    // Vertices by sign: filled inside, hollow outside.
    for (v, &f) in model.values.iter().enumerate() {
        let (x, y) = xy(model.vertex(v));
        let fill = if f < model.level { "#222222" } else { "white" };
        let _ = writeln!(
            out,
            r##"<circle cx="{x:.2}" cy="{y:.2}" r="1.8" fill="{fill}" stroke="#222222" stroke-width="0.6"/>"##
        );
    }
    out.push_str("</svg>\n");
    Ok(out)
}

fn escape(text: &str) -> String {
    text.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}

//! The written complex: only the simplices that hold the solid, and only the face records that
//! can move the shape.
//!
//! The fitter refines a Kuhn grid of the whole domain, but the file needs less (spec
//! `ism-format.md` §3.3): on a top simplex `σ` the function is `F(p) = Σ f(sᵢ) · X_σ(w)ᵢ` with
//! `X_σ(w) ∈ Δⁿ` (every stage is K-invariant), so `F` is a convex combination of the vertex values.
//!
//! - On a simplex whose vertices are all **outside** (`f > c`), `F > c` everywhere: it holds no
//!   point of the shape `O = {F = c}` nor of its interior `{F < c}`. Leaving it out changes
//!   neither; the faces it shares with a kept simplex have only outside vertices, so `F > c` there
//!   too and the shape stays closed inside the smaller `|K|`.
//! - A simplex whose vertices are all **inside** holds no point of the shape either, but it is part
//!   of the interior `{F < c}` — the solid that volume consumers (`ism sample --volume`, the
//!   volume export) read. It is kept.
//! - A face record (control points, weights) only changes `X_σ` on the simplices containing its
//!   face. If none of them is crossed (vertices of both signs), `F` keeps its sign on each of them
//!   whatever the record holds, so the record is dropped: the stage is the identity there, which is
//!   always a valid stage.
//!
//! Vertices no kept simplex uses are dropped and the rest renumbered in their old order, so
//! sorted face ids stay sorted, records stay in order, and every simplex keeps its stored vertex
//! order (orientation unchanged).

use std::collections::HashSet;

use ism_format::faces::FaceTable;
use ism_format::indexed::simplex_faces;
use ism_format::model::Model;

/// How many vertices of each simplex (`m` ids each in `simplices`) are inside (`f < c`):
/// [`shell`] keeps those with at least one, unless none has (then it keeps every simplex).
fn inside_counts(simplices: &[u32], m: usize, values: &[f64], c: f64) -> Vec<usize> {
    let inside = |v: u32| values.get(v as usize).is_some_and(|&f| f < c);
    simplices
        .chunks_exact(m)
        .map(|s| s.iter().filter(|&&v| inside(v)).count())
        .collect()
}

/// Which simplices [`shell`] keeps, in order, of a model with these `simplices` (`m` ids each),
/// vertex `values` and level `c` — without building the model.
pub fn kept_simplices(simplices: &[u32], m: usize, values: &[f64], c: f64) -> Vec<bool> {
    let counts = inside_counts(simplices, m, values, c);
    let any = counts.iter().any(|&k| k > 0);
    counts.iter().map(|&k| k > 0 || !any).collect()
}

/// The model restricted to the simplices with at least one inside vertex (see the module doc).
/// Returns the model unchanged when no simplex has an inside vertex (nothing to keep).
pub fn shell(model: &Model) -> Model {
    let m = model.dim() + 1;
    let mut kept: Vec<u32> = Vec::with_capacity(model.simplices.len());
    let mut crossed_faces: HashSet<Vec<u32>> = HashSet::new();
    let counts = inside_counts(&model.simplices, m, &model.values, model.level);
    for (s, ins) in model.simplex_iter().zip(counts) {
        if ins == 0 {
            continue;
        }
        kept.extend_from_slice(s);
        if ins < m {
            crossed_faces.extend(simplex_faces(s, 1).map(|f| f.ids().to_vec()));
        }
    }
    if kept.is_empty() {
        return model.clone();
    }
    // New ids in the old order (monotone, so sorted faces stay sorted).
    let nv = model.num_vertices();
    let mut used = vec![false; nv];
    for &v in &kept {
        used[v as usize] = true;
    }
    let mut new_id = vec![u32::MAX; nv];
    let mut next = 0u32;
    for (v, &u) in used.iter().enumerate() {
        if u {
            new_id[v] = next;
            next += 1;
        }
    }
    let n = model.dim();
    let mut out = model.clone();
    out.vertices = (0..nv)
        .filter(|&v| used[v])
        .flat_map(|v| model.vertex(v).iter().copied())
        .collect();
    out.values = (0..nv)
        .filter(|&v| used[v])
        .map(|v| model.values[v])
        .collect();
    debug_assert_eq!(out.vertices.len(), next as usize * n);
    out.simplices = kept.iter().map(|&v| new_id[v as usize]).collect();
    for stage in &mut out.stages {
        let mut faces = FaceTable::with_capacity(stage.faces.len());
        for r in stage.faces.iter() {
            if !crossed_faces.contains(r.face) {
                continue;
            }
            let ids: Vec<u32> = r.face.iter().map(|&v| new_id[v as usize]).collect();
            faces.push(&ids, r.points, r.weights);
        }
        stage.faces = faces;
        stage.vertex_maps.retain(|map| {
            map.vertex
                .try_into()
                .ok()
                .and_then(|v: usize| used.get(v).copied())
                .unwrap_or(false)
        });
        for map in &mut stage.vertex_maps {
            map.vertex = new_id[map.vertex as usize];
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use ism_format::model::{Model, Stage, StageKind};

    fn no_errors(model: &Model) {
        let errors: Vec<_> = ism_format::structure::check(model, 100)
            .into_iter()
            .filter(|d| d.severity == ism_format::Severity::Error)
            .collect();
        assert!(errors.is_empty(), "{errors:?}");
    }

    /// `F` of `shell` agrees with `F` of `full` wherever `shell` is defined, and `full` is
    /// outside (`F > c`) wherever it is not: the same shape and the same solid.
    fn same_solid(full: &Model, shell: &Model, lo: [f64; 2], hi: [f64; 2], steps: usize) {
        let (a, b) = (
            ism_geom::ModelEval::new(full).unwrap(),
            ism_geom::ModelEval::new(shell).unwrap(),
        );
        let mut dropped = 0;
        for i in 0..=steps {
            for j in 0..=steps {
                let t = [i as f64 / steps as f64, j as f64 / steps as f64];
                let p = [
                    lo[0] + t[0] * (hi[0] - lo[0]),
                    lo[1] + t[1] * (hi[1] - lo[1]),
                ];
                let f = a.value(&p).expect("the full model covers its box");
                match b.value(&p) {
                    Some(g) => assert!((f - g).abs() <= 1e-12 * (1.0 + f.abs()), "{p:?}: {f} {g}"),
                    None => {
                        assert!(f > full.level, "{p:?}: dropped but F = {f}");
                        dropped += 1;
                    }
                }
            }
        }
        assert!(dropped > 0, "the test should reach a dropped simplex");
    }

    #[test]
    fn drops_outside_simplices_and_records_of_uncrossed_faces_and_renumbers() {
        // A 4 × 1 strip of squares, two triangles each; columns x = 0, 1, 2, 3, 4. Values: −1 at
        // x ≤ 1, +1 at x ≥ 2, so square [0,1] is inside, [1,2] crossed, [2,3] and [3,4] outside.
        // The outside column x = 4 gets the lowest ids, to exercise renumbering.
        let xs = [4.0, 0.0, 1.0, 2.0, 3.0];
        let mut model = Model::new(2);
        for &x in &xs {
            model.vertices.extend([x, 0.0]);
            model.values.push(if x <= 1.0 { -1.0 } else { 1.0 });
        }
        for &x in &xs {
            model.vertices.extend([x, 1.0]);
            model.values.push(if x <= 1.0 { -1.0 } else { 1.0 });
        }
        // Vertex at (column k, row r): id of column k in `xs`, + 5 for the top row.
        let id = |x: f64, r: u32| xs.iter().position(|&c| c == x).unwrap() as u32 + 5 * r;
        for k in 0..4 {
            let x = k as f64;
            let (a, b, c, d) = (id(x, 0), id(x + 1.0, 0), id(x + 1.0, 1), id(x, 1));
            model.simplices.extend([a, b, c, a, c, d]);
        }
        let mut stage = Stage::identity(StageKind::Bezier, 2);
        // Edge records: on the inside square (dropped), on the crossed square's diagonal and on
        // the edge x = 2 it shares with an outside square (kept), on an outside square (dropped).
        let mut edges = [
            [id(0.0, 0), id(1.0, 1)],
            [id(1.0, 0), id(2.0, 1)],
            [id(2.0, 0), id(2.0, 1)],
            [id(3.0, 0), id(4.0, 1)],
        ];
        for e in &mut edges {
            e.sort_unstable();
        }
        edges.sort_unstable();
        for e in &edges {
            stage.faces.push(e, &[0.3, 0.7], &[]);
        }
        model.stages.push(stage);
        no_errors(&model);

        let out = shell(&model);
        no_errors(&out);
        // Two inside and two crossed triangles; the columns x = 3, 4 are gone.
        assert_eq!(out.num_simplices(), 4);
        assert_eq!(out.num_vertices(), 6);
        assert!(out.vertices.chunks(2).all(|p| p[0] <= 2.0));
        let kept: Vec<Vec<f64>> = out.stages[0]
            .faces
            .iter()
            .map(|r| {
                r.face
                    .iter()
                    .flat_map(|&v| out.vertex(v as usize).to_vec())
                    .collect()
            })
            .collect();
        let mut expect = vec![vec![1.0, 0.0, 2.0, 1.0], vec![2.0, 0.0, 2.0, 1.0]];
        let mut got = kept.clone();
        got.sort_by(|a, b| a.partial_cmp(b).unwrap());
        expect.sort_by(|a, b| a.partial_cmp(b).unwrap());
        assert_eq!(got, expect);
        same_solid(&model, &out, [0.0, 0.0], [4.0, 1.0], 40);
    }

    #[test]
    fn a_fitted_circle_keeps_its_shape_on_fewer_simplices() {
        let preset = crate::Preset::find("circle").unwrap();
        let g = preset.expression().unwrap();
        let mut options = crate::FitOptions::new(preset.domain);
        options.resolution = 6;
        options.tolerance = 1e-3;
        let fitted = crate::fit(&g, &options, &ism_format::Progress::none()).unwrap();
        let full = fitted.full_model("circle");
        let out = fitted.to_model("circle");
        no_errors(&out);
        assert!(out.num_simplices() < full.num_simplices());
        assert!(crate::fit::stored_numbers(&out) < crate::fit::stored_numbers(&full));
        let d = preset.domain;
        same_solid(&full, &out, [d[0], d[2]], [d[1], d[3]], 60);
    }
}

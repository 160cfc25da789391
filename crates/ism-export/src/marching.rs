//! Marching triangles / tetrahedra: the linear isocomplex `f̂⁻¹(c)`, the piecewise-linear shape
//! before any stage. It is the topology reference of [`crate::extract`] (same components, same
//! Euler characteristic) and the lower bound of extraction cost.
//!
//! Works on the [`Model`] alone (no evaluator, no spatial index): one crossing point per crossed
//! K-edge, welded by the edge, one segment / triangle / quad (two triangles) per crossed simplex,
//! oriented so normals point to `f̂ > c`.

use std::collections::HashMap;

use ism_format::Model;
use rayon::prelude::*;

use crate::mesh::{cross, dot, sub, Mesh, Primitive};
use crate::{Error, Result};

/// Extracts the linear isocomplex of `model` (stages ignored). Normals are the PL gradient's
/// direction; `gradient_norm` its length.
///
/// # Errors
/// [`Error::Unsupported`] for a dimension other than 2 or 3, or simplices/values that do not fit
/// the vertex array.
pub fn marching(model: &Model) -> Result<Mesh> {
    let n = model.dim();
    if n != 2 && n != 3 {
        return Err(Error::Unsupported(format!(
            "marching needs a 2D or 3D model, got dimension {n}"
        )));
    }
    let nv = model.num_vertices();
    if model.values.len() != nv || model.simplices.iter().any(|&v| v as usize >= nv) {
        return Err(Error::Unsupported(
            "values or simplex ids do not match the vertex array".into(),
        ));
    }
    let c = model.level;
    let pos = |v: u32| {
        let q = model.vertex(v as usize);
        [q[0], q[1], if n == 3 { q[2] } else { 0.0 }]
    };
    struct Piece {
        simplex: u32,
        /// Corners as (inside vertex, outside vertex) global ids, oriented.
        corners: Vec<(u32, u32)>,
        gradient: [f64; 3],
    }
    let pieces: Vec<Piece> = (0..model.num_simplices())
        .into_par_iter()
        .filter_map(|s| {
            let ids = model.simplex(s);
            let inside: Vec<u32> = ids
                .iter()
                .copied()
                .filter(|&v| model.values[v as usize] < c)
                .collect();
            let outside: Vec<u32> = ids
                .iter()
                .copied()
                .filter(|&v| model.values[v as usize] >= c)
                .collect();
            if inside.is_empty() || outside.is_empty() {
                return None;
            }
            let mut corners: Vec<(u32, u32)> = if inside.len() == 2 && outside.len() == 2 {
                vec![
                    (inside[0], outside[0]),
                    (inside[0], outside[1]),
                    (inside[1], outside[1]),
                    (inside[1], outside[0]),
                ]
            } else {
                inside
                    .iter()
                    .flat_map(|&a| outside.iter().map(move |&b| (a, b)))
                    .collect()
            };
            let g = pl_gradient(model, ids);
            let cp = |(a, b): (u32, u32)| {
                crossing(
                    pos(a),
                    pos(b),
                    model.values[a as usize] - c,
                    model.values[b as usize] - c,
                )
            };
            let d1 = sub(cp(corners[1]), cp(corners[0]));
            let normal = if n == 2 {
                [d1[1], -d1[0], 0.0]
            } else {
                cross(d1, sub(cp(corners[2]), cp(corners[0])))
            };
            if dot(normal, g) < 0.0 {
                corners.reverse();
            }
            Some(Piece {
                simplex: s as u32,
                corners,
                gradient: g,
            })
        })
        .collect();
    let mut mesh = Mesh::new(
        n,
        if n == 2 {
            Primitive::Segments
        } else {
            Primitive::Triangles
        },
    );
    let mut index: HashMap<(u32, u32), u32> = HashMap::with_capacity(pieces.len() * 2);
    for piece in &pieces {
        let len = dot(piece.gradient, piece.gradient).sqrt();
        let ids: Vec<u32> = piece
            .corners
            .iter()
            .map(|&(a, b)| {
                *index.entry((a, b)).or_insert_with(|| {
                    mesh.positions.push(crossing(
                        pos(a),
                        pos(b),
                        model.values[a as usize] - c,
                        model.values[b as usize] - c,
                    ));
                    mesh.normals.push(if len > 0.0 {
                        piece.gradient.map(|x| x / len)
                    } else {
                        [0.0; 3]
                    });
                    mesh.gradient_norm.push(len);
                    mesh.vertex_simplex.push(piece.simplex);
                    (mesh.positions.len() - 1) as u32
                })
            })
            .collect();
        match ids.len() {
            2 => mesh.cells.extend_from_slice(&ids),
            3 => mesh.cells.extend_from_slice(&ids),
            _ => {
                // Quad: the shorter diagonal.
                let p = |i: u32| mesh.positions[i as usize];
                let d02 = sub(p(ids[0]), p(ids[2]));
                let d13 = sub(p(ids[1]), p(ids[3]));
                if dot(d02, d02) <= dot(d13, d13) {
                    mesh.cells
                        .extend_from_slice(&[ids[0], ids[1], ids[2], ids[0], ids[2], ids[3]]);
                } else {
                    mesh.cells
                        .extend_from_slice(&[ids[0], ids[1], ids[3], ids[1], ids[2], ids[3]]);
                }
                mesh.cell_simplex.push(piece.simplex);
            }
        }
        mesh.cell_simplex.push(piece.simplex);
    }
    Ok(mesh)
}

/// The zero of the linear interpolant on edge `a → b` with `fa < 0 ≤ fb` (values minus `c`).
fn crossing(a: [f64; 3], b: [f64; 3], fa: f64, fb: f64) -> [f64; 3] {
    let t = fa / (fa - fb);
    [
        a[0] + t * (b[0] - a[0]),
        a[1] + t * (b[1] - a[1]),
        a[2] + t * (b[2] - a[2]),
    ]
}

/// Gradient of the linear interpolant of the values on one simplex (3-vector; z = 0 in 2D).
fn pl_gradient(model: &Model, ids: &[u32]) -> [f64; 3] {
    let n = model.dim();
    let v0 = model.vertex(ids[0] as usize);
    let f0 = model.values[ids[0] as usize];
    // Solve E^T g = df with E the edge vectors from v0 (rows).
    let mut e = [[0.0f64; 3]; 3];
    let mut df = [0.0f64; 3];
    for k in 0..n {
        let vk = model.vertex(ids[k + 1] as usize);
        for x in 0..n {
            e[k][x] = vk[x] - v0[x];
        }
        df[k] = model.values[ids[k + 1] as usize] - f0;
    }
    if n == 2 {
        let det = e[0][0] * e[1][1] - e[0][1] * e[1][0];
        return [
            (df[0] * e[1][1] - df[1] * e[0][1]) / det,
            (e[0][0] * df[1] - e[1][0] * df[0]) / det,
            0.0,
        ];
    }
    // Cramer's rule on the 3 × 3 system E g = df.
    let det = dot(e[0], cross(e[1], e[2]));
    let cols = |k: usize| [e[0][k], e[1][k], e[2][k]];
    let (c0, c1, c2) = (cols(0), cols(1), cols(2));
    [
        dot(df, cross(c1, c2)) / det,
        dot(c0, cross(df, c2)) / det,
        dot(c0, cross(c1, df)) / det,
    ]
}

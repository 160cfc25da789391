//! Extraction against the topology reference (marching) and the implicit form (distance to O),
//! on every named example.

use ism_export::extract::{extract, extract_coarsened, ExtractOptions};
use ism_export::marching::marching;
use ism_export::mesh::{Mesh, Primitive};
use ism_export::Result;
use ism_geom::ModelEval;

/// Distance from `p` to `O` estimated by Newton projection along ∇F: iterate
/// `p ← p − (F − c) ∇F / |∇F|²` and return the total displacement. `None` if the iteration leaves
/// the complex.
fn distance_to_shape(eval: &ModelEval, p: [f64; 3]) -> Option<f64> {
    let n = eval.dim();
    let c = eval.model().level;
    let mut q = p;
    for _ in 0..8 {
        let f = eval.value(&q[..n])? - c;
        let g = eval.gradient(&q[..n])?;
        let g2: f64 = g.iter().map(|x| x * x).sum();
        if f == 0.0 || g2 == 0.0 {
            break;
        }
        for k in 0..n {
            q[k] -= f * g[k] / g2;
        }
    }
    Some((0..3).map(|k| (q[k] - p[k]).powi(2)).sum::<f64>().sqrt())
}

fn examples() -> Vec<(&'static str, ism_format::Model)> {
    ism_examples::named::all_examples()
}

type Extractor =
    fn(&ModelEval, &ExtractOptions) -> Result<(Mesh, ism_export::extract::ExtractReport)>;

/// Both extractions: refined, and refined then coarsened.
const EXTRACTORS: [(&str, Extractor); 2] = [("refined", extract), ("coarsened", extract_coarsened)];

#[test]
fn every_example_keeps_the_linear_topology_and_lies_on_the_shape() {
    for ((name, model), (how, extract)) in examples()
        .into_iter()
        .flat_map(|e| EXTRACTORS.map(|x| (e.clone(), x)))
    {
        let name = format!("{name} ({how})");
        let eval = ModelEval::new(&model).unwrap();
        let linear = marching(&model).unwrap().topology();
        let options = ExtractOptions {
            tolerance: 2e-3,
            max_depth: 6,
        };
        let (mesh, report) = extract(&eval, &options).unwrap();
        let t = mesh.topology();
        assert_eq!(
            (t.components, t.euler_characteristic),
            (linear.components, linear.euler_characteristic),
            "{name}"
        );
        assert_eq!(t.boundary_edges, linear.boundary_edges, "{name}: {t:?}");
        assert_eq!(
            (
                t.non_manifold_edges,
                t.orientation_conflicts,
                t.degenerate_cells
            ),
            (0, 0, 0),
            "{name}: {t:?}"
        );
        assert!(report.max_residual < 1e-10, "{name}: {report:?}");
        let worst = mesh
            .positions
            .iter()
            .map(|&p| distance_to_shape(&eval, p).unwrap())
            .fold(0.0, f64::max);
        assert!(worst < 1e-9, "{name}: vertex {worst:e} from O");
        if linear.is_closed_oriented_manifold() {
            assert!(t.is_closed_oriented_manifold(), "{name}: {t:?}");
            assert!(mesh.enclosed_measure() > 0.0, "{name}: outward orientation");
        }
        // Normals agree with the cells' orientation (outward).
        if mesh.primitive == Primitive::Triangles {
            let agree = mesh
                .cell_iter()
                .filter(|c| {
                    let [a, b, d] = [0, 1, 2].map(|k| mesh.positions[c[k] as usize]);
                    let e1 = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
                    let e2 = [d[0] - a[0], d[1] - a[1], d[2] - a[2]];
                    let nrm = [
                        e1[1] * e2[2] - e1[2] * e2[1],
                        e1[2] * e2[0] - e1[0] * e2[2],
                        e1[0] * e2[1] - e1[1] * e2[0],
                    ];
                    let avg: Vec<f64> = (0..3)
                        .map(|k| c.iter().map(|&v| mesh.normals[v as usize][k]).sum())
                        .collect();
                    nrm[0] * avg[0] + nrm[1] * avg[1] + nrm[2] * avg[2] > 0.0
                })
                .count();
            assert!(
                agree as f64 >= 0.99 * mesh.num_cells() as f64,
                "{name}: {agree} of {} cells agree with ∇F",
                mesh.num_cells()
            );
        }
    }
}

fn named(name: &str) -> ism_format::Model {
    examples().into_iter().find(|(n, _)| *n == name).unwrap().1
}

/// Largest estimated distance from an edge midpoint of the mesh to O.
fn worst_chord(eval: &ModelEval, mesh: &Mesh) -> f64 {
    let mut worst = 0.0f64;
    for c in mesh.cell_iter() {
        let k = c.len();
        for i in 0..k {
            let (a, b) = (
                mesh.positions[c[i] as usize],
                mesh.positions[c[(i + 1) % k] as usize],
            );
            let m = [
                (a[0] + b[0]) / 2.0,
                (a[1] + b[1]) / 2.0,
                (a[2] + b[2]) / 2.0,
            ];
            if let Some(d) = distance_to_shape(eval, m) {
                worst = worst.max(d);
            }
        }
    }
    worst
}

#[test]
fn sphere_and_torus_are_closed_with_euler_two_and_zero_and_meet_the_tolerance() {
    for (name, euler) in [("sphere", 2), ("torus", 0)] {
        let model = named(name);
        let eval = ModelEval::new(&model).unwrap();
        let mut counts = Vec::new();
        for tol in [4e-3, 2e-3, 1e-3] {
            let (mesh, report) = extract(
                &eval,
                &ExtractOptions {
                    tolerance: tol,
                    max_depth: 14,
                },
            )
            .unwrap();
            let t = mesh.topology();
            assert!(t.is_closed_oriented_manifold(), "{name} {tol}: {t:?}");
            assert_eq!((t.components, t.euler_characteristic), (1, euler), "{name}");
            assert_eq!(report.depth_limited_edges, 0, "{name} {tol}");
            assert_eq!(report.depth_limited_error, 0.0, "{name} {tol}");
            let chord = worst_chord(&eval, &mesh);
            // The criterion bounds the distance from the chord to the mapped parameter midpoint,
            // which is on O; the Newton estimate of the distance to O can only be smaller, up to
            // its first-order error.
            assert!(
                chord <= 1.1 * tol,
                "{name} tol {tol}: an edge midpoint is {chord:e} from O"
            );
            counts.push(mesh.num_cells());
        }
        eprintln!("{name}: triangles at tolerance 4e-3, 2e-3, 1e-3: {counts:?}");
        assert!(
            counts[0] < counts[1] && counts[1] < counts[2],
            "{name}: {counts:?}"
        );
    }
}

#[test]
fn curve_examples_give_closed_counter_clockwise_polylines() {
    let model = named("circle-curved");
    let eval = ModelEval::new(&model).unwrap();
    let (mesh, _) = extract(
        &eval,
        &ExtractOptions {
            tolerance: 1e-4,
            max_depth: 12,
        },
    )
    .unwrap();
    let t = mesh.topology();
    assert_eq!(mesh.primitive, Primitive::Segments);
    assert!(t.is_closed_oriented_manifold(), "{t:?}");
    assert_eq!((t.components, t.euler_characteristic), (1, 0));
    // The circle of radius 0.28: the fitted curve's area is close to π r².
    let area = mesh.enclosed_measure();
    assert!(
        (area - std::f64::consts::PI * 0.28 * 0.28).abs() < 0.02,
        "area {area}"
    );
}

#[test]
fn max_depth_zero_maps_only_the_patch_corners() {
    let model = named("sphere");
    let eval = ModelEval::new(&model).unwrap();
    let (mesh, _) = extract(
        &eval,
        &ExtractOptions {
            tolerance: 1e-6,
            max_depth: 0,
        },
    )
    .unwrap();
    let linear = marching(&model).unwrap();
    assert_eq!(mesh.num_vertices(), linear.num_vertices());
    assert_eq!(mesh.num_cells(), linear.num_cells());
}

/// Coarsening only removes vertices inside patches: never more cells than the refined mesh, the
/// same vertices on the patches' boundaries, and on curved 3D examples strictly fewer triangles.
#[test]
fn coarsening_removes_triangles_and_keeps_the_boundary_vertices() {
    for (name, model) in examples() {
        let eval = ModelEval::new(&model).unwrap();
        let options = ExtractOptions {
            tolerance: 1e-3,
            max_depth: 8,
        };
        let (fine, _) = extract(&eval, &options).unwrap();
        let (coarse, _) = extract_coarsened(&eval, &options).unwrap();
        assert!(coarse.num_cells() <= fine.num_cells(), "{name}");
        if fine.primitive == Primitive::Triangles && ["sphere", "torus"].contains(&name) {
            assert!(
                (coarse.num_cells() as f64) < 0.9 * fine.num_cells() as f64,
                "{name}: {} of {} triangles",
                coarse.num_cells(),
                fine.num_cells()
            );
        }
        // Every vertex on a patch boundary (used by cells of two simplices) is kept, bit for bit.
        let shared = |m: &Mesh| {
            let mut owner: Vec<Option<u32>> = vec![None; m.positions.len()];
            let mut on_boundary = vec![false; m.positions.len()];
            let arity = m.primitive.arity();
            for (i, &s) in m.cell_simplex.iter().enumerate() {
                for &v in &m.cells[i * arity..(i + 1) * arity] {
                    match owner[v as usize] {
                        None => owner[v as usize] = Some(s),
                        Some(o) if o != s => on_boundary[v as usize] = true,
                        _ => {}
                    }
                }
            }
            let mut pts: Vec<[u64; 3]> = m
                .positions
                .iter()
                .zip(&on_boundary)
                .filter(|(_, &b)| b)
                .map(|(p, _)| p.map(f64::to_bits))
                .collect();
            pts.sort_unstable();
            pts
        };
        assert_eq!(shared(&fine), shared(&coarse), "{name}");
    }
}

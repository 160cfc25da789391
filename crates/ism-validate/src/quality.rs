//! Layer 4: quality (warnings and infos, `--quality`; spec/validation.md §5). Nothing here makes a
//! file invalid.
//!
//! - ISM-401: the angle between the normals of `O` computed in the two simplices of an interior
//!   facet, at points of `O` on the facet (Mello & Velho 2009 §8: the normal of a curved isocomplex jumps unless
//!   the stages are fitted to avoid it).
//! - ISM-402: the C¹ residual of a rational stage at an interior facet, Mello & Velho 2009 §8 eq. (6), with
//!   `f̂(b_I) = Σ f(vᵢ) b_Iⁱ` for general control points.
//! - ISM-403: the range of `det DX` of each stage, sampled.

use ism_format::{multi_index, IndexedModel, Location, Model, Rule, StageKind};
use rayon::prelude::*;

use crate::net::StageIndex;
use crate::report::{Message, NormalJumps, QualityStats, StageReport};

/// A facet whose normals differ by more than this many degrees gets an ISM-401 warning: below
/// about 5° shading hides a crease, so smaller jumps are reported only in the totals.
pub const NORMAL_JUMP_WARN_DEGREES: f64 = 5.0;

/// A rational stage's C¹ residual, relative to `max |f| · max q` of the two simplices, above which
/// a facet gets an ISM-402 warning. The residual of a fitted (smoothed) stage is a least-squares
/// optimum, not zero; 1e-6 separates "solved" from "not attempted".
pub const C1_RELATIVE_TOLERANCE: f64 = 1e-6;

/// Points of `O` sampled per 3D facet (along the segment `θ ∩ δ`); a 2D facet has one.
const FACET_SAMPLES_3D: usize = 5;

/// Lattice degree of the `det DX` samples per simplex (35 points in a tetrahedron).
const DET_SAMPLE_DEGREE: u32 = 4;

/// An interior facet: sorted key and `[(simplex, opposite local position); 2]`.
type InteriorFacet = ([u32; 4], [(usize, usize); 2]);

/// The interior facets (shared by exactly two simplices), from the topology's facet neighbours,
/// in increasing order of their sorted vertex ids.
fn interior_facets(indexed: &IndexedModel) -> Vec<InteriorFacet> {
    let model: &Model = indexed;
    let topology = indexed.topology();
    let m = model.dim() + 1;
    let mut out: Vec<InteriorFacet> = (0..model.num_simplices())
        .into_par_iter()
        .flat_map_iter(|s| {
            let ids = model.simplex(s);
            (0..m).filter_map(move |skip| {
                let t = topology.neighbour(s, skip)?.0 as usize;
                if t < s {
                    return None; // each facet once, from its lower simplex
                }
                let mut key = [u32::MAX; 4];
                let mut len = 0;
                for (i, &id) in ids.iter().enumerate() {
                    if i != skip {
                        key[len] = id;
                        len += 1;
                    }
                }
                key[..len].sort_unstable();
                let other = model.simplex(t);
                let t_skip = (0..m).find(|&i| !key[..len].contains(&other[i]))?;
                Some((key, [(s, skip), (t, t_skip)]))
            })
        })
        .collect();
    out.par_sort_unstable();
    out
}

fn angle_degrees(a: &[f64; 3], b: &[f64; 3]) -> Option<f64> {
    let dot: f64 = (0..3).map(|i| a[i] * b[i]).sum();
    let na: f64 = a.iter().map(|x| x * x).sum::<f64>().sqrt();
    let nb: f64 = b.iter().map(|x| x * x).sum::<f64>().sqrt();
    if na == 0.0 || nb == 0.0 || !na.is_finite() || !nb.is_finite() {
        return None;
    }
    Some((dot / (na * nb)).clamp(-1.0, 1.0).acos().to_degrees())
}

/// Quality findings; fills `det_range` of the stage reports. Stages that failed earlier layers
/// (`stage_ok[k] == false`) are skipped, and normal jumps need every stage valid.
pub fn check(
    indexed: &IndexedModel,
    stages: &mut [StageReport],
    stage_ok: &[bool],
) -> (Vec<Message>, QualityStats) {
    let mut stats = QualityStats::default();
    let model: &Model = indexed;
    let mut out = Vec::new();
    let n = model.dim();
    let m = n + 1;
    let facets = interior_facets(indexed);
    let eval = ism_geom::ModelEval::from_indexed(indexed).ok();

    // ISM-403: det DX range per stage.
    for (k, _) in stage_ok.iter().enumerate().filter(|(_, &ok)| ok) {
        let lattice: Vec<[f64; 4]> = multi_index::all(m, DET_SAMPLE_DEGREE)
            .chunks(m)
            .map(|i| {
                let mut w = [0.0; 4];
                for c in 0..m {
                    w[c] = f64::from(i[c]) / f64::from(DET_SAMPLE_DEGREE);
                }
                w
            })
            .collect();
        let (lo, hi) = (0..model.num_simplices())
            .into_par_iter()
            .map(|s| {
                let Ok(local) = ism_geom::LocalStage::from_indexed(indexed, k, s) else {
                    return (f64::NAN, f64::NAN);
                };
                if local.is_identity() {
                    return (1.0, 1.0);
                }
                lattice
                    .iter()
                    .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), w| {
                        let (_, j) = local.jacobian_stored(w);
                        let det = ism_geom::linalg::det(n, &j);
                        (lo.min(det), hi.max(det))
                    })
            })
            .reduce(
                || (f64::INFINITY, f64::NEG_INFINITY),
                |a, b| (a.0.min(b.0), a.1.max(b.1)),
            );
        if let Some(st) = stages.iter_mut().find(|st| st.index == k) {
            st.det_range = Some([lo, hi]);
        }
        let mut msg = Message::new(
            Rule::JacobianRange,
            Location { stage: Some(k), ..Location::pointer(format!("/stages/{k}")) },
            format!("det DX of the stored map ranges over [{lo:.6e}, {hi:.6e}] (sampled at degree-{DET_SAMPLE_DEGREE} lattice points)"),
        );
        msg.value = Some(lo);
        out.push(msg);
    }

    // ISM-402: C¹ residual of rational stages.
    for (k, stage) in model.stages.iter().enumerate() {
        if !stage_ok[k] || stage.kind != StageKind::Rational {
            continue;
        }
        let index = StageIndex::new(indexed, k);
        let d = stage.degree;
        let found: Vec<Message> = facets
            .par_iter()
            .filter_map(|(key, sides)| {
                let (s1, a1) = sides[0];
                let (s2, _) = sides[1];
                let net1 = index.dense_net(s1, &index.records(s1));
                let net2 = index.dense_net(s2, &index.records(s2));
                let ids1 = model.simplex(s1);
                let ids2 = model.simplex(s2);
                // The condition is about the shape F = c, so about f − c, and only where the shape
                // meets the facet (its vertex values straddle the level).
                let level = model.level;
                let facet_values = || key[..n].iter().map(|&v| model.values[v as usize] - level);
                if !(facet_values().any(|x| x < 0.0) && facet_values().any(|x| x > 0.0)) {
                    return None;
                }
                let f1: Vec<f64> = ids1.iter().map(|&v| model.values[v as usize] - level).collect();
                let f2: Vec<f64> = ids2.iter().map(|&v| model.values[v as usize] - level).collect();
                let fhat = |f: &[f64], b: &[f64; 4]| (0..m).map(|i| f[i] * b[i]).sum::<f64>();
                let p0 = model.vertex(ids1[a1] as usize);
                let w = eval.as_ref()?.barycentric(s2, p0);
                let mut err = 0.0;
                let mut scale = 0.0f64;
                for j in multi_index::all(m, d - 1).chunks(m) {
                    if j[a1] != 0 {
                        continue;
                    }
                    let mut i1 = j.to_vec();
                    i1[a1] += 1;
                    let r1 = multi_index::rank(&i1);
                    let lhs = net1.weights[r1] * fhat(&f1, &net1.points[r1]);
                    // J in σ′'s local positions.
                    let mut j2 = vec![0u32; m];
                    for (pos, &e) in j.iter().enumerate() {
                        if e > 0 {
                            let p2 = ids2.iter().position(|&v| v == ids1[pos]).expect("facet vertex in both simplices");
                            j2[p2] = e;
                        }
                    }
                    let mut rhs = 0.0;
                    for (i, wi) in w.iter().enumerate().take(m) {
                        let mut i2 = j2.clone();
                        i2[i] += 1;
                        let r2 = multi_index::rank(&i2);
                        rhs += wi * net2.weights[r2] * fhat(&f2, &net2.points[r2]);
                    }
                    err += (lhs - rhs).powi(2);
                    scale = scale.max(net1.weights[r1].abs());
                }
                let fmax = f1.iter().chain(&f2).fold(0.0f64, |a, &x| a.max(x.abs()));
                let relative = err.sqrt() / (fmax * scale.max(f64::MIN_POSITIVE));
                (relative > C1_RELATIVE_TOLERANCE).then(|| {
                    let face: Vec<u32> = key[..n].to_vec();
                    let mut msg = Message::new(
                        Rule::RationalC1,
                        Location { stage: Some(k), simplex: Some(s1), face: Some(face), ..Location::pointer(format!("/stages/{k}")) },
                        format!("C¹ residual sqrt(err) = {:.3e} (relative {relative:.3e}) between simplices {s1} and {s2}", err.sqrt()),
                    );
                    msg.value = Some(relative);
                    msg
                })
            })
            .collect();
        out.extend(found);
    }

    // ISM-401: normal jumps (needs every stage valid, so that X⁻¹ exists).
    if stage_ok.iter().all(|&ok| ok) && stages.iter().all(|st| st.status == "certified") {
        if let Some(eval) = &eval {
            let level = model.level;
            let jumps: Vec<(usize, f64, usize, [u32; 4])> = facets
                .par_iter()
                .filter_map(|(key, sides)| {
                    let (s1, a1) = sides[0];
                    let (s2, _) = sides[1];
                    let ids1 = model.simplex(s1);
                    let f: Vec<f64> = ids1
                        .iter()
                        .map(|&v| model.values[v as usize] - level)
                        .collect();
                    // Crossing points of θ on the facet's edges, in σ's local coordinates.
                    let pos: Vec<usize> = (0..m).filter(|&i| i != a1).collect();
                    let mut ends = Vec::new();
                    for x in 0..pos.len() {
                        for y in (x + 1)..pos.len() {
                            let (i, j) = (pos[x], pos[y]);
                            if f[i] * f[j] < 0.0 {
                                let t = f[j] / (f[j] - f[i]);
                                let mut u = [0.0; 4];
                                u[i] = t;
                                u[j] = 1.0 - t;
                                ends.push(u);
                            }
                        }
                    }
                    let samples: Vec<[f64; 4]> = match ends.len() {
                        1 => ends,
                        2 => (0..FACET_SAMPLES_3D)
                            .map(|s| {
                                let t = (s as f64 + 0.5) / FACET_SAMPLES_3D as f64;
                                let mut u = [0.0; 4];
                                for c in 0..m {
                                    u[c] = (1.0 - t) * ends[0][c] + t * ends[1][c];
                                }
                                u
                            })
                            .collect(),
                        _ => return None,
                    };
                    let mut worst = 0.0f64;
                    for u in samples {
                        let inv = eval.local_map(s1).inverse(&u);
                        if !inv.converged {
                            continue;
                        }
                        let p = eval.point(s1, &inv.w);
                        let w2 = ism_geom::stage::project(m, &eval.barycentric(s2, &p));
                        let (Some(g1), Some(g2)) =
                            (eval.gradient_at(s1, &inv.w), eval.gradient_at(s2, &w2))
                        else {
                            continue;
                        };
                        if let Some(a) = angle_degrees(&g1, &g2) {
                            worst = worst.max(a);
                        }
                    }
                    Some((s1, worst, s2, *key))
                })
                .collect();
            let checked = jumps.len();
            let max = jumps.iter().map(|j| j.1).fold(0.0f64, f64::max);
            let mean = if checked > 0 {
                jumps.iter().map(|j| j.1).sum::<f64>() / checked as f64
            } else {
                0.0
            };
            for (s1, angle, s2, key) in jumps {
                if angle > NORMAL_JUMP_WARN_DEGREES {
                    let mut msg = Message::new(
                        Rule::NormalJump,
                        Location {
                            simplex: Some(s1),
                            face: Some(key[..n].to_vec()),
                            ..Location::pointer(format!("/simplices/{}", s1 * m))
                        },
                        format!("normal of the shape jumps by {angle:.2}° between simplices {s1} and {s2}"),
                    );
                    msg.value = Some(angle);
                    out.push(msg);
                }
            }
            let jumps = NormalJumps {
                facets: checked,
                max_degrees: max,
                mean_degrees: mean,
            };
            stats.normal_jumps = Some(jumps);
            out.push(normal_jump_summary(&jumps));
        }
    }
    (out, stats)
}

/// The ISM-401 summary message, rendered from the statistics.
fn normal_jump_summary(j: &NormalJumps) -> Message {
    let mut msg = Message::new(
        Rule::NormalJump,
        Location::default(),
        format!(
            "{} interior facets cross the shape: normal jump max {:.3}°, mean {:.3}°",
            j.facets, j.max_degrees, j.mean_degrees
        ),
    );
    msg.severity = ism_format::Severity::Info;
    msg.value = Some(j.max_degrees);
    msg
}

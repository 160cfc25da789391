//! Layer 2: invariance (ISM-201..204, spec/validation.md §3).
//!
//! Every stored control point must lie in the open face that owns it — positive coordinates that
//! sum to 1 — which makes the stage K-invariant (Mello & Velho 2009 Prop. 5.1); weights must be positive and
//! monotonic coefficients strictly increasing from 0.

use ism_format::{Location, Model, Rule, StageKind};
use rayon::prelude::*;

use crate::report::Message;

/// A stored point's coordinates must sum to 1 within this absolute tolerance (ISM-202).
///
/// Writers that normalise in f64 land within a few ulps (k ≤ 4 terms: ≤ 1e-15); 1e-9 also admits
/// points written with 10 significant decimal digits, and keeps the map within 1e-9 of a
/// K-invariant one, far below any modelling scale.
pub const SUM_TOLERANCE: f64 = 1e-9;

/// Layer-2 findings of stage `k`.
pub fn check_stage(model: &Model, k: usize) -> Vec<Message> {
    let stage = &model.stages[k];
    let mut out = Vec::new();
    let at = |suffix: String| Location::pointer(format!("/stages/{k}{suffix}"));
    match stage.kind {
        StageKind::Monotonic => {
            for (r, map) in stage.vertex_maps.iter().enumerate() {
                let loc = |j: usize| Location {
                    stage: Some(k),
                    vertex: Some(map.vertex as usize),
                    ..at(format!("/vertexMaps/{r}/coefficients/{j}"))
                };
                let a = &map.coefficients;
                if a.first() != Some(&0.0) {
                    out.push(Message::new(
                        Rule::MonotonicIncreasing,
                        loc(0),
                        format!(
                            "a_0 = {}; a vertex map starts at 0",
                            a.first().copied().unwrap_or(f64::NAN)
                        ),
                    ));
                } else if let Some(j) = (1..a.len()).find(|&j| a[j] <= a[j - 1]) {
                    out.push(Message::new(
                        Rule::MonotonicIncreasing,
                        loc(j),
                        format!(
                            "a_{j} = {} ≤ a_{} = {}; coefficients must strictly increase",
                            a[j],
                            j - 1,
                            a[j - 1]
                        ),
                    ));
                }
            }
        }
        StageKind::Bezier | StageKind::Rational => {
            // Per record on every core; only the (rare) findings are formatted, in record order.
            let found: Vec<Message> = (0..stage.faces.len())
                .into_par_iter()
                .flat_map_iter(|r| {
                    let rec = stage.faces.record(r);
                    let mut out = Vec::new();
                    let k1 = rec.face.len();
                    let loc = |suffix: String| Location {
                        stage: Some(k),
                        face: Some(rec.face.to_vec()),
                        ..at(format!("/faces/{r}{suffix}"))
                    };
                    for (p, point) in rec.points.chunks(k1).enumerate() {
                        let mut bad = false;
                        for (j, &x) in point.iter().enumerate() {
                            if x <= 0.0 {
                                bad = true;
                                out.push(Message::new(
                                    Rule::CoordinatePositive,
                                    loc(format!("/points/{}", p * k1 + j)),
                                    format!("coordinate {j} of point {p} is {x}; it must be > 0 (the point lies in the open face)"),
                                ));
                            }
                        }
                        let sum: f64 = point.iter().sum();
                        if !bad && (sum - 1.0).abs() > SUM_TOLERANCE {
                            out.push(Message::new(
                                Rule::CoordinateSum,
                                loc(format!("/points/{}", p * k1)),
                                format!("point {p}'s coordinates sum to {sum}; expected 1 within {SUM_TOLERANCE:e}"),
                            ));
                        }
                    }
                    if stage.kind == StageKind::Rational {
                        for (j, &q) in rec.weights.iter().enumerate() {
                            if q <= 0.0 {
                                out.push(Message::new(
                                    Rule::WeightPositive,
                                    loc(format!("/weights/{j}")),
                                    format!("weight {j} is {q}; weights must be > 0"),
                                ));
                            }
                        }
                    }
                    out
                })
                .collect();
            out.extend(found);
        }
    }
    out
}

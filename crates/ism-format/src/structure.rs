//! Structural requirements every reader enforces (spec §2–5): what makes a file well-formed.
//!
//! Positivity of the maps is not structural; the validator certifies it (spec §6).

use std::collections::HashSet;
use std::sync::atomic::{AtomicU64, Ordering};

use rayon::prelude::*;

use crate::indexed::{FacetDefect, RecordLookup, Topology, NONE};
use crate::model::{Model, StageKind};
use crate::multi_index::owned_count;
use crate::rules::{Diagnostic, Location, Rule, Severity};

/// Highest stage degree a conforming reader must accept and may refuse beyond (spec §5).
///
/// 16 keeps the largest dense control net (`C(19, 3) = 969` points in 3D) and the certificate
/// polynomials of the validator small, while leaving ample room above the degrees in use (≤ 8).
pub const MAX_DEGREE: u32 = 16;

/// A simplex is degenerate when `|det[v1−v0 … vn−v0]| ≤ DEGENERACY_TOLERANCE · L^n`, with `L` its
/// longest edge (spec §3.2).
///
/// The ratio is scale-free; below 1e-12 barycentric coordinates computed in f64 keep fewer than four
/// significant digits, which no later computation can recover.
pub const DEGENERACY_TOLERANCE: f64 = 1e-12;

/// Default cap on the number of diagnostics one check collects, so hostile files cannot make the
/// report itself unbounded.
pub const DEFAULT_MAX_DIAGNOSTICS: usize = 1000;

/// Signed `det[v1−v0 … vn−v0]` and longest edge length of simplex `s`. Indices must be in range.
pub fn orientation(model: &Model, s: usize) -> (f64, f64) {
    let n = model.dim();
    let ids = model.simplex(s);
    let v0 = model.vertex(ids[0] as usize);
    let mut e = [[0.0f64; 3]; 3];
    for (k, &id) in ids[1..].iter().enumerate() {
        let v = model.vertex(id as usize);
        for c in 0..n {
            e[k][c] = v[c] - v0[c];
        }
    }
    let det = if n == 2 {
        e[0][0] * e[1][1] - e[0][1] * e[1][0]
    } else {
        e[0][0] * (e[1][1] * e[2][2] - e[1][2] * e[2][1])
            - e[0][1] * (e[1][0] * e[2][2] - e[1][2] * e[2][0])
            + e[0][2] * (e[1][0] * e[2][1] - e[1][1] * e[2][0])
    };
    let mut longest = 0.0f64;
    for a in 0..=n {
        for b in (a + 1)..=n {
            let (pa, pb) = (model.vertex(ids[a] as usize), model.vertex(ids[b] as usize));
            let d2: f64 = (0..n).map(|c| (pa[c] - pb[c]).powi(2)).sum();
            longest = longest.max(d2.sqrt());
        }
    }
    (det, longest)
}

/// [`orientation`] of a simplex of `N + 1` vertices (`N` = 2 or 3, the model's dimension) with the
/// loops unrolled: the same operations in the same order, so the same bits, but for the longest
/// edge, which is the square root of the largest squared length instead of the largest square
/// root (the same number: a correctly rounded square root is monotonic; a NaN squared length is
/// skipped by `max` either way). Indices must be in range.
fn orientation_of<const N: usize>(model: &Model, ids: &[u32]) -> (f64, f64) {
    debug_assert!(N == 2 || N == 3);
    let vertex = |id: u32| -> &[f64; N] {
        let at = id as usize * N;
        model.vertices[at..at + N]
            .try_into()
            .expect("N coordinates")
    };
    let v: [&[f64; N]; 4] = std::array::from_fn(|i| vertex(ids[i.min(N)]));
    let mut e = [[0.0f64; 3]; 3];
    for k in 0..N {
        for c in 0..N {
            e[k][c] = v[k + 1][c] - v[0][c];
        }
    }
    let det = if N == 2 {
        e[0][0] * e[1][1] - e[0][1] * e[1][0]
    } else {
        e[0][0] * (e[1][1] * e[2][2] - e[1][2] * e[2][1])
            - e[0][1] * (e[1][0] * e[2][2] - e[1][2] * e[2][0])
            + e[0][2] * (e[1][0] * e[2][1] - e[1][1] * e[2][0])
    };
    let mut longest2 = 0.0f64;
    for a in 0..=N {
        for b in (a + 1)..=N {
            let mut d2 = (v[a][0] - v[b][0]).powi(2);
            for (x, y) in v[a][1..].iter().zip(&v[b][1..]) {
                d2 += (x - y).powi(2);
            }
            longest2 = longest2.max(d2);
        }
    }
    (det, longest2.sqrt())
}

/// Collects up to `max` errors and, separately, up to `max` warnings: warnings never crowd out an
/// error or stop the checks, so a file with many unused vertices still has its stages checked.
struct Collector {
    out: Vec<Diagnostic>,
    max: usize,
    errors: usize,
    warnings: usize,
}

impl Collector {
    fn new(max: usize) -> Collector {
        Collector {
            out: Vec::new(),
            max,
            errors: 0,
            warnings: 0,
        }
    }
    fn push(&mut self, rule: Rule, location: Location, message: String) {
        let count = match rule.severity() {
            Severity::Error => &mut self.errors,
            _ => &mut self.warnings,
        };
        if *count < self.max {
            *count += 1;
            self.out.push(Diagnostic::new(rule, location, message));
        }
    }
    /// Whether the error budget is spent (later checks would only add unreported errors).
    fn full(&self) -> bool {
        self.errors >= self.max
    }
}

/// Checks every structural requirement; returns errors and warnings, at most `max` of each.
pub fn check(model: &Model, max: usize) -> Vec<Diagnostic> {
    check_indexed(model, max, false).0
}

/// [`check`], also counting the faces of each dimension `k = 0 … n` of the complex (vertices that
/// belong to a simplex, edges, …, top simplices) from the topology the check builds anyway; `None`
/// when the arrays could not be indexed. Costs what [`check`] costs (`ism info`).
pub fn check_counting_faces(model: &Model, max: usize) -> (Vec<Diagnostic>, Option<Vec<usize>>) {
    let (diagnostics, topology) = check_indexed(model, max, false);
    let counts = topology.map(|(t, _)| (0..=model.dim()).map(|k| t.num_faces(k)).collect());
    (diagnostics, counts)
}

/// Per stage, the index (among the faces of its dimension, `face.len() − 1`) of the face each
/// record names, [`crate::indexed::NONE`] where it names none; empty when the stage checks did not
/// run.
pub(crate) type RecordFaces = Vec<Vec<u32>>;

/// [`check`], also returning the topology it built (whenever the arrays could be indexed: every
/// length and index in range, not stopped by `max`). [`crate::IndexedModel::new`] keeps it;
/// `full = false` (a check that keeps nothing) builds only what the rules need (no simplex → face
/// tables, no neighbours).
pub(crate) fn check_indexed(
    model: &Model,
    max: usize,
    full: bool,
) -> (Vec<Diagnostic>, Option<(Topology, RecordFaces)>) {
    let mut c = Collector::new(max);
    check_arrays(model, &mut c);
    if c.out.iter().any(|d| {
        matches!(
            d.rule,
            Rule::Dimension | Rule::VertexArray | Rule::SimplexArray | Rule::IndexRange
        )
    }) {
        // Later checks index vertices through simplices; stop before they would misread.
        return (c.out, None);
    }
    let topology = check_simplices(model, &mut c, full);
    check_values(model, &mut c);
    check_extensions(model, &mut c);
    let record_faces = match (c.full(), topology.as_ref()) {
        (false, Some((t, lookups))) => check_stages(model, t, lookups.as_deref(), &mut c),
        _ => Vec::new(),
    };
    (c.out, topology.map(|(t, _)| (t, record_faces)))
}

fn check_arrays(model: &Model, c: &mut Collector) {
    let n = model.dim();
    if !(2..=3).contains(&n) {
        c.push(
            Rule::Dimension,
            Location::pointer("/dimension"),
            format!("dimension is {n}; expected 2 or 3"),
        );
        return;
    }
    if model.vertices.len() % n != 0 {
        c.push(
            Rule::VertexArray,
            Location::pointer("/vertices"),
            format!(
                "{} numbers is not a multiple of dimension {n}",
                model.vertices.len()
            ),
        );
    }
    for (i, x) in model.vertices.iter().enumerate() {
        if !x.is_finite() {
            let loc = Location {
                vertex: Some(i / n),
                ..Location::pointer(format!("/vertices/{i}"))
            };
            c.push(
                Rule::VertexArray,
                loc,
                format!("coordinate {x} is not finite"),
            );
        }
    }
    let m = n + 1;
    if model.simplices.len() % m != 0 || model.simplices.is_empty() {
        c.push(
            Rule::SimplexArray,
            Location::pointer("/simplices"),
            format!(
                "{} indices; expected a positive multiple of {m}",
                model.simplices.len()
            ),
        );
        return;
    }
    let nv = model.num_vertices();
    for (i, &id) in model.simplices.iter().enumerate() {
        if id as usize >= nv {
            let loc = Location {
                simplex: Some(i / m),
                ..Location::pointer(format!("/simplices/{i}"))
            };
            c.push(
                Rule::IndexRange,
                loc,
                format!("vertex index {id} out of range (model has {nv} vertices)"),
            );
        }
    }
}

/// Whether `model` has no array error (dimension, shapes, finite coordinates, index ranges) and
/// no simplex repeating a vertex: then an evaluator's index of a model without stages refuses
/// nothing ([`crate::IndexedModel::for_evaluation`]), and the rest of the check (orientation,
/// manifoldness, values, …: diagnostics it only keeps) can wait. One pass over the arrays, no
/// topology; `false` whenever in doubt (the full check then decides).
pub(crate) fn arrays_sound_and_no_repeated_vertex(model: &Model) -> bool {
    let mut c = Collector::new(usize::MAX);
    check_arrays(model, &mut c);
    if c.out.iter().any(|d| d.severity == Severity::Error) {
        return false;
    }
    let m = model.dim() + 1;
    model
        .simplices
        .par_chunks_exact(m)
        .all(|ids| (0..m).all(|a| !ids[a + 1..].contains(&ids[a])))
}

fn simplex_location(s: usize, m: usize) -> Location {
    Location {
        simplex: Some(s),
        ..Location::pointer(format!("/simplices/{}", s * m))
    }
}

/// The topology, and (check-only scan, `full = false`, when every stage's records allow it:
/// [`Topology::scannable`]) what the scan found of each stage's records.
type Indexed = (Topology, Option<Vec<RecordLookup>>);

fn check_simplices(model: &Model, c: &mut Collector, full: bool) -> Option<Indexed> {
    let n = model.dim();
    let m = n + 1;
    // Per-simplex checks in parallel, one byte each; only the (rare) failures are formatted, in
    // simplex order, recomputing their determinant.
    #[derive(Clone, Copy, PartialEq)]
    enum Status {
        Ok,
        Repeated,
        Degenerate,
        Inverted,
    }
    let status: Vec<Status> = (0..model.num_simplices())
        .into_par_iter()
        .map(|s| {
            let ids = model.simplex(s);
            if (0..m).any(|a| ids[a + 1..].contains(&ids[a])) {
                return Status::Repeated;
            }
            let (det, longest) = match n {
                2 => orientation_of::<2>(model, ids),
                3 => orientation_of::<3>(model, ids),
                _ => orientation(model, s),
            };
            let tol = DEGENERACY_TOLERANCE * longest.powi(n as i32);
            if det.abs() <= tol || !det.is_finite() {
                Status::Degenerate
            } else if det < 0.0 {
                Status::Inverted
            } else {
                Status::Ok
            }
        })
        .collect();
    let repeated: Vec<bool> = status.iter().map(|&t| t == Status::Repeated).collect();
    for (s, &t) in status.iter().enumerate() {
        match t {
            Status::Ok => {}
            Status::Repeated => c.push(
                Rule::RepeatedIndex,
                simplex_location(s, m),
                format!("vertices {:?} repeat an index", model.simplex(s)),
            ),
            Status::Degenerate => {
                let (det, longest) = orientation(model, s);
                c.push(
                    Rule::Degenerate,
                    simplex_location(s, m),
                    format!("det = {det:e}, longest edge {longest:e}: relative volume at most {DEGENERACY_TOLERANCE:e}"),
                )
            }
            Status::Inverted => {
                let (det, _) = orientation(model, s);
                c.push(
                    Rule::Inverted,
                    simplex_location(s, m),
                    format!("det = {det:e} < 0; expected positive orientation (swap two vertices)"),
                )
            }
        }
    }
    if c.full() {
        return None;
    }
    // Duplicate simplices and facet sharing come out of indexing the complex: sorting face keys,
    // not hashing, keeps memory flat on millions of simplices. A check that keeps nothing looks
    // the stages' face records up in the same pass, when their order allows (the usual one: by
    // first vertex), instead of building face tables to search.
    let empty = crate::FaceTable::new();
    let tables: Vec<&crate::FaceTable> = model
        .stages
        .iter()
        .map(|s| match s.kind {
            StageKind::Monotonic => &empty,
            StageKind::Bezier | StageKind::Rational => &s.faces,
        })
        .collect();
    let nv = model.num_vertices();
    let scan = !full && tables.iter().all(|t| Topology::scannable(t, nv));
    let (topology, duplicates, defects, lookups) = if scan {
        let (t, d, f, l) = Topology::scan(model, &repeated, &tables);
        (t, d, f, Some(l))
    } else {
        let (t, d, f) = Topology::build(model, &repeated, full);
        (t, d, f, None)
    };
    for (s, first) in duplicates {
        c.push(
            Rule::DuplicateSimplex,
            simplex_location(s as usize, m),
            format!("same vertex set as simplex {first}"),
        );
    }
    for defect in defects {
        match defect {
            FacetDefect::Overshared { face, simplices } => {
                let loc = Location {
                    face: Some(face),
                    ..simplex_location(simplices[2] as usize, m)
                };
                c.push(
                    Rule::FacetOvershared,
                    loc,
                    format!(
                        "facet shared by {} simplices {simplices:?}; at most 2 allowed",
                        simplices.len()
                    ),
                );
            }
            FacetDefect::Overlap {
                face,
                first,
                second,
            } => {
                let loc = Location {
                    face: Some(face),
                    ..simplex_location(second as usize, m)
                };
                c.push(
                    Rule::Overlap,
                    loc,
                    format!(
                        "simplices {first} and {second} lie on the same side of their shared facet"
                    ),
                );
            }
        }
        if c.full() {
            return Some((topology, lookups));
        }
    }
    for v in 0..model.num_vertices() {
        if topology.vertex_simplices(v).is_empty() {
            let loc = Location {
                vertex: Some(v),
                ..Location::pointer(format!("/vertices/{}", v * n))
            };
            c.push(
                Rule::UnusedVertex,
                loc,
                "vertex belongs to no simplex".into(),
            );
        }
    }
    Some((topology, lookups))
}

fn check_values(model: &Model, c: &mut Collector) {
    if !model.level.is_finite() {
        c.push(
            Rule::Level,
            Location::pointer("/level"),
            format!("level {} is not finite", model.level),
        );
    }
    let nv = model.num_vertices();
    if model.values.len() != nv {
        c.push(
            Rule::ValueArray,
            Location::pointer("/values"),
            format!(
                "{} values for {nv} vertices; expected one per vertex",
                model.values.len()
            ),
        );
    }
    for (v, &x) in model.values.iter().enumerate() {
        let loc = || Location {
            vertex: Some(v),
            ..Location::pointer(format!("/values/{v}"))
        };
        if !x.is_finite() {
            c.push(Rule::ValueArray, loc(), format!("value {x} is not finite"));
        } else if x == 0.0 {
            c.push(
                Rule::ValueZero,
                loc(),
                "value is zero; vertex values must be nonzero".into(),
            );
        } else if x == model.level {
            c.push(
                Rule::ValueAtLevel,
                loc(),
                format!("value equals the level {}", model.level),
            );
        }
    }
}

fn check_extensions(model: &Model, c: &mut Collector) {
    for (member, names) in [
        ("extensionsUsed", &model.extensions_used),
        ("extensionsRequired", &model.extensions_required),
    ] {
        let mut seen = HashSet::new();
        for (i, name) in names.iter().enumerate() {
            if !seen.insert(name) {
                c.push(
                    Rule::ExtensionsListed,
                    Location::pointer(format!("/{member}/{i}")),
                    format!("extension {name:?} is listed twice in {member}"),
                );
            }
        }
    }
    for (i, name) in model.extensions_required.iter().enumerate() {
        if !model.extensions_used.contains(name) {
            c.push(
                Rule::ExtensionsListed,
                Location::pointer(format!("/extensionsRequired/{i}")),
                format!("required extension {name:?} is not in extensionsUsed"),
            );
        }
    }
    for name in model.extensions.keys() {
        if !model.extensions_used.contains(name) {
            c.push(
                Rule::ExtensionsListed,
                Location::pointer(format!("/extensions/{}", escape_pointer(name))),
                format!("extension {name:?} has data but is not in extensionsUsed"),
            );
        }
    }
}

/// Escapes a JSON-pointer reference token (RFC 6901 §4).
pub fn escape_pointer(token: &str) -> String {
    token.replace('~', "~0").replace('/', "~1")
}

/// The face index of each record of `stage` ([`NONE`] where it names no face of the complex;
/// empty for a monotonic stage), in parallel.
fn stage_record_faces(model: &Model, topology: &Topology, stage: &crate::model::Stage) -> Vec<u32> {
    (0..stage.faces.len())
        .into_par_iter()
        .map(|r| {
            topology
                .find(model, stage.faces.face(r))
                .map_or(NONE, |f| f.index)
        })
        .collect()
}

/// Per stage, [`stage_record_faces`]: what [`check_indexed`] returns with its full topology.
pub(crate) fn record_faces(model: &Model, topology: &Topology) -> RecordFaces {
    model
        .stages
        .iter()
        .map(|stage| stage_record_faces(model, topology, stage))
        .collect()
}

/// Checks the stages; returns, per stage, the face index each record names ([`NONE`] where it
/// names no face of the complex) — empty when `scanned` gives, per stage, the records naming no
/// face and the repeated ones instead (the check-only scan).
fn check_stages(
    model: &Model,
    topology: &Topology,
    scanned: Option<&[RecordLookup]>,
    c: &mut Collector,
) -> RecordFaces {
    let n = model.dim();
    let nv = model.num_vertices();
    let mut record_faces = Vec::with_capacity(model.stages.len());
    for (k, stage) in model.stages.iter().enumerate() {
        // Face lookups are the costly part: in parallel, once, kept for the stage tables.
        let scan = scanned.map(|s| &s[k]);
        let found: Vec<u32> = match scan {
            Some(_) => Vec::new(),
            None => stage_record_faces(model, topology, stage),
        };
        if scan.is_none() {
            record_faces.push(found);
        }
        let found = record_faces.get(k).map_or(&[][..], Vec::as_slice);
        let missing = |r: usize| match scan {
            Some(s) => s.missing.binary_search(&(r as u32)).is_ok(),
            None => found[r] == NONE,
        };
        let base = format!("/stages/{k}");
        let at = |suffix: String| Location {
            stage: Some(k),
            ..Location::pointer(format!("{base}{suffix}"))
        };
        let d = stage.degree;
        if d == 0 || d > crate::structure::MAX_DEGREE {
            c.push(
                Rule::StageDegree,
                at("/degree".into()),
                format!("degree {d}; expected 1 to {MAX_DEGREE}"),
            );
            continue;
        }
        match stage.kind {
            StageKind::Monotonic => {
                if !stage.faces.is_empty() {
                    c.push(
                        Rule::KindMismatch,
                        at("/faces".into()),
                        "a monotonic stage has vertexMaps, not faces".into(),
                    );
                }
                let mut seen = HashSet::new();
                for (r, map) in stage.vertex_maps.iter().enumerate() {
                    let loc = |suffix: &str| Location {
                        vertex: Some(map.vertex as usize),
                        ..at(format!("/vertexMaps/{r}{suffix}"))
                    };
                    if map.vertex as usize >= nv {
                        c.push(
                            Rule::VertexMapIndex,
                            loc("/vertex"),
                            format!("vertex {} out of range ({nv} vertices)", map.vertex),
                        );
                    } else if !seen.insert(map.vertex) {
                        c.push(
                            Rule::VertexMapIndex,
                            loc("/vertex"),
                            format!("vertex {} has two maps in this stage", map.vertex),
                        );
                    }
                    if map.coefficients.len() != d as usize + 1 {
                        c.push(
                            Rule::CoefficientCount,
                            loc("/coefficients"),
                            format!(
                                "{} coefficients; degree {d} needs {}",
                                map.coefficients.len(),
                                d + 1
                            ),
                        );
                    }
                    if let Some(j) = map.coefficients.iter().position(|x| !x.is_finite()) {
                        c.push(
                            Rule::NonFinite,
                            loc(&format!("/coefficients/{j}")),
                            "coefficient is not finite".into(),
                        );
                    }
                }
            }
            StageKind::Bezier | StageKind::Rational => {
                if !stage.vertex_maps.is_empty() {
                    c.push(
                        Rule::KindMismatch,
                        at("/vertexMaps".into()),
                        format!("a {} stage has faces, not vertexMaps", stage.kind.as_str()),
                    );
                }
                // Duplicates by face id: one bit per face, set on every core; only when some
                // face is named twice, the first record of each face, in one pass.
                let key = |r: usize| {
                    let id = found[r];
                    (id != NONE).then(|| (stage.faces.face(r).len() - 1, id as usize))
                };
                let mut repeats: Vec<(usize, usize)> = Vec::new();
                let clash = match scan {
                    Some(s) => {
                        repeats.extend(s.repeats.iter().map(|&(r, f)| (r as usize, f as usize)));
                        false
                    }
                    None => {
                        let seen: Vec<Vec<AtomicU64>> = (0..=n)
                            .map(|k| topology.face_slots(k))
                            .map(|len| (0..len.div_ceil(64)).map(|_| AtomicU64::new(0)).collect())
                            .collect();
                        (0..found.len()).into_par_iter().any(|r| {
                            key(r).is_some_and(|(dim, id)| {
                                let bit = 1u64 << (id % 64);
                                seen[dim][id / 64].fetch_or(bit, Ordering::Relaxed) & bit != 0
                            })
                        })
                    }
                };
                if clash {
                    let slots: Vec<usize> = (0..=n).map(|k| topology.face_slots(k)).collect();
                    let mut first: Vec<Vec<u32>> =
                        slots.iter().map(|&len| vec![NONE; len]).collect();
                    for r in 0..found.len() {
                        if let Some((dim, id)) = key(r) {
                            let slot = &mut first[dim][id];
                            if *slot == NONE {
                                *slot = r as u32;
                            } else {
                                repeats.push((r, *slot as usize));
                            }
                        }
                    }
                }
                // The per-record rules in parallel; only the records breaking one are visited
                // below, in order, to format exactly what a visit of every record would.
                let rational = stage.kind == StageKind::Rational;
                // (A superset of the records breaking a rule is enough: the visit below decides.
                // The counts come straight from the offsets; when every number of the stage is
                // finite, as usual, no record's numbers are looked at one by one.)
                let table = &stage.faces;
                // (A table read without its numbers was tested finite as it was decoded; the
                // reader reads a file again keeping them when one was not.)
                let finite = table.elided_finite().unwrap_or(true)
                    && table.all_points().par_iter().all(|x| x.is_finite())
                    && table.all_weights().iter().all(|x| x.is_finite());
                let owned_of: Vec<usize> = (0..=n + 1).map(|size| owned_count(size, d)).collect();
                let counts_wrong = |[size, points, weights]: [usize; 3]| {
                    let owned = owned_of.get(size).copied().unwrap_or(0);
                    owned == 0
                        || points != owned * size
                        || weights != if rational { owned } else { 0 }
                };
                let suspects: Vec<usize> = match table.uniform_lengths() {
                    // Records of one length (one face dimension): their counts are right or
                    // wrong all together.
                    Some(lens) if finite && !counts_wrong(lens) => match scan {
                        Some(s) => s.missing.iter().map(|&r| r as usize).collect(),
                        None => (0..table.len())
                            .into_par_iter()
                            .filter(|&r| missing(r))
                            .collect(),
                    },
                    Some(_) => (0..table.len()).collect(),
                    None => {
                        let (fo, po, wo) = (
                            table.face_offsets(),
                            table.point_offsets(),
                            table.weight_offsets(),
                        );
                        (0..table.len())
                            .into_par_iter()
                            .filter(|&r| {
                                let len = |o: &[u32]| (o[r + 1] - o[r]) as usize;
                                !finite
                                    || counts_wrong([len(&fo), len(&po), len(&wo)])
                                    || missing(r)
                            })
                            .collect()
                    }
                };
                let mut visit: Vec<(usize, usize)> = suspects
                    .into_iter()
                    .map(|r| (r, usize::MAX))
                    .chain(repeats)
                    .collect();
                visit.sort_unstable_by_key(|&(r, first)| (r, first == usize::MAX));
                visit.dedup_by_key(|&mut (r, _)| r);
                for (r, first) in visit {
                    let rec = stage.faces.record(r);
                    // From the lengths, which a table read without its numbers keeps too.
                    let [_, num_points, num_weights] = stage.faces.lengths(r).unwrap_or_default();
                    let loc = |suffix: &str| Location {
                        face: Some(rec.face.to_vec()),
                        ..at(format!("/faces/{r}{suffix}"))
                    };
                    let kdim = rec.face.len();
                    if kdim == 0 || kdim > n + 1 {
                        c.push(
                            Rule::NotAFace,
                            loc("/face"),
                            format!("{kdim} vertex ids; a face has 1 to {}", n + 1),
                        );
                        continue;
                    }
                    if rec.face.windows(2).any(|w| w[0] >= w[1]) {
                        c.push(
                            Rule::FaceSorted,
                            loc("/face"),
                            format!("{:?} is not strictly increasing", rec.face),
                        );
                        continue;
                    }
                    if missing(r) {
                        c.push(
                            Rule::NotAFace,
                            loc("/face"),
                            format!("{:?} is not a face of any simplex", rec.face),
                        );
                        continue;
                    }
                    if first != usize::MAX {
                        c.push(
                            Rule::DuplicateFace,
                            loc("/face"),
                            format!("face already recorded at /stages/{k}/faces/{first}"),
                        );
                    }
                    let owned = owned_count(kdim, d);
                    if owned == 0 {
                        c.push(
                            Rule::PointCount,
                            loc("/points"),
                            format!("a face with {kdim} vertices owns no control point at degree {d} (needs degree ≥ {kdim})"),
                        );
                        continue;
                    }
                    if num_points != owned * kdim {
                        c.push(
                            Rule::PointCount,
                            loc("/points"),
                            format!(
                                "{} coordinates; expected {} ({owned} point(s) × {kdim} coordinates)",
                                num_points,
                                owned * kdim
                            ),
                        );
                    }
                    let expect_w = if stage.kind == StageKind::Rational {
                        owned
                    } else {
                        0
                    };
                    if num_weights != expect_w {
                        c.push(
                            Rule::WeightCount,
                            loc("/weights"),
                            format!("{num_weights} weights; expected {expect_w}"),
                        );
                    }
                    if let Some(j) = rec.points.iter().position(|x| !x.is_finite()) {
                        c.push(
                            Rule::NonFinite,
                            loc(&format!("/points/{j}")),
                            "coordinate is not finite".into(),
                        );
                    }
                    if let Some(j) = rec.weights.iter().position(|x| !x.is_finite()) {
                        c.push(
                            Rule::NonFinite,
                            loc(&format!("/weights/{j}")),
                            "weight is not finite".into(),
                        );
                    }
                    if c.full() {
                        return record_faces;
                    }
                }
            }
        }
    }
    record_faces
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The unrolled orientation gives the bits of [`orientation`] (the reference: the general
    /// loops), NaN compared as NaN, on simplices with repeated, zero, negative, subnormal, huge,
    /// infinite and NaN coordinates.
    #[test]
    fn unrolled_orientation_gives_the_same_bits() {
        let specials = [
            0.0,
            -0.0,
            1.0,
            -1.0,
            0.5,
            1e-310,
            -1e-310,
            1e300,
            -1e300,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NAN,
            f64::MIN_POSITIVE,
            3.0,
        ];
        // A small xorshift: the values only need to vary.
        let mut state = 0x9E37_79B9_7F4A_7C15u64;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        let same = |a: f64, b: f64| a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan());
        for n in [2usize, 3] {
            let nv = 64;
            let mut vertices = Vec::with_capacity(nv * n);
            for i in 0..nv * n {
                let r = next();
                vertices.push(if i % 5 == 0 {
                    specials[(r % specials.len() as u64) as usize]
                } else {
                    (r >> 11) as f64 / (1u64 << 53) as f64 * 4.0 - 2.0
                });
            }
            let mut simplices = Vec::new();
            for _ in 0..20_000 {
                for _ in 0..=n {
                    simplices.push((next() % nv as u64) as u32);
                }
            }
            let model = Model {
                vertices,
                simplices,
                ..Model::new(n as u8)
            };
            for s in 0..model.num_simplices() {
                let ids = model.simplex(s);
                let fast = if n == 2 {
                    orientation_of::<2>(&model, ids)
                } else {
                    orientation_of::<3>(&model, ids)
                };
                let slow = orientation(&model, s);
                assert!(
                    same(fast.0, slow.0) && same(fast.1, slow.1),
                    "simplex {s} {ids:?}: {fast:?} vs {slow:?}"
                );
            }
        }
    }

    /// A unit square of two triangles with one stage whose records all have the same lengths
    /// (a table keeping no offsets): each count or value rule is reported for exactly the records
    /// breaking it, in record order (truth: written out by hand).
    #[test]
    fn stages_of_same_length_records_report_each_record() {
        use crate::model::{FaceRecord, Stage};
        let edges: [[u32; 2]; 5] = [[0, 1], [0, 2], [0, 3], [1, 2], [2, 3]];
        let check_stage = |kind: StageKind, degree: u32, records: Vec<FaceRecord>| {
            let mut m = Model::new(2);
            m.vertices = vec![0.0, 0.0, 1.0, 0.0, 1.0, 1.0, 0.0, 1.0];
            m.simplices = vec![0, 1, 2, 0, 2, 3];
            m.values = vec![-1.0, 1.0, 1.0, 1.0];
            let mut stage = Stage::identity(kind, degree);
            stage.faces = crate::FaceTable::from(records);
            assert!(stage.faces.uniform_lengths().is_some());
            m.stages = vec![stage];
            check(&m, 100)
                .into_iter()
                .map(|d| (d.rule, d.location.pointer.unwrap_or_default()))
                .collect::<Vec<_>>()
        };
        let rec = |face: &[u32], points: Vec<f64>, weights: Vec<f64>| FaceRecord {
            face: face.to_vec(),
            points,
            weights,
        };
        let valid: Vec<FaceRecord> = edges
            .iter()
            .map(|e| rec(e, vec![0.5, 0.5], vec![]))
            .collect();
        assert_eq!(check_stage(StageKind::Bezier, 2, valid.clone()), vec![]);
        let every = |rule: Rule, suffix: &str| -> Vec<(Rule, String)> {
            (0..5)
                .map(|r| (rule, format!("/stages/0/faces/{r}{suffix}")))
                .collect()
        };
        // Three coordinates per edge record: every record's count is wrong.
        let three: Vec<FaceRecord> = edges
            .iter()
            .map(|e| rec(e, vec![0.5, 0.25, 0.25], vec![]))
            .collect();
        assert_eq!(
            check_stage(StageKind::Bezier, 2, three),
            every(Rule::PointCount, "/points")
        );
        // Degree 1: an edge owns no control point.
        assert_eq!(
            check_stage(StageKind::Bezier, 1, valid.clone()),
            every(Rule::PointCount, "/points")
        );
        // Rational without weights.
        assert_eq!(
            check_stage(StageKind::Rational, 2, valid.clone()),
            every(Rule::WeightCount, "/weights")
        );
        // One non-finite coordinate, one weight: only those records.
        let mut nan = valid.clone();
        nan[3].points[1] = f64::NAN;
        assert_eq!(
            check_stage(StageKind::Bezier, 2, nan),
            vec![(Rule::NonFinite, "/stages/0/faces/3/points/1".to_string())]
        );
        let mut weighted: Vec<FaceRecord> = edges
            .iter()
            .map(|e| rec(e, vec![0.5, 0.5], vec![2.0]))
            .collect();
        weighted[0].weights[0] = f64::INFINITY;
        assert_eq!(
            check_stage(StageKind::Rational, 2, weighted),
            vec![(Rule::NonFinite, "/stages/0/faces/0/weights/0".to_string())]
        );
        // Records naming no edge ([1, 3] is the square's other diagonal) and one edge twice.
        let mut odd = valid.clone();
        odd.insert(3, rec(&[1, 3], vec![0.5, 0.5], vec![]));
        odd.push(rec(&[2, 3], vec![0.5, 0.5], vec![]));
        assert_eq!(
            check_stage(StageKind::Bezier, 2, odd),
            vec![
                (Rule::NotAFace, "/stages/0/faces/3/face".to_string()),
                (Rule::DuplicateFace, "/stages/0/faces/6/face".to_string()),
            ]
        );
    }
}

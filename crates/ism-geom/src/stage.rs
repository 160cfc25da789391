//! One stage restricted to one top simplex ([`LocalStage`]) and all stages of one simplex in
//! order ([`LocalMap`]).
//!
//! Coordinates are barycentric, `m = n + 1` of them, in the simplex's LOCAL (stored) vertex order,
//! held in `[f64; 4]` arrays whose unused tail is zero. Jacobians are `[[f64; 4]; 4]` whose upper-left
//! block is meaningful: the *reduced* Jacobian is `n × n`, w.r.t. `(w_1..w_n)` with `w_0 = 1 − Σ`, rows
//! `u_1..u_n`; the *homogeneous* one is `m × m`, the partial derivatives of the stored formula in all
//! `m` variables.
//!
//! K-invariance is structural: a control point owned by a face has zero coordinates off that face,
//! and `0^e = 0` exactly, so `w_i = 0` gives `u_i = 0` with no rounding; a vertex maps to itself
//! exactly. The inverse restricts its unknowns to the support of `u` for the same reason.

// Index loops mirror the matrix and multi-index formulas they implement; iterator chains over
// several arrays at once would hide them.
#![allow(clippy::needless_range_loop)]

use std::collections::HashMap;

use ism_format::indexed::{simplex_faces, LocalFace, NONE};
use ism_format::{multi_index, Direction, IndexedModel, Model, Stage, StageKind};

use crate::error::{GeomError, Result};
use crate::linalg;
use crate::tables::{basis_m, const_terms, const_up, pow_table, tables, ConstTerm, Tables};
use crate::{Bary, Mat, MAX_DEGREE, MAX_VARS};

/// Calls a const-generic kernel for the stage's variable count (2, 3 or 4).
macro_rules! dispatch {
    ($s:ident, $f:ident, $w:expr) => {
        match $s.m {
            2 => $s.$f::<2>($w),
            3 => $s.$f::<3>($w),
            _ => $s.$f::<4>($w),
        }
    };
}

/// Calls the compile-time-table kernel `$f::<M, D, N, NL>` for the stage's variable count `M` and
/// degree `D ≤ 4` (`N`, `NL`: the counts of degree-`D` and degree-`D − 1` indices), else the
/// table-driven `$g` through [`dispatch!`]. Both compute the same bits (module `tables`,
/// [`const_terms`]); the specialised ones unroll completely (most stages of the format's examples
/// and of fitted models are of degree 1–4).
macro_rules! dispatch_degree {
    ($s:ident, $f:ident, $g:ident, $w:expr) => {
        match ($s.m, $s.degree) {
            (4, 1) => $s.$f::<4, 1, 4, 1>($w),
            (4, 2) => $s.$f::<4, 2, 10, 4>($w),
            (4, 3) => $s.$f::<4, 3, 20, 10>($w),
            (4, 4) => $s.$f::<4, 4, 35, 20>($w),
            (3, 1) => $s.$f::<3, 1, 3, 1>($w),
            (3, 2) => $s.$f::<3, 2, 6, 3>($w),
            (3, 3) => $s.$f::<3, 3, 10, 6>($w),
            (3, 4) => $s.$f::<3, 4, 15, 10>($w),
            (2, 1) => $s.$f::<2, 1, 2, 1>($w),
            (2, 2) => $s.$f::<2, 2, 3, 2>($w),
            (2, 3) => $s.$f::<2, 3, 4, 3>($w),
            (2, 4) => $s.$f::<2, 4, 5, 4>($w),
            _ => dispatch!($s, $g, $w),
        }
    };
}

/// Acceptance threshold of the inverse for a well-scaled stage: max-norm of `X(w) − u`. Values
/// are barycentric coordinates of order 1, so this is about 5 000 ulps — far below any geometric
/// tolerance of the format. Newton itself iterates to `NEWTON_TARGET` (much tighter), so that a
/// result is never accepted at the threshold's edge, where a re-evaluation of `X(w)` with other
/// rounding (value-only instead of value-and-Jacobian) lands on the other side of it: that was
/// "stage inversion did not converge … (residual 1.0000056e-12)" on valid rational models
/// (issue 19). For a stage whose evaluation at the solution cannot be that accurate (a large
/// Jacobian amplifies the rounding of `w` itself) the threshold grows with the stage's scale:
/// see [`acceptance_tolerance`].
pub const INVERSE_TOLERANCE: f64 = 1e-12;

/// A barycentric coordinate below this is rounding left where a face's zero should be (points
/// combined from points of the face): dropping it moves the point by less than a thousandth of
/// [`INVERSE_TOLERANCE`]. Used only to retry an inverse that failed ([`LocalMap::inverse`]).
pub const FACE_DUST: f64 = 1e-15;

/// What Newton aims for before stopping: a hundredth of [`INVERSE_TOLERANCE`], reached by one
/// more quadratic step from there, or the rounding floor of the stage at the point, whichever is
/// larger. Stopping only here leaves a margin of 100× between the solver and the acceptance test.
const NEWTON_TARGET: f64 = INVERSE_TOLERANCE / 100.0;

/// Rounding floor of `X(w) − u`, in units of `f64::EPSILON · scale` (scale from
/// [`rounding_scale`]): evaluating a stage sums `O(count)` products of order-1 terms, and `w`
/// itself carries half an ulp per entry, amplified by the Jacobian. 64 ulps of the scale is a
/// generous allowance for both at the degrees of the format (≤ 16).
const ROUNDING_ULPS: f64 = 64.0;

/// Acceptance floor, in the same units: a residual this many ulps of the scale is rounding, not a
/// failure to converge. 4× the Newton floor, so the solver's stopping point is always accepted.
const ACCEPT_ULPS: f64 = 4.0 * ROUNDING_ULPS;

/// Scale of the rounding error of `X(w) − u` at `w` with homogeneous Jacobian `h`:
/// `1 + max_i Σ_j |h_ij| |w_j|`. The first term is the values' own magnitude (barycentric, ≤ 1);
/// the second is how much half an ulp in every `w_j` moves `X`.
fn rounding_scale(m: usize, w: &Bary, h: &Mat) -> f64 {
    let mut worst = 0.0f64;
    for i in 0..m {
        let row: f64 = (0..m).map(|j| (h[i][j] * w[j]).abs()).sum();
        worst = worst.max(row);
    }
    1.0 + worst
}

/// The residual accepted as converged for a stage of rounding scale `scale` (see
/// `rounding_scale`): [`INVERSE_TOLERANCE`] for a well-scaled stage, `ACCEPT_ULPS · ε · scale`
/// when that is larger (a stage with a Jacobian of 10⁴ cannot be evaluated more accurately than
/// ~10⁴ ulps at any floating-point `w`, so demanding 1e-12 there would fail on valid models).
/// Non-finite scales give the plain tolerance (NaN never passes).
pub fn acceptance_tolerance(scale: f64) -> f64 {
    if scale.is_finite() {
        INVERSE_TOLERANCE.max(ACCEPT_ULPS * f64::EPSILON * scale)
    } else {
        INVERSE_TOLERANCE
    }
}

/// Newton iterations tried before falling back to continuation. Newton converges quadratically
/// from a good start, so a valid stage either converges in far fewer or is in a region where
/// continuation is the right tool.
const NEWTON_MAX_ITERATIONS: u32 = 30;

/// Corrector iterations per continuation step; small steps make a few enough.
const CONTINUATION_CORRECTOR_ITERATIONS: u32 = 12;

/// Smallest continuation step (in the path parameter `t ∈ [0, 1]`) before giving up; the inverse
/// path of a diffeomorphism is continuous, so needing smaller steps means the stage is not valid
/// (or is extremely close to singular).
const CONTINUATION_MIN_STEP: f64 = 1e-7;

/// Newton steps on the composed map after inverting stage by stage: the start is already within
/// the stages' residuals, so two or three quadratic steps suffice.
const MAP_POLISH_ITERATIONS: u32 = 4;

/// Bound on continuation steps (accepted or halved), so that an invalid stage costs bounded time:
/// a valid one needs a handful (steps double after each success).
const CONTINUATION_MAX_STEPS: u32 = 200;

/// Bisection steps of the edge safeguard: halving `[0, 1]` 64 times reaches adjacent doubles.
const EDGE_BISECTION_STEPS: u32 = 64;

/// Tolerance of intermediate continuation points: they only need to be good starting guesses.
const CONTINUATION_INTERMEDIATE_TOLERANCE: f64 = 1e-9;

/// Sum defect below which [`project`] leaves coordinates untouched: barycentric coordinates
/// computed in floating point sum to 1 only within a few ulps, and rescaling them would perturb
/// points (vertices, exact face points) that are otherwise exact.
const PROJECT_SLACK: f64 = 1e-14;

/// Result of inverting a map at one point.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct InverseResult {
    /// Barycentric preimage (first `m` entries).
    pub w: Bary,
    /// Newton iterations spent (all stages, all continuation steps).
    pub iterations: u32,
    /// Max-norm of `X(w) − u` at the returned `w` (after projecting `u` onto the simplex).
    pub residual: f64,
    /// `residual ≤` [`acceptance_tolerance`] of the point (`INVERSE_TOLERANCE` for a well-scaled
    /// stage), and, for a map, every stage converged; for a map of parametric stages only (a
    /// direct evaluation, exact to rounding), a finite preimage.
    pub converged: bool,
}

/// Map from sorted face ids to their record index, and from vertex ids to monotonic maps, for one
/// free-standing stage: the route of [`LocalStage::from_stage`] and [`LocalStage::from_model`],
/// which build one simplex without indexing a model. Many simplices of a model are built from its
/// [`IndexedModel`] instead ([`LocalStage::from_indexed`]), where the topology already names each
/// simplex's faces; this hashing route stays as the independent one the tests compare it with.
#[derive(Clone, Debug, Default)]
struct StageLookup {
    stage_index: usize,
    faces: HashMap<Vec<u32>, usize>,
    vertices: HashMap<u32, usize>,
}

impl StageLookup {
    /// Indexes the records of `stage` (the `stage_index` is only used in error messages).
    fn new(stage: &Stage, stage_index: usize) -> StageLookup {
        let faces = stage
            .faces
            .iter()
            .enumerate()
            .map(|(i, r)| (r.face.to_vec(), i))
            .collect();
        let vertices = stage
            .vertex_maps
            .iter()
            .enumerate()
            .map(|(i, r)| (r.vertex, i))
            .collect();
        StageLookup {
            stage_index,
            faces,
            vertices,
        }
    }

    /// Whether any face record has a face among the subsets of `simplex` (so the local map may differ
    /// from the identity).
    fn touches(&self, stage: &Stage, simplex: &[u32]) -> bool {
        match stage.kind {
            StageKind::Monotonic => simplex.iter().any(|v| self.vertices.contains_key(v)),
            _ => {
                // Few records per stage is the common case (stratified, sparse edits); many records
                // are checked per subset instead.
                let m = simplex.len();
                if self.faces.len() < (1 << m) {
                    stage
                        .faces
                        .iter()
                        .any(|r| r.face.iter().all(|v| simplex.contains(v)))
                } else {
                    simplex_faces(simplex, 1).any(|f| self.faces.contains_key(f.ids()))
                }
            }
        }
    }
}

/// One stage on one top simplex: the dense control net in local vertex order.
#[derive(Clone, Debug)]
pub struct LocalStage {
    kind: StageKind,
    direction: Direction,
    degree: u32,
    m: usize,
    identity: bool,
    tables: &'static Tables,
    /// Dense control points `b_I` (Bézier, rational), canonical order.
    points: Vec<Bary>,
    /// Dense weights `q_I` (rational only).
    weights: Vec<f64>,
    /// `q_I b_I` (rational only).
    weighted: Vec<Bary>,
    /// Monotonic: `a_j` per local vertex, `(d + 1)` each.
    mono: Vec<f64>,
    /// Monotonic: `a_j C(d, j)`.
    mono_scaled: Vec<f64>,
    /// Monotonic: `d (a_{j+1} − a_j) C(d − 1, j)`, the derivative's scaled coefficients.
    mono_deriv: Vec<f64>,
    /// Bézier, when set ([`LocalStage::sparsify`]): the terms whose control point is not the
    /// identity net's `I/d`, evaluated instead of the dense net as the identity plus their
    /// deviations ([`LocalStage::eval_sparse`]).
    sparse: Option<Vec<SparseTerm>>,
}

/// `w_k^{e_k}` and `w_k^{e_k − 1}` (1 where `e_k = 0`) by repeated products, as the dense kernels'
/// power tables form them, for a sparse term's few factors (a whole power table, `M` rows of
/// [`crate::MAX_DEGREE`]` + 1` entries initialised per call, was a fifth of stratified-3d's
/// evaluation).
#[inline(always)]
fn sparse_powers<const M: usize>(e: &[u8; MAX_VARS], w: &Bary) -> ([f64; M], [f64; M]) {
    let mut powers = [1.0; M];
    let mut lower = [1.0; M];
    for k in 0..M {
        for _ in 1..e[k] {
            lower[k] *= w[k];
        }
        powers[k] = if e[k] == 0 { 1.0 } else { lower[k] * w[k] };
    }
    (powers, lower)
}

/// `a^e` by square-and-multiply exactly as the runtime routine behind `f64::powi` with a
/// run-time exponent (compiler-builtins' `__powidf2`: the same products in the same order, so the
/// same bits), but inline: a sparse stage's evaluation called it once per point, 1.6 % of
/// stratified-3d's export.
#[inline(always)]
fn powi(mut a: f64, mut e: u32) -> f64 {
    let mut product = 1.0;
    loop {
        if e & 1 != 0 {
            product *= a;
        }
        e >>= 1;
        if e == 0 {
            return product;
        }
        a *= a;
    }
}

/// A term of a Bézier net whose control point `b_I` differs from the identity net's `I/d`:
/// `B_I`'s exponents and multinomial, and `b_I − I/d`.
#[derive(Clone, Copy, Debug)]
struct SparseTerm {
    exps: [u8; MAX_VARS],
    mult: f64,
    delta: Bary,
}

impl LocalStage {
    /// Bytes this stage holds on the heap (its tables' capacities), for a cache's budget.
    pub fn heap_bytes(&self) -> usize {
        use std::mem::size_of;
        self.points.capacity() * size_of::<Bary>()
            + self.weights.capacity() * size_of::<f64>()
            + self.weighted.capacity() * size_of::<Bary>()
            + (self.mono.capacity() + self.mono_scaled.capacity() + self.mono_deriv.capacity())
                * size_of::<f64>()
            + self
                .sparse
                .as_ref()
                .map_or(0, |t| t.capacity() * size_of::<SparseTerm>())
    }

    /// Builds stage `stage_index` of `model` on top simplex `simplex_index`.
    ///
    /// Indexes the stage's records on every call (O(records)); to build many simplices index the
    /// model once ([`IndexedModel`]) and use [`LocalStage::from_indexed`] (or [`crate::ModelEval`]).
    pub fn from_model(
        model: &Model,
        stage_index: usize,
        simplex_index: usize,
    ) -> Result<LocalStage> {
        let stage = model.stages.get(stage_index).ok_or(GeomError::NoStage {
            index: stage_index,
            count: model.stages.len(),
        })?;
        let count = model.num_simplices();
        if simplex_index >= count {
            return Err(GeomError::NoSimplex {
                index: simplex_index,
                count,
            });
        }
        LocalStage::from_stage(stage, stage_index, model.simplex(simplex_index))
    }

    /// Builds a free-standing `stage` (not necessarily part of a model; `stage_index` is only used
    /// in error messages) on the top simplex with vertex ids `simplex` (stored order, `m = n + 1`
    /// ids). Indexes the stage's records on every call (O(records)), like
    /// [`LocalStage::from_model`].
    pub fn from_stage(stage: &Stage, stage_index: usize, simplex: &[u32]) -> Result<LocalStage> {
        LocalStage::build(stage, &StageLookup::new(stage, stage_index), simplex)
    }

    /// Builds `stage` on the top simplex with vertex ids `simplex` (stored order, `m = n + 1` ids).
    fn build(stage: &Stage, lookup: &StageLookup, simplex: &[u32]) -> Result<LocalStage> {
        let m = simplex.len();
        if !(2..=MAX_VARS).contains(&m) {
            return Err(GeomError::Dimension(m.saturating_sub(1)));
        }
        let d = stage.degree;
        if d == 0 || d > MAX_DEGREE {
            return Err(GeomError::Degree {
                stage: lookup.stage_index,
                degree: d,
            });
        }
        let t = tables(m, d);
        let mut local = LocalStage {
            kind: stage.kind,
            direction: stage.direction,
            degree: d,
            m,
            identity: !lookup.touches(stage, simplex),
            tables: t,
            points: Vec::new(),
            weights: Vec::new(),
            weighted: Vec::new(),
            mono: Vec::new(),
            mono_scaled: Vec::new(),
            mono_deriv: Vec::new(),
            sparse: None,
        };
        match stage.kind {
            StageKind::Monotonic => local.fill_monotonic(stage, lookup, simplex)?,
            StageKind::Bezier | StageKind::Rational => local.fill_net(stage, lookup, simplex)?,
        }
        Ok(local)
    }

    /// Builds stage `stage_index` of an indexed model on its top simplex `s`, reading every control
    /// point from the stage's flat tables (O(1) per multi-index: the simplex's face ids come from
    /// the topology, no face key is hashed).
    pub fn from_indexed(model: &IndexedModel, stage_index: usize, s: usize) -> Result<LocalStage> {
        Ok(
            LocalStage::build_indexed(model, stage_index, s, false, true, None)?
                .expect("built whether or not it is the identity"),
        )
    }

    /// [`LocalStage::from_indexed`], or `None` without filling a net when `skip_identity` and no
    /// record touches the simplex ([`LocalMap`] drops identity stages: their dense default net
    /// was built only to be freed, a fifth of a fitted model's `--max-depth 0` export).
    /// `finish = false` leaves a monotonic stage's evaluation tables unbuilt: [`LocalMap::fused`]
    /// builds them for a stage it does not fuse (a fused one only reads the coefficients).
    /// `recorded` gets the canonical index of each control point read from a record, ascending:
    /// every other point is the identity net's ([`LocalStage::sparsify_among`]).
    fn build_indexed(
        model: &IndexedModel,
        stage_index: usize,
        s: usize,
        skip_identity: bool,
        finish: bool,
        mut recorded: Option<&mut Vec<usize>>,
    ) -> Result<Option<LocalStage>> {
        let stage = model.stages.get(stage_index).ok_or(GeomError::NoStage {
            index: stage_index,
            count: model.stages.len(),
        })?;
        let count = model.num_simplices();
        if s >= count {
            return Err(GeomError::NoSimplex { index: s, count });
        }
        let simplex = model.simplex(s);
        let m = simplex.len();
        let d = stage.degree;
        if !(2..=MAX_VARS).contains(&m) {
            return Err(GeomError::Dimension(m.saturating_sub(1)));
        }
        let per_vertex = d as usize + 1;
        // Per support mask (a subset of the local positions): the record of the face it names
        // (NONE without one), looked up once per face of the simplex — by face ids on a lazily
        // indexed model, whose face tables are then never built.
        let mut records = [NONE; 1 << MAX_VARS];
        let identity = match stage.kind {
            StageKind::Monotonic => {
                let table = model.stage(stage_index);
                simplex
                    .iter()
                    .all(|&v| table.vertex_records()[v as usize] == NONE)
            }
            _ => {
                records = model.simplex_records(stage_index, s);
                records[1..1 << m].iter().all(|&r| r == NONE)
            }
        };
        if identity && skip_identity {
            return Ok(None);
        }
        let mut local = LocalStage {
            kind: stage.kind,
            direction: stage.direction,
            degree: d,
            m,
            identity,
            tables: tables(m, d),
            points: Vec::new(),
            weights: Vec::new(),
            weighted: Vec::new(),
            mono: Vec::new(),
            mono_scaled: Vec::new(),
            mono_deriv: Vec::new(),
            sparse: None,
        };
        if stage.kind == StageKind::Monotonic {
            let table = model.stage(stage_index);
            for &v in simplex {
                let v = v as usize;
                local
                    .mono
                    .extend_from_slice(&table.coefficients()[v * per_vertex..(v + 1) * per_vertex]);
            }
            if finish {
                local.finish_monotonic();
            }
            return Ok(Some(local));
        }
        let rational = stage.kind == StageKind::Rational;
        let n_idx = local.tables.exps.len();
        local.points = Vec::with_capacity(n_idx);
        if rational {
            local.weights = Vec::with_capacity(n_idx);
        }
        // Per support mask with a record: the face's control points and weights, and the
        // positions ordered by global id (the face's own vertex order). Made once per mask, not
        // once per control point.
        type Support<'a> = (&'a [f64], &'a [f64], [usize; MAX_VARS], usize);
        let mut supports: [Option<Support>; 1 << MAX_VARS] = [None; 1 << MAX_VARS];
        let t = local.tables;
        for (index, e) in t.exps.iter().enumerate() {
            // Fixed default I/d, weight 1.
            let mut b = t.identity[index];
            let mut q = 1.0;
            if !local.identity {
                // The support's local positions (a subset, in increasing order) name the face.
                let mask = usize::from(t.support[index]);
                if records[mask] != NONE {
                    let (points, weights, pos, len) = *supports[mask].get_or_insert_with(|| {
                        let record = stage.faces.record(records[mask] as usize);
                        // Positions ordered by global id → the face's own vertex order
                        // t_0 < … < t_k.
                        let local = LocalFace::of_mask(simplex, mask as u8);
                        let mut pos: [usize; MAX_VARS] = [0; MAX_VARS];
                        for (slot, &p) in pos.iter_mut().zip(local.positions()) {
                            *slot = usize::from(p);
                        }
                        let len = local.len();
                        (record.points, record.weights, pos, len)
                    });
                    let mut shifted = [0u32; MAX_VARS];
                    for (x, &p) in shifted.iter_mut().zip(&pos[..len]) {
                        *x = u32::from(e[p]) - 1;
                    }
                    let r = small_rank(&shifted[..len]);
                    b = [0.0; MAX_VARS];
                    for (jj, &p) in pos[..len].iter().enumerate() {
                        b[p] = points[r * len + jj];
                    }
                    // A rational record without weights has unit weights.
                    if rational && !weights.is_empty() {
                        q = weights[r];
                    }
                    if let Some(recorded) = recorded.as_deref_mut() {
                        recorded.push(index);
                    }
                }
            }
            local.points.push(b);
            if rational {
                local.weights.push(q);
            }
        }
        if rational {
            local.finish_rational();
        }
        Ok(Some(local))
    }

    /// An identity stage (no records) of the given kind and degree in `m` variables.
    pub fn identity(kind: StageKind, degree: u32, m: usize) -> Result<LocalStage> {
        let stage = Stage::identity(kind, degree);
        let ids: Vec<u32> = (0..m as u32).collect();
        LocalStage::from_stage(&stage, 0, &ids)
    }

    fn fill_net(&mut self, stage: &Stage, lookup: &StageLookup, simplex: &[u32]) -> Result<()> {
        let (m, d) = (self.m, self.degree);
        let rational = stage.kind == StageKind::Rational;
        let n_idx = self.tables.exps.len();
        self.points = Vec::with_capacity(n_idx);
        if rational {
            self.weights = Vec::with_capacity(n_idx);
        }
        for e in &self.tables.exps {
            // Fixed default I/d, weight 1.
            let mut b = [0.0; MAX_VARS];
            for i in 0..m {
                b[i] = f64::from(e[i]) / f64::from(d);
            }
            let mut q = 1.0;
            if !self.identity {
                // Local positions of the support, ordered by global id → t_0 < … < t_k.
                let mask = (0..m).filter(|&i| e[i] > 0).fold(0u8, |a, i| a | 1 << i);
                let face = LocalFace::of_mask(simplex, mask);
                let pos: Vec<usize> = face.positions().iter().map(|&p| usize::from(p)).collect();
                if let Some(&ri) = lookup.faces.get(face.ids()) {
                    let rec = stage.faces.record(ri);
                    let k1 = pos.len();
                    let owned = multi_index::owned_count(k1, d);
                    let err = |what, found, expected| GeomError::FaceRecord {
                        stage: lookup.stage_index,
                        record: ri,
                        face: rec.face.to_vec(),
                        what,
                        found,
                        expected,
                    };
                    if rec.points.len() != owned * k1 {
                        return Err(err("points", rec.points.len(), owned * k1));
                    }
                    if rational && !rec.weights.is_empty() && rec.weights.len() != owned {
                        return Err(err("weights", rec.weights.len(), owned));
                    }
                    let j: Vec<u32> = pos.iter().map(|&i| u32::from(e[i])).collect();
                    let r = rank_owned(&j);
                    b = [0.0; MAX_VARS];
                    for (jj, &p) in pos.iter().enumerate() {
                        b[p] = rec.points[r * k1 + jj];
                    }
                    if rational && !rec.weights.is_empty() {
                        q = rec.weights[r];
                    }
                }
            }
            self.points.push(b);
            if rational {
                self.weights.push(q);
            }
        }
        if rational {
            self.finish_rational();
        }
        Ok(())
    }

    fn fill_monotonic(
        &mut self,
        stage: &Stage,
        lookup: &StageLookup,
        simplex: &[u32],
    ) -> Result<()> {
        let d = self.degree as usize;
        for &v in simplex {
            match lookup.vertices.get(&v) {
                Some(&ri) => {
                    let rec = &stage.vertex_maps[ri];
                    if rec.coefficients.len() != d + 1 {
                        return Err(GeomError::VertexMap {
                            stage: lookup.stage_index,
                            record: ri,
                            vertex: v,
                            found: rec.coefficients.len(),
                            expected: d + 1,
                        });
                    }
                    self.mono.extend_from_slice(&rec.coefficients);
                }
                None => self.mono.extend((0..=d).map(|j| j as f64 / d as f64)),
            }
        }
        self.finish_monotonic();
        Ok(())
    }

    /// `q_I b_I` of the rational net in `points` and `weights`.
    fn finish_rational(&mut self) {
        let m = self.m;
        self.weighted = self
            .points
            .iter()
            .zip(&self.weights)
            .map(|(b, &q)| weigh(m, q, b))
            .collect();
    }

    /// For an implicit monotonic stage of degree 1 whose maps all vanish at 0 (`g_i(t) = a_i t`,
    /// `a_i > 0`: the stage is the projective map `u_i = a_i w_i / Σ_j a_j w_j`) followed by the
    /// implicit Bézier or rational stage `next` in as many variables: the one rational stage equal
    /// to the pair. With `s = Σ a_j w_j` and `v = (a ∘ w) / s`, a degree-`d` net gives
    /// `Σ q_I b_I B_I(v) / Σ q_I B_I(v)` and `B_I(v) = a^I B_I(w) / s^d` (the `s^d` cancels), so
    /// the weights become `q_I a^I` and the control points move over from `next` (which the caller
    /// then drops). `None`, with `next` untouched, for any other pair.
    fn fuse_projective(&self, next: &mut LocalStage) -> Option<LocalStage> {
        let projective = self.kind == StageKind::Monotonic
            && self.direction == Direction::Implicit
            && !self.identity
            && self.degree == 1
            && self.mono.len() == 2 * self.m
            && self
                .mono
                .chunks_exact(2)
                .all(|c| projective_pair(c[0], c[1]));
        if !projective {
            return None;
        }
        let mut a = [0.0; MAX_VARS];
        for i in 0..self.m {
            a[i] = self.mono[2 * i + 1];
        }
        next.fuse_scales(self.m, &a)
    }

    /// [`LocalStage::fuse_projective`] of the projective stage `u_i = a_i w_i / Σ_j a_j w_j` in `m`
    /// variables (scales `a`, each positive and finite) followed by this stage: the fused rational
    /// stage (the points move over), or `None`, with this stage untouched, when this is not an
    /// implicit non-identity net in `m` variables or a fused weight is not positive and finite.
    fn fuse_scales(&mut self, m: usize, a: &Bary) -> Option<LocalStage> {
        let net = matches!(self.kind, StageKind::Bezier | StageKind::Rational)
            && self.direction == Direction::Implicit
            && !self.identity
            && self.m == m
            && self.points.len() == self.tables.exps.len();
        if !net {
            return None;
        }
        let rational = self.kind == StageKind::Rational;
        let count = self.points.len();
        let mut weights = Vec::with_capacity(count);
        // `q_I b_I` in the same pass, as [`LocalStage::finish_rational`] forms it.
        let mut weighted = Vec::with_capacity(count);
        for (r, (e, b)) in self.tables.exps.iter().zip(&self.points).enumerate() {
            let mut q = if rational { self.weights[r] } else { 1.0 };
            for i in 0..m {
                for _ in 0..e[i] {
                    q *= a[i];
                }
            }
            if !(q > 0.0 && q.is_finite()) {
                return None;
            }
            weights.push(q);
            weighted.push(weigh(m, q, b));
        }
        Some(LocalStage {
            kind: StageKind::Rational,
            direction: Direction::Implicit,
            degree: self.degree,
            m,
            identity: false,
            tables: self.tables,
            // The net is consumed by the fusion: its points move.
            points: std::mem::take(&mut self.points),
            weights,
            weighted,
            mono: Vec::new(),
            mono_scaled: Vec::new(),
            mono_deriv: Vec::new(),
            sparse: None,
        })
    }

    /// The scales `a_i` (by local vertex) of stage `stage_index` of an indexed model on its top
    /// simplex `s` when that stage is an implicit projective one ([`LocalStage::fuse_projective`]:
    /// monotonic of degree 1, not the identity there, each `g_i(t) = a_i t` with `a_i` positive
    /// and finite), read from the stage's table without building the stage; `None` otherwise
    /// (also for a simplex or dimension [`LocalStage::build_indexed`] refuses: it says why).
    fn projective_scales(model: &IndexedModel, stage_index: usize, s: usize) -> Option<Bary> {
        let stage = model.stages.get(stage_index)?;
        if stage.kind != StageKind::Monotonic
            || stage.direction != Direction::Implicit
            || stage.degree != 1
            || s >= model.num_simplices()
        {
            return None;
        }
        let simplex = model.simplex(s);
        if !(2..=MAX_VARS).contains(&simplex.len()) {
            return None;
        }
        let table = model.stage(stage_index);
        let records = table.vertex_records();
        if simplex.iter().all(|&v| records[v as usize] == NONE) {
            return None;
        }
        let coefficients = table.coefficients();
        let mut a = [0.0; MAX_VARS];
        for (slot, &v) in a.iter_mut().zip(simplex) {
            let v = v as usize;
            let (c0, c1) = (coefficients[2 * v], coefficients[2 * v + 1]);
            if !projective_pair(c0, c1) {
                return None;
            }
            *slot = c1;
        }
        Some(a)
    }

    /// Scaled coefficients and derivative coefficients of the monotonic maps in `mono`.
    fn finish_monotonic(&mut self) {
        let d = self.degree as usize;
        // Exact sizes up front: growing both vectors push by push was most of a small model's
        // monotonic stage construction.
        let vertices = self.mono.len() / (d + 1);
        self.mono_scaled.reserve_exact(vertices * (d + 1));
        self.mono_deriv.reserve_exact(vertices * d);
        for coeffs in self.mono.chunks_exact(d + 1) {
            for (j, a) in coeffs.iter().enumerate() {
                self.mono_scaled
                    .push(a * multi_index::binomial(d as u64, j as u64) as f64);
            }
            for j in 0..d {
                self.mono_deriv.push(
                    d as f64
                        * (coeffs[j + 1] - coeffs[j])
                        * multi_index::binomial(d as u64 - 1, j as u64) as f64,
                );
            }
        }
    }

    /// Map kind.
    pub fn kind(&self) -> StageKind {
        self.kind
    }

    /// Stored direction.
    pub fn direction(&self) -> Direction {
        self.direction
    }

    /// Degree `d`.
    pub fn degree(&self) -> u32 {
        self.degree
    }

    /// Number of barycentric coordinates `m = n + 1`.
    pub fn vars(&self) -> usize {
        self.m
    }

    /// True when no record touches this simplex: the local map is the identity.
    pub fn is_identity(&self) -> bool {
        self.identity
    }

    /// Dense control points `b_I` in canonical order, local vertex order (Bézier and rational; empty
    /// for monotonic). Each is `[f64; 4]`; the first `m` entries are the coordinates.
    pub fn control_points(&self) -> &[Bary] {
        &self.points
    }

    /// Dense weights `q_I` (rational only; empty otherwise).
    pub fn weights(&self) -> &[f64] {
        &self.weights
    }

    /// Monotonic coefficients `a_0..a_d` of local vertex `i` (empty slice for other kinds).
    pub fn monotonic_coefficients(&self, i: usize) -> &[f64] {
        let d = self.degree as usize + 1;
        self.mono.get(i * d..(i + 1) * d).unwrap_or(&[])
    }

    /// Evaluates the STORED map at `w` (for a parametric stage this is `X⁻¹`).
    #[inline]
    pub fn eval_stored(&self, w: &Bary) -> Bary {
        if self.identity {
            return *w;
        }
        match self.kind {
            StageKind::Bezier if self.sparse.is_some() => dispatch!(self, eval_sparse, w),
            StageKind::Bezier => dispatch_degree!(self, eval_bezier_const, eval_bezier, w),
            StageKind::Rational => dispatch_degree!(self, eval_rational_const, eval_rational, w),
            StageKind::Monotonic => {
                let m = self.m;
                let mut g = [0.0; MAX_VARS];
                let mut s = 0.0;
                for i in 0..m {
                    g[i] = self.g(i, w[i]);
                    s += g[i];
                }
                for v in g.iter_mut() {
                    *v /= s;
                }
                g
            }
        }
    }

    /// The same Bézier stage evaluated as the identity plus the deviations of the control points
    /// that are not the identity net's `I/d` ([`SparseTerm`]), when at most half of them deviate;
    /// otherwise unchanged. The identity net reproduces `w` (linear precision: `Σ_I (I/d) B_I(w) =
    /// w (Σ_j w_j)^(d−1)`, the homogeneous form the dense kernels compute), so
    /// `X(w) = w (Σ w)^(d−1) + Σ_{I deviating} (b_I − I/d) B_I(w)` with the same Jacobian: a
    /// stratified net (a solitary point per face: spec example `stratified-3d`, degrees 4, 3 and
    /// 2, with 1, ≤ 4 and ≤ 6 of its 35, 20 and 10 points deviating) costs a few terms instead of
    /// the whole net. Equal to the dense evaluation up to rounding, not bit for bit (the exporter
    /// uses it: [`LocalMap::fused`]); exact zeros stay zero as in the dense kernels (a deviation
    /// `b_I − I/d` has coordinate `i` only where `I_i > 0`, and then `B_I` carries `w_i^{I_i}`).
    fn sparsify(&mut self) {
        self.sparsify_among(0..self.points.len());
    }

    /// [`LocalStage::sparsify`] looking only at the control points of `candidates` (canonical
    /// indices, ascending), every other point being the identity net's: a stage built from its
    /// records ([`LocalMap::from_indexed_fused`]) looks at the points its records gave, not the
    /// whole net (on stratified-3d's export the scan of every net was 1.7 % of the instructions).
    fn sparsify_among(&mut self, candidates: impl IntoIterator<Item = usize>) {
        if self.kind != StageKind::Bezier
            || self.identity
            || self.degree == 0
            || self.points.len() != self.tables.exps.len()
        {
            return;
        }
        let (m, d) = (self.m, f64::from(self.degree));
        let mut terms = Vec::new();
        for r in candidates {
            let (e, mult, b) = (
                &self.tables.exps[r],
                self.tables.multinom[r],
                &self.points[r],
            );
            let mut delta = [0.0; MAX_VARS];
            for i in 0..m {
                // The identity net's point exactly as the nets are filled (`fill_net`).
                delta[i] = b[i] - f64::from(e[i]) / d;
            }
            if delta[..m].iter().any(|&x| x != 0.0) {
                terms.push(SparseTerm {
                    exps: *e,
                    mult,
                    delta,
                });
                if 4 * terms.len() > self.points.len() {
                    // Dense after all (see below): the rest of the scan changes nothing.
                    return;
                }
            }
        }
        // Per term the sparse kernels cost about what a dense term costs; past half the net the
        // dense kernels (unrolled, one de Casteljau pass for the Jacobian) are as fast.
        if 4 * terms.len() <= self.points.len() {
            self.sparse = Some(terms);
        }
    }

    /// [`Self::sparsify`]'s evaluation: `w (Σ w)^(d−1) + Σ (b_I − I/d) B_I(w)`.
    #[inline(always)]
    fn eval_sparse<const M: usize>(&self, w: &Bary) -> Bary {
        let d = self.degree as usize;
        let mut sum = 0.0;
        for &x in w.iter().take(M) {
            sum += x;
        }
        let scale = powi(sum, d as u32 - 1);
        let mut u = [0.0; MAX_VARS];
        for i in 0..M {
            u[i] = w[i] * scale;
        }
        for t in self.sparse.as_deref().unwrap_or(&[]) {
            let (powers, _) = sparse_powers::<M>(&t.exps, w);
            let mut bi = t.mult;
            for p in powers {
                bi *= p;
            }
            for i in 0..M {
                u[i] += bi * t.delta[i];
            }
        }
        u
    }

    /// [`Self::eval_sparse`] with the homogeneous Jacobian: the identity part's
    /// `δ_ij s^(d−1) + (d−1) w_i s^(d−2)` (`s = Σ w`), plus `(b_I − I/d) ∂B_I/∂w_j` with
    /// `∂B_I/∂w_j = mult_I I_j w_j^(I_j−1) Π_{k≠j} w_k^{I_k}`.
    #[inline(always)]
    fn val_jac_sparse<const M: usize>(&self, w: &Bary) -> (Bary, Mat) {
        let d = self.degree as usize;
        let mut sum = 0.0;
        for &x in w.iter().take(M) {
            sum += x;
        }
        let scale = powi(sum, d as u32 - 1);
        let slope = if d >= 2 {
            (d - 1) as f64 * powi(sum, d as u32 - 2)
        } else {
            0.0
        };
        let mut u = [0.0; MAX_VARS];
        let mut h = [[0.0; MAX_VARS]; MAX_VARS];
        for i in 0..M {
            u[i] = w[i] * scale;
            for j in 0..M {
                h[i][j] = w[i] * slope;
            }
            h[i][i] += scale;
        }
        for t in self.sparse.as_deref().unwrap_or(&[]) {
            let e = &t.exps;
            let (powers, lower) = sparse_powers::<M>(e, w);
            let mut bi = t.mult;
            for p in powers {
                bi *= p;
            }
            for i in 0..M {
                u[i] += bi * t.delta[i];
            }
            for j in 0..M {
                if e[j] == 0 {
                    continue;
                }
                let mut g = t.mult * f64::from(e[j]);
                for k in 0..M {
                    g *= if k == j { lower[k] } else { powers[k] };
                }
                for i in 0..M {
                    h[i][j] += g * t.delta[i];
                }
            }
        }
        (u, h)
    }

    /// `Σ b_I B_I(w)` with the variable count fixed at compile time, so the loops unroll.
    #[inline(always)]
    fn eval_bezier<const M: usize>(&self, w: &Bary) -> Bary {
        let t = self.tables;
        let pw = pow_table::<M>(self.degree as usize, w);
        let mut u = [0.0; MAX_VARS];
        for ((e, &mult), b) in t.exps.iter().zip(&t.multinom).zip(&self.points) {
            let bi = basis_m::<M>(mult, e, &pw);
            for i in 0..M {
                u[i] += bi * b[i];
            }
        }
        u
    }

    /// `Σ q_I b_I B_I / Σ q_I B_I`, fixed variable count.
    #[inline(always)]
    fn eval_rational<const M: usize>(&self, w: &Bary) -> Bary {
        let t = self.tables;
        let pw = pow_table::<M>(self.degree as usize, w);
        let mut p = [0.0; MAX_VARS];
        let mut q = 0.0;
        for (((e, &mult), qb), &wt) in t
            .exps
            .iter()
            .zip(&t.multinom)
            .zip(&self.weighted)
            .zip(&self.weights)
        {
            let bi = basis_m::<M>(mult, e, &pw);
            q += wt * bi;
            for i in 0..M {
                p[i] += bi * qb[i];
            }
        }
        for v in p.iter_mut().take(M) {
            *v /= q;
        }
        p
    }

    /// [`Self::eval_bezier`] over the compile-time table of degree `D` (`N` terms; `NL` unused):
    /// the same products in the same order, so the same bits, with every exponent known.
    #[inline(always)]
    fn eval_bezier_const<const M: usize, const D: usize, const N: usize, const NL: usize>(
        &self,
        w: &Bary,
    ) -> Bary {
        let terms: &[ConstTerm<M>; N] = &const { const_terms::<M, N>(D) };
        let Ok(points) = <&[Bary; N]>::try_from(self.points.as_slice()) else {
            return self.eval_bezier::<M>(w);
        };
        let pw = pow_table::<M>(D, w);
        let mut u = [0.0; MAX_VARS];
        for t in 0..N {
            let (e, mult) = &terms[t];
            let mut bi = *mult;
            for i in 0..M {
                bi *= pw[i][e[i]];
            }
            for i in 0..M {
                u[i] += bi * points[t][i];
            }
        }
        u
    }

    /// [`Self::eval_rational`] over the compile-time table (as [`Self::eval_bezier_const`]).
    #[inline(always)]
    fn eval_rational_const<const M: usize, const D: usize, const N: usize, const NL: usize>(
        &self,
        w: &Bary,
    ) -> Bary {
        let terms: &[ConstTerm<M>; N] = &const { const_terms::<M, N>(D) };
        let (Ok(weighted), Ok(weights)) = (
            <&[Bary; N]>::try_from(self.weighted.as_slice()),
            <&[f64; N]>::try_from(self.weights.as_slice()),
        ) else {
            return self.eval_rational::<M>(w);
        };
        let pw = pow_table::<M>(D, w);
        let mut p = [0.0; MAX_VARS];
        let mut q = 0.0;
        for t in 0..N {
            let (e, mult) = &terms[t];
            let mut bi = *mult;
            for i in 0..M {
                bi *= pw[i][e[i]];
            }
            q += weights[t] * bi;
            for i in 0..M {
                p[i] += bi * weighted[t][i];
            }
        }
        for v in p.iter_mut().take(M) {
            *v /= q;
        }
        p
    }

    /// [`Self::val_jac_bezier`] over the compile-time tables of degrees `D − 1` (`NL` terms) and
    /// `D` (`N`, for the ranks of `K + e_j`): the same bits.
    #[inline(always)]
    fn val_jac_bezier_const<const M: usize, const D: usize, const N: usize, const NL: usize>(
        &self,
        w: &Bary,
    ) -> (Bary, Mat) {
        let lower: &[ConstTerm<M>; NL] = &const { const_terms::<M, NL>(D - 1) };
        let up: &[[usize; M]; NL] =
            &const { const_up::<M, N, NL>(&const_terms::<M, N>(D), &const_terms::<M, NL>(D - 1)) };
        let Ok(points) = <&[Bary; N]>::try_from(self.points.as_slice()) else {
            return self.val_jac_bezier::<M>(w);
        };
        let pw = pow_table::<M>(D - 1, w);
        let mut u = [0.0; MAX_VARS];
        let mut h = [[0.0; MAX_VARS]; MAX_VARS];
        for r in 0..NL {
            let (e, mult) = &lower[r];
            let mut bk = *mult;
            for i in 0..M {
                bk *= pw[i][e[i]];
            }
            for j in 0..M {
                let b = &points[up[r][j]];
                let s = bk * w[j];
                for i in 0..M {
                    h[i][j] += bk * b[i];
                    u[i] += s * b[i];
                }
            }
        }
        let df = D as f64;
        scale_jacobian::<M>(&mut h, df);
        (u, h)
    }

    /// [`Self::val_jac_rational`] over the compile-time tables (as [`Self::val_jac_bezier_const`]).
    #[inline(always)]
    fn val_jac_rational_const<const M: usize, const D: usize, const N: usize, const NL: usize>(
        &self,
        w: &Bary,
    ) -> (Bary, Mat) {
        let lower: &[ConstTerm<M>; NL] = &const { const_terms::<M, NL>(D - 1) };
        let up: &[[usize; M]; NL] =
            &const { const_up::<M, N, NL>(&const_terms::<M, N>(D), &const_terms::<M, NL>(D - 1)) };
        let (Ok(weighted), Ok(weights)) = (
            <&[Bary; N]>::try_from(self.weighted.as_slice()),
            <&[f64; N]>::try_from(self.weights.as_slice()),
        ) else {
            return self.val_jac_rational::<M>(w);
        };
        let pw = pow_table::<M>(D - 1, w);
        let mut p = [0.0; MAX_VARS];
        let mut q = 0.0;
        let mut dp = [[0.0; MAX_VARS]; MAX_VARS];
        let mut dq = [0.0; MAX_VARS];
        for r in 0..NL {
            let (e, mult) = &lower[r];
            let mut bk = *mult;
            for i in 0..M {
                bk *= pw[i][e[i]];
            }
            for j in 0..M {
                let t = up[r][j];
                let qb = &weighted[t];
                let wt = weights[t];
                let s = bk * w[j];
                q += s * wt;
                dq[j] += bk * wt;
                for i in 0..M {
                    dp[i][j] += bk * qb[i];
                    p[i] += s * qb[i];
                }
            }
        }
        let df = D as f64;
        rational_quotient::<M>(&p, q, &dp, &dq, df)
    }

    /// Value and homogeneous Jacobian of a Bézier stage in one pass over the degree-`d − 1`
    /// basis: `∂X/∂w_j = d Σ_K B_K b_{K+e_j}` and `X = Σ_K B_K Σ_j w_j b_{K+e_j}` (one de Casteljau
    /// step). Zero coordinates stay exactly zero: `b_{K+e_j}` has coordinate `i` only if `K_i > 0`
    /// (then `B_K` carries `w_i^{K_i} = 0`) or `j = i` (then `w_j = 0`).
    #[inline(always)]
    fn val_jac_bezier<const M: usize>(&self, w: &Bary) -> (Bary, Mat) {
        let t = self.tables;
        let pw = pow_table::<M>(self.degree as usize - 1, w);
        let mut u = [0.0; MAX_VARS];
        let mut h = [[0.0; MAX_VARS]; MAX_VARS];
        for ((e, &mult), up) in t.lower_exps.iter().zip(&t.lower_multinom).zip(&t.up) {
            let bk = basis_m::<M>(mult, e, &pw);
            for j in 0..M {
                let b = &self.points[up[j] as usize];
                let s = bk * w[j];
                for i in 0..M {
                    h[i][j] += bk * b[i];
                    u[i] += s * b[i];
                }
            }
        }
        let df = f64::from(self.degree);
        scale_jacobian::<M>(&mut h, df);
        (u, h)
    }

    /// Value and homogeneous Jacobian of a rational stage in one pass over the degree-`d − 1`
    /// basis (numerator `P`, denominator `Q` and their partials), then the quotient rule.
    #[inline(always)]
    fn val_jac_rational<const M: usize>(&self, w: &Bary) -> (Bary, Mat) {
        let t = self.tables;
        let pw = pow_table::<M>(self.degree as usize - 1, w);
        let mut p = [0.0; MAX_VARS];
        let mut q = 0.0;
        let mut dp = [[0.0; MAX_VARS]; MAX_VARS];
        let mut dq = [0.0; MAX_VARS];
        for ((e, &mult), up) in t.lower_exps.iter().zip(&t.lower_multinom).zip(&t.up) {
            let bk = basis_m::<M>(mult, e, &pw);
            for j in 0..M {
                let r = up[j] as usize;
                let qb = &self.weighted[r];
                let wt = self.weights[r];
                let s = bk * w[j];
                q += s * wt;
                dq[j] += bk * wt;
                for i in 0..M {
                    dp[i][j] += bk * qb[i];
                    p[i] += s * qb[i];
                }
            }
        }
        let df = f64::from(self.degree);
        rational_quotient::<M>(&p, q, &dp, &dq, df)
    }

    /// `g_i(t)` of local vertex `i` (monotonic).
    #[inline]
    fn g(&self, i: usize, t: f64) -> f64 {
        let d = self.degree as usize;
        let a = &self.mono_scaled[i * (d + 1)..(i + 1) * (d + 1)];
        bernstein_1d(a, t)
    }

    /// `g_i'(t)` (monotonic).
    #[inline]
    fn g_prime(&self, i: usize, t: f64) -> f64 {
        let d = self.degree as usize;
        let a = &self.mono_deriv[i * d..(i + 1) * d];
        bernstein_1d(a, t)
    }

    /// Value and homogeneous `m × m` Jacobian `H[i][j] = ∂S_i/∂w_j` of the STORED map `S` at `w`.
    pub fn homogeneous_jacobian_stored(&self, w: &Bary) -> (Bary, Mat) {
        let m = self.m;
        let mut h = [[0.0; MAX_VARS]; MAX_VARS];
        if self.identity {
            for (i, row) in h.iter_mut().enumerate().take(m) {
                row[i] = 1.0;
            }
            return (*w, h);
        }
        match self.kind {
            StageKind::Bezier if self.sparse.is_some() => dispatch!(self, val_jac_sparse, w),
            StageKind::Bezier => dispatch_degree!(self, val_jac_bezier_const, val_jac_bezier, w),
            StageKind::Rational => {
                dispatch_degree!(self, val_jac_rational_const, val_jac_rational, w)
            }
            StageKind::Monotonic => {
                let mut g = [0.0; MAX_VARS];
                let mut gp = [0.0; MAX_VARS];
                let mut s = 0.0;
                for i in 0..m {
                    g[i] = self.g(i, w[i]);
                    gp[i] = self.g_prime(i, w[i]);
                    s += g[i];
                }
                let mut u = [0.0; MAX_VARS];
                for i in 0..m {
                    u[i] = g[i] / s;
                }
                for i in 0..m {
                    for j in 0..m {
                        let diag = if i == j { gp[i] } else { 0.0 };
                        h[i][j] = (diag - u[i] * gp[j]) / s;
                    }
                }
                (u, h)
            }
        }
    }

    /// Value and reduced `n × n` Jacobian of the STORED map at `w`.
    pub fn jacobian_stored(&self, w: &Bary) -> (Bary, Mat) {
        let (u, h) = self.homogeneous_jacobian_stored(w);
        (u, reduce(self.m, &h))
    }

    /// `X(w)`: the stage in the implicit direction (point coordinates → function coordinates),
    /// whatever the stored direction.
    #[inline]
    pub fn eval(&self, w: &Bary) -> Bary {
        match self.direction {
            Direction::Implicit => self.eval_stored(w),
            Direction::Parametric => self.invert_stored_with(w, true).w,
        }
    }

    /// `X⁻¹(u)`: function coordinates → point coordinates, whatever the stored direction.
    pub fn inverse(&self, u: &Bary) -> InverseResult {
        match self.direction {
            Direction::Implicit => self.invert_stored(u),
            Direction::Parametric => {
                let w = self.eval_stored(&project(self.m, u));
                InverseResult {
                    w,
                    iterations: 0,
                    residual: 0.0,
                    converged: true,
                }
            }
        }
    }

    /// `X(w)` and the reduced Jacobian `DX(w)` (for a parametric stage, the inverse of the stored
    /// map's Jacobian at `X(w)`; `None` there when it is singular).
    pub fn jacobian(&self, w: &Bary) -> (Bary, Option<Mat>) {
        match self.direction {
            Direction::Implicit => {
                let (u, j) = self.jacobian_stored(w);
                (u, Some(j))
            }
            Direction::Parametric => {
                let u = self.invert_stored_with(w, true).w;
                let (_, j) = self.jacobian_stored(&u);
                (u, linalg::inverse(self.m - 1, &j))
            }
        }
    }

    /// `det DX(w)` in reduced coordinates.
    pub fn det(&self, w: &Bary) -> f64 {
        match self.jacobian(w) {
            (_, Some(j)) => linalg::det(self.m - 1, &j),
            (_, None) => f64::INFINITY,
        }
    }

    /// Solves `S(w) = u` for the STORED map `S`: damped Newton on the face that supports `u`, then
    /// continuation from the face centroid if Newton stalls. `u` is first projected onto the simplex
    /// (negative or non-finite entries become 0, then it is rescaled to sum 1).
    pub fn invert_stored(&self, u: &Bary) -> InverseResult {
        self.invert_stored_with(u, false)
    }

    /// [`LocalStage::invert_stored`], optionally polished to rounding level (used when the inverse
    /// is itself the forward map of a parametric stage, whose errors compound through later stages).
    fn invert_stored_with(&self, u: &Bary, polish: bool) -> InverseResult {
        let m = self.m;
        let u = project(m, u);
        if self.identity {
            return InverseResult {
                w: u,
                iterations: 0,
                residual: 0.0,
                converged: true,
            };
        }
        let mut support = [0usize; MAX_VARS];
        let mut k1 = 0;
        for i in 0..m {
            if u[i] > 0.0 {
                support[k1] = i;
                k1 += 1;
            }
        }
        if k1 <= 1 {
            // A vertex (or nothing left after projection): vertices are fixed exactly.
            return InverseResult {
                w: u,
                iterations: 0,
                residual: 0.0,
                converged: k1 == 1,
            };
        }
        let sup = &support[..k1];
        let mut iterations = 0;
        let start = self.projective_inverse(sup, &u).unwrap_or(u);
        if let Some((w, r)) = self.newton(
            sup,
            &u,
            start,
            NEWTON_MAX_ITERATIONS,
            INVERSE_TOLERANCE,
            polish,
            &mut iterations,
        ) {
            return InverseResult {
                w,
                iterations,
                residual: r,
                converged: true,
            };
        }
        // Continuation: from the face centroid c (whose image c* = S(c) is known) follow
        // u(t) = c* + t (u − c*); the preimage path is continuous for a diffeomorphism.
        let mut w = [0.0; MAX_VARS];
        for &i in sup {
            w[i] = 1.0 / k1 as f64;
        }
        let c_star = self.eval_stored(&w);
        let (mut t, mut h) = (0.0f64, 0.25f64);
        let mut steps = 0;
        while t < 1.0 && steps < CONTINUATION_MAX_STEPS {
            steps += 1;
            let t_next = (t + h).min(1.0);
            let mut target = [0.0; MAX_VARS];
            for &i in sup {
                target[i] = c_star[i] + t_next * (u[i] - c_star[i]);
            }
            let tol = if t_next >= 1.0 {
                INVERSE_TOLERANCE
            } else {
                CONTINUATION_INTERMEDIATE_TOLERANCE
            };
            match self.newton(
                sup,
                &target,
                w,
                CONTINUATION_CORRECTOR_ITERATIONS,
                tol,
                polish && t_next >= 1.0,
                &mut iterations,
            ) {
                Some((w_next, r)) => {
                    w = w_next;
                    t = t_next;
                    h = (h * 2.0).min(0.5);
                    if t >= 1.0 {
                        return InverseResult {
                            w,
                            iterations,
                            residual: r,
                            converged: true,
                        };
                    }
                }
                None => {
                    h *= 0.5;
                    if h < CONTINUATION_MIN_STEP {
                        break;
                    }
                }
            }
        }
        if k1 == 2 {
            // Safeguard on an edge: the stage maps the edge onto itself fixing its ends, so
            // `t ↦ S((1 − t) e_a + t e_b)_b` increases from 0 to 1 and bisection cannot fail.
            let (a, b) = (sup[0], sup[1]);
            let (mut lo, mut hi) = (0.0f64, 1.0f64);
            for _ in 0..EDGE_BISECTION_STEPS {
                let mid = 0.5 * (lo + hi);
                if mid <= lo || mid >= hi {
                    break;
                }
                iterations += 1;
                let mut x = [0.0; MAX_VARS];
                x[a] = 1.0 - mid;
                x[b] = mid;
                if self.eval_stored(&x)[b] < u[b] {
                    lo = mid;
                } else {
                    hi = mid;
                }
            }
            let t = 0.5 * (lo + hi);
            w = [0.0; MAX_VARS];
            w[a] = 1.0 - t;
            w[b] = t;
        }
        let (val, jac) = self.homogeneous_jacobian_stored(&w);
        let r = residual(m, &val, &u);
        InverseResult {
            w,
            iterations,
            residual: r,
            converged: r <= acceptance_tolerance(rounding_scale(m, &w, &jac)),
        }
    }

    /// The inverse of a degree-1 monotonic stage on the face `sup`, in closed form: `g_i(t) =
    /// a_i t` (`a₀ = 0`, spec §5.4), so `S(w)_i = a_i w_i / Σ_j a_j w_j` is projective and
    /// `w_i = (u_i / a_i) / Σ_j u_j / a_j`. Newton's start ([`LocalStage::invert_stored_with`]):
    /// it then only confirms the residual and polishes the rounding, where from `w = u` it took
    /// ~5 iterations. `None` for any other stage, or weights that are not positive and finite.
    fn projective_inverse(&self, sup: &[usize], u: &Bary) -> Option<Bary> {
        if self.kind != StageKind::Monotonic || self.degree != 1 {
            return None;
        }
        let mut w = [0.0; MAX_VARS];
        let mut total = 0.0;
        for &i in sup {
            // `mono_scaled` holds `a_j C(1, j)`: entries `a_0`, `a_1` of vertex `i`. A stage
            // with `a_0 ≠ 0` is not one the spec allows; Newton starts from `u` there as before.
            let (a0, a) = (
                *self.mono_scaled.get(2 * i)?,
                *self.mono_scaled.get(2 * i + 1)?,
            );
            if a0 != 0.0 || !(a > 0.0 && a.is_finite()) {
                return None;
            }
            w[i] = u[i] / a;
            total += w[i];
        }
        if !(total > 0.0 && total.is_finite()) {
            return None;
        }
        for &i in sup {
            w[i] /= total;
        }
        Some(w)
    }

    /// Damped Newton on the stored map (see [`newton_solve`]).
    #[allow(clippy::too_many_arguments)]
    fn newton(
        &self,
        sup: &[usize],
        target: &Bary,
        w: Bary,
        max_iter: u32,
        tol: f64,
        polish: bool,
        iterations: &mut u32,
    ) -> Option<(Bary, f64)> {
        newton_solve(
            self.m,
            sup,
            target,
            w,
            NewtonSettings {
                max_iter,
                tol,
                // Final solves aim well inside the acceptance threshold; intermediate
                // continuation points only need to be good starts.
                target: if tol <= INVERSE_TOLERANCE {
                    NEWTON_TARGET
                } else {
                    tol
                },
                polish,
            },
            iterations,
            |x| self.homogeneous_jacobian_stored(x),
        )
        .map(|(w, r, _, _)| (w, r))
    }
}

/// Iteration limits of [`newton_solve`].
#[derive(Clone, Copy)]
struct NewtonSettings {
    max_iter: u32,
    /// Residual accepted (raised to the rounding floor of the point when that is larger, see
    /// [`acceptance_tolerance`]).
    tol: f64,
    /// Residual Newton iterates towards before stopping (≤ `tol`; raised to the rounding floor):
    /// stopping well inside the acceptance threshold keeps a re-evaluation from crossing it.
    target: f64,
    /// After reaching `tol`, take one more step and keep it if it lowers the residual: Newton
    /// converges quadratically, so this lands at rounding level for the price of one iteration.
    polish: bool,
}

/// Damped Newton for `S(w) = target` with unknowns on `sup` only (the others stay exactly 0), in
/// barycentric coordinates based at `sup[0]`. `jac` returns the value and a homogeneous Jacobian
/// that is correct on tangent vectors (`Σ v = 0`). Steps stop short of the face boundary
/// (the solution is in the open face) and are halved until the residual decreases. Iterates until
/// the residual reaches `settings.target` (or the rounding floor `ROUNDING_ULPS · ε · scale` of the
/// point, [`rounding_scale`]) or stops decreasing; returns the solution and its residual when that
/// is within `settings.tol` or the acceptance floor ([`acceptance_tolerance`]), `None` otherwise.
#[allow(clippy::too_many_arguments)]
fn newton_solve(
    m: usize,
    sup: &[usize],
    target: &Bary,
    mut w: Bary,
    settings: NewtonSettings,
    iterations: &mut u32,
    jac: impl Fn(&Bary) -> (Bary, Mat),
) -> Option<(Bary, f64, Bary, Mat)> {
    let k = sup.len() - 1;
    let s0 = sup[0];
    let (mut val, mut h) = jac(&w);
    let mut r = residual(m, &val, target);
    let mut polishing = false;
    // Accepted residual at the current point: the caller's tolerance, or the point's rounding
    // floor when the stage's scale makes that larger.
    let accept = |w: &Bary, h: &Mat| {
        let scale = rounding_scale(m, w, h);
        let floor = if scale.is_finite() {
            ACCEPT_ULPS * f64::EPSILON * scale
        } else {
            0.0
        };
        settings.tol.max(floor)
    };
    for _ in 0..=settings.max_iter {
        let scale = rounding_scale(m, &w, &h);
        let floor = if scale.is_finite() {
            ROUNDING_ULPS * f64::EPSILON * scale
        } else {
            0.0
        };
        if r <= settings.target.max(floor) {
            if !settings.polish || polishing || r == 0.0 {
                return Some((w, r, val, h));
            }
            polishing = true;
        }
        *iterations += 1;
        let mut a = [[0.0; MAX_VARS]; MAX_VARS];
        let mut rhs = [0.0; MAX_VARS];
        for (ri, &s) in sup[1..].iter().enumerate() {
            rhs[ri] = target[s] - val[s];
            for (ci, &c) in sup[1..].iter().enumerate() {
                a[ri][ci] = h[s][c] - h[s][s0];
            }
        }
        let Some(delta) = linalg::solve(k, &a, &rhs) else {
            return (r <= accept(&w, &h)).then_some((w, r, val, h));
        };
        let mut full = [0.0; MAX_VARS];
        let mut sum = 0.0;
        for (ci, &c) in sup[1..].iter().enumerate() {
            full[c] = delta[ci];
            sum += delta[ci];
        }
        full[s0] = -sum;
        // Fraction to the boundary: the solution lies in the open face, so never step past it.
        let mut alpha = 1.0f64;
        for &i in sup {
            if full[i] < 0.0 && w[i] + full[i] <= 0.0 {
                alpha = alpha.min(0.9 * w[i] / -full[i]);
            }
        }
        let mut accepted = false;
        for _ in 0..if polishing { 1 } else { 20 } {
            let mut trial = w;
            for &i in sup {
                trial[i] += alpha * full[i];
            }
            // Value and Jacobian together: an accepted full step (the usual case) needs no
            // second evaluation.
            let (tv, th) = jac(&trial);
            let tr = residual(m, &tv, target);
            if tr < r {
                w = trial;
                r = tr;
                val = tv;
                h = th;
                accepted = true;
                break;
            }
            alpha *= 0.5;
        }
        if !accepted {
            // No step lowers the residual: rounding level (accepted) or a stall (refused).
            return (r <= accept(&w, &h)).then_some((w, r, val, h));
        }
        if polishing {
            return Some((w, r, val, h));
        }
    }
    (r <= accept(&w, &h)).then_some((w, r, val, h))
}

/// Homogeneous `m × m` matrix acting on tangent vectors like the reduced `n × n` matrix `r`
/// (inverse of [`reduce`] on tangent vectors): `H[k][l] = R[k−1][l−1]`, column 0 zero, row 0 minus
/// the column sums.
pub fn embed(m: usize, r: &Mat) -> Mat {
    let mut h = [[0.0; MAX_VARS]; MAX_VARS];
    for l in 1..m {
        let mut col = 0.0;
        for k in 1..m {
            h[k][l] = r[k - 1][l - 1];
            col += r[k - 1][l - 1];
        }
        h[0][l] = -col;
    }
    h
}

/// Reduced `n × n` Jacobian from the homogeneous one: `R[k−1][l−1] = H[k][l] − H[k][0]`.
pub fn reduce(m: usize, h: &Mat) -> Mat {
    let mut r = [[0.0; MAX_VARS]; MAX_VARS];
    for k in 1..m {
        for l in 1..m {
            r[k - 1][l - 1] = h[k][l] - h[k][0];
        }
    }
    r
}

/// Projects onto the closed simplex: negative or non-finite entries become 0, then the rest are
/// rescaled to sum 1 unless the sum is already within `1e-14` of 1 (exact zeros stay zero). An
/// all-zero input stays zero.
pub fn project(m: usize, u: &Bary) -> Bary {
    let mut out = [0.0; MAX_VARS];
    let mut s = 0.0;
    for i in 0..m {
        // `0 < x ≤ MAX` is "finite and positive" (NaN fails it), written as one select so the
        // loop has no branch: the exporter projects every point it places (~5 % of an export
        // went to this line). Adding the 0.0 of a dropped entry leaves `s ≥ 0` unchanged.
        let x = u[i];
        let kept = if x > 0.0 && x <= f64::MAX { x } else { 0.0 };
        out[i] = kept;
        s += kept;
    }
    if s > 0.0 && (s - 1.0).abs() > PROJECT_SLACK {
        for v in out.iter_mut() {
            *v /= s;
        }
    }
    out
}

fn residual(m: usize, a: &Bary, b: &Bary) -> f64 {
    (0..m).map(|i| (a[i] - b[i]).abs()).fold(0.0, f64::max)
}

/// `Σ_j c_j t^j (1 − t)^{d−j}` with `c_j` already scaled by `C(d, j)`.
///
/// Degrees 0–4 (the examples' monotonic maps and their derivatives) go through
/// [`bernstein_1d_fixed`]: the same sum.
#[inline]
fn bernstein_1d(c: &[f64], t: f64) -> f64 {
    match c.len() {
        1 => bernstein_1d_fixed::<0>(c, t),
        2 => bernstein_1d_fixed::<1>(c, t),
        3 => bernstein_1d_fixed::<2>(c, t),
        4 => bernstein_1d_fixed::<3>(c, t),
        5 => bernstein_1d_fixed::<4>(c, t),
        _ => bernstein_1d_any(c, t),
    }
}

/// [`bernstein_1d`] with the degree `D` (`c.len() = D + 1`) known to the compiler: the loops
/// unroll and the factors `t⁰ = (1 − t)⁰ = 1` fold away (exact), so the bits are those of
/// [`bernstein_1d_any`].
#[inline(always)]
fn bernstein_1d_fixed<const D: usize>(c: &[f64], t: f64) -> f64 {
    let c = &c[..=D];
    let s = 1.0 - t;
    let mut tp = [1.0; MAX_DEGREE as usize + 1];
    let mut sp = [1.0; MAX_DEGREE as usize + 1];
    for j in 1..=D {
        tp[j] = tp[j - 1] * t;
        sp[j] = sp[j - 1] * s;
    }
    (0..=D).map(|j| c[j] * tp[j] * sp[D - j]).sum()
}

/// [`bernstein_1d`] of any degree.
fn bernstein_1d_any(c: &[f64], t: f64) -> f64 {
    let d = c.len().saturating_sub(1);
    let s = 1.0 - t;
    let mut tp = [1.0; MAX_DEGREE as usize + 1];
    let mut sp = [1.0; MAX_DEGREE as usize + 1];
    for j in 1..=d {
        tp[j] = tp[j - 1] * t;
        sp[j] = sp[j - 1] * s;
    }
    (0..=d).map(|j| c[j] * tp[j] * sp[d - j]).sum()
}

/// Rank of owned index `j` (all entries ≥ 1, sum `d`) in canonical order of owned indices:
/// subtracting 1 from every entry is an order-preserving bijection onto all indices of degree
/// `d − k − 1`.
/// `q b` in the first `m` coordinates (the rest zero): a rational net's weighted point `q_I b_I`.
#[inline]
fn weigh(m: usize, q: f64, b: &Bary) -> Bary {
    let mut out = [0.0; MAX_VARS];
    for i in 0..m {
        out[i] = q * b[i];
    }
    out
}

/// Whether the degree-1 monotonic map with Bernstein coefficients `c0`, `c1`
/// (`g(t) = c0 (1 − t) + c1 t`) is `a t` with `a` positive and finite: a projective stage's map
/// ([`LocalStage::fuse_projective`]).
fn projective_pair(c0: f64, c1: f64) -> bool {
    c0 == 0.0 && c1 > 0.0 && c1.is_finite()
}

fn rank_owned(j: &[u32]) -> usize {
    let shifted: Vec<u32> = j.iter().map(|&e| e - 1).collect();
    multi_index::rank(&shifted)
}

/// Binomial coefficients `C(n, k)` for `n < 24` (Pascal's triangle, exact): enough for
/// [`small_rank`] (`n ≤ MAX_DEGREE + MAX_VARS − 2`).
const SMALL_BINOMIAL: [[u32; 24]; 24] = {
    let mut c = [[0u32; 24]; 24];
    let mut n = 0;
    while n < 24 {
        c[n][0] = 1;
        let mut k = 1;
        while k <= n {
            c[n][k] = c[n - 1][k - 1] + c[n - 1][k];
            k += 1;
        }
        n += 1;
    }
    c
};

/// [`multi_index::rank`] for the short indices of a local net (at most [`MAX_VARS`] entries,
/// entries summing below [`MAX_DEGREE`]) from a table, without its per-term binomials: the indices with a
/// larger entry `e > index[p]` at position `p` number `Σ_e C(rest − e + a, a)` with `a = m − p − 2`,
/// which is `C(rest − index[p] + a, a + 1)` (the hockey-stick identity).
#[inline]
fn small_rank(index: &[u32]) -> usize {
    let m = index.len();
    let mut remaining: usize = index.iter().map(|&e| e as usize).sum();
    let mut r = 0usize;
    for (p, &entry) in index.iter().enumerate().take(m.saturating_sub(1)) {
        let entry = entry as usize;
        if remaining > entry {
            r += SMALL_BINOMIAL[remaining - entry + m - p - 2][m - p - 1] as usize;
        }
        remaining -= entry;
    }
    r
}

/// All stages of one top simplex, in application order (`stages[0]` first).
#[derive(Clone, Debug)]
pub struct LocalMap {
    m: usize,
    stages: Vec<LocalStage>,
}

impl LocalMap {
    /// Builds every stage of `model` on simplex `simplex_index`.
    pub fn from_model(model: &Model, simplex_index: usize) -> Result<LocalMap> {
        let count = model.num_simplices();
        if simplex_index >= count {
            return Err(GeomError::NoSimplex {
                index: simplex_index,
                count,
            });
        }
        let simplex = model.simplex(simplex_index);
        let stages = model
            .stages
            .iter()
            .enumerate()
            .map(|(i, s)| LocalStage::from_stage(s, i, simplex))
            .collect::<Result<Vec<_>>>()?;
        Ok(LocalMap {
            m: simplex.len(),
            stages: stages.into_iter().filter(|s| !s.is_identity()).collect(),
        })
    }

    /// Builds every stage of an indexed model on its top simplex `s` (see
    /// [`LocalStage::from_indexed`]).
    pub fn from_indexed(model: &IndexedModel, s: usize) -> Result<LocalMap> {
        LocalMap::build_indexed(model, s, true)
    }

    /// [`LocalMap::from_indexed`] then [`LocalMap::fused`], without building the evaluation
    /// tables of a monotonic stage that the fusion replaces (on the sphere example's export, 0.8 %
    /// of the instructions went to tables that were built and dropped).
    ///
    /// # Errors
    /// As [`LocalMap::from_indexed`].
    pub fn from_indexed_fused(model: &IndexedModel, s: usize) -> Result<LocalMap> {
        let m = model.dim() + 1;
        let mut stages = Vec::with_capacity(model.stages.len());
        // A projective stage not yet placed (its index and scales): it is built only if the next
        // non-identity stage does not take it in. Identity stages are left out before pairing,
        // as in [`LocalMap::fused`] of the unfused map.
        let mut pending: Option<(usize, Bary)> = None;
        // The control points a stage's records gave (the rest are the identity net's).
        let mut recorded = Vec::new();
        let place = |stages: &mut Vec<LocalStage>, i: usize| -> Result<()> {
            let stage = LocalStage::build_indexed(model, i, s, true, true, None)?;
            stages.push(stage.expect("a projective stage is not the identity"));
            Ok(())
        };
        for i in 0..model.stages.len() {
            if let Some(a) = LocalStage::projective_scales(model, i, s) {
                if let Some((j, _)) = pending.replace((i, a)) {
                    place(&mut stages, j)?;
                }
                continue;
            }
            recorded.clear();
            let built = LocalStage::build_indexed(model, i, s, true, true, Some(&mut recorded))?;
            let Some(mut stage) = built else {
                continue;
            };
            if let Some((j, a)) = pending.take() {
                if let Some(fused) = stage.fuse_scales(m, &a) {
                    stages.push(fused);
                    continue;
                }
                place(&mut stages, j)?;
            }
            stage.sparsify_among(recorded.iter().copied());
            stages.push(stage);
        }
        if let Some((j, _)) = pending {
            place(&mut stages, j)?;
        }
        // Stages were fused or left out: give their room back (in place), a map per crossed
        // simplex is kept.
        stages.shrink_to_fit();
        Ok(LocalMap { m, stages })
    }

    fn build_indexed(model: &IndexedModel, s: usize, finish: bool) -> Result<LocalMap> {
        let m = model.dim() + 1;
        let mut stages = Vec::with_capacity(model.stages.len());
        for i in 0..model.stages.len() {
            if let Some(stage) = LocalStage::build_indexed(model, i, s, true, finish, None)? {
                stages.push(stage);
            }
        }
        // Identity stages are left out: give their room back (in place), a map per crossed simplex
        // is kept.
        stages.shrink_to_fit();
        Ok(LocalMap { m, stages })
    }

    /// A map from explicit local stages (all with `m` variables), in application order.
    pub fn from_stages(m: usize, stages: Vec<LocalStage>) -> LocalMap {
        LocalMap { m, stages }
    }

    /// The same map with each implicit projective stage (monotonic of degree 1, `g_i(t) = a_i t`)
    /// that is followed by an implicit Bézier or rational stage merged into it as one rational
    /// stage (`LocalStage::fuse_projective`): the spec examples' "vertex weights, then level
    /// crossings" pair. One evaluation instead of two and no chain-rule product per Jacobian;
    /// equal to the original map up to rounding (not bit for bit), so callers that must
    /// reproduce the unfused bits keep the unfused map.
    ///
    /// Also evaluates each Bézier stage whose net mostly is the identity's as the identity plus
    /// its few deviating terms (`LocalStage::sparsify`; equal up to rounding as well).
    pub fn fused(self) -> LocalMap {
        let mut stages = Vec::with_capacity(self.stages.len());
        let mut it = self.stages.into_iter().peekable();
        while let Some(stage) = it.next() {
            match it.peek_mut().and_then(|next| stage.fuse_projective(next)) {
                Some(f) => {
                    stages.push(f);
                    it.next();
                }
                None => stages.push(stage),
            }
        }
        for stage in &mut stages {
            // A monotonic stage built without its tables ([`LocalMap::from_indexed_fused`]) that
            // was not fused gets them now.
            if stage.kind == StageKind::Monotonic
                && stage.mono_scaled.is_empty()
                && !stage.mono.is_empty()
            {
                stage.finish_monotonic();
            }
            stage.sparsify();
        }
        LocalMap { m: self.m, stages }
    }

    /// The non-identity stages, in application order.
    pub fn stages(&self) -> &[LocalStage] {
        &self.stages
    }

    /// Bytes this map holds on the heap (its stages and their tables), for a cache's budget
    /// ([`crate::ModelEval::with_map_cache_budget`]).
    pub fn heap_bytes(&self) -> usize {
        self.stages.capacity() * std::mem::size_of::<LocalStage>()
            + self
                .stages
                .iter()
                .map(LocalStage::heap_bytes)
                .sum::<usize>()
    }

    /// Number of barycentric coordinates.
    pub fn vars(&self) -> usize {
        self.m
    }

    /// `X(w) = X_{last}(… X_0(w))`.
    #[inline]
    pub fn eval(&self, w: &Bary) -> Bary {
        let mut u = *w;
        for s in &self.stages {
            u = s.eval(&u);
        }
        u
    }

    /// `X(w)` and its reduced Jacobian by the chain rule; `None` if a parametric stage's stored
    /// Jacobian is singular.
    pub fn jacobian(&self, w: &Bary) -> (Bary, Option<Mat>) {
        // One stage (the fused examples, most fitted models): its own Jacobian, the value the
        // loop below returns, without the accumulator's copies (a sixth of an exporter's
        // Jacobian).
        if let [only] = self.stages.as_slice() {
            let (u, j) = only.jacobian(w);
            return match j {
                Some(j) => (u, Some(j)),
                None => (self.eval(w), None),
            };
        }
        let n = self.m - 1;
        let mut u = *w;
        let mut acc: Option<Mat> = None;
        for s in &self.stages {
            let (next, j) = s.jacobian(&u);
            let Some(j) = j else {
                return (self.eval(w), None);
            };
            // The first stage's Jacobian is the product so far (a product with the identity
            // would only add zeros: the same values, but for the sign of a zero entry).
            acc = Some(match acc {
                Some(a) => linalg::mul(n, &j, &a),
                None => j,
            });
            u = next;
        }
        (u, Some(acc.unwrap_or_else(|| identity_mat(n))))
    }

    /// `det DX(w)` (reduced).
    pub fn det(&self, w: &Bary) -> f64 {
        match self.jacobian(w).1 {
            Some(j) => linalg::det(self.m - 1, &j),
            None => f64::INFINITY,
        }
    }

    /// `X⁻¹(u) = X_0⁻¹(… X_{last}⁻¹(u))`, then (with more than one stage) a few Newton steps on the
    /// whole map, since each stage's residual is amplified by the later stages. `residual` is that
    /// of the whole map, `|X(w) − u|∞`.
    ///
    /// A point a hair off a face — coordinates below [`FACE_DUST`], the rounding that combining
    /// points of the face leaves where its zeros are — whose inverse is not accepted is solved
    /// again on the face itself (faces map to themselves): Newton started a hair inside the
    /// simplex had stalled at 1.02e-12 on a valid implicit chain (test
    /// `inverses_converge_a_hair_off_a_face` in ism-export). Only failures take the second
    /// solve, so every accepted inverse is unchanged.
    pub fn inverse(&self, u: &Bary) -> InverseResult {
        let first = self.inverse_once(u);
        if first.converged {
            return first;
        }
        let m = self.m;
        let u = project(m, u);
        let mut on_face = u;
        let mut dust = false;
        for x in on_face[..m].iter_mut() {
            if *x > 0.0 && *x < FACE_DUST {
                *x = 0.0;
                dust = true;
            }
        }
        if !dust {
            return first;
        }
        let second = self.inverse_once(&on_face);
        if !second.converged {
            return first;
        }
        // Judged against the point asked for: the dust it dropped is below the tolerance.
        let residual = residual(m, &self.eval(&second.w), &u);
        InverseResult {
            iterations: first.iterations + second.iterations,
            residual,
            converged: self.accepts(&second.w, residual),
            ..second
        }
    }

    /// [`LocalMap::inverse`] without the second solve on a face.
    fn inverse_once(&self, u: &Bary) -> InverseResult {
        let m = self.m;
        let u = project(m, u);
        let mut w = u;
        let mut iterations = 0;
        let mut all = true;
        for s in self.stages.iter().rev() {
            let r = s.inverse(&w);
            iterations += r.iterations;
            all &= r.converged;
            w = r.w;
        }
        // A parametric stage's inverse is its stored map, evaluated directly: nothing to polish.
        let all_parametric = self
            .stages
            .iter()
            .all(|s| s.direction() == Direction::Parametric);
        if self.stages.len() <= 1 || all_parametric {
            let residual = if self.stages.is_empty() {
                0.0
            } else {
                residual(m, &self.eval(&w), &u)
            };
            // A map of parametric stages only is inverted by evaluating its stored maps: exact to
            // rounding, whatever the residual says. That residual measures the forward map
            // `X = Y⁻¹` at `w`, itself a Newton solve on each stored map, which can stop ulps
            // above `INVERSE_TOLERANCE` a hair off a face (1.05e-12 on a quadratic edge stage,
            // test `inverses_converge_a_hair_off_a_face` in ism-export): it is reported, not
            // judged, and only a non-finite preimage fails.
            let converged = if all_parametric && !self.stages.is_empty() {
                all && w[..m].iter().all(|x| x.is_finite())
            } else {
                all && self.accepts(&w, residual)
            };
            return InverseResult {
                w,
                iterations,
                residual,
                converged,
            };
        }
        let mut support = [0usize; MAX_VARS];
        let mut k1 = 0;
        for i in 0..m {
            if u[i] > 0.0 {
                support[k1] = i;
                k1 += 1;
            }
        }
        if k1 > 1 {
            let settings = NewtonSettings {
                max_iter: MAP_POLISH_ITERATIONS,
                tol: INVERSE_TOLERANCE,
                target: NEWTON_TARGET,
                polish: true,
            };
            let jac = |x: &Bary| {
                let (val, j) = self.jacobian(x);
                (val, embed(m, &j.unwrap_or_else(|| identity_mat(m - 1))))
            };
            if let Some((polished, ..)) =
                newton_solve(m, &support[..k1], &u, w, settings, &mut iterations, jac)
            {
                w = polished;
            }
        }
        let residual = residual(m, &self.eval(&w), &u);
        InverseResult {
            w,
            iterations,
            residual,
            converged: self.accepts(&w, residual),
        }
    }

    /// Whether `|X(w) − u|∞ = residual` counts as converged: [`INVERSE_TOLERANCE`], or the
    /// rounding floor of the whole map at `w` ([`acceptance_tolerance`] of a scale
    /// `stages · (1 + ‖DX(w)‖∞)`: every stage rounds its output, and the later stages' Jacobians
    /// amplify it). The Jacobian is only computed when the plain tolerance is missed.
    fn accepts(&self, w: &Bary, residual: f64) -> bool {
        if residual <= INVERSE_TOLERANCE {
            return true;
        }
        if residual.is_nan() {
            return false;
        }
        let n = self.m - 1;
        let Some(j) = self.jacobian(w).1 else {
            return false;
        };
        let norm = (0..n)
            .map(|k| (0..n).map(|l| j[k][l].abs()).sum::<f64>())
            .fold(0.0, f64::max);
        let scale = self.stages.len().max(1) as f64 * (1.0 + norm);
        residual <= acceptance_tolerance(scale)
    }
}

/// `X⁻¹(u)` together with `X` and its reduced Jacobian at the solution: what a caller that needs
/// `det DX` or `∇F` there would otherwise compute again.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Solved {
    /// Barycentric preimage.
    pub w: Bary,
    /// `X(w)` (equal to `u` within `residual`).
    pub x: Bary,
    /// Reduced Jacobian `DX(w)`.
    pub jacobian: Mat,
    /// `|X(w) − u|∞`.
    pub residual: f64,
    /// Newton iterations spent.
    pub iterations: u32,
}

/// Newton iterations [`LocalMap::inverse_near`] spends before giving up: from a guess within a few
/// `1e-3` of the solution, quadratic convergence reaches `1e-12` in three or four.
const NEAR_MAX_ITERATIONS: u32 = 8;

impl LocalMap {
    /// For a map whose stages are all stored in the parametric direction (`Y = X⁻¹` stored):
    /// `w = Y(u)` by direct evaluation, `X(w) = u`, and `DX(w) = DY(u)⁻¹`, without any Newton
    /// solve. `None` when a stage is implicit or `DY` is singular.
    pub fn param_solve(&self, u: &Bary) -> Option<Solved> {
        if !self
            .stages
            .iter()
            .all(|s| s.direction() == Direction::Parametric)
        {
            return None;
        }
        let n = self.m - 1;
        let u = project(self.m, u);
        let mut w = u;
        let mut dy = identity_mat(n);
        // Y = Y_0 ∘ … ∘ Y_{last}: the last stored stage acts on u first.
        for s in self.stages.iter().rev() {
            let (next, j) = s.jacobian_stored(&w);
            dy = linalg::mul(n, &j, &dy);
            w = next;
        }
        let jacobian = linalg::inverse(n, &dy)?;
        Some(Solved {
            w,
            x: u,
            jacobian,
            residual: 0.0,
            iterations: 0,
        })
    }

    /// `X⁻¹(u)` by damped Newton on the whole map started at `guess` (which should be close, e.g.
    /// interpolated from nearby solved points), returning `X` and `DX` at the solution as well.
    /// `None` when Newton does not reach [`INVERSE_TOLERANCE`] within a few iterations; callers
    /// then fall back to [`LocalMap::inverse`], which always converges on a valid map.
    pub fn inverse_near(&self, u: &Bary, guess: &Bary) -> Option<Solved> {
        let m = self.m;
        let n = m - 1;
        let u = project(m, u);
        let mut support = [0usize; MAX_VARS];
        let mut k1 = 0;
        for i in 0..m {
            if u[i] > 0.0 {
                support[k1] = i;
                k1 += 1;
            }
        }
        // Unknowns off the support of u stay exactly zero (faces map to themselves).
        let mut start = project(m, guess);
        for i in 0..m {
            if u[i] <= 0.0 {
                start[i] = 0.0;
            }
        }
        let start = project(m, &start);
        if k1 == 2 {
            if let Some(solved) = self.inverse_on_edge(&u, support[0], support[1], &start) {
                return Some(solved);
            }
        }
        let mut iterations = 0;
        if k1 <= 1 {
            let (x, j) = self.jacobian(&u);
            return Some(Solved {
                w: u,
                x,
                jacobian: j?,
                residual: residual(m, &x, &u),
                iterations,
            });
        }
        let settings = NewtonSettings {
            max_iter: NEAR_MAX_ITERATIONS,
            tol: INVERSE_TOLERANCE,
            target: NEWTON_TARGET,
            polish: false,
        };
        // A singular parametric stage anywhere on the path makes the result unusable: flag it.
        let singular = std::cell::Cell::new(false);
        let jac = |x: &Bary| {
            let (val, j) = self.jacobian(x);
            let j = j.unwrap_or_else(|| {
                singular.set(true);
                identity_mat(n)
            });
            (val, embed(m, &j))
        };
        let (w, r, x, h) =
            newton_solve(m, &support[..k1], &u, start, settings, &mut iterations, jac)?;
        let jacobian = reduce(m, &h);
        let finite = jacobian.iter().flatten().all(|v| v.is_finite());
        (finite && !singular.get()).then_some(Solved {
            w,
            x,
            jacobian,
            residual: r,
            iterations,
        })
    }
}

/// Evaluations of the map [`LocalMap::inverse_on_edge`] spends at most: the secant steps from the
/// start take six to ten, and bisection halves the bracket at least every third one, so this
/// only stops an invalid map (not monotonic along the edge).
const EDGE_MAX_EVALS: u32 = 64;

impl LocalMap {
    /// `X⁻¹(u)` for `u` on the edge from vertex `a` to `b` (its only nonzero coordinates), where
    /// `X` is a one-dimensional map: faces map to themselves and vertices stay fixed, so along
    /// the edge `t ↦ X((1 − t) e_a + t e_b)_b` rises from 0 to 1. A bracketed secant iteration on
    /// `t` (bisection when a secant step leaves the bracket or the bracket shrinks too slowly)
    /// needs one evaluation of `X` per step, where Newton needs a value with Jacobian (about four
    /// evaluations' cost) and starts from the linear isocomplex's crossing, often a tenth of the
    /// edge off: corners of the patches cost ~10 Jacobians that way. Stops at the same point as
    /// Newton ([`NEWTON_TARGET`]) and meets the same acceptance test; `X` and `DX` at the solution
    /// are returned as by [`LocalMap::inverse_near`]. `None` when the map does not behave as a
    /// valid map along the edge (the caller's Newton and the robust inverse then decide).
    fn inverse_on_edge(&self, u: &Bary, a: usize, b: usize, start: &Bary) -> Option<Solved> {
        let m = self.m;
        let at = |t: f64| {
            let mut w = [0.0; MAX_VARS];
            w[a] = 1.0 - t;
            w[b] = t;
            w
        };
        let target = u[b];
        // f(t) = X(at(t))_b − u_b: −u_b at t = 0 and 1 − u_b at t = 1 (the vertices are fixed).
        let (mut lo, mut hi) = (0.0f64, 1.0f64);
        let (mut flo, mut fhi) = (-target, 1.0 - target);
        let sum = start[a] + start[b];
        let mut t = if sum > 0.0 { start[b] / sum } else { target };
        if !(t > 0.0 && t < 1.0) {
            t = target;
        }
        // The previous iterate for the secant (the bracket's end on the other side at first).
        let mut prev: Option<(f64, f64)> = None;
        let mut width = hi - lo;
        let mut evals = 0;
        loop {
            if evals == EDGE_MAX_EVALS {
                return None;
            }
            evals += 1;
            let w = at(t);
            let x = self.eval(&w);
            let f = x[b] - target;
            if !f.is_finite() {
                return None;
            }
            if residual(m, &x, u) <= NEWTON_TARGET || f == 0.0 {
                return self.finish_edge(u, w, evals);
            }
            if f < 0.0 {
                lo = t;
                flo = f;
            } else {
                hi = t;
                fhi = f;
            }
            // At the rounding level the bracket cannot shrink further: what is left is the
            // point's rounding floor, for the acceptance test to judge.
            if hi - lo <= 4.0 * f64::EPSILON * hi {
                return self.finish_edge(u, w, evals);
            }
            let (tp, fp) = prev.unwrap_or(if f < 0.0 { (hi, fhi) } else { (lo, flo) });
            let secant = t - f * (t - tp) / (f - fp);
            prev = Some((t, f));
            // Every third evaluation the bracket must have halved, or it is bisected: the secant
            // alone can creep from one side.
            let slow = evals % 3 == 0 && hi - lo > 0.5 * width;
            if evals % 3 == 0 {
                width = hi - lo;
            }
            t = if !slow && secant > lo && secant < hi {
                secant
            } else {
                0.5 * (lo + hi)
            };
        }
    }

    /// [`LocalMap::inverse_on_edge`]'s result at its last iterate `w`: `X` and `DX` there and the
    /// usual acceptance test.
    fn finish_edge(&self, u: &Bary, w: Bary, evals: u32) -> Option<Solved> {
        let (x, j) = self.jacobian(&w);
        let jacobian = j?;
        let r = residual(self.m, &x, u);
        let finite = jacobian.iter().flatten().all(|v| v.is_finite());
        (finite && self.accepts(&w, r)).then_some(Solved {
            w,
            x,
            jacobian,
            residual: r,
            iterations: evals,
        })
    }
}

/// Identity in the upper-left `n × n` block.
pub fn identity_mat(n: usize) -> Mat {
    let mut a = [[0.0; MAX_VARS]; MAX_VARS];
    for (i, row) in a.iter_mut().enumerate().take(n) {
        row[i] = 1.0;
    }
    a
}

/// The quotient rule that ends a rational stage's value and homogeneous Jacobian: `u = P / Q` and
/// `∂u/∂w_j = d (∂P/∂w_j − u ∂Q/∂w_j) / Q` from the degree-`d − 1` sums. One function for the
/// table-driven and the compile-time kernels, so both end with the same operations in the same
/// order (their bit equality is tested).
#[inline(always)]
fn rational_quotient<const M: usize>(
    p: &Bary,
    q: f64,
    dp: &Mat,
    dq: &Bary,
    df: f64,
) -> (Bary, Mat) {
    let mut u = [0.0; MAX_VARS];
    for i in 0..M {
        u[i] = p[i] / q;
    }
    let mut h = [[0.0; MAX_VARS]; MAX_VARS];
    for i in 0..M {
        for j in 0..M {
            h[i][j] = df * (dp[i][j] - u[i] * dq[j]) / q;
        }
    }
    (u, h)
}

/// `h *= d` on the leading `M × M` block: the factor of a Bézier stage's homogeneous Jacobian.
#[inline(always)]
fn scale_jacobian<const M: usize>(h: &mut Mat, df: f64) {
    for row in h.iter_mut().take(M) {
        for v in row.iter_mut().take(M) {
            *v *= df;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const _: () = assert!((MAX_DEGREE as usize) + MAX_VARS - 2 < 24);

    /// SplitMix64: a fixed, seeded stream of test inputs.
    struct Stream(u64);

    impl Stream {
        fn next(&mut self) -> f64 {
            self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            z ^= z >> 31;
            (z >> 11) as f64 / (1u64 << 53) as f64
        }
    }

    /// The inline `powi` gives `f64::powi`'s bits for a run-time exponent (the library routine
    /// the sparse kernels called before), over sums of barycentric coordinates near 1 (what the
    /// kernels pass) and over a wide range; the exponents of degrees up to `MAX_DEGREE` and beyond.
    #[test]
    fn inline_powi_gives_the_library_powi_bits() {
        let mut rng = Stream(19);
        for k in 0..20_000 {
            let a = if k % 2 == 0 {
                1.0 + (rng.next() - 0.5) * 1e-3
            } else {
                (rng.next() - 0.5) * 2f64.powi((rng.next() * 40.0) as i32 - 20)
            };
            for e in 0..=9u32 {
                let library = a.powi(std::hint::black_box(e as i32));
                assert_eq!(powi(a, e).to_bits(), library.to_bits(), "{a:e}^{e}");
            }
        }
    }

    /// A one-stage map's `jacobian` (its short path) against central differences of its `eval`
    /// along `e_l − e_0`: implicit Bézier and rational stages of degrees 1–3 in 2 and 3
    /// dimensions, at random points, on faces and at vertices (the polynomials extend past them).
    #[test]
    fn one_stage_map_jacobian_matches_central_differences() {
        // Step and tolerance: degree ≤ 3 numerators and weights in [½, 2] keep the third
        // derivatives O(10²), so the O(h²) truncation is ~1e-8 and rounding ~1e-11 at h = 1e-5.
        const H: f64 = 1e-5;
        const TOL: f64 = 1e-6;
        let mut rng = Stream(27);
        for kind in [StageKind::Bezier, StageKind::Rational] {
            for m in [3, 4] {
                for d in 1..=3 {
                    let map = LocalMap::from_stages(m, vec![random_stage(kind, m, d, &mut rng)]);
                    for _ in 0..20 {
                        let w = random_point(m, &mut rng);
                        let (x, j) = map.jacobian(&w);
                        let j = j.expect("an implicit stage has a Jacobian");
                        // The value comes with the Jacobian's own rounding.
                        let y = map.eval(&w);
                        assert!((0..m).all(|i| (x[i] - y[i]).abs() <= 1e-12 * (1.0 + y[i].abs())));
                        for l in 1..m {
                            let (mut wp, mut wm) = (w, w);
                            wp[l] += H;
                            wp[0] -= H;
                            wm[l] -= H;
                            wm[0] += H;
                            let (a, b) = (map.eval(&wp), map.eval(&wm));
                            for k in 1..m {
                                let fd = (a[k] - b[k]) / (2.0 * H);
                                let got = j[k - 1][l - 1];
                                assert!(
                                    (got - fd).abs() <= TOL * (1.0 + fd.abs()),
                                    "{kind:?} m={m} d={d} J[{}][{}] = {got} vs {fd}",
                                    k - 1,
                                    l - 1
                                );
                            }
                        }
                    }
                }
            }
        }
    }

    /// A non-identity stage of `kind` with `m` variables and degree `d` and random control points
    /// (and weights in [½, 2]); the net need not be valid, only the arithmetic is compared.
    fn random_stage(kind: StageKind, m: usize, d: u32, rng: &mut Stream) -> LocalStage {
        let count = multi_index::count(m, d);
        let mut st = LocalStage::identity(kind, d, m).expect("identity stage");
        st.identity = false;
        st.points = (0..count)
            .map(|_| {
                let mut b = [0.0; MAX_VARS];
                for v in b.iter_mut().take(m) {
                    *v = rng.next() * 2.0 - 0.5;
                }
                b
            })
            .collect();
        if kind == StageKind::Rational {
            st.weights = (0..count).map(|_| 0.5 + 1.5 * rng.next()).collect();
            st.finish_rational();
        }
        st
    }

    /// A point of the simplex: random, on a random face (zero coordinates), or a vertex.
    fn random_point(m: usize, rng: &mut Stream) -> Bary {
        let mut w = [0.0; MAX_VARS];
        let shape = rng.next();
        for v in w.iter_mut().take(m) {
            *v = rng.next();
            if shape < 0.3 && rng.next() < 0.5 {
                *v = 0.0;
            }
        }
        if shape > 0.9 {
            w = [0.0; MAX_VARS];
            w[(rng.next() * m as f64) as usize % m] = 1.0;
        }
        let sum: f64 = w.iter().sum();
        if sum == 0.0 {
            w[0] = 1.0;
        } else {
            for v in w.iter_mut() {
                *v /= sum;
            }
        }
        w
    }

    fn same_bits(a: &[f64], b: &[f64]) -> bool {
        a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits())
    }

    /// The compile-time tables list what [`tables`] lists: the same exponents in the same order,
    /// the same multinomials and the same ranks of `K + e_j`.
    #[test]
    fn const_tables_equal_the_runtime_tables() {
        fn check<const M: usize, const N: usize, const NL: usize>(d: u32) {
            let t = tables(M, d);
            let upper = const_terms::<M, N>(d as usize);
            let lower = const_terms::<M, NL>(d as usize - 1);
            let up = const_up::<M, N, NL>(&upper, &lower);
            assert_eq!(t.exps.len(), N, "M = {M}, d = {d}");
            assert_eq!(t.lower_exps.len(), NL, "M = {M}, d = {d}");
            for (k, (e, mult)) in upper.iter().enumerate() {
                for i in 0..MAX_VARS {
                    assert_eq!(usize::from(t.exps[k][i]), if i < M { e[i] } else { 0 });
                }
                assert_eq!(
                    mult.to_bits(),
                    t.multinom[k].to_bits(),
                    "M = {M}, d = {d}, {e:?}"
                );
            }
            for (r, (e, mult)) in lower.iter().enumerate() {
                for i in 0..M {
                    assert_eq!(usize::from(t.lower_exps[r][i]), e[i]);
                    assert_eq!(up[r][i], t.up[r][i] as usize);
                }
                assert_eq!(mult.to_bits(), t.lower_multinom[r].to_bits());
            }
        }
        check::<4, 4, 1>(1);
        check::<4, 10, 4>(2);
        check::<4, 20, 10>(3);
        check::<4, 35, 20>(4);
        check::<3, 3, 1>(1);
        check::<3, 6, 3>(2);
        check::<3, 10, 6>(3);
        check::<3, 15, 10>(4);
        check::<2, 2, 1>(1);
        check::<2, 3, 2>(2);
        check::<2, 4, 3>(3);
        check::<2, 5, 4>(4);
    }

    /// The degree-specialised 1D Bernstein sums (monotonic stages) give the general one's bits.
    #[test]
    fn fixed_degree_bernstein_1d_gives_the_general_bits() {
        let mut rng = Stream(7);
        for len in 1..=6 {
            for _ in 0..500 {
                let c: Vec<f64> = (0..len).map(|_| rng.next() * 4.0 - 1.0).collect();
                for t in [0.0, 1.0, 0.5, rng.next(), rng.next()] {
                    let (a, b) = (bernstein_1d(&c, t), bernstein_1d_any(&c, t));
                    assert_eq!(a.to_bits(), b.to_bits(), "{c:?} at {t}");
                }
            }
        }
    }

    /// The specialised kernels (`dispatch_degree!`, degrees 1–4) give the table-driven kernels'
    /// bits: values of Bézier and rational stages and their homogeneous Jacobians, at random
    /// points, points on faces and vertices.
    #[test]
    fn specialised_kernels_give_the_table_kernels_bits() {
        let mut rng = Stream(19);
        for kind in [StageKind::Bezier, StageKind::Rational] {
            for m in 2..=MAX_VARS {
                for d in 1..=4 {
                    for _ in 0..40 {
                        let st = random_stage(kind, m, d, &mut rng);
                        for _ in 0..25 {
                            let w = random_point(m, &mut rng);
                            let (value, (jv, jac)) = match kind {
                                StageKind::Bezier => (
                                    dispatch!(st, eval_bezier, &w),
                                    dispatch!(st, val_jac_bezier, &w),
                                ),
                                _ => (
                                    dispatch!(st, eval_rational, &w),
                                    dispatch!(st, val_jac_rational, &w),
                                ),
                            };
                            let what = format!("{kind:?} m = {m} d = {d} at {w:?}");
                            assert!(same_bits(&st.eval_stored(&w), &value), "{what}");
                            let (jv2, jac2) = st.homogeneous_jacobian_stored(&w);
                            assert!(same_bits(&jv2, &jv), "{what}");
                            for (a, b) in jac2.iter().zip(&jac) {
                                assert!(same_bits(a, b), "{what}");
                            }
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn small_rank_is_the_canonical_rank() {
        for m in 1..=MAX_VARS {
            for d in 0..MAX_DEGREE {
                let all = multi_index::all(m, d);
                for (r, index) in all.chunks(m).enumerate() {
                    assert_eq!(small_rank(index), r, "{index:?}");
                    assert_eq!(small_rank(index), multi_index::rank(index));
                }
            }
        }
    }

    /// A monotonic stage of degree `d` on `m` variables with the given per-vertex coefficients
    /// (`d + 1` each).
    fn monotonic_stage(m: usize, d: u32, coefficients: &[f64]) -> LocalStage {
        let mut st = LocalStage::identity(StageKind::Monotonic, d, m).expect("identity stage");
        st.identity = false;
        st.mono = coefficients.to_vec();
        st.mono_scaled.clear();
        st.mono_deriv.clear();
        st.finish_monotonic();
        st
    }

    /// A projective monotonic stage's inverse (`g_i(t) = a_i t`), in closed form as Newton's
    /// start: `S` of it is `u` to rounding (checked against the forward evaluation, an
    /// independent computation), on the simplex and its faces, for weights over three orders of
    /// magnitude; the inversion from it confirms it within two iterations (Newton's check and its
    /// polishing step) and agrees with the preimage Newton finds from `u` (the start used for
    /// every other stage). Not projective (`a_0 ≠ 0`, degree 2): no closed form.
    #[test]
    fn projective_inverse_is_the_preimage() {
        let mut rng = Stream(0x0b5e_55ed);
        for m in 2..=4usize {
            for _ in 0..40 {
                let a: Vec<f64> = (0..m)
                    .flat_map(|_| [0.0, 10f64.powf(3.0 * rng.next() - 1.5)])
                    .collect();
                let st = monotonic_stage(m, 1, &a);
                for _ in 0..20 {
                    let u = random_point(m, &mut rng);
                    let sup: Vec<usize> = (0..m).filter(|&i| u[i] > 0.0).collect();
                    let w = st.projective_inverse(&sup, &u).expect("projective");
                    let back = st.eval_stored(&w);
                    for i in 0..m {
                        assert!((back[i] - u[i]).abs() <= 8.0 * f64::EPSILON, "{a:?} {u:?}");
                        assert_eq!(w[i] == 0.0, u[i] == 0.0, "the face is kept");
                    }
                    let inv = st.invert_stored_with(&u, true);
                    assert!(inv.converged && inv.iterations <= 2, "{inv:?}");
                    if sup.len() > 1 {
                        let mut iterations = 0;
                        let (from_u, _) = st
                            .newton(
                                &sup,
                                &u,
                                u,
                                NEWTON_MAX_ITERATIONS,
                                INVERSE_TOLERANCE,
                                true,
                                &mut iterations,
                            )
                            .expect("Newton from u converges");
                        for i in 0..m {
                            assert!((from_u[i] - inv.w[i]).abs() <= 1e-14, "{from_u:?} {inv:?}");
                        }
                    }
                }
                let mut shifted = a.clone();
                shifted[0] = 0.1;
                let all: Vec<usize> = (0..m).collect();
                let u = random_point(m, &mut rng);
                assert!(monotonic_stage(m, 1, &shifted)
                    .projective_inverse(&all, &u)
                    .is_none());
                let degree2: Vec<f64> = (0..m).flat_map(|_| [0.0, 0.4, 1.0]).collect();
                assert!(monotonic_stage(m, 2, &degree2)
                    .projective_inverse(&all, &u)
                    .is_none());
            }
        }
    }

    /// A projective monotonic stage (`g_i(t) = a_i t`) followed by a Bézier or rational stage is
    /// fused into one rational stage that equals the composition (compared with the unfused
    /// map's evaluation and chain-rule Jacobian at random points of the simplex and its faces, to
    /// rounding); other pairs are left alone.
    #[test]
    fn fused_projective_stage_equals_the_composition() {
        let mut rng = Stream(0x5eed_f00d);
        for m in 2..=4usize {
            for d in 1..=4u32 {
                for kind in [StageKind::Bezier, StageKind::Rational] {
                    let a: Vec<f64> = (0..m)
                        .flat_map(|_| [0.0, 0.25 + 1.75 * rng.next()])
                        .collect();
                    let mono = monotonic_stage(m, 1, &a);
                    let net = random_stage(kind, m, d, &mut rng);
                    let map = LocalMap::from_stages(m, vec![mono.clone(), net.clone()]);
                    let fused = map.clone().fused();
                    assert_eq!(fused.stages().len(), 1, "{kind:?} m = {m} d = {d}");
                    assert_eq!(fused.stages()[0].kind(), StageKind::Rational);
                    assert_eq!(fused.stages()[0].direction(), Direction::Implicit);
                    for _ in 0..50 {
                        let w = random_point(m, &mut rng);
                        let what = format!("{kind:?} m = {m} d = {d} at {w:?}");
                        let (x, j) = map.jacobian(&w);
                        let (xf, jf) = fused.jacobian(&w);
                        let (j, jf) = (j.unwrap(), jf.unwrap());
                        let scale = 1.0 + j.iter().flatten().map(|v| v.abs()).fold(0.0, f64::max);
                        for i in 0..m {
                            assert!((x[i] - xf[i]).abs() <= 1e-13 * scale, "{what}");
                            assert!((map.eval(&w)[i] - fused.eval(&w)[i]).abs() <= 1e-13 * scale);
                        }
                        for (r, rf) in j.iter().zip(&jf) {
                            for (v, vf) in r.iter().zip(rf) {
                                assert!((v - vf).abs() <= 1e-12 * scale, "{what}: {j:?} {jf:?}");
                            }
                        }
                    }
                    // Not projective (g_i(0) ≠ 0, or degree 2), or in the other order: unchanged.
                    let mut shifted = a.clone();
                    shifted[0] = 0.1;
                    let degree2: Vec<f64> = (0..m).flat_map(|_| [0.0, 0.4, 1.0]).collect();
                    for stages in [
                        vec![monotonic_stage(m, 1, &shifted), net.clone()],
                        vec![monotonic_stage(m, 2, &degree2), net.clone()],
                        vec![net.clone(), mono.clone()],
                    ] {
                        let kept = LocalMap::from_stages(m, stages).fused();
                        assert_eq!(kept.stages().len(), 2, "{kind:?} m = {m} d = {d}");
                    }
                    // A monotonic stage built without its tables (`from_indexed_fused`) and not
                    // fused gets them: the same bits as the one built with them.
                    let finished = monotonic_stage(m, 2, &degree2);
                    let mut bare = finished.clone();
                    bare.mono_scaled.clear();
                    bare.mono_deriv.clear();
                    let a = LocalMap::from_stages(m, vec![finished, net.clone()]).fused();
                    let b = LocalMap::from_stages(m, vec![bare, net.clone()]).fused();
                    for _ in 0..10 {
                        let w = random_point(m, &mut rng);
                        assert_eq!(a.eval(&w), b.eval(&w), "{kind:?} m = {m} d = {d}");
                        assert_eq!(a.jacobian(&w), b.jacobian(&w), "{kind:?} m = {m} d = {d}");
                    }
                }
            }
        }
    }

    /// A Bézier net that is the identity's but for a few points evaluates through its deviations
    /// ([`LocalStage::sparsify`], as [`LocalMap::fused`] does) to the dense kernels' value and
    /// homogeneous Jacobian (to rounding, also off the plane `Σ w = 1`, where both are the
    /// homogeneous form), keeps exact zeros exact, and is left dense past a quarter of the net.
    #[test]
    fn sparse_bezier_stage_equals_the_dense_net() {
        let mut rng = Stream(0x5ba_45e);
        for m in 2..=4usize {
            for d in 1..=MAX_DEGREE.min(6) {
                let count = multi_index::count(m, d);
                for deviating in [1usize, count / 4, count / 4 + 1] {
                    let mut dense = LocalStage::identity(StageKind::Bezier, d, m).unwrap();
                    dense.identity = false;
                    // Deviating points on faces of two vertices or more, each moved within its
                    // face's support (the format's records: a point of a face lies on it).
                    let candidates: Vec<usize> = (0..count)
                        .filter(|&r| {
                            dense.tables.exps[r][..m].iter().filter(|&&e| e > 0).count() >= 2
                        })
                        .collect();
                    let deviating = deviating.min(candidates.len());
                    for &r in candidates.iter().rev().take(deviating) {
                        let e = dense.tables.exps[r];
                        let support: Vec<usize> = (0..m).filter(|&i| e[i] > 0).collect();
                        let moves: Vec<f64> = support.iter().map(|_| rng.next() - 0.5).collect();
                        let mean = moves.iter().sum::<f64>() / moves.len() as f64;
                        for (&i, dx) in support.iter().zip(&moves) {
                            dense.points[r][i] += 0.2 * (dx - mean);
                        }
                    }
                    let mut sparse = dense.clone();
                    sparse.sparsify();
                    let what = format!("m = {m} d = {d}, {deviating} of {count} deviating");
                    assert_eq!(sparse.sparse.is_some(), 4 * deviating <= count, "{what}");
                    if sparse.sparse.is_none() {
                        continue;
                    }
                    for trial in 0..60 {
                        let mut w = random_point(m, &mut rng);
                        if trial % 4 == 3 {
                            // Off the plane: the homogeneous forms agree there too.
                            for v in w.iter_mut() {
                                *v *= 1.3;
                            }
                        }
                        let at = format!("{what} at {w:?}");
                        let (x, h) = dense.homogeneous_jacobian_stored(&w);
                        let (xs, hs) = sparse.homogeneous_jacobian_stored(&w);
                        let xe = sparse.eval_stored(&w);
                        let scale = 1.0 + h.iter().flatten().map(|v| v.abs()).fold(0.0, f64::max);
                        for i in 0..m {
                            assert!((x[i] - xs[i]).abs() <= 1e-13 * scale, "{at}: {x:?} {xs:?}");
                            assert!((xs[i] - xe[i]).abs() <= 1e-13 * scale, "{at}");
                            if w[i] == 0.0 {
                                assert_eq!((xs[i], xe[i]), (0.0, 0.0), "{at}: zero kept");
                            }
                            for j in 0..m {
                                assert!(
                                    (h[i][j] - hs[i][j]).abs() <= 1e-12 * scale,
                                    "{at}: {h:?} {hs:?}"
                                );
                            }
                        }
                    }
                }
            }
        }
    }
}

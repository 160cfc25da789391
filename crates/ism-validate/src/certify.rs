//! Certified sign of `det DX` on a closed simplex (spec/validation.md §4.3).
//!
//! For one stage restricted to one top simplex (a [`DenseNet`]), [`DetKernel::det_coefficients`]
//! computes the Bernstein coefficients of the Jacobian polynomial together with a rigorous bound on
//! their rounding error, and [`DetKernel::certify`] decides its sign by adaptive subdivision:
//!
//! - polynomial stage of degree `d`: `det ∂(X₁..Xₙ)/∂(w₁..wₙ)` (reduced barycentric coordinates,
//!   `w₀ = 1 − Σ`), degree `n(d − 1)`; the identity has `det = 1`;
//! - rational stage: `N = det[V, ∂₁V, …, ∂ₙV]` with `V = (Q, P₁, …, Pₙ)`, degree `(n + 1)d − n`;
//!   `det DX = N / Q^{n+1}` with `Q > 0`, so `N` has the sign of `det DX` (spec/mathematics.md §4).
//!
//! # Why this is not in `ism-geom`
//! The kernel carries, for every coefficient, the same computation on absolute values; with the
//! number of roundings on the longest path `k` this bounds the error by `γₖ · |·|` (Higham,
//! *Accuracy and Stability of Numerical Algorithms*, §3.1). Subdivision propagates a running error
//! bound. A general Bernstein library has no reason to do either, and the hot loop must not allocate
//! per element, so the certificate arithmetic lives here; tests check it against `ism-geom`'s
//! evaluation of the same maps.

use ism_format::multi_index;

/// Unit roundoff of f64 (round to nearest).
pub(crate) const UNIT_ROUNDOFF: f64 = f64::EPSILON / 2.0;

/// Absolute slack added to every error bound for gradual underflow: each rounding may also lose up
/// to the smallest subnormal, and no computation here has more than 10⁴ roundings on a path.
const UNDERFLOW_SLACK: f64 = 1e4 * f64::MIN_POSITIVE;

/// Deepest floating-point bisection: corners stay exact dyadic doubles (each bisection adds at most
/// one bit to a corner coordinate), so a candidate witness is the exact corner, and the exact path
/// takes over long before rounding in the coefficients could matter.
pub const MAX_FLOAT_DEPTH: u32 = 50;

/// Deepest bisection of the double-double tier: its pieces near a minimum 10⁻¹² of the scale are
/// about 10⁻⁶ of the simplex (60 bisections in 3D). Beyond depth 50 a corner may be rounded; a
/// certificate of positivity does not depend on the corners, and a witness is proven exactly at
/// the point printed, so a rounded corner costs at most a missed witness, never a false one.
pub const MAX_TWOFOLD_DEPTH: u32 = 120;

/// How much work one element may take (spec/validation.md §4.4). Pieces, not depth: a piece count
/// bounds time and memory whatever the shape of the subdivision tree.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Budget {
    /// Pieces of the floating-point certificate.
    pub pieces: usize,
    /// Pieces of the exact path (each may also run the floating-point filter on up to 64
    /// sub-pieces).
    pub exact_pieces: usize,
}

/// Default floating-point pieces per element: a few milliseconds at the highest degrees.
pub const DEFAULT_MAX_PIECES: usize = 1 << 16;

impl Budget {
    /// The budget for `pieces` floating-point pieces, and a sixteenth as many exact ones (an exact
    /// bisection costs tens of floating-point ones).
    pub fn new(pieces: usize) -> Budget {
        Budget {
            pieces,
            exact_pieces: (pieces / 16).max(1),
        }
    }
}

impl Default for Budget {
    fn default() -> Budget {
        Budget::new(DEFAULT_MAX_PIECES)
    }
}

/// One stage on one top simplex: the dense control net in local vertex order.
#[derive(Clone, Debug, PartialEq)]
pub struct DenseNet {
    /// Space dimension `n` (1 to 3); every point has `n + 1` coordinates.
    pub n: usize,
    /// Degree `d`.
    pub degree: u32,
    /// Control points in the canonical order of `multi_index::all(n + 1, d)`, barycentric.
    pub points: Vec<[f64; 4]>,
    /// Weights in the same order (rational stages), empty for polynomial ones.
    pub weights: Vec<f64>,
}

impl DenseNet {
    /// The identity net `b_I = I/d` (all points fixed), polynomial.
    pub fn identity(n: usize, degree: u32) -> DenseNet {
        let m = n + 1;
        let points = multi_index::all(m, degree)
            .chunks(m)
            .map(|i| {
                let mut p = [0.0; 4];
                for (c, &e) in p.iter_mut().zip(i) {
                    *c = f64::from(e) / f64::from(degree);
                }
                p
            })
            .collect();
        DenseNet {
            n,
            degree,
            points,
            weights: Vec::new(),
        }
    }

    /// Whether the net carries weights.
    pub fn is_rational(&self) -> bool {
        !self.weights.is_empty()
    }
}

/// Coefficients with their rounding-error bounds: `|computed − exact| ≤ error` for each.
#[derive(Clone, Debug, PartialEq)]
pub struct BoundedCoefficients {
    /// Bernstein coefficients in canonical order.
    pub values: Vec<f64>,
    /// Error bound of each coefficient.
    pub errors: Vec<f64>,
}

/// Outcome of the sign decision for one element.
#[derive(Clone, Debug, PartialEq)]
pub enum Decision {
    /// Every coefficient of every piece exceeds its error bound.
    Positive {
        /// Greatest subdivision depth used (0: the coefficients were positive at once).
        depth: u32,
        /// Pieces examined.
        pieces: usize,
        /// A certified lower bound of the polynomial on the simplex (min of value − error).
        lower_bound: f64,
    },
    /// The polynomial is `≤ 0` as computed at this corner of a piece: a candidate witness, to be
    /// proven exactly ([`crate::exact::witness_at`]).
    NonPositive {
        /// Barycentric point of the simplex.
        point: Vec<f64>,
        /// The polynomial's value there (an exact vertex coefficient of a piece).
        value: f64,
        /// Its rounding-error bound: `value + error ≤ 0` makes the sign certain.
        error: f64,
    },
    /// Undecided at the depth or piece limit, or a number was not finite.
    Undetermined {
        /// Depth reached.
        depth: u32,
        /// Pieces examined.
        pieces: usize,
        /// Certified lower bound over the undecided pieces (negative or zero).
        lower_bound: f64,
        /// Smallest value found at a piece vertex (an upper bound of the minimum).
        upper_bound: f64,
    },
}

impl Decision {
    /// Whether the sign is certified positive.
    pub fn is_positive(&self) -> bool {
        matches!(self, Decision::Positive { .. })
    }
}

/// The decision for one element: floating point, then exact.
#[derive(Clone, Debug, PartialEq)]
pub enum Certificate {
    /// Positive on the closed simplex.
    Positive {
        /// Whether the exact path decided it (otherwise a floating-point certificate did, from
        /// double or double-double coefficients).
        exact: bool,
        /// Greatest subdivision depth used.
        depth: u32,
        /// Pieces examined (by the path that decided).
        pieces: usize,
        /// Certified lower bound of the floating-point certificate polynomial (of the net with
        /// normalised weights); `None` for the exact path, whose coefficients carry an arbitrary
        /// positive factor.
        lower_bound: Option<f64>,
    },
    /// A point where the polynomial is `≤ 0`, proven by exact evaluation.
    NonPositive(crate::exact::ExactWitness),
    /// Neither path decided within the budget.
    Undetermined {
        /// Depth reached.
        depth: u32,
        /// Pieces examined by both paths.
        pieces: usize,
        /// Certified lower bound over the floating-point pieces left undecided (−∞ when the
        /// floating-point path could not run).
        lower_bound: f64,
        /// Smallest value the floating-point path found at a piece corner.
        upper_bound: f64,
    },
}

impl Certificate {
    /// Whether the sign is certified positive.
    pub fn is_positive(&self) -> bool {
        matches!(self, Certificate::Positive { .. })
    }
}

/// The coefficient lines along one edge `(a, b)`, each listed by increasing exponent of `b`.
type EdgeLines = ((usize, usize), Vec<Vec<u16>>);

/// Table of the products `x_i · y_j → z_k` of a homogeneous convolution, as one row of output
/// positions per `i`: `zrows[i · len_b + j] = k`.
#[derive(Clone, Debug)]
pub(crate) struct Convolution {
    pub(crate) zrows: Vec<u16>,
    pub(crate) len_b: usize,
    pub(crate) out_len: usize,
    /// Most terms summed into one output coefficient.
    pub(crate) max_terms: usize,
}

impl Convolution {
    fn new(m: usize, a: u32, b: u32) -> Convolution {
        let ia = multi_index::all(m, a);
        let ib = multi_index::all(m, b);
        let len_b = ib.len() / m;
        let out_len = multi_index::count(m, a + b);
        let mut zrows = Vec::with_capacity(ia.len() / m * len_b);
        let mut terms = vec![0usize; out_len];
        let mut sum = vec![0u32; m];
        for x in ia.chunks(m) {
            for y in ib.chunks(m) {
                for c in 0..m {
                    sum[c] = x[c] + y[c];
                }
                let k = multi_index::rank(&sum);
                terms[k] += 1;
                zrows.push(k as u16);
            }
        }
        Convolution {
            zrows,
            len_b,
            out_len,
            max_terms: terms.into_iter().max().unwrap_or(0),
        }
    }
}

/// Permanent of the upper-left `s × s` block (`s ≤ 4`), by expansion along the first row.
pub(crate) fn permanent(a: &[[f64; 4]; 4], s: usize) -> f64 {
    fn rec(a: &[[f64; 4]; 4], s: usize, row: usize, used: u32) -> f64 {
        if row == s {
            return 1.0;
        }
        (0..s)
            .filter(|c| used & (1 << c) == 0)
            .map(|c| a[row][c] * rec(a, s, row + 1, used | (1 << c)))
            .sum()
    }
    rec(a, s, 0, 0)
}

/// Multinomial coefficients `d!/(I₀!…Iₘ₋₁!)` in canonical order (exact in f64 for `d ≤ 48`, as
/// `48! / (12!)⁴ < 2⁵³`).
fn multinomials(m: usize, d: u32) -> Vec<f64> {
    let fact = |k: u32| (1..=k).fold(1.0f64, |a, x| a * f64::from(x));
    multi_index::all(m, d)
        .chunks(m)
        .map(|i| fact(d) / i.iter().map(|&e| fact(e)).product::<f64>())
        .collect()
}

/// Everything the certificate needs for one `(n, d, rational)` triple, built once per stage and
/// shared across threads.
#[derive(Clone, Debug)]
pub struct DetKernel {
    pub(crate) n: usize,
    pub(crate) degree: u32,
    pub(crate) rational: bool,
    /// Size of the determinant: `n` (polynomial) or `n + 1` (rational).
    pub(crate) size: usize,
    /// Canonical index positions: for each multi-index of degree `d − 1`, the ranks of `I + e_k` in
    /// degree `d`, `k = 0..m`.
    pub(crate) shift: Vec<[u16; 4]>,
    /// Multinomials of degree `d − 1` and `d`.
    pub(crate) mult_entry: Vec<f64>,
    pub(crate) mult_first: Vec<f64>,
    /// Laplace levels: `conv[j]` multiplies column `j` by a minor of columns `j + 1..`.
    pub(crate) conv: Vec<Convolution>,
    /// Degree of the determinant polynomial.
    pub(crate) det_degree: u32,
    pub(crate) mult_det: Vec<f64>,
    /// `γ_k` for the longest rounding path, with a safety factor.
    gamma: f64,
    /// Rank of `D·e_i` in the determinant's canonical order.
    pub(crate) vertex_rank: [usize; 4],
    /// For each edge `(a, b)`, `a < b`: the lines of coefficients along the edge, each listed by
    /// increasing exponent of `b`.
    lines: Vec<EdgeLines>,
    /// Integer tables of the exact path, built on first use.
    exact: std::sync::OnceLock<crate::exact::ExactTables>,
    /// Tables of the decision around the estimated minimum, built on first use.
    star: std::sync::OnceLock<StarTables>,
}

impl DetKernel {
    /// Builds the tables for stages of dimension `n` (1 to 3), degree `d` (1 to 16).
    ///
    /// # Panics
    /// When `n` or `d` is out of that range (callers have validated the structure).
    pub fn new(n: usize, degree: u32, rational: bool) -> DetKernel {
        assert!((1..=3).contains(&n) && (1..=ism_format::structure::MAX_DEGREE).contains(&degree));
        let m = n + 1;
        let d = degree;
        let size = if rational { n + 1 } else { n };
        let mut column_degrees = vec![d - 1; size];
        if rational {
            column_degrees[0] = d;
        }
        let shift = multi_index::all(m, d - 1)
            .chunks(m)
            .map(|i| {
                let mut out = [0u16; 4];
                let mut j = i.to_vec();
                for (k, o) in out.iter_mut().enumerate().take(m) {
                    j[k] += 1;
                    *o = multi_index::rank(&j) as u16;
                    j[k] -= 1;
                }
                out
            })
            .collect();
        // Minors of columns j.. have degree Σ column_degrees[j..].
        let mut conv = Vec::new();
        let mut minor_degree = column_degrees[size - 1];
        for j in (0..size - 1).rev() {
            conv.push(Convolution::new(m, column_degrees[j], minor_degree));
            minor_degree += column_degrees[j];
        }
        conv.reverse();
        let det_degree = minor_degree;
        // Roundings on the longest path: entry (difference, ×d, ×multinomial, and ×weight for
        // rational nets) = 4; each Laplace level: one product plus its summation into a coefficient
        // over at most rows × max_terms terms; the final division by the multinomial: 1.
        let mut k = 4usize;
        for (level, c) in conv.iter().enumerate() {
            let rows = size - level;
            k += 1 + rows * c.max_terms;
        }
        k += 1;
        let kf = k as f64 * UNIT_ROUNDOFF;
        // The bound itself is computed in floating point with a handful of roundings; a factor 2
        // covers them with a wide margin.
        let gamma = 2.0 * kf / (1.0 - kf);
        let mut vertex_rank = [0usize; 4];
        for (i, v) in vertex_rank.iter_mut().enumerate().take(m) {
            let mut e = vec![0u32; m];
            e[i] = det_degree;
            *v = multi_index::rank(&e);
        }
        let all = multi_index::all(m, det_degree);
        let mut lines = Vec::new();
        for a in 0..m {
            for b in (a + 1)..m {
                // Group indices by their entries off {a, b}; order each group by I_b.
                let mut groups: std::collections::BTreeMap<Vec<u32>, Vec<(u32, u16)>> =
                    Default::default();
                for (r, idx) in all.chunks(m).enumerate() {
                    let key: Vec<u32> = (0..m)
                        .map(|c| if c == a || c == b { u32::MAX } else { idx[c] })
                        .collect();
                    groups.entry(key).or_default().push((idx[b], r as u16));
                }
                let edge_lines = groups
                    .into_values()
                    .map(|mut g| {
                        g.sort_unstable();
                        g.into_iter().map(|(_, r)| r).collect()
                    })
                    .collect();
                lines.push(((a, b), edge_lines));
            }
        }
        DetKernel {
            n,
            degree: d,
            rational,
            size,
            shift,
            mult_entry: multinomials(m, d - 1),
            mult_first: multinomials(m, d),
            conv,
            det_degree,
            mult_det: multinomials(m, det_degree),
            gamma,
            vertex_rank,
            lines,
            exact: std::sync::OnceLock::new(),
            star: std::sync::OnceLock::new(),
        }
    }

    /// The tables of the decision around the minimum (built once per kernel).
    fn star_tables(&self) -> &StarTables {
        self.star
            .get_or_init(|| StarTables::new(self.n + 1, self.det_degree))
    }

    /// The integer tables of the exact path (built once per kernel).
    pub(crate) fn exact_tables(&self) -> &crate::exact::ExactTables {
        self.exact
            .get_or_init(|| crate::exact::ExactTables::new(self))
    }

    /// The lines of coefficients along edge `(a, b)`, `a < b`.
    pub(crate) fn edge_lines(&self, a: usize, b: usize) -> &[Vec<u16>] {
        &self
            .lines
            .iter()
            .find(|(e, _)| *e == (a, b))
            .expect("every edge has lines")
            .1
    }

    /// Degree of the determinant polynomial: `n(d − 1)` or `(n + 1)d − n`.
    pub fn det_degree(&self) -> u32 {
        self.det_degree
    }

    /// The relative error factor `γ` applied to the absolute-value companion.
    pub fn gamma(&self) -> f64 {
        self.gamma
    }

    /// Bernstein coefficients of the Jacobian polynomial of `net` with rigorous error bounds.
    ///
    /// The error bound is uniform: `γₖ · E` with `E` the permanent of the matrix of the entries'
    /// largest absolute Bernstein coefficients. In Bernstein form the product formula is a convex
    /// combination (`Σ_{I+J=K} C(a;I)C(b;J) = C(a+b;K)`), so the absolute-value companion of every
    /// coefficient — the sum of the absolute values of all terms, which bounds the rounding error
    /// through `γₖ` — is at most `E`.
    ///
    /// # Panics
    /// When the net does not match the kernel's dimension, degree and kind.
    pub fn det_coefficients(&self, net: &DenseNet) -> BoundedCoefficients {
        let m = self.n + 1;
        assert_eq!(net.n, self.n);
        assert_eq!(net.degree, self.degree);
        assert_eq!(net.points.len(), multi_index::count(m, self.degree));
        assert_eq!(net.is_rational(), self.rational);
        let d = f64::from(self.degree);
        let s = self.size;
        // Row r of a polynomial net is coordinate r + 1; of a rational net, component r of
        // V = q·(1, b₁, …, bₙ).
        let component = |idx: usize, r: usize| -> f64 {
            if self.rational {
                let q = net.weights[idx];
                if r == 0 {
                    q
                } else {
                    q * net.points[idx][r]
                }
            } else {
                net.points[idx][r + 1]
            }
        };
        // Columns in scaled (monomial) form, cols[j][r], and the largest absolute Bernstein
        // coefficient of each entry (for the bound).
        let mut cols: Vec<Vec<Vec<f64>>> = Vec::with_capacity(s);
        let mut maxabs = [[0.0f64; 4]; 4];
        if self.rational {
            let mut col = Vec::with_capacity(s);
            for (r, mx) in maxabs.iter_mut().enumerate().take(s) {
                let v: Vec<f64> = self
                    .mult_first
                    .iter()
                    .enumerate()
                    .map(|(i, mlt)| {
                        let x = component(i, r);
                        mx[0] = mx[0].max(x.abs());
                        x * mlt
                    })
                    .collect();
                col.push(v);
            }
            cols.push(col);
        }
        for k in 1..=self.n {
            let j = cols.len();
            let mut col = Vec::with_capacity(s);
            for (r, mx) in maxabs.iter_mut().enumerate().take(s) {
                let v: Vec<f64> = self
                    .shift
                    .iter()
                    .zip(&self.mult_entry)
                    .map(|(sh, mlt)| {
                        let xk = component(sh[k] as usize, r);
                        let x0 = component(sh[0] as usize, r);
                        let diff = xk - x0;
                        // The exact entry's Bernstein coefficient is d·(x_k − x₀). Polynomial
                        // nets: x_k, x₀ are the stored doubles, so fl(x_k − x₀) is within u of
                        // the exact difference (relative; exact when it underflows) and
                        // d·|fl(x_k − x₀)|·(1 + 4u) bounds it. Rational nets: the components
                        // q·b were rounded, so the difference is only within u(|x_k| + |x₀|) of
                        // the exact one, and that sum stays in the bound.
                        let magnitude = if self.rational {
                            d * (xk.abs() + x0.abs())
                        } else {
                            d * diff.abs() * (1.0 + 4.0 * UNIT_ROUNDOFF)
                        };
                        mx[j] = mx[j].max(magnitude);
                        diff * (d * mlt)
                    })
                    .collect();
                col.push(v);
            }
            cols.push(col);
        }
        // Laplace expansion from the last column: minors[mask] over the rows in `mask`, using the
        // last popcount(mask) columns.
        let full = (1usize << s) - 1;
        let mut minors: Vec<Vec<f64>> = vec![Vec::new(); full + 1];
        for r in 0..s {
            minors[1 << r] = std::mem::take(&mut cols[s - 1][r]);
        }
        for j in (0..s - 1).rev() {
            let rows = s - j;
            let conv = &self.conv[j];
            for mask in 0..=full {
                if (mask as u32).count_ones() as usize != rows {
                    continue;
                }
                let mut out = vec![0.0; conv.out_len];
                let mut sign = 1.0;
                for r in 0..s {
                    if mask & (1 << r) == 0 {
                        continue;
                    }
                    let entry = &cols[j][r];
                    let minor = &minors[mask & !(1 << r)];
                    for (x, &ex) in entry.iter().enumerate() {
                        let ex = sign * ex;
                        let zrow = &conv.zrows[x * conv.len_b..(x + 1) * conv.len_b];
                        for (&z, &my) in zrow.iter().zip(minor) {
                            out[z as usize] += ex * my;
                        }
                    }
                    sign = -sign;
                }
                minors[mask] = out;
            }
        }
        let bound = permanent(&maxabs, s);
        let error = self.gamma * bound + UNDERFLOW_SLACK;
        let values: Vec<f64> = minors[full]
            .iter()
            .zip(&self.mult_det)
            .map(|(x, mlt)| x / mlt)
            .collect();
        let errors = vec![error; values.len()];
        BoundedCoefficients { values, errors }
    }

    /// Decides the sign of the certificate polynomial of `net` on the closed simplex: the
    /// floating-point certificate with at most `budget.pieces` pieces, then, if that did not
    /// decide, the exact path of [`crate::exact`]. Every witness is proven exactly.
    pub fn certify(&self, net: &DenseNet, budget: Budget) -> Certificate {
        let mut bounds = (f64::NEG_INFINITY, f64::INFINITY, 0u32, 0usize);
        // Where the polynomial is least (estimated once, by the first tier that needs it).
        let mut estimate = None;
        if let Some(scaled) = normalized(net) {
            // Floating point first; where its error bound is too wide (minima near the fold
            // threshold), the same polynomial in double-double, whose bound is ~10⁻¹⁷ as wide.
            let tiers = [
                (Some(self.det_coefficients(&scaled)), MAX_FLOAT_DEPTH),
                (None, MAX_TWOFOLD_DEPTH),
            ];
            for (tier, (coefficients, max_depth)) in tiers.into_iter().enumerate() {
                let coefficients = match coefficients {
                    Some(c) => c,
                    None => match self.det_coefficients_twofold(&scaled) {
                        Some(c) => c,
                        None => break,
                    },
                };
                // Impatient before the double-double tier, patient in it.
                let mut coef = coefficients.values;
                coef.extend_from_slice(&coefficients.errors);
                match self.decide_tier(
                    net,
                    &coef,
                    budget.pieces,
                    max_depth,
                    tier == 0,
                    &mut estimate,
                ) {
                    TierOutcome::Witness(w) => return Certificate::NonPositive(w),
                    TierOutcome::Decided(Decision::Positive {
                        depth,
                        pieces,
                        lower_bound,
                    }) => {
                        return Certificate::Positive {
                            exact: false,
                            depth,
                            pieces: pieces + bounds.3,
                            lower_bound: Some(lower_bound),
                        }
                    }
                    // An unproven candidate: the next tier decides.
                    TierOutcome::Decided(Decision::NonPositive { .. }) => {}
                    TierOutcome::Decided(Decision::Undetermined {
                        depth,
                        pieces,
                        lower_bound,
                        upper_bound,
                    }) => {
                        bounds = if tier == 0 {
                            (lower_bound, upper_bound, depth, pieces)
                        } else {
                            (
                                lower_bound,
                                upper_bound.min(bounds.1),
                                depth.max(bounds.2),
                                pieces + bounds.3,
                            )
                        }
                    }
                }
            }
        }
        match crate::exact::decide(self, net, budget.exact_pieces) {
            crate::exact::ExactDecision::Positive { depth, pieces } => Certificate::Positive {
                exact: true,
                depth,
                pieces,
                lower_bound: None,
            },
            crate::exact::ExactDecision::NonPositive(w) => Certificate::NonPositive(w),
            crate::exact::ExactDecision::Undetermined { depth, pieces } => {
                Certificate::Undetermined {
                    depth: depth.max(bounds.2),
                    pieces: pieces + bounds.3,
                    lower_bound: bounds.0,
                    upper_bound: bounds.1,
                }
            }
        }
    }

    /// The floating-point sign decision on one piece with corners `corners` (barycentric, at
    /// subdivision depth `depth`), using at most `budget` pieces. Sound for any input: a value or
    /// bound that is not finite leaves the piece undecided, never certified.
    pub fn decide_piece(
        &self,
        coefficients: BoundedCoefficients,
        corners: [[f64; 4]; 4],
        depth: u32,
        budget: usize,
        max_depth: u32,
    ) -> Decision {
        let mut coef = coefficients.values;
        coef.extend_from_slice(&coefficients.errors);
        self.decide_inner(&coef, corners, depth, budget, max_depth, false)
            .0
    }

    /// [`DetKernel::decide_piece`] on `coefficients` (values, then error bounds), also saying why
    /// it stopped short; `impatient` also gives up at the first coefficient whose sign its bound
    /// cannot settle (`|value| ≤ error`). Such a coefficient can still be settled by bisection, but
    /// in practice it means the minimum is within the bound of 0 — a near-threshold net that a
    /// tighter tier decides far sooner than bisection down to the error floor.
    fn decide_inner(
        &self,
        coefficients: &[f64],
        corners: [[f64; 4]; 4],
        depth: u32,
        budget: usize,
        max_depth: u32,
        impatient: bool,
    ) -> (Decision, Stop) {
        let m = self.n + 1;
        let len = coefficients.len() / 2;
        struct Piece {
            /// Values, then error bounds.
            coef: Vec<f64>,
            corners: [[f64; 4]; 4],
            depth: u32,
        }
        // Buffers of finished pieces, reused by their children and by the next elements on this
        // thread: no allocation per bisection, and none per element once warm.
        let mut pool = POOL.with(|p| std::mem::take(&mut *p.borrow_mut()));
        let mut coef = pool.pop().unwrap_or_default();
        coef.clear();
        coef.extend_from_slice(coefficients);
        let mut stack = vec![Piece {
            coef,
            corners,
            depth,
        }];
        let mut pieces = 0usize;
        let mut deepest = depth;
        let mut lower = f64::INFINITY;
        let mut undecided: Option<f64> = None;
        let mut stop = Stop::Decided;
        let mut upper = f64::INFINITY;
        while let Some(piece) = stack.pop() {
            pieces += 1;
            deepest = deepest.max(piece.depth);
            let (values, errors) = piece.coef.split_at(len);
            // NaN and infinities (overflow) decide nothing: the piece goes to the exact path.
            if !piece.coef.iter().all(|x| x.is_finite()) {
                undecided = Some(f64::NEG_INFINITY);
                stop = Stop::Precision;
                break;
            }
            let mut hopeless = None;
            for i in 0..m {
                let value = values[self.vertex_rank[i]];
                let error = errors[self.vertex_rank[i]];
                upper = upper.min(value);
                if value + error <= 0.0 {
                    // Negative beyond its error bound: a candidate the caller proves exactly.
                    pool.push(piece.coef);
                    pool.extend(stack.into_iter().map(|p| p.coef));
                    give_back(pool);
                    return (
                        Decision::NonPositive {
                            point: piece.corners[i][..m].to_vec(),
                            value,
                            error,
                        },
                        Stop::Decided,
                    );
                }
                if value - error <= 0.0 {
                    hopeless = Some(value - error);
                }
            }
            // A vertex whose sign the bound cannot settle settles nothing below: bisection copies a
            // piece's vertex coefficients and their bounds unchanged into the child that keeps the
            // vertex, so no descendant containing it can be certified: the whole simplex cannot
            // be. Give up at once (always sound) and let a tighter computation decide.
            if let Some(low) = hopeless {
                undecided = Some(undecided.map_or(low, |l: f64| l.min(low)));
                stop = Stop::Precision;
                break;
            }
            let low = values
                .iter()
                .zip(errors)
                .map(|(v, e)| v - e)
                .fold(f64::INFINITY, f64::min);
            if impatient && low <= 0.0 && values.iter().zip(errors).any(|(v, e)| v.abs() <= *e) {
                undecided = Some(undecided.map_or(low, |l: f64| l.min(low)));
                stop = Stop::Precision;
                break;
            }
            if low > 0.0 {
                lower = lower.min(low);
                pool.push(piece.coef);
                continue;
            }
            if piece.depth >= max_depth || pieces + stack.len() >= budget {
                let l = undecided.get_or_insert(low);
                *l = l.min(low);
                stop = Stop::Budget;
                pool.push(piece.coef);
                continue;
            }
            let (a, b) = longest_edge(&piece.corners, m);
            let mut left = pool.pop().unwrap_or_default();
            let mut right = pool.pop().unwrap_or_default();
            self.bisect(&piece.coef, a, b, &mut left, &mut right);
            pool.push(piece.coef);
            let (ca, cb) = split_corners(&piece.corners, a, b, m);
            // Depth first into the child with the lower least coefficient: where the polynomial is
            // lowest is where a witness is, and where bisection gives up soonest.
            let least = |c: &[f64]| c[..len].iter().copied().fold(f64::INFINITY, f64::min);
            let right_first = least(&right) < least(&left);
            let l = Piece {
                coef: left,
                corners: ca,
                depth: piece.depth + 1,
            };
            let r = Piece {
                coef: right,
                corners: cb,
                depth: piece.depth + 1,
            };
            if right_first {
                stack.push(l);
                stack.push(r);
            } else {
                stack.push(r);
                stack.push(l);
            }
        }
        pool.extend(stack.into_iter().map(|p| p.coef));
        give_back(pool);
        match undecided {
            None => (
                Decision::Positive {
                    depth: deepest,
                    pieces,
                    lower_bound: lower,
                },
                Stop::Decided,
            ),
            Some(l) => (
                Decision::Undetermined {
                    depth: deepest,
                    pieces,
                    lower_bound: l,
                    upper_bound: upper,
                },
                stop,
            ),
        }
    }

    /// Splits the simplex at the midpoint of edge `(a, b)`. `piece` holds the values then the
    /// error bounds (`2L` numbers); `left` and `right` (recycled buffers) receive those of the child
    /// that keeps vertex `a` and of the child that keeps vertex `b`, with propagated bounds.
    fn bisect(&self, piece: &[f64], a: usize, b: usize, left: &mut Vec<f64>, right: &mut Vec<f64>) {
        let (a, b, swap) = if a < b { (a, b, false) } else { (b, a, true) };
        let (left, right) = if swap { (right, left) } else { (left, right) };
        let len_all = piece.len() / 2;
        // Every position is written below (the lines along an edge partition the coefficients):
        // no need to clear a recycled buffer of the right length.
        left.resize(piece.len(), 0.0);
        right.resize(piece.len(), 0.0);
        let (values, errors) = piece.split_at(len_all);
        let (lv, le) = left.split_at_mut(len_all);
        let (rv, re) = right.split_at_mut(len_all);
        // A line holds at most D + 1 ≤ 62 coefficients (degree 16 rational in 3D).
        let mut tv = [0.0f64; 64];
        let mut te = [0.0f64; 64];
        for line in self.edge_lines(a, b) {
            let len = line.len();
            for (j, &r) in line.iter().enumerate() {
                tv[j] = values[r as usize];
                te[j] = errors[r as usize];
            }
            // De Casteljau at t = 1/2 along the line (index j = exponent of b). After step s, entry 0
            // is the left child's coefficient s and entry len−1−s the right child's coefficient
            // len−1−s.
            lv[line[0] as usize] = tv[0];
            le[line[0] as usize] = te[0];
            rv[line[len - 1] as usize] = tv[len - 1];
            re[line[len - 1] as usize] = te[len - 1];
            for step in 1..len {
                for j in 0..len - step {
                    let v = (tv[j] + tv[j + 1]) * 0.5;
                    // |fl((x+y)/2) − (x+y)/2| ≤ u·|v|(1+u); the bound's own roundings are covered by
                    // the factor 4 in place of 1.
                    let e = ((te[j] + te[j + 1]) * 0.5 + 2.0 * UNIT_ROUNDOFF * v.abs())
                        * (1.0 + 4.0 * UNIT_ROUNDOFF)
                        + UNDERFLOW_SLACK;
                    tv[j] = v;
                    te[j] = e;
                }
                lv[line[step] as usize] = tv[0];
                le[line[step] as usize] = te[0];
                rv[line[len - 1 - step] as usize] = tv[len - 1 - step];
                re[line[len - 1 - step] as usize] = te[len - 1 - step];
            }
        }
    }
}

/// Pieces the plain subdivision of the whole simplex may use before the element is decided around
/// its estimated minimum instead: most elements decide within a handful; an element whose minimum
/// is near 0 would take ~50 bisections of midpoint subdivision to reach it.
const QUICK_PIECES: usize = 4;

/// Pieces of plain subdivision each star piece gets before it is decided around its own estimated
/// minimum instead.
const STAR_QUICK_PIECES: usize = 16;

/// Levels of star decisions (the last subdivides with the whole remaining budget).
const STAR_LEVELS: u32 = 3;

/// Coordinates of the estimated minimiser are multiples of 2⁻⁵⁰: every sum of them in `[0, 1]` is
/// exact in f64, so the largest coordinate is `1 − Σ others` exactly — the de Casteljau weights
/// of the star subdivision sum exactly to 1, and the printed point is the one subdivided at.
const MINIMISER_GRID: f64 = 1_125_899_906_842_624.0; // 2^50

/// Newton steps toward the minimum (quadratic convergence: a handful suffice from the least
/// coefficient's domain point; the result is only a subdivision point, never trusted).
const NEWTON_STEPS: usize = 10;

/// Tables of the evaluation at a point and of the star subdivision at a point, for one
/// determinant degree `D` in `m` barycentric coordinates.
#[derive(Clone, Debug)]
struct StarTables {
    /// `steps[r]`: for each multi-index `J` of degree `r < D`, the ranks of `J + eᵢ` in degree
    /// `r + 1` (one de Casteljau step maps degree `r + 1` to degree `r`).
    steps: Vec<Vec<[u16; 4]>>,
    /// Offset of the coefficients of degree `D − r` in the flattened de Casteljau pyramid.
    offsets: Vec<usize>,
    /// `star[i][K]`: position in the pyramid of coefficient `K` of the piece whose vertex `i` is
    /// the subdivision point (the blossom `b(v₀^{K₀} … x^{Kᵢ} … vₙ^{Kₙ})` is the entry `K − Kᵢeᵢ`
    /// after `Kᵢ` de Casteljau steps at `x`).
    star: Vec<Vec<u32>>,
    /// Rank of `eᵢ + eⱼ` in degree 2.
    quad: [[usize; 4]; 4],
    /// Newton's start for each least coefficient `K`: its domain point `K/D`, moved a fifth of
    /// the way to the centroid (a start on a face would keep the coordinates that are 0 there at 0).
    start: Vec<[f64; 4]>,
}

impl StarTables {
    fn new(m: usize, det_degree: u32) -> StarTables {
        let steps = (0..det_degree)
            .map(|r| {
                multi_index::all(m, r)
                    .chunks(m)
                    .map(|j| {
                        let mut out = [0u16; 4];
                        let mut k = j.to_vec();
                        for (i, o) in out.iter_mut().enumerate().take(m) {
                            k[i] += 1;
                            *o = multi_index::rank(&k) as u16;
                            k[i] -= 1;
                        }
                        out
                    })
                    .collect()
            })
            .collect();
        let mut offsets = Vec::with_capacity(det_degree as usize + 2);
        let mut acc = 0;
        for r in 0..=det_degree {
            offsets.push(acc);
            acc += multi_index::count(m, det_degree - r);
        }
        offsets.push(acc);
        let all = multi_index::all(m, det_degree);
        let star = (0..m)
            .map(|i| {
                all.chunks(m)
                    .map(|k| {
                        let mut j = k.to_vec();
                        j[i] = 0;
                        (offsets[k[i] as usize] + multi_index::rank(&j)) as u32
                    })
                    .collect()
            })
            .collect();
        let mut quad = [[0usize; 4]; 4];
        if det_degree >= 2 {
            for (i, row) in quad.iter_mut().enumerate().take(m) {
                for (j, q) in row.iter_mut().enumerate().take(m) {
                    let mut e = vec![0u32; m];
                    e[i] += 1;
                    e[j] += 1;
                    *q = multi_index::rank(&e);
                }
            }
        }
        let start = all
            .chunks(m)
            .map(|k| {
                let mut x = [0.0; 4];
                for (xi, &e) in x.iter_mut().zip(k) {
                    *xi = 0.8 * f64::from(e) / f64::from(det_degree) + 0.2 / m as f64;
                }
                x
            })
            .collect();
        StarTables {
            steps,
            offsets,
            star,
            quad,
            start,
        }
    }
}

thread_local! {
    /// Coefficient buffers of [`DetKernel::decide_inner`], kept between elements on each thread.
    static POOL: std::cell::RefCell<Vec<Vec<f64>>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// Most buffers kept per thread (memory stays bounded after a deep element).
const POOL_KEEP: usize = 64;

/// Returns buffers to this thread's pool.
fn give_back(mut pool: Vec<Vec<f64>>) {
    pool.truncate(POOL_KEEP);
    POOL.with(|p| *p.borrow_mut() = pool);
}

/// Why [`DetKernel::decide_inner`] stopped short of a decision.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Stop {
    /// Decided (positive, or a candidate witness).
    Decided,
    /// The piece budget or the depth limit: a better subdivision may still decide.
    Budget,
    /// A sign within its error bound (or a number not finite): only a tighter tier decides.
    Precision,
}

/// One tier's outcome: [`Decision`] with the candidate witness already proven (or not).
enum TierOutcome {
    Decided(Decision),
    Witness(crate::exact::ExactWitness),
}

/// Solves `(H + μI) δ = −g` (size ≤ 3, `H` symmetric) by Cholesky, raising `μ` until the matrix
/// is positive definite: a damped Newton step that is always a descent direction. (Index loops:
/// the triangular solves read clearer with the indices of the formulas.)
#[allow(clippy::needless_range_loop)]
fn damped_newton_step(h: &[[f64; 3]; 3], g: &[f64; 3], k: usize) -> Option<[f64; 3]> {
    let scale = (0..k).map(|i| h[i][i].abs()).fold(0.0f64, f64::max);
    if !(scale.is_finite() && scale > 0.0) {
        return None;
    }
    let mut mu = 0.0;
    for _ in 0..40 {
        let mut l = [[0.0f64; 3]; 3];
        let mut ok = true;
        'rows: for i in 0..k {
            for j in 0..=i {
                let mut s = h[i][j] + if i == j { mu } else { 0.0 };
                for p in 0..j {
                    s -= l[i][p] * l[j][p];
                }
                if i == j {
                    if s.is_nan() || s <= 1e-14 * scale {
                        ok = false;
                        break 'rows;
                    }
                    l[i][i] = s.sqrt();
                } else {
                    l[i][j] = s / l[j][j];
                }
            }
        }
        if ok {
            let mut y = [0.0f64; 3];
            for i in 0..k {
                let mut s = -g[i];
                for p in 0..i {
                    s -= l[i][p] * y[p];
                }
                y[i] = s / l[i][i];
            }
            let mut x = [0.0f64; 3];
            for i in (0..k).rev() {
                let mut s = y[i];
                for p in (i + 1)..k {
                    s -= l[p][i] * x[p];
                }
                x[i] = s / l[i][i];
            }
            return x.iter().all(|v| v.is_finite()).then_some(x);
        }
        mu = if mu == 0.0 { 1e-8 * scale } else { mu * 10.0 };
    }
    None
}

impl DetKernel {
    /// The symmetric matrix `Q` with `p(y) ≈ yᵀQy` near `x`: the degree-2 coefficients after
    /// `D − 2` de Casteljau steps at `x`, so that `p(x) = xᵀQx`, `∇p` along `eₖ − eⱼ` is
    /// `D (Qx)ₖ − D (Qx)ⱼ` and the Hessian `D(D − 1)` times the second differences of `Q`.
    /// Plain floating point: only used to place a subdivision point.
    fn local_quadratic(
        &self,
        t: &StarTables,
        values: &[f64],
        x: &[f64; 4],
        buffers: &mut (Vec<f64>, Vec<f64>),
    ) -> [[f64; 4]; 4] {
        let m = self.n + 1;
        let (cur, next) = buffers;
        cur.clear();
        cur.extend_from_slice(values);
        for r in (2..self.det_degree as usize).rev() {
            next.clear();
            next.extend(t.steps[r].iter().map(|sh| {
                let mut v = 0.0;
                for i in 0..m {
                    v += x[i] * cur[sh[i] as usize];
                }
                v
            }));
            std::mem::swap(cur, next);
        }
        let mut q = [[0.0; 4]; 4];
        for i in 0..m {
            for j in 0..m {
                q[i][j] = cur[t.quad[i][j]];
            }
        }
        q
    }

    /// An estimate of the point where the polynomial with Bernstein coefficients `values` is least
    /// on the simplex: damped Newton ([`DetKernel::newton`]) from the least coefficient's domain
    /// point. It may stop at a local minimum away from the least one: the star decision then
    /// finds the least one in one of its pieces and decides that piece around its own estimate.
    /// Coordinates are rounded to multiples of [`MINIMISER_GRID`] with the largest one
    /// `1 − Σ others`, exactly: a point of the closed simplex whose coordinates sum exactly to 1.
    /// `None` when Newton fails (degree below 2, or numbers not finite).
    fn minimiser(&self, t: &StarTables, values: &[f64]) -> Option<[f64; 4]> {
        let m = self.n + 1;
        if self.det_degree < 2 {
            return None;
        }
        let least = values
            .iter()
            .enumerate()
            .min_by(|a, b| a.1.total_cmp(b.1))?
            .0;
        let mut buffers = (Vec::with_capacity(values.len()), Vec::new());
        let x = self.newton(t, values, t.start[least], &mut buffers)?;
        on_grid(x, m)
    }

    /// Damped Newton from `x` toward a local minimum of the polynomial on the simplex, steps
    /// truncated at the boundary: a coordinate that reaches 0 is held there while the gradient
    /// pushes outward and released when it points back inside (an active set). Plain floating
    /// point: the result is only a subdivision point.
    #[allow(clippy::needless_range_loop)]
    fn newton(
        &self,
        t: &StarTables,
        values: &[f64],
        mut x: [f64; 4],
        buffers: &mut (Vec<f64>, Vec<f64>),
    ) -> Option<[f64; 4]> {
        let m = self.n + 1;
        let dg = f64::from(self.det_degree);
        let mut free = [false; 4];
        free[..m].iter_mut().for_each(|f| *f = true);
        for _ in 0..NEWTON_STEPS {
            let q = self.local_quadratic(t, values, &x, buffers);
            let mut qx = [0.0f64; 4];
            for i in 0..m {
                qx[i] = (0..m).map(|j| q[i][j] * x[j]).sum();
            }
            let base = (0..m)
                .filter(|&i| free[i])
                .max_by(|&a, &b| x[a].total_cmp(&x[b]))?;
            // Release a held coordinate whose direction into the simplex descends.
            for i in 0..m {
                if !free[i] && qx[i] < qx[base] {
                    free[i] = true;
                }
            }
            let mut dirs = [0usize; 3];
            let mut k = 0;
            for i in (0..m).filter(|&i| free[i] && i != base) {
                dirs[k] = i;
                k += 1;
            }
            let dirs = &dirs[..k];
            if k == 0 {
                break;
            }
            let mut g = [0.0f64; 3];
            let mut h = [[0.0f64; 3]; 3];
            for (a, &i) in dirs.iter().enumerate() {
                g[a] = dg * (qx[i] - qx[base]);
                for (b, &j) in dirs.iter().enumerate() {
                    h[a][b] = dg * (dg - 1.0) * (q[i][j] - q[i][base] - q[base][j] + q[base][base]);
                }
            }
            let delta = damped_newton_step(&h, &g, k)?;
            let mut step = [0.0f64; 4];
            for (a, &i) in dirs.iter().enumerate() {
                step[i] = delta[a];
                step[base] -= delta[a];
            }
            // Truncate at the boundary; the blocking coordinate becomes 0 and is held there.
            let mut tmax = 1.0f64;
            let mut blocking = None;
            for i in 0..m {
                if free[i] && step[i] < 0.0 && x[i] + step[i] < 0.0 {
                    let t = x[i] / -step[i];
                    if t < tmax {
                        tmax = t;
                        blocking = Some(i);
                    }
                }
            }
            for i in 0..m {
                x[i] += tmax * step[i];
            }
            if let Some(i) = blocking {
                x[i] = 0.0;
                free[i] = false;
            }
            for xi in x.iter_mut().take(m) {
                *xi = xi.max(0.0);
            }
            let size = step[..m].iter().map(|s| s.abs()).fold(0.0, f64::max) * tmax;
            if !size.is_finite() {
                return None;
            }
            if size < 1e-15 && blocking.is_none() {
                break;
            }
        }
        Some(x)
    }

    /// The de Casteljau pyramid at `x` (coordinates ≥ 0 summing exactly to 1) of bounded
    /// coefficients, flattened by degree (`D`, then `D − 1`, … 0), values then errors.
    ///
    /// Each entry is `Σᵢ xᵢ yᵢ` of `m` entries `yᵢ` of the level above: with the exact inputs
    /// within `eᵢ` of the computed ones, the exact entry is within `Σ xᵢ eᵢ` of the computed inputs'
    /// combination (a convex combination), and the computed sum within `γₘ Σ xᵢ|yᵢ|` of that
    /// (Higham, Accuracy and Stability, §3.1, `m` products and `m − 1` additions). The bound is
    /// itself summed in floating point over non-negative terms (at most `m + 2` roundings, covered
    /// by `γₘ` taken twice and the factor `1 + 4(m + 2)u`); underflow adds [`UNDERFLOW_SLACK`].
    fn pyramid(&self, t: &StarTables, coefficients: &[f64], x: &[f64; 4], out: &mut Vec<f64>) {
        let m = self.n + 1;
        let dd = self.det_degree as usize;
        let total = t.offsets[dd + 1];
        let len = t.offsets[1];
        // Every entry is written below.
        out.resize(2 * total, 0.0);
        let (pv, pe) = out.split_at_mut(total);
        pv[..len].copy_from_slice(&coefficients[..len]);
        pe[..len].copy_from_slice(&coefficients[len..]);
        let mf = m as f64;
        let gamma = 2.0 * mf * UNIT_ROUNDOFF / (1.0 - mf * UNIT_ROUNDOFF);
        let grow = 1.0 + 4.0 * (mf + 2.0) * UNIT_ROUNDOFF;
        for r in 1..=dd {
            let src = t.offsets[r - 1];
            let dst = t.offsets[r];
            for (j, sh) in t.steps[dd - r].iter().enumerate() {
                let (mut v, mut e, mut a) = (0.0, 0.0, 0.0);
                for i in 0..m {
                    let y = pv[src + sh[i] as usize];
                    v += x[i] * y;
                    a += x[i] * y.abs();
                    e += x[i] * pe[src + sh[i] as usize];
                }
                pv[dst + j] = v;
                pe[dst + j] = (e + gamma * a) * grow + UNDERFLOW_SLACK;
            }
        }
    }

    /// Decides the sign around the estimated minimum: if the polynomial is negative there, the
    /// point is the candidate witness; otherwise the simplex is cut into the star of pieces that
    /// share that point as a vertex (a piece per facet not containing it), each decided by
    /// subdivision. A piece with its vertex at the minimum has its lowest coefficients at that
    /// vertex and its neighbours (the gradient vanishes there), so near-threshold minima are
    /// certified at a depth that does not grow as the minimum approaches 0 — where midpoint
    /// subdivision must bisect until the pieces are ~√min wide. `None` when this settles nothing
    /// (the caller subdivides the whole simplex).
    fn around_minimum(
        &self,
        coefficients: &[f64],
        budget: usize,
        max_depth: u32,
        impatient: bool,
        estimate: &mut Option<Option<[f64; 4]>>,
    ) -> Option<(Decision, usize)> {
        let t = self.star_tables();
        let len = t.offsets[1];
        // The tiers' coefficients differ by their rounding only: one estimate serves both.
        let x = (*estimate.get_or_insert_with(|| self.minimiser(t, &coefficients[..len])))?;
        let corners = unit_corners(self.n + 1);
        let mut pieces = 0usize;
        let decision = self.star_decide(
            coefficients,
            &corners,
            x,
            budget,
            max_depth,
            impatient,
            0,
            &mut pieces,
        )?;
        Some((decision, pieces))
    }

    /// The star decision on one piece with corners `corners` (barycentric in the element) and
    /// coefficients `coefficients` (values then errors, in the piece's own barycentric
    /// coordinates), cut at `x` (the piece's coordinates, ≥ 0, summing exactly to 1). Each star
    /// piece gets [`STAR_QUICK_PIECES`] of plain subdivision; one that the budget, not the
    /// precision, stopped is decided by the same method around its own estimated minimum (up to
    /// [`STAR_LEVELS`] levels, the last with the whole remaining budget): the estimate may have
    /// found a local minimum far from the near-zero one (Newton on a polynomial of degree up to
    /// 9 here), which then lies in one of the pieces. `pieces` counts the pieces examined.
    #[allow(clippy::too_many_arguments)]
    fn star_decide(
        &self,
        coefficients: &[f64],
        corners: &[[f64; 4]; 4],
        x: [f64; 4],
        budget: usize,
        max_depth: u32,
        impatient: bool,
        level: u32,
        pieces: &mut usize,
    ) -> Option<Decision> {
        let m = self.n + 1;
        let t = self.star_tables();
        let len = t.offsets[1];
        let mut pyramid = Vec::new();
        self.pyramid(t, coefficients, &x, &mut pyramid);
        let total = t.offsets[self.det_degree as usize + 1];
        let (value, error) = (pyramid[total - 1], pyramid[2 * total - 1]);
        if !(value.is_finite() && error.is_finite()) {
            return None;
        }
        *pieces += 1;
        // The point in the element's coordinates (only a candidate witness and a corner of the
        // star pieces, which locate candidates: the pieces' coefficients are those at `x`).
        let point = if level == 0 {
            x
        } else {
            element_point(corners, &x, m)?
        };
        if value + error <= 0.0 {
            return Some(Decision::NonPositive {
                point: point[..m].to_vec(),
                value,
                error,
            });
        }
        if value - error <= 0.0 {
            // The point is a vertex of every star piece: none could be certified.
            return None;
        }
        let mut deepest = 0u32;
        let mut lower = f64::INFINITY;
        let mut coef = Vec::with_capacity(2 * len);
        for i in 0..m {
            if x[i] == 0.0 {
                // The facet opposite vertex i contains x: its piece is flat, and the others cover
                // the simplex.
                continue;
            }
            coef.clear();
            coef.extend(t.star[i].iter().map(|&p| pyramid[p as usize]));
            coef.extend(t.star[i].iter().map(|&p| pyramid[total + p as usize]));
            let mut piece_corners = *corners;
            piece_corners[i] = point;
            let left = budget.saturating_sub(*pieces);
            let quick = if level + 1 < STAR_LEVELS {
                left.min(STAR_QUICK_PIECES)
            } else {
                left
            };
            let (decision, stop) =
                self.decide_inner(&coef, piece_corners, 0, quick, max_depth, impatient);
            let decision = match (decision, stop) {
                (Decision::Undetermined { pieces: p, .. }, Stop::Budget)
                    if level + 1 < STAR_LEVELS && quick < left =>
                {
                    *pieces += p;
                    let y = self.minimiser(t, &coef[..len])?;
                    let d = self.star_decide(
                        &coef,
                        &piece_corners,
                        y,
                        budget,
                        max_depth,
                        impatient,
                        level + 1,
                        pieces,
                    )?;
                    match d {
                        Decision::Positive {
                            depth, lower_bound, ..
                        } => Decision::Positive {
                            depth,
                            pieces: 0,
                            lower_bound,
                        },
                        other => other,
                    }
                }
                (
                    Decision::Positive {
                        depth,
                        pieces: p,
                        lower_bound,
                    },
                    _,
                ) => {
                    *pieces += p;
                    Decision::Positive {
                        depth,
                        pieces: 0,
                        lower_bound,
                    }
                }
                (other, _) => other,
            };
            match decision {
                Decision::Positive {
                    depth, lower_bound, ..
                } => {
                    deepest = deepest.max(depth);
                    lower = lower.min(lower_bound);
                }
                candidate @ Decision::NonPositive { .. } => return Some(candidate),
                Decision::Undetermined { .. } => return None,
            }
        }
        Some(Decision::Positive {
            depth: deepest,
            pieces: *pieces,
            lower_bound: lower,
        })
    }

    /// One tier of the certificate on coefficients `coefficients` (values then errors): plain
    /// subdivision with [`QUICK_PIECES`]; if the budget, not the precision, stopped it, the
    /// decision around the estimated minimum; if that settles nothing, plain subdivision with the
    /// whole budget. Candidate witnesses are proven exactly on `net` here.
    fn decide_tier(
        &self,
        net: &DenseNet,
        coefficients: &[f64],
        budget: usize,
        max_depth: u32,
        impatient: bool,
        estimate: &mut Option<Option<[f64; 4]>>,
    ) -> TierOutcome {
        let m = self.n + 1;
        let unit = unit_corners(m);
        let mut used = 0usize;
        // The impatient (first) tier sees every element: most decide within a few pieces. The
        // patient tier sees only those the first could not settle, whose minimum is near 0.
        let quick = if impatient { QUICK_PIECES } else { 0 };
        if budget > quick {
            let (first, stop) = if quick > 0 {
                self.decide_inner(coefficients, unit, 0, quick, max_depth, impatient)
            } else {
                (
                    Decision::Undetermined {
                        depth: 0,
                        pieces: 0,
                        lower_bound: f64::NEG_INFINITY,
                        upper_bound: f64::INFINITY,
                    },
                    Stop::Budget,
                )
            };
            match (first, stop) {
                (Decision::Undetermined { pieces, .. }, Stop::Budget) => used = pieces,
                (decision, _) => return self.prove(net, decision),
            }
            if let Some((decision, pieces)) =
                self.around_minimum(coefficients, budget - used, max_depth, impatient, estimate)
            {
                used += pieces;
                match decision {
                    Decision::Positive {
                        depth, lower_bound, ..
                    } => {
                        return TierOutcome::Decided(Decision::Positive {
                            depth,
                            pieces: used,
                            lower_bound,
                        })
                    }
                    Decision::NonPositive { point, .. } => {
                        if let Some(w) = crate::exact::witness_at(net, &point) {
                            return TierOutcome::Witness(w);
                        }
                    }
                    Decision::Undetermined { .. } => {}
                }
            }
            if impatient {
                // Not settled around the minimum in floating point: the minimum is within the
                // bound of 0, which the patient tier's tighter coefficients decide sooner than
                // this tier's subdivision of the whole simplex.
                return TierOutcome::Decided(Decision::Undetermined {
                    depth: 0,
                    pieces: used,
                    lower_bound: f64::NEG_INFINITY,
                    upper_bound: f64::INFINITY,
                });
            }
        }
        let (decision, _) = self.decide_inner(
            coefficients,
            unit,
            0,
            budget.saturating_sub(used).max(1),
            max_depth,
            impatient,
        );
        match self.prove(net, decision) {
            TierOutcome::Decided(Decision::Positive {
                depth,
                pieces,
                lower_bound,
            }) => TierOutcome::Decided(Decision::Positive {
                depth,
                pieces: pieces + used,
                lower_bound,
            }),
            TierOutcome::Decided(Decision::Undetermined {
                depth,
                pieces,
                lower_bound,
                upper_bound,
            }) => TierOutcome::Decided(Decision::Undetermined {
                depth,
                pieces: pieces + used,
                lower_bound,
                upper_bound,
            }),
            other => other,
        }
    }

    /// A candidate witness proven exactly on `net`, or the decision as it is (an unproven
    /// candidate decides nothing: the caller goes on to the next tier).
    fn prove(&self, net: &DenseNet, decision: Decision) -> TierOutcome {
        match decision {
            Decision::NonPositive { ref point, .. } => match crate::exact::witness_at(net, point) {
                Some(w) => TierOutcome::Witness(w),
                None => TierOutcome::Decided(decision),
            },
            other => TierOutcome::Decided(other),
        }
    }
}

/// The corners of the two children of a bisection at the midpoint of edge `(a, b)`: the child
/// keeping `a` (`b` moved to the midpoint) and the child keeping `b`.
pub(crate) fn split_corners(
    corners: &[[f64; 4]; 4],
    a: usize,
    b: usize,
    m: usize,
) -> ([[f64; 4]; 4], [[f64; 4]; 4]) {
    let mut mid = [0.0; 4];
    for (c, x) in mid.iter_mut().enumerate().take(m) {
        *x = 0.5 * (corners[a][c] + corners[b][c]);
    }
    let mut ca = *corners;
    ca[b] = mid;
    let mut cb = *corners;
    cb[a] = mid;
    (ca, cb)
}

/// The corners of the whole simplex: the unit vectors of `R^m`.
pub(crate) fn unit_corners(m: usize) -> [[f64; 4]; 4] {
    let mut corners = [[0.0; 4]; 4];
    for (i, c) in corners.iter_mut().enumerate().take(m) {
        c[i] = 1.0;
    }
    corners
}

/// The point with barycentric coordinates `x` in the piece with corners `corners`, in the
/// element's coordinates, rounded to multiples of 2⁻⁵⁰ with the largest coordinate `1 − Σ others`
/// (a point of the closed simplex whose coordinates sum exactly to 1). `None` if not finite.
pub(crate) fn element_point(corners: &[[f64; 4]; 4], x: &[f64; 4], m: usize) -> Option<[f64; 4]> {
    let mut p = [0.0f64; 4];
    for (j, c) in corners.iter().enumerate().take(m) {
        for (pc, &cc) in p.iter_mut().zip(c).take(m) {
            *pc += x[j] * cc;
        }
    }
    on_grid(p, m)
}

/// `x` rounded to multiples of [`MINIMISER_GRID`] with the largest coordinate `1 − Σ others`
/// (exact: every such sum in `[0, 1]` is a double), or `None` if that leaves the simplex or a
/// number is not finite.
fn on_grid(mut x: [f64; 4], m: usize) -> Option<[f64; 4]> {
    let big = (0..m).max_by(|&a, &b| x[a].total_cmp(&x[b]))?;
    let mut rest = 0.0;
    for (i, xi) in x.iter_mut().enumerate().take(m) {
        if i != big {
            *xi = ((*xi * MINIMISER_GRID).round() / MINIMISER_GRID).clamp(0.0, 1.0);
            rest += *xi;
        }
    }
    x[big] = 1.0 - rest;
    (x[big] >= 0.0 && x.iter().all(|v| v.is_finite())).then_some(x)
}

/// The net with its weights scaled by one power of two so that the largest lies in `[1, 2)`: the
/// same map (a common factor of the weights cancels in `P/Q`) and, since the scaling is exact, the
/// same exact certificate polynomial up to the positive factor `2^{-k(n+1)}` — but with no overflow
/// in the floating-point kernel. `None` when a weight is not finite or would lose bits (weights
/// spread over more than the exponent range): such nets go to the exact path.
pub fn normalized(net: &DenseNet) -> Option<std::borrow::Cow<'_, DenseNet>> {
    if !net.is_rational() {
        return Some(std::borrow::Cow::Borrowed(net));
    }
    let max = net.weights.iter().copied().fold(0.0f64, f64::max);
    if !(max.is_finite() && max > 0.0) {
        return None;
    }
    // 2^-k with k = ⌊log₂ max⌋, formed from bits; outside the normal range the net goes exact.
    let k = max.log2().floor() as i32;
    if !(-1022..=1022).contains(&k) {
        return None;
    }
    let factor = f64::from_bits(((1023 - k) as u64) << 52);
    let inverse = f64::from_bits(((1023 + k) as u64) << 52);
    let mut scaled = net.clone();
    for w in &mut scaled.weights {
        let s = *w * factor;
        if !(s.is_finite() && s > 0.0 && s * inverse == *w) {
            return None;
        }
        *w = s;
    }
    Some(std::borrow::Cow::Owned(scaled))
}

/// The pair of corners farthest apart (in barycentric coordinates), ties to the first pair.
pub(crate) fn longest_edge(corners: &[[f64; 4]; 4], m: usize) -> (usize, usize) {
    let mut best = (0, 1);
    let mut len = -1.0;
    for a in 0..m {
        for b in (a + 1)..m {
            let l: f64 = (0..m)
                .map(|c| (corners[a][c] - corners[b][c]).powi(2))
                .sum();
            if l > len {
                len = l;
                best = (a, b);
            }
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_support::{exact_bernstein, vertices_and_dyadic_points};

    /// The degree-4 1-D net of Mello & Velho 2009 Fig. 2 with the interior points at positions `t` (second
    /// coordinate) in canonical order `31, 22, 13`.
    fn one_d(t: [f64; 3]) -> DenseNet {
        let mut points = vec![[1.0, 0.0, 0.0, 0.0]];
        points.extend(t.iter().map(|&x| [1.0 - x, x, 0.0, 0.0]));
        points.push([0.0, 1.0, 0.0, 0.0]);
        DenseNet {
            n: 1,
            degree: 4,
            points,
            weights: Vec::new(),
        }
    }

    #[test]
    fn identity_has_unit_jacobian_in_every_dimension_and_kind() {
        for n in 1..=3 {
            for d in 1..=5 {
                for rational in [false, true] {
                    let mut net = DenseNet::identity(n, d);
                    if rational {
                        net.weights = vec![1.0; net.points.len()];
                    }
                    let kernel = DetKernel::new(n, d, rational);
                    let c = kernel.det_coefficients(&net);
                    assert_eq!(
                        c.values.len(),
                        multi_index::count(n + 1, kernel.det_degree())
                    );
                    for (v, e) in c.values.iter().zip(&c.errors) {
                        assert!(
                            (v - 1.0).abs() <= *e,
                            "n={n} d={d} rational={rational}: {v} ± {e}"
                        );
                    }
                    assert!(kernel.certify(&net, Budget::new(1)).is_positive());
                }
            }
        }
    }

    #[test]
    fn fig2_swapped_points_are_rejected_and_ordered_ones_certified() {
        let kernel = DetKernel::new(1, 4, false);
        // Ordered (Prop. 5.4): certified.
        assert!(kernel
            .certify(&one_d([0.2, 0.5, 0.8]), Budget::default())
            .is_positive());
        // b31 and b13 exchanged beyond the midpoint: det < 0 at t = 1/2.
        match kernel.certify(&one_d([0.9, 0.5, 0.1]), Budget::default()) {
            Certificate::NonPositive(w) => {
                assert!(w.polynomial_value <= 0.0 && w.det <= 0.0, "{w:?}");
                assert_eq!(w.point.len(), 2);
            }
            other => panic!("expected a witness, got {other:?}"),
        }
        // Exactly exchanged (b31 = 3/4 ↔ b13 = 1/4): det = 0 at t = 1/2, never certified.
        assert!(!kernel
            .certify(&one_d([0.75, 0.5, 0.25]), Budget::default())
            .is_positive());
    }

    #[test]
    fn one_d_derivative_coefficients_match_the_hand_computation() {
        // x(t) = Σ c_j B_j(t), c = (0, .2, .5, .8, 1): x' = 4 Σ (c_{j+1} − c_j) B^3_j, and the
        // reduced Jacobian of the 1-D map is x'. Coefficients in canonical order (exponent of w₀
        // decreasing) are those of increasing t.
        let kernel = DetKernel::new(1, 4, false);
        let c = kernel.det_coefficients(&one_d([0.2, 0.5, 0.8]));
        let expect = [0.8, 1.2, 1.2, 0.8];
        for ((v, e), x) in c.values.iter().zip(&c.errors).zip(expect) {
            assert!((v - x).abs() <= e + 1e-15, "{v} vs {x}");
        }
    }

    #[test]
    fn subdivision_finds_a_positive_polynomial_with_a_negative_coefficient() {
        // 1-D degree 4 with control values 0, .45, .5, .55, 1: x' coefficients 1.8, .2, .2, 1.8 are
        // positive; push the middle points so one coefficient is negative but x' stays positive.
        let kernel = DetKernel::new(1, 4, false);
        let net = one_d([0.4, 0.38, 0.62]);
        let c = kernel.det_coefficients(&net);
        assert!(c.values.iter().any(|&v| v < 0.0), "{:?}", c.values);
        match kernel.certify(&net, Budget::default()) {
            Certificate::Positive {
                exact: false,
                depth,
                lower_bound: Some(lower_bound),
                ..
            } => assert!(depth > 0 && lower_bound > 0.0),
            other => panic!("{other:?}"),
        }
    }

    /// The floating-point coefficients of polynomial nets against exact arithmetic: at every
    /// vertex and at random dyadic points, `|Σ c_K B_K(w) − exact(w)| ≤ Σ err_K B_K(w)`, the exact
    /// value from [`crate::exact::jacobian_at`] (a pointwise evaluation of the stored map, not these
    /// coefficients). The nets include coordinates far from 0 with small differences (the bound
    /// follows the differences, not the coordinates) and tiny ones near underflow.
    #[test]
    fn float_coefficients_are_within_their_bound_of_the_exact_polynomial() {
        use num_traits::Signed;
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(41);
        let q = |v: f64| crate::exact::rational(v).unwrap();
        for n in 1..=3usize {
            let m = n + 1;
            for d in 1..=5u32 {
                let kernel = DetKernel::new(n, d, false);
                for trial in 0..12 {
                    let mut net = DenseNet::identity(n, d);
                    let amplitude = [0.01, 0.2, 0.6][trial % 3];
                    // Offset and scale: far from 0 (cancellation in every difference), or tiny.
                    let (offset, scale) = match trial / 3 {
                        0 => (0.0, 1.0),
                        1 => (1e6, 1.0),
                        2 => (-3.5e3, 1e-3),
                        _ => (0.0, 1e-300),
                    };
                    for p in net.points.iter_mut() {
                        for c in p.iter_mut().take(m) {
                            *c = (*c + rng.random_range(-amplitude..amplitude)) * scale + offset;
                        }
                    }
                    let c = kernel.det_coefficients(&net);
                    let dd = kernel.det_degree();
                    for w in &vertices_and_dyadic_points(&mut rng, m, 4) {
                        let (det, _) = crate::exact::jacobian_at(&net, w).expect("inside");
                        let exact_w: Vec<_> = w.iter().map(|&x| q(x)).collect();
                        let value = exact_bernstein(m, dd, &c.values, &exact_w);
                        let bound = exact_bernstein(m, dd, &c.errors, &exact_w);
                        assert!(
                            (value - det).abs() <= bound,
                            "n={n} d={d} trial {trial} at {w:?}"
                        );
                    }
                }
            }
        }
    }

    /// The star pieces' coefficients (de Casteljau pyramid at a point of 2⁻⁵⁰-multiples) against
    /// exact arithmetic: the polynomial of each piece at a point `t` of the piece is the original
    /// polynomial at the point `Σ tⱼ cornerⱼ` of the simplex, evaluated exactly from the
    /// original coefficients (taken as exact, error 0) — within `Σ err_K B_K(t)`.
    #[test]
    fn star_pieces_are_within_their_bound_of_the_exact_subdivision() {
        use num_rational::BigRational;
        use num_traits::Signed;
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(21);
        for n in 1..=3usize {
            let m = n + 1;
            for dd in 2..=9u32 {
                let len = multi_index::count(m, dd);
                // A kernel only for its tables: the degree of the determinant is what matters.
                let kernel = DetKernel {
                    det_degree: dd,
                    ..DetKernel::new(n, 2, false)
                };
                let t = StarTables::new(m, dd);
                for _ in 0..3 {
                    let mut coef: Vec<f64> = (0..len)
                        .map(|_| rng.random_range(-1.0..1.0) * 2f64.powi(rng.random_range(-3..3)))
                        .collect();
                    coef.resize(2 * len, 0.0);
                    // Minimiser of a random polynomial: some point of the closed simplex with exact
                    // coordinates summing to 1, possibly on a face.
                    let x = kernel.minimiser(&t, &coef[..len]).expect("finite");
                    assert_eq!(x[..m].iter().sum::<f64>(), 1.0);
                    assert!(x[..m].iter().all(|&v| v >= 0.0));
                    let mut pyramid = Vec::new();
                    kernel.pyramid(&t, &coef, &x, &mut pyramid);
                    let total = t.offsets[dd as usize + 1];
                    let q = |v: f64| crate::exact::rational(v).unwrap();
                    for i in (0..m).filter(|&i| x[i] > 0.0) {
                        let values: Vec<f64> =
                            t.star[i].iter().map(|&p| pyramid[p as usize]).collect();
                        let errors: Vec<f64> = t.star[i]
                            .iter()
                            .map(|&p| pyramid[total + p as usize])
                            .collect();
                        let mut corners = unit_corners(m);
                        corners[i] = x;
                        for trial in 0..(m + 3) {
                            // The piece's vertices, then random dyadic points of the piece.
                            let tt: Vec<BigRational> = if trial < m {
                                (0..m).map(|j| q(f64::from(u8::from(j == trial)))).collect()
                            } else {
                                let raw: Vec<u32> =
                                    (0..m).map(|_| rng.random_range(1..1000)).collect();
                                let sum: u32 = raw.iter().sum();
                                raw.iter()
                                    .map(|&r| BigRational::new(r.into(), sum.into()))
                                    .collect()
                            };
                            let w: Vec<BigRational> = (0..m)
                                .map(|c| {
                                    (0..m).fold(BigRational::from_integer(0.into()), |a, j| {
                                        a + &tt[j] * q(corners[j][c])
                                    })
                                })
                                .collect();
                            let piece = exact_bernstein(m, dd, &values, &tt);
                            let bound = exact_bernstein(m, dd, &errors, &tt);
                            let truth = exact_bernstein(m, dd, &coef[..len], &w);
                            assert!(
                                (piece - truth).abs() <= bound,
                                "n={n} D={dd} piece {i} at {x:?}"
                            );
                        }
                    }
                }
            }
        }
    }

    /// A 1-D cubic whose derivative has its minimum `≈ gap` (relative) inside the segment, off
    /// every dyadic point: certified around the minimum in a handful of pieces whatever the gap
    /// (midpoint subdivision needs about log₂(1/gap)/2 levels); just past the threshold, rejected
    /// with a witness near the minimum. Truth: the exact minimum of the quadratic `x'`.
    #[test]
    fn a_minimum_near_zero_is_decided_around_it_in_few_pieces() {
        use num_traits::Signed;
        // x(t) with control points 0, a, c, 1: x' = 3(a, c − a, 1 − c) in Bernstein form, which
        // touches 0 where (c − a)² = a(1 − c), at a₀ below.
        let c = 0.2;
        let a0 = (1.2 + (1.2f64 * 1.2 - 0.16).sqrt()) / 2.0;
        let kernel = DetKernel::new(1, 3, false);
        for gap in [1e-4, 1e-8, 1e-12] {
            for sign in [-1.0, 1.0] {
                let a = a0 * (1.0 + sign * gap);
                let net = DenseNet {
                    n: 1,
                    degree: 3,
                    points: vec![
                        [1.0, 0.0, 0.0, 0.0],
                        [1.0 - a, a, 0.0, 0.0],
                        [1.0 - c, c, 0.0, 0.0],
                        [0.0, 1.0, 0.0, 0.0],
                    ],
                    weights: Vec::new(),
                };
                // Exact minimum of the quadratic with Bernstein coefficients p (convex here).
                let q = |v: f64| crate::exact::rational(v).unwrap();
                let three = q(3.0);
                let p = [
                    &three * q(a),
                    &three * (q(c) - q(a)),
                    &three * (q(1.0) - q(c)),
                ];
                let min = (&p[0] * &p[2] - &p[1] * &p[1]) / (&p[0] - &p[1] * q(2.0) + &p[2]);
                assert_eq!(min.is_positive(), sign < 0.0, "gap {gap}: the family");
                match kernel.certify(&net, Budget::default()) {
                    Certificate::Positive { pieces, .. } => {
                        assert!(min.is_positive());
                        assert!(pieces <= 12, "gap {gap}: {pieces} pieces");
                    }
                    Certificate::NonPositive(w) => {
                        assert!(!min.is_positive());
                        assert!(w.det <= 0.0);
                    }
                    other => panic!("gap {gap}: {other:?}"),
                }
            }
        }
    }
}

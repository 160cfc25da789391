//! First-order models over a cell: a quantity as an affine function of the cell's parameter plus a
//! certified remainder, so that products of them (the chain's cofactor products) keep the
//! correlation of their variations.
//!
//! [`crate::chain`] bounds `J = |E⁻ᵀ cof(DY_0) ⋯ cof(DY_{m−1}) Δf| / |∇F_lin|` on a cell of the
//! linear patch. Bounding every factor by an interval over the cell loses twice (session 15's
//! measurement on the fitted sphere: the bound is 2.55× the exact `J` at depth 5): the interval
//! product forgets that the entries vary together with the cell's parameter, and each later
//! stage's Jacobian is bounded over a box around the image of the cell rather than over the
//! image. Both losses are first order in the cell size. Here every entry is carried as
//!
//! `x(λ) ∈ Σ_j λ_j v_j + [−r, r]`, `λ` the cell's barycentric coordinates,
//!
//! an affine function given by its values `v_j` at the cell's vertices and a remainder radius `r`.
//! A Bernstein polynomial on the cell gives one exactly: `v_j` are its vertex coefficients, and
//! `P − Σ λ_j v_j` has the Bernstein coefficients `b_I − Σ_j (I_j / d) v_j`, whose hull encloses it.
//! A product of two affine functions is a quadratic whose Bernstein coefficients are `a_j b_j`
//! at the vertices and `(a_j b_k + a_k b_j) / 2` at the edge midpoints, so its vertex interpolant
//! misses it by the hull of `0` and `−(a_j − a_k)(b_j − b_k) / 2`: second order in the cell
//! size. A later stage is restricted exactly to the triangle of the previous image's vertex values
//! (its Jacobian entries are then Bernstein polynomials on the cell) and the image's remainder is
//! carried through by the stage's derivative bounds over its simplex (a mean-value step whose
//! factor is second order already). The slack of the whole bound is then second order in the cell
//! size, where intervals leave it first order.
//!
//! Floating point: every operation adds [`AFFINE_ROUNDING`] times the magnitudes it combined to
//! the remainder, far above the few ulps each operation can err by, so the enclosures hold for
//! the computed vertex values.

use std::sync::OnceLock;

use ism_format::multi_index;

use crate::bound::BOUND_ROUNDING_MARGIN;

/// Relative rounding allowance of one operation on affine forms: each result is a few correctly
/// rounded operations on the inputs (at most ~10 ulps, 2e-15, of the magnitudes combined);
/// `1e-12` covers that with a wide margin and costs nothing measurable in tightness.
pub(crate) const AFFINE_ROUNDING: f64 = 1e-12;

/// Highest degree of a polynomial converted with [`Affine::from_bernstein`].
pub(crate) const AFFINE_DEGREE: usize = 8;

/// `Σ_j λ_j v_j + [−r, r]` over a cell with three vertices (a segment repeats its second vertex:
/// `v_2 = v_1`, which changes no maximum and adds a zero edge).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub(crate) struct Affine {
    /// Values at the cell's vertices.
    pub v: [f64; 3],
    /// Remainder radius (≥ 0).
    pub r: f64,
}

impl Affine {
    /// The constant `c` (exact).
    pub(crate) fn constant(c: f64) -> Affine {
        Affine { v: [c; 3], r: 0.0 }
    }

    /// Largest `|v_j|`.
    fn top(&self) -> f64 {
        self.v[0].abs().max(self.v[1].abs()).max(self.v[2].abs())
    }

    /// Largest magnitude over the cell, `max_j |v_j| + r` (an affine function's extremes are at
    /// vertices).
    pub(crate) fn magnitude(&self) -> f64 {
        self.top() + self.r
    }

    /// `self + other`.
    pub(crate) fn add(&self, o: &Affine) -> Affine {
        Affine {
            v: [self.v[0] + o.v[0], self.v[1] + o.v[1], self.v[2] + o.v[2]],
            r: self.r + o.r + AFFINE_ROUNDING * (self.magnitude() + o.magnitude()),
        }
    }

    /// `self − other`.
    pub(crate) fn sub(&self, o: &Affine) -> Affine {
        Affine {
            v: [self.v[0] - o.v[0], self.v[1] - o.v[1], self.v[2] - o.v[2]],
            r: self.r + o.r + AFFINE_ROUNDING * (self.magnitude() + o.magnitude()),
        }
    }

    /// `s · self` for a number `s`.
    pub(crate) fn scale(&self, s: f64) -> Affine {
        Affine {
            v: [s * self.v[0], s * self.v[1], s * self.v[2]],
            r: s.abs() * self.r + AFFINE_ROUNDING * s.abs() * self.magnitude(),
        }
    }

    /// `self · other`: the vertex interpolant of the product of the affine parts, shifted by the
    /// centre of its quadratic residual (whose Bernstein coefficients are `0` at the vertices and
    /// `e_jk = −(a_j − a_k)(b_j − b_k) / 2` at the edges, i.e. `Σ_{j<k} 2 e_jk λ_j λ_k`), plus the
    /// remainders' cross terms.
    pub(crate) fn mul(&self, o: &Affine) -> Affine {
        let (a, b) = (&self.v, &o.v);
        let e01 = -0.5 * (a[0] - a[1]) * (b[0] - b[1]);
        let e02 = -0.5 * (a[0] - a[2]) * (b[0] - b[2]);
        let e12 = -0.5 * (a[1] - a[2]) * (b[1] - b[2]);
        // The residual is Σ_{j<k} 2 e_jk λ_j λ_k with λ_j λ_k ≤ 1/4 and Σ_{j<k} λ_j λ_k ≤ 1/3.
        let (p, q) = (e01.max(0.0), e01.min(0.0));
        let (p2, q2) = (e02.max(0.0), e02.min(0.0));
        let (p3, q3) = (e12.max(0.0), e12.min(0.0));
        let hi = (0.5 * (p + p2 + p3)).min(2.0 / 3.0 * p.max(p2).max(p3));
        let lo = (0.5 * (q + q2 + q3)).max(2.0 / 3.0 * q.min(q2).min(q3));
        let c = 0.5 * (lo + hi);
        let (am, bm) = (self.top(), o.top());
        Affine {
            v: [a[0] * b[0] + c, a[1] * b[1] + c, a[2] * b[2] + c],
            r: 0.5 * (hi - lo)
                + am * o.r
                + bm * self.r
                + self.r * o.r
                + AFFINE_ROUNDING * (self.magnitude() * o.magnitude()),
        }
    }

    /// Widens the remainder by `dr ≥ 0`.
    pub(crate) fn widen(mut self, dr: f64) -> Affine {
        self.r += dr;
        self
    }

    /// The affine model of a Bernstein polynomial on the cell (coefficients in canonical order,
    /// `k` = 2 or 3 cell variables, degree `d ≤ AFFINE_DEGREE`): vertex coefficients and the hull of
    /// `b_I − Σ_j (I_j / d) v_j`, widened like [`crate::bound::quotient_range`] for the rounding of
    /// the coefficients themselves. `None` for a shape without a plan.
    pub(crate) fn from_bernstein(k: usize, d: u32, coeffs: &[f64]) -> Option<Affine> {
        let plan = vertex_plan(k, d)?;
        debug_assert_eq!(coeffs.len(), plan.weights.len());
        let mut v = [0.0; 3];
        for (j, &at) in plan.vertices.iter().enumerate().take(k) {
            v[j] = coeffs[at as usize];
        }
        if k == 2 {
            v[2] = v[1];
        }
        let (mut lo, mut hi, mut top) = (0.0f64, 0.0f64, 0.0f64);
        for (&b, w) in coeffs.iter().zip(&plan.weights) {
            let e = b - (w[0] * v[0] + w[1] * v[1] + w[2] * v[2]);
            lo = lo.min(e);
            hi = hi.max(e);
            top = top.max(b.abs());
        }
        let c = 0.5 * (lo + hi);
        Some(Affine {
            v: [v[0] + c, v[1] + c, v[2] + c],
            r: 0.5 * (hi - lo)
                + (BOUND_ROUNDING_MARGIN + AFFINE_ROUNDING) * top
                + f64::MIN_POSITIVE,
        })
    }
}

/// Where the vertex coefficients of a `(k, d)` Bernstein polynomial are, and each coefficient's
/// weights `I_j / d` of the vertex interpolant (zero for a missing third vertex).
struct VertexPlan {
    vertices: [u32; 3],
    weights: Vec<[f64; 3]>,
}

fn vertex_plan(k: usize, d: u32) -> Option<&'static VertexPlan> {
    static PLANS: [[OnceLock<VertexPlan>; AFFINE_DEGREE + 1]; 2] =
        [const { [const { OnceLock::new() }; AFFINE_DEGREE + 1] }; 2];
    if !(2..=3).contains(&k) || d as usize > AFFINE_DEGREE {
        return None;
    }
    Some(PLANS[k - 2][d as usize].get_or_init(|| {
        let mut vertices = [0u32; 3];
        for (j, v) in vertices.iter_mut().enumerate().take(k) {
            let mut idx = [0u32; 3];
            idx[j] = d;
            *v = multi_index::rank(&idx[..k]) as u32;
        }
        let weights = multi_index::all(k, d)
            .chunks_exact(k)
            .map(|i| {
                let mut w = [0.0; 3];
                for j in 0..k {
                    // Degree 0: the constant's only coefficient is its value at every vertex.
                    w[j] = if d == 0 {
                        if j == 0 {
                            1.0
                        } else {
                            0.0
                        }
                    } else {
                        f64::from(i[j]) / f64::from(d)
                    };
                }
                w
            })
            .collect();
        VertexPlan { vertices, weights }
    }))
}

#[cfg(test)]
mod tests {
    use super::*;
    use ism_geom::Bernstein;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// Points of the triangle (or segment) on a lattice, as barycentric weights.
    fn lattice(k: usize) -> Vec<[f64; 3]> {
        let s = 10;
        let mut out = Vec::new();
        for i in 0..=s {
            for j in 0..=(if k == 2 { 0 } else { s - i }) {
                let (a, b) = (f64::from(i) / f64::from(s), f64::from(j) / f64::from(s));
                out.push(if k == 2 {
                    [1.0 - a, a, 0.0]
                } else {
                    [1.0 - a - b, a, b]
                });
            }
        }
        out
    }

    fn at(a: &Affine, l: &[f64; 3]) -> (f64, f64) {
        let c = a.v[0] * l[0] + a.v[1] * l[1] + a.v[2] * l[2];
        (c - a.r, c + a.r)
    }

    /// Ground truth from direct evaluation of the polynomials (the kernel's de Casteljau) and
    /// of their products at lattice points: every value lies in the affine model's band there.
    #[test]
    fn models_enclose_polynomials_and_their_products() {
        let mut rng = ChaCha8Rng::seed_from_u64(31);
        for k in 2..=3usize {
            for d in 0..=5u32 {
                for _ in 0..20 {
                    let p = Bernstein::from_fn(k, d, |_| rng.random_range(-2.0..2.0));
                    let q = Bernstein::from_fn(k, d, |_| rng.random_range(-2.0..2.0));
                    let (ap, aq) = (
                        Affine::from_bernstein(k, d, p.coeffs()).unwrap(),
                        Affine::from_bernstein(k, d, q.coeffs()).unwrap(),
                    );
                    let prod = ap.mul(&aq).sub(&ap.scale(0.5)).add(&Affine::constant(0.25));
                    for l in lattice(k) {
                        let (x, y) = (p.eval(&l[..k]), q.eval(&l[..k]));
                        for (model, exact) in [(&ap, x), (&aq, y), (&prod, x * y - 0.5 * x + 0.25)]
                        {
                            let (lo, hi) = at(model, &l);
                            assert!(
                                lo <= exact && exact <= hi,
                                "k {k} d {d}: {exact} ∉ [{lo}, {hi}]"
                            );
                        }
                    }
                }
            }
        }
    }

    /// A linear polynomial is modelled exactly (zero remainder but for rounding), and the
    /// remainder of a product shrinks like the square of the cell: halving the cell quarters it.
    #[test]
    fn remainders_are_second_order() {
        let lin = Bernstein::from_fn(3, 1, |i| f64::from(i[1]) - 2.0 * f64::from(i[2]));
        let a = Affine::from_bernstein(3, 1, lin.coeffs()).unwrap();
        assert!(a.r < 1e-8);
        // x(1 − x) on cells [0, h]: the product of two affine models.
        let mut last = f64::INFINITY;
        for h in [1.0, 0.5, 0.25, 0.125] {
            let x = Affine {
                v: [0.0, h, h],
                r: 0.0,
            };
            let y = Affine {
                v: [1.0, 1.0 - h, 1.0 - h],
                r: 0.0,
            };
            let r = x.mul(&y).r;
            // x(h − x) ∈ [0, h²/4] exactly; the model gives [0, h²/3] (a segment is a triangle
            // with a repeated vertex, so the edge bound 2/3 · e applies, e = h²/2).
            assert!((r - h * h / 6.0).abs() < 1e-9, "h {h}: r {r}");
            assert!(r < 0.3 * last);
            last = r;
        }
    }
}

//! Double-double (twofold) Bernstein coefficients of the certificate polynomial, with a rigorous
//! error bound about `10⁻²⁸` of the scale: the middle tier between the floating-point kernel of
//! [`crate::certify`] (error `γₖ · E`, about `10⁻¹¹` of the scale at degree 4 in 3D) and the exact
//! path of [`crate::exact`] (big integers). Near the fold threshold the minimum of `det DX` is far
//! below the floating-point bound but far above this one, so the sign is decided here at a small
//! multiple of the floating-point cost instead of the big-integer one.
//!
//! # The arithmetic
//! Each value is an unevaluated sum `hi + lo` of two doubles with `|lo| ≤ u·|hi|` (`u = 2⁻⁵³`).
//! Only error-free transformations and plain double operations are used, all on the stable Rust
//! standard library (no FMA: Dekker's product needs none, so the result does not depend on the
//! target):
//!
//! - `TwoSum(a, b)` (Knuth): `s + e = a + b` exactly, for any doubles (also subnormal);
//! - `TwoProduct(a, b)` (Dekker 1971, Veltkamp splitting): `p + e = a · b` exactly when no
//!   underflow or overflow occurs.
//!
//! # The bound (proved in the comments beside each step)
//! For a value computed from exact inputs whose *companion* (the same expression on absolute
//! values) is `C`, write `|computed − exact| ≤ ρ · C`. Then:
//!
//! - an entry `(x_k − x₀)·c` (`c` an integer below 2⁵³): `ρ ≤ 8u²`;
//! - a Laplace level summing `t` products `x̂ · ŷ` into one coefficient: each product carries at
//!   most `9u²|x̂||ŷ|` (the dropped `lo·lo` term and four roundings of `O(u)`-sized terms), and the
//!   accumulation — exact `TwoSum` on the high parts, the low parts summed in plain doubles — at
//!   most `γ₂ₜ(u) · Σ(|e_i| + |pl_i|) ≤ 2.1 · t(t + 4) u² Σ|x̂||ŷ|`; so `ρ_level ≤ (3t(t+4) + 16)u²`;
//! - errors compose as `(1 + ρ_x)(1 + ρ_y)(1 + ρ_level) − 1` over the products (the same argument
//!   as the floating-point kernel's, `u` replaced by these `ρ`), and the companion of every
//!   Bernstein-normalised coefficient is at most `E` (the permanent of the entries' largest
//!   absolute coefficients, [`crate::certify::DetKernel::det_coefficients`]);
//! - the final rounding to one double and division by the multinomial add `3u|v|`.
//!
//! The total is doubled (as in the floating-point kernel, to cover the bound's own roundings).
//!
//! Underflow and overflow: the path runs only when every entry's companion is at most `2³²` and
//! `E ≤ 2²⁵⁶`, so no intermediate exceeds `2³⁰⁰` (Dekker's splitting is exact below `2⁹⁹⁶`). An
//! underflowing product loses at most `8 · 2⁻¹⁰⁷⁴` per term, amplified by at most `(2³² · 2²⁶)³`
//! (entries times multinomials, three levels) over at most 2¹⁶ terms: below `2⁻⁸⁰⁰`, which every
//! bound adds. Any non-finite result hands the element on to the exact path.

use crate::certify::{permanent, BoundedCoefficients, DenseNet, DetKernel, UNIT_ROUNDOFF};

/// Absolute slack for gradual underflow (see the module documentation).
const TWOFOLD_UNDERFLOW_SLACK: f64 = 1.5e-241; // 2^-800 ≈ 1.5e-241

/// Largest entry companion admitted (`2³²`).
const MAX_ENTRY: f64 = 4_294_967_296.0;

/// Largest `E` admitted (`2²⁵⁶`).
const MAX_SCALE: f64 = 1.157_920_892_373_162e77;

/// `s + e = a + b` exactly (Knuth's TwoSum).
#[inline(always)]
fn two_sum(a: f64, b: f64) -> (f64, f64) {
    let s = a + b;
    let bb = s - a;
    let e = (a - (s - bb)) + (b - bb);
    (s, e)
}

/// Veltkamp's splitting: `a = h + l` with both halves of at most 26 significant bits.
#[inline(always)]
fn split(a: f64) -> (f64, f64) {
    let c = 134_217_729.0 * a; // 2^27 + 1
    let h = c - (c - a);
    (h, a - h)
}

/// The error `a·b − fl(a·b)` from the splittings of `a` and `b` (Dekker's TwoProduct), exact
/// without underflow.
#[inline(always)]
fn product_error(p: f64, a: (f64, f64), b: (f64, f64)) -> f64 {
    ((a.0 * b.0 - p) + a.0 * b.1 + a.1 * b.0) + a.1 * b.1
}

/// A double-double `hi + lo`, normalised (`|lo| ≤ u|hi|`).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub(crate) struct Twofold {
    pub(crate) hi: f64,
    pub(crate) lo: f64,
}

impl Twofold {
    /// `a · b` of two doubles, exactly (without underflow).
    pub(crate) fn product(a: f64, b: f64) -> Twofold {
        let p = a * b;
        let (hi, lo) = two_sum(p, product_error(p, split(a), split(b)));
        Twofold { hi, lo }
    }

    /// `(self − other) · c` for an integer-valued double `c`, within `8u²(|self| + |other|)|c|`:
    /// the difference of the high parts is exact (`TwoSum`), that of the low parts and its sum
    /// with the residual round once each (`u · 2u(|self|+|other|)` and `u · 3u(…)`); the product
    /// by `c` is exact on the high part and rounds `u · |lo·c|` on the low one.
    fn difference_times(self, other: Twofold, c: f64) -> Twofold {
        let (s, e) = two_sum(self.hi, -other.hi);
        let (h, l) = two_sum(s, e + (self.lo - other.lo));
        let p = h * c;
        let pe = product_error(p, split(h), split(c));
        let (hi, lo) = two_sum(p, pe + l * c);
        Twofold { hi, lo }
    }
}

impl DetKernel {
    /// Bernstein coefficients of the certificate polynomial of `net` computed in double-double,
    /// rounded to doubles, with rigorous error bounds (module documentation): about `10⁻²⁸` of
    /// the scale plus `3u` of each coefficient. `None` when the net is outside the admitted range
    /// or a number is not finite — the caller goes on exactly.
    ///
    /// # Panics
    /// When the net does not match the kernel's dimension, degree and kind.
    pub fn det_coefficients_twofold(&self, net: &DenseNet) -> Option<BoundedCoefficients> {
        let m = self.n + 1;
        assert_eq!(net.n, self.n);
        assert_eq!(net.degree, self.degree);
        assert_eq!(
            net.points.len(),
            ism_format::multi_index::count(m, self.degree)
        );
        assert_eq!(net.is_rational(), self.rational);
        let u = UNIT_ROUNDOFF;
        let d = f64::from(self.degree);
        let s = self.size;
        // Components of V: coordinates (polynomial) or q·(1, b) (rational, exact products).
        let component = |idx: usize, r: usize| -> Twofold {
            if self.rational {
                let q = net.weights[idx];
                if r == 0 {
                    Twofold { hi: q, lo: 0.0 }
                } else {
                    Twofold::product(q, net.points[idx][r])
                }
            } else {
                Twofold {
                    hi: net.points[idx][r + 1],
                    lo: 0.0,
                }
            }
        };
        let zero = Twofold::default();
        let mut cols: Vec<Vec<Vec<Twofold>>> = Vec::with_capacity(s);
        let mut maxabs = [[0.0f64; 4]; 4];
        if self.rational {
            let mut col = Vec::with_capacity(s);
            for (r, mx) in maxabs.iter_mut().enumerate().take(s) {
                let v: Vec<Twofold> = self
                    .mult_first
                    .iter()
                    .enumerate()
                    .map(|(i, &mlt)| {
                        let x = component(i, r);
                        mx[0] = mx[0].max(x.hi.abs() * (1.0 + 2.0 * u));
                        x.difference_times(zero, mlt)
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
                let v: Vec<Twofold> = self
                    .shift
                    .iter()
                    .zip(&self.mult_entry)
                    .map(|(sh, &mlt)| {
                        let xk = component(sh[k] as usize, r);
                        let x0 = component(sh[0] as usize, r);
                        mx[j] = mx[j].max(d * (xk.hi.abs() + x0.hi.abs()) * (1.0 + 4.0 * u));
                        xk.difference_times(x0, d * mlt)
                    })
                    .collect();
                col.push(v);
            }
            cols.push(col);
        }
        if !maxabs
            .iter()
            .flatten()
            .all(|x| x.is_finite() && *x <= MAX_ENTRY)
        {
            return None;
        }
        // Laplace expansion from the last column, as in the floating-point kernel; every level
        // accumulates the high parts with TwoSum and the low parts in plain doubles.
        let full = (1usize << s) - 1;
        let mut minors: Vec<Vec<Twofold>> = vec![Vec::new(); full + 1];
        for r in 0..s {
            minors[1 << r] = std::mem::take(&mut cols[s - 1][r]);
        }
        // Σ over the levels of ρ_level, and the entries' ρ once per column.
        let mut rho = s as f64 * 8.0 * u * u;
        let mut hi: Vec<f64> = Vec::new();
        let mut lo: Vec<f64> = Vec::new();
        let mut ysplit: Vec<(f64, f64)> = Vec::new();
        for j in (0..s - 1).rev() {
            let rows = s - j;
            let conv = &self.conv[j];
            let t = (rows * conv.max_terms) as f64;
            rho += (3.0 * t * (t + 4.0) + 16.0) * u * u;
            for mask in 0..=full {
                if (mask as u32).count_ones() as usize != rows {
                    continue;
                }
                hi.clear();
                hi.resize(conv.out_len, 0.0);
                lo.clear();
                lo.resize(conv.out_len, 0.0);
                let mut negative = false;
                for r in 0..s {
                    if mask & (1 << r) == 0 {
                        continue;
                    }
                    let minor = &minors[mask & !(1 << r)];
                    ysplit.clear();
                    ysplit.extend(minor.iter().map(|y| split(y.hi)));
                    for (x, ex) in cols[j][r].iter().enumerate() {
                        let (xh, xl) = if negative {
                            (-ex.hi, -ex.lo)
                        } else {
                            (ex.hi, ex.lo)
                        };
                        let xs = split(xh);
                        let zrow = &conv.zrows[x * conv.len_b..(x + 1) * conv.len_b];
                        for ((&z, y), &ys) in zrow.iter().zip(minor).zip(&ysplit) {
                            let p = xh * y.hi;
                            let pl = product_error(p, xs, ys) + (xh * y.lo + xl * y.hi);
                            let (sum, e) = two_sum(hi[z as usize], p);
                            hi[z as usize] = sum;
                            lo[z as usize] += e + pl;
                        }
                    }
                    negative = !negative;
                }
                minors[mask] = hi
                    .iter()
                    .zip(&lo)
                    .map(|(&h, &l)| {
                        let (hi, lo) = two_sum(h, l);
                        Twofold { hi, lo }
                    })
                    .collect();
            }
        }
        let scale = permanent(&maxabs, s);
        if !(scale.is_finite() && scale <= MAX_SCALE) {
            return None;
        }
        // (1 + ρ)-products over at most four factors: 2ρ covers the cross terms for ρ ≪ 1, and
        // the factor 2 the bound's own roundings.
        let uniform = 4.0 * rho * scale + TWOFOLD_UNDERFLOW_SLACK;
        let mut values = Vec::with_capacity(minors[full].len());
        let mut errors = Vec::with_capacity(minors[full].len());
        for (x, &mlt) in minors[full].iter().zip(&self.mult_det) {
            // fl(hi / mult): |lo|/mult ≤ u|hi|/mult plus one rounding, ≤ 3u|v| with margin.
            let v = x.hi / mlt;
            let e = uniform + 3.0 * u * v.abs();
            if !(v.is_finite() && e.is_finite()) {
                return None;
            }
            values.push(v);
            errors.push(e);
        }
        Some(BoundedCoefficients { values, errors })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::certify::DetKernel;
    use crate::test_support::{exact_bernstein, vertices_and_dyadic_points};
    use num_rational::BigRational;
    use num_traits::Signed;
    use rand::{Rng, SeedableRng};

    fn exact(x: f64) -> BigRational {
        crate::exact::rational(x).expect("finite")
    }

    /// Nets near the identity moved by up to `amplitude` (vertices too, so corners are not trivial),
    /// with weights in [1/2, 2] for rational ones.
    fn random_net(
        rng: &mut impl Rng,
        n: usize,
        d: u32,
        rational: bool,
        amplitude: f64,
    ) -> DenseNet {
        let mut net = DenseNet::identity(n, d);
        for p in net.points.iter_mut() {
            for c in p.iter_mut().take(n + 1) {
                *c += rng.random_range(-amplitude..amplitude);
            }
        }
        if rational {
            net.weights = (0..net.points.len())
                .map(|_| rng.random_range(0.5..2.0))
                .collect();
        }
        net
    }

    /// The twofold coefficients against exact arithmetic: at every vertex (where the Bernstein sum is
    /// one coefficient) and at random dyadic points, `|Σ c_K B_K(w) − exact(w)| ≤ Σ err_K B_K(w)`,
    /// with the exact value from [`crate::exact::jacobian_at`] (a pointwise evaluation of the stored
    /// map, not these coefficients); and, beyond the final rounding, the bound is at least 10¹⁰
    /// times tighter than the floating-point kernel's.
    #[test]
    fn twofold_coefficients_are_within_their_bound_of_the_exact_polynomial() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(12);
        for n in 1..=3usize {
            for d in 1..=4u32 {
                for rational in [false, true] {
                    let kernel = DetKernel::new(n, d, rational);
                    let m = n + 1;
                    let dd = kernel.det_degree();
                    for trial in 0..6 {
                        let amplitude = [0.02, 0.2, 0.6][trial % 3];
                        let net = random_net(&mut rng, n, d, rational, amplitude);
                        let tight = kernel.det_coefficients_twofold(&net).expect("in range");
                        let loose = kernel.det_coefficients(&net);
                        // Beyond the final rounding (3u|v|), the bound is 10¹⁰ times tighter.
                        let worst_loose = loose.errors.iter().copied().fold(0.0, f64::max);
                        for (v, e) in tight.values.iter().zip(&tight.errors) {
                            assert!(
                                *e <= 3.0 * UNIT_ROUNDOFF * v.abs() + worst_loose * 1e-10,
                                "n={n} d={d}: {e} for {v} vs {worst_loose}"
                            );
                        }
                        for w in &vertices_and_dyadic_points(&mut rng, m, 4) {
                            let (det, _) = crate::exact::jacobian_at(&net, w).expect("inside");
                            let exact_w: Vec<BigRational> = w.iter().map(|&x| exact(x)).collect();
                            let value = exact_bernstein(m, dd, &tight.values, &exact_w);
                            let bound = exact_bernstein(m, dd, &tight.errors, &exact_w);
                            assert!(
                                (value.clone() - det.clone()).abs() <= bound,
                                "n={n} d={d} rational={rational} at {w:?}: {} vs {}",
                                crate::exact::to_f64_signed(&value),
                                crate::exact::to_f64_signed(&det)
                            );
                        }
                    }
                }
            }
        }
    }

    /// Error-free transformations against exact rationals, including cancellation and operands
    /// of very different magnitude.
    #[test]
    fn two_sum_and_product_are_exact() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        for _ in 0..2000 {
            let a: f64 = rng.random_range(-1.0..1.0) * 2f64.powi(rng.random_range(-60..60));
            let b: f64 = if rng.random_bool(0.3) {
                -a * (1.0 + f64::EPSILON * f64::from(rng.random_range(-8..8)))
            } else {
                rng.random_range(-1.0..1.0) * 2f64.powi(rng.random_range(-60..60))
            };
            let (s, e) = two_sum(a, b);
            assert_eq!(exact(s) + exact(e), exact(a) + exact(b));
            let p = Twofold::product(a, b);
            assert_eq!(exact(p.hi) + exact(p.lo), exact(a) * exact(b));
            assert!(p.lo.abs() <= p.hi.abs() * UNIT_ROUNDOFF);
        }
    }
}

//! Exact arithmetic for the positivity layer (spec/validation.md §4.4): the last resort when the
//! floating-point certificate of [`crate::certify`] cannot decide, and the proof behind every
//! witness.
//!
//! Every finite double is a dyadic rational `m · 2^e`, so the certificate polynomial's Bernstein
//! coefficients are rationals computed from the stored numbers by additions and multiplications
//! only, and midpoint subdivision keeps them dyadic. Here they are integers: each row of the
//! determinant is scaled by a power of two that makes its entries integers, and the coefficients
//! by the least common multiple of the multinomials — positive factors, which change no sign. A
//! bisection multiplies a piece by `2^D` (`D` the polynomial's degree) instead of halving, then
//! divides out the common power of two. The sign of every coefficient is therefore exact, and the
//! decision of [`decide`] is a proof, not an estimate.
//!
//! Witnesses are proven independently of the coefficients: [`witness_at`] evaluates the stored
//! map's Jacobian pointwise from its definition (Bernstein sums at the point, then the
//! determinant) in exact dyadic arithmetic — or, at a vertex of a polynomial element, by Shewchuk's
//! exact orientation predicates — at exactly the point the report prints.
//!
//! # Why `num-bigint` and `num-rational`
//! Both are the rust-num project's maintained, pure-Rust big-number crates and are already in the
//! workspace's dependency tree, so they add no build time and no C toolchain (`rug` needs GMP).
//! Coefficients stay integers on purpose: `BigRational` would reduce by a gcd after every operation,
//! and the hot loop here is additions of numbers with a common denominator; witnesses use a small
//! dyadic type (`m · 2^e` in big integers) for the same reason, and `BigRational` only to round a
//! final value to a double.

use num_bigint::BigInt;
use num_rational::BigRational;
use num_traits::{One, Signed, ToPrimitive, Zero};

use ism_format::multi_index;

use crate::certify::{BoundedCoefficients, Decision, DenseNet, DetKernel};

/// Pieces the floating-point filter may use on one exact piece before the piece is bisected
/// exactly: enough to certify a piece whose difficulty is only rounding, small enough that a piece
/// at a true zero costs little.
const FILTER_PIECES: usize = 64;

/// Pieces the floating-point filter may use on the whole simplex, from the exactly computed
/// coefficients: rounded once, they carry bounds many orders tighter than the floating-point
/// kernel's, so most elements the kernel could not decide (minima down to 1e-12 of the scale) are
/// decided here by floating-point subdivision alone, without exact bisection.
const ROOT_FILTER_PIECES: usize = 1 << 12;

/// Deepest exact bisection. Corners are tracked in doubles, which hold the dyadic corners exactly
/// to about 52 bisections and approximately beyond; a witness is proven at the point actually
/// printed, so approximate corners cost at most a missed witness, never a false one.
pub const MAX_EXACT_DEPTH: u32 = 160;

/// Largest exact piece, in bits (coefficients × their longest length): integer de Casteljau adds up
/// to `D` bits per bisection, so deep pieces of high-degree elements grow; past 4 Mbit (512 KiB) a
/// piece is left undecided. With the depth limit this bounds the exact path's memory per thread to
/// about 80 MiB whatever the input.
pub const MAX_EXACT_PIECE_BITS: u64 = 1 << 22;

/// The exact value of a finite double as `(m, e)` with `x = m · 2^e`; `None` when not finite.
pub fn dyadic(x: f64) -> Option<(BigInt, i64)> {
    if !x.is_finite() {
        return None;
    }
    let bits = x.to_bits();
    let negative = bits >> 63 == 1;
    let biased = ((bits >> 52) & 0x7ff) as i64;
    let fraction = bits & ((1u64 << 52) - 1);
    let (m, e) = if biased == 0 {
        (fraction, -1074)
    } else {
        (fraction | (1u64 << 52), biased - 1075)
    };
    let m = BigInt::from(m);
    Some((if negative { -m } else { m }, e))
}

/// The exact rational value of a finite double.
pub fn rational(x: f64) -> Option<BigRational> {
    let (m, e) = dyadic(x)?;
    Some(if e >= 0 {
        BigRational::from_integer(m << e as usize)
    } else {
        BigRational::new(m, BigInt::one() << (-e) as usize)
    })
}

/// The double nearest a rational, never of the other sign: a value `≤ 0` gives a double `≤ 0`.
pub fn to_f64_signed(x: &BigRational) -> f64 {
    let f = x.to_f64().unwrap_or(if x.is_negative() {
        f64::NEG_INFINITY
    } else {
        f64::INFINITY
    });
    if x.is_positive() {
        f.max(0.0)
    } else if x.is_zero() {
        0.0
    } else {
        f.min(-0.0)
    }
}

/// `d! / (I₀! … Iₘ₋₁!)`, exactly.
fn multinomial(index: &[u32]) -> BigInt {
    let fact = |k: u32| (1..=k).fold(BigInt::one(), |a, x| a * x);
    let d: u32 = index.iter().sum();
    index.iter().fold(fact(d), |a, &e| a / fact(e))
}

/// [`multinomial`] in machine integers for degrees up to 30 (`30! < 2¹²⁸`), the big-integer one
/// beyond: the pointwise evaluation of a witness calls it for every term.
fn multinomial_small(index: &[u32]) -> BigInt {
    let d: u32 = index.iter().sum();
    if d > 30 {
        return multinomial(index);
    }
    let fact = |k: u32| (1..=u128::from(k)).product::<u128>();
    BigInt::from(index.iter().fold(fact(d), |a, &e| a / fact(e)))
}

fn multinomials(m: usize, d: u32) -> Vec<BigInt> {
    multi_index::all(m, d).chunks(m).map(multinomial).collect()
}

/// Integer tables of one kernel: the multinomials and the factors `L / C(D; K)` that turn the
/// convolution's monomial coefficients into integer multiples of the Bernstein coefficients.
#[derive(Clone, Debug)]
pub struct ExactTables {
    mult_first: Vec<BigInt>,
    mult_entry: Vec<BigInt>,
    to_bernstein: Vec<BigInt>,
}

impl ExactTables {
    /// Builds the tables for `kernel`.
    pub fn new(kernel: &DetKernel) -> ExactTables {
        let m = kernel.n + 1;
        let d = kernel.degree;
        let mult_det = multinomials(m, kernel.det_degree);
        let lcm = mult_det
            .iter()
            .fold(BigInt::one(), |a, x| num_integer::Integer::lcm(&a, x));
        ExactTables {
            mult_first: multinomials(m, d),
            mult_entry: multinomials(m, d - 1),
            to_bernstein: mult_det.iter().map(|x| &lcm / x).collect(),
        }
    }
}

/// Integer multiples (one positive factor for all) of the Bernstein coefficients of the certificate
/// polynomial of `net`; `None` when a stored number is not finite.
///
/// # Panics
/// When the net does not match the kernel's dimension, degree and kind.
pub fn coefficients(
    kernel: &DetKernel,
    tables: &ExactTables,
    net: &DenseNet,
) -> Option<Vec<BigInt>> {
    let m = kernel.n + 1;
    assert_eq!(net.n, kernel.n);
    assert_eq!(net.points.len(), multi_index::count(m, kernel.degree));
    assert_eq!(net.is_rational(), kernel.rational);
    let s = kernel.size;
    let count = net.points.len();
    // Row r: coordinate r + 1 (polynomial) or component r of v_I = q_I·(1, b_I) (rational), each
    // exactly as m·2^e, then scaled by the row's smallest power of two into integers.
    let mut rows: Vec<Vec<BigInt>> = Vec::with_capacity(s);
    for r in 0..s {
        let mut exact = Vec::with_capacity(count);
        for i in 0..count {
            let value = if kernel.rational {
                let (mq, eq) = dyadic(net.weights[i])?;
                if r == 0 {
                    (mq, eq)
                } else {
                    let (mb, eb) = dyadic(net.points[i][r])?;
                    (mq * mb, eq + eb)
                }
            } else {
                dyadic(net.points[i][r + 1])?
            };
            exact.push(value);
        }
        let low = exact
            .iter()
            .filter(|(x, _)| !x.is_zero())
            .map(|&(_, e)| e)
            .min()
            .unwrap_or(0);
        rows.push(
            exact
                .into_iter()
                .map(|(x, e)| x << (e - low) as usize)
                .collect(),
        );
    }
    // Columns in monomial scaling (the float kernel's, without the common factor d of the
    // derivative columns, a positive constant).
    let mut cols: Vec<Vec<Vec<BigInt>>> = Vec::with_capacity(s);
    if kernel.rational {
        cols.push(
            rows.iter()
                .map(|row| {
                    row.iter()
                        .zip(&tables.mult_first)
                        .map(|(x, c)| x * c)
                        .collect()
                })
                .collect(),
        );
    }
    for k in 1..=kernel.n {
        cols.push(
            rows.iter()
                .map(|row| {
                    kernel
                        .shift
                        .iter()
                        .zip(&tables.mult_entry)
                        .map(|(sh, c)| (&row[sh[k] as usize] - &row[sh[0] as usize]) * c)
                        .collect()
                })
                .collect(),
        );
    }
    // Laplace expansion from the last column, as in the float kernel.
    let full = (1usize << s) - 1;
    let mut minors: Vec<Vec<BigInt>> = vec![Vec::new(); full + 1];
    for r in 0..s {
        minors[1 << r] = std::mem::take(&mut cols[s - 1][r]);
    }
    for j in (0..s - 1).rev() {
        let rows_here = s - j;
        let conv = &kernel.conv[j];
        for mask in 0..=full {
            if (mask as u32).count_ones() as usize != rows_here {
                continue;
            }
            let mut out = vec![BigInt::zero(); conv.out_len];
            let mut positive = true;
            for r in 0..s {
                if mask & (1 << r) == 0 {
                    continue;
                }
                let minor = &minors[mask & !(1 << r)];
                for (x, ex) in cols[j][r].iter().enumerate() {
                    if ex.is_zero() {
                        continue;
                    }
                    let zrow = &conv.zrows[x * conv.len_b..(x + 1) * conv.len_b];
                    for (&z, my) in zrow.iter().zip(minor) {
                        if positive {
                            out[z as usize] += ex * my;
                        } else {
                            out[z as usize] -= ex * my;
                        }
                    }
                }
                positive = !positive;
            }
            minors[mask] = out;
        }
    }
    Some(
        std::mem::take(&mut minors[full])
            .into_iter()
            .zip(&tables.to_bernstein)
            .map(|(x, f)| x * f)
            .collect(),
    )
}

/// Divides out the largest power of two common to all coefficients (keeps numbers short).
fn reduce(values: &mut [BigInt]) {
    let shift = values
        .iter()
        .filter_map(|x| x.trailing_zeros())
        .min()
        .unwrap_or(0);
    if shift > 0 {
        for x in values.iter_mut() {
            *x >>= shift as usize;
        }
    }
}

/// Splits the simplex at the midpoint of edge `(a, b)`: integer multiples of the coefficients of
/// the child keeping `a` and of the child keeping `b` (each child scaled by its own positive
/// factor).
fn bisect(kernel: &DetKernel, values: &[BigInt], a: usize, b: usize) -> (Vec<BigInt>, Vec<BigInt>) {
    let (a, b, swap) = if a < b { (a, b, false) } else { (b, a, true) };
    let lines = kernel.edge_lines(a, b);
    let degree = kernel.det_degree as usize;
    let mut left = vec![BigInt::zero(); values.len()];
    let mut right = vec![BigInt::zero(); values.len()];
    let mut t: Vec<BigInt> = Vec::new();
    for line in lines {
        let len = line.len();
        t.clear();
        t.extend(line.iter().map(|&r| values[r as usize].clone()));
        // De Casteljau at t = 1/2 without the halvings: after step s every entry is 2^s times the
        // true one, so multiplying by 2^(D − s) brings the whole piece to the common scale 2^D.
        left[line[0] as usize] = &t[0] << degree;
        right[line[len - 1] as usize] = &t[len - 1] << degree;
        for step in 1..len {
            for j in 0..len - step {
                let next = t[j + 1].clone();
                t[j] += next;
            }
            left[line[step] as usize] = &t[0] << (degree - step);
            right[line[len - 1 - step] as usize] = &t[len - 1 - step] << (degree - step);
        }
    }
    reduce(&mut left);
    reduce(&mut right);
    if swap {
        (right, left)
    } else {
        (left, right)
    }
}

/// Doubles approximating integer coefficients up to one positive factor, with rigorous bounds: the
/// input to the floating-point filter.
fn to_float(values: &[BigInt]) -> BoundedCoefficients {
    // Keep the largest magnitude near 2^500: far from overflow through subdivision, and anything
    // 2^-1000 smaller than it is below every error bound anyway.
    let bits = values.iter().map(|x| x.bits()).max().unwrap_or(0);
    let shift = bits.saturating_sub(500) as usize;
    let mut out = Vec::with_capacity(values.len());
    let mut errors = Vec::with_capacity(values.len());
    for x in values {
        // `>>` rounds toward −∞ (error < 1); `to_f64` is within 2 ulps (it rounds the top 64 bits).
        let v = (x >> shift).to_f64().unwrap_or(f64::NAN);
        out.push(v);
        errors.push(v.abs() * f64::EPSILON * 2.0 + 2.0);
    }
    BoundedCoefficients {
        values: out,
        errors,
    }
}

/// A point of the closed simplex where the certificate polynomial is `≤ 0`, proven exactly.
#[derive(Clone, Debug, PartialEq)]
pub struct ExactWitness {
    /// Barycentric coordinates as printed: the proven point is `(w₁ … wₙ)` with `w₀ = 1 − Σ wᵢ`
    /// (equal to the printed `w₀` for corners of pieces to depth 50, rounded beyond).
    pub point: Vec<f64>,
    /// `det DX` there (reduced coordinates), rounded to a double of the proven sign.
    pub det: f64,
    /// The certificate polynomial there (`det DX`, or `N` for rational stages), likewise rounded.
    pub polynomial_value: f64,
}

/// An exact dyadic number `m · 2^e`: sums and products of doubles without rounding and without
/// the gcd a rational type would take after every operation.
#[derive(Clone, Debug)]
struct Dyadic {
    m: BigInt,
    e: i64,
}

impl Dyadic {
    fn zero() -> Dyadic {
        Dyadic {
            m: BigInt::zero(),
            e: 0,
        }
    }

    fn from_f64(x: f64) -> Option<Dyadic> {
        let (m, e) = dyadic(x)?;
        Some(Dyadic { m, e })
    }

    fn from_int(x: BigInt) -> Dyadic {
        Dyadic { m: x, e: 0 }
    }

    fn add(&self, other: &Dyadic) -> Dyadic {
        if self.m.is_zero() {
            return other.clone();
        }
        if other.m.is_zero() {
            return self.clone();
        }
        let e = self.e.min(other.e);
        Dyadic {
            m: (&self.m << (self.e - e) as usize) + (&other.m << (other.e - e) as usize),
            e,
        }
    }

    fn neg(&self) -> Dyadic {
        Dyadic {
            m: -&self.m,
            e: self.e,
        }
    }

    fn sub(&self, other: &Dyadic) -> Dyadic {
        self.add(&other.neg())
    }

    fn mul(&self, other: &Dyadic) -> Dyadic {
        if self.m.is_zero() || other.m.is_zero() {
            return Dyadic::zero();
        }
        Dyadic {
            m: &self.m * &other.m,
            e: self.e + other.e,
        }
    }

    /// The nearest double (ties to even), when it is a normal number; `None` otherwise (the caller
    /// converts through [`to_f64_signed`]). Same result as the rational conversion, without its
    /// gcd: a dyadic needs only a shift and one rounding.
    fn to_f64_normal(&self) -> Option<f64> {
        if self.m.is_zero() {
            return Some(0.0);
        }
        let mag = self.m.magnitude();
        let bits = mag.bits() as i64;
        let lead = bits - 1 + self.e;
        if !(-1021..=1022).contains(&lead) {
            return None;
        }
        let (top, scale) = if bits <= 53 {
            (mag.to_u64()?, self.e)
        } else {
            let shift = (bits - 53) as u64;
            let mut top = (mag >> shift).to_u64()?;
            let rem = mag - (num_bigint::BigUint::from(top) << shift);
            let half = num_bigint::BigUint::one() << (shift - 1);
            if rem > half || (rem == half && top & 1 == 1) {
                top += 1;
            }
            (top, self.e + shift as i64)
        };
        // top < 2^54 is exact in f64; scale by 2^scale in two exact steps (each factor normal).
        let a = scale / 2;
        let b = scale - a;
        let pow = |k: i64| f64::from_bits(((k + 1023) as u64) << 52);
        let f = top as f64 * pow(a) * pow(b);
        Some(if self.m.is_negative() { -f } else { f })
    }

    fn to_rational(&self) -> BigRational {
        if self.e >= 0 {
            BigRational::from_integer(&self.m << self.e as usize)
        } else {
            BigRational::new(self.m.clone(), BigInt::one() << (-self.e) as usize)
        }
    }
}

/// The stored map's Jacobian determinant at `point`, exactly, from the definitions: for a
/// polynomial stage `det DX`; for a rational one `(N, Q)` with `det DX = N / Q^{n+1}`.
/// `point` is read as `(w₁ … wₙ)` with `w₀ = 1 − Σ`; `None` when that point is outside the closed
/// simplex or a number is not finite.
pub fn jacobian_at(net: &DenseNet, point: &[f64]) -> Option<(BigRational, BigRational)> {
    let (value, q) = jacobian_dyadic(net, point)?;
    Some((value.to_rational(), q.to_rational()))
}

fn jacobian_dyadic(net: &DenseNet, point: &[f64]) -> Option<(Dyadic, Dyadic)> {
    let n = net.n;
    let m = n + 1;
    let d = net.degree;
    let mut w = vec![Dyadic::zero(); m];
    let mut rest = Dyadic::from_int(BigInt::one());
    for i in 1..m {
        w[i] = Dyadic::from_f64(point[i])?;
        if w[i].m.is_negative() {
            return None;
        }
        rest = rest.sub(&w[i]);
    }
    if rest.m.is_negative() {
        return None;
    }
    w[0] = rest;
    // Powers of each coordinate up to d.
    let powers: Vec<Vec<Dyadic>> = w
        .iter()
        .map(|x| {
            let mut p = vec![Dyadic::from_int(BigInt::one())];
            for k in 1..=d as usize {
                let next = p[k - 1].mul(x);
                p.push(next);
            }
            p
        })
        .collect();
    // B_J(w), or None when it vanishes (a coordinate 0 with a positive exponent): at a corner or
    // on a face most terms do, and skipping them is what keeps a witness cheap.
    let bernstein = |index: &[u32]| -> Option<Dyadic> {
        if index.iter().zip(&w).any(|(&e, x)| e > 0 && x.m.is_zero()) {
            return None;
        }
        Some(
            index
                .iter()
                .enumerate()
                .fold(Dyadic::from_int(multinomial_small(index)), |a, (i, &e)| {
                    a.mul(&powers[i][e as usize])
                }),
        )
    };
    // v_I: rows of the homogeneous vector (rational: q(1, b); polynomial: b₁ … bₙ).
    let rational_stage = net.is_rational();
    let size = if rational_stage { m } else { n };
    let component = |i: usize, r: usize| -> Option<Dyadic> {
        if rational_stage {
            let q = Dyadic::from_f64(net.weights[i])?;
            Some(if r == 0 {
                q
            } else {
                q.mul(&Dyadic::from_f64(net.points[i][r])?)
            })
        } else {
            Dyadic::from_f64(net.points[i][r + 1])
        }
    };
    let mut matrix = vec![vec![Dyadic::zero(); size]; size];
    let mut q_value = Dyadic::from_int(BigInt::one());
    let mut col = 0;
    if rational_stage {
        // Column 0: V(w) itself.
        for (i, index) in multi_index::all(m, d).chunks(m).enumerate() {
            let Some(b) = bernstein(index) else { continue };
            for (r, row) in matrix.iter_mut().enumerate() {
                row[0] = row[0].add(&component(i, r)?.mul(&b));
            }
        }
        q_value = matrix[0][0].clone();
        col = 1;
    }
    // Columns ∂V/∂w_k − ∂V/∂w₀ = d Σ_J (v_{J+e_k} − v_{J+e₀}) B_J(w), |J| = d − 1 (the positive
    // factor d is applied once, to the determinant's value).
    let lower = multi_index::all(m, d - 1);
    let mut shifted = vec![0u32; m];
    for k in 1..m {
        for index in lower.chunks(m) {
            let Some(b) = bernstein(index) else { continue };
            shifted.copy_from_slice(index);
            shifted[k] += 1;
            let ik = multi_index::rank(&shifted);
            shifted[k] -= 1;
            shifted[0] += 1;
            let i0 = multi_index::rank(&shifted);
            for (r, row) in matrix.iter_mut().enumerate() {
                row[col] = row[col].add(&component(ik, r)?.sub(&component(i0, r)?).mul(&b));
            }
        }
        col += 1;
    }
    let scale = Dyadic::from_int(num_traits::pow(BigInt::from(d), n));
    Some((determinant(&matrix).mul(&scale), q_value))
}

/// Determinant by cofactor expansion (size ≤ 4).
fn determinant(a: &[Vec<Dyadic>]) -> Dyadic {
    fn rec(a: &[Vec<Dyadic>], rows: &[usize], col: usize) -> Dyadic {
        if rows.is_empty() {
            return Dyadic::from_int(BigInt::one());
        }
        let mut sum = Dyadic::zero();
        for (pos, &r) in rows.iter().enumerate() {
            if a[r][col].m.is_zero() {
                continue;
            }
            let rest: Vec<usize> = rows.iter().copied().filter(|&x| x != r).collect();
            let term = a[r][col].mul(&rec(a, &rest, col + 1));
            sum = if pos % 2 == 0 {
                sum.add(&term)
            } else {
                sum.sub(&term)
            };
        }
        sum
    }
    let rows: Vec<usize> = (0..a.len()).collect();
    rec(a, &rows, 0)
}

/// Smallest magnitude of a nonzero coordinate for which Shewchuk's predicates are exact here: with
/// every nonzero input at least 2^-200, no product or expansion term of `orient2d`/`orient3d`
/// reaches the subnormal range, where the adaptive predicates lose exactness.
const PREDICATE_FLOOR: f64 = 6.223015277861142e-61; // 2^-200

/// Exact sign of `det DX` at vertex `i` of a polynomial element by Shewchuk's adaptive predicates
/// (`robust`): there `det DX = dⁿ det[P₁ − P₀ … Pₙ − P₀]` with `P_k` the control point at
/// `(d − 1)eᵢ + e_k`, an orientation. Returns the determinant (sign exact, magnitude approximate),
/// or `None` when the predicates do not apply (dimension, rational stage, tiny inputs).
fn vertex_det_by_predicate(net: &DenseNet, vertex: usize) -> Option<f64> {
    let n = net.n;
    if net.is_rational() || !(1..=3).contains(&n) {
        return None;
    }
    let m = n + 1;
    let d = net.degree;
    let mut index = vec![0u32; m];
    let p = |k: usize, index: &mut Vec<u32>| -> [f64; 3] {
        index.iter_mut().for_each(|x| *x = 0);
        index[vertex] = d - 1;
        index[k] += 1;
        let b = net.points[multi_index::rank(index)];
        [b[1], b[2], b[3]]
    };
    let pts: Vec<[f64; 3]> = (0..m).map(|k| p(k, &mut index)).collect();
    let small = pts
        .iter()
        .flat_map(|x| &x[..n])
        .any(|&x| x != 0.0 && !(x.abs() >= PREDICATE_FLOOR && x.is_finite()));
    if small {
        return None;
    }
    let scale = f64::from(d).powi(n as i32);
    let det = match n {
        1 => {
            // det = x₁ − x₀: its sign is the comparison.
            let diff = pts[1][0] - pts[0][0];
            if pts[1][0] > pts[0][0] {
                diff.max(f64::MIN_POSITIVE)
            } else if pts[1][0] < pts[0][0] {
                diff.min(-f64::MIN_POSITIVE)
            } else {
                0.0
            }
        }
        2 => {
            let c = |x: [f64; 3]| robust::Coord { x: x[0], y: x[1] };
            // det[P₁ − P₀, P₂ − P₀] = orient2d(P₁, P₂, P₀).
            robust::orient2d(c(pts[1]), c(pts[2]), c(pts[0]))
        }
        _ => {
            let c = |x: [f64; 3]| robust::Coord3D {
                x: x[0],
                y: x[1],
                z: x[2],
            };
            // robust's orient3d(a, b, c, d) = det[a − d; b − d; c − d] (checked against the dyadic
            // evaluation in the tests), so det[P₁ − P₀, P₂ − P₀, P₃ − P₀] = orient3d(P₁, P₂, P₃, P₀).
            robust::orient3d(c(pts[1]), c(pts[2]), c(pts[3]), c(pts[0]))
        }
    };
    Some(det * scale)
}

/// The witness at `point` if the certificate polynomial is exactly `≤ 0` there.
pub fn witness_at(net: &DenseNet, point: &[f64]) -> Option<ExactWitness> {
    let m = net.n + 1;
    // At a vertex of the simplex, an exact orientation predicate decides (the common case: a fold
    // shows first at a corner).
    if let Some(vertex) = (0..m).find(|&i| point[i] == 1.0) {
        if point
            .iter()
            .enumerate()
            .all(|(j, &x)| j == vertex || x == 0.0)
        {
            if let Some(det) = vertex_det_by_predicate(net, vertex) {
                // The sign is exact; a zero is reported as 0, a negative value as it came.
                let det = if det == 0.0 { 0.0 } else { det };
                return (det <= 0.0).then(|| ExactWitness {
                    point: point.to_vec(),
                    det,
                    polynomial_value: det,
                });
            }
        }
    }
    let (value, q) = jacobian_dyadic(net, point)?;
    if value.m.is_positive() {
        return None;
    }
    let det = if net.is_rational() {
        let q = q.to_rational();
        let mut qn = BigRational::one();
        for _ in 0..=net.n {
            qn *= &q;
        }
        to_f64_signed(&(value.to_rational() / qn))
    } else {
        // Polynomial stage: the certificate polynomial is det DX itself (one conversion).
        value
            .to_f64_normal()
            .unwrap_or_else(|| to_f64_signed(&value.to_rational()))
    };
    let value = if net.is_rational() {
        value
            .to_f64_normal()
            .unwrap_or_else(|| to_f64_signed(&value.to_rational()))
    } else {
        det
    };
    Some(ExactWitness {
        point: point.to_vec(),
        det,
        polynomial_value: value,
    })
}

/// Outcome of the exact decision.
#[derive(Clone, Debug, PartialEq)]
pub enum ExactDecision {
    /// Every piece has only positive coefficients (or was certified by the filter).
    Positive {
        /// Deepest piece.
        depth: u32,
        /// Pieces examined exactly.
        pieces: usize,
    },
    /// A proven witness.
    NonPositive(ExactWitness),
    /// The piece budget ran out.
    Undetermined {
        /// Deepest piece.
        depth: u32,
        /// Pieces examined exactly.
        pieces: usize,
    },
}

/// Decides the sign of the certificate polynomial of `net` on the closed simplex exactly, with at
/// most `budget` exact pieces. Each exact piece is first offered to the floating-point certificate
/// (a rigorous bound, so a certified piece is positive); only what it cannot settle is bisected in
/// integers.
pub fn decide(kernel: &DetKernel, net: &DenseNet, budget: usize) -> ExactDecision {
    let tables = kernel.exact_tables();
    let Some(root) = coefficients(kernel, tables, net) else {
        return ExactDecision::Undetermined {
            depth: 0,
            pieces: 0,
        };
    };
    let m = kernel.n + 1;
    struct Piece {
        values: Vec<BigInt>,
        corners: [[f64; 4]; 4],
        depth: u32,
    }
    let mut stack = vec![Piece {
        values: root,
        corners: crate::certify::unit_corners(m),
        depth: 0,
    }];
    let mut pieces = 0usize;
    let mut deepest = 0u32;
    let mut undecided = false;
    while let Some(piece) = stack.pop() {
        pieces += 1;
        deepest = deepest.max(piece.depth);
        // Corner coefficients are exact values of the polynomial (up to the piece's factor).
        let mut corner_unproven = false;
        for i in 0..m {
            if !piece.values[kernel.vertex_rank[i]].is_positive() {
                match witness_at(net, &piece.corners[i][..m]) {
                    Some(w) => return ExactDecision::NonPositive(w),
                    // The printed corner is a rounding of the true one: keep looking.
                    None => corner_unproven = true,
                }
            }
        }
        if !corner_unproven && piece.values.iter().all(Signed::is_positive) {
            continue;
        }
        if !corner_unproven {
            let filtered = to_float(&piece.values);
            let filter = if piece.depth == 0 {
                ROOT_FILTER_PIECES
            } else {
                FILTER_PIECES
            };
            match kernel.decide_piece(
                filtered,
                piece.corners,
                piece.depth,
                filter,
                MAX_EXACT_DEPTH,
            ) {
                Decision::Positive { .. } => continue,
                Decision::NonPositive { point, .. } => {
                    if let Some(w) = witness_at(net, &point) {
                        return ExactDecision::NonPositive(w);
                    }
                }
                Decision::Undetermined { .. } => {}
            }
        }
        let size =
            piece.values.iter().map(BigInt::bits).max().unwrap_or(0) * piece.values.len() as u64;
        if pieces + stack.len() >= budget
            || piece.depth >= MAX_EXACT_DEPTH
            || size > MAX_EXACT_PIECE_BITS
        {
            undecided = true;
            continue;
        }
        let (a, b) = crate::certify::longest_edge(&piece.corners, m);
        let (left, right) = bisect(kernel, &piece.values, a, b);
        let (ca, cb) = crate::certify::split_corners(&piece.corners, a, b, m);
        stack.push(Piece {
            values: right,
            corners: cb,
            depth: piece.depth + 1,
        });
        stack.push(Piece {
            values: left,
            corners: ca,
            depth: piece.depth + 1,
        });
    }
    if undecided {
        ExactDecision::Undetermined {
            depth: deepest,
            pieces,
        }
    } else {
        ExactDecision::Positive {
            depth: deepest,
            pieces,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// The orientation predicate at a vertex and the dyadic evaluation agree in sign, on nets that
    /// fold at a vertex and nets that do not, in 1D, 2D and 3D.
    #[test]
    fn vertex_predicate_agrees_with_the_dyadic_evaluation() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        for n in 1..=3usize {
            for d in 1..=4u32 {
                for _ in 0..200 {
                    let mut net = DenseNet::identity(n, d);
                    for p in net.points.iter_mut() {
                        for c in p.iter_mut().take(n + 1) {
                            *c += rng.random_range(-0.4..0.4);
                        }
                    }
                    for vertex in 0..=n {
                        let mut point = vec![0.0; n + 1];
                        point[vertex] = 1.0;
                        let by_predicate = vertex_det_by_predicate(&net, vertex).unwrap();
                        let (exact, _) = jacobian_dyadic(&net, &point).unwrap();
                        assert_eq!(
                            by_predicate.partial_cmp(&0.0),
                            exact.m.sign().cmp(&num_bigint::Sign::NoSign).into(),
                            "n={n} d={d} vertex {vertex}: {by_predicate} vs {:?}",
                            exact.to_rational()
                        );
                        let rel = (by_predicate - to_f64_signed(&exact.to_rational())).abs();
                        assert!(rel <= 1e-9 * by_predicate.abs().max(1e-300), "{rel}");
                    }
                }
            }
        }
    }

    /// The dyadic-to-double conversion against the rational one (correctly rounded), on values
    /// with long mantissas, exact ties and both signs.
    #[test]
    fn dyadic_conversion_matches_the_rational_one() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(8);
        for _ in 0..5000 {
            let bits = rng.random_range(1..200u32);
            let mut m = BigInt::zero();
            for _ in 0..bits.div_ceil(32) {
                m = (m << 32) + BigInt::from(rng.random::<u32>());
            }
            m >>= (bits.div_ceil(32) * 32 - bits) as usize;
            if rng.random_bool(0.3) {
                // An exact tie: 53 significant bits, then a single 1 bit.
                m = (m >> 60usize << 60usize) + (BigInt::one() << 59usize);
            }
            if rng.random_bool(0.5) {
                m = -m;
            }
            let d = Dyadic {
                m,
                e: rng.random_range(-1200..1100),
            };
            let reference = to_f64_signed(&d.to_rational());
            if let Some(f) = d.to_f64_normal() {
                assert_eq!(f.to_bits(), reference.to_bits(), "{d:?}");
            }
        }
    }
}

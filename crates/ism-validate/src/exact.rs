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
//! determinant) in rational arithmetic, at exactly the point the report prints.
//!
//! # Why `num-bigint` and `num-rational`
//! Both are the rust-num project's maintained, pure-Rust big-number crates and are already in the
//! workspace's dependency tree, so they add no build time and no C toolchain (`rug` needs GMP).
//! Coefficients stay integers on purpose: `BigRational` would reduce by a gcd after every operation,
//! and the hot loop here is additions of numbers with a common denominator. `BigRational` is used
//! only for the pointwise witness, where clarity matters more than speed.

use num_bigint::BigInt;
use num_rational::BigRational;
use num_traits::{One, Signed, ToPrimitive, Zero};

use ism_format::multi_index;

use crate::certify::{BoundedCoefficients, Decision, DenseNet, DetKernel};

/// Pieces the floating-point filter may use on one exact piece before the piece is bisected
/// exactly: enough to certify a piece whose difficulty is only rounding, small enough that a piece
/// at a true zero costs little.
const FILTER_PIECES: usize = 64;

/// Deepest exact bisection. Corners are tracked in doubles, which hold the dyadic corners exactly
/// to about 52 bisections and approximately beyond; a witness is proven at the point actually
/// printed, so approximate corners cost at most a missed witness, never a false one.
pub const MAX_EXACT_DEPTH: u32 = 160;

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
        f.max(f64::MIN_POSITIVE * f64::EPSILON)
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
    /// Barycentric coordinates as printed; `w₀ = 1 − (w₁ + … + wₙ)` holds exactly.
    pub point: Vec<f64>,
    /// `det DX` there (reduced coordinates), rounded toward nothing positive.
    pub det: f64,
    /// The certificate polynomial there (`det DX`, or `N` for rational stages), likewise rounded.
    pub polynomial_value: f64,
}

/// The stored map's Jacobian determinant at `point`, exactly, from the definitions: for a
/// polynomial stage `det DX`; for a rational one `(N, Q)` with `det DX = N / Q^{n+1}`.
/// `point` is read as `(w₁ … wₙ)` with `w₀ = 1 − Σ`; `None` when that point is outside the closed
/// simplex or a number is not finite.
pub fn jacobian_at(net: &DenseNet, point: &[f64]) -> Option<(BigRational, BigRational)> {
    let n = net.n;
    let m = n + 1;
    let d = net.degree;
    let mut w = vec![BigRational::zero(); m];
    let mut rest = BigRational::one();
    for i in 1..m {
        w[i] = rational(point[i])?;
        if w[i].is_negative() {
            return None;
        }
        rest -= &w[i];
    }
    if rest.is_negative() {
        return None;
    }
    w[0] = rest;
    // Powers of each coordinate up to d.
    let powers: Vec<Vec<BigRational>> = w
        .iter()
        .map(|x| {
            let mut p = vec![BigRational::one()];
            for k in 1..=d as usize {
                let next = &p[k - 1] * x;
                p.push(next);
            }
            p
        })
        .collect();
    let bernstein = |index: &[u32]| -> BigRational {
        index.iter().enumerate().fold(
            BigRational::from_integer(multinomial(index)),
            |a, (i, &e)| a * &powers[i][e as usize],
        )
    };
    // v_I: rows of the homogeneous vector (rational: q(1, b); polynomial: b₁ … bₙ).
    let rational_stage = net.is_rational();
    let size = if rational_stage { m } else { n };
    let component = |i: usize, r: usize| -> Option<BigRational> {
        if rational_stage {
            let q = rational(net.weights[i])?;
            Some(if r == 0 {
                q
            } else {
                q * rational(net.points[i][r])?
            })
        } else {
            rational(net.points[i][r + 1])
        }
    };
    let all = multi_index::all(m, d);
    let lower = multi_index::all(m, d - 1);
    let mut matrix = vec![vec![BigRational::zero(); size]; size];
    let mut q_value = BigRational::one();
    let mut col = 0;
    if rational_stage {
        // Column 0: V(w) itself.
        for (i, index) in all.chunks(m).enumerate() {
            let b = bernstein(index);
            for (r, row) in matrix.iter_mut().enumerate() {
                row[0] += component(i, r)? * &b;
            }
        }
        q_value = matrix[0][0].clone();
        col = 1;
    }
    // Columns ∂V/∂w_k − ∂V/∂w₀ = d Σ_J (v_{J+e_k} − v_{J+e₀}) B_J(w), |J| = d − 1.
    let mut shifted = vec![0u32; m];
    for k in 1..m {
        for index in lower.chunks(m) {
            let b = bernstein(index) * BigRational::from_integer(BigInt::from(d));
            shifted.copy_from_slice(index);
            shifted[k] += 1;
            let ik = multi_index::rank(&shifted);
            shifted[k] -= 1;
            shifted[0] += 1;
            let i0 = multi_index::rank(&shifted);
            for (r, row) in matrix.iter_mut().enumerate() {
                row[col] += (component(ik, r)? - component(i0, r)?) * &b;
            }
        }
        col += 1;
    }
    Some((determinant(matrix), q_value))
}

/// Determinant by cofactor expansion (size ≤ 4).
fn determinant(a: Vec<Vec<BigRational>>) -> BigRational {
    fn rec(a: &[Vec<BigRational>], rows: &[usize], col: usize) -> BigRational {
        if rows.is_empty() {
            return BigRational::one();
        }
        let mut sum = BigRational::zero();
        for (pos, &r) in rows.iter().enumerate() {
            if a[r][col].is_zero() {
                continue;
            }
            let rest: Vec<usize> = rows.iter().copied().filter(|&x| x != r).collect();
            let term = &a[r][col] * rec(a, &rest, col + 1);
            if pos % 2 == 0 {
                sum += term;
            } else {
                sum -= term;
            }
        }
        sum
    }
    let rows: Vec<usize> = (0..a.len()).collect();
    rec(&a, &rows, 0)
}

/// The witness at `point` if the certificate polynomial is exactly `≤ 0` there.
pub fn witness_at(net: &DenseNet, point: &[f64]) -> Option<ExactWitness> {
    let (value, q) = jacobian_at(net, point)?;
    if value.is_positive() {
        return None;
    }
    let det = if net.is_rational() {
        let mut qn = BigRational::one();
        for _ in 0..=net.n {
            qn *= &q;
        }
        &value / qn
    } else {
        value.clone()
    };
    Some(ExactWitness {
        point: point.to_vec(),
        det: to_f64_signed(&det),
        polynomial_value: to_f64_signed(&value),
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
            match kernel.decide_piece(filtered, piece.corners, piece.depth, FILTER_PIECES) {
                Decision::Positive { .. } => continue,
                Decision::NonPositive { point, .. } => {
                    if let Some(w) = witness_at(net, &point) {
                        return ExactDecision::NonPositive(w);
                    }
                }
                Decision::Undetermined { .. } => {}
            }
        }
        if pieces + stack.len() >= budget || piece.depth >= MAX_EXACT_DEPTH {
            undecided = true;
            continue;
        }
        let (a, b) = crate::certify::longest_edge(&piece.corners, m);
        let (left, right) = bisect(kernel, &piece.values, a, b);
        let mut mid = [0.0; 4];
        for (c, x) in mid.iter_mut().enumerate().take(m) {
            *x = 0.5 * (piece.corners[a][c] + piece.corners[b][c]);
        }
        let mut ca = piece.corners;
        ca[b] = mid;
        let mut cb = piece.corners;
        cb[a] = mid;
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

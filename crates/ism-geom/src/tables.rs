//! Per-`(m, d)` index tables shared by every local stage of that shape: exponents and multinomial
//! coefficients of the canonical multi-index order, and the ranks of `K + e_j` for the
//! degree-`d − 1` indices `K` (the partial derivatives). Built once, on first use, and kept for the
//! life of the process (at most `4 × 17` small tables).

use std::sync::OnceLock;

use ism_format::multi_index;

use crate::{MAX_DEGREE, MAX_VARS};

/// Index tables for `m` variables and degree `d`.
#[derive(Debug)]
pub(crate) struct Tables {
    /// Exponents of every degree-`d` index, canonical order.
    pub exps: Vec<[u8; MAX_VARS]>,
    /// `d! / (I_0! … I_{m−1}!)`.
    pub multinom: Vec<f64>,
    /// Exponents of every degree-`d − 1` index (empty for `d = 0`).
    pub lower_exps: Vec<[u8; MAX_VARS]>,
    /// Multinomials of the degree-`d − 1` indices.
    pub lower_multinom: Vec<f64>,
    /// `up[r][j]` = rank of `K_r + e_j` among the degree-`d` indices.
    pub up: Vec<[u32; MAX_VARS]>,
    /// The identity net's control point `I / d` of every degree-`d` index (coordinates past `m`
    /// zero), as a stage's net is filled where no record gives the point.
    pub identity: Vec<[f64; MAX_VARS]>,
    /// The support of every degree-`d` index: bit `i` set where `I_i > 0` (the local positions of
    /// the face owning the control point).
    pub support: Vec<u8>,
}

static TABLES: [[OnceLock<Tables>; MAX_DEGREE as usize + 1]; MAX_VARS + 1] =
    [const { [const { OnceLock::new() }; MAX_DEGREE as usize + 1] }; MAX_VARS + 1];

pub(crate) fn multinomial(exps: &[u32]) -> f64 {
    let d: u32 = exps.iter().sum();
    let mut acc = 1.0f64;
    let mut used = 0u64;
    for &e in exps {
        acc *= multi_index::binomial(u64::from(d) - used, u64::from(e)) as f64;
        used += u64::from(e);
    }
    acc
}

fn list(m: usize, d: u32) -> (Vec<[u8; MAX_VARS]>, Vec<f64>) {
    let flat = multi_index::all(m, d);
    let mut exps = Vec::with_capacity(flat.len() / m.max(1));
    let mut mult = Vec::with_capacity(flat.len() / m.max(1));
    for chunk in flat.chunks_exact(m) {
        let mut e = [0u8; MAX_VARS];
        for (dst, &src) in e.iter_mut().zip(chunk) {
            *dst = src as u8;
        }
        exps.push(e);
        mult.push(multinomial(chunk));
    }
    (exps, mult)
}

/// The tables of `m ≤ 4` variables and degree `d ≤ MAX_DEGREE`.
pub(crate) fn tables(m: usize, d: u32) -> &'static Tables {
    assert!(
        (1..=MAX_VARS).contains(&m) && d <= MAX_DEGREE,
        "tables({m}, {d}): callers check the range"
    );
    TABLES[m][d as usize].get_or_init(|| {
        let (exps, multinom) = list(m, d);
        let (lower_exps, lower_multinom) = if d == 0 {
            (Vec::new(), Vec::new())
        } else {
            list(m, d - 1)
        };
        let mut up = Vec::with_capacity(lower_exps.len());
        let mut idx = vec![0u32; m];
        for k in &lower_exps {
            let mut row = [0u32; MAX_VARS];
            for (j, slot) in row.iter_mut().enumerate().take(m) {
                for (i, v) in idx.iter_mut().enumerate() {
                    *v = u32::from(k[i]) + u32::from(i == j);
                }
                *slot = multi_index::rank(&idx) as u32;
            }
            up.push(row);
        }
        let identity = exps
            .iter()
            .map(|e| {
                let mut b = [0.0; MAX_VARS];
                for (x, &ei) in b.iter_mut().zip(e).take(m) {
                    *x = f64::from(ei) / f64::from(d);
                }
                b
            })
            .collect();
        let support = exps
            .iter()
            .map(|e| {
                (0..m)
                    .filter(|&i| e[i] > 0)
                    .fold(0u8, |mask, i| mask | 1 << i)
            })
            .collect();
        Tables {
            exps,
            multinom,
            lower_exps,
            lower_multinom,
            up,
            identity,
            support,
        }
    })
}

/// Length of a power-table row: exponents `0..=MAX_DEGREE`.
pub(crate) const POW_LEN: usize = MAX_DEGREE as usize + 1;

/// Powers `w_i^e` for `e = 0..=d`, one row per variable. `0^0 = 1`, and `0^e = 0` exactly.
#[inline(always)]
pub(crate) fn pow_table<const M: usize>(d: usize, w: &[f64; MAX_VARS]) -> [[f64; POW_LEN]; M] {
    let mut pw = [[1.0; POW_LEN]; M];
    for i in 0..M {
        let x = w[i];
        for e in 1..=d {
            pw[i][e] = pw[i][e - 1] * x;
        }
    }
    pw
}

/// `B_I(w)` from a power table.
#[inline(always)]
pub(crate) fn basis_m<const M: usize>(
    mult: f64,
    e: &[u8; MAX_VARS],
    pw: &[[f64; POW_LEN]; M],
) -> f64 {
    let mut b = mult;
    for i in 0..M {
        b *= pw[i][e[i] as usize];
    }
    b
}

/// One term of a compile-time table: the exponents of a multi-index and its multinomial.
pub(crate) type ConstTerm<const M: usize> = ([usize; M], f64);

/// `n!` for the small degrees of the compile-time tables.
const fn factorial(n: usize) -> u64 {
    let mut acc = 1u64;
    let mut k = 2;
    while k <= n {
        acc *= k as u64;
        k += 1;
    }
    acc
}

/// The degree-`d` multi-indices in `M` variables in canonical order (lexicographically
/// decreasing: [`multi_index::all`]) with their multinomials, built at compile time; `N` must be
/// their count (checked). A kernel over this table, unrolled, knows every exponent: its power
/// lookups become registers and its factors `w⁰ = 1` and multinomials `1` fold away — a product
/// by 1.0 is exact, so it computes the same bits as the loop over [`Tables`] with [`basis_m`].
pub(crate) const fn const_terms<const M: usize, const N: usize>(d: usize) -> [ConstTerm<M>; N] {
    let mut out = [([0usize; M], 0.0f64); N];
    let base = d + 1;
    let mut total = 1usize;
    let mut i = 0;
    while i < M {
        total *= base;
        i += 1;
    }
    // Counting down through the base-(d + 1) numerals of M digits, most significant first, visits
    // the exponent vectors in lexicographically decreasing order; keep those of degree d.
    let mut c = total;
    let mut k = 0;
    while c > 0 {
        c -= 1;
        let mut e = [0usize; M];
        let mut x = c;
        let mut sum = 0;
        let mut i = M;
        while i > 0 {
            i -= 1;
            e[i] = x % base;
            sum += e[i];
            x /= base;
        }
        if sum == d {
            assert!(k < N, "const_terms: N is smaller than the count");
            let mut denominator = 1u64;
            let mut i = 0;
            while i < M {
                denominator *= factorial(e[i]);
                i += 1;
            }
            // An exact integer below 2⁵³, as `multinomial` computes it.
            out[k] = (e, (factorial(d) / denominator) as f64);
            k += 1;
        }
    }
    assert!(k == N, "const_terms: N is not the count");
    out
}

/// For each degree-`d − 1` index `K` of `lower` ([`const_terms`]), the ranks of `K + e_j` among
/// the degree-`d` indices `upper` (the `up` table of [`Tables`]).
pub(crate) const fn const_up<const M: usize, const N: usize, const NL: usize>(
    upper: &[ConstTerm<M>; N],
    lower: &[ConstTerm<M>; NL],
) -> [[usize; M]; NL] {
    let mut out = [[0usize; M]; NL];
    let mut r = 0;
    while r < NL {
        let mut j = 0;
        while j < M {
            let mut t = 0;
            let mut found = false;
            while t < N && !found {
                let mut same = true;
                let mut i = 0;
                while i < M {
                    let want = lower[r].0[i] + if i == j { 1 } else { 0 };
                    if upper[t].0[i] != want {
                        same = false;
                    }
                    i += 1;
                }
                if same {
                    out[r][j] = t;
                    found = true;
                } else {
                    t += 1;
                }
            }
            assert!(found, "const_up: K + e_j is not of degree D");
            j += 1;
        }
        r += 1;
    }
    out
}

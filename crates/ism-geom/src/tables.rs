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
        Tables {
            exps,
            multinom,
            lower_exps,
            lower_multinom,
            up,
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

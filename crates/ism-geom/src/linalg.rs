//! Small dense linear algebra on fixed `4 × 4` arrays (only the upper-left `k × k` block is used).
//!
//! Hand-written rather than `nalgebra`: every matrix here is at most `4 × 4`, sized at run time by
//! the dimension, and must live on the stack on the evaluation hot path.

// Index loops mirror the matrix and multi-index formulas they implement; iterator chains over
// several arrays at once would hide them.
#![allow(clippy::needless_range_loop)]

use crate::{Mat, MAX_VARS};

/// Determinant of the upper-left `k × k` block (`k ≤ 4`), by cofactor formulas for `k ≤ 3`.
pub fn det(k: usize, a: &Mat) -> f64 {
    match k {
        0 => 1.0,
        1 => a[0][0],
        2 => a[0][0] * a[1][1] - a[0][1] * a[1][0],
        3 => {
            a[0][0] * (a[1][1] * a[2][2] - a[1][2] * a[2][1])
                - a[0][1] * (a[1][0] * a[2][2] - a[1][2] * a[2][0])
                + a[0][2] * (a[1][0] * a[2][1] - a[1][1] * a[2][0])
        }
        _ => {
            let mut m = *a;
            let mut d = 1.0;
            for c in 0..k {
                let p = (c..k)
                    .max_by(|&i, &j| m[i][c].abs().total_cmp(&m[j][c].abs()))
                    .unwrap_or(c);
                if m[p][c] == 0.0 {
                    return 0.0;
                }
                if p != c {
                    m.swap(p, c);
                    d = -d;
                }
                d *= m[c][c];
                for r in c + 1..k {
                    let f = m[r][c] / m[c][c];
                    for cc in c..k {
                        m[r][cc] -= f * m[c][cc];
                    }
                }
            }
            d
        }
    }
}

/// Solves `a x = b` on the upper-left `k × k` block by Gaussian elimination with partial
/// pivoting; `None` when a pivot is zero or not finite.
pub fn solve(k: usize, a: &Mat, b: &[f64; MAX_VARS]) -> Option<[f64; MAX_VARS]> {
    let mut m = *a;
    let mut x = *b;
    for c in 0..k {
        let p = (c..k).max_by(|&i, &j| m[i][c].abs().total_cmp(&m[j][c].abs()))?;
        if m[p][c] == 0.0 || !m[p][c].is_finite() {
            return None;
        }
        if p != c {
            m.swap(p, c);
            x.swap(p, c);
        }
        for r in c + 1..k {
            let f = m[r][c] / m[c][c];
            for cc in c..k {
                m[r][cc] -= f * m[c][cc];
            }
            x[r] -= f * x[c];
        }
    }
    for c in (0..k).rev() {
        let mut s = x[c];
        for cc in c + 1..k {
            s -= m[c][cc] * x[cc];
        }
        x[c] = s / m[c][c];
    }
    x[..k].iter().all(|v| v.is_finite()).then_some(x)
}

/// Inverse of the upper-left `k × k` block; `None` when singular.
///
/// One elimination with partial pivoting applied to the `k` unit right-hand sides at once: the
/// same operations, in the same order, as [`solve`] per column (so the same bits), with the
/// factorisation done once instead of `k` times (this is on the sampler's per-candidate path).
pub fn inverse(k: usize, a: &Mat) -> Option<Mat> {
    let mut m = *a;
    // x[c] is the c-th right-hand side (a unit vector), stored as a row for contiguous access.
    let mut x = [[0.0; MAX_VARS]; MAX_VARS];
    for (c, col) in x.iter_mut().enumerate().take(k) {
        col[c] = 1.0;
    }
    for c in 0..k {
        let p = (c..k).max_by(|&i, &j| m[i][c].abs().total_cmp(&m[j][c].abs()))?;
        if m[p][c] == 0.0 || !m[p][c].is_finite() {
            return None;
        }
        if p != c {
            m.swap(p, c);
            for col in x.iter_mut().take(k) {
                col.swap(p, c);
            }
        }
        for r in c + 1..k {
            let f = m[r][c] / m[c][c];
            for cc in c..k {
                m[r][cc] -= f * m[c][cc];
            }
            for col in x.iter_mut().take(k) {
                col[r] -= f * col[c];
            }
        }
    }
    let mut out = [[0.0; MAX_VARS]; MAX_VARS];
    for (j, col) in x.iter_mut().enumerate().take(k) {
        for c in (0..k).rev() {
            let mut s = col[c];
            for cc in c + 1..k {
                s -= m[c][cc] * col[cc];
            }
            col[c] = s / m[c][c];
        }
        if !col[..k].iter().all(|v| v.is_finite()) {
            return None;
        }
        for r in 0..k {
            out[r][j] = col[r];
        }
    }
    Some(out)
}

/// Product of the upper-left `k × k` blocks.
pub fn mul(k: usize, a: &Mat, b: &Mat) -> Mat {
    let mut out = [[0.0; MAX_VARS]; MAX_VARS];
    for i in 0..k {
        for j in 0..k {
            let mut s = 0.0;
            for l in 0..k {
                s += a[i][l] * b[l][j];
            }
            out[i][j] = s;
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn solve_and_det_agree_with_hand_values() {
        let a: Mat = [
            [2.0, 1.0, 0.0, 0.0],
            [1.0, 3.0, 1.0, 0.0],
            [0.0, 1.0, 4.0, 0.0],
            [0.0; 4],
        ];
        assert!((det(3, &a) - 18.0).abs() < 1e-14);
        let mut a4 = a;
        a4[3][3] = 2.0;
        assert!((det(4, &a4) - 36.0).abs() < 1e-12);
        let x = solve(3, &a, &[1.0, 2.0, 3.0, 0.0]).unwrap();
        for (r, row) in a.iter().take(3).enumerate() {
            let lhs: f64 = (0..3).map(|c| row[c] * x[c]).sum();
            assert!((lhs - [1.0, 2.0, 3.0][r]).abs() < 1e-14);
        }
        let inv = inverse(3, &a).unwrap();
        let id = mul(3, &a, &inv);
        for (i, row) in id.iter().take(3).enumerate() {
            for (j, v) in row.iter().take(3).enumerate() {
                assert!((v - f64::from(u8::from(i == j))).abs() < 1e-14);
            }
        }
        // The one-factorisation inverse equals the column-by-column solves bit for bit.
        let mut s = 3u64;
        for k in 1..=4 {
            for _ in 0..200 {
                let mut b = [[0.0; MAX_VARS]; MAX_VARS];
                for row in b.iter_mut().take(k) {
                    for v in row.iter_mut().take(k) {
                        s = s
                            .wrapping_mul(6364136223846793005)
                            .wrapping_add(1442695040888963407);
                        *v = (s >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0;
                    }
                }
                let fast = inverse(k, &b).unwrap();
                for c in 0..k {
                    let mut e = [0.0; MAX_VARS];
                    e[c] = 1.0;
                    let col = solve(k, &b, &e).unwrap();
                    for r in 0..k {
                        assert_eq!(fast[r][c].to_bits(), col[r].to_bits(), "k={k}");
                    }
                }
            }
        }
        assert!(solve(
            2,
            &[
                [1.0, 2.0, 0.0, 0.0],
                [2.0, 4.0, 0.0, 0.0],
                [0.0; 4],
                [0.0; 4]
            ],
            &[1.0, 1.0, 0.0, 0.0]
        )
        .is_none());
    }
}

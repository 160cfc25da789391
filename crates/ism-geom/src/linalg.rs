//! Small dense linear algebra on fixed `4 × 4` arrays (only the upper-left `k × k` block is used).
//!
//! Hand-written rather than `nalgebra`: every matrix here is at most `4 × 4`, sized at run time by
//! the dimension, and must live on the stack on the evaluation hot path.

// Index loops mirror the matrix and multi-index formulas they implement; iterator chains over
// several arrays at once would hide them.
#![allow(clippy::needless_range_loop)]

use crate::{Mat, MAX_VARS};

/// Determinant of the upper-left `k × k` block (`k ≤ 4`), by cofactor formulas for `k ≤ 3`.
#[inline]
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
        _ => det_eliminated(k, a),
    }
}

/// Determinant by elimination with partial pivoting (`k = 4`; off the hot paths).
fn det_eliminated(k: usize, a: &Mat) -> f64 {
    let mut m = *a;
    let mut d = 1.0;
    for c in 0..k {
        let p = pivot(&m, c, k);
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

/// Row of the pivot in column `c`: the largest `|m[i][c]|` for `i ∈ c..k` by `total_cmp` (so a NaN
/// is chosen, and then refused, rather than skipped), the last of equal ones.
#[inline(always)]
fn pivot(m: &Mat, c: usize, k: usize) -> usize {
    let mut p = c;
    let mut best = m[c][c].abs();
    for i in c + 1..k {
        let v = m[i][c].abs();
        if v.total_cmp(&best).is_ge() {
            p = i;
            best = v;
        }
    }
    p
}

/// Solves `a x = b` on the upper-left `k × k` block by Gaussian elimination with partial
/// pivoting; `None` when a pivot is zero or not finite.
#[inline]
pub fn solve(k: usize, a: &Mat, b: &[f64; MAX_VARS]) -> Option<[f64; MAX_VARS]> {
    debug_assert!(k <= MAX_VARS);
    // One body, specialised per size so that the loops unroll: the same operations in the same
    // order for every `k` (the same bits), 5–10× faster for k = 2, 3 than the run-time loops
    // (benches/linalg.rs).
    match k {
        0 => Some(*b),
        1 => solve_k::<1>(a, b),
        2 => solve_k::<2>(a, b),
        3 => solve_k::<3>(a, b),
        _ => solve_k::<4>(a, b),
    }
}

#[inline(always)]
fn solve_k<const K: usize>(a: &Mat, b: &[f64; MAX_VARS]) -> Option<[f64; MAX_VARS]> {
    let mut m = *a;
    let mut x = *b;
    for c in 0..K {
        let p = pivot(&m, c, K);
        if m[p][c] == 0.0 || !m[p][c].is_finite() {
            return None;
        }
        if p != c {
            m.swap(p, c);
            x.swap(p, c);
        }
        for r in c + 1..K {
            let f = m[r][c] / m[c][c];
            for cc in c..K {
                m[r][cc] -= f * m[c][cc];
            }
            x[r] -= f * x[c];
        }
    }
    for c in (0..K).rev() {
        let mut s = x[c];
        for cc in c + 1..K {
            s -= m[c][cc] * x[cc];
        }
        x[c] = s / m[c][c];
    }
    x[..K].iter().all(|v| v.is_finite()).then_some(x)
}

/// Inverse of the upper-left `k × k` block; `None` when singular.
///
/// One elimination with partial pivoting applied to the `k` unit right-hand sides at once: the
/// same operations, in the same order, as [`solve`] per column (so the same bits), with the
/// factorisation done once instead of `k` times (this is on the sampler's per-candidate path).
///
/// Why not `glam::DMat3::inverse` (issue 13 asked to use glam where it fits): glam inverts by
/// the adjugate over the determinant, without pivoting — faster (benches/linalg.rs), but Cramer's
/// rule is not backward stable beyond 2 × 2 (Higham, *Accuracy and Stability of Numerical
/// Algorithms*, §14.6), it never reports a singular matrix (it divides by 0), and it would change
/// every bit the exporter's and sampler's Newton steps produce. Elimination with partial pivoting,
/// specialised per size, stays.
#[inline]
pub fn inverse(k: usize, a: &Mat) -> Option<Mat> {
    debug_assert!(k <= MAX_VARS);
    match k {
        0 => Some([[0.0; MAX_VARS]; MAX_VARS]),
        1 => inverse_k::<1>(a),
        2 => inverse_k::<2>(a),
        3 => inverse_k::<3>(a),
        _ => inverse_k::<4>(a),
    }
}

#[inline(always)]
fn inverse_k<const K: usize>(a: &Mat) -> Option<Mat> {
    let mut m = *a;
    // x[c] is the c-th right-hand side (a unit vector), stored as a row for contiguous access.
    let mut x = [[0.0; MAX_VARS]; MAX_VARS];
    for (c, col) in x.iter_mut().enumerate().take(K) {
        col[c] = 1.0;
    }
    for c in 0..K {
        let p = pivot(&m, c, K);
        if m[p][c] == 0.0 || !m[p][c].is_finite() {
            return None;
        }
        if p != c {
            m.swap(p, c);
            for col in x.iter_mut().take(K) {
                col.swap(p, c);
            }
        }
        for r in c + 1..K {
            let f = m[r][c] / m[c][c];
            for cc in c..K {
                m[r][cc] -= f * m[c][cc];
            }
            for col in x.iter_mut().take(K) {
                col[r] -= f * col[c];
            }
        }
    }
    let mut out = [[0.0; MAX_VARS]; MAX_VARS];
    for (j, col) in x.iter_mut().enumerate().take(K) {
        for c in (0..K).rev() {
            let mut s = col[c];
            for cc in c + 1..K {
                s -= m[c][cc] * col[cc];
            }
            col[c] = s / m[c][c];
        }
        if !col[..K].iter().all(|v| v.is_finite()) {
            return None;
        }
        for r in 0..K {
            out[r][j] = col[r];
        }
    }
    Some(out)
}

/// Product of the upper-left `k × k` blocks.
#[inline]
pub fn mul(k: usize, a: &Mat, b: &Mat) -> Mat {
    debug_assert!(k <= MAX_VARS);
    match k {
        1 => mul_k::<1>(a, b),
        2 => mul_k::<2>(a, b),
        3 => mul_k::<3>(a, b),
        4 => mul_k::<4>(a, b),
        _ => [[0.0; MAX_VARS]; MAX_VARS],
    }
}

#[inline(always)]
fn mul_k<const K: usize>(a: &Mat, b: &Mat) -> Mat {
    let mut out = [[0.0; MAX_VARS]; MAX_VARS];
    for i in 0..K {
        for j in 0..K {
            let mut s = 0.0;
            for l in 0..K {
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

    /// The run-time-loop implementation these functions replaced (commit dd2ef567), kept verbatim
    /// as the reference: the specialised versions must give the same bits on every input.
    mod reference {
        use crate::{Mat, MAX_VARS};

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

        pub fn inverse(k: usize, a: &Mat) -> Option<Mat> {
            let mut out = [[0.0; MAX_VARS]; MAX_VARS];
            for j in 0..k {
                let mut e = [0.0; MAX_VARS];
                e[j] = 1.0;
                let col = solve(k, a, &e)?;
                for r in 0..k {
                    out[r][j] = col[r];
                }
            }
            Some(out)
        }

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
    }

    /// Bits, with every NaN as one: Rust leaves a NaN's sign and payload unspecified (the compiler
    /// may swap the operands of `a * b`), so only "NaN" is a result; every other value is compared
    /// bit for bit.
    fn bits<const N: usize>(v: &[f64; N]) -> [u64; N] {
        v.map(|x| {
            if x.is_nan() {
                f64::NAN.to_bits()
            } else {
                x.to_bits()
            }
        })
    }

    fn mat_bits(m: &Mat) -> [[u64; MAX_VARS]; MAX_VARS] {
        m.map(|r| bits(&r))
    }

    /// Random entries from a law with ties (small integers), zeros, signed zeros, huge, tiny and
    /// subnormal values, infinities and NaN beside plain uniforms: pivoting's ties and refusals
    /// are where a reimplementation would differ.
    #[test]
    fn specialised_versions_give_the_reference_bits() {
        let mut s = 11u64;
        let mut next = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            s >> 11
        };
        let specials = [
            0.0,
            -0.0,
            1.0,
            -1.0,
            2.0,
            1e300,
            -1e-300,
            5e-324,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NAN,
        ];
        for round in 0..200_000 {
            let k = 1 + round % 4;
            let mut a = [[0.0; MAX_VARS]; MAX_VARS];
            let mut b = [0.0; MAX_VARS];
            let special_share = if round % 3 == 0 { 0 } else { 8 };
            let draw = |next: &mut dyn FnMut() -> u64| {
                let r = next();
                if (r % 64) < special_share {
                    specials[(r / 64) as usize % specials.len()]
                } else if r % 5 == 0 {
                    ((r / 64) % 5) as f64 - 2.0
                } else {
                    (r >> 1) as f64 / (1u64 << 52) as f64 * 2.0 - 1.0
                }
            };
            // Every cell, also outside the k × k block: the functions must not read it.
            for row in a.iter_mut() {
                for v in row.iter_mut() {
                    *v = draw(&mut next);
                }
            }
            for v in b.iter_mut() {
                *v = draw(&mut next);
            }
            let other = {
                let mut o = a;
                o.reverse();
                o
            };
            let (d0, d1) = (det(k, &a), reference::det(k, &a));
            assert_eq!(bits(&[d0]), bits(&[d1]), "det k={k} {a:?}: {d0} vs {d1}");
            assert_eq!(
                solve(k, &a, &b).map(|x| bits(&x)),
                reference::solve(k, &a, &b).map(|x| bits(&x)),
                "solve k={k} {a:?} {b:?}"
            );
            assert_eq!(
                inverse(k, &a).map(|m| mat_bits(&m)),
                reference::inverse(k, &a).map(|m| mat_bits(&m)),
                "inverse k={k} {a:?}"
            );
            assert_eq!(
                mat_bits(&mul(k, &a, &other)),
                mat_bits(&reference::mul(k, &a, &other)),
                "mul k={k}"
            );
        }
    }
}

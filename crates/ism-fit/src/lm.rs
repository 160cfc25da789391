//! Levenberg–Marquardt on the logits of one face of a stratified block ([`lm_face`]): the
//! per-face optimizer of Hermite fitting ([`crate::hermite`]) and smoothing ([`crate::smooth`]).

use ism_geom::{linalg, MAX_VARS};

use crate::strata::{StratifiedMap, LOGIT_BOUND};

/// Levenberg–Marquardt on the logits of one face. `residuals` evaluates the block's residual
/// vector for a map; only this face's logits change. Every accepted step lowers `Σ r²`, so the
/// objective never increases. Returns the final cost. Hand-written for the same reason as
/// [`crate::fit`]'s: a ≤ 4×4 solve with the softmax clamp.
pub(crate) fn lm_face(
    map: &mut StratifiedMap,
    face: &[u32],
    steps: usize,
    residuals: &dyn Fn(&StratifiedMap) -> Vec<f64>,
) -> f64 {
    /// Forward-difference step on logits: the residuals are smooth in them, ~1e−8 relative
    /// truncation against ~1e−9 rounding.
    const H: f64 = 1e-6;
    let k = face.len();
    let mut x = map.logits(face);
    let mut r = residuals(map);
    let mut cost: f64 = r.iter().map(|v| v * v).sum();
    let mut lambda = 1e-3;
    for _ in 0..steps {
        let mut jac = vec![vec![0.0; r.len()]; k];
        for (j, col) in jac.iter_mut().enumerate() {
            let mut xh = x.clone();
            xh[j] += H;
            map.set_logits(face, &xh);
            let rh = residuals(map);
            for (i, v) in col.iter_mut().enumerate() {
                *v = (rh[i] - r[i]) / H;
            }
        }
        let mut improved = false;
        for _ in 0..5 {
            let mut a = [[0.0; MAX_VARS]; MAX_VARS];
            let mut b = [0.0; MAX_VARS];
            for i in 0..k {
                for j in 0..k {
                    a[i][j] = jac[i].iter().zip(&jac[j]).map(|(p, q)| p * q).sum();
                }
                b[i] = -jac[i].iter().zip(&r).map(|(p, q)| p * q).sum::<f64>();
            }
            for (i, row) in a.iter_mut().enumerate().take(k) {
                row[i] += lambda * row[i] + 1e-12;
            }
            let Some(step) = linalg::solve(k, &a, &b) else {
                break;
            };
            let xn: Vec<f64> = (0..k)
                .map(|i| (x[i] + step[i]).clamp(-LOGIT_BOUND, LOGIT_BOUND))
                .collect();
            map.set_logits(face, &xn);
            let rn = residuals(map);
            let cn: f64 = rn.iter().map(|v| v * v).sum();
            if cn < cost {
                x = xn;
                r = rn;
                cost = cn;
                lambda = (lambda / 3.0).max(1e-9);
                improved = true;
                break;
            }
            lambda *= 5.0;
        }
        map.set_logits(face, &x);
        if !improved {
            break;
        }
    }
    map.set_logits(face, &x);
    cost
}

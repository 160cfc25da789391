//! Theorems that certify a stage without computation (spec/validation.md §4.2), and the
//! Sottile–Zhu compatibility test for 2D rational stages (Sottile & Zhu Thm. III.4).

use ism_format::multi_index;

use crate::certify::DenseNet;

/// Every stage of the implicit direction whose coefficients strictly increase from 0: `g_v' > 0`.
pub const MONOTONIC: &str = "Mello & Velho 2009 §4: monotonic, strictly increasing coefficients";
/// No moved control point touches the simplex.
pub const IDENTITY: &str = "identity: no moved control point";
/// Adjusted quadratic Bézier stage (also stratum G₁).
pub const PROP_5_6: &str = "Mello & Velho 2009 Prop. 5.6: adjusted quadratic";
/// One free control point, at the centre index of a face.
pub const PROP_5_7: &str = "Mello & Velho 2009 Prop. 5.7: solitary control point";
/// Stratum G₂ of the stratified scheme in 3D.
pub const PROP_5_9: &str = "Mello & Velho 2009 Prop. 5.9: stratum G2 in 3D";
/// Rational stage with every control point fixed.
pub const THM_6_4: &str = "Mello & Velho 2009 Thm. 6.4: rational, fixed control points";
/// Adjusted quadratic rational stage.
pub const THM_6_5: &str = "Mello & Velho 2009 Thm. 6.5: adjusted quadratic rational";
/// 2D rational stage with a compatible control net: valid for every choice of positive weights.
pub const SOTTILE_ZHU: &str = "Sottile & Zhu Thm. III.4: compatible net";
/// Bernstein coefficients of det DX, positive after subdivision (floating point with rigorous
/// rounding bounds).
pub const SUBDIVISION: &str = "Bernstein coefficients with subdivision";
/// Bernstein coefficients of det DX, positive after subdivision in exact integer arithmetic.
pub const EXACT_SUBDIVISION: &str = "exact Bernstein coefficients with subdivision";

/// Whether the 2D control net is *compatible* (Sottile & Zhu Def. III.1/III.3): for every triple of lattice
/// points `I` (as `(I₁, I₂)`) that is affinely independent and whose control points (as `(b₁, b₂)`)
/// are too, the two triangles have the same orientation; and one such triple exists. Distinct vertex
/// images hold for every adjusted net. Orientation of the control points uses Shewchuk's exact
/// adaptive predicate, so the test is exact for the stored doubles. `O(N³)` for `N = C(d + 2, 2)`.
pub fn sottile_zhu_compatible(net: &DenseNet) -> bool {
    if net.n != 2 {
        return false;
    }
    let lattice: Vec<(i64, i64)> = multi_index::all(3, net.degree)
        .chunks(3)
        .map(|i| (i64::from(i[1]), i64::from(i[2])))
        .collect();
    let pts: Vec<robust::Coord<f64>> = net
        .points
        .iter()
        .map(|p| robust::Coord { x: p[1], y: p[2] })
        .collect();
    let n = lattice.len();
    let mut witnessed = false;
    for a in 0..n {
        for b in (a + 1)..n {
            for c in (b + 1)..n {
                let (la, lb, lc) = (lattice[a], lattice[b], lattice[c]);
                let lat = (lb.0 - la.0) * (lc.1 - la.1) - (lb.1 - la.1) * (lc.0 - la.0);
                if lat == 0 {
                    continue;
                }
                let ctl = robust::orient2d(pts[a], pts[b], pts[c]);
                if ctl == 0.0 {
                    continue;
                }
                if (lat > 0) != (ctl > 0.0) {
                    return false;
                }
                witnessed = true;
            }
        }
    }
    witnessed
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn identity_net_is_compatible_and_a_folded_one_is_not() {
        let mut net = DenseNet::identity(2, 3);
        net.weights = vec![1.0; net.points.len()];
        assert!(sottile_zhu_compatible(&net));
        // Centre point (rank of 111 in degree 3 is 4) pushed across the edge opposite vertex 0.
        let centre = multi_index::rank(&[1, 1, 1]);
        net.points[centre] = [0.05, 0.9, 0.05, 0.0];
        assert!(!sottile_zhu_compatible(&net));
        // A mild move keeps compatibility.
        net.points[centre] = [0.3, 0.4, 0.3, 0.0];
        assert!(sottile_zhu_compatible(&net));
    }
}

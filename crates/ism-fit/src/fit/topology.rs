//! The topology of a fit: the Plantinga–Vegter test on a cell (interval enclosures of `g` and `∇g`
//! over boxes that cover the simplex, then gradient generators), its cache, and the clusters of
//! cells where it could not be certified.

use super::*;

impl Fitter<'_> {
    /// The Plantinga–Vegter test on cell `c`: `0 ∉ □g(C)`, or `⟨□∇g(C), □∇g(C)⟩ > 0` (no two
    /// gradients in `C` orthogonal or opposed). The enclosures are over boxes that cover `C`:
    /// first its bounding box; when that fails, the [`PV_SPLIT`]`ⁿ` parts of the box that meet
    /// the simplex (a part that lies beyond one of its facets is left out), with `□∇g` the hull
    /// over them. Both cover `C`, so both are sound; the parts hug the simplex, which fills only
    /// `1/n!` of its box (a Kuhn cell lies along the box's diagonal), so fewer cells fail that
    /// contain no zero, and the gradient's range is taken over less.
    ///
    /// Where the function gives [`PvWitness`](crate::expr::PvWitness)es (a mesh) they are asked first
    /// ([`Fitter::pv_witnessed`]): they decide most failing cells for one nearest-point query
    /// per part; the rest goes through [`Fitter::pv_passes_by_enclosures`]. The same answer as
    /// without them, for every cell (test
    /// `the_plantinga_vegter_shortcuts_give_the_reference_answer_on_every_cell`).
    pub(super) fn pv_passes(&self, c: u32) -> bool {
        let (lo, hi) = self.complex.bounding_box(c);
        match self.pv_witnessed(c, &lo, &hi) {
            Witnessed::Fails => false,
            w => self.pv_passes_by_enclosures(c, &lo, &hi, w == Witnessed::HullFails),
        }
    }

    /// What the function's [`PvWitness`](crate::expr::PvWitness)es tell about [`Fitter::pv_passes_by_enclosures`] on
    /// cell `c` (bounding box `[lo, hi]`), from the box and the [`PV_SPLIT`]`ⁿ` parts meeting
    /// the cell:
    /// - [`Witnessed::Fails`] when the box's value enclosure holds 0, so does one part's, and
    ///   the witnesses of two parts point apart (dot product ≤ −[`GENERATOR_DOT_MARGIN`]). Both
    ///   witnesses lie in the box's gradient enclosure and in the parts' hull (each within
    ///   [`GENERATOR_ERROR`](crate::expr::GENERATOR_ERROR) per component, which moves the dot
    ///   product by < [`GENERATOR_DOT_MARGIN`]), so neither interval test can pass; and both are
    ///   among the parts' generators, whose pairwise test then fails.
    /// - [`Witnessed::HullFails`] when instead one part's value enclosure holds 0 and another
    ///   part's gradient enclosure is the unit box: the hull test then fails (its dot product's
    ///   lower bound is ≤ −1), only the box's and the generators' tests are left.
    /// - [`Witnessed::Undecided`] otherwise (also when the function has no witnesses).
    ///
    /// For a mesh a witness is one nearest-point query, where a part's gradient enclosure or
    /// generators cost 64 and a range query: most cells of the Stanford bunny fail the test
    /// (issue 17, session 23).
    pub(super) fn pv_witnessed(&self, c: u32, lo: &[f64], hi: &[f64]) -> Witnessed {
        let Some(whole) = self.g.pv_witness(lo, hi) else {
            return Witnessed::Undecided;
        };
        if !whole.value.contains(0.0) {
            return Witnessed::Undecided;
        }
        let n = self.n;
        let Some(inside) = simplex_test(&self.complex, c) else {
            return Witnessed::Undecided;
        };
        let m = PV_SPLIT;
        let (mut zero, mut unit) = (false, false);
        let mut normals: Vec<[f64; 3]> = Vec::with_capacity(m.pow(n as u32));
        let (mut l, mut h) = (vec![0.0; n], vec![0.0; n]);
        let mut meeting: Vec<usize> = Vec::with_capacity(m.pow(n as u32));
        for idx in 0..m.pow(n as u32) {
            sub_box(lo, hi, m, idx, &mut l, &mut h);
            if !inside(&l, &h) {
                continue;
            }
            let Some(w) = self.g.pv_witness(&l, &h) else {
                return Witnessed::Undecided;
            };
            zero |= w.value.contains(0.0) || w.value.lo.is_nan();
            unit |= w.unit_gradient;
            if !normals.contains(&w.normal) {
                normals.push(w.normal);
            }
            meeting.push(idx);
        }
        if !zero {
            return Witnessed::Undecided;
        }
        let dot = |a: &[f64; 3], b: &[f64; 3]| {
            a[..n].iter().zip(&b[..n]).map(|(x, y)| x * y).sum::<f64>()
        };
        let apart_from = |normals: &[[f64; 3]], from: usize| {
            normals.iter().enumerate().skip(from).any(|(i, b)| {
                normals[..i]
                    .iter()
                    .any(|a| dot(a, b) <= -GENERATOR_DOT_MARGIN)
            })
        };
        let mut apart = apart_from(&normals, 1);
        if !apart {
            // Then the parts' corners (points of the parts: the witness of the point
            // `[p, p]` is a generator of every part containing it), each once.
            let from = normals.len().max(1);
            let mut done: HashSet<usize> = HashSet::new();
            let mut p = vec![0.0; n];
            for &idx in &meeting {
                for mask in 0..1usize << n {
                    let mut rest = idx;
                    let mut key = 0;
                    for k in 0..n {
                        let i = rest % m + (mask >> k & 1);
                        rest /= m;
                        key = key * (m + 1) + i;
                        let w = (hi[k] - lo[k]) / m as f64;
                        p[k] = if i == m { hi[k] } else { lo[k] + i as f64 * w };
                    }
                    if !done.insert(key) {
                        continue;
                    }
                    if let Some(w) = self.g.pv_witness(&p, &p) {
                        if !normals.contains(&w.normal) {
                            normals.push(w.normal);
                        }
                    }
                }
            }
            apart = apart_from(&normals, from);
        }
        if apart {
            Witnessed::Fails
        } else if unit {
            Witnessed::HullFails
        } else {
            Witnessed::Undecided
        }
    }

    /// Over the [`PV_SPLIT`]`ⁿ` parts of `[lo, hi]` that meet the cell (`inside`): whether some
    /// part's value enclosure holds 0 (or is NaN), and the hull of the parts' gradient
    /// enclosures; `None` where a part has no enclosure or a NaN gradient bound (the test fails).
    fn parts_hull(
        &self,
        lo: &[f64],
        hi: &[f64],
        inside: &impl Fn(&[f64], &[f64]) -> bool,
    ) -> Option<(bool, Vec<crate::interval::Interval>)> {
        let n = self.n;
        let m = PV_SPLIT;
        let mut hull: Vec<Option<(f64, f64)>> = vec![None; n];
        let mut zero = false;
        let (mut l, mut h) = (vec![0.0; n], vec![0.0; n]);
        for idx in 0..m.pow(n as u32) {
            sub_box(lo, hi, m, idx, &mut l, &mut h);
            if !inside(&l, &h) {
                continue;
            }
            let e = self.g.enclose(&l, &h)?;
            zero |= e.value.contains(0.0) || e.value.lo.is_nan();
            for (acc, gk) in hull.iter_mut().zip(&e.gradient) {
                let (a, b) = (gk.lo, gk.hi);
                if a.is_nan() || b.is_nan() {
                    return None;
                }
                *acc = Some(acc.map_or((a, b), |(x, y)| (x.min(a), y.max(b))));
            }
        }
        let gradient = hull
            .iter()
            .map(|x| {
                x.map_or(crate::interval::Interval::ENTIRE, |(a, b)| {
                    crate::interval::Interval::new(a, b)
                })
            })
            .collect();
        Some((zero, gradient))
    }

    /// [`Fitter::pv_passes`] from the enclosures and generators alone (see there); `hull_fails`:
    /// the parts' hull test is known to fail and one part's value enclosure to hold 0
    /// ([`Witnessed::HullFails`]), so their enclosures are not computed.
    pub(super) fn pv_passes_by_enclosures(
        &self,
        c: u32,
        lo: &[f64],
        hi: &[f64],
        hull_fails: bool,
    ) -> bool {
        let Some(enc) = self.g.enclose(lo, hi) else {
            return true;
        };
        if !enc.value.contains(0.0) || gradients_agree(&enc.gradient) {
            return true;
        }
        let Some(inside) = simplex_test(&self.complex, c) else {
            return false;
        };
        if hull_fails {
            return self.generators_agree(lo, hi, &inside);
        }
        let Some((zero, gradient)) = self.parts_hull(lo, hi, &inside) else {
            return false;
        };
        if !zero {
            return true;
        }
        gradients_agree(&gradient) || self.generators_agree(lo, hi, &inside)
    }

    /// The cells of `cells` that fail [`Fitter::pv_passes`], in their order: cells not tested
    /// before in parallel, the others from [`Fitter::pv`] (under `cfg(test)` re-tested and checked
    /// to give the same answer).
    pub(super) fn pv_failing(&mut self, cells: Vec<u32>) -> Vec<u32> {
        let fresh: Vec<(u32, bool)> = {
            let f = &*self;
            cells
                .par_iter()
                .filter(|c| !f.pv.contains_key(c))
                .map(|&c| (c, f.pv_passes(c)))
                .collect()
        };
        #[cfg(test)]
        {
            let f = &*self;
            cells.par_iter().for_each(|c| {
                if let Some(&known) = f.pv.get(c) {
                    assert_eq!(known, f.pv_passes(*c), "cached PV status of cell {c}");
                }
            });
        }
        self.pv.extend(fresh);
        cells.into_iter().filter(|c| !self.pv[c]).collect()
    }

    /// The Plantinga–Vegter test from the function's gradient generators over the sub-boxes of
    /// `[lo, hi]` that meet the cell (see [`ImplicitFunction::gradient_generators`]); `false`
    /// when it has none. The answer of [`unit_vectors_agree`] on their distinct vectors, found
    /// sooner where it can be: `true` when a superset of them agrees
    /// ([`Fitter::superset_agrees`]); `false` as soon as two of those gathered so far do not
    /// (the pairwise test over all of them then fails: the quick test in
    /// [`unit_vectors_agree`] passes only vectors whose pairwise dot products are above ~10⁻⁸).
    pub(super) fn generators_agree(
        &self,
        lo: &[f64],
        hi: &[f64],
        inside: &impl Fn(&[f64], &[f64]) -> bool,
    ) -> bool {
        let n = self.n;
        let m = PV_SPLIT;
        if self.superset_agrees(lo, hi, inside) {
            return true;
        }
        let mut generators = Vec::new();
        let (mut l, mut h) = (vec![0.0; n], vec![0.0; n]);
        // The distinct vectors so far: a pair of them at or below the margin decides (the
        // pairwise test over all of them fails), so the remaining parts are not asked.
        let mut seen: HashSet<Vec<u64>> = HashSet::new();
        let mut distinct: Vec<f64> = Vec::new();
        let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
        for idx in 0..m.pow(n as u32) {
            sub_box(lo, hi, m, idx, &mut l, &mut h);
            if !inside(&l, &h) {
                continue;
            }
            let from = generators.len();
            if !self.g.gradient_generators(&l, &h, &mut generators) {
                return false;
            }
            for v in generators[from..].chunks_exact(n) {
                if !seen.insert(v.iter().map(|x| x.to_bits()).collect()) {
                    continue;
                }
                if distinct.len() / n >= MAX_GENERATORS
                    || distinct
                        .chunks_exact(n)
                        .any(|u| dot(u, v) <= GENERATOR_DOT_MARGIN)
                {
                    return false;
                }
                distinct.extend_from_slice(v);
            }
        }
        // Neighbouring sub-boxes give mostly the same vectors: each once (bit-equal copies).
        unit_vectors_agree(n, &distinct_vectors(n, &generators))
    }

    /// Whether the function's superset of the generators of the sub-boxes of `[lo, hi]` that
    /// meet the cell ([`ImplicitFunction::gradient_generators_superset`]) agrees pairwise: then
    /// so do the generators themselves (fewer vectors, the same bits, and at least one — a
    /// sub-box meets the cell when this is asked), and [`Fitter::generators_agree`] is `true`.
    /// `false` when undecided. For a mesh the superset costs about one sub-box's generators
    /// where the exact set costs every sub-box's; it decided half of the bunny's passing cells
    /// that got this far (issue 17, session 23).
    pub(super) fn superset_agrees(
        &self,
        lo: &[f64],
        hi: &[f64],
        inside: &impl Fn(&[f64], &[f64]) -> bool,
    ) -> bool {
        let n = self.n;
        let m = PV_SPLIT;
        let (mut l, mut h) = (vec![0.0; n], vec![0.0; n]);
        let parts: Vec<(Vec<f64>, Vec<f64>)> = (0..m.pow(n as u32))
            .filter_map(|idx| {
                sub_box(lo, hi, m, idx, &mut l, &mut h);
                inside(&l, &h).then(|| (l.clone(), h.clone()))
            })
            .collect();
        let boxes: Vec<(&[f64], &[f64])> = parts.iter().map(|(a, b)| (&a[..], &b[..])).collect();
        let mut superset = Vec::new();
        !boxes.is_empty()
            && self.g.gradient_generators_superset(&boxes, &mut superset)
            && unit_vectors_agree(n, &distinct_vectors(n, &superset))
    }

    /// [`Fitter::pv_passes`] as it was before the witnesses, the superset and the early exit
    /// (session 22): the reference the tests hold the faster test to.
    #[cfg(test)]
    pub(super) fn pv_passes_reference(&self, c: u32) -> bool {
        let (lo, hi) = self.complex.bounding_box(c);
        let Some(enc) = self.g.enclose(&lo, &hi) else {
            return true;
        };
        if !enc.value.contains(0.0) || gradients_agree(&enc.gradient) {
            return true;
        }
        let n = self.n;
        let Some(inside) = simplex_test(&self.complex, c) else {
            return false;
        };
        let Some((zero, gradient)) = self.parts_hull(&lo, &hi, &inside) else {
            return false;
        };
        if !zero {
            return true;
        }
        let m = PV_SPLIT;
        let (mut l, mut h) = (vec![0.0; n], vec![0.0; n]);
        if gradients_agree(&gradient) {
            return true;
        }
        let mut generators = Vec::new();
        for idx in 0..m.pow(n as u32) {
            sub_box(&lo, &hi, m, idx, &mut l, &mut h);
            if inside(&l, &h) && !self.g.gradient_generators(&l, &h, &mut generators) {
                return false;
            }
        }
        unit_vectors_agree(n, &distinct_vectors(n, &generators))
    }

    /// Groups `cells` into clusters of cells within `2·size` of each other (a grid hash of cell
    /// centres, connected through neighbouring grid cells).
    pub(super) fn clusters(&self, cells: &[u32], size: f64) -> Vec<Uncertain> {
        let n = self.n;
        let h = (2.0 * size).max(f64::MIN_POSITIVE);
        let centres: Vec<(Vec<f64>, f64)> = cells
            .iter()
            .map(|&c| {
                let (lo, hi) = self.complex.bounding_box(c);
                let centre: Vec<f64> = lo.iter().zip(&hi).map(|(a, b)| 0.5 * (a + b)).collect();
                let half = lo
                    .iter()
                    .zip(&hi)
                    .map(|(a, b)| (0.5 * (b - a)).powi(2))
                    .sum::<f64>()
                    .sqrt();
                (centre, half)
            })
            .collect();
        let key = |p: &[f64]| -> Vec<i64> { p.iter().map(|x| (x / h).floor() as i64).collect() };
        let mut grid: HashMap<Vec<i64>, Vec<usize>> = HashMap::new();
        for (i, (c, _)) in centres.iter().enumerate() {
            grid.entry(key(c)).or_default().push(i);
        }
        let mut label = vec![usize::MAX; cells.len()];
        let mut out = Vec::new();
        for start in 0..cells.len() {
            if label[start] != usize::MAX {
                continue;
            }
            let id = out.len();
            let mut stack = vec![start];
            label[start] = id;
            let mut members = Vec::new();
            while let Some(i) = stack.pop() {
                members.push(i);
                let k = key(&centres[i].0);
                for offset in 0..3usize.pow(n as u32) {
                    let mut nk = k.clone();
                    let mut o = offset;
                    for x in nk.iter_mut() {
                        *x += (o % 3) as i64 - 1;
                        o /= 3;
                    }
                    for &j in grid.get(&nk).map_or(&[][..], |v| &v[..]) {
                        if label[j] == usize::MAX {
                            label[j] = id;
                            stack.push(j);
                        }
                    }
                }
            }
            let mut centre = vec![0.0; n];
            for &i in &members {
                for (c, x) in centre.iter_mut().zip(&centres[i].0) {
                    *c += x / members.len() as f64;
                }
            }
            let radius = members
                .iter()
                .map(|&i| {
                    let d: f64 = (0..n)
                        .map(|k| (centres[i].0[k] - centre[k]).powi(2))
                        .sum::<f64>()
                        .sqrt();
                    d + centres[i].1
                })
                .fold(0.0, f64::max);
            let gradient_may_vanish = members.iter().any(|&i| {
                let (lo, hi) = self.complex.bounding_box(cells[i]);
                self.g
                    .enclose(&lo, &hi)
                    .is_some_and(|e| e.gradient.iter().all(|d| d.contains(0.0)))
            });
            out.push(Uncertain {
                centre,
                radius,
                cells: members.len(),
                gradient_may_vanish,
                shape_to_target: 0.0,
                target_to_shape: 0.0,
            });
        }
        out
    }
}

/// Parts per axis of a cell's bounding box in the Plantinga–Vegter test ([`Fitter::pv_passes`]).
/// Measured on the presets at their default tolerance (session 10): the topology phase's
/// complex, torus 10,680 → 7,010 simplices (504,283 → 420,255 .ismb bytes), genus-2 18,496 →
/// 11,910 (812,596 → 608,512); the sphere's is unchanged (its topology phase refines nothing
/// the accuracy loop would not). 3 parts: 7,068 / 12,915; 5: 6,946 / 11,454.
pub(super) const PV_SPLIT: usize = 4;

/// `⟨□∇g, □∇g⟩ > 0` with the two factors as independent boxes (not squares): no two gradients
/// in the box are orthogonal or opposed.
pub(super) fn gradients_agree(gradient: &[crate::interval::Interval]) -> bool {
    let mut dot = crate::interval::Interval::point(0.0);
    for gk in gradient {
        dot = dot + *gk * *gk;
    }
    dot.lo > 0.0
}

/// Sub-box `idx` (in 0..m^n, first axis fastest) of `[lo, hi]` split into `m` parts per axis,
/// written to `[l, h]`; the last part ends exactly at `hi`.
pub(super) fn sub_box(lo: &[f64], hi: &[f64], m: usize, idx: usize, l: &mut [f64], h: &mut [f64]) {
    let mut rest = idx;
    for k in 0..lo.len() {
        let i = rest % m;
        rest /= m;
        let w = (hi[k] - lo[k]) / m as f64;
        l[k] = lo[k] + i as f64 * w;
        h[k] = if i + 1 == m {
            hi[k]
        } else {
            lo[k] + (i + 1) as f64 * w
        };
    }
}

/// Pairwise dot products of unit vectors each within
/// [`GENERATOR_ERROR`](crate::expr::GENERATOR_ERROR) per component of the true ones must exceed
/// this to count as positive: the rounding of a dot product of vectors of length ≲ 1 is ~10⁻¹⁶,
/// the generators' own error moves it by at most 2·√n·10⁻⁹ < 4·10⁻⁹.
pub(super) const GENERATOR_DOT_MARGIN: f64 = 4.0 * crate::expr::GENERATOR_ERROR;

/// Whether every pair of the unit vectors in `flat` (`n` numbers each) has a dot product above
/// [`GENERATOR_DOT_MARGIN`] — then so has every pair of vectors in their conic hull
/// (bilinearity), which is the Plantinga–Vegter condition. `false` for none. First the cheap
/// sufficient test: all within 45° (less the margin) of their mean direction; then every pair.
pub(crate) fn unit_vectors_agree(n: usize, flat: &[f64]) -> bool {
    let count = flat.len() / n;
    if count == 0 || count > MAX_GENERATORS {
        return false;
    }
    let v = |i: usize| &flat[i * n..(i + 1) * n];
    let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
    let mut mean = vec![0.0; n];
    for i in 0..count {
        for (m, x) in mean.iter_mut().zip(v(i)) {
            *m += x;
        }
    }
    let len = dot(&mean, &mean).sqrt();
    if len > 0.0 {
        mean.iter_mut().for_each(|m| *m /= len);
        // Two vectors at angles a, b ≤ 45° − δ from one axis are at most 90° − 2δ apart. The
        // mean is rounded: its own error (≲ 10⁻¹⁵) is far inside the margin.
        let cos_limit = std::f64::consts::FRAC_1_SQRT_2 + GENERATOR_DOT_MARGIN;
        if (0..count).all(|i| dot(v(i), &mean) > cos_limit) {
            return true;
        }
    }
    (0..count).all(|i| (i + 1..count).all(|j| dot(v(i), v(j)) > GENERATOR_DOT_MARGIN))
}

/// More distinct generators than this for one cell fail the test rather than cost a quadratic
/// number of dot products (a cell that sees this many triangles is far from passing anyway).
pub(super) const MAX_GENERATORS: usize = 4096;

/// A conservative test of whether a box `[l, h]` meets simplex `c`: `false` only when every
/// corner of the box has the same barycentric coordinate below `−CONTAINS_SLACK` (the box lies beyond
/// that facet's plane). `None` for a degenerate simplex.
pub(super) fn simplex_test(complex: &Complex, c: u32) -> Option<impl Fn(&[f64], &[f64]) -> bool> {
    let n = complex.dim();
    let ids = complex.cell(c);
    let v0: Vec<f64> = complex.point(ids[0]).to_vec();
    // Edge matrix E (columns v_i − v_0) and its inverse: λ_{1..n} = E⁻¹ (p − v_0).
    let mut e: ism_geom::Mat = Default::default();
    for i in 0..n {
        let p = complex.point(ids[i + 1]);
        for k in 0..n {
            e[k][i] = p[k] - v0[k];
        }
    }
    let inv = ism_geom::linalg::inverse(n, &e)?;
    Some(move |l: &[f64], h: &[f64]| {
        let corners = 1usize << n;
        // Per coordinate λ_0..λ_n: is it below the margin at every corner?
        let mut beyond = [true; 4];
        for mask in 0..corners {
            let mut d = [0.0f64; 3];
            for k in 0..n {
                let x = if mask & (1 << k) == 0 { l[k] } else { h[k] };
                d[k] = x - v0[k];
            }
            let mut sum = 0.0;
            for i in 0..n {
                let li: f64 = (0..n).map(|k| inv[i][k] * d[k]).sum();
                sum += li;
                if li >= -CONTAINS_SLACK {
                    beyond[i + 1] = false;
                }
            }
            if 1.0 - sum >= -CONTAINS_SLACK {
                beyond[0] = false;
            }
        }
        !beyond[..=n].iter().any(|&b| b)
    })
}

/// What [`Fitter::pv_witnessed`] found.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Witnessed {
    /// The Plantinga–Vegter test fails.
    Fails,
    /// The test's hull stage fails and a part meeting the cell may hold a zero.
    HullFails,
    /// Nothing known.
    Undecided,
}

/// The distinct vectors of `flat` (`n` numbers each; bit-equal copies once), sorted.
pub(super) fn distinct_vectors(n: usize, flat: &[f64]) -> Vec<f64> {
    let mut unique: Vec<&[f64]> = flat.chunks_exact(n).collect();
    unique.sort_unstable_by(|a, b| {
        a.iter()
            .zip(*b)
            .map(|(x, y)| x.total_cmp(y))
            .find(|o| o.is_ne())
            .unwrap_or(std::cmp::Ordering::Equal)
    });
    unique.dedup();
    unique.concat()
}

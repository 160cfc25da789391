//! The complex of a Kuhn grid refined by edge bisections (spec `ism-format.md` §7.4.3,
//! `complexForm` 1): what `ism fit` builds, described by the grid and the bisections instead of
//! every vertex coordinate and simplex id.
//!
//! [`Refinement`] replays the construction the spec fixes bit for bit (binary64, one rounding per
//! operation): the grid points, the grid's simplices in slot order, then each split — the midpoint
//! becomes the next vertex and every live slot on the edge is retired and followed by its two
//! halves. [`KuhnRefinement`] is the whole description (what a file holds); its
//! [`KuhnRefinement::model_arrays`] gives the model's `vertices` and `simplices`, which is how the
//! structured writer checks that a description it was handed is the model's, and how the reader
//! decodes one. Nothing here reads bytes: the decoder reports errors at its own offsets.

use std::collections::HashMap;
use std::fmt;

use crate::builder::kuhn_simplices;

/// A Kuhn grid and its edge bisections, with the kept simplices: everything `complexForm` 1
/// stores (spec §7.4.3).
#[derive(Clone, Debug, PartialEq)]
pub struct KuhnRefinement {
    /// `lo, hi` per axis (`2n` numbers).
    pub domain: Vec<f64>,
    /// Cubes along each axis.
    pub cells: Vec<u32>,
    /// The bisected edges `(a, b)`, `a < b`, in order.
    pub splits: Vec<[u32; 2]>,
    /// Per live slot after the splits (increasing slot order): whether it is a top simplex of
    /// the model.
    pub kept: Vec<bool>,
}

/// Why a refinement cannot be built (the decoder maps each to its spec location).
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum RefineError {
    /// `domain` is not `2n` finite numbers with `lo < hi` and a finite extent, for `n` 2 or 3.
    Domain(String),
    /// `cells` is not `n` numbers ≥ 1.
    Cells(String),
    /// The grid has `2³²` vertices or more (ids are `u32`).
    TooManyVertices(u128),
    /// Split `index` names no edge of a live slot (or `a ≥ b`, or an id that does not exist).
    Split {
        /// Position of the pair in `splits`.
        index: usize,
        /// What is wrong.
        reason: String,
    },
    /// Split `index` is an edge of a live slot, but its midpoint would get the id `2³² − 1` or
    /// more (ids are `u32`; ISM-007 in a file).
    IdsExhausted {
        /// Position of the pair in `splits`.
        index: usize,
    },
    /// `kept` does not have one entry per live slot.
    Kept {
        /// Live slots after the splits.
        expected: usize,
        /// Entries given.
        got: usize,
    },
}

impl fmt::Display for RefineError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            RefineError::Domain(why) => write!(f, "box: {why}"),
            RefineError::Cells(why) => write!(f, "cells: {why}"),
            RefineError::TooManyVertices(n) => {
                write!(f, "cells: the grid has {n} vertices, ids are below 2^32")
            }
            RefineError::Split { index, reason } => write!(f, "split {index}: {reason}"),
            RefineError::IdsExhausted { index } => write!(
                f,
                "split {index}: its midpoint would get the id 2^32 - 1 or more (ids are u32)"
            ),
            RefineError::Kept { expected, got } => write!(
                f,
                "kept: {got} entries for {expected} live simplices after the splits"
            ),
        }
    }
}

impl std::error::Error for RefineError {}

/// An edge as its two vertex ids, smaller first.
type Edge = (u32, u32);

fn edge(a: u32, b: u32) -> Edge {
    (a.min(b), a.max(b))
}

/// The construction in progress: vertices, slots (retired ones keep their ids), and the live
/// slots around each edge in increasing slot order.
#[derive(Clone, Debug)]
pub struct Refinement {
    n: usize,
    points: Vec<f64>,
    slots: Vec<u32>,
    alive: Vec<bool>,
    live: usize,
    around: HashMap<Edge, Vec<u32>>,
}

impl Refinement {
    /// The Kuhn grid of `domain` (`lo, hi` per axis) with `cells[k]` cubes along axis `k`
    /// (spec §7.4.3 steps 1–3). Allocates for `n! · Π cells` slots: a decoder checks first that
    /// its input can hold their `kept` bits.
    ///
    /// # Errors
    /// [`RefineError::Domain`], [`RefineError::Cells`], [`RefineError::TooManyVertices`].
    pub fn kuhn(domain: &[f64], cells: &[u32]) -> Result<Refinement, RefineError> {
        let n = cells.len();
        check_grid(domain, cells)?;
        let grid: Vec<usize> = cells.iter().map(|&c| c as usize).collect();
        let points = grid_points(domain, &grid);
        let mut out = Refinement {
            n,
            points,
            slots: Vec::new(),
            alive: Vec::new(),
            live: 0,
            around: HashMap::new(),
        };
        for s in kuhn_simplices(&grid) {
            out.push(&s.oriented());
        }
        Ok(out)
    }

    /// The grid's slot count `n! · Π cells` without building it (`None` past `u64`): what a
    /// decoder checks its input against first.
    pub fn grid_slots(cells: &[u32]) -> Option<u64> {
        let factorial: u64 = (1..=cells.len() as u64).product();
        cells
            .iter()
            .try_fold(factorial, |acc, &c| acc.checked_mul(u64::from(c)))
    }

    /// Space dimension.
    pub fn dim(&self) -> usize {
        self.n
    }

    /// Vertices constructed so far.
    pub fn num_vertices(&self) -> usize {
        self.points.len() / self.n
    }

    /// Live slots.
    pub fn live(&self) -> usize {
        self.live
    }

    fn push(&mut self, ids: &[u32]) {
        let c = self.alive.len() as u32;
        self.slots.extend_from_slice(ids);
        self.alive.push(true);
        self.live += 1;
        for i in 0..ids.len() {
            for &b in &ids[i + 1..] {
                // Slots are pushed in increasing order, and retiring keeps the order: each list
                // stays sorted, the order a split visits them in.
                self.around.entry(edge(ids[i], b)).or_default().push(c);
            }
        }
    }

    fn retire(&mut self, c: u32) {
        self.alive[c as usize] = false;
        self.live -= 1;
        let m = self.n + 1;
        let ids: Vec<u32> = self.slots[c as usize * m..][..m].to_vec();
        for i in 0..m {
            for &b in &ids[i + 1..] {
                let key = edge(ids[i], b);
                if let Some(list) = self.around.get_mut(&key) {
                    list.retain(|&x| x != c);
                    if list.is_empty() {
                        self.around.remove(&key);
                    }
                }
            }
        }
    }

    /// Split `index` of the spec's step 4: bisects edge `(a, b)` (`a < b`) in every live slot
    /// containing it, in increasing slot order. Returns the midpoint's id.
    ///
    /// # Errors
    /// [`RefineError::Split`] when `a ≥ b`, an id does not exist, or no live slot has the edge.
    pub fn split(&mut self, index: usize, a: u32, b: u32) -> Result<u32, RefineError> {
        let fail = |reason: String| RefineError::Split { index, reason };
        let nv = self.num_vertices();
        if a >= b {
            return Err(fail(format!("expected a < b, got ({a}, {b})")));
        }
        if b as usize >= nv {
            return Err(fail(format!(
                "vertex {b} does not exist yet ({nv} vertices)"
            )));
        }
        let Some(around) = self.around.get(&(a, b)).cloned() else {
            return Err(fail(format!("no live simplex has the edge ({a}, {b})")));
        };
        // Checked after the edge (the order of spec §7.4.3: not a split of a live edge, then the
        // midpoint's id).
        if nv >= u32::MAX as usize {
            return Err(RefineError::IdsExhausted { index });
        }
        let n = self.n;
        for k in 0..n {
            let x = (self.points[a as usize * n + k] + self.points[b as usize * n + k]) * 0.5;
            self.points.push(x);
        }
        let m = nv as u32;
        let width = n + 1;
        for c in around {
            let ids: Vec<u32> = self.slots[c as usize * width..][..width].to_vec();
            self.retire(c);
            let first: Vec<u32> = ids.iter().map(|&v| if v == b { m } else { v }).collect();
            let second: Vec<u32> = ids.iter().map(|&v| if v == a { m } else { v }).collect();
            self.push(&first);
            self.push(&second);
        }
        Ok(m)
    }

    /// Steps 5–6: the model's `vertices` and `simplices` from the live slots kept (`kept[i]` for
    /// the `i`-th live slot in slot order).
    ///
    /// # Errors
    /// [`RefineError::Kept`] when `kept` does not have one entry per live slot.
    pub fn model_arrays(&self, kept: &[bool]) -> Result<(Vec<f64>, Vec<u32>), RefineError> {
        if kept.len() != self.live {
            return Err(RefineError::Kept {
                expected: self.live,
                got: kept.len(),
            });
        }
        let width = self.n + 1;
        let live = self
            .alive
            .iter()
            .enumerate()
            .filter(|(_, &a)| a)
            .map(|(c, _)| c);
        let mut chosen: Vec<usize> = Vec::new();
        for (c, &k) in live.zip(kept) {
            if k {
                chosen.push(c);
            }
        }
        let nv = self.num_vertices();
        let mut used = vec![false; nv];
        for &c in &chosen {
            for &v in &self.slots[c * width..][..width] {
                used[v as usize] = true;
            }
        }
        let mut new_id = vec![u32::MAX; nv];
        let mut vertices = Vec::new();
        let mut next = 0u32;
        for (v, &u) in used.iter().enumerate() {
            if u {
                new_id[v] = next;
                next += 1;
                vertices.extend_from_slice(&self.points[v * self.n..][..self.n]);
            }
        }
        let simplices = chosen
            .iter()
            .flat_map(|&c| self.slots[c * width..][..width].iter())
            .map(|&v| new_id[v as usize])
            .collect();
        Ok((vertices, simplices))
    }
}

/// The points of the grid of `domain` (`lo, hi` per axis) with `cells[k]` cubes along axis `k`,
/// flat, ids axis 0 fastest (spec §7.4.3 step 2): `lo + i · ((hi − lo) / c)` in that order of
/// operations (the quotient, the product, the sum), and `hi` itself on the last line — no
/// accumulated rounding, and the same bits wherever the grid is built (the fitter's complex
/// starts from these points too, so the file's construction is its own).
pub fn grid_points(domain: &[f64], cells: &[usize]) -> Vec<f64> {
    let n = cells.len();
    let counts: Vec<usize> = cells.iter().map(|&c| c + 1).collect();
    let total: usize = counts.iter().product();
    let mut points = Vec::with_capacity(total * n);
    for id in 0..total {
        let mut rest = id;
        for k in 0..n {
            let i = rest % counts[k];
            rest /= counts[k];
            let (lo, hi) = (domain[2 * k], domain[2 * k + 1]);
            let x = if i == cells[k] {
                hi
            } else {
                lo + i as f64 * ((hi - lo) / cells[k] as f64)
            };
            points.push(x);
        }
    }
    points
}

fn check_grid(domain: &[f64], cells: &[u32]) -> Result<(), RefineError> {
    let n = cells.len();
    if !(2..=3).contains(&n) {
        return Err(RefineError::Cells(format!("expected 2 or 3 axes, got {n}")));
    }
    check_domain(domain, n)?;
    check_cells(cells, n)?;
    let vertices = grid_vertices(cells);
    if vertices >= 1u128 << 32 {
        return Err(RefineError::TooManyVertices(vertices));
    }
    Ok(())
}

/// Step 1's check of `box` for `n` axes (spec §7.4.3): `2n` finite numbers, `lo < hi` per axis
/// with `hi − lo`, `lo + lo` and `hi + hi` finite. What a decoder checks before it reads `cells`.
///
/// # Errors
/// [`RefineError::Domain`].
pub fn check_domain(domain: &[f64], n: usize) -> Result<(), RefineError> {
    if domain.len() != 2 * n {
        return Err(RefineError::Domain(format!(
            "expected {} numbers (lo, hi per axis), got {}",
            2 * n,
            domain.len()
        )));
    }
    for (k, pair) in domain.chunks_exact(2).enumerate() {
        let (lo, hi) = (pair[0], pair[1]);
        // Finite sums too: every coordinate lies in [lo, hi], so no midpoint's sum overflows.
        let finite = [lo, hi, hi - lo, lo + lo, hi + hi];
        if !(finite.iter().all(|x| x.is_finite()) && lo < hi) {
            return Err(RefineError::Domain(format!(
                "axis {k}: expected lo < hi with hi - lo, 2 lo and 2 hi finite, got [{lo}, {hi}]"
            )));
        }
    }
    Ok(())
}

/// Step 1's check of `cells` for `n` axes: `n` numbers, each at least 1 (the vertex count is
/// checked apart, [`grid_vertices`]).
///
/// # Errors
/// [`RefineError::Cells`].
pub fn check_cells(cells: &[u32], n: usize) -> Result<(), RefineError> {
    if cells.len() != n {
        return Err(RefineError::Cells(format!(
            "expected {n} numbers (one per axis), got {}",
            cells.len()
        )));
    }
    if let Some(k) = cells.iter().position(|&c| c == 0) {
        return Err(RefineError::Cells(format!(
            "axis {k}: expected at least 1 cube, got 0"
        )));
    }
    Ok(())
}

/// The grid's vertex count `Π (c_k + 1)` (ids are `u32`: below `2³²` for a grid to be built).
pub fn grid_vertices(cells: &[u32]) -> u128 {
    cells.iter().map(|&c| u128::from(c) + 1).product()
}

impl KuhnRefinement {
    /// The model's `vertices` and `simplices` this description gives (spec §7.4.3).
    ///
    /// # Errors
    /// The first [`RefineError`] of the construction.
    pub fn model_arrays(&self) -> Result<(Vec<f64>, Vec<u32>), RefineError> {
        let mut r = Refinement::kuhn(&self.domain, &self.cells)?;
        for (i, &[a, b]) in self.splits.iter().enumerate() {
            r.split(i, a, b)?;
        }
        r.model_arrays(&self.kept)
    }

    /// Whether this description gives exactly `vertices` and `simplices` (every bit, in order):
    /// what a writer checks before it writes `complexForm` 1.
    pub fn describes(&self, vertices: &[f64], simplices: &[u32]) -> bool {
        match self.model_arrays() {
            Ok((v, s)) => {
                s == simplices
                    && v.len() == vertices.len()
                    && v.iter()
                        .zip(vertices)
                        .all(|(x, y)| x.to_bits() == y.to_bits())
            }
            Err(_) => false,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Signed volume (times n!) of simplex `ids` over flat `points`: the orientation check.
    fn det(points: &[f64], n: usize, ids: &[u32]) -> f64 {
        let p = |v: u32, k: usize| points[v as usize * n + k];
        let e: Vec<Vec<f64>> = (1..=n)
            .map(|i| (0..n).map(|k| p(ids[i], k) - p(ids[0], k)).collect())
            .collect();
        if n == 2 {
            e[0][0] * e[1][1] - e[0][1] * e[1][0]
        } else {
            e[0][0] * (e[1][1] * e[2][2] - e[1][2] * e[2][1])
                - e[0][1] * (e[1][0] * e[2][2] - e[1][2] * e[2][0])
                + e[0][2] * (e[1][0] * e[2][1] - e[1][1] * e[2][0])
        }
    }

    #[test]
    fn the_unit_square_split_on_its_diagonal_by_hand() {
        // Grid ids 0 (0,0), 1 (1,0), 2 (0,1), 3 (1,1); permutation 01: path 0 → 1 → 3; 10 (odd):
        // 0 → 2 → 3, last two swapped: (0, 3, 2). Splitting the diagonal (0, 3) at m = 4
        // (0.5, 0.5): slot 0 → (0, 1, 4), (4, 1, 3); slot 1 → (0, 4, 2), (4, 3, 2).
        let r = KuhnRefinement {
            domain: vec![0.0, 1.0, 0.0, 1.0],
            cells: vec![1, 1],
            splits: vec![[0, 3]],
            kept: vec![true, false, true, true],
        };
        let (v, s) = r.model_arrays().unwrap();
        assert_eq!(v, [0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 1.0, 1.0, 0.5, 0.5]);
        assert_eq!(s, [0, 1, 4, 0, 4, 2, 4, 3, 2]);
        assert!(r.describes(&v, &s));
        assert!(!r.describes(&v, &[0, 1, 4, 4, 3, 2, 0, 4, 2]));
        // Dropping vertex 1's only kept simplex renumbers the rest in order.
        let r = KuhnRefinement {
            kept: vec![false, false, true, true],
            ..r
        };
        let (v, s) = r.model_arrays().unwrap();
        assert_eq!(v, [0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 0.5, 0.5]);
        assert_eq!(s, [0, 3, 1, 3, 2, 1]);
    }

    #[test]
    fn refined_grids_stay_conforming_positive_and_fill_the_box() {
        // Ground truth by geometry, not by the construction's own bookkeeping: every simplex
        // positively oriented, the volumes summing to the box's (n! · volume in det units), and
        // every interior facet shared by exactly two simplices.
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        let mut next = |m: usize| {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state % m as u64) as usize
        };
        for (domain, cells) in [
            (vec![-1.0, 1.0, -0.5, 0.7], vec![3u32, 2]),
            (vec![-1.2, 1.2, -1.2, 1.2, -0.3, 0.3], vec![3, 3, 1]),
        ] {
            let n = cells.len();
            let mut r = Refinement::kuhn(&domain, &cells).unwrap();
            for i in 0..60 {
                // A random edge of a random live slot.
                let width = n + 1;
                let live: Vec<usize> = (0..r.alive.len()).filter(|&c| r.alive[c]).collect();
                let c = live[next(live.len())];
                let ids = &r.slots[c * width..][..width];
                let (x, y) = (ids[next(width)], ids[next(width)]);
                if x == y {
                    continue;
                }
                r.split(i, x.min(y), x.max(y)).unwrap();
            }
            let (v, s) = r.model_arrays(&vec![true; r.live()]).unwrap();
            let factorial: f64 = (1..=n).map(|k| k as f64).product();
            let mut volume = 0.0;
            let mut facets: HashMap<Vec<u32>, usize> = HashMap::new();
            for simplex in s.chunks_exact(n + 1) {
                let d = det(&v, n, simplex);
                assert!(d > 0.0, "{simplex:?}: {d}");
                volume += d / factorial;
                for skip in 0..=n {
                    let mut f: Vec<u32> = simplex
                        .iter()
                        .enumerate()
                        .filter(|&(i, _)| i != skip)
                        .map(|(_, &x)| x)
                        .collect();
                    f.sort_unstable();
                    *facets.entry(f).or_default() += 1;
                }
            }
            let expect: f64 = domain.chunks(2).map(|p| p[1] - p[0]).product();
            assert!(
                (volume - expect).abs() < 1e-12 * expect,
                "{volume} vs {expect}"
            );
            assert!(facets.values().all(|&k| k <= 2));
            // A facet used once lies on the box's boundary.
            for (f, &k) in &facets {
                if k == 1 {
                    let on_boundary = (0..n).any(|axis| {
                        [domain[2 * axis], domain[2 * axis + 1]]
                            .iter()
                            .any(|&side| f.iter().all(|&p| v[p as usize * n + axis] == side))
                    });
                    assert!(on_boundary, "{f:?}");
                }
            }
        }
    }

    #[test]
    fn bad_descriptions_are_refused_with_their_reason() {
        let ok = |d: Vec<f64>, c: Vec<u32>| Refinement::kuhn(&d, &c).map(|_| ());
        assert!(matches!(
            ok(vec![0.0, 1.0, 0.0], vec![1, 1]),
            Err(RefineError::Domain(_))
        ));
        assert!(matches!(
            ok(vec![1.0, 0.0, 0.0, 1.0], vec![1, 1]),
            Err(RefineError::Domain(_))
        ));
        assert!(matches!(
            ok(vec![-f64::MAX, f64::MAX, 0.0, 1.0], vec![1, 1]),
            Err(RefineError::Domain(_))
        ));
        // A finite extent whose midpoints' sums would overflow.
        assert!(matches!(
            ok(vec![0.9 * f64::MAX, f64::MAX, 0.0, 1.0], vec![1, 1]),
            Err(RefineError::Domain(_))
        ));
        assert!(matches!(
            ok(vec![0.0, 1.0, 0.0, 1.0], vec![0, 1]),
            Err(RefineError::Cells(_))
        ));
        assert!(matches!(
            ok(vec![0.0, 1.0, 0.0, 1.0, 0.0, 1.0], vec![2000, 2000, 2000]),
            Err(RefineError::TooManyVertices(_))
        ));
        let mut r = Refinement::kuhn(&[0.0, 1.0, 0.0, 1.0], &[1, 1]).unwrap();
        // (1, 2) is not an edge of the grid (the diagonal is (0, 3)); (3, 0) has a > b; 9 does
        // not exist.
        for (a, b) in [(1, 2), (3, 0), (0, 9)] {
            assert!(matches!(
                r.split(7, a, b),
                Err(RefineError::Split { index: 7, .. })
            ));
        }
        assert_eq!(r.split(0, 0, 3), Ok(4));
        assert_eq!(
            r.model_arrays(&[true]),
            Err(RefineError::Kept {
                expected: 4,
                got: 1
            })
        );
        assert_eq!(Refinement::grid_slots(&[3, 3, 1]), Some(54));
        assert_eq!(
            Refinement::grid_slots(&[u32::MAX, u32::MAX, u32::MAX]),
            None
        );
    }
}

//! The first stage of an all-parametric chain restricted to a cell, in one fixed-size record.
//!
//! [`crate::chain::parametric_leaves`] bisects cells of the linear patch and restricts the last
//! stored stage to each exactly: its `m` components and the `n²` reduced partials of the rows
//! `1..n`, as Bernstein polynomials in the cell's `k ≤ 3` barycentric variables. As kernel
//! [`Bernstein`]s that is `m + n²` vectors (and the vectors holding them) per cell, allocated and
//! freed at every bisection: about 38 allocations per split, a third of the table's cost. Here
//! they are the blocks of one array, and a bisection is the kernel's
//! [`Bernstein::split_edge`] arithmetic (the same de Casteljau steps in the same order, hence the
//! same bits) walked along precomputed lines.

use std::sync::OnceLock;

use ism_format::multi_index;
use ism_geom::bernstein::halve_line;
use ism_geom::Bernstein;

use crate::homothety::{coeff_count, restrict_batch_into, BatchLevels, BATCH};

/// Highest degree held (the components'; the partials are one lower).
pub(crate) const FLAT_DEGREE: usize = 4;
/// Most cell variables (a triangle of the linear patch; a segment in 2D).
const FLAT_VARS: usize = 3;
/// Coefficients held: `m ≤ 4` components of degree 4 and `n² ≤ 9` partials of degree 3 in three
/// variables (fitted models' last stage is quartic; a higher degree keeps the kernel's
/// polynomials).
const FLAT_CAP: usize = 4 * 15 + 9 * 10;

/// The lines of one split: for cell variables `k`, degree `d` and edge `(a, b)`, every index
/// `I` with `I_b = 0` starts the line `I − j e_a + j e_b`, `j = 0..=I_a`, along which the kernel's
/// [`Bernstein::split_edge`] runs de Casteljau. `ranks` holds the lines back to back (the rank of
/// each index in the canonical order), `lines` each line's start and length.
struct SplitPlan {
    lines: Vec<(u32, u32)>,
    ranks: Vec<u32>,
}

impl SplitPlan {
    fn build(k: usize, d: u32, a: usize, b: usize) -> SplitPlan {
        let mut lines = Vec::new();
        let mut ranks = Vec::new();
        let all = multi_index::all(k, d);
        let mut idx = [0u32; FLAT_VARS];
        for i in all.chunks_exact(k) {
            if i[b] != 0 {
                continue;
            }
            let l = i[a];
            lines.push((ranks.len() as u32, l + 1));
            idx[..k].copy_from_slice(i);
            for j in 0..=l {
                idx[a] = l - j;
                idx[b] = j;
                ranks.push(multi_index::rank(&idx[..k]) as u32);
            }
        }
        SplitPlan { lines, ranks }
    }
}

/// The cached plan of `(k, d, a, b)` (`a ≠ b < k ≤ 3`, `d ≤ FLAT_DEGREE`).
fn split_plan(k: usize, d: u32, a: usize, b: usize) -> &'static SplitPlan {
    type Plans = [[[[OnceLock<SplitPlan>; FLAT_VARS]; FLAT_VARS]; FLAT_DEGREE + 1]; FLAT_VARS + 1];
    static PLANS: Plans = [const {
        [const { [const { [const { OnceLock::new() }; FLAT_VARS] }; FLAT_VARS] }; FLAT_DEGREE + 1]
    }; FLAT_VARS + 1];
    PLANS[k][d as usize][a][b].get_or_init(|| SplitPlan::build(k, d, a, b))
}

/// Splits one polynomial (`src`, canonical order) at the midpoint of edge `(a, b)` into the half
/// keeping vertex `a` (`left`) and the one keeping `b` (`right`) by the kernel's [`halve_line`],
/// the routine [`Bernstein::split_edge`] uses, so the halves are its bits.
fn split_block(plan: &SplitPlan, a_first: bool, src: &[f64], left: &mut [f64], right: &mut [f64]) {
    let mut line = [0.0; FLAT_DEGREE + 1];
    for &(start, len) in &plan.lines {
        let ranks = &plan.ranks[start as usize..(start + len) as usize];
        let l = len as usize - 1;
        for (x, &r) in line.iter_mut().zip(ranks) {
            *x = src[r as usize];
        }
        halve_line(&mut line[..=l], a_first, |level, lo, hi| {
            left[ranks[level] as usize] = lo;
            right[ranks[l - level] as usize] = hi;
        });
    }
}

/// `m` components of degree `d` and `n × n` partials of degree `dd`, in `k` cell variables, as
/// blocks of one array: component `i` at `i · pc`, partial `(row, col)` at
/// `m · pc + (row · n + col) · nc`.
#[derive(Clone)]
pub(crate) struct Flat {
    k: usize,
    m: usize,
    n: usize,
    d: u32,
    dd: u32,
    pc: usize,
    nc: usize,
    coeffs: [f64; FLAT_CAP],
}

impl Flat {
    /// The record of `p` (components) and `num` (rows of partials), all in the same `k ≤ 3`
    /// variables, the components of one degree `≤ FLAT_DEGREE` and the partials of one degree;
    /// `None` otherwise (use the kernel's polynomials).
    pub(crate) fn new(p: &[Bernstein], num: &[Vec<Bernstein>]) -> Option<Flat> {
        let first = p.first()?;
        let (k, d) = (first.vars(), first.degree());
        let n = num.len();
        if k == 0 || k > FLAT_VARS || d as usize > FLAT_DEGREE || n == 0 {
            return None;
        }
        let dd = num[0].first()?.degree();
        if dd as usize > FLAT_DEGREE {
            return None;
        }
        let (pc, nc) = (multi_index::count(k, d), multi_index::count(k, dd));
        let mut flat = Flat::zeroed(k, p.len(), n, (d, pc), (dd, nc))?;
        let m = flat.m;
        for (i, pi) in p.iter().enumerate() {
            if pi.vars() != k || pi.degree() != d {
                return None;
            }
            flat.coeffs[i * pc..(i + 1) * pc].copy_from_slice(pi.coeffs());
        }
        for (row, entries) in num.iter().enumerate() {
            if entries.len() != n {
                return None;
            }
            for (col, e) in entries.iter().enumerate() {
                if e.vars() != k || e.degree() != dd {
                    return None;
                }
                let at = m * pc + (row * n + col) * nc;
                flat.coeffs[at..at + nc].copy_from_slice(e.coeffs());
            }
        }
        Some(flat)
    }

    /// A record of `m` polynomials of degree `d` (`pc` coefficients each) and `n × n` entries of
    /// degree `dd` (`nc` each) in `k` variables, all zero; `None` when they do not fit in
    /// [`FLAT_CAP`] numbers.
    fn zeroed(
        k: usize,
        m: usize,
        n: usize,
        (d, pc): (u32, usize),
        (dd, nc): (u32, usize),
    ) -> Option<Flat> {
        if m * pc + n * n * nc > FLAT_CAP {
            return None;
        }
        Some(Flat {
            k,
            m,
            n,
            d,
            dd,
            pc,
            nc,
            coeffs: [0.0; FLAT_CAP],
        })
    }

    /// [`Flat::new`] of `p` and `num` (polynomials in the same `m` variables) restricted to the
    /// face spanned by `vertices` ([`crate::homothety::restrict_to_face`] of each, the same bits),
    /// restricted straight into the record by one batched walk per degree: no kernel polynomial
    /// per entry (13 allocations per root region of a 3D patch, and the walk's index work
    /// shared). `None` where [`Flat::new`] of the restrictions would give `None`, or a shape the
    /// batched walk does not cover (then restrict with the kernel's polynomials and try
    /// [`Flat::new`]).
    pub(crate) fn restricted(
        p: &[Bernstein],
        num: &[Vec<Bernstein>],
        vertices: &[[f64; 4]],
        level: &mut BatchLevels,
    ) -> Option<Flat> {
        let first = p.first()?;
        let (vars, d) = (first.vars(), first.degree());
        let (k, n, m) = (vertices.len(), num.len(), p.len());
        if k == 0 || k > FLAT_VARS || d as usize > FLAT_DEGREE || n == 0 || m > BATCH {
            return None;
        }
        let dd = num[0].first()?.degree();
        if dd as usize > FLAT_DEGREE || n * n > BATCH {
            return None;
        }
        if p.iter().any(|pi| pi.vars() != vars || pi.degree() != d)
            || num.iter().any(|row| {
                row.len() != n || row.iter().any(|e| e.vars() != vars || e.degree() != dd)
            })
        {
            return None;
        }
        let (pc, nc) = (coeff_count(k, d), coeff_count(k, dd));
        let mut flat = Flat::zeroed(k, m, n, (d, pc), (dd, nc))?;
        let mut srcs: [&[f64]; BATCH] = [&[]; BATCH];
        for (s, pi) in srcs.iter_mut().zip(p) {
            *s = pi.coeffs();
        }
        let (head, tail) = flat.coeffs.split_at_mut(m * pc);
        if !restrict_batch_into(&srcs[..m], (vars, d), vertices, level, head, pc) {
            return None;
        }
        for (s, e) in srcs.iter_mut().zip(num.iter().flatten()) {
            *s = e.coeffs();
        }
        if !restrict_batch_into(&srcs[..n * n], (vars, dd), vertices, level, tail, nc) {
            return None;
        }
        Some(flat)
    }

    /// Component `i`'s coefficients.
    pub(crate) fn component(&self, i: usize) -> &[f64] {
        &self.coeffs[i * self.pc..(i + 1) * self.pc]
    }

    /// Partial `(row, col)`'s coefficients.
    pub(crate) fn partial(&self, row: usize, col: usize) -> &[f64] {
        let at = self.m * self.pc + (row * self.n + col) * self.nc;
        &self.coeffs[at..at + self.nc]
    }

    /// Cell variables (3 for a triangle, 2 for a segment).
    pub(crate) fn vars(&self) -> usize {
        self.k
    }

    /// Degree of the components.
    pub(crate) fn degree(&self) -> u32 {
        self.d
    }

    /// Degree of the partials.
    pub(crate) fn partial_degree(&self) -> u32 {
        self.dd
    }

    /// Number of components.
    pub(crate) fn components(&self) -> usize {
        self.m
    }

    /// Both halves of the cell split at the midpoint of edge `(a, b)`: the one keeping vertex `a`
    /// first, as [`Bernstein::split_edge`] gives them, bit for bit.
    pub(crate) fn split(&self, a: usize, b: usize) -> (Flat, Flat) {
        let mut left = self.clone();
        let mut right = self.clone();
        let a_first = a < b;
        let top = self.m * self.pc;
        // The m output polynomials of degree d, then the n x n Jacobian entries of degree dd.
        let blocks = [
            (self.d, 0, self.pc, self.m),
            (self.dd, top, self.nc, self.n * self.n),
        ];
        for (degree, base, stride, count) in blocks {
            let plan = split_plan(self.k, degree, a, b);
            for i in 0..count {
                let r = base + i * stride..base + (i + 1) * stride;
                split_block(
                    plan,
                    a_first,
                    &self.coeffs[r.clone()],
                    &mut left.coeffs[r.clone()],
                    &mut right.coeffs[r],
                );
            }
        }
        (left, right)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// The kernel's `Bernstein::split_edge` is the reference, bit for bit, for every shape and
    /// edge the record holds, over several generations of splits.
    #[test]
    fn splits_equal_the_kernel_bit_for_bit() {
        let mut rng = ChaCha8Rng::seed_from_u64(29);
        for k in 1..=FLAT_VARS {
            for d in 0..=FLAT_DEGREE as u32 {
                for n in 1..=3usize {
                    let m = n + 1;
                    let dd = d.saturating_sub(1);
                    let p: Vec<Bernstein> = (0..m)
                        .map(|_| Bernstein::from_fn(k, d, |_| rng.random_range(-2.0..2.0)))
                        .collect();
                    let num: Vec<Vec<Bernstein>> = (0..n)
                        .map(|_| {
                            (0..n)
                                .map(|_| Bernstein::from_fn(k, dd, |_| rng.random_range(-3.0..3.0)))
                                .collect()
                        })
                        .collect();
                    let Some(mut flat) = Flat::new(&p, &num) else {
                        assert!(
                            m * multi_index::count(k, d) + n * n * multi_index::count(k, dd)
                                > FLAT_CAP
                        );
                        continue;
                    };
                    let (mut p, mut num) = (p, num);
                    for _ in 0..5 {
                        if k < 2 {
                            break;
                        }
                        let a = rng.random_range(0..k);
                        let mut b = rng.random_range(0..k - 1);
                        if b >= a {
                            b += 1;
                        }
                        let keep_left = rng.random_bool(0.5);
                        let (l, r) = flat.split(a, b);
                        flat = if keep_left { l } else { r };
                        let pick = |(x, y): (Bernstein, Bernstein)| if keep_left { x } else { y };
                        p = p.iter().map(|q| pick(q.split_edge(a, b))).collect();
                        num = num
                            .iter()
                            .map(|row| row.iter().map(|q| pick(q.split_edge(a, b))).collect())
                            .collect();
                        for (i, q) in p.iter().enumerate() {
                            let same = q
                                .coeffs()
                                .iter()
                                .zip(flat.component(i))
                                .all(|(x, y)| x.to_bits() == y.to_bits());
                            assert!(same, "k {k} d {d} n {n} component {i}");
                        }
                        for (row, entries) in num.iter().enumerate() {
                            for (col, q) in entries.iter().enumerate() {
                                let same = q
                                    .coeffs()
                                    .iter()
                                    .zip(flat.partial(row, col))
                                    .all(|(x, y)| x.to_bits() == y.to_bits());
                                assert!(same, "k {k} d {d} n {n} partial {row} {col}");
                            }
                        }
                    }
                }
            }
        }
    }
}

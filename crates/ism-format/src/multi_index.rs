//! Multi-indices of Bernstein polynomials on a simplex and their canonical order (spec §4).
//!
//! The canonical order of all `I ∈ ℕᵐ` with `|I| = d` is *lexicographically decreasing*: `I₀`
//! descending, ties broken by `I₁` descending, and so on. For `m = 3, d = 2`:
//! `200, 110, 101, 020, 011, 002`.

/// Binomial coefficient `C(n, k)`, saturating at `u64::MAX` (callers bound the inputs).
pub fn binomial(n: u64, k: u64) -> u64 {
    if k > n {
        return 0;
    }
    let k = k.min(n - k);
    let mut acc: u128 = 1;
    for i in 0..k {
        acc = acc * u128::from(n - i) / u128::from(i + 1);
        if acc > u128::from(u64::MAX) {
            return u64::MAX;
        }
    }
    acc as u64
}

/// Number of multi-indices of degree `d` in `m` variables: `C(d + m − 1, m − 1)`.
pub fn count(m: usize, d: u32) -> usize {
    if m == 0 {
        return usize::from(d == 0);
    }
    binomial(u64::from(d) + m as u64 - 1, m as u64 - 1) as usize
}

/// Number of multi-indices of degree `d` owned by a face with `m = k + 1` vertices, i.e. with every
/// entry positive: `C(d − 1, k)`.
pub fn owned_count(m: usize, d: u32) -> usize {
    if m == 0 || d == 0 || (d as usize) < m {
        return 0;
    }
    binomial(u64::from(d) - 1, m as u64 - 1) as usize
}

/// All multi-indices of degree `d` in `m` variables, in canonical order, flattened (`m` per index).
pub fn all(m: usize, d: u32) -> Vec<u32> {
    let mut out = Vec::with_capacity(count(m, d) * m);
    let mut cur = vec![0u32; m];
    fill(&mut cur, 0, d, &mut out, 0);
    out
}

/// The multi-indices of degree `d` in `m` variables with every entry `≥ 1` (those a face with `m`
/// vertices owns), in canonical order, flattened.
pub fn owned(m: usize, d: u32) -> Vec<u32> {
    if owned_count(m, d) == 0 {
        return Vec::new();
    }
    let mut out = Vec::with_capacity(owned_count(m, d) * m);
    let mut cur = vec![0u32; m];
    fill(&mut cur, 0, d, &mut out, 1);
    out
}

fn fill(cur: &mut [u32], pos: usize, remaining: u32, out: &mut Vec<u32>, min_entry: u32) {
    let m = cur.len();
    if m == 0 {
        return;
    }
    if pos == m - 1 {
        if remaining >= min_entry {
            cur[pos] = remaining;
            out.extend_from_slice(cur);
        }
        return;
    }
    let reserve = min_entry * (m - pos - 1) as u32;
    if remaining < reserve + min_entry {
        return;
    }
    let mut v = remaining - reserve;
    loop {
        cur[pos] = v;
        fill(cur, pos + 1, remaining - v, out, min_entry);
        if v == min_entry {
            break;
        }
        v -= 1;
    }
}

/// Position of `index` in the canonical order of all multi-indices of its degree.
///
/// Counts the indices that precede it: for each position `p`, those that agree before `p` and
/// have a larger entry at `p`.
pub fn rank(index: &[u32]) -> usize {
    let m = index.len();
    let mut remaining: u32 = index.iter().sum();
    let mut r = 0usize;
    for (p, &entry) in index.iter().enumerate().take(m.saturating_sub(1)) {
        // Indices with a larger entry e > entry at position p: the rest (m-p-1 vars) sums to
        // remaining - e.
        for e in (entry + 1)..=remaining {
            r += count(m - p - 1, remaining - e);
        }
        remaining -= entry;
    }
    r
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn canonical_order_matches_spec_example() {
        assert_eq!(
            all(3, 2),
            vec![2, 0, 0, 1, 1, 0, 1, 0, 1, 0, 2, 0, 0, 1, 1, 0, 0, 2]
        );
        assert_eq!(owned(3, 4), vec![2, 1, 1, 1, 2, 1, 1, 1, 2]);
        assert_eq!(owned(2, 3), vec![2, 1, 1, 2]);
    }

    #[test]
    fn counts_and_ranks_agree_with_enumeration() {
        for m in 1..=5 {
            for d in 0..=9 {
                let idx = all(m, d);
                assert_eq!(idx.len(), count(m, d) * m);
                for (r, chunk) in idx.chunks(m).enumerate() {
                    assert_eq!(rank(chunk), r);
                    assert_eq!(chunk.iter().sum::<u32>(), d);
                }
                let own = owned(m, d);
                assert_eq!(own.len(), owned_count(m, d) * m);
                assert!(own.chunks(m).all(|c| c.iter().all(|&e| e >= 1)));
            }
        }
        assert_eq!(owned_count(4, 4), 1);
        assert_eq!(owned_count(3, 2), 0);
        assert_eq!(binomial(10, 3), 120);
    }
}

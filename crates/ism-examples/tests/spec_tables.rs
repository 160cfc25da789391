//! The worked example of `spec/ism-format.md` §4.5 agrees with the reference implementation's
//! multi-index functions, and the spec's rank formula (§4.3) with `multi_index::rank`.

use ism_format::multi_index::{all, binomial, owned, rank};

fn spec_text() -> String {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../../spec/ism-format.md");
    std::fs::read_to_string(path).expect("spec/ism-format.md")
}

/// One row of the §4.5 table as computed from `ism_format`: local multi-index, sorted face, J,
/// owned index, owned count, slice start/end, placement.
fn computed_rows() -> Vec<String> {
    let sigma = [7u32, 2, 9, 4];
    let d = 3;
    all(4, d)
        .chunks(4)
        .enumerate()
        .map(|(r, local)| {
            let mut face: Vec<u32> = (0..4).filter(|&i| local[i] > 0).map(|i| sigma[i]).collect();
            face.sort_unstable();
            let pos = |g: u32| sigma.iter().position(|&s| s == g).unwrap();
            let j: Vec<u32> = face.iter().map(|&g| local[pos(g)]).collect();
            let m = face.len();
            let list = owned(m, d);
            let index = list.chunks(m).position(|c| c == j.as_slice()).unwrap();
            // Spec §4.4: the position among owned indices is rank(J − 1).
            let shifted: Vec<u32> = j.iter().map(|e| e - 1).collect();
            assert_eq!(rank(&shifted), index);
            let digits = |v: &[u32]| v.iter().map(|e| e.to_string()).collect::<String>();
            let place: Vec<String> = face
                .iter()
                .enumerate()
                .map(|(c, &g)| format!("c{c}→w{}", pos(g)))
                .collect();
            format!(
                "| {r} | `{}` | {{{}}} | `{}` | {index} of {} | `points[{}..{}]` | {} |",
                digits(local),
                face.iter()
                    .map(|g| g.to_string())
                    .collect::<Vec<_>>()
                    .join(", "),
                digits(&j),
                list.len() / m,
                index * m,
                index * m + m,
                place.join(", ")
            )
        })
        .collect()
}

#[test]
fn worked_example_table_matches_the_reference_implementation() {
    let text = spec_text();
    let start = text
        .find("| rank | local `I` |")
        .expect("table header in §4.5");
    let rows: Vec<&str> = text[start..]
        .lines()
        .skip(2)
        .take_while(|l| l.starts_with('|'))
        .collect();
    assert_eq!(rows.len(), 20);
    for (spec_row, ours) in rows.iter().zip(computed_rows()) {
        assert_eq!(*spec_row, ours);
    }
}

#[test]
fn spec_rank_formula_matches_rank() {
    // rank(I) = Σ_p Σ_{e = I_p + 1}^{r_p} C(r_p − e + m − p − 2, m − p − 2), r_p = d − I_0 − … − I_{p−1}.
    for m in 1..=5usize {
        for d in 0..=7u32 {
            for (r, idx) in all(m, d).chunks(m).enumerate() {
                let mut total = 0u64;
                let mut rest = d;
                for (p, &entry) in idx.iter().enumerate().take(m.saturating_sub(1)) {
                    for e in (entry + 1)..=rest {
                        total +=
                            binomial(u64::from(rest - e) + (m - p - 2) as u64, (m - p - 2) as u64);
                    }
                    rest -= entry;
                }
                assert_eq!(total as usize, r, "m = {m}, d = {d}, I = {idx:?}");
                assert_eq!(rank(idx), r);
            }
        }
    }
}

#[test]
fn spec_canonical_order_example() {
    let text = spec_text();
    assert!(text.contains("`d = 2`: `200, 110, 101, 020, 011, 002`"));
    let listed: Vec<String> = all(3, 2)
        .chunks(3)
        .map(|c| c.iter().map(|e| e.to_string()).collect::<String>())
        .collect();
    assert_eq!(listed.join(", "), "200, 110, 101, 020, 011, 002");
}

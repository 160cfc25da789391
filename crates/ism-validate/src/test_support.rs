//! Helpers shared by the certificate tests: exact Bernstein evaluation and exact dyadic sample
//! points, so that each test's ground truth comes from rational arithmetic, not from the floating
//! kernel under test.

use ism_format::multi_index;
use num_bigint::BigInt;
use num_rational::BigRational;
use num_traits::{One, Zero};
use rand::Rng;

/// `Σ c_K B_K(w)` in exact rationals, for barycentric `w` of `m` coordinates; every `c_K` is
/// taken as the exact dyadic value of its double.
pub(crate) fn exact_bernstein(
    m: usize,
    degree: u32,
    coefficients: &[f64],
    w: &[BigRational],
) -> BigRational {
    let fact = |k: u32| (1..=k).fold(BigInt::one(), |a, x| a * x);
    multi_index::all(m, degree)
        .chunks(m)
        .zip(coefficients)
        .map(|(k, &c)| {
            let mut term = BigRational::from_integer(fact(degree))
                * crate::exact::rational(c).expect("finite coefficient");
            for (wc, &e) in w.iter().zip(k) {
                term /= BigRational::from_integer(fact(e));
                for _ in 0..e {
                    term *= wc;
                }
            }
            term
        })
        .fold(BigRational::zero(), |a, t| a + t)
}

/// The `m` vertices of the reference simplex, then `random` barycentric points whose coordinates
/// are multiples of 2⁻¹⁰ summing to exactly 1 (so every coordinate is an exact double and the
/// point is exactly on the simplex).
pub(crate) fn vertices_and_dyadic_points<R: Rng>(
    rng: &mut R,
    m: usize,
    random: usize,
) -> Vec<Vec<f64>> {
    let mut points: Vec<Vec<f64>> = (0..m)
        .map(|i| (0..m).map(|j| f64::from(u8::from(i == j))).collect())
        .collect();
    for _ in 0..random {
        let raw: Vec<u32> = (0..m).map(|_| rng.random_range(0..1024)).collect();
        let total = raw.iter().sum::<u32>().max(1);
        let mut w: Vec<u32> = raw.iter().map(|&x| x * 1024 / total).collect();
        let rest: u32 = w[1..].iter().sum();
        w[0] = 1024 - rest.min(1024);
        points.push(w.iter().map(|&x| f64::from(x) / 1024.0).collect());
    }
    points
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    /// The dyadic points sum to exactly 1 and lie on the simplex; the Bernstein sum of the
    /// coefficients `c_K = 1` is 1 at each of them (partition of unity), and of `c_K = K_0` is
    /// `d·w_0` (linear precision) — identities independent of the code under test.
    #[test]
    fn points_are_on_the_simplex_and_bernstein_reproduces_linear_functions() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        for m in 2..=4 {
            for degree in 1..=5u32 {
                let ones = vec![1.0; multi_index::count(m, degree)];
                let first: Vec<f64> = multi_index::all(m, degree)
                    .chunks(m)
                    .map(|k| f64::from(k[0]))
                    .collect();
                for w in vertices_and_dyadic_points(&mut rng, m, 5) {
                    assert_eq!(w.iter().sum::<f64>(), 1.0);
                    assert!(w.iter().all(|&x| (0.0..=1.0).contains(&x)));
                    let q: Vec<BigRational> = w
                        .iter()
                        .map(|&x| crate::exact::rational(x).unwrap())
                        .collect();
                    assert_eq!(exact_bernstein(m, degree, &ones, &q), BigRational::one());
                    let d = BigRational::from_integer(BigInt::from(degree));
                    assert_eq!(exact_bernstein(m, degree, &first, &q), d * &q[0]);
                }
            }
        }
    }
}

//! The faces of a complex, and deterministic pseudo-random numbers keyed by face.

use ism_format::{Model, Topology};

/// Every distinct `k`-face of the complex (`k + 1` sorted vertex ids each), flat and sorted
/// lexicographically. `k = 0` gives the used vertices, `k = n` the top simplices. The faces are
/// the indexed model's ([`Topology::sorted_faces`]): nothing here enumerates faces again. A model
/// whose arrays are unsound or with a simplex repeating a vertex has none (empty).
///
/// ```
/// use ism_examples::{faces_of_dimension, kuhn_grid_2d, Aabb};
/// let m = kuhn_grid_2d(1, 1, Aabb::cube(0.0, 1.0), |p| p[0] - 0.5)?;
/// assert_eq!(faces_of_dimension(&m, 1), vec![0, 1, 0, 2, 0, 3, 1, 3, 2, 3]);
/// # Ok::<(), ism_examples::Error>(())
/// ```
pub fn faces_of_dimension(model: &Model, k: usize) -> Vec<u32> {
    Topology::of_complex(model).map_or_else(Vec::new, |t| t.sorted_faces(model, k))
}

/// A reproducible pseudo-random stream keyed by a seed and a face.
///
/// Hand-written (SplitMix64, Steele et al. 2014) rather than a `rand` generator because each face
/// needs its own stream derived from its vertex ids: the numbers must not depend on the order in
/// which faces are visited or on the number of threads, and must stay the same across versions of
/// any dependency, since checked-in example files are regenerated from them.
#[derive(Clone, Debug)]
pub struct FaceRng {
    state: u64,
}

impl FaceRng {
    /// The stream for `face` under `seed`.
    pub fn new(seed: u64, face: &[u32]) -> FaceRng {
        let mut rng = FaceRng {
            state: seed ^ 0x6A09_E667_F3BC_C908,
        };
        for &id in face {
            rng.state ^= rng.next_u64().wrapping_add(u64::from(id));
        }
        rng.state ^= face.len() as u64;
        rng
    }

    /// The next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in `[−1, 1)`, with 53 random bits.
    pub fn symmetric(&mut self) -> f64 {
        let unit = (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64;
        2.0 * unit - 1.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{kuhn_grid_3d, Aabb};

    #[test]
    fn face_counts_of_a_kuhn_cube_grid_satisfy_euler() {
        let m = kuhn_grid_3d(3, 2, 2, Aabb::cube(0.0, 1.0), |p| p[0] - 0.3).unwrap();
        let counts: Vec<usize> = (0..4)
            .map(|k| faces_of_dimension(&m, k).len() / (k + 1))
            .collect();
        // A triangulated ball has Euler characteristic 1.
        assert_eq!(
            counts[0] as i64 - counts[1] as i64 + counts[2] as i64 - counts[3] as i64,
            1
        );
        assert_eq!(counts[0], 4 * 3 * 3);
        assert_eq!(counts[3], 6 * 12);
        // Cross-check against a direct count: each interior triangle lies in 2 tets, each boundary
        // one in 1; the boundary of the box has 2 triangles per boundary square.
        let boundary_squares = 2 * (3 * 2 + 3 * 2 + 2 * 2);
        assert_eq!(4 * counts[3], 2 * counts[2] - 2 * boundary_squares);
    }

    #[test]
    fn rng_is_keyed_by_face_and_seed() {
        let a: Vec<u64> = (0..4)
            .map(|_| FaceRng::new(7, &[1, 2]).next_u64())
            .collect();
        assert!(a.windows(2).all(|w| w[0] == w[1]));
        assert_ne!(
            FaceRng::new(7, &[1, 2]).next_u64(),
            FaceRng::new(7, &[1, 3]).next_u64()
        );
        assert_ne!(
            FaceRng::new(7, &[1, 2]).next_u64(),
            FaceRng::new(8, &[1, 2]).next_u64()
        );
        assert_ne!(
            FaceRng::new(7, &[1, 2]).next_u64(),
            FaceRng::new(7, &[1, 2, 3]).next_u64()
        );
        let mut r = FaceRng::new(1, &[5]);
        let xs: Vec<f64> = (0..1000).map(|_| r.symmetric()).collect();
        assert!(xs.iter().all(|x| (-1.0..1.0).contains(x)));
        let mean = xs.iter().sum::<f64>() / 1000.0;
        assert!(mean.abs() < 0.1, "{mean}");
    }
}

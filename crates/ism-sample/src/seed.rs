//! Reproducible random streams: every chunk of work draws from its own ChaCha stream.
//!
//! A run is split into chunks of a fixed number of samples; chunk `i` of purpose `p` uses the
//! ChaCha8 generator seeded with the user's seed and switched to stream `(p << 48) | i`. Which
//! thread runs a chunk, and in what order, cannot change what it draws, so the output is bit for bit
//! the same for any thread count.

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

/// Samples per chunk: large enough to amortize the per-chunk setup and rayon overhead, small
/// enough to balance two to a few dozen cores and to keep a chunk's buffer in cache.
pub const CHUNK: usize = 4096;

/// The independent purposes that draw random numbers in one run.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u64)]
pub enum Purpose {
    /// Points on the surface.
    Surface = 1,
    /// Points in the complex or a box.
    Volume = 2,
    /// Surface points displaced off the surface.
    NearSurface = 3,
}

/// The generator of chunk `chunk` for `purpose`.
pub fn chunk_rng(seed: u64, purpose: Purpose, chunk: u64) -> ChaCha8Rng {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(((purpose as u64) << 48) | (chunk & ((1 << 48) - 1)));
    rng
}

/// Splits `count` samples into chunk sizes (all [`CHUNK`] but the last).
pub fn chunk_sizes(count: u64) -> impl Iterator<Item = usize> {
    let full = count / CHUNK as u64;
    let rest = (count % CHUNK as u64) as usize;
    (0..full).map(|_| CHUNK).chain((rest > 0).then_some(rest))
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::Rng;

    #[test]
    fn streams_differ_and_repeat() {
        let a: u64 = chunk_rng(7, Purpose::Surface, 0).random();
        let b: u64 = chunk_rng(7, Purpose::Surface, 1).random();
        let c: u64 = chunk_rng(7, Purpose::Volume, 0).random();
        let a2: u64 = chunk_rng(7, Purpose::Surface, 0).random();
        assert_eq!(a, a2);
        assert!(a != b && a != c && b != c);
        assert_eq!(
            chunk_sizes(2 * CHUNK as u64 + 5).collect::<Vec<_>>(),
            vec![CHUNK, CHUNK, 5]
        );
        assert_eq!(chunk_sizes(0).count(), 0);
    }
}

//! The test suites' one pseudo-random sequence: Knuth's MMIX linear congruential generator.
//! Tests need fixed, platform-independent inputs, not statistical quality, so a dependency-free
//! recurrence of a few lines does (each test names its own seed).

/// `x ← 6364136223846793005·x + 1442695040888963407 (mod 2⁶⁴)`.
pub(crate) struct Lcg(u64);

impl Lcg {
    /// The generator starting from `seed`.
    pub(crate) fn new(seed: u64) -> Lcg {
        Lcg(seed)
    }

    /// The next state, all 64 bits (callers keep high bits: an LCG's low bits have short
    /// periods).
    pub(crate) fn next_u64(&mut self) -> u64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        self.0
    }

    /// Uniform in `[0, 1)`: the state's top 53 bits.
    pub(crate) fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }
}

//! The unit tests' random numbers: a small xorshift generator, reproducible from its seed, so a
//! failing case fails again. Kept rather than swapped for `fastrand` (a dependency here only
//! behind the `testkit` feature): the drift tests' strength was checked on these sequences (the
//! tests fail when the bounds are cut), and another generator would draw other cases.

/// xorshift64 (Marsaglia); the seed must not be 0.
pub struct Rng(pub u64);

impl Rng {
    pub fn next(&mut self) -> u64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        self.0
    }

    /// Uniform in [0, 1).
    pub fn unit(&mut self) -> f64 {
        (self.next() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// In 0..k (with the modulo's small bias, which these tests do not mind).
    pub fn below(&mut self, k: u64) -> u64 {
        self.next() % k
    }
}

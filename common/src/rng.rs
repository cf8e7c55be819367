//! Deterministic pseudo-random numbers for synthetic data and tests: SplitMix64 (Steele, Lea &
//! Flood, "Fast splittable pseudorandom number generators", OOPSLA 2014; the constants of
//! Vigna's public-domain reference `splitmix64.c`, which is also the seeder of the xoshiro
//! family). One `u64` of state, no dependency, the same sequence on every platform, so synthetic
//! scenes and randomised tests are reproducible from their seed.
//!
//! Not for anything secret (the state is recoverable from one output), and not a statistical
//! workhorse beyond test data: scenes, noise fills, random rows.

/// The SplitMix64 generator: state `s` advances by the golden-ratio increment
/// `0x9E3779B97F4A7C15` per draw and each output is the 64-bit finaliser of the new state
/// (xor-shift 30, multiply, xor-shift 27, multiply, xor-shift 31).
///
/// A seed is any `u64` (0 included); the first output for seed 0 is `0xE220A8397B1DCDAF`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SplitMix64 {
    state: u64,
}

/// One SplitMix64 step on a bare state word: advances `state` and returns the next output (the
/// same sequence as [`SplitMix64::next_u64`] started from that state as seed).
pub fn splitmix64(state: &mut u64) -> u64 {
    *state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
    let mut z = *state;
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

impl SplitMix64 {
    /// A generator whose state starts at `seed`.
    pub fn new(seed: u64) -> Self {
        Self { state: seed }
    }

    /// The next 64 uniformly distributed bits.
    pub fn next_u64(&mut self) -> u64 {
        splitmix64(&mut self.state)
    }

    /// Uniform in `[0, 1)` with 53 random bits (the top 53 bits of [`SplitMix64::next_u64`]
    /// scaled by 2^-53, so every value is an exact multiple of 2^-53).
    pub fn next_f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Uniform in `[lo, hi)` (for `lo < hi`): `lo + (hi - lo) · u` with `u` from
    /// [`SplitMix64::next_f64`]; f64 rounding may land on `hi` when the interval is tiny.
    pub fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.next_f64()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// SplitMix64 written from its definition with wide (u128) arithmetic reduced mod 2^64, an
    /// implementation independent of the wrapping ops above.
    fn reference(seed: u64, n: usize) -> Vec<u64> {
        const M: u128 = 1 << 64;
        let mut s = seed as u128;
        (0..n)
            .map(|_| {
                s = (s + 0x9E37_79B9_7F4A_7C15) % M;
                let mut z = s;
                z = ((z ^ (z >> 30)) * 0xBF58_476D_1CE4_E5B9) % M;
                z = ((z ^ (z >> 27)) * 0x94D0_49BB_1331_11EB) % M;
                (z ^ (z >> 31)) as u64
            })
            .collect()
    }

    #[test]
    fn matches_the_published_reference_outputs() {
        // First outputs of Vigna's splitmix64.c for seeds 0 and 1234567 (the latter are the
        // test vectors quoted with the algorithm).
        let cases: [(u64, [u64; 5]); 2] = [
            (
                0,
                [
                    0xE220_A839_7B1D_CDAF,
                    0x6E78_9E6A_A1B9_65F4,
                    0x06C4_5D18_8009_454F,
                    0xF88B_B8A8_724C_81EC,
                    0x1B39_896A_51A8_749B,
                ],
            ),
            (
                1_234_567,
                [
                    6_457_827_717_110_365_317,
                    3_203_168_211_198_807_973,
                    9_817_491_932_198_370_423,
                    4_593_380_528_125_082_431,
                    16_408_922_859_458_223_821,
                ],
            ),
        ];
        for (seed, want) in cases {
            let mut r = SplitMix64::new(seed);
            let got: Vec<u64> = (0..5).map(|_| r.next_u64()).collect();
            assert_eq!(got, want, "seed {seed}");
        }
    }

    #[test]
    fn matches_the_wide_arithmetic_definition() {
        for seed in [
            0,
            1,
            0x5eed,
            u64::MAX,
            0x9E37_79B9_7F4A_7C15u64.wrapping_neg(),
        ] {
            let mut r = SplitMix64::new(seed);
            let mut bare = seed;
            for (i, want) in reference(seed, 64).into_iter().enumerate() {
                assert_eq!(r.next_u64(), want, "seed {seed:#x}, draw {i}");
                assert_eq!(
                    splitmix64(&mut bare),
                    want,
                    "bare, seed {seed:#x}, draw {i}"
                );
            }
        }
    }

    #[test]
    fn floats_are_the_top_53_bits() {
        let mut a = SplitMix64::new(42);
        let mut b = SplitMix64::new(42);
        for _ in 0..1000 {
            let bits = a.next_u64() >> 11;
            let u = b.next_f64();
            assert!((0.0..1.0).contains(&u));
            assert_eq!(u * 9_007_199_254_740_992.0, bits as f64);
        }
        let mut a = SplitMix64::new(7);
        let mut b = SplitMix64::new(7);
        for _ in 0..1000 {
            let x = a.range(-3.0, 5.0);
            assert_eq!(x, -3.0 + 8.0 * b.next_f64());
            assert!((-3.0..5.0).contains(&x));
        }
    }
}

//! Random streams and sample patterns.
//!
//! Every random decision is drawn from a stream keyed on `(seed, i, j, replicate)` (the
//! pbrt-v4 rule: work item i has its own stream), so results depend only on the seed and
//! patch ids, never on the thread count or the order rows are computed in.
//!
//! The generator is PCG32 (O'Neill 2014, XSH-RR output, 64-bit state), seeded through
//! SplitMix64 (Steele, Lea and Flood 2014) of the key.

/// SplitMix64 finaliser: a bijective 64-bit mix.
#[inline]
pub fn mix64(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// PCG32 random number generator.
#[derive(Clone, Debug)]
pub struct Pcg32 {
    state: u64,
    inc: u64,
}

impl Pcg32 {
    /// A stream keyed on a seed and up to three integers.
    pub fn keyed(seed: u64, a: u64, b: u64, c: u64) -> Pcg32 {
        let k = mix64(seed ^ mix64(a ^ mix64(b ^ mix64(c))));
        let mut r = Pcg32 {
            state: 0,
            inc: (mix64(k ^ 0xDA94_2042_E4DD_58B5) << 1) | 1,
        };
        r.next_u32();
        r.state = r.state.wrapping_add(k);
        r.next_u32();
        r
    }

    /// Next 32 random bits.
    #[inline]
    pub fn next_u32(&mut self) -> u32 {
        let old = self.state;
        self.state = old
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(self.inc);
        let xorshifted = (((old >> 18) ^ old) >> 27) as u32;
        let rot = (old >> 59) as u32;
        xorshifted.rotate_right(rot)
    }

    /// Uniform double in [0, 1) with 53 random bits.
    #[inline]
    pub fn next_f64(&mut self) -> f64 {
        let hi = (self.next_u32() as u64) << 21;
        let lo = (self.next_u32() >> 11) as u64;
        ((hi | lo) as f64) * (1.0 / (1u64 << 53) as f64)
    }

    /// Uniform integer in [0, n) (Lemire's method without the rejection refinement's bias
    /// for n far below 2^32: the bias is below 2^-32 n).
    #[inline]
    pub fn below(&mut self, n: u32) -> u32 {
        ((self.next_u32() as u64 * n as u64) >> 32) as u32
    }
}

/// Jittered samples on an `s x s` grid of strata of the unit square, in stratum order.
pub fn jittered(rng: &mut Pcg32, s: usize, out: &mut Vec<(f64, f64)>) {
    out.clear();
    let inv = 1.0 / s as f64;
    for b in 0..s {
        for a in 0..s {
            out.push((
                (a as f64 + rng.next_f64()) * inv,
                (b as f64 + rng.next_f64()) * inv,
            ));
        }
    }
}

/// Shuffles a slice in place (Fisher-Yates).
pub fn shuffle<T>(rng: &mut Pcg32, v: &mut [T]) {
    for k in (1..v.len()).rev() {
        let j = rng.below(k as u32 + 1) as usize;
        v.swap(k, j);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn streams_differ_and_repeat() {
        let a: Vec<u32> = (0..4)
            .map({
                let mut r = Pcg32::keyed(1, 2, 3, 4);
                move |_| r.next_u32()
            })
            .collect();
        let b: Vec<u32> = (0..4)
            .map({
                let mut r = Pcg32::keyed(1, 2, 3, 4);
                move |_| r.next_u32()
            })
            .collect();
        let c: Vec<u32> = (0..4)
            .map({
                let mut r = Pcg32::keyed(1, 3, 2, 4);
                move |_| r.next_u32()
            })
            .collect();
        assert_eq!(a, b);
        assert_ne!(a, c);
    }

    #[test]
    fn uniform_mean_and_variance() {
        let mut r = Pcg32::keyed(7, 0, 0, 0);
        let n = 200_000;
        let xs: Vec<f64> = (0..n).map(|_| r.next_f64()).collect();
        let mean = xs.iter().sum::<f64>() / n as f64;
        let var = xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n as f64;
        // Standard error of the mean is sqrt(1/12 / n) = 6.5e-4; 5 sigma.
        assert!(
            (mean - 0.5).abs() < 5.0 * (1.0f64 / 12.0 / n as f64).sqrt(),
            "{mean}"
        );
        assert!((var - 1.0 / 12.0).abs() < 2e-3, "{var}");
    }
}

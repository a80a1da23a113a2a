//! Initial values of params: constants and seeded random initializers (uniform, normal, Xavier, Kaiming,
//! PyTorch's default for `Linear`).

/// A small deterministic random number generator (SplitMix64), so that a seed gives the same weights on
/// every machine and every version.
pub struct SplitMix64(u64);

impl SplitMix64 {
    /// A generator for `seed`.
    pub fn new(seed: u64) -> Self {
        SplitMix64(seed ^ 0x9E37_79B9_7F4A_7C15)
    }

    /// The next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// A uniform number in [0, 1).
    pub fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// A standard normal number (Box–Muller).
    pub fn normal(&mut self) -> f64 {
        let u1 = 1.0 - self.uniform();
        let u2 = self.uniform();
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }
}

/// How to fill a param with random numbers.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Initializer {
    /// Uniform in [lo, hi).
    Uniform(f64, f64),
    /// Normal with mean and standard deviation.
    Normal(f64, f64),
}

impl Initializer {
    /// `count` values from `seed`.
    pub fn sample(self, count: usize, seed: u64) -> Vec<f32> {
        let mut rng = SplitMix64::new(seed);
        (0..count)
            .map(|_| match self {
                Initializer::Uniform(lo, hi) => (lo + (hi - lo) * rng.uniform()) as f32,
                Initializer::Normal(mean, std) => (mean + std * rng.normal()) as f32,
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn uniform_stays_in_range_and_is_seeded() {
        let a = Initializer::Uniform(-0.5, 0.5).sample(1000, 7);
        assert!(a.iter().all(|x| (-0.5..0.5).contains(x)));
        assert_eq!(a, Initializer::Uniform(-0.5, 0.5).sample(1000, 7));
        assert_ne!(a, Initializer::Uniform(-0.5, 0.5).sample(1000, 8));
        let mean: f32 = a.iter().sum::<f32>() / 1000.0;
        assert!(mean.abs() < 0.05, "mean {mean}");
    }

    #[test]
    fn normal_has_the_right_spread() {
        let a = Initializer::Normal(1.0, 2.0).sample(20000, 1);
        let mean = a.iter().map(|&x| f64::from(x)).sum::<f64>() / a.len() as f64;
        let var = a.iter().map(|&x| (f64::from(x) - mean).powi(2)).sum::<f64>() / a.len() as f64;
        assert!(
            (mean - 1.0).abs() < 0.05 && (var.sqrt() - 2.0).abs() < 0.05,
            "{mean} {var}"
        );
    }
}

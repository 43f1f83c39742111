//! Seeded random generators, one per optimisation step or epoch: a run's
//! draws depend only on (seed, stream, step), so a resumed run draws the
//! same batches as an uninterrupted one.

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

/// Which sequence of draws a generator belongs to (XORed into the seed, so
/// two phases of one run never share draws).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stream {
    /// Photorealistic fitting: ray batches and TV subsets.
    Fit = 0,
    /// The stylization's colour refit.
    Refit = 0x5EF1,
    /// The stylization's image steps (pseudo-ray batches, TV subsets).
    ImageStep = 0x1A6E,
}

/// The generator of step `step` of `stream` under `seed`.
pub fn step_rng(seed: u64, stream: Stream, step: usize) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(seed ^ stream as u64 ^ (step as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15))
}

/// The generator of epoch `epoch`'s view order under `seed`.
pub fn epoch_rng(seed: u64, epoch: usize) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(seed ^ (epoch as u64 + 1).wrapping_mul(0xA24B_AED4_963E_E407))
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::Rng;

    #[test]
    fn streams_and_steps_draw_differently_and_repeatably() {
        let draw = |mut r: ChaCha8Rng| r.random::<u64>();
        assert_eq!(draw(step_rng(7, Stream::Fit, 3)), draw(step_rng(7, Stream::Fit, 3)));
        assert_ne!(draw(step_rng(7, Stream::Fit, 3)), draw(step_rng(7, Stream::Fit, 4)));
        assert_ne!(draw(step_rng(7, Stream::Refit, 3)), draw(step_rng(7, Stream::ImageStep, 3)));
        assert_ne!(draw(epoch_rng(7, 0)), draw(epoch_rng(7, 1)));
    }
}

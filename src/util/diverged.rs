//! A run whose loss stops being a finite number stops at once, saying where,
//! instead of training on (and checkpointing) a field of NaNs.

use anyhow::{Result, bail};

use crate::util::progress::Phase;

/// An error when `loss` (step `step`, counted from 1, of `phase`) is NaN or
/// infinite; `kept` says what on disk is still good (called only then: the
/// check runs every step).
pub fn check_loss(loss: f32, phase: Phase, step: usize, kept: impl FnOnce() -> String) -> Result<()> {
    if loss.is_finite() {
        return Ok(());
    }
    let kept = kept();
    bail!(
        "the {phase} diverged at step {step}: its loss is {loss} (a learning rate too high for this scene?); \
         stopped before writing anything from it; {kept}"
    )
}

/// The name of the first array holding a NaN or an infinity, if any.
pub fn first_non_finite<'a>(arrays: &[(&'a str, &[f32])]) -> Option<&'a str> {
    arrays.iter().find(|(_, a)| a.iter().any(|v| !v.is_finite())).map(|(name, _)| *name)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_nan_or_infinite_loss_names_phase_and_step() {
        assert!(check_loss(0.25, Phase::Fit, 3, || unreachable!("only asked on divergence")).is_ok());
        let e = check_loss(f32::NAN, Phase::ImageEpochs, 7, || "nothing written".into()).unwrap_err().to_string();
        assert!(e.contains("image epochs diverged at step 7") && e.contains("NaN"), "{e}");
        assert!(check_loss(f32::INFINITY, Phase::Refit, 1, String::new).is_err());
        assert_eq!(first_non_finite(&[("a", &[1.0]), ("b", &[0.0, f32::NAN])]), Some("b"));
        assert_eq!(first_non_finite(&[("a", &[1.0])]), None);
    }
}

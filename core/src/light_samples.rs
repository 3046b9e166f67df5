//! `--light-samples N` (`JobSpec.light_samples`): how many samples of each light that is
//! not a delta light the integrators take at every hit.
//!
//! One sample per hit is the usual path tracer's set-up and dray's default. Bolstad 2017
//! casts 10-100 area-light shadow rays per hit at 16 spp, and its probability hit maps
//! pay where shadow rays are many; this setting reproduces that set-up (issue 43), and
//! trades rays for less noise in soft shadows at the same spp.
//!
//! Only lights with an extent take N samples (the emitter chosen by power, the sun's
//! disk, the environment map): a punctual light's one shadow ray is already exact.

/// The most samples of each light a job may ask for. Every hit then casts up to
/// `3 * MAX_LIGHT_SAMPLES` shadow rays besides one per punctual light, and tiles' credit
/// is sized for it (`Integrator::credit_needed`, tested at the deepest depth, the most
/// samples and the most lights); it is also 2.5 times Bolstad's largest count.
pub const MAX_LIGHT_SAMPLES: u32 = 256;

/// Samples per hit of each light that is not a delta light: 1..=[`MAX_LIGHT_SAMPLES`].
/// The default is 1, which renders the same bits as before the setting existed.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct LightSamples(u32);

/// A light-sample count out of range; names the value so a caller can name its field
/// or flag.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0} is out of range (1..={MAX_LIGHT_SAMPLES})")]
pub struct LightSamplesError(pub u32);

impl LightSamples {
    /// One sample per light, the default.
    pub const ONE: LightSamples = LightSamples(1);

    /// `n` samples, when it is in 1..=[`MAX_LIGHT_SAMPLES`].
    pub fn new(n: u32) -> Result<LightSamples, LightSamplesError> {
        if (1..=MAX_LIGHT_SAMPLES).contains(&n) {
            Ok(LightSamples(n))
        } else {
            Err(LightSamplesError(n))
        }
    }

    /// The count a job spec's optional field gives: absent means 1.
    pub fn from_spec(n: Option<u32>) -> Result<LightSamples, LightSamplesError> {
        n.map_or(Ok(LightSamples::ONE), LightSamples::new)
    }

    /// The count, in 1..=[`MAX_LIGHT_SAMPLES`].
    pub fn get(self) -> u32 {
        self.0
    }
}

impl Default for LightSamples {
    fn default() -> LightSamples {
        LightSamples::ONE
    }
}

impl std::str::FromStr for LightSamples {
    type Err = String;

    /// The CLI's `--light-samples N`.
    fn from_str(s: &str) -> Result<LightSamples, String> {
        let n: u32 = s
            .trim()
            .parse()
            .map_err(|_| format!("expected a whole number 1..={MAX_LIGHT_SAMPLES}, got {s:?}"))?;
        LightSamples::new(n).map_err(|e| e.to_string())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_in_range_are_taken_and_absent_means_one() {
        assert_eq!(LightSamples::default().get(), 1);
        assert_eq!(LightSamples::from_spec(None), Ok(LightSamples::ONE));
        assert_eq!(
            LightSamples::from_spec(Some(16)).map(LightSamples::get),
            Ok(16)
        );
        assert_eq!(
            LightSamples::new(MAX_LIGHT_SAMPLES).map(LightSamples::get),
            Ok(MAX_LIGHT_SAMPLES)
        );
        assert_eq!("10".parse::<LightSamples>().map(LightSamples::get), Ok(10));
    }

    #[test]
    fn zero_and_beyond_the_bound_are_refused_naming_the_bound() {
        for n in [0, MAX_LIGHT_SAMPLES + 1, u32::MAX] {
            let e = LightSamples::new(n).expect_err("out of range");
            assert_eq!(e, LightSamplesError(n));
            assert_eq!(
                e.to_string(),
                format!("{n} is out of range (1..={MAX_LIGHT_SAMPLES})")
            );
        }
        assert_eq!(LightSamples::from_spec(Some(0)), Err(LightSamplesError(0)));
        assert!("-1".parse::<LightSamples>().is_err());
        assert!("many".parse::<LightSamples>().is_err());
    }
}

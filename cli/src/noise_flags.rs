//! The flags that tame noise and feed denoisers (`--clamp-indirect`,
//! `--noise-threshold`, `--aov`), shared
//! by `dray render` and `dray submit` through [`crate::job_flags::JobFlags`], and the
//! `JobSpec` fields they set.

use anyhow::{Result, anyhow};
use clap::Args;
use dray_core::aov::AovSet;

#[derive(Args, Debug, Clone, Default)]
#[command(next_help_heading = crate::help_heading::NOISE)]
pub struct NoiseFlags {
    /// Clamp indirect light: every contribution of light that reached the eye by two or
    /// more surfaces is scaled so that its largest component is at most X (as Cycles'
    /// Clamp Indirect). Removes fireflies for some lost energy; direct light is never
    /// clamped. Counted in the summary and `--stats` (`clamped_indirect`). Default: no
    /// clamp.
    #[arg(long, value_name = "X", value_parser = parse_clamp)]
    pub clamp_indirect: Option<f32>,
    /// Adaptive sampling: after each progressive pass from 16 samples on, a 32x32 tile
    /// whose noise estimate (the change of its pixels over the pass, relative to the
    /// square root of their brightness, as Cycles measures it) is below X takes no more
    /// samples. Above 0, at most 1; 0.01 is Cycles' default. Needs passes (doubling is
    /// used unless --passes says otherwise). The summary and `--stats` count the tiles
    /// stopped and samples saved; `--aov samples` shows each pixel's count. Default:
    /// every tile takes --spp.
    #[arg(long, value_name = "X", value_parser = parse_threshold)]
    pub noise_threshold: Option<f32>,
    /// AOVs to write into the --exr file as more channels, comma-separated: albedo
    /// (albedo.R/G/B), normal (normal.X/Y/Z, world space), depth (depth.Z, distance
    /// from the camera; +inf where nothing was hit), samples (samples.Y). Each is the
    /// camera rays' first hit averaged over the pixel's samples: what a denoiser (OIDN:
    /// albedo, normal) or a compositor needs.
    #[arg(long, value_name = "NAME,...", value_delimiter = ',')]
    pub aov: Vec<String>,
}

impl NoiseFlags {
    /// The AOVs `--aov` names.
    pub fn aovs(&self) -> Result<AovSet> {
        AovSet::parse(&self.aov).map_err(|e| anyhow!("--aov: {e}"))
    }
}

/// `--clamp-indirect X`, checked as the coordinator checks `JobSpec.clamp_indirect`.
fn parse_clamp(s: &str) -> Result<f32, String> {
    let x = s
        .trim()
        .parse::<f32>()
        .map_err(|_| format!("{s:?} is not a number"))?;
    dray_core::clamp::check_limit(x)
}

/// `--noise-threshold X`, checked as the coordinator checks `JobSpec.noise_threshold`.
fn parse_threshold(s: &str) -> Result<f32, String> {
    let x = s
        .trim()
        .parse::<f32>()
        .map_err(|_| format!("{s:?} is not a number"))?;
    dray_core::adaptive::check_threshold(x)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn clamp_values_and_their_errors() {
        assert_eq!(parse_clamp("10"), Ok(10.0));
        assert_eq!(parse_clamp(" 0.5 "), Ok(0.5));
        for (bad, says) in [
            ("x", "\"x\" is not a number"),
            ("0", "finite number above 0, got 0"),
            ("-2", "finite number above 0, got -2"),
            ("inf", "finite number above 0, got inf"),
            ("NaN", "finite number above 0, got NaN"),
        ] {
            let e = parse_clamp(bad).expect_err(bad);
            assert!(e.contains(says), "{bad}: {e}");
        }
    }

    #[test]
    fn threshold_values_and_their_errors() {
        assert_eq!(parse_threshold("0.01"), Ok(0.01));
        for (bad, says) in [
            ("x", "\"x\" is not a number"),
            ("0", "default), got 0"),
            ("-0.5", "default), got -0.5"),
            ("2", "default), got 2"),
            ("NaN", "default), got NaN"),
        ] {
            let e = parse_threshold(bad).expect_err(bad);
            assert!(e.contains(says), "{bad}: {e}");
        }
    }

    #[test]
    fn aov_names_and_their_errors() {
        let flags = |names: &[&str]| NoiseFlags {
            aov: names.iter().map(|s| s.to_string()).collect(),
            ..NoiseFlags::default()
        };
        assert_eq!(
            flags(&["normal", "albedo"]).aovs().expect("valid").names(),
            ["albedo", "normal"]
        );
        let e = flags(&["albdo"]).aovs().expect_err("typo").to_string();
        assert!(e.starts_with("--aov: unknown AOV \"albdo\""), "{e}");
        let e = flags(&["depth", "depth"])
            .aovs()
            .expect_err("twice")
            .to_string();
        assert!(e.contains("named twice"), "{e}");
    }
}

//! The flags that add lights to a job (`--sun`), shared by `dray render` and `dray
//! submit` through [`crate::job_flags::JobFlags`], and their `JobSpec.lighting`.

use clap::Args;
use dray_core::sun::{SUN_DIAMETER_DEG, Sun};
use dray_proto::v1::{LightingSpec, SunSpec};

#[derive(Args, Debug, Clone, Default)]
#[command(next_help_heading = crate::help_heading::LIGHTS)]
pub struct LightFlags {
    /// A sun at azimuth AZ (degrees around +Y, from +Z toward +X) and elevation EL
    /// (degrees above the XZ plane, -90..=90), giving IRRADIANCE (default 1) to a surface
    /// facing it: a disk the real sun's 0.53 degrees wide, so shadows have soft edges.
    /// Like a light of the scene, it makes the default environment black (--env adds a
    /// sky).
    #[arg(
        long,
        value_name = "AZ,EL[,IRRADIANCE]",
        allow_hyphen_values = true,
        value_parser = parse_sun
    )]
    pub sun: Option<SunSpec>,
}

impl LightFlags {
    /// `JobSpec.lighting` for these flags (absent when they add no light).
    pub fn lighting_spec(&self) -> Option<LightingSpec> {
        self.sun.map(|sun| LightingSpec { sun: Some(sun) })
    }
}

/// `--sun AZ,EL[,IRRADIANCE]`, checked as the coordinator will check it, so a bad value
/// is refused here with the flag's name rather than by the server with a field's.
fn parse_sun(s: &str) -> Result<SunSpec, String> {
    let vals = s
        .split(',')
        .map(|p| {
            p.trim()
                .parse::<f32>()
                .map_err(|_| format!("{:?} is not a number", p.trim()))
        })
        .collect::<Result<Vec<f32>, String>>()?;
    let (az, el, irradiance) = match vals.as_slice() {
        [az, el] => (*az, *el, DEFAULT_IRRADIANCE),
        [az, el, e] => (*az, *el, *e),
        _ => return Err(format!("expected AZ,EL or AZ,EL,IRRADIANCE, got {s:?}")),
    };
    Sun::new(az, el, irradiance, SUN_DIAMETER_DEG).map_err(|e| e.to_string())?;
    Ok(SunSpec {
        azimuth_deg: az,
        elevation_deg: el,
        irradiance: Some(irradiance),
        angular_diameter_deg: Some(SUN_DIAMETER_DEG),
    })
}

/// `--sun`'s irradiance when only AZ,EL are given (the coordinator's default too).
const DEFAULT_IRRADIANCE: f32 = dray_coordinator::lighting::DEFAULT_SUN_IRRADIANCE;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sun_values_and_their_errors() {
        let s = parse_sun("30,45").expect("az,el");
        assert_eq!(
            (s.azimuth_deg, s.elevation_deg, s.irradiance),
            (30.0, 45.0, Some(1.0))
        );
        let s = parse_sun("-30, 10, 5").expect("az,el,e");
        assert_eq!(
            (s.azimuth_deg, s.elevation_deg, s.irradiance),
            (-30.0, 10.0, Some(5.0))
        );
        for (bad, says) in [
            ("30", "expected AZ,EL"),
            ("1,2,3,4", "expected AZ,EL"),
            ("x,45", "\"x\" is not a number"),
            ("0,NaN", "elevation must be"),
            ("0,91", "elevation must be"),
            ("0,-90.5", "elevation must be"),
            ("inf,45", "azimuth must be"),
            ("0,45,-1", "irradiance must be"),
            ("0,45,nan", "irradiance must be"),
        ] {
            let e = parse_sun(bad).expect_err(bad);
            assert!(e.contains(says), "{bad}: {e}");
        }
    }
}

//! `JobSpec.lighting`: check the lights a job adds, fill in their defaults (so GetJob
//! and the workers see every value the render used) and make them ready to sample.

use dray_core::lighting::Lighting;
use dray_core::sun::{SUN_DIAMETER_DEG, Sun, SunError};
use dray_proto::v1::LightingSpec;
use tonic::Status;

/// The default `lighting.sun.irradiance`.
pub const DEFAULT_SUN_IRRADIANCE: f32 = 1.0;

/// Check `spec` and fill in its defaults in place; errors name the field.
pub fn check_lighting(spec: &mut Option<LightingSpec>) -> Result<Lighting, Status> {
    let Some(spec) = spec.as_mut() else {
        return Ok(Lighting::default());
    };
    let sun = match spec.sun.as_mut() {
        None => None,
        Some(s) => {
            let irradiance = *s.irradiance.get_or_insert(DEFAULT_SUN_IRRADIANCE);
            let diameter = *s.angular_diameter_deg.get_or_insert(SUN_DIAMETER_DEG);
            let sun =
                Sun::new(s.azimuth_deg, s.elevation_deg, irradiance, diameter).map_err(|e| {
                    let field = match e {
                        SunError::Azimuth(_) => "azimuth_deg",
                        SunError::Elevation(_) => "elevation_deg",
                        SunError::Irradiance(_) => "irradiance",
                        SunError::Diameter(_) => "angular_diameter_deg",
                    };
                    Status::invalid_argument(format!("lighting.sun.{field}: {e}"))
                })?;
            Some(sun)
        }
    };
    Ok(Lighting { sun, env_map: None })
}

#[cfg(test)]
mod tests {
    use super::*;
    use dray_proto::v1::SunSpec;

    #[test]
    fn defaults_are_filled_in_and_bad_values_name_their_field() {
        let mut spec = Some(LightingSpec {
            sun: Some(SunSpec {
                azimuth_deg: 10.0,
                elevation_deg: 30.0,
                ..SunSpec::default()
            }),
        });
        let l = check_lighting(&mut spec).expect("valid");
        let sun = l.sun.expect("a sun");
        assert_eq!(sun.irradiance, DEFAULT_SUN_IRRADIANCE);
        let s = spec.and_then(|l| l.sun).expect("sun spec");
        assert_eq!(
            (s.irradiance, s.angular_diameter_deg),
            (Some(DEFAULT_SUN_IRRADIANCE), Some(SUN_DIAMETER_DEG))
        );
        let none = check_lighting(&mut None).expect("none");
        assert!(none.sun.is_none() && none.env_map.is_none());
        for (sun, field) in [
            (
                SunSpec {
                    elevation_deg: 91.0,
                    ..SunSpec::default()
                },
                "lighting.sun.elevation_deg",
            ),
            (
                SunSpec {
                    elevation_deg: f32::NAN,
                    ..SunSpec::default()
                },
                "lighting.sun.elevation_deg",
            ),
            (
                SunSpec {
                    azimuth_deg: f32::INFINITY,
                    ..SunSpec::default()
                },
                "lighting.sun.azimuth_deg",
            ),
            (
                SunSpec {
                    irradiance: Some(-1.0),
                    ..SunSpec::default()
                },
                "lighting.sun.irradiance",
            ),
            (
                SunSpec {
                    angular_diameter_deg: Some(0.0),
                    ..SunSpec::default()
                },
                "lighting.sun.angular_diameter_deg",
            ),
        ] {
            let e = check_lighting(&mut Some(LightingSpec { sun: Some(sun) })).expect_err(field);
            assert_eq!(e.code(), tonic::Code::InvalidArgument);
            assert!(e.message().starts_with(field), "{}", e.message());
        }
    }
}

//! The flags that add lights to a job (`--sun`, `--env-map`, `--env-rotation`,
//! `--env-intensity`), shared by `dray render` and `dray submit` through
//! [`crate::job_flags::JobFlags`], and their `JobSpec.lighting`.

use clap::Args;
use dray_core::sun::{SUN_DIAMETER_DEG, Sun};
use dray_proto::v1::{EnvMapSpec, LightingSpec, SunSpec};

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

    /// An environment map lighting the scene from every direction: an equirectangular
    /// Radiance .hdr or OpenEXR .exr (at most 4096x2048), +Y up, the image's centre
    /// looking along -Z. It replaces the constant sky (--env). `dray render` reads FILE
    /// from here; `dray submit` names it under the coordinator's scene root, which
    /// serves it to the workers.
    #[arg(long, value_name = "FILE")]
    pub env_map: Option<String>,

    /// Degrees the environment map is turned about +Y (counter-clockwise seen from
    /// above). Default 0.
    #[arg(
        long,
        value_name = "DEG",
        requires = "env_map",
        allow_hyphen_values = true,
        value_parser = parse_rotation
    )]
    pub env_rotation: Option<f32>,

    /// Factor on the environment map's radiance (finite, >= 0). Default 1.
    #[arg(
        long,
        value_name = "X",
        requires = "env_map",
        allow_hyphen_values = true,
        value_parser = parse_intensity
    )]
    pub env_intensity: Option<f32>,
}

impl LightFlags {
    /// `JobSpec.lighting` for these flags (absent when they add no light).
    pub fn lighting_spec(&self) -> Option<LightingSpec> {
        let env_map = self.env_map.as_ref().map(|path| EnvMapSpec {
            path: path.clone(),
            rotation_deg: Some(self.env_rotation.unwrap_or(DEFAULT_ROTATION)),
            intensity: Some(self.env_intensity.unwrap_or(DEFAULT_INTENSITY)),
        });
        (self.sun.is_some() || env_map.is_some()).then_some(LightingSpec {
            sun: self.sun,
            env_map,
        })
    }
}

/// A coordinator's error about `lighting.*` with the flag that set the field in place
/// of the field's name, so `dray render` names what the user typed.
pub fn flag_error(message: &str) -> String {
    for (field, flag) in [
        ("lighting.env_map.path", "--env-map"),
        ("lighting.env_map.rotation_deg", "--env-rotation"),
        ("lighting.env_map.intensity", "--env-intensity"),
        ("lighting.sun", "--sun"),
    ] {
        if let Some(rest) = message.strip_prefix(field) {
            let rest =
                rest.trim_start_matches(|c: char| c == '.' || c.is_alphanumeric() || c == '_');
            return format!("{flag}{rest}");
        }
    }
    message.to_string()
}

/// `--env-rotation DEG`: any finite number of degrees.
fn parse_rotation(s: &str) -> Result<f32, String> {
    let v: f32 = s
        .trim()
        .parse()
        .map_err(|_| format!("{:?} is not a number", s.trim()))?;
    if !v.is_finite() {
        return Err(format!("must be a finite number of degrees, got {v}"));
    }
    Ok(v)
}

/// `--env-intensity X`: finite and non-negative.
fn parse_intensity(s: &str) -> Result<f32, String> {
    let v: f32 = s
        .trim()
        .parse()
        .map_err(|_| format!("{:?} is not a number", s.trim()))?;
    if !(v.is_finite() && v >= 0.0) {
        return Err(format!("must be finite and non-negative, got {v}"));
    }
    Ok(v)
}

/// `--env-rotation`'s default (the coordinator's too).
const DEFAULT_ROTATION: f32 = dray_coordinator::lighting::DEFAULT_ENV_ROTATION_DEG;
/// `--env-intensity`'s default (the coordinator's too).
const DEFAULT_INTENSITY: f32 = dray_coordinator::lighting::DEFAULT_ENV_INTENSITY;

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

    #[test]
    fn env_map_values_and_their_errors() {
        assert_eq!(parse_rotation("-90").unwrap(), -90.0);
        assert!(parse_rotation("inf").unwrap_err().contains("finite"));
        assert!(parse_rotation("x").unwrap_err().contains("not a number"));
        assert_eq!(parse_intensity("2.5").unwrap(), 2.5);
        assert!(parse_intensity("-1").unwrap_err().contains("non-negative"));
        assert!(parse_intensity("nan").unwrap_err().contains("non-negative"));
        let flags = LightFlags {
            env_map: Some("sky.hdr".into()),
            env_intensity: Some(3.0),
            ..LightFlags::default()
        };
        let e = flags.lighting_spec().and_then(|l| l.env_map).expect("map");
        assert_eq!(
            (e.path.as_str(), e.rotation_deg, e.intensity),
            ("sky.hdr", Some(0.0), Some(3.0))
        );
        assert!(LightFlags::default().lighting_spec().is_none());
        assert_eq!(
            flag_error("lighting.env_map.path: environment map x.hdr: no such file"),
            "--env-map: environment map x.hdr: no such file"
        );
        assert_eq!(
            flag_error("lighting.sun.elevation_deg: elevation must be"),
            "--sun: elevation must be"
        );
    }
}

//! The flags that add lights to a job (`--sun`, `--sun-size`, `--sun-color`,
//! `--env-map`, `--env-rotation`, `--env-intensity`) and say how many samples each
//! takes (`--light-samples`), shared by `dray render`, `dray submit` and `dray sweep`
//! through [`crate::job_flags::JobFlags`], and their `JobSpec.lighting`,
//! `JobSpec.sun_color` and `JobSpec.light_samples`.

use clap::Args;
use dray_core::light_samples::LightSamples;
use dray_core::sun::{SUN_DIAMETER_DEG, Sun};
use dray_proto::v1::{EnvMapSpec, LightingSpec, Rgb, SunSpec};

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

    /// The sun's angular diameter in degrees, in (0, 45]: a wider sun gives wider
    /// penumbrae and a softer highlight, at the same irradiance. Default 0.53 (the real
    /// sun's). Needs --sun.
    #[arg(
        long,
        value_name = "DEG",
        requires = "sun",
        allow_hyphen_values = true,
        value_parser = parse_sun_size
    )]
    pub sun_size: Option<f32>,

    /// The sun's colour: linear R,G,B factors on its irradiance (each finite and >= 0),
    /// so a surface facing it receives IRRADIANCE times each. Default 1,1,1 (white).
    /// Needs --sun.
    #[arg(
        long,
        value_name = "R,G,B",
        requires = "sun",
        allow_hyphen_values = true,
        value_parser = parse_sun_color
    )]
    pub sun_color: Option<Rgb>,

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

    /// Shadow rays per hit to each light with an extent: N samples of the scene's
    /// emitters (chosen by power), N of the sun's disk and N of the environment map,
    /// each carrying 1/N of the light (Bolstad 2017's 10-100 area-light rays per hit).
    /// Less noise in soft shadows at the same --spp, for N times their shadow rays.
    /// Punctual lights keep one exact ray each. 1..=256; default 1 (the same bits as
    /// without the flag).
    #[arg(long, value_name = "N")]
    pub light_samples: Option<LightSamples>,
}

impl LightFlags {
    /// `JobSpec.lighting` for these flags (absent when they add no light).
    pub fn lighting_spec(&self) -> Option<LightingSpec> {
        let env_map = self.env_map.as_ref().map(|path| EnvMapSpec {
            path: path.clone(),
            rotation_deg: Some(self.env_rotation.unwrap_or(DEFAULT_ROTATION)),
            intensity: Some(self.env_intensity.unwrap_or(DEFAULT_INTENSITY)),
        });
        let sun = self.sun.map(|s| SunSpec {
            angular_diameter_deg: Some(self.sun_size.unwrap_or(SUN_DIAMETER_DEG)),
            ..s
        });
        (sun.is_some() || env_map.is_some()).then_some(LightingSpec { sun, env_map })
    }

    /// `JobSpec.sun_color` for these flags (absent without --sun-color: the coordinator
    /// fills in white).
    pub fn sun_color_spec(&self) -> Option<Rgb> {
        self.sun_color
    }

    /// `JobSpec.light_samples` for these flags (absent without --light-samples: one).
    pub fn light_samples_spec(&self) -> Option<u32> {
        self.light_samples.map(LightSamples::get)
    }

    /// The samples per light these flags ask for (`dray render --workers 0`).
    pub fn light_samples(&self) -> LightSamples {
        self.light_samples.unwrap_or_default()
    }
}

/// A coordinator's error about `lighting.*` with the flag that set the field in place
/// of the field's name, so `dray render` names what the user typed.
pub fn flag_error(message: &str) -> String {
    for (field, flag) in [
        ("lighting.sun.angular_diameter_deg", "--sun-size"),
        ("sun_color", "--sun-color"),
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

/// `--sun-size DEG`, checked as the coordinator checks `lighting.sun.angular_diameter_deg`.
fn parse_sun_size(s: &str) -> Result<f32, String> {
    let v: f32 = s
        .trim()
        .parse()
        .map_err(|_| format!("{:?} is not a number", s.trim()))?;
    Sun::new(0.0, 0.0, 1.0, v).map_err(|e| e.to_string())?;
    Ok(v)
}

/// `--sun-color R,G,B`, checked as the coordinator checks `sun_color`.
fn parse_sun_color(s: &str) -> Result<Rgb, String> {
    let vals = s
        .split(',')
        .map(|p| {
            p.trim()
                .parse::<f32>()
                .map_err(|_| format!("{:?} is not a number", p.trim()))
        })
        .collect::<Result<Vec<f32>, String>>()?;
    let [r, g, b] = vals[..] else {
        return Err(format!("expected R,G,B, got {s:?}"));
    };
    Sun::new(0.0, 0.0, 1.0, SUN_DIAMETER_DEG)
        .and_then(|sun| sun.with_color(glam::Vec3::new(r, g, b)))
        .map_err(|e| e.to_string())?;
    Ok(Rgb { r, g, b })
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
    fn sun_size_and_colour_values_and_their_errors() {
        assert_eq!(parse_sun_size("2.5").unwrap(), 2.5);
        for (bad, says) in [
            ("0", "angular diameter must be"),
            ("-1", "angular diameter must be"),
            ("46", "angular diameter must be"),
            ("nan", "angular diameter must be"),
            ("x", "not a number"),
        ] {
            let e = parse_sun_size(bad).expect_err(bad);
            assert!(e.contains(says), "{bad}: {e}");
        }
        let c = parse_sun_color("1, 0.8,0.6").expect("r,g,b");
        assert_eq!((c.r, c.g, c.b), (1.0, 0.8, 0.6));
        for (bad, says) in [
            ("1,1", "expected R,G,B"),
            ("1,1,1,1", "expected R,G,B"),
            ("1,x,1", "\"x\" is not a number"),
            ("1,-0.5,1", "colour must be"),
            ("1,1,inf", "colour must be"),
        ] {
            let e = parse_sun_color(bad).expect_err(bad);
            assert!(e.contains(says), "{bad}: {e}");
        }
        let flags = LightFlags {
            sun: Some(parse_sun("10,20").expect("sun")),
            sun_size: Some(3.0),
            sun_color: Some(c),
            ..LightFlags::default()
        };
        let sun = flags.lighting_spec().and_then(|l| l.sun).expect("sun");
        assert_eq!(sun.angular_diameter_deg, Some(3.0));
        assert_eq!(flags.sun_color_spec(), Some(c));
        assert_eq!(
            flag_error("lighting.sun.angular_diameter_deg: angular diameter must be"),
            "--sun-size: angular diameter must be"
        );
        assert_eq!(
            flag_error("sun_color: colour must be"),
            "--sun-color: colour must be"
        );
    }

    #[test]
    fn light_samples_are_sent_only_when_given() {
        assert_eq!(LightFlags::default().light_samples_spec(), None);
        assert_eq!(LightFlags::default().light_samples().get(), 1);
        let flags = LightFlags {
            light_samples: Some("16".parse().expect("16")),
            ..LightFlags::default()
        };
        assert_eq!(flags.light_samples_spec(), Some(16));
        assert_eq!(flags.light_samples().get(), 16);
        let e = "0".parse::<LightSamples>().expect_err("0");
        assert_eq!(e, "0 is out of range (1..=256)");
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

//! The camera flags (`--look-from`, `--orbit`, `--aperture`, ...; docs/cameras.md),
//! shared by `dray render` and `dray submit`, and the `JobSpec.view` they make. Every
//! check of their values is the coordinator's (`dray_coordinator::view::check`), so the
//! command line and the API refuse the same things with the same words.

use anyhow::{Result, bail};
use clap::Args;
use dray_proto::v1::camera_spec::Orbit;
use dray_proto::v1::{CameraSpec, Vec3};

#[derive(Args, Debug, Clone, Default)]
#[command(next_help_heading = crate::help_heading::CAMERA)]
pub struct ViewFlags {
    /// Place the camera at "X,Y,Z" (scene units, moved with --translate); with --look-at.
    #[arg(long, value_name = "X,Y,Z", allow_hyphen_values = true)]
    pub look_from: Option<String>,
    /// The point at the image's centre, "X,Y,Z"; with --look-from.
    #[arg(long, value_name = "X,Y,Z", allow_hyphen_values = true)]
    pub look_at: Option<String>,
    /// Which way is up in the image (default +Y; with --orbit, the direction of rising
    /// elevation).
    #[arg(long, value_name = "X,Y,Z", allow_hyphen_values = true)]
    pub up: Option<String>,
    /// Vertical field of view in degrees, in (0, 180) (default 40 with --look-from or
    /// --orbit, else the scene camera's).
    #[arg(long, value_name = "DEG")]
    pub fov: Option<f32>,
    /// A camera around the scene's bounds, framing them, at azimuth AZ (degrees around
    /// +Y, 0 looking from +Z, 90 from +X) and elevation EL (degrees above the horizon,
    /// -90..=90). Not with --look-from or --camera.
    #[arg(long, value_name = "AZ,EL", allow_hyphen_values = true)]
    pub orbit: Option<String>,
    /// Parallel rays: an orthographic camera spanning, at every depth, the height the
    /// field of view spans at the look-at point (with neither --look-from nor --orbit,
    /// the point of the camera's axis nearest the scene's centre).
    #[arg(long)]
    pub orthographic: bool,
    /// A thin lens for depth of field: its radius in scene units ("0.05"), or an
    /// f-number ("f/2.8") read with the focal length the field of view gives on a 36 mm
    /// film back along the image's wider side, scene units being metres. Default: a
    /// pinhole. Also works on a scene's own camera.
    #[arg(long, value_name = "RADIUS|f/N")]
    pub aperture: Option<String>,
    /// Distance of the plane in focus along the view axis (default: the look-at point's).
    #[arg(long, value_name = "D")]
    pub focus_distance: Option<f32>,
    /// Focus on the point "X,Y,Z": the plane in focus passes through it.
    #[arg(long, value_name = "X,Y,Z", allow_hyphen_values = true)]
    pub focus_on: Option<String>,
}

/// "X,Y,Z": three numbers (finiteness is the coordinator's check, so NaN is refused
/// there with the field's name).
fn point(flag: &str, s: &str) -> Result<Vec3> {
    match numbers(flag, s)?.as_slice() {
        [x, y, z] => Ok(Vec3 {
            x: *x,
            y: *y,
            z: *z,
        }),
        _ => bail!("{flag}: expected X,Y,Z (three comma-separated numbers), got {s:?}"),
    }
}

fn numbers(flag: &str, s: &str) -> Result<Vec<f32>> {
    s.split(',')
        .map(|p| {
            p.trim()
                .parse::<f32>()
                .map_err(|_| anyhow::anyhow!("{flag}: {:?} is not a number", p.trim()))
        })
        .collect()
}

impl ViewFlags {
    /// The `JobSpec.view` these flags ask for; None when no camera flag is given (the
    /// scene's camera is used untouched).
    pub fn spec(&self) -> Result<Option<CameraSpec>> {
        let given = self.look_from.is_some()
            || self.look_at.is_some()
            || self.up.is_some()
            || self.fov.is_some()
            || self.orbit.is_some()
            || self.orthographic
            || self.aperture.is_some()
            || self.focus_distance.is_some()
            || self.focus_on.is_some();
        if !given {
            return Ok(None);
        }
        let p = |flag: &str, v: &Option<String>| v.as_deref().map(|s| point(flag, s)).transpose();
        let orbit = match self.orbit.as_deref() {
            None => None,
            Some(s) => match numbers("--orbit", s)?.as_slice() {
                [azimuth, elevation] => Some(Orbit {
                    azimuth: *azimuth,
                    elevation: *elevation,
                }),
                _ => bail!("--orbit: expected AZ,EL (two comma-separated degrees), got {s:?}"),
            },
        };
        Ok(Some(CameraSpec {
            look_from: p("--look-from", &self.look_from)?,
            look_at: p("--look-at", &self.look_at)?,
            up: p("--up", &self.up)?,
            fov: self.fov,
            orbit,
            orthographic: self.orthographic,
            aperture: self.aperture.clone().unwrap_or_default(),
            focus_distance: self.focus_distance,
            focus_on: p("--focus-on", &self.focus_on)?,
        }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn flags_make_the_view() {
        assert_eq!(ViewFlags::default().spec().unwrap(), None);
        let v = ViewFlags {
            orbit: Some("-30, 20".into()),
            aperture: Some("f/2.8".into()),
            focus_on: Some("1,-2,3".into()),
            ..Default::default()
        }
        .spec()
        .unwrap()
        .unwrap();
        assert_eq!(
            v.orbit,
            Some(Orbit {
                azimuth: -30.0,
                elevation: 20.0
            })
        );
        assert_eq!(v.aperture, "f/2.8");
        assert_eq!(v.focus_on.map(|p| (p.x, p.y, p.z)), Some((1.0, -2.0, 3.0)));
        let e = ViewFlags {
            look_from: Some("1,2".into()),
            ..Default::default()
        }
        .spec()
        .unwrap_err();
        assert!(
            e.to_string().starts_with("--look-from: expected X,Y,Z"),
            "{e}"
        );
        let e = ViewFlags {
            orbit: Some("a,1".into()),
            ..Default::default()
        }
        .spec()
        .unwrap_err();
        assert!(e.to_string().contains("\"a\" is not a number"), "{e}");
    }
}

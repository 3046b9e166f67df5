//! A camera given by where it stands, what it looks at and its lens (`dray render
//! --look-from/--look-at/--orbit/--orthographic/--aperture`, `JobSpec.view`): the one
//! place such a camera is built ([`View::camera`]), so the coordinator, `dray render
//! --workers 0` and every worker make the same camera, bit for bit, from the same
//! resolved numbers.

use glam::Vec3;

use crate::camera::{Camera, Lens, Projection};

/// A resolved view: every number the camera is made from, nothing left to the scene.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct View {
    /// Where the camera (the lens's centre) stands.
    pub eye: Vec3,
    /// The point at the image's centre.
    pub target: Vec3,
    /// Which way is up in the image (any vector not parallel to `target - eye`).
    pub up: Vec3,
    /// Vertical field of view in radians, in (0, pi). An orthographic view keeps the
    /// height this angle spans at the target's distance (`yfov` framing the same view).
    pub yfov: f32,
    /// Parallel rays instead of rays through a point.
    pub orthographic: bool,
    /// A thin lens, or None for a pinhole.
    pub lens: Option<Lens>,
}

impl View {
    /// The view a resolved `JobSpec.view` describes, read the same way by the
    /// coordinator, `dray render --workers 0` and every worker: field of view in degrees,
    /// the aperture as a radius (an f-number must have been resolved already), the
    /// focus distance used only with a lens. A radius of 0 is a pinhole.
    pub fn from_resolved(
        eye: Vec3,
        target: Vec3,
        up: Vec3,
        fov_deg: f32,
        orthographic: bool,
        aperture: &str,
        focus_distance: Option<f32>,
    ) -> Result<View, ResolvedError> {
        let radius = match aperture.trim() {
            "" => 0.0,
            a => match Aperture::parse(a)? {
                Aperture::Radius(r) => r,
                Aperture::FStop(_) => return Err(ResolvedError::FStop),
            },
        };
        let lens = if radius > 0.0 {
            let focus_distance = focus_distance.ok_or(ResolvedError::NoFocus)?;
            Some(Lens {
                radius,
                focus_distance,
            })
        } else {
            None
        };
        Ok(View {
            eye,
            target,
            up,
            yfov: fov_deg.to_radians(),
            orthographic,
            lens,
        })
    }

    /// The camera this view describes.
    pub fn camera(&self) -> Camera {
        let mut c = Camera::look_at("view", self.eye, self.target, self.up, self.yfov);
        if self.orthographic {
            let h = (self.target - self.eye).length() * (self.yfov * 0.5).tan();
            c.projection = Projection::Orthographic { xmag: h, ymag: h };
        }
        c.lens = self.lens;
        c
    }
}

/// The unit direction from the scene's centre toward a camera orbiting it at azimuth
/// `az` and elevation `el` (degrees), and the image's up there. Azimuth 0 looks from +Z
/// toward -Z (glTF's front), 90 from +X; elevation 90 looks straight down. The up is the
/// direction of rising elevation, so it is never parallel to the view, even from the
/// poles; it is +Y at elevation 0.
pub fn orbit_direction(az_deg: f32, el_deg: f32) -> (Vec3, Vec3) {
    let (sa, ca) = az_deg.to_radians().sin_cos();
    let (se, ce) = el_deg.to_radians().sin_cos();
    let dir = Vec3::new(ce * sa, se, ce * ca);
    let up = Vec3::new(-se * sa, ce, -se * ca);
    (dir, up)
}

/// The film back an f-number is read against: 36 mm along the image's wider side (a
/// full-frame sensor, and Blender's default sensor fit), so a field of view gives a
/// focal length as a camera body would.
pub const FILM_BACK_MM: f32 = 36.0;

/// `--aperture`: a lens radius in scene units, or an f-number (`f/2.8`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Aperture {
    /// Radius of the lens in scene units; 0 means a pinhole.
    Radius(f32),
    /// Focal length over aperture diameter.
    FStop(f32),
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ApertureError {
    #[error("{0:?} is neither a radius in scene units nor an f-number like f/2.8")]
    Syntax(String),
    #[error("the radius must be finite and >= 0, got {0}")]
    Radius(f32),
    #[error("the f-number must be finite and > 0, got {0}")]
    FStop(f32),
}

/// Why a resolved view cannot be read ([`View::from_resolved`]).
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ResolvedError {
    #[error("aperture: {0}")]
    Aperture(#[from] ApertureError),
    #[error("aperture: an f-number is not resolved (the coordinator resolves it to a radius)")]
    FStop,
    #[error("focus_distance: a lens needs one")]
    NoFocus,
}

impl Aperture {
    /// `"0.05"` (a radius) or `"f/2.8"` (an f-number).
    pub fn parse(s: &str) -> Result<Aperture, ApertureError> {
        let t = s.trim();
        if let Some(n) = t.strip_prefix("f/").or_else(|| t.strip_prefix("F/")) {
            let n: f32 = n
                .trim()
                .parse()
                .map_err(|_| ApertureError::Syntax(s.to_string()))?;
            if !(n.is_finite() && n > 0.0) {
                return Err(ApertureError::FStop(n));
            }
            return Ok(Aperture::FStop(n));
        }
        let r: f32 = t
            .parse()
            .map_err(|_| ApertureError::Syntax(s.to_string()))?;
        if !(r.is_finite() && r >= 0.0) {
            return Err(ApertureError::Radius(r));
        }
        Ok(Aperture::Radius(r))
    }

    /// The lens radius in scene units for a camera of vertical field of view `yfov`
    /// (radians) on an image of `aspect`. An f-number takes the focal length a
    /// [`FILM_BACK_MM`] film back gives that field of view, and scene units as metres
    /// (glTF's unit): radius = focal length / (2 N).
    pub fn radius(self, yfov: f32, aspect: f32) -> f32 {
        match self {
            Aperture::Radius(r) => r,
            Aperture::FStop(n) => {
                // The film's height: the whole back for a portrait image, less for a
                // landscape one.
                let film_h_mm = FILM_BACK_MM / aspect.max(1.0);
                let focal_mm = film_h_mm * 0.5 / (yfov * 0.5).tan();
                focal_mm / (2.0 * n) / 1000.0
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use glam::Vec2;

    use super::*;

    fn view() -> View {
        View {
            eye: Vec3::new(1.0, 2.0, 5.0),
            target: Vec3::new(-1.0, 0.5, 0.0),
            up: Vec3::Y,
            yfov: 0.6,
            orthographic: false,
            lens: None,
        }
    }

    #[test]
    fn the_centre_ray_hits_the_target() {
        for orthographic in [false, true] {
            let v = View {
                orthographic,
                ..view()
            };
            let r = v.camera().generate(Vec2::splat(0.5), 1.5);
            let to = v.target - r.origin;
            assert!(
                r.dir.cross(to.normalize()).length() < 1e-5,
                "{orthographic}"
            );
            assert!(r.dir.dot(to) > 0.0);
        }
    }

    /// An orthographic view spans at every depth the height the perspective one spans
    /// at the target.
    #[test]
    fn orthographic_frames_the_targets_plane_like_the_perspective_view() {
        let p = view().camera();
        let o = View {
            orthographic: true,
            ..view()
        }
        .camera();
        let d = (view().target - view().eye).length();
        let top_p = p.generate(Vec2::new(0.5, 0.0), 1.0);
        let top_o = o.generate(Vec2::new(0.5, 0.0), 1.0);
        // The perspective top ray at the target's depth, and the orthographic one there.
        let fwd = (view().target - view().eye).normalize();
        let at_p = top_p.origin + top_p.dir * (d / top_p.dir.dot(fwd));
        let at_o = top_o.origin + top_o.dir * (view().target - top_o.origin).dot(fwd);
        assert!((at_p - at_o).length() < 1e-4, "{at_p} {at_o}");
        // Parallel rays: the top and the centre rays share a direction.
        let c = o.generate(Vec2::splat(0.5), 1.0);
        assert!((c.dir - top_o.dir).length() < 1e-6);
    }

    #[test]
    fn orbit_directions() {
        let (d, up) = orbit_direction(0.0, 0.0);
        assert!((d - Vec3::Z).length() < 1e-6 && (up - Vec3::Y).length() < 1e-6);
        let (d, _) = orbit_direction(90.0, 0.0);
        assert!((d - Vec3::X).length() < 1e-6);
        for (az, el) in [(30.0, 90.0), (200.0, -90.0), (10.0, 45.0)] {
            let (d, up) = orbit_direction(az, el);
            assert!((d.length() - 1.0).abs() < 1e-6 && (up.length() - 1.0).abs() < 1e-6);
            assert!(d.dot(up).abs() < 1e-6, "{az},{el}");
        }
        assert!(orbit_direction(0.0, 90.0).0.y > 0.9999);
    }

    /// A 50 mm lens on a 36 x 24 mm back at f/2 has a 12.5 mm radius.
    #[test]
    fn f_numbers_use_a_full_frame_back() {
        let yfov = 2.0 * (12.0f32 / 50.0).atan();
        let r = Aperture::parse("f/2").unwrap().radius(yfov, 1.5);
        assert!((r - 0.0125).abs() < 1e-7, "{r}");
        // Portrait: the 36 mm side is vertical.
        let yfov = 2.0 * (18.0f32 / 50.0).atan();
        let r = Aperture::parse("f/2").unwrap().radius(yfov, 0.5);
        assert!((r - 0.0125).abs() < 1e-7, "{r}");
        assert_eq!(Aperture::parse(" 0.25 "), Ok(Aperture::Radius(0.25)));
        assert!(matches!(
            Aperture::parse("f/0"),
            Err(ApertureError::FStop(_))
        ));
        assert!(matches!(
            Aperture::parse("-1"),
            Err(ApertureError::Radius(_))
        ));
        assert!(matches!(
            Aperture::parse("NaN"),
            Err(ApertureError::Radius(_))
        ));
        assert!(matches!(
            Aperture::parse("wide"),
            Err(ApertureError::Syntax(_))
        ));
    }
}

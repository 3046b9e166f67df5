//! The sun (`--sun AZ,EL[,IRRADIANCE]`): a directional light with a finite angular size.
//!
//! A glTF directional light is a delta: it casts hard shadows and a mirror never shows
//! it. The real sun subtends 0.53 degrees, which is what softens a shadow's edge with
//! distance from its occluder, so the sun here is a disk of uniform radiance on the sky:
//! direct lighting samples a direction inside its cone, and a bounce ray that leaves the
//! scene inside the cone sees it (weighted against the light sample by MIS in the path
//! tracer). It belongs to the render settings, not to the scene, so every configuration
//! reads it from the job spec (`JobSpec.lighting`) and no scene package changes.
//!
//! The irradiance given is the one a surface facing the sun receives: a disk of radiance
//! `L` and half-angle `a` gives `L * pi * sin(a)^2` there, so `L` is chosen to make that
//! exactly the irradiance asked for, at any angular size.
//!
//! A colour (`--sun-color R,G,B`, linear, default white) multiplies that radiance per
//! channel, so a surface facing the sun receives `irradiance * colour`: as a glTF
//! light's `color` times its `intensity`, and Mitsuba's `irradiance` given as RGB.

use glam::{Vec2, Vec3};

/// The real sun's angular diameter, degrees.
pub const SUN_DIAMETER_DEG: f32 = 0.53;

/// The largest angular diameter accepted, degrees: a "sun" wider than this is an area
/// of sky, and cone sampling of it would no longer be the right tool.
pub const MAX_SUN_DIAMETER_DEG: f32 = 45.0;

/// Why a sun cannot be made; each names the value so a caller can name its flag.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SunError {
    #[error("azimuth must be a finite number of degrees, got {0}")]
    Azimuth(f32),
    #[error("elevation must be a number of degrees in [-90, 90], got {0}")]
    Elevation(f32),
    #[error("irradiance must be finite and non-negative, got {0}")]
    Irradiance(f32),
    #[error("angular diameter must be in (0, {MAX_SUN_DIAMETER_DEG}] degrees, got {0}")]
    Diameter(f32),
    #[error("colour must be three finite, non-negative linear values, got {0}")]
    Color(Vec3),
}

/// A disk of uniform radiance on the sky.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sun {
    /// Unit direction from the scene toward the sun's centre.
    pub direction: Vec3,
    /// Irradiance on a surface facing the sun, before the colour.
    pub irradiance: f32,
    /// Linear colour, a factor per channel (white by default).
    pub color: Vec3,
    /// Radiance of the disk before the colour: `irradiance / (pi sin^2 a)`.
    radiance: f32,
    /// `1 - cos a`, computed as `2 sin^2(a/2)` so it keeps its digits for a small `a`.
    one_minus_cos: f32,
    /// `sin^2 a`: a direction is inside the disk when its squared sine to the centre is
    /// at most this (exact where a cosine near 1 would round).
    sin2: f32,
    /// Uniform-cone pdf (1 / solid angle).
    pdf: f32,
    /// An orthonormal frame around `direction`.
    t: Vec3,
    b: Vec3,
}

impl Sun {
    /// The sun at azimuth `az_deg` (degrees around +Y from +Z toward +X) and elevation
    /// `el_deg` (degrees above the XZ plane; glTF's +Y is up), giving `irradiance` to a
    /// surface facing it, with angular diameter `diameter_deg`.
    pub fn new(
        az_deg: f32,
        el_deg: f32,
        irradiance: f32,
        diameter_deg: f32,
    ) -> Result<Sun, SunError> {
        if !az_deg.is_finite() {
            return Err(SunError::Azimuth(az_deg));
        }
        if !(-90.0..=90.0).contains(&el_deg) {
            return Err(SunError::Elevation(el_deg));
        }
        if !irradiance.is_finite() || irradiance < 0.0 {
            return Err(SunError::Irradiance(irradiance));
        }
        if !(diameter_deg > 0.0 && diameter_deg <= MAX_SUN_DIAMETER_DEG) {
            return Err(SunError::Diameter(diameter_deg));
        }
        let (az, el) = (
            f64::from(az_deg).to_radians(),
            f64::from(el_deg).to_radians(),
        );
        let d = glam::DVec3::new(az.sin() * el.cos(), el.sin(), az.cos() * el.cos()).normalize();
        let a = f64::from(diameter_deg).to_radians() * 0.5;
        let sin2 = a.sin() * a.sin();
        let one_minus_cos = 2.0 * (a * 0.5).sin().powi(2);
        let direction = d.as_vec3();
        let (t, b) = direction.any_orthonormal_pair();
        Ok(Sun {
            direction,
            irradiance,
            color: Vec3::ONE,
            radiance: (f64::from(irradiance) / (std::f64::consts::PI * sin2)) as f32,
            one_minus_cos: one_minus_cos as f32,
            sin2: sin2 as f32,
            pdf: (1.0 / (2.0 * std::f64::consts::PI * one_minus_cos)) as f32,
            t,
            b,
        })
    }

    /// The same sun with linear colour `color` (a factor per channel on its radiance;
    /// white, `Vec3::ONE`, changes no bit). Each channel must be finite and >= 0.
    pub fn with_color(self, color: Vec3) -> Result<Sun, SunError> {
        if !color.is_finite() || color.min_element() < 0.0 {
            return Err(SunError::Color(color));
        }
        Ok(Sun { color, ..self })
    }

    /// The disk's radiance, coloured (white: the same bits as a grey sun's).
    pub fn radiance(&self) -> Vec3 {
        Vec3::splat(self.radiance) * self.color
    }

    /// The solid-angle pdf of [`Sun::sample`] (the same for every direction in the disk).
    pub fn pdf(&self) -> f32 {
        self.pdf
    }

    /// A direction inside the disk, uniform in solid angle, from `u` in [0, 1)^2.
    pub fn sample(&self, u: Vec2) -> Vec3 {
        // cos(theta) = 1 - u (1 - cos a); sin from the same small quantity, not from a
        // cosine next to 1.
        let k = u.x * self.one_minus_cos;
        let cos_t = 1.0 - k;
        let sin_t = (k * (2.0 - k)).max(0.0).sqrt();
        let phi = 2.0 * std::f32::consts::PI * u.y;
        (self.t * (sin_t * phi.cos()) + self.b * (sin_t * phi.sin()) + self.direction * cos_t)
            .normalize_or(self.direction)
    }

    /// Whether unit direction `dir` points into the disk.
    pub fn contains(&self, dir: Vec3) -> bool {
        dir.dot(self.direction) > 0.0 && dir.cross(self.direction).length_squared() <= self.sin2
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn samples_lie_in_the_disk_and_the_irradiance_is_the_one_asked_for() {
        for diameter in [SUN_DIAMETER_DEG, 5.0, 40.0] {
            let sun = Sun::new(30.0, 50.0, 2.0, diameter).expect("sun");
            // E_normal = integral of L cos(theta) over the disk, estimated with the
            // sampler's own pdf: exact up to the estimator's noise.
            let n = 64;
            let mut e = 0.0f64;
            for i in 0..n {
                for j in 0..n {
                    let u = Vec2::new((i as f32 + 0.5) / n as f32, (j as f32 + 0.5) / n as f32);
                    let w = sun.sample(u);
                    assert!(sun.contains(w), "diameter {diameter}: {w} outside");
                    e += f64::from(sun.radiance * w.dot(sun.direction) / sun.pdf());
                }
            }
            e /= (n * n) as f64;
            assert!(
                (e - 2.0).abs() < 2e-3,
                "diameter {diameter}: irradiance {e}"
            );
        }
        let sun = Sun::new(0.0, 90.0, 1.0, SUN_DIAMETER_DEG).expect("sun");
        assert!((sun.direction - Vec3::Y).length() < 1e-6);
        let off = Vec3::new(0.0, 1.0, (SUN_DIAMETER_DEG * 0.6).to_radians().tan()).normalize();
        assert!(!sun.contains(off) && !sun.contains(-Vec3::Y));
    }

    #[test]
    fn bad_values_are_named() {
        assert!(matches!(
            Sun::new(f32::NAN, 0.0, 1.0, 0.53),
            Err(SunError::Azimuth(_))
        ));
        assert!(matches!(
            Sun::new(0.0, 91.0, 1.0, 0.53),
            Err(SunError::Elevation(_))
        ));
        assert!(matches!(
            Sun::new(0.0, f32::NAN, 1.0, 0.53),
            Err(SunError::Elevation(_))
        ));
        assert!(matches!(
            Sun::new(0.0, 10.0, -1.0, 0.53),
            Err(SunError::Irradiance(_))
        ));
        assert!(matches!(
            Sun::new(0.0, 10.0, f32::NAN, 0.53),
            Err(SunError::Irradiance(_))
        ));
        assert!(matches!(
            Sun::new(0.0, 10.0, 1.0, 0.0),
            Err(SunError::Diameter(_))
        ));
        assert!(Sun::new(0.0, -90.0, 0.0, 0.53).is_ok());
        let sun = Sun::new(0.0, 10.0, 1.0, 0.53).expect("sun");
        for bad in [
            Vec3::new(-0.1, 1.0, 1.0),
            Vec3::new(1.0, f32::NAN, 1.0),
            Vec3::new(1.0, 1.0, f32::INFINITY),
        ] {
            assert!(matches!(sun.with_color(bad), Err(SunError::Color(_))));
        }
    }

    /// The colour scales the radiance per channel (so the irradiance a facing surface
    /// receives is `irradiance * colour`), and white changes no bit.
    #[test]
    fn the_colour_scales_each_channel() {
        let sun = Sun::new(30.0, 50.0, 2.0, 5.0).expect("sun");
        assert_eq!(sun.with_color(Vec3::ONE).expect("white"), sun);
        let c = Vec3::new(1.0, 0.8, 0.25);
        let warm = sun.with_color(c).expect("warm");
        assert_eq!(warm.radiance(), sun.radiance() * c);
        assert_eq!(warm.pdf(), sun.pdf());
        // Recolouring replaces the colour, it does not compound it.
        let again = warm.with_color(Vec3::new(0.5, 0.5, 0.5)).expect("grey");
        assert_eq!(again.radiance(), sun.radiance() * 0.5);
        // A black channel stays black; the others keep their value.
        let blue = sun.with_color(Vec3::new(0.0, 0.0, 1.0)).expect("blue");
        assert_eq!(blue.radiance(), Vec3::new(0.0, 0.0, sun.radiance().z));
    }
}

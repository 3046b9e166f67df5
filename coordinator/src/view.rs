//! `JobSpec.view` (docs/cameras.md): checked at submission ([`check`], no scene
//! needed), then resolved once against the loaded scene ([`resolve`]) into numbers that
//! need no scene (orbit and `focus_on` become `look_from`, `look_at` and
//! `focus_distance`; an f-number becomes a radius). Workers get the resolved view in
//! their JobSetup's spec and `dray render --workers 0` uses [`resolve`] too, so every
//! configuration builds its camera with `dray_core::view::View::from_resolved` from the
//! same numbers: the same camera, bit for bit.

use dray_core::camera::{Camera, Projection};
use dray_core::view::{Aperture, View, orbit_direction};
use dray_proto::v1::{CameraSpec, Vec3 as PVec3};
use glam::Vec3;
use tonic::Status;

/// Field of view of a view that places the camera itself and names none (as the
/// camera framing a scene without cameras), degrees.
pub const DEFAULT_FOV_DEG: f32 = 40.0;

/// The sine of the least angle between `up` and the view direction: below it the image
/// has no well-defined up.
const PARALLEL_SINE: f32 = 1e-4;

fn bad(msg: String) -> Status {
    Status::invalid_argument(msg)
}

fn v3(v: &PVec3) -> Vec3 {
    Vec3::new(v.x, v.y, v.z)
}

fn p3(v: Vec3) -> PVec3 {
    PVec3 {
        x: v.x,
        y: v.y,
        z: v.z,
    }
}

/// The vector field `name` of the view, if given, refused unless finite.
fn finite(name: &str, v: Option<&PVec3>) -> Result<Option<Vec3>, Status> {
    match v.map(v3) {
        Some(p) if !p.is_finite() => Err(bad(format!(
            "view.{name}: must be finite, got ({}, {}, {})",
            p.x, p.y, p.z
        ))),
        p => Ok(p),
    }
}

/// Whether `up` is (nearly) parallel to `dir`.
fn parallel(up: Vec3, dir: Vec3) -> bool {
    let (u, d) = (up.normalize_or_zero(), dir.normalize_or_zero());
    u.cross(d).length() < PARALLEL_SINE
}

/// The checks that need no scene, each refusal naming its field. `camera` is the
/// spec's `camera`: a view that places the camera itself cannot also pick one.
pub fn check(v: &CameraSpec, camera: Option<&str>) -> Result<(), Status> {
    if v.aperture.len() > crate::text::MAX_NAME_BYTES {
        return Err(bad(format!(
            "view.aperture: {} bytes is longer than {}",
            v.aperture.len(),
            crate::text::MAX_NAME_BYTES
        )));
    }
    let from = finite("look_from", v.look_from.as_ref())?;
    let at = finite("look_at", v.look_at.as_ref())?;
    let up = finite("up", v.up.as_ref())?;
    finite("focus_on", v.focus_on.as_ref())?;
    if let Some(u) = up
        && !(u.length_squared() > 0.0 && u.length_squared().is_finite())
    {
        return Err(bad("view.up: must not be zero".into()));
    }
    match (from, at) {
        (Some(_), None) => return Err(bad("view.look_at: needed with view.look_from".into())),
        (None, Some(_)) => return Err(bad("view.look_from: needed with view.look_at".into())),
        (Some(f), Some(a)) => {
            if f == a {
                return Err(bad(format!(
                    "view.look_at: equals view.look_from ({}, {}, {}): no direction to look in",
                    f.x, f.y, f.z
                )));
            }
            if let Some(u) = up
                && parallel(u, a - f)
            {
                return Err(bad(
                    "view.up: parallel to the view direction (look_at - look_from)".into(),
                ));
            }
        }
        (None, None) => {}
    }
    if let Some(f) = v.fov
        && !(f > 0.0 && f < 180.0)
    {
        return Err(bad(format!(
            "view.fov: must be in (0, 180) degrees, got {f}"
        )));
    }
    if let Some(o) = &v.orbit {
        if from.is_some() {
            return Err(bad(
                "view.orbit: not with view.look_from/look_at (an orbit places the camera)".into(),
            ));
        }
        if !o.azimuth.is_finite() {
            return Err(bad(format!(
                "view.orbit: azimuth must be finite, got {}",
                o.azimuth
            )));
        }
        if !(-90.0..=90.0).contains(&o.elevation) {
            return Err(bad(format!(
                "view.orbit: elevation must be in [-90, 90] degrees, got {}",
                o.elevation
            )));
        }
    }
    if let Some(c) = camera
        && (from.is_some() || v.orbit.is_some())
    {
        let which = if from.is_some() { "look_from" } else { "orbit" };
        return Err(bad(format!(
            "view.{which}: not with camera {} (pick a scene camera or place one, not both)",
            crate::text::bounded(c)
        )));
    }
    let lens = match v.aperture.trim() {
        "" => false,
        a => {
            let a = Aperture::parse(a).map_err(|e| bad(format!("view.aperture: {e}")))?;
            a != Aperture::Radius(0.0)
        }
    };
    if let Some(d) = v.focus_distance {
        if !(d.is_finite() && d > 0.0) {
            return Err(bad(format!(
                "view.focus_distance: must be finite and > 0, got {d}"
            )));
        }
        if v.focus_on.is_some() {
            return Err(bad(
                "view.focus_distance: not with view.focus_on (each sets the plane in focus)".into(),
            ));
        }
    }
    if !lens && (v.focus_distance.is_some() || v.focus_on.is_some()) {
        let which = if v.focus_on.is_some() {
            "focus_on"
        } else {
            "focus_distance"
        };
        return Err(bad(format!(
            "view.{which}: only with view.aperture (a pinhole is in focus everywhere)"
        )));
    }
    Ok(())
}

/// The view resolved against the scene: `base` is the camera the spec's `camera`
/// chooses (used when the view places no camera), `bounds` the scene's box (for
/// `orbit`), `offset` the spec's `translate` (a view's points move with the scene).
/// Returns the resolved view, as workers receive it, and the camera built from it.
/// `view` must have passed [`check`].
pub fn resolve(
    v: &CameraSpec,
    base: &Camera,
    bounds: (Vec3, Vec3),
    aspect: f32,
    offset: Vec3,
) -> Result<(CameraSpec, Camera), Status> {
    let from = finite("look_from", v.look_from.as_ref())?;
    let at = finite("look_at", v.look_at.as_ref())?;
    let up = finite("up", v.up.as_ref())?;
    let focus_on = finite("focus_on", v.focus_on.as_ref())?.map(|p| p + offset);
    let (eye, target, up, fov, base_ortho) = match (from, at, &v.orbit) {
        (Some(f), Some(a), _) => (
            f + offset,
            a + offset,
            up.unwrap_or(Vec3::Y),
            v.fov.unwrap_or(DEFAULT_FOV_DEG),
            false,
        ),
        (_, _, Some(o)) => {
            let fov = v.fov.unwrap_or(DEFAULT_FOV_DEG);
            let (dir, orbit_up) = orbit_direction(o.azimuth, o.elevation);
            let (eye, centre) =
                dray_core::camera::framing_eye(bounds.0, bounds.1, aspect, dir, fov.to_radians());
            (eye, centre, up.unwrap_or(orbit_up), fov, false)
        }
        _ => from_camera(base, bounds, up, v.fov),
    };
    if !(eye.is_finite() && target.is_finite()) || eye == target {
        return Err(bad(format!(
            "view: the camera cannot be placed (from {eye} looking at {target})"
        )));
    }
    let forward = (target - eye).normalize();
    if parallel(up, forward) {
        return Err(bad(format!(
            "view.up: parallel to the view direction {forward}"
        )));
    }
    let radius = match v.aperture.trim() {
        "" => 0.0,
        a => Aperture::parse(a)
            .map_err(|e| bad(format!("view.aperture: {e}")))?
            .radius(fov.to_radians(), aspect),
    };
    if !(radius.is_finite() && radius >= 0.0) {
        return Err(bad(format!("view.aperture: gives the radius {radius}")));
    }
    let focus_distance = if radius > 0.0 {
        let d = match (v.focus_distance, focus_on) {
            (Some(d), _) => d,
            (None, Some(p)) => (p - eye).dot(forward),
            (None, None) => (target - eye).length(),
        };
        if !(d.is_finite() && d > 0.0) {
            return Err(bad(format!(
                "view.focus_on: lies {d} along the view axis, not in front of the camera"
            )));
        }
        Some(d)
    } else {
        None
    };
    let resolved = CameraSpec {
        look_from: Some(p3(eye)),
        look_at: Some(p3(target)),
        up: Some(p3(up)),
        fov: Some(fov),
        orbit: None,
        orthographic: v.orthographic || base_ortho,
        aperture: if radius > 0.0 {
            format!("{radius}")
        } else {
            String::new()
        },
        focus_distance,
        focus_on: None,
    };
    let camera = camera_of_resolved(&resolved).map_err(|e| bad(format!("view.{e}")))?;
    Ok((resolved, camera))
}

/// The placement a view with no `look_from` nor `orbit` keeps: `base`'s position, view
/// direction and up, looking at the point of its axis nearest the scene's centre
/// (which sets the orthographic height and the default focus), and its field of view.
fn from_camera(
    base: &Camera,
    bounds: (Vec3, Vec3),
    up: Option<Vec3>,
    fov: Option<f32>,
) -> (Vec3, Vec3, Vec3, f32, bool) {
    let t = base.transform;
    let eye = t.w_axis.truncate();
    let forward = (-t.z_axis.truncate()).normalize_or(Vec3::NEG_Z);
    let centre = (bounds.0 + bounds.1) * 0.5;
    let radius = ((bounds.1 - bounds.0).length() * 0.5).max(1e-6);
    let along = (centre - eye).dot(forward);
    let dist = if along.is_finite() && along > 0.0 {
        along
    } else {
        radius
    };
    let (yfov, ortho) = match base.projection {
        Projection::Perspective { yfov, .. } => (yfov, false),
        Projection::Orthographic { ymag, .. } => (2.0 * (ymag.abs() / dist).atan(), true),
    };
    let up = up.unwrap_or_else(|| t.y_axis.truncate().normalize_or(Vec3::Y));
    (
        eye,
        eye + forward * dist,
        up,
        fov.unwrap_or(yfov.to_degrees()),
        ortho,
    )
}

/// The camera a resolved view describes, as every worker builds it.
pub fn camera_of_resolved(v: &CameraSpec) -> Result<Camera, String> {
    let get = |name: &str, p: Option<&PVec3>| p.map(v3).ok_or(format!("{name}: not resolved"));
    let view = View::from_resolved(
        get("look_from", v.look_from.as_ref())?,
        get("look_at", v.look_at.as_ref())?,
        get("up", v.up.as_ref())?,
        v.fov.ok_or("fov: not resolved")?,
        v.orthographic,
        &v.aperture,
        v.focus_distance,
    )
    .map_err(|e| e.to_string())?;
    Ok(view.camera())
}

#[cfg(test)]
mod tests {
    use dray_proto::v1::camera_spec::Orbit;

    use super::*;

    fn p(x: f32, y: f32, z: f32) -> Option<PVec3> {
        Some(PVec3 { x, y, z })
    }

    fn look() -> CameraSpec {
        CameraSpec {
            look_from: p(0.0, 1.0, 5.0),
            look_at: p(0.0, 1.0, 0.0),
            ..Default::default()
        }
    }

    /// Each bad view is refused with INVALID_ARGUMENT, the message starting with the
    /// field at fault.
    #[test]
    fn bad_views_name_their_field() {
        let orbit = Some(Orbit {
            azimuth: 10.0,
            elevation: 20.0,
        });
        let cases: Vec<(CameraSpec, Option<&str>, &str)> = vec![
            (
                CameraSpec {
                    look_from: p(f32::NAN, 0.0, 0.0),
                    ..look()
                },
                None,
                "view.look_from: must be finite",
            ),
            (
                CameraSpec {
                    look_at: None,
                    ..look()
                },
                None,
                "view.look_at: needed",
            ),
            (
                CameraSpec {
                    look_from: None,
                    ..look()
                },
                None,
                "view.look_from: needed",
            ),
            (
                CameraSpec {
                    look_at: p(0.0, 1.0, 5.0),
                    ..look()
                },
                None,
                "view.look_at: equals",
            ),
            (
                CameraSpec {
                    up: p(0.0, 0.0, 0.0),
                    ..look()
                },
                None,
                "view.up: must not be zero",
            ),
            (
                CameraSpec {
                    up: p(0.0, 0.0, -2.0),
                    ..look()
                },
                None,
                "view.up: parallel",
            ),
            (
                CameraSpec {
                    fov: Some(180.0),
                    ..look()
                },
                None,
                "view.fov: must be in (0, 180)",
            ),
            (
                CameraSpec {
                    fov: Some(0.0),
                    ..look()
                },
                None,
                "view.fov",
            ),
            (
                CameraSpec {
                    fov: Some(f32::NAN),
                    ..look()
                },
                None,
                "view.fov",
            ),
            (
                CameraSpec { orbit, ..look() },
                None,
                "view.orbit: not with view.look_from",
            ),
            (
                CameraSpec {
                    orbit: Some(Orbit {
                        azimuth: 0.0,
                        elevation: 91.0,
                    }),
                    ..Default::default()
                },
                None,
                "view.orbit: elevation",
            ),
            (look(), Some("0"), "view.look_from: not with camera \"0\""),
            (
                CameraSpec {
                    orbit,
                    ..Default::default()
                },
                Some("Cam"),
                "view.orbit: not with camera",
            ),
            (
                CameraSpec {
                    aperture: "f/-2".into(),
                    ..look()
                },
                None,
                "view.aperture: the f-number",
            ),
            (
                CameraSpec {
                    aperture: "wide".into(),
                    ..look()
                },
                None,
                "view.aperture: \"wide\"",
            ),
            (
                CameraSpec {
                    focus_distance: Some(3.0),
                    ..look()
                },
                None,
                "view.focus_distance: only with view.aperture",
            ),
            (
                CameraSpec {
                    focus_on: p(0.0, 0.0, 0.0),
                    aperture: "0".into(),
                    ..look()
                },
                None,
                "view.focus_on: only with",
            ),
            (
                CameraSpec {
                    aperture: "0.1".into(),
                    focus_distance: Some(-1.0),
                    ..look()
                },
                None,
                "view.focus_distance: must be finite and > 0",
            ),
            (
                CameraSpec {
                    aperture: "0.1".into(),
                    focus_distance: Some(1.0),
                    focus_on: p(0.0, 0.0, 0.0),
                    ..look()
                },
                None,
                "view.focus_distance: not with view.focus_on",
            ),
        ];
        for (v, camera, want) in cases {
            let e = check(&v, camera).expect_err(want);
            assert_eq!(e.code(), tonic::Code::InvalidArgument);
            assert!(e.message().starts_with(want), "{want}: {}", e.message());
        }
        check(&look(), None).expect("a plain look-at");
        check(
            &CameraSpec {
                aperture: "f/2.8".into(),
                ..Default::default()
            },
            Some("0"),
        )
        .expect("a lens on a scene camera");
    }

    /// Resolution leaves nothing to the scene (no orbit, no f-number, no focus point),
    /// and the camera built from the resolved view is the one returned.
    #[test]
    fn resolved_views_need_no_scene() {
        let base = Camera::framing(Vec3::splat(-1.0), Vec3::splat(1.0), 1.0);
        let bounds = (Vec3::splat(-1.0), Vec3::splat(1.0));
        let v = CameraSpec {
            orbit: Some(Orbit {
                azimuth: 30.0,
                elevation: 90.0,
            }),
            aperture: "f/2".into(),
            focus_on: p(0.0, 0.5, 0.0),
            ..Default::default()
        };
        check(&v, None).unwrap();
        let (r, cam) = resolve(&v, &base, bounds, 1.5, Vec3::ZERO).unwrap();
        assert!(r.orbit.is_none() && r.focus_on.is_none());
        let radius: f32 = r.aperture.parse().expect("a radius");
        assert!(radius > 0.0);
        // Straight down onto the centre, focused on a point 0.5 above it.
        let eye = r.look_from.map(|p| v3(&p)).unwrap();
        let dist = eye.y;
        assert!(eye.x.abs() < 1e-5 && eye.z.abs() < 1e-5, "{eye}");
        assert!((r.focus_distance.unwrap() - (dist - 0.5)).abs() < 1e-4);
        assert_eq!(camera_of_resolved(&r).unwrap(), cam);
        assert!(cam.is_valid());
        // A focus point behind the camera is refused at resolution.
        let behind = CameraSpec {
            focus_on: p(0.0, 100.0, 0.0),
            ..v
        };
        let e = resolve(&behind, &base, bounds, 1.5, Vec3::ZERO).unwrap_err();
        assert!(e.message().starts_with("view.focus_on:"), "{}", e.message());
        // Points move with the scene.
        let (r, _) = resolve(&look(), &base, bounds, 1.0, Vec3::new(10.0, 0.0, 0.0)).unwrap();
        assert_eq!(r.look_from.map(|p| p.x), Some(10.0));
    }
}

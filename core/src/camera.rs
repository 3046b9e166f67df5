//! Cameras with glTF conventions: the camera looks down its local -Z with +Y up, and its
//! placement is the world transform of the node that holds it.

use glam::{Mat4, Vec2, Vec3, Vec3A};

#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Projection {
    /// `yfov` in radians. `aspect` is the file's `aspectRatio`, kept for the record: rays
    /// always take the output image's aspect (see [`Camera::frustum`]).
    Perspective { yfov: f32, aspect: Option<f32> },
    /// Half-extents of the view volume. Rays keep `ymag` and take the horizontal extent
    /// from the image's aspect (see [`Camera::frustum`]); `xmag` gives only its sign.
    Orthographic { xmag: f32, ymag: f32 },
}

#[derive(Clone, Debug, PartialEq)]
pub struct Camera {
    pub name: String,
    /// Camera-to-world transform (may contain scale; directions are renormalised).
    pub transform: Mat4,
    pub projection: Projection,
    /// Near clip distance along the view axis (glTF `znear`); rays start there.
    pub znear: f32,
    /// A thin lens (depth of field), or None for a pinhole: every ray through the pixel
    /// passes through one point. glTF cameras have none; `JobSpec.view` adds one.
    pub lens: Option<Lens>,
}

/// A thin lens (pbrt's `PerspectiveCamera` with a lens radius): rays start on a disc of
/// `radius` around the camera's position, in its image plane, and all rays through one
/// film point meet at `focus_distance` along the view axis, so points at that depth are
/// as sharp as through a pinhole and others blur in proportion to their distance from it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Lens {
    /// Radius of the aperture in scene units, > 0.
    pub radius: f32,
    /// Distance of the plane in focus along the view axis, in scene units, > 0.
    pub focus_distance: f32,
}

/// A point of the unit disc from a point of the unit square, by Shirley and Chiu's
/// concentric map (what pbrt and Mitsuba use for lens samples): it keeps the strata of
/// the square, so nearby samples stay nearby on the lens.
pub fn concentric_disk(u: Vec2) -> Vec2 {
    let o = u * 2.0 - Vec2::ONE;
    if o.x == 0.0 && o.y == 0.0 {
        return Vec2::ZERO;
    }
    let (r, theta) = if o.x.abs() > o.y.abs() {
        (o.x, std::f32::consts::FRAC_PI_4 * (o.y / o.x))
    } else {
        (
            o.y,
            std::f32::consts::FRAC_PI_2 - std::f32::consts::FRAC_PI_4 * (o.x / o.y),
        )
    };
    Vec2::new(theta.cos(), theta.sin()) * r
}

/// A camera ray before it is given pixel and sample bookkeeping.
#[derive(Clone, Copy, Debug)]
pub struct CameraRay {
    pub origin: Vec3,
    pub dir: Vec3,
}

/// A camera ready to make an image's rays ([`Camera::frustum`]): the rays are those of
/// [`Camera::generate`], bit for bit, without a tangent per ray.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Frustum {
    transform: Mat4,
    shape: Shape,
    /// The near clip distance, at least 0.
    znear: f32,
    /// The scene's box, when rays start at it (see [`Frustum::clipped_to`]).
    scene: Option<SceneBox>,
    /// The camera's thin lens, if any (see [`Frustum::generate_through_lens`]).
    lens: Option<Lens>,
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Shape {
    Perspective { tan_half_yfov: f32, aspect: f32 },
    Orthographic { xmag: f32, ymag: f32 },
}

impl Frustum {
    /// The ray through film position `film` in [0,1]^2 (x right, y down).
    #[inline]
    pub fn generate(&self, film: Vec2) -> CameraRay {
        self.generate_through_lens(film, Vec2::splat(0.5))
    }

    /// Whether the camera has a thin lens, so its rays need a lens sample.
    #[inline]
    pub fn has_lens(&self) -> bool {
        self.lens.is_some()
    }

    /// The ray through film position `film` and lens position `lens_u` in [0,1]^2 (the
    /// lens's centre at (0.5, 0.5), ignored without a lens): the pinhole ray is moved to
    /// start at the lens point and aimed at the pinhole ray's point on the plane in focus
    /// (pbrt-v4 `PerspectiveCamera::GenerateRay`; the same for an orthographic camera).
    #[inline]
    pub fn generate_through_lens(&self, film: Vec2, lens_u: Vec2) -> CameraRay {
        let sx = film.x * 2.0 - 1.0;
        let sy = 1.0 - film.y * 2.0;
        let (o_local, d_local) = match self.shape {
            Shape::Perspective {
                tan_half_yfov: th,
                aspect,
            } => {
                let d = Vec3::new(sx * th * aspect, sy * th, -1.0);
                (d * self.znear, d)
            }
            Shape::Orthographic { xmag, ymag } => (
                Vec3::new(sx * xmag, sy * ymag, -self.znear),
                Vec3::new(0.0, 0.0, -1.0),
            ),
        };
        // `d_local.z` is -1 for both shapes: `o + d * f` lies `f` further along the axis.
        let (o_local, d_local) = match self.lens {
            Some(l) => {
                let focus = o_local + d_local * l.focus_distance;
                let p = concentric_disk(lens_u) * l.radius;
                let o = o_local + Vec3::new(p.x, p.y, 0.0);
                (o, focus - o)
            }
            None => (o_local, d_local),
        };
        let origin = self.transform.transform_point3(o_local);
        let dir = self
            .transform
            .transform_vector3(d_local)
            .normalize_or_zero();
        let origin = match &self.scene {
            Some(b) => b.advance(origin, dir),
            None => origin,
        };
        CameraRay { origin, dir }
    }

    /// This frustum with its rays starting just outside the scene's box `[lo, hi]`
    /// instead of at the camera, when the camera is outside it.
    ///
    /// Far from the scene, `bound - origin` rounds by more than any margin relative to
    /// the scene, so a ray from the camera itself could not be clipped to domains, nor
    /// its hits assigned to them, exactly: a split render would lose hits near the
    /// bounds and split planes that one BVH finds (docs/numerics.md "Far cameras").
    /// Every configuration starts the ray at the same computed point, so they agree bit
    /// for bit, and no geometry lies between the camera and that point.
    pub fn clipped_to(self, lo: Vec3, hi: Vec3) -> Frustum {
        let ok = lo.is_finite() && hi.is_finite() && lo.cmple(hi).all();
        Frustum {
            scene: ok.then(|| SceneBox::new(lo, hi)),
            ..self
        }
    }
}

/// The margin [`advance_to_box`] leaves outside the box, relative to the magnitudes of
/// the box's and the origin's coordinates: 16 times the rounding of the slab distances
/// and of the moved origin (about 2^-21 of those magnitudes), so the moved origin
/// provably stays outside the box.
const BOX_MARGIN: f32 = 1.0 / (1u32 << 17) as f32;

/// The least distance [`advance_to_box`] leaves between the moved origin and the box,
/// relative to the box's largest extent: 1/64 of it.
///
/// The margin above only keeps the origin provably outside. A triangle lying on the box
/// (a cube whose faces are the scene's bounds) was then hit at a distance of about
/// 2^-17 of the scene, below the watertight test's own error bound on the distance
/// (pbrt-v4's, `intersect::t_error_bound`, which grows with the triangle's extent around
/// the ray and refuses hits it cannot tell from the origin): rays passed through the
/// cube's near faces in curved patches (issue 38, Khronos `BoxVertexColors`). Starting
/// 1/64 of the scene away keeps every hit far above that bound for any triangle no
/// larger than the scene with an aspect below about a thousand, and costs no precision:
/// the origin's coordinates are of the box's own magnitude.
const BOX_STANDOFF: f32 = 1.0 / 64.0;

/// `origin` moved along `dir` to just outside the box `[lo, hi]` when it starts outside
/// and the ray meets the box; otherwise `origin`. Done twice: the first step's margin
/// is relative to the (possibly huge) distance of the origin, the second's to the box.
/// The origin stays at least [`BOX_STANDOFF`] of the box's extent away from it (a
/// camera already closer than that keeps its own position).
///
/// All three slabs at once in SSE lanes (every camera ray pays for this: the loop over
/// axes it replaces cost about 350 instructions a ray). The arithmetic per axis is that
/// of the scalar loop in the tests, so the bits are too: an axis the ray runs parallel
/// to either rejects the ray (origin outside its slab) or bounds nothing.
pub fn advance_to_box(origin: Vec3, dir: Vec3, lo: Vec3, hi: Vec3) -> Vec3 {
    SceneBox::new(lo, hi).advance(origin, dir)
}

/// The box camera rays start at, with what [`advance_to_box`] derives from the box
/// alone worked out once per frustum rather than once per camera ray (the same
/// values, so the same origins bit for bit).
#[derive(Clone, Copy, Debug, PartialEq)]
struct SceneBox {
    lo: Vec3A,
    hi: Vec3A,
    /// The largest magnitude of the box's coordinates.
    size: f32,
    /// [`BOX_STANDOFF`] of the box's largest extent.
    standoff: f32,
}

impl SceneBox {
    fn new(lo: Vec3, hi: Vec3) -> SceneBox {
        let (lo, hi) = (Vec3A::from(lo), Vec3A::from(hi));
        SceneBox {
            lo,
            hi,
            size: lo.abs().max(hi.abs()).max_element(),
            standoff: (hi - lo).max_element() * BOX_STANDOFF,
        }
    }

    /// [`advance_to_box`] of this box.
    fn advance(&self, origin: Vec3, dir: Vec3) -> Vec3 {
        let SceneBox {
            lo,
            hi,
            size,
            standoff,
        } = *self;
        let d = Vec3A::from(dir);
        let parallel = d.cmpeq(Vec3A::ZERO);
        // Infinite on a parallel axis, whose distances are replaced below.
        let inv = Vec3A::ONE / d;
        let mut o = Vec3A::from(origin);
        for _ in 0..2 {
            let m = ((o.abs().max_element() + size) * BOX_MARGIN).max(standoff);
            let (blo, bhi) = (lo - m, hi + m);
            if (parallel & (o.cmplt(blo) | o.cmpgt(bhi))).any() {
                return o.into();
            }
            let (ta, tb) = ((blo - o) * inv, (bhi - o) * inv);
            let near = Vec3A::select(parallel, Vec3A::ZERO, ta.min(tb));
            let far = Vec3A::select(parallel, Vec3A::INFINITY, ta.max(tb));
            let t0 = near.max_element().max(0.0);
            let t1 = far.min_element();
            if !(t0 > 0.0 && t0 <= t1 && t0.is_finite()) {
                return o.into();
            }
            o += d * t0;
        }
        o.into()
    }
}

/// Where a camera with vertical field of view `yfov` (radians) must stand, on the side
/// `dir` (unit) of the box `[min, max]`, to see the box's bounding sphere whole in an
/// image of `image_aspect`; and the box's centre it looks at. [`Camera::framing`] and
/// `--orbit` (`crate::view`) stand there.
pub fn framing_eye(min: Vec3, max: Vec3, image_aspect: f32, dir: Vec3, yfov: f32) -> (Vec3, Vec3) {
    let center = (min + max) * 0.5;
    let radius = ((max - min).length() * 0.5).max(1e-6);
    let half = (yfov * 0.5).tan();
    // The bounding sphere must fit both vertically and horizontally.
    let fit = half.min(half * image_aspect.max(1e-3));
    let dist = radius / (fit.atan()).sin();
    (center + dir * dist, center)
}

impl Camera {
    /// How far `p` is from the camera, as the depth AOV (`crate::aov`) gives it: from
    /// its position (the lens's centre) for a perspective camera, from its image plane
    /// along the view axis for an orthographic one. Not from a camera ray's origin,
    /// which starts at the scene's box ([`Frustum::clipped_to`]).
    pub fn depth_of(&self, p: Vec3) -> f32 {
        let eye = self.transform.w_axis.truncate();
        match self.projection {
            Projection::Perspective { .. } => (p - eye).length(),
            Projection::Orthographic { .. } => {
                let forward = -self.transform.z_axis.truncate().normalize_or_zero();
                (p - eye).dot(forward)
            }
        }
    }

    /// A perspective camera at `eye` looking at `target`.
    pub fn look_at(name: &str, eye: Vec3, target: Vec3, up: Vec3, yfov: f32) -> Camera {
        // Camera-to-world with the camera looking down its local -Z.
        let forward = (target - eye).normalize_or(Vec3::NEG_Z);
        let mut right = forward.cross(up);
        if right.length_squared() < 1e-12 {
            right = forward.any_orthonormal_vector();
        }
        let right = right.normalize();
        let true_up = right.cross(forward);
        let transform = Mat4::from_cols(
            right.extend(0.0),
            true_up.extend(0.0),
            (-forward).extend(0.0),
            eye.extend(1.0),
        );
        Camera {
            name: name.to_string(),
            transform,
            projection: Projection::Perspective { yfov, aspect: None },
            znear: 0.0,
            lens: None,
        }
    }

    /// A camera that frames a bounding box from a three-quarter view, so a scene without
    /// a camera still gives a useful picture.
    pub fn framing(min: Vec3, max: Vec3, image_aspect: f32) -> Camera {
        let yfov = 40f32.to_radians();
        let dir = Vec3::new(0.55, 0.45, 1.0).normalize();
        let (eye, center) = framing_eye(min, max, image_aspect, dir, yfov);
        Camera::look_at("auto", eye, center, Vec3::Y, yfov)
    }

    /// The ray through film position `film` in [0,1]^2 (x right, y down), for an image of
    /// the given aspect (width / height).
    pub fn generate(&self, film: Vec2, image_aspect: f32) -> CameraRay {
        self.frustum(image_aspect).generate(film)
    }

    /// The camera made ready for many rays of an image of the given aspect: what does not
    /// change from ray to ray (the projection's tangent) is worked out once.
    ///
    /// The vertical field of view (perspective `yfov`, orthographic `ymag`) is kept and
    /// the horizontal one follows the image, whatever `aspectRatio` or `xmag` the file
    /// gives: that is what glTF viewers do (the Khronos Sample Viewer, three.js and
    /// Blender's importer fit the camera to the viewport), and it never stretches the
    /// picture. Applying the file's aspect to an image of another shape would squash
    /// every round thing into an ellipse.
    pub fn frustum(&self, image_aspect: f32) -> Frustum {
        let shape = match self.projection {
            Projection::Perspective { yfov, .. } => Shape::Perspective {
                tan_half_yfov: (yfov * 0.5).tan(),
                aspect: image_aspect,
            },
            Projection::Orthographic { xmag, ymag } => Shape::Orthographic {
                xmag: ymag.abs() * image_aspect * if xmag < 0.0 { -1.0 } else { 1.0 },
                ymag,
            },
        };
        Frustum {
            transform: self.transform,
            shape,
            znear: self.znear.max(0.0),
            scene: None,
            lens: self.lens,
        }
    }
    /// True when the camera gives finite, non-degenerate rays.
    pub fn is_valid(&self) -> bool {
        let t_ok = self.transform.is_finite() && self.transform.determinant().abs() > 0.0;
        // A perspective camera's aspect ratio is not used for rays (see `frustum`), so
        // a bad one does not make the camera unusable.
        let p_ok = match self.projection {
            Projection::Perspective { yfov, .. } => {
                yfov.is_finite() && yfov > 0.0 && yfov < std::f32::consts::PI
            }
            Projection::Orthographic { xmag, ymag } => {
                xmag.is_finite() && ymag.is_finite() && xmag != 0.0 && ymag != 0.0
            }
        };
        let l_ok = self.lens.is_none_or(|l| {
            l.radius.is_finite()
                && l.radius > 0.0
                && l.focus_distance.is_finite()
                && l.focus_distance > 0.0
        });
        t_ok && p_ok && l_ok && self.znear.is_finite()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn center_ray_looks_down_minus_z() {
        let cam = Camera {
            name: "c".into(),
            transform: Mat4::from_translation(Vec3::new(0.5, 0.5, 3.0)),
            projection: Projection::Perspective {
                yfov: 0.7,
                aspect: Some(1.0),
            },
            znear: 0.01,
            lens: None,
        };
        let r = cam.generate(Vec2::new(0.5, 0.5), 1.0);
        assert!((r.dir - Vec3::new(0.0, 0.0, -1.0)).length() < 1e-6);
        assert!((r.origin - Vec3::new(0.5, 0.5, 2.99)).length() < 1e-5);
        // Top of the film goes up.
        let top = cam.generate(Vec2::new(0.5, 0.0), 1.0);
        assert!(top.dir.y > 0.0);
    }

    /// A file camera with aspect 1 rendering a 2:1 image: the vertical field of view is
    /// the file's, the horizontal one widens with the image (no stretching). The same
    /// for an orthographic camera's magnifications.
    #[test]
    fn file_aspect_is_fitted_to_the_image_not_stretched() {
        let yfov = 0.8f32;
        let persp = Camera {
            name: "p".into(),
            transform: Mat4::IDENTITY,
            projection: Projection::Perspective {
                yfov,
                aspect: Some(1.0),
            },
            znear: 0.0,
            lens: None,
        };
        let top = persp.generate(Vec2::new(0.5, 0.0), 2.0).dir;
        let right = persp.generate(Vec2::new(1.0, 0.5), 2.0).dir;
        let half = (yfov * 0.5).tan();
        assert!((top.y / -top.z - half).abs() < 1e-5, "{top}");
        assert!((right.x / -right.z - 2.0 * half).abs() < 1e-5, "{right}");

        let ortho = Camera {
            projection: Projection::Orthographic {
                xmag: 1.0,
                ymag: 1.0,
            },
            ..persp
        };
        let top = ortho.generate(Vec2::new(0.5, 0.0), 2.0).origin;
        let right = ortho.generate(Vec2::new(1.0, 0.5), 2.0).origin;
        assert!((top.y - 1.0).abs() < 1e-6, "{top}");
        assert!((right.x - 2.0).abs() < 1e-6, "{right}");
    }

    /// Every ray through one film point, wherever it crosses the lens, meets the
    /// pinhole ray at the plane in focus; the lens's centre gives the pinhole's
    /// direction; lens samples cover the disc of the lens's radius.
    #[test]
    fn thin_lens_rays_meet_at_the_focus_plane() {
        let lens = Lens {
            radius: 0.2,
            focus_distance: 4.0,
        };
        for projection in [
            Projection::Perspective {
                yfov: 0.7,
                aspect: None,
            },
            Projection::Orthographic {
                xmag: 1.0,
                ymag: 1.0,
            },
        ] {
            let pinhole = Camera {
                name: "c".into(),
                transform: Mat4::from_translation(Vec3::new(0.5, -1.0, 3.0))
                    * Mat4::from_rotation_y(0.3),
                projection,
                znear: 0.0,
                lens: None,
            };
            let thin = Camera {
                lens: Some(lens),
                ..pinhole.clone()
            };
            let axis = pinhole.transform.transform_vector3(Vec3::NEG_Z);
            let (p, t) = (pinhole.frustum(1.0), thin.frustum(1.0));
            for film in [
                Vec2::new(0.5, 0.5),
                Vec2::new(0.1, 0.8),
                Vec2::new(0.9, 0.2),
            ] {
                let a = p.generate(film);
                let in_focus = a.origin + a.dir * (lens.focus_distance / a.dir.dot(axis));
                let mut widest = 0.0f32;
                for u in [
                    Vec2::new(0.0, 0.0),
                    Vec2::new(0.99, 0.3),
                    Vec2::new(0.2, 0.7),
                ] {
                    let b = t.generate_through_lens(film, u);
                    let depth = (in_focus - b.origin).dot(axis);
                    let at = b.origin + b.dir * (depth / b.dir.dot(axis));
                    assert!((at - in_focus).length() < 1e-5, "{projection:?} {film} {u}");
                    widest = widest.max((b.origin - a.origin).length());
                }
                assert!(widest > 0.15 && widest <= 0.2 + 1e-6, "{widest}");
                let c = t.generate_through_lens(film, Vec2::splat(0.5));
                assert!((c.dir - a.dir).length() < 1e-6);
            }
        }
    }

    #[test]
    fn concentric_disk_stays_in_the_disc() {
        for i in 0..=16 {
            for j in 0..=16 {
                let u = Vec2::new(i as f32 / 16.0, j as f32 / 16.0);
                assert!(concentric_disk(u).length() <= 1.0 + 1e-6, "{u}");
            }
        }
        assert!((concentric_disk(Vec2::new(1.0, 0.5)) - Vec2::X).length() < 1e-6);
    }

    #[test]
    fn framing_sees_the_box_centre() {
        let cam = Camera::framing(Vec3::splat(-1.0), Vec3::splat(1.0), 1.5);
        let r = cam.generate(Vec2::new(0.5, 0.5), 1.5);
        let to_center = (-r.origin).normalize();
        assert!(r.dir.dot(to_center) > 0.9999);
    }

    /// The axis-by-axis loop [`advance_to_box`] replaced (2026-11-26): the lanes must
    /// give its bits.
    fn advance_scalar(origin: Vec3, dir: Vec3, lo: Vec3, hi: Vec3) -> Vec3 {
        let mut o = origin.to_array();
        let d = dir.to_array();
        let size = lo.abs().max(hi.abs()).max_element();
        let standoff = (hi - lo).max_element() * BOX_STANDOFF;
        let (lo, hi) = (lo.to_array(), hi.to_array());
        for _ in 0..2 {
            let m = ((Vec3::from_array(o).abs().max_element() + size) * BOX_MARGIN).max(standoff);
            let (mut t0, mut t1) = (0.0f32, f32::INFINITY);
            for a in 0..3 {
                let (blo, bhi) = (lo[a] - m, hi[a] + m);
                if d[a] == 0.0 {
                    if o[a] < blo || o[a] > bhi {
                        return Vec3::from_array(o);
                    }
                    continue;
                }
                let inv = 1.0 / d[a];
                let (ta, tb) = ((blo - o[a]) * inv, (bhi - o[a]) * inv);
                t0 = t0.max(ta.min(tb));
                t1 = t1.min(ta.max(tb));
            }
            if !(t0 > 0.0 && t0 <= t1 && t0.is_finite()) {
                return Vec3::from_array(o);
            }
            o = (Vec3::from_array(o) + dir * t0).to_array();
        }
        Vec3::from_array(o)
    }

    #[test]
    fn advance_to_box_lanes_give_the_scalar_loops_bits() {
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 40) as f32 / (1u64 << 24) as f32
        };
        let (lo, hi) = (Vec3::new(-1.0, -0.5, -2.0), Vec3::new(1.5, 0.75, 0.25));
        let mut moved = 0;
        for i in 0..20_000 {
            // Origins near and far (up to 1e7 away), some inside the box; directions
            // with axes zeroed to run parallel to slabs, some on a slab plane.
            let scale = [1.0, 10.0, 1e3, 1e7][i % 4];
            let mut o = Vec3::new(next() - 0.5, next() - 0.5, next() - 0.5) * 2.0 * scale;
            if i % 97 == 0 {
                o.x = hi.x;
            }
            let mut d = Vec3::new(next() - 0.5, next() - 0.5, next() - 0.5);
            if i % 5 == 0 {
                d[i % 3] = 0.0;
            }
            if i % 11 == 0 {
                d[(i + 1) % 3] = -0.0;
            }
            // Aim most rays at the box.
            if i % 3 != 0 {
                d = ((lo + hi) * 0.5 + d - o).normalize_or_zero();
            }
            let (a, b) = (advance_to_box(o, d, lo, hi), advance_scalar(o, d, lo, hi));
            assert_eq!(
                a.to_array().map(f32::to_bits),
                b.to_array().map(f32::to_bits),
                "o {o} d {d}"
            );
            moved += usize::from(a != o);
        }
        assert!(moved > 5_000, "only {moved} rays were advanced");
    }
}

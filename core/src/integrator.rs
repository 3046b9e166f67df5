//! The integrators' per-ray steps.
//!
//! Rays are non-recursive and self-contained ([`RayState`]): whoever traces a ray calls
//! [`Integrator::shade_hit`], [`Integrator::shade_miss`] or
//! [`Integrator::shadow_result`], which add contributions to pixels and spawn children
//! through a [`Sink`]. The single-process renderer and the distributed workers drive the
//! same steps; only where the ray is traced differs.
//!
//! Only the ray kinds the scene's [`Effects`] call for are ever spawned.

use std::cell::Cell;
use std::sync::Arc;

use glam::{Vec2, Vec3};
use serde::Serialize;

use crate::aov::{AovSet, FirstHit};
use crate::bsdf::{Bsdf, BsdfAt, BsdfParams, Lobe};
use crate::bvh::{Hit, QueryRay};
use crate::camera::{Camera, Frustum};
use crate::credit::Credit;
use crate::effects::{Effect, Effects};
use crate::env_map::EnvMap;
use crate::intersect::offset_ray_origin;
use crate::light_sampler::{LightSample, LightSampler};
use crate::lighting::Lighting;
use crate::material::Material;
use crate::sampling::{PathKey, PathStream, Purpose, cosine_hemisphere};
use crate::scene::Scene;
use crate::sun::Sun;
use crate::surface::{ShadingValues, Surface, alpha_passes};
use crate::trace::Trace;

/// The kinds of rays, counted separately in every summary.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum RayKind {
    #[default]
    Camera = 0,
    Shadow = 1,
    Reflection = 2,
    Refraction = 3,
    Diffuse = 4,
    AmbientOcclusion = 5,
}

impl RayKind {
    pub const COUNT: usize = 6;
    pub const ALL: [RayKind; 6] = [
        RayKind::Camera,
        RayKind::Shadow,
        RayKind::Reflection,
        RayKind::Refraction,
        RayKind::Diffuse,
        RayKind::AmbientOcclusion,
    ];

    /// Every kind's name, in [`RayKind::ALL`]'s order: the one spelling of the list
    /// (stats keys, metrics labels, the `kinds` knobs of ray caches and hit maps).
    pub const NAMES: [&'static str; RayKind::COUNT] = [
        RayKind::Camera.name(),
        RayKind::Shadow.name(),
        RayKind::Reflection.name(),
        RayKind::Refraction.name(),
        RayKind::Diffuse.name(),
        RayKind::AmbientOcclusion.name(),
    ];

    /// The kinds that carry radiance of their own (occlusion rays only answer "is
    /// anything in the way?"): what a ray cache may store and answer.
    pub const RADIANCE: [RayKind; 4] = [
        RayKind::Camera,
        RayKind::Reflection,
        RayKind::Refraction,
        RayKind::Diffuse,
    ];

    /// The kind named `name` (as [`RayKind::name`] spells it).
    pub fn from_name(name: &str) -> Option<RayKind> {
        RayKind::ALL.into_iter().find(|k| k.name() == name)
    }

    /// `kinds`' names, comma-separated, for help texts and errors that list the choices
    /// ("camera, shadow, ...").
    pub fn help_list(kinds: &[RayKind]) -> String {
        kinds
            .iter()
            .map(|k| k.name())
            .collect::<Vec<_>>()
            .join(", ")
    }

    pub const fn name(self) -> &'static str {
        match self {
            RayKind::Camera => "camera",
            RayKind::Shadow => "shadow",
            RayKind::Reflection => "reflection",
            RayKind::Refraction => "refraction",
            RayKind::Diffuse => "diffuse",
            RayKind::AmbientOcclusion => "ambient_occlusion",
        }
    }

    /// Shadow and AO rays only ask "is anything in the way?".
    pub fn is_occlusion(self) -> bool {
        matches!(self, RayKind::Shadow | RayKind::AmbientOcclusion)
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum IntegratorKind {
    /// Primary rays, direct light with its shadow rays, and unshadowed ambient light.
    /// `benches/caches.py` runs Little 2011's Table 5.1 with it, but it is not the
    /// thesis's renderer, which casts camera rays only: that is [`IntegratorKind::Primary`]
    /// (docs/caches.md "Faithful to / departs from").
    Raycast,
    /// Camera rays only, as Little 2011's ray caster casts them: the first hit is shaded
    /// with its emission and the direct light of every light as if nothing were in the
    /// way (no shadow rays, no ambient term, no bounces), and a miss sees the
    /// environment. It spawns no ray at all, so a ray cache on it caches exactly what
    /// the thesis's caches hold: the radiance a camera ray brings back from behind a
    /// wall.
    Primary,
    /// Shadows plus perfect mirror reflection and refraction to the maximum depth.
    Whitted,
    /// Unidirectional path tracing with next-event estimation, MIS and Russian roulette.
    Path,
    /// Ambient occlusion with N rays per hit.
    Ao,
}

impl IntegratorKind {
    pub const ALL: [IntegratorKind; 5] = [
        IntegratorKind::Raycast,
        IntegratorKind::Primary,
        IntegratorKind::Whitted,
        IntegratorKind::Path,
        IntegratorKind::Ao,
    ];

    /// The integrator named `s` (as [`IntegratorKind::name`] spells it).
    pub fn from_name(s: &str) -> Option<IntegratorKind> {
        IntegratorKind::ALL.into_iter().find(|k| k.name() == s)
    }

    /// Every integrator's name, for errors that list the choices ("raycast, whitted,
    /// path or ao").
    pub fn choices() -> String {
        let names = IntegratorKind::ALL.map(IntegratorKind::name);
        let (last, rest) = names.split_last().expect("at least one integrator");
        format!("{} or {last}", rest.join(", "))
    }

    /// The one spelling of each integrator's name (the JobSpec, the CLI, stats).
    pub fn name(self) -> &'static str {
        match self {
            IntegratorKind::Raycast => "raycast",
            IntegratorKind::Primary => "primary",
            IntegratorKind::Whitted => "whitted",
            IntegratorKind::Path => "path",
            IntegratorKind::Ao => "ao",
        }
    }
}

/// The deepest `max_depth` a job accepts: [`Integrator::credit_needed`] fits in a tile's
/// credit at this depth, the most samples and the most lights a scene may have.
pub const MAX_DEPTH: u32 = 1024;

/// Bounces up to which Whitted spawns both a mirror and a refraction ray at glass; deeper,
/// one of the two (see [`Integrator::credit_needed`]).
pub const WHITTED_BRANCH_DEPTH: u32 = 8;

/// The part of a shadow ray's length toward a point it does not test (pbrt-v4's
/// `ShadowEpsilon`): the light's own surface lies just beyond that point (the point is
/// offset toward the shading point by its error bound), but the normalised direction and
/// the length round by a few ulps of the length, which can exceed that offset when the
/// light is nearer the origin than the shading point is. An occluder within 2^-13 of the
/// distance from the light is not seen; the bound is relative, so it is the same at any
/// scale (docs/numerics.md "Spawned rays").
pub const SHADOW_EPSILON: f32 = 1.0 / 8192.0;

/// Everything about a render that is not the scene.
#[derive(Clone, Debug)]
pub struct RenderSettings {
    pub width: u32,
    pub height: u32,
    pub spp: u32,
    pub integrator: IntegratorKind,
    pub max_depth: u32,
    pub seed: u64,
    /// Constant environment radiance.
    pub environment: Vec3,
    pub effects: Effects,
    /// Rays per hit for the `ao` integrator.
    pub ao_samples: u32,
    /// Occlusion distance for `ao`, in scene units (infinite by default).
    pub ao_distance: f32,
    /// Lights the job spec adds (a sun), used under their effects.
    pub lighting: Lighting,
    /// `--clamp-indirect`: the largest component a contribution of indirect light may
    /// have (`crate::clamp`); `None` clamps nothing.
    pub clamp_indirect: Option<f32>,
    /// The AOVs the job writes (`crate::aov`); camera rays' first hits are recorded only
    /// when one of them needs them.
    pub aovs: AovSet,
}

/// One ray in flight. Self-contained: it can be traced anywhere, in any order.
///
/// The default (a camera ray at the origin with a zero direction) traces nothing: it is
/// a slot to be overwritten, for loops that reuse one ray in place.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RayState {
    pub origin: Vec3,
    pub dir: Vec3,
    pub tmax: f32,
    pub pixel: u32,
    pub sample: u32,
    /// Number of surface interactions before this ray.
    pub depth: u32,
    pub kind: RayKind,
    /// Path throughput; for shadow and AO rays, the contribution added if unoccluded.
    pub weight: Vec3,
    /// Solid-angle pdf of the BSDF sample that made this ray, for MIS against light
    /// sampling when it hits an emitter; 0 means no MIS (camera or delta bounce, or no
    /// light sample was taken at the previous vertex).
    pub bsdf_pdf: f32,
}

/// Where the steps put their results.
pub trait Sink {
    fn contribute(&mut self, pixel: u32, value: Vec3);
    fn spawn(&mut self, ray: RayState);
    /// The contribution just made was scaled down by `--clamp-indirect`. Sinks that keep
    /// statistics count it (the film's `clamped_indirect`); the default ignores it.
    fn clamped_indirect(&mut self) {}
    /// A camera ray's first hit, for the AOVs (made only when the job asks for AOVs that
    /// need it). Sinks that keep AOV sums add it to `pixel`'s; the default ignores it.
    fn first_hit(&mut self, _pixel: u32, _hit: &FirstHit) {}
}

/// The scene-wide state the steps read: the scene, its lights and the settings.
pub struct Integrator<'a> {
    pub scene: &'a Scene,
    /// Shared, so a worker builds the table once per job and an integrator per batch.
    pub lights: Arc<LightSampler>,
    /// Read-only after construction: the camera rays' [`Frustum`] is made from it and
    /// `camera` when the integrator is.
    pub settings: RenderSettings,
    pub camera: Camera,
    /// Scene-wide id of each triangle of `scene` when it holds only part of the scene (a
    /// worker's domains and the emitters, in scene order); `None` when it is whole.
    /// Random numbers keyed by a triangle use the scene-wide id, so they are the same
    /// wherever the triangle is shaded.
    pub global_ids: Option<&'a [u32]>,
    /// `camera` made ready for `settings`' image, once.
    frustum: Frustum,
    /// Whether any material is single-sided, so camera rays must skip its back faces
    /// (see [`Integrator::accept`]); false spares every other scene the test.
    cull_camera_back_faces: bool,
}

/// Whether any material of `scene` is single-sided (glTF `doubleSided: false`).
fn any_single_sided(scene: &Scene) -> bool {
    scene.materials.iter().any(|m| !m.double_sided)
}

/// The image's aspect (width / height), as the camera rays use it.
fn image_aspect(settings: &RenderSettings) -> f32 {
    settings.width.max(1) as f32 / settings.height.max(1) as f32
}

/// How [`Integrator`]'s direct light treats its light samples.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct DirectMode {
    /// Weight the area and distant samples against BSDF sampling (path tracing).
    mis: bool,
    /// Cast a shadow ray per sample; without, each sample counts as unoccluded.
    shadowed: bool,
}

impl DirectMode {
    /// Path tracing: shadow rays, MIS-weighted.
    const MIS: DirectMode = DirectMode {
        mis: true,
        shadowed: true,
    };
    /// Raycast and Whitted: shadow rays, every sample at full weight.
    const FULL_WEIGHT: DirectMode = DirectMode {
        mis: false,
        shadowed: true,
    };
    /// Primary: no shadow rays, every sample at full weight.
    const UNSHADOWED: DirectMode = DirectMode {
        mis: false,
        shadowed: false,
    };
}

fn power_heuristic(a: f32, b: f32) -> f32 {
    let (a2, b2) = (a * a, b * b);
    if a2 + b2 > 0.0 && (a2 + b2).is_finite() {
        a2 / (a2 + b2)
    } else if a > b {
        1.0
    } else {
        0.0
    }
}

/// A hit's [`Surface`] with the origins of the rays that leave it, each side's
/// computed once: a path-traced hit casts its shadow ray and its bounce from the same
/// point, nearly always to the same side, and `offset_ray_origin` (about 80
/// instructions) gives the same bits for the same point and side. Dereferences to the
/// surface, so the shading steps read it as before.
struct HitPoint<'a> {
    surf: &'a Surface,
    /// The origin on `ng`'s side and on the other, once computed.
    origins: [Cell<Option<Vec3>>; 2],
}

impl<'a> HitPoint<'a> {
    fn new(surf: &'a Surface) -> HitPoint<'a> {
        HitPoint {
            surf,
            origins: [Cell::new(None), Cell::new(None)],
        }
    }

    /// The origin of a ray leaving along `dir`: offset to the side of the geometric
    /// normal `dir` is on ([`offset_ray_origin`]).
    fn origin_toward(&self, dir: Vec3) -> Vec3 {
        let s = self.surf;
        let front = s.ng.dot(dir) >= 0.0;
        let cached = &self.origins[usize::from(!front)];
        if let Some(origin) = cached.get() {
            return origin;
        }
        let side = if front { s.ng } else { -s.ng };
        let origin = offset_ray_origin(s.p, s.p_err, side);
        cached.set(Some(origin));
        origin
    }
}

impl std::ops::Deref for HitPoint<'_> {
    type Target = Surface;

    fn deref(&self) -> &Surface {
        self.surf
    }
}

/// The BSDF's parameters at a hit: the material's shading values, the coat's normal, and
/// `ior` (the material's, or one colour channel's under dispersion).
fn bsdf_params(sv: &ShadingValues, surf: &Surface, ior: f32) -> BsdfParams {
    BsdfParams {
        base_color: sv.base_color,
        metallic: sv.metallic,
        roughness: sv.roughness,
        specular: sv.specular,
        specular_color: sv.specular_color,
        transmission: sv.transmission,
        ior,
        clearcoat: sv.clearcoat,
        clearcoat_roughness: sv.clearcoat_roughness,
        sheen_color: sv.sheen_color,
        sheen_roughness: sv.sheen_roughness,
        anisotropy: sv.anisotropy,
        anisotropy_direction: sv.anisotropy_direction,
        clearcoat_normal: surf.coat_n,
        iridescence: sv.iridescence,
        iridescence_ior: sv.iridescence_ior,
        iridescence_thickness: sv.iridescence_thickness,
    }
}

impl<'a> Integrator<'a> {
    pub fn new(scene: &'a Scene, camera: Camera, settings: RenderSettings) -> Integrator<'a> {
        let lights = Arc::new(LightSampler::new(
            scene,
            settings.effects.contains(Effect::Emission),
        ));
        let (lo, hi) = lights.scene_bounds();
        Integrator {
            scene,
            frustum: camera.frustum(image_aspect(&settings)).clipped_to(lo, hi),
            lights,
            settings,
            camera,
            global_ids: None,
            cull_camera_back_faces: any_single_sided(scene),
        }
    }

    /// The steps over part of a scene: `scene` holds a subset of the triangles in
    /// scene order (with every emitter), `global_ids` their scene-wide ids, and `lights`
    /// was made by [`LightSampler::with_bounds`] with the whole scene's bounds. Every
    /// result is bit for bit the one over the whole scene for rays whose hits lie in the
    /// subset.
    pub fn partial(
        scene: &'a Scene,
        camera: Camera,
        settings: RenderSettings,
        lights: Arc<LightSampler>,
        global_ids: &'a [u32],
    ) -> Integrator<'a> {
        let (lo, hi) = lights.scene_bounds();
        Integrator {
            scene,
            frustum: camera.frustum(image_aspect(&settings)).clipped_to(lo, hi),
            lights,
            settings,
            camera,
            global_ids: Some(global_ids),
            cull_camera_back_faces: any_single_sided(scene),
        }
    }

    /// The least credit a camera ray needs so that every ray of its tree, down to the
    /// job's maximum depth, can give each of its children a share (docs/architecture.md
    /// "Credit"): the credit of the largest tree the integrator can make, with a shadow
    /// ray to every punctual light and N (`--light-samples`) to each of an emitter, the
    /// sun and the environment map at every hit. [`MAX_DEPTH`], `film::MAX_SPP`,
    /// `light::MAX_PUNCTUAL_LIGHTS`, `light_samples::MAX_LIGHT_SAMPLES` and the tile
    /// size are chosen so that this always fits a camera ray's share of a tile (tested
    /// below); were a limit raised past that, a share too small would still fail the
    /// job with [`crate::credit::CreditError`], never give a wrong image.
    pub fn credit_needed(&self) -> Credit {
        let s = &self.settings;
        let punctual = self.lights.punctual_entries().len() as u128;
        let area = u128::from(self.lights.choose_area(0.0).is_some());
        let sun = u128::from(self.sun().is_some()) + u128::from(self.env_map().is_some());
        let per_light = u128::from(s.lighting.samples.get());
        let shadows = if s.effects.contains(Effect::DirectLight) {
            punctual + per_light * (area + sun)
        } else {
            0
        };
        let depth = s.max_depth.max(1);
        // need(d): the credit a ray at depth d needs; a hit keeps one unit for itself and
        // gives one to each shadow ray, the rest to the rays that go on.
        let need = match s.integrator {
            IntegratorKind::Ao => u128::from(s.ao_samples.max(1)) + 1,
            IntegratorKind::Raycast => shadows + 1,
            // A camera ray and nothing else.
            IntegratorKind::Primary => 1,
            IntegratorKind::Path => {
                // Hits at depth 0..depth spawn shadow rays and one bounce; at `depth`,
                // nothing.
                (0..depth).fold(1u128, |below, _| {
                    (shadows + 1 + below).min(u128::from(u64::MAX))
                })
            }
            IntegratorKind::Whitted => {
                // Hits at depth 0..depth spawn shadow rays, and those before depth - 1
                // mirror and refraction rays too: both before WHITTED_BRANCH_DEPTH, one
                // from there on.
                let mut below = shadows + 1;
                for d in (0..depth - 1).rev() {
                    let k = if d < WHITTED_BRANCH_DEPTH { 2 } else { 1 };
                    below = (shadows + 1 + k * below).min(u128::from(u64::MAX));
                }
                below
            }
        };
        Credit::from_wire(need.min(u128::from(u64::MAX)) as u64)
    }

    fn key(&self, ray: &RayState) -> PathStream {
        PathKey {
            seed: self.settings.seed,
            pixel: ray.pixel,
            sample: ray.sample,
        }
        .stream()
    }

    fn env(&self) -> Vec3 {
        if self.settings.effects.contains(Effect::Environment) {
            self.settings.environment
        } else {
            Vec3::ZERO
        }
    }

    /// Add `value`, light reflected by `bounces` surfaces on its way to the eye, to
    /// `pixel`, clamped when it is indirect light and the job clamps it
    /// (`crate::clamp`). Every radiance contribution of the integrators goes through here.
    #[inline]
    fn emit(&self, pixel: u32, bounces: u32, value: Vec3, sink: &mut impl Sink) {
        let (value, clamped) =
            crate::clamp::clamp_indirect(self.settings.clamp_indirect, bounces, value);
        sink.contribute(pixel, value);
        if clamped {
            sink.clamped_indirect();
        }
    }

    /// The spec's sun, when the job uses it.
    fn sun(&self) -> Option<&Sun> {
        if self.settings.effects.contains(Effect::Sun) {
            self.settings.lighting.sun.as_ref()
        } else {
            None
        }
    }

    /// The spec's environment map, when the job uses it.
    fn env_map(&self) -> Option<&EnvMap> {
        if self.settings.effects.contains(Effect::EnvMap) {
            self.settings.lighting.env_map.as_deref()
        } else {
            None
        }
    }

    /// The camera ray for `pixel` (row-major) and `sample`.
    pub fn camera_ray(&self, pixel: u32, sample: u32) -> RayState {
        let w = self.settings.width.max(1);
        self.camera_ray_xy(pixel % w, pixel / w, sample)
    }

    /// [`Integrator::camera_ray`] for the pixel at column `x`, row `y`: the same ray,
    /// for a caller that walks pixels by row and column and so needs no division per
    /// ray (an integer division costs as much as the rest of a camera ray's set-up).
    #[inline]
    pub fn camera_ray_xy(&self, x: u32, y: u32, sample: u32) -> RayState {
        let w = self.settings.width.max(1);
        let pixel = y * w + x;
        let key = PathKey {
            seed: self.settings.seed,
            pixel,
            sample,
        };
        let j = key.uniform2(0, Purpose::Film, 0);
        let film = Vec2::new(
            (x as f32 + j.x) / w as f32,
            (y as f32 + j.y) / self.settings.height.max(1) as f32,
        );
        self.camera_ray_through(film, pixel, sample)
    }

    /// The camera ray through `film` (image coordinates in [0, 1]^2, y down), labelled
    /// with `pixel` and `sample` (which key its path's random numbers). Inlined: a
    /// caller in another crate (the worker's loop) would otherwise get the ray through
    /// memory and stall reloading what was just stored.
    #[inline]
    pub fn camera_ray_through(&self, film: Vec2, pixel: u32, sample: u32) -> RayState {
        let r = if self.frustum.has_lens() {
            // The lens point is keyed by the ray's pixel and sample like every other
            // random number, so any process tracing this ray makes the same one.
            let key = PathKey {
                seed: self.settings.seed,
                pixel,
                sample,
            };
            self.frustum
                .generate_through_lens(film, key.uniform2(0, Purpose::Lens, 0))
        } else {
            self.frustum.generate(film)
        };
        RayState {
            origin: r.origin,
            dir: r.dir,
            tmax: f32::INFINITY,
            pixel,
            sample,
            depth: 0,
            kind: RayKind::Camera,
            weight: Vec3::ONE,
            bsdf_pdf: 0.0,
        }
    }

    /// Whether a hit on `tri` counts, given back-face culling, alpha cut-outs and
    /// stochastic blending.
    ///
    /// Camera rays pass through the back faces of single-sided materials (glTF
    /// `doubleSided: false`), as a rasteriser culls them. Every other ray sees both
    /// sides: light transport treats geometry as two-sided, as pbrt and Mitsuba do, so
    /// a closed single-sided object still casts shadows and reflects whichever way a
    /// ray meets it (the glTF Sample Viewer culls in rasterisation only, so its shadows
    /// and reflections are not culled either, where it has them).
    fn accept(&self, ray: &RayState, tri: u32, b: [f32; 3]) -> bool {
        if self.cull_camera_back_faces
            && ray.kind == RayKind::Camera
            && self.is_single_sided_back_face(ray, tri)
        {
            return false;
        }
        if !self.settings.effects.contains(Effect::Alpha) {
            return true;
        }
        let scene = self.scene;
        if self.material_of(tri).is_none_or(|m| !m.has_alpha()) {
            return true;
        }
        let id = self
            .global_ids
            .and_then(|g| g.get(tri as usize).copied())
            .unwrap_or(tri);
        let u = self.key(ray).uniform(ray.depth, Purpose::Alpha, id);
        alpha_passes(scene, tri, b, u)
    }

    /// The material of triangle `tri`, if it has a valid one.
    fn material_of(&self, tri: u32) -> Option<&Material> {
        let scene = self.scene;
        scene
            .mesh
            .material
            .get(tri as usize)
            .and_then(|&m| scene.materials.get(m as usize))
    }

    /// Whether `ray` meets triangle `tri` from behind (clockwise as seen from the ray,
    /// the same test [`Surface::new`] makes) and its material is single-sided.
    fn is_single_sided_back_face(&self, ray: &RayState, tri: u32) -> bool {
        if self.material_of(tri).is_none_or(|m| m.double_sided) {
            return false;
        }
        let [a, b, c] = self.scene.mesh.corners(tri as usize);
        (b - a).cross(c - a).dot(ray.dir) > 0.0
    }

    fn query(ray: &RayState) -> QueryRay {
        QueryRay {
            origin: ray.origin,
            dir: ray.dir,
            tmin: 0.0,
            tmax: ray.tmax,
        }
    }

    /// Closest accepted hit of `ray` in `geometry`.
    ///
    /// Generic over the geometry so that a worker's span-limited BVH is called directly,
    /// not through a vtable and two wrappers per ray.
    #[inline]
    pub fn intersect<T: Trace + ?Sized>(&self, geometry: &T, ray: &RayState) -> Option<Hit> {
        geometry.closest(&Self::query(ray), &mut |tri, h| {
            self.accept(ray, tri, [h.b0, h.b1, h.b2])
        })
    }

    /// Whether anything accepted blocks `ray` in `geometry`.
    #[inline]
    pub fn occluded<T: Trace + ?Sized>(&self, geometry: &T, ray: &RayState) -> bool {
        geometry.occluded(&Self::query(ray), &mut |tri, h| {
            self.accept(ray, tri, [h.b0, h.b1, h.b2])
        })
    }

    /// An occlusion ray came back: add its carried contribution if nothing blocked it.
    pub fn shadow_result(&self, ray: &RayState, occluded: bool, sink: &mut impl Sink) {
        if !occluded {
            // Made at a hit of depth `ray.depth - 1`: the light it carries is reflected
            // there and at every surface before.
            self.emit(ray.pixel, ray.depth, ray.weight, sink);
        }
    }

    /// A camera or bounce ray left the scene: it sees the environment.
    pub fn shade_miss(&self, ray: &RayState, sink: &mut impl Sink) {
        let env = self.env();
        // A ray of depth d saw this light after d reflections.
        if env != Vec3::ZERO {
            self.emit(ray.pixel, ray.depth, ray.weight * env, sink);
        }
        // The sun's disk: seen at full weight by a ray no light sample competed with
        // (camera rays, delta bounces), weighted against the sun's sample otherwise.
        if let Some(sun) = self.sun()
            && sun.contains(ray.dir)
        {
            let w = if ray.bsdf_pdf > 0.0 {
                power_heuristic(ray.bsdf_pdf, sun.pdf())
            } else {
                1.0
            };
            self.emit(ray.pixel, ray.depth, ray.weight * sun.radiance() * w, sink);
        }
        // The environment map, weighted against its light sample as the sun is.
        if let Some(map) = self.env_map() {
            let w = if ray.bsdf_pdf > 0.0 {
                power_heuristic(ray.bsdf_pdf, map.pdf(ray.dir))
            } else {
                1.0
            };
            let l = map.radiance(ray.dir);
            if l != Vec3::ZERO {
                self.emit(ray.pixel, ray.depth, ray.weight * l * w, sink);
            }
        }
    }

    /// Beer-Lambert attenuation of a ray that reached `surf` from inside an absorbing
    /// transmissive object (`KHR_materials_volume`): it hit the object's back face, so
    /// it crossed the medium from its origin to here. Stateless (the ray carries no
    /// medium), so the distance is measured from the ray's own origin to the hit point,
    /// both the same bits on every worker. `None` when nothing is absorbed.
    fn volume_transmittance(&self, ray: &RayState, surf: &Surface) -> Option<Vec3> {
        if surf.front || !self.settings.effects.contains(Effect::Volume) {
            return None;
        }
        let m = self.scene.materials.get(surf.material as usize)?;
        if !m.has_volume() {
            return None;
        }
        let t = m.volume?.transmittance((surf.p - ray.origin).length());
        t.is_finite().then_some(t)
    }

    /// A camera or bounce ray hit a surface.
    pub fn shade_hit(&self, ray: &RayState, hit: &Hit, sink: &mut impl Sink) {
        let effects = self.settings.effects;
        let surf = Surface::new(self.scene, hit, ray.dir, effects);
        let sv = surf.shading(self.scene, effects);
        if ray.kind == RayKind::Camera && self.settings.aovs.records_hits() {
            sink.first_hit(
                ray.pixel,
                &FirstHit {
                    albedo: sv.base_color,
                    normal: surf.n,
                    depth: self.camera.depth_of(surf.p),
                },
            );
        }
        let wo = -ray.dir;
        let key = self.key(ray);
        let attenuated;
        let ray = match self.volume_transmittance(ray, &surf) {
            Some(t) => {
                attenuated = RayState {
                    weight: ray.weight * t,
                    ..*ray
                };
                &attenuated
            }
            None => ray,
        };

        self.emission_seen(ray, &surf, sv.emission, sink);

        if self.settings.integrator == IntegratorKind::Ao {
            self.ao_rays(ray, &surf, key, sink);
            return;
        }

        let dispersed = self.disperse(ray, &sv, key);
        let (ray, ior) = match &dispersed {
            Some((r, ior)) => (r, *ior),
            None => (ray, sv.ior),
        };
        let params = bsdf_params(&sv, &surf, ior);
        // The BSDF tells inside from outside by the outward (winding) normal.
        let outward = if surf.front { surf.ng } else { -surf.ng };
        let bsdf = Bsdf::new(&params, surf.n, outward);
        let surf = HitPoint::new(&surf);
        match self.settings.integrator {
            IntegratorKind::Path => self.path_step(ray, &surf, &bsdf, wo, key, sink),
            IntegratorKind::Raycast | IntegratorKind::Whitted => {
                self.raycast_step(ray, &surf, &bsdf, wo, key, sink)
            }
            IntegratorKind::Primary => {
                // First-hit shading (Little 2011's ray caster): every light's sample taken
                // as the shadow rays of `raycast` would take it, its contribution added as
                // if the shadow ray had reached the light. No ambient term.
                if self.settings.effects.contains(Effect::DirectLight)
                    && !bsdf.is_delta_only()
                    && let Some(at) = bsdf.at(wo)
                {
                    self.direct_light(ray, &surf, &at, key, DirectMode::UNSHADOWED, sink);
                }
            }
            IntegratorKind::Ao => {}
        }
    }

    /// Emission seen directly, or by a bounce weighted (power heuristic) against the
    /// light sampling that could have found the same emitter.
    fn emission_seen(&self, ray: &RayState, surf: &Surface, emission: Vec3, sink: &mut impl Sink) {
        if emission != Vec3::ZERO {
            let mut w = 1.0;
            if ray.bsdf_pdf > 0.0 {
                let pl = self
                    .lights
                    .pdf_triangle(self.scene, surf.tri, ray.origin, surf.p);
                w = power_heuristic(ray.bsdf_pdf, pl);
            }
            self.emit(ray.pixel, ray.depth, ray.weight * emission * w, sink);
        }
    }

    /// The `ao` integrator's rays at a hit: `ao_samples` cosine-weighted occlusion rays of
    /// length `ao_distance`, each carrying its share of the ray's weight.
    fn ao_rays(&self, ray: &RayState, surf: &Surface, key: PathStream, sink: &mut impl Sink) {
        let n = self.settings.ao_samples.max(1);
        let origin = offset_ray_origin(surf.p, surf.p_err, surf.ng);
        for i in 0..n {
            let u = key.uniform2(ray.depth, Purpose::AmbientOcclusion, i);
            let dir = cosine_hemisphere(surf.ng, u);
            sink.spawn(RayState {
                origin,
                dir,
                tmax: self.settings.ao_distance,
                depth: ray.depth + 1,
                kind: RayKind::AmbientOcclusion,
                weight: ray.weight / n as f32,
                bsdf_pdf: 0.0,
                ..*ray
            });
        }
    }

    /// `KHR_materials_dispersion`: at a transmissive hit whose material disperses, the
    /// path follows one colour channel from here (core/src/dispersion.rs): the ray with
    /// that channel's weight, and the channel's index of refraction. None elsewhere.
    fn disperse(
        &self,
        ray: &RayState,
        sv: &ShadingValues,
        key: PathStream,
    ) -> Option<(RayState, f32)> {
        if !(sv.dispersion > 0.0 && sv.transmission > 0.0) {
            return None;
        }
        let u = key.uniform(ray.depth, Purpose::Dispersion, 0);
        let (channel, weight) = crate::dispersion::pick_channel(ray.weight, u)?;
        let ior = crate::dispersion::channel_ior(sv.ior, sv.dispersion, channel);
        Some((RayState { weight, ..*ray }, ior))
    }

    /// `raycast` and `whitted` at a hit: direct light at full weight, unshadowed ambient
    /// light from the constant environment, and Whitted's mirror and refraction rays.
    fn raycast_step(
        &self,
        ray: &RayState,
        surf: &HitPoint,
        bsdf: &Bsdf,
        wo: Vec3,
        key: PathStream,
        sink: &mut impl Sink,
    ) {
        if self.settings.effects.contains(Effect::DirectLight)
            && !bsdf.is_delta_only()
            && let Some(at) = bsdf.at(wo)
        {
            self.direct_light(ray, surf, &at, key, DirectMode::FULL_WEIGHT, sink);
        }
        // Unshadowed ambient light from the constant environment: raycast and Whitted
        // trace no rays toward the sky, so this keeps unlit scenes legible.
        let env = self.env();
        if env != Vec3::ZERO {
            let facing = surf.n.dot(wo).abs();
            let ambient = bsdf.diffuse_albedo() * env * (0.25 + 0.75 * facing);
            // Reflected here too: one surface more than the ray's depth.
            self.emit(ray.pixel, ray.depth + 1, ray.weight * ambient, sink);
        }
        if self.settings.integrator == IntegratorKind::Whitted
            && ray.depth + 1 < self.settings.max_depth
        {
            self.whitted_children(ray, surf, bsdf, wo, sink);
        }
    }

    /// A light sample's shadow ray `s`: traced (spawned) when `mode` casts shadow rays,
    /// else its contribution added at once, as [`Integrator::shadow_result`] adds it for
    /// a shadow ray that nothing blocked.
    fn light_out(&self, s: Option<RayState>, mode: DirectMode, sink: &mut impl Sink) {
        let Some(s) = s else {
            return;
        };
        if mode.shadowed {
            sink.spawn(s);
        } else {
            self.shadow_result(&s, false, sink);
        }
    }

    /// A shadow ray from `surf` toward light sample `ls`, carrying `contribution`.
    fn shadow_ray(
        &self,
        ray: &RayState,
        surf: &HitPoint,
        ls: &LightSample,
        contribution: Vec3,
    ) -> Option<RayState> {
        if !contribution.is_finite() || contribution.max_element() <= 0.0 {
            return None;
        }
        let origin = surf.origin_toward(ls.wi);
        let (dir, tmax) = if ls.dist.is_finite() {
            let target = if ls.delta {
                ls.light_p
            } else {
                offset_ray_origin(ls.light_p, ls.light_p_err, ls.light_n)
            };
            let d = target - origin;
            let len = d.length();
            (d / len, len * (1.0 - SHADOW_EPSILON))
        } else {
            (ls.wi, f32::INFINITY)
        };
        if !dir.is_finite() || tmax.is_nan() || tmax <= 0.0 {
            return None;
        }
        Some(RayState {
            origin,
            dir,
            tmax,
            depth: ray.depth + 1,
            kind: RayKind::Shadow,
            weight: contribution,
            bsdf_pdf: 0.0,
            ..*ray
        })
    }

    /// Direct light: every punctual light with its own shadow ray (they are few and
    /// cheap, and sampling one by power starves dim-but-near lights), N samples of the
    /// sun's disk, N of the environment map, and N emissive-triangle samples, each
    /// chosen by power, where N is the job's `--light-samples` (1 by default). Sample k
    /// of a light draws its numbers with index k, so each is independent of the others
    /// and the same wherever the hit is shaded; each carries 1/N of its contribution.
    /// Punctual lights take one sample whatever N is: it is exact. With `mode.mis`, the
    /// area and distant samples are weighted against BSDF sampling (path tracing) as one
    /// sample is: the light samples' mean and the BSDF sample still weigh every
    /// direction by one in all, so the estimate is unbiased, and only the light-sampled
    /// part's variance falls (by 1/N) while the BSDF sample keeps its share. Weights
    /// counting the N samples (Veach's `n p`) would hand that share to the light too,
    /// which is worse where BSDF sampling is the better strategy: on a diffuse plane
    /// under a sky map they made 16 samples noisier than one (docs/lights.md "Light
    /// samples per hit"). Raycast and Whitted take them at full weight. Without
    /// `mode.shadowed` (the `primary` integrator) no shadow ray is cast: each sample's
    /// contribution is added unoccluded.
    #[allow(clippy::too_many_arguments)]
    fn direct_light(
        &self,
        ray: &RayState,
        surf: &HitPoint,
        bsdf: &BsdfAt,
        key: PathStream,
        mode: DirectMode,
        sink: &mut impl Sink,
    ) {
        for e in self.lights.punctual_entries() {
            if let Some(ls) = self
                .lights
                .sample_entry(self.scene, e, 1.0, surf.p, Vec2::ZERO)
            {
                let c = ray.weight * bsdf.eval(ls.wi) * surf.n.dot(ls.wi).abs() * ls.li / ls.pdf;
                self.light_out(self.shadow_ray(ray, surf, &ls, c), mode, sink);
            }
        }
        let n = self.settings.lighting.samples.get();
        if let Some(sun) = self.sun() {
            for k in 0..n {
                let wi = sun.sample(key.uniform2(ray.depth, Purpose::SunPoint, k));
                let sample = (wi, sun.radiance(), sun.pdf());
                self.distant_sample(ray, surf, bsdf, sample, mode, sink);
            }
        }
        if let Some(map) = self.env_map() {
            for k in 0..n {
                if let Some(sample) = map.sample(key.uniform2(ray.depth, Purpose::EnvMapPoint, k)) {
                    self.distant_sample(ray, surf, bsdf, sample, mode, sink);
                }
            }
        }
        if !self.lights.has_area() {
            return;
        }
        for k in 0..n {
            let u_sel = key.uniform(ray.depth, Purpose::LightSelect, k);
            let Some((e, p)) = self.lights.choose_area(u_sel) else {
                continue;
            };
            let u = key.uniform2(ray.depth, Purpose::LightPoint, k);
            if let Some(ls) = self.lights.sample_entry(self.scene, e, p, surf.p, u) {
                let (f, pdf) = bsdf.eval_pdf(ls.wi);
                let w = if mode.mis {
                    power_heuristic(ls.pdf, pdf)
                } else {
                    1.0
                };
                let c = ray.weight
                    * f
                    * surf.n.dot(ls.wi).abs()
                    * ls.li
                    * (w / ls.pdf * self.per_light_sample());
                self.light_out(self.shadow_ray(ray, surf, &ls, c), mode, sink);
            }
        }
    }

    /// The share of a light's contribution one of its N samples carries, 1/N. At N = 1,
    /// 1.0, and a product by 1.0 is exact in IEEE 754, so one sample's contribution
    /// keeps the bits it had before N existed.
    fn per_light_sample(&self) -> f32 {
        1.0 / self.settings.lighting.samples.get() as f32
    }

    /// A shadow ray toward a light at infinity (the sun, the environment map) along
    /// `wi`, of radiance `li` sampled with solid-angle density `pdf_l`, carrying its
    /// share of the light's N samples; with `mode.mis`, weighted against BSDF sampling,
    /// as the miss that finds the same light is ([`Integrator::shade_miss`]).
    fn distant_sample(
        &self,
        ray: &RayState,
        surf: &HitPoint,
        bsdf: &BsdfAt,
        (wi, li, pdf_l): (Vec3, Vec3, f32),
        mode: DirectMode,
        sink: &mut impl Sink,
    ) {
        let (f, pdf) = bsdf.eval_pdf(wi);
        let w = if mode.mis {
            power_heuristic(pdf_l, pdf)
        } else {
            1.0
        };
        let ls = LightSample {
            wi,
            dist: f32::INFINITY,
            li,
            pdf: pdf_l,
            delta: false,
            light_p: surf.p,
            light_p_err: Vec3::ZERO,
            light_n: -wi,
        };
        let c = ray.weight * f * surf.n.dot(wi).abs() * li * (w / pdf_l * self.per_light_sample());
        self.light_out(self.shadow_ray(ray, surf, &ls, c), mode, sink);
    }

    /// Whitted's mirror and refraction rays. Up to [`WHITTED_BRANCH_DEPTH`] bounces a hit
    /// on glass spawns both; deeper, it spawns one of them, chosen with probability
    /// proportional to its weight (and weighted by the inverse), which has the same
    /// expectation. A ray tree then holds at most 2^[`WHITTED_BRANCH_DEPTH`] chains of
    /// bounces whatever the depth, so its credit (and its ray count) is bounded at the
    /// deepest depth a job accepts (docs/numerics.md "Deep ray trees").
    fn whitted_children(
        &self,
        ray: &RayState,
        surf: &HitPoint,
        bsdf: &Bsdf,
        wo: Vec3,
        sink: &mut impl Sink,
    ) {
        let effects = self.settings.effects;
        let mirror = if effects.contains(Effect::Specular) {
            bsdf.mirror(wo)
                .map(|(wi, w)| (wi, ray.weight * w, RayKind::Reflection))
        } else {
            None
        };
        let refraction = if effects.contains(Effect::Transmission) {
            bsdf.refraction(wo)
                .map(|(wi, w)| (wi, ray.weight * w, RayKind::Refraction))
        } else {
            None
        };
        let children = match (mirror, refraction) {
            (Some(m), Some(r)) if ray.depth >= WHITTED_BRANCH_DEPTH => {
                let (lm, lr) = (m.1.max_element().max(0.0), r.1.max_element().max(0.0));
                let pm = if lm + lr > 0.0 { lm / (lm + lr) } else { 0.5 };
                let u = self.key(ray).uniform(ray.depth, Purpose::Roulette, 0);
                if u < pm {
                    [Some((m.0, m.1 / pm, m.2)), None]
                } else {
                    [Some((r.0, r.1 / (1.0 - pm), r.2)), None]
                }
            }
            (m, r) => [m, r],
        };
        for (wi, weight, kind) in children.into_iter().flatten() {
            self.spawn_bounce(ray, surf, wi, weight, kind, 0.0, sink);
        }
    }

    #[allow(clippy::too_many_arguments)]
    fn spawn_bounce(
        &self,
        ray: &RayState,
        surf: &HitPoint,
        wi: Vec3,
        weight: Vec3,
        kind: RayKind,
        pdf: f32,
        sink: &mut impl Sink,
    ) {
        if !weight.is_finite() || weight.max_element() <= 0.0 || !wi.is_finite() {
            return;
        }
        sink.spawn(RayState {
            origin: surf.origin_toward(wi),
            dir: wi,
            tmax: f32::INFINITY,
            depth: ray.depth + 1,
            kind,
            weight,
            bsdf_pdf: pdf,
            ..*ray
        });
    }

    /// Path tracing: the light samples of [`Integrator::direct_light`] (MIS-weighted),
    /// then one BSDF sample with Russian roulette.
    fn path_step(
        &self,
        ray: &RayState,
        surf: &HitPoint,
        bsdf: &Bsdf,
        wo: Vec3,
        key: PathStream,
        sink: &mut impl Sink,
    ) {
        let depth = ray.depth;
        if depth + 1 > self.settings.max_depth {
            return;
        }
        let effects = self.settings.effects;
        let nee = effects.contains(Effect::DirectLight)
            && !bsdf.is_delta_only()
            && (!self.lights.is_empty() || self.sun().is_some() || self.env_map().is_some());
        // With no frame for `wo` every evaluation is zero and every sample absorbed:
        // neither a shadow ray nor a bounce would carry anything.
        let Some(at) = bsdf.at(wo) else {
            return;
        };
        if nee {
            self.direct_light(ray, surf, &at, key, DirectMode::MIS, sink);
        }
        let u_lobe = key.uniform(depth, Purpose::BsdfLobe, 0);
        let u = key.uniform2(depth, Purpose::BsdfDirection, 0);
        let Some(bs) = at.sample(u_lobe, u) else {
            return;
        };
        let mut weight = ray.weight * bs.f * surf.n.dot(bs.wi).abs() / bs.pdf;
        // Russian roulette after three bounces.
        if depth >= 3 {
            let q = weight.max_element().min(0.95);
            if key.uniform(depth, Purpose::Roulette, 0) >= q {
                return;
            }
            weight /= q;
        }
        let kind = match bs.lobe {
            Lobe::Diffuse | Lobe::Sheen => RayKind::Diffuse,
            Lobe::GlossyReflection | Lobe::SpecularReflection | Lobe::CoatReflection => {
                RayKind::Reflection
            }
            Lobe::SpecularTransmission | Lobe::GlossyTransmission => RayKind::Refraction,
        };
        let pdf = if bs.delta || !nee { 0.0 } else { bs.pdf };
        self.spawn_bounce(ray, surf, bs.wi, weight, kind, pdf, sink);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn integrators_are_named_once_and_found_by_name() {
        for k in IntegratorKind::ALL {
            assert_eq!(IntegratorKind::from_name(k.name()), Some(k));
        }
        assert_eq!(IntegratorKind::from_name("bdpt"), None);
        assert_eq!(
            IntegratorKind::choices(),
            "raycast, primary, whitted, path or ao"
        );
    }

    #[test]
    fn credit_suffices_at_the_deepest_depth_the_most_samples_and_lights() {
        use crate::credit::Credit;
        use crate::film::MAX_SPP;
        use crate::light::{Light, MAX_PUNCTUAL_LIGHTS};
        use crate::light_samples::{LightSamples, MAX_LIGHT_SAMPLES};
        use crate::tiles::TILE_SIZE;
        // The most punctual lights a scene may have, and an emitter.
        let mut scene = Scene::default();
        let base = scene.mesh.push_vertices(&[Vec3::ZERO, Vec3::X, Vec3::Y]);
        scene.mesh.indices.push([base, base + 1, base + 2]);
        scene.mesh.material.push(0);
        scene.materials.push(Material {
            emissive: Vec3::ONE,
            ..Material::default()
        });
        scene.lights = (0..MAX_PUNCTUAL_LIGHTS)
            .map(|i| Light::Point {
                position: Vec3::new(i as f32, 2.0, 0.0),
                intensity: Vec3::ONE,
            })
            .collect();
        // What each camera ray of a whole tile gets at the most samples.
        let rays = u64::from(TILE_SIZE * TILE_SIZE) * u64::from(MAX_SPP);
        let per_ray = Credit::TILE.to_wire() / rays;
        let mut deepest = 0;
        for integrator in IntegratorKind::ALL {
            let settings = RenderSettings {
                width: 64,
                height: 64,
                spp: MAX_SPP,
                integrator,
                max_depth: MAX_DEPTH,
                seed: 0,
                environment: Vec3::ONE,
                effects: Effect::ALL.into_iter().fold(Effects::NONE, Effects::with),
                ao_samples: 4096,
                ao_distance: f32::INFINITY,
                // And a sun and an environment map; these and the emitter each take
                // the most samples a job may ask for, MAX_LIGHT_SAMPLES shadow rays per
                // hit.
                lighting: Lighting {
                    sun: Some(Sun::new(0.0, 45.0, 1.0, crate::sun::SUN_DIAMETER_DEG).expect("sun")),
                    env_map: Some(Arc::new(
                        EnvMap::new(1, 1, vec![Vec3::ONE], 0.0, 1.0).expect("map"),
                    )),
                    samples: LightSamples::new(MAX_LIGHT_SAMPLES).expect("the bound"),
                },
                clamp_indirect: None,
                aovs: Default::default(),
            };
            let cam = Camera::look_at("c", Vec3::Z, Vec3::ZERO, Vec3::Y, 0.5);
            let need = Integrator::new(&scene, cam, settings).credit_needed();
            assert!(
                need.to_wire() <= per_ray,
                "{integrator:?}: a camera ray needs {need}, gets {per_ray}"
            );
            deepest = deepest.max(need.to_wire());
        }
        // Whitted's tree: 2^8 chains of 1024 hits, each hit with a shadow ray per
        // punctual light and MAX_LIGHT_SAMPLES to each of the other three.
        assert!(
            deepest > (1 << 8) * 1000 * u64::from(MAX_PUNCTUAL_LIGHTS + 3 * MAX_LIGHT_SAMPLES),
            "{deepest}"
        );
    }

    #[test]
    fn kinds_are_named_once_and_found_by_name() {
        for (i, k) in RayKind::ALL.into_iter().enumerate() {
            assert_eq!(k as usize, i, "ALL is in discriminant order");
            assert_eq!(RayKind::NAMES[i], k.name());
            assert_eq!(RayKind::from_name(k.name()), Some(k));
        }
        assert_eq!(RayKind::from_name("ao"), None);
        assert!(RayKind::RADIANCE.iter().all(|k| !k.is_occlusion()));
        assert_eq!(
            RayKind::RADIANCE.len(),
            RayKind::ALL.iter().filter(|k| !k.is_occlusion()).count()
        );
        assert_eq!(RayKind::help_list(&RayKind::ALL), RayKind::NAMES.join(", "));
    }
}

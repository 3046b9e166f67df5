//! Picking a light to sample: punctual lights and emissive triangles, chosen in proportion
//! to their power. The table is small (it lists lights, not geometry) and every worker
//! holds all of it.

use glam::{Vec2, Vec3};

use crate::intersect::interpolate_with_error;
use crate::light::Light;
use crate::material::{Material, TexCoords};
use crate::sampling::uniform_triangle;
use crate::scene::Scene;
use crate::surface::interpolate_uv;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LightRef {
    Punctual(u32),
    Triangle(u32),
}

/// A sampled direction toward a light.
#[derive(Clone, Copy, Debug)]
pub struct LightSample {
    /// Unit direction from the shading point toward the light.
    pub wi: Vec3,
    /// Distance to the light point (infinite for directional lights).
    pub dist: f32,
    /// Incident radiance (area lights) or irradiance-like intensity (delta lights), before
    /// the selection probability.
    pub li: Vec3,
    /// Solid-angle pdf including the selection probability; for delta lights, just the
    /// selection probability.
    pub pdf: f32,
    pub delta: bool,
    /// The point on an area light (for the shadow ray's far end) and its normal.
    pub light_p: Vec3,
    /// A bound on each coordinate's rounding error in `light_p` (zero for punctual lights:
    /// no surface lies there for the shadow ray to stop short of).
    pub light_p_err: Vec3,
    pub light_n: Vec3,
}

pub struct LightSampler {
    /// The punctual lights first (`..punctual`), then the emissive triangles.
    entries: Vec<LightRef>,
    /// How many entries are punctual lights.
    punctual: usize,
    pmf: Vec<f32>,
    cdf: Vec<f32>,
    /// Entries of the emissive triangles only, with their own distribution, for the
    /// integrators that loop over punctual lights and take one area-light sample.
    area_entries: Vec<u32>,
    area_pmf: Vec<f32>,
    area_cdf: Vec<f32>,
    /// (triangle, entry index), sorted by triangle, for MIS look-ups.
    tri_entry: Vec<(u32, u32)>,
    scene_radius: f32,
    /// The whole scene's bounds, as given: where camera rays start (see
    /// [`crate::camera::Frustum::clipped_to`]).
    bounds: (Vec3, Vec3),
}

/// Normalised probabilities and their running sum.
fn distribution(weights: &[f32]) -> (Vec<f32>, Vec<f32>) {
    let total: f64 = weights.iter().map(|&w| w as f64).sum();
    let pmf: Vec<f32> = weights.iter().map(|&w| (w as f64 / total) as f32).collect();
    let mut acc = 0.0f64;
    let cdf = weights
        .iter()
        .map(|&w| {
            acc += w as f64 / total;
            acc as f32
        })
        .collect();
    (pmf, cdf)
}

fn luminance(c: Vec3) -> f32 {
    c.x * 0.2126 + c.y * 0.7152 + c.z * 0.0722
}

impl LightSampler {
    pub fn new(scene: &Scene, use_emission: bool) -> LightSampler {
        LightSampler::with_bounds(scene, use_emission, scene.bounds())
    }

    /// [`LightSampler::new`] with the whole scene's bounds given, for a worker whose
    /// `scene` holds only its own domains and the emitters: the light powers (which read
    /// the scene radius) then match those of the whole scene exactly.
    pub fn with_bounds(scene: &Scene, use_emission: bool, bounds: (Vec3, Vec3)) -> LightSampler {
        let (lo, hi) = bounds;
        let scene_radius = ((hi - lo).length() * 0.5).max(1e-6);
        let mut entries = Vec::new();
        let mut weights = Vec::new();
        for (i, l) in scene.lights.iter().enumerate() {
            let w = l.power_weight(scene_radius);
            if w > 0.0 && w.is_finite() {
                entries.push(LightRef::Punctual(i as u32));
                weights.push(w);
            }
        }
        if use_emission {
            for (t, &m) in scene.mesh.material.iter().enumerate() {
                let Some(mat) = scene.materials.get(m as usize) else {
                    continue;
                };
                if !mat.has_emission() {
                    continue;
                }
                let [a, b, c] = scene.mesh.corners(t);
                let area = 0.5 * (b - a).cross(c - a).length();
                let sides = if mat.double_sided { 2.0 } else { 1.0 };
                let w = area * luminance(mat.emissive) * std::f32::consts::PI * sides;
                if w > 0.0 && w.is_finite() {
                    entries.push(LightRef::Triangle(t as u32));
                    weights.push(w);
                }
            }
        }
        let punctual = entries
            .iter()
            .take_while(|r| matches!(r, LightRef::Punctual(_)))
            .count();
        let (pmf, cdf) = distribution(&weights);
        let area_entries: Vec<u32> = (0..entries.len() as u32)
            .filter(|&e| matches!(entries[e as usize], LightRef::Triangle(_)))
            .collect();
        let area_weights: Vec<f32> = area_entries.iter().map(|&e| weights[e as usize]).collect();
        let (area_pmf, area_cdf) = distribution(&area_weights);
        let mut tri_entry: Vec<(u32, u32)> = entries
            .iter()
            .enumerate()
            .filter_map(|(e, r)| match r {
                LightRef::Triangle(t) => Some((*t, e as u32)),
                LightRef::Punctual(_) => None,
            })
            .collect();
        tri_entry.sort_unstable();
        LightSampler {
            entries,
            punctual,
            pmf,
            cdf,
            area_entries,
            area_pmf,
            area_cdf,
            tri_entry,
            scene_radius,
            bounds,
        }
    }

    /// The whole scene's bounds this sampler was made with.
    pub fn scene_bounds(&self) -> (Vec3, Vec3) {
        self.bounds
    }

    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    pub fn len(&self) -> usize {
        self.entries.len()
    }

    pub fn entries(&self) -> &[LightRef] {
        &self.entries
    }

    /// Choose an entry with probability proportional to power.
    pub fn choose(&self, u: f32) -> Option<(usize, f32)> {
        if self.entries.is_empty() {
            return None;
        }
        let i = self
            .cdf
            .partition_point(|&c| c <= u)
            .min(self.entries.len() - 1);
        Some((i, self.pmf[i]))
    }

    /// The entries of the punctual lights, which direct lighting visits every one of:
    /// a range, so a scene with thousands of emissive triangles does not walk past them
    /// all at every shaded point to find its few punctual lights.
    pub fn punctual_entries(&self) -> std::ops::Range<usize> {
        0..self.punctual
    }

    /// Whether any light has an area (emissive triangles): without one, a shaded hit
    /// draws no number to choose among them.
    pub fn has_area(&self) -> bool {
        !self.area_entries.is_empty()
    }

    /// Choose an emissive-triangle entry with probability proportional to power.
    #[inline]
    pub fn choose_area(&self, u: f32) -> Option<(usize, f32)> {
        if !self.has_area() {
            return None;
        }
        let i = self
            .area_cdf
            .partition_point(|&c| c <= u)
            .min(self.area_entries.len() - 1);
        Some((self.area_entries[i] as usize, self.area_pmf[i]))
    }

    /// Sample entry `entry` (selected with probability `p_select`) from point `p`.
    pub fn sample_entry(
        &self,
        scene: &Scene,
        entry: usize,
        p_select: f32,
        p: Vec3,
        u: Vec2,
    ) -> Option<LightSample> {
        match *self.entries.get(entry)? {
            LightRef::Punctual(i) => {
                let light = scene.lights.get(i as usize)?;
                let (wi, dist, li) = match light {
                    Light::Point {
                        position,
                        intensity,
                    } => {
                        let d = *position - p;
                        let dist = d.length();
                        (d / dist, dist, *intensity / (dist * dist))
                    }
                    Light::Spot {
                        position,
                        direction,
                        intensity,
                        inner_cone,
                        outer_cone,
                    } => {
                        let d = *position - p;
                        let dist = d.length();
                        let wi = d / dist;
                        // glTF KHR_lights_punctual smooth cone falloff.
                        let cos_outer = outer_cone.cos();
                        let cos_inner = inner_cone.cos();
                        let scale = 1.0 / (cos_inner - cos_outer).max(1e-4);
                        let cd = direction.dot(-wi);
                        let a = ((cd - cos_outer) * scale).clamp(0.0, 1.0);
                        (wi, dist, *intensity * (a * a) / (dist * dist))
                    }
                    Light::Directional {
                        direction,
                        irradiance,
                    } => (-*direction, f32::INFINITY, *irradiance),
                };
                if !wi.is_finite() || !li.is_finite() || li == Vec3::ZERO {
                    return None;
                }
                Some(LightSample {
                    wi,
                    dist,
                    li,
                    pdf: p_select,
                    delta: true,
                    light_p: if dist.is_finite() { p + wi * dist } else { p },
                    light_p_err: Vec3::ZERO,
                    light_n: -wi,
                })
            }
            LightRef::Triangle(t) => {
                let mat = scene
                    .materials
                    .get(*scene.mesh.material.get(t as usize)? as usize)?;
                let [a, b, c] = scene.mesh.corners(t as usize);
                let (b1, b2) = uniform_triangle(u);
                let b0 = 1.0 - b1 - b2;
                let (q, q_err) = interpolate_with_error([a, b, c], [b0, b1, b2]);
                let cross = (b - a).cross(c - a);
                let area = 0.5 * cross.length();
                let n = cross.normalize_or_zero();
                let d = q - p;
                let dist2 = d.length_squared();
                let dist = dist2.sqrt();
                let wi = d / dist;
                let cos_l = n.dot(-wi);
                if !mat.double_sided && cos_l <= 0.0 {
                    return None;
                }
                let cos_l = cos_l.abs();
                if area <= 0.0 || cos_l <= 1e-7 || !wi.is_finite() {
                    return None;
                }
                let uv = interpolate_uv(scene, t, [b0, b1, b2]);
                let le = emitted(scene, mat, uv);
                let pdf = p_select * dist2 / (area * cos_l);
                if !pdf.is_finite() || pdf <= 0.0 {
                    return None;
                }
                Some(LightSample {
                    wi,
                    dist,
                    li: le,
                    pdf,
                    delta: false,
                    light_p: q,
                    light_p_err: q_err,
                    light_n: if n.dot(wi) < 0.0 { n } else { -n },
                })
            }
        }
    }

    /// Sample one light chosen by power.
    pub fn sample(&self, scene: &Scene, p: Vec3, u_select: f32, u: Vec2) -> Option<LightSample> {
        let (e, pmf) = self.choose(u_select)?;
        self.sample_entry(scene, e, pmf, p, u)
    }

    /// The solid-angle pdf with which the area-light sample of the integrators
    /// ([`LightSampler::choose_area`] then [`LightSampler::sample_entry`]) would have produced the
    /// point `q` (normal `nq`) on emissive triangle `tri`, seen from `p`. Zero when the
    /// triangle is not in the table.
    pub fn pdf_triangle(&self, scene: &Scene, tri: u32, p: Vec3, q: Vec3) -> f32 {
        let Ok(k) = self.tri_entry.binary_search_by_key(&tri, |&(t, _)| t) else {
            return 0.0;
        };
        let entry = self.tri_entry[k].1;
        let Ok(ai) = self.area_entries.binary_search(&entry) else {
            return 0.0;
        };
        let [a, b, c] = scene.mesh.corners(tri as usize);
        let cross = (b - a).cross(c - a);
        let area = 0.5 * cross.length();
        let n = cross.normalize_or_zero();
        let d = q - p;
        let dist2 = d.length_squared();
        let cos_l = n.dot(d.normalize_or_zero()).abs();
        if area <= 0.0 || cos_l <= 1e-7 {
            return 0.0;
        }
        let pdf = self.area_pmf[ai] * dist2 / (area * cos_l);
        if pdf.is_finite() { pdf } else { 0.0 }
    }

    pub fn scene_radius(&self) -> f32 {
        self.scene_radius
    }
}

/// Emitted radiance of material `m` at texture coordinates `uv` (both sides handled by
/// the caller).
pub fn emitted(scene: &Scene, m: &Material, uv: TexCoords) -> Vec3 {
    let t = m
        .emissive_tex
        .and_then(|r| Some((scene.textures.get(r.texture as usize)?, r.uv(uv))))
        .map(|(t, uv)| t.sample(uv, true).truncate())
        .unwrap_or(Vec3::ONE);
    (m.emissive * t).max(Vec3::ZERO)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::material::Material;

    #[test]
    fn punctual_entries_are_exactly_the_punctual_lights() {
        // Emissive triangles and punctual lights; the triangles' entries must not be
        // walked to find the lights (direct lighting visits the range at every hit).
        let mut scene = Scene::default();
        for k in 0..5 {
            let o = Vec3::new(k as f32, 0.0, 0.0);
            let base = scene.mesh.push_vertices(&[o, o + Vec3::X, o + Vec3::Y]);
            scene.mesh.indices.push([base, base + 1, base + 2]);
            scene.mesh.material.push(0);
        }
        scene.materials.push(Material {
            emissive: Vec3::ONE,
            ..Material::default()
        });
        scene.lights = (0..3)
            .map(|i| Light::Point {
                position: Vec3::new(i as f32, 2.0, 0.0),
                intensity: Vec3::ONE,
            })
            .collect();
        let s = LightSampler::new(&scene, true);
        let range = s.punctual_entries();
        assert_eq!(range, 0..3);
        for (e, r) in s.entries().iter().enumerate() {
            assert_eq!(
                range.contains(&e),
                matches!(r, LightRef::Punctual(_)),
                "entry {e}"
            );
        }
        assert!(s.has_area());
        // Without emission the triangles are no lights at all.
        let s = LightSampler::new(&scene, false);
        assert_eq!((s.punctual_entries(), s.has_area()), (0..3, false));
    }
}

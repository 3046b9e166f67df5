//! What a ray sees where it hits: position, normals, texture coordinates and the material
//! evaluated there (textures applied).

use glam::{Vec2, Vec3, Vec4};

use crate::bvh::Hit;
use crate::effects::{Effect, Effects};
use crate::intersect::interpolate_with_error;
use crate::material::{AlphaMode, Material, TexCoords, TexRef};
use crate::scene::Scene;

/// A hit point with everything shading needs.
#[derive(Clone, Copy, Debug)]
pub struct Surface {
    /// World position, from barycentrics (more accurate than origin + t * dir).
    pub p: Vec3,
    /// A bound on each coordinate's rounding error in `p`
    /// ([`crate::intersect::interpolate_with_error`]): rays leaving the surface start
    /// just outside it ([`crate::intersect::offset_ray_origin`]).
    pub p_err: Vec3,
    /// Unit geometric normal, facing the incoming ray's origin.
    pub ng: Vec3,
    /// Unit shading normal on the same side as `ng`.
    pub n: Vec3,
    /// The clear coat's own shading normal (`clearcoatNormalTexture`), on the same side
    /// as `ng`; zero when the coat has no normal map (it then uses `n`).
    pub coat_n: Vec3,
    /// Texture coordinates (both UV sets; each texture reads the one it names). Zero
    /// when nothing at this hit reads them (textures off, or a material without
    /// textures): interpolating them then cost a cache miss per hit on the mesh's UV
    /// rows and changed no value the render uses.
    pub uv: TexCoords,
    /// Interpolated vertex colour (white when the mesh has none).
    pub color: Vec4,
    /// Unit tangent and bitangent of the shading frame (from the mesh's tangents), for
    /// anisotropic materials only; zero otherwise.
    pub tangent: Vec3,
    pub bitangent: Vec3,
    /// Whether the ray hit the front face (counter-clockwise winding, glTF convention).
    pub front: bool,
    pub tri: u32,
    pub material: u32,
}

/// Material values at a surface point, after textures.
#[derive(Clone, Copy, Debug)]
pub struct ShadingValues {
    pub base_color: Vec3,
    pub alpha: f32,
    pub metallic: f32,
    pub roughness: f32,
    pub specular: f32,
    pub specular_color: Vec3,
    pub transmission: f32,
    pub ior: f32,
    pub emission: Vec3,
    /// `KHR_materials_clearcoat` strength (0: no coat) and roughness.
    pub clearcoat: f32,
    pub clearcoat_roughness: f32,
    /// `KHR_materials_sheen` colour (black: no sheen) and roughness.
    pub sheen_color: Vec3,
    pub sheen_roughness: f32,
    /// `KHR_materials_anisotropy` strength (0: isotropic) and world direction.
    pub anisotropy: f32,
    pub anisotropy_direction: Vec3,
    /// `KHR_materials_iridescence` strength (0: no film), film index and thickness (nm).
    pub iridescence: f32,
    pub iridescence_ior: f32,
    pub iridescence_thickness: f32,
    /// `KHR_materials_dispersion` (20 / Abbe number; 0: none).
    pub dispersion: f32,
}

fn tex(scene: &Scene, r: Option<TexRef>, uv: TexCoords, srgb: bool) -> Vec4 {
    match r.and_then(|r| Some((scene.textures.get(r.texture as usize)?, r.uv(uv)))) {
        Some((t, uv)) => t.sample(uv, srgb),
        None => Vec4::ONE,
    }
}

/// Interpolated texture coordinates of triangle `tri` at barycentrics: both UV sets,
/// the second zero (and not computed) when the mesh has none.
pub fn interpolate_uv(scene: &Scene, tri: u32, b: [f32; 3]) -> TexCoords {
    let idx = scene.mesh.indices[tri as usize];
    let uvs = &scene.mesh.uvs;
    let first =
        uvs[idx[0] as usize] * b[0] + uvs[idx[1] as usize] * b[1] + uvs[idx[2] as usize] * b[2];
    let uvs2 = &scene.mesh.uvs2;
    let second = if uvs2.is_empty() {
        Vec2::ZERO
    } else {
        let at = |k: usize| uvs2.get(idx[k] as usize).copied().unwrap_or(Vec2::ZERO);
        at(0) * b[0] + at(1) * b[1] + at(2) * b[2]
    };
    TexCoords { first, second }
}

/// Interpolated vertex colour of triangle `tri` at barycentrics; white when the mesh
/// has no vertex colours.
pub fn interpolate_color(scene: &Scene, tri: u32, b: [f32; 3]) -> Vec4 {
    let colors = &scene.mesh.colors;
    if colors.is_empty() {
        return Vec4::ONE;
    }
    let idx = scene.mesh.indices[tri as usize];
    let at = |k: usize| colors.get(idx[k] as usize).copied().unwrap_or(Vec4::ONE);
    at(0) * b[0] + at(1) * b[1] + at(2) * b[2]
}

/// Alpha of a surface point (base colour alpha times texture alpha times vertex colour
/// alpha, as glTF multiplies them).
pub fn alpha_at(scene: &Scene, m: &Material, uv: TexCoords, vertex_alpha: f32) -> f32 {
    m.base_color.w * tex(scene, m.base_color_tex, uv, true).w * vertex_alpha
}

impl Surface {
    /// Build the surface for `hit` on a ray travelling along `dir`.
    pub fn new(scene: &Scene, hit: &Hit, dir: Vec3, effects: Effects) -> Surface {
        let mesh = &scene.mesh;
        let idx = mesh.indices[hit.tri as usize];
        let [a, b, c] = idx.map(|i| mesh.positions[i as usize]);
        let bary = [hit.b0, hit.b1, hit.b2];
        let (p, p_err) = interpolate_with_error([a, b, c], bary);
        let mut ng = (b - a).cross(c - a).normalize_or_zero();
        if ng == Vec3::ZERO {
            ng = -dir;
        }
        let front = ng.dot(dir) < 0.0;
        if !front {
            ng = -ng;
        }
        let ns = idx.map(|i| mesh.normals[i as usize]);
        let mut n = (ns[0] * bary[0] + ns[1] * bary[1] + ns[2] * bary[2]).normalize_or_zero();
        let material = mesh.material[hit.tri as usize];
        // A missing material stands in as the glTF default, which has no textures.
        let reads_uv = effects.contains(Effect::Textures)
            && scene
                .materials
                .get(material as usize)
                .is_some_and(|m| m.has_textures());
        let uv = if reads_uv {
            interpolate_uv(scene, hit.tri, bary)
        } else {
            TexCoords::default()
        };
        let color = interpolate_color(scene, hit.tri, bary);
        let mut coat_n = Vec3::ZERO;
        if let Some(m) = scene.materials.get(material as usize)
            && effects.contains(Effect::Textures)
            && n != Vec3::ZERO
        {
            // The coat's map is read in the same tangent frame as the base's: both
            // perturb the interpolated vertex normal.
            let coat_map = m
                .clearcoat
                .filter(|c| c.factor > 0.0 && effects.contains(Effect::Clearcoat))
                .and_then(|c| Some((c.normal_tex?, c.normal_scale)));
            let base_map = m.normal_tex.map(|t| (t, m.normal_scale));
            if base_map.is_some() || coat_map.is_some() {
                let ts = idx.map(|i| mesh.tangents[i as usize]);
                let t4 = ts[0] * bary[0] + ts[1] * bary[1] + ts[2] * bary[2];
                let t = (t4.truncate() - n * n.dot(t4.truncate())).normalize_or_zero();
                if t != Vec3::ZERO {
                    let sign = if ts[0].w < 0.0 { -1.0 } else { 1.0 };
                    let bt = n.cross(t) * sign;
                    let n0 = n;
                    let apply = |(map, scale): (TexRef, f32)| {
                        let s = tex(scene, Some(map), uv, false);
                        let k = Vec3::new(
                            (s.x * 2.0 - 1.0) * scale,
                            (s.y * 2.0 - 1.0) * scale,
                            s.z * 2.0 - 1.0,
                        );
                        (t * k.x + bt * k.y + n0 * k.z).normalize_or_zero()
                    };
                    if let Some(map) = coat_map {
                        coat_n = apply(map);
                    }
                    if let Some(map) = base_map {
                        let mapped = apply(map);
                        if mapped != Vec3::ZERO {
                            n = mapped;
                        }
                    }
                }
            }
        }
        if coat_n.dot(ng) < 0.0 {
            coat_n = -coat_n;
        }
        let (tangent, bitangent) = match scene.materials.get(material as usize) {
            Some(m) if m.has_anisotropy() && effects.contains(Effect::Anisotropy) => {
                tangent_frame(scene, idx, bary, if n == Vec3::ZERO { ng } else { n })
            }
            _ => (Vec3::ZERO, Vec3::ZERO),
        };
        if n == Vec3::ZERO {
            n = ng;
        } else if n.dot(ng) < 0.0 {
            n = -n;
        }
        Surface {
            p,
            p_err,
            ng,
            n,
            coat_n,
            uv,
            color,
            tangent,
            bitangent,
            front,
            tri: hit.tri,
            material,
        }
    }

    /// Evaluate the material at this point. Effects switched off are removed here, so
    /// no integrator can spawn their rays.
    pub fn shading(&self, scene: &Scene, effects: Effects) -> ShadingValues {
        // The glTF default stands in for a missing material; it is built only then (its
        // name is a `String`: building it for every hit cost an allocation per hit).
        let fallback;
        let m = match scene.materials.get(self.material as usize) {
            Some(m) => m,
            None => {
                fallback = Material::default();
                &fallback
            }
        };
        let textured = effects.contains(Effect::Textures);
        // A slot's texture value, `None` when the slot is empty or textures are off. A
        // factor times an absent texture's white (1) is the factor itself, exactly, so
        // empty slots take the factor as it is: no lookup and no product per slot.
        let lookup = |r: Option<TexRef>, srgb: bool| {
            r.filter(|_| textured)
                .map(|r| tex(scene, Some(r), self.uv, srgb))
        };
        let t = |r: Option<TexRef>, srgb: bool| lookup(r, srgb).unwrap_or(Vec4::ONE);
        // glTF: base colour = factor x texture x COLOR_0 (white without vertex colours,
        // and x * 1 is exact, so such scenes keep their bits).
        let bc =
            lookup(m.base_color_tex, true).map_or(m.base_color, |s| m.base_color * s) * self.color;
        let (metallic, roughness) = lookup(m.metallic_roughness_tex, false)
            .map_or((m.metallic, m.roughness), |s| {
                (m.metallic * s.z, m.roughness * s.y)
            });
        let mut v = ShadingValues {
            base_color: bc.truncate().max(Vec3::ZERO),
            alpha: bc.w,
            metallic: metallic.clamp(0.0, 1.0),
            roughness: roughness.clamp(0.0, 1.0),
            specular: lookup(m.specular_tex, false)
                .map_or(m.specular, |s| m.specular * s.w)
                .clamp(0.0, 1.0),
            specular_color: lookup(m.specular_color_tex, true)
                .map_or(m.specular_color, |s| m.specular_color * s.truncate())
                .max(Vec3::ZERO),
            transmission: lookup(m.transmission_tex, false)
                .map_or(m.transmission, |s| m.transmission * s.x)
                .clamp(0.0, 1.0),
            ior: if m.ior.is_finite() && m.ior >= 1.0 {
                m.ior
            } else {
                1.5
            },
            emission: lookup(m.emissive_tex, true)
                .map_or(m.emissive, |s| m.emissive * s.truncate())
                .max(Vec3::ZERO),
            clearcoat: 0.0,
            clearcoat_roughness: 0.0,
            sheen_color: Vec3::ZERO,
            sheen_roughness: 0.0,
            anisotropy: 0.0,
            anisotropy_direction: Vec3::ZERO,
            iridescence: 0.0,
            iridescence_ior: crate::iridescence::DEFAULT_IOR,
            iridescence_thickness: 0.0,
            dispersion: 0.0,
        };
        self.extension_layers(m, effects, &t, &mut v);
        switch_off(&mut v, m, self.front, effects);
        v
    }

    /// The glTF extensions' layers the job's effects keep (anisotropy, clear coat, sheen,
    /// iridescence, dispersion), written into `v`; `t` looks a texture up (white with
    /// textures off).
    fn extension_layers(
        &self,
        m: &Material,
        effects: Effects,
        t: &impl Fn(Option<TexRef>, bool) -> Vec4,
        v: &mut ShadingValues,
    ) {
        let textured = effects.contains(Effect::Textures);
        if let Some(a) = m.anisotropy
            && effects.contains(Effect::Anisotropy)
            && self.tangent != Vec3::ZERO
        {
            // RG of the texture is the direction in tangent space (default: the
            // tangent), turned by the rotation; B multiplies the strength.
            let tx = t(a.tex, false);
            let dir = match a.tex {
                Some(_) if textured => Vec2::new(tx.x * 2.0 - 1.0, tx.y * 2.0 - 1.0),
                _ => Vec2::X,
            };
            let (s, c) = a.rotation.sin_cos();
            let d = Vec2::new(c * dir.x - s * dir.y, s * dir.x + c * dir.y);
            v.anisotropy = (a.strength * tx.z).clamp(0.0, 1.0);
            v.anisotropy_direction = self.tangent * d.x + self.bitangent * d.y;
        }
        if let Some(c) = m.clearcoat
            && effects.contains(Effect::Clearcoat)
        {
            v.clearcoat = (c.factor * t(c.tex, false).x).clamp(0.0, 1.0);
            v.clearcoat_roughness = (c.roughness * t(c.roughness_tex, false).y).clamp(0.0, 1.0);
        }
        if let Some(sh) = m.sheen
            && effects.contains(Effect::Sheen)
        {
            v.sheen_color =
                (sh.color * t(sh.color_tex, true).truncate()).clamp(Vec3::ZERO, Vec3::ONE);
            v.sheen_roughness = (sh.roughness * t(sh.roughness_tex, false).w).clamp(0.0, 1.0);
        }
        if let Some(ir) = m.iridescence
            && effects.contains(Effect::Iridescence)
        {
            v.iridescence = (ir.factor * t(ir.tex, false).x).clamp(0.0, 1.0);
            v.iridescence_ior = ir.ior;
            // Without a thickness texture the film is `thickness_max` thick.
            v.iridescence_thickness = match ir.thickness_tex {
                Some(_) if textured => {
                    let g = t(ir.thickness_tex, false).y;
                    ir.thickness_min + (ir.thickness_max - ir.thickness_min) * g
                }
                _ => ir.thickness_max,
            };
        }

        if m.has_dispersion() && effects.contains(Effect::Dispersion) {
            v.dispersion = m.dispersion;
        }
    }
}

/// Takes out of `v` what the material or the job switches off: emission from the back of
/// a single-sided surface, and each effect the job leaves out; an unlit material
/// (`KHR_materials_unlit`) shows its base colour as emission over a lobeless BSDF.
fn switch_off(v: &mut ShadingValues, m: &Material, front: bool, effects: Effects) {
    if !m.double_sided && !front {
        // Back faces of single-sided surfaces do not emit.
        v.emission = Vec3::ZERO;
    }
    if !effects.contains(Effect::Emission) {
        v.emission = Vec3::ZERO;
    }
    if !effects.contains(Effect::Specular) {
        v.metallic = 0.0;
        v.specular = 0.0;
    }
    if !effects.contains(Effect::Transmission) {
        v.transmission = 0.0;
        v.dispersion = 0.0;
    }
    if m.unlit && effects.contains(Effect::Unlit) {
        // The base colour is what the eye (or a bounce) sees, unlit and lighting
        // nothing: shown as emission over a black, lobeless BSDF, so every
        // integrator shows it and none spawns a ray from it. Unlit triangles are
        // not in the light sampler, so a bounce that finds one weighs it fully.
        v.emission = v.base_color;
        v.base_color = Vec3::ZERO;
        v.metallic = 0.0;
        v.specular = 0.0;
        v.transmission = 0.0;
        v.clearcoat = 0.0;
        v.sheen_color = Vec3::ZERO;
        v.iridescence = 0.0;
        v.dispersion = 0.0;
    }
}

/// The tangent frame at barycentrics `b` of the triangle with vertices `idx`, made
/// orthonormal to the shading normal `n`; zero when the mesh has no tangent there.
fn tangent_frame(scene: &Scene, idx: [u32; 3], b: [f32; 3], n: Vec3) -> (Vec3, Vec3) {
    let ts = idx.map(|i| {
        scene
            .mesh
            .tangents
            .get(i as usize)
            .copied()
            .unwrap_or(Vec4::ZERO)
    });
    let t4 = ts[0] * b[0] + ts[1] * b[1] + ts[2] * b[2];
    let t = (t4.truncate() - n * n.dot(t4.truncate())).normalize_or_zero();
    if t == Vec3::ZERO {
        return (Vec3::ZERO, Vec3::ZERO);
    }
    let sign = if ts[0].w < 0.0 { -1.0 } else { 1.0 };
    (t, n.cross(t) * sign)
}

/// Whether a hit on triangle `tri` at barycentrics `b` is a real surface, given its
/// material's alpha mode. `u` is the stochastic-alpha random number for blended
/// materials.
pub fn alpha_passes(scene: &Scene, tri: u32, b: [f32; 3], u: f32) -> bool {
    let Some(m) = scene
        .mesh
        .material
        .get(tri as usize)
        .and_then(|&i| scene.materials.get(i as usize))
    else {
        return true;
    };
    let alpha = || {
        let uv = interpolate_uv(scene, tri, b);
        alpha_at(scene, m, uv, interpolate_color(scene, tri, b).w)
    };
    match m.alpha_mode {
        AlphaMode::Opaque => true,
        AlphaMode::Mask { cutoff } => alpha() >= cutoff,
        AlphaMode::Blend => u < alpha(),
    }
}

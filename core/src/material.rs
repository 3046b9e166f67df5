//! Materials: the glTF 2.0 metallic-roughness model and the extensions dray supports.
//!
//! Factors are stored as glTF gives them; textures multiply them at shading time.
//! Emission is stored already multiplied by `KHR_materials_emissive_strength`.
//!
//! These types are also what a scene package's manifest stores, through serde: the
//! field attributes (and [`crate::material_serde`]) keep the JSON what it has always
//! been, so read that module before adding a field.

use glam::{Affine2, Vec2, Vec3, Vec4};
use serde::{Deserialize, Serialize};

use crate::material_serde::{affine2_opt, is_one, is_zero, one, real, vec3, vec4};

/// The texture coordinates of a surface point: the mesh's first UV set
/// ([`crate::scene::Mesh::uvs`]) and its second ([`crate::scene::Mesh::uvs2`], zero when
/// the mesh has none). Each [`TexRef`] says which of the two it reads.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct TexCoords {
    pub first: Vec2,
    pub second: Vec2,
}

impl TexCoords {
    /// Coordinates with only a first set (the second zero, as a mesh without one reads).
    pub fn first(uv: Vec2) -> TexCoords {
        TexCoords {
            first: uv,
            second: Vec2::ZERO,
        }
    }
}

/// A reference from a material slot to a texture in [`crate::scene::Scene::textures`].
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct TexRef {
    /// Index into `Scene::textures`.
    pub texture: u32,
    /// Which UV set of the source file the texture reads (`TEXCOORD_n`), for messages
    /// and tests: shading reads [`TexRef::second_uv`]. A slot that named a third set of
    /// its material holds the first set's here, as that is what it reads.
    pub tex_coord: u32,
    /// Whether the texture reads the mesh's second UV set ([`crate::scene::Mesh::uvs2`])
    /// rather than its first ([`crate::scene::Mesh::uvs`]). A mesh keeps per triangle the
    /// set its material reads first and, only for materials whose slots name two sets,
    /// the other one (docs/gltf.md, "Texture coordinates").
    ///
    /// Written only when true (package format version 3), so manifests of scenes whose
    /// materials read one UV set each are what they were.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub second_uv: bool,
    /// `KHR_texture_transform`: the affine map from the mesh's UV to the texture's UV
    /// (offset, rotation and scale composed), `None` for the identity. Kept as `None`
    /// rather than an identity matrix so untransformed lookups keep their bits.
    /// Written as the map's columns, and left out when there is none, so manifests of
    /// scenes without transforms are unchanged.
    #[serde(default, skip_serializing_if = "Option::is_none", with = "affine2_opt")]
    pub transform: Option<Affine2>,
}

impl TexRef {
    /// A reference to `texture` through UV set 0, untransformed.
    pub fn new(texture: u32) -> TexRef {
        TexRef {
            texture,
            tex_coord: 0,
            second_uv: false,
            transform: None,
        }
    }

    /// The texture-space coordinate at a point with mesh coordinates `at`: the set this
    /// reference reads, transformed.
    #[inline]
    pub fn uv(&self, at: TexCoords) -> Vec2 {
        let uv = if self.second_uv { at.second } else { at.first };
        match &self.transform {
            Some(t) => t.transform_point2(uv),
            None => uv,
        }
    }
}

/// `KHR_materials_clearcoat`: a clear dielectric coat (ior 1.5, GGX) over the material.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Clearcoat {
    /// Coat strength in [0, 1] (texture R multiplies it).
    #[serde(with = "real")]
    pub factor: f32,
    pub tex: Option<TexRef>,
    /// Coat perceptual roughness (texture G multiplies it).
    #[serde(with = "real")]
    pub roughness: f32,
    pub roughness_tex: Option<TexRef>,
    /// `clearcoatNormalTexture`: the coat's own normal map, read in the same tangent
    /// frame as the material's normal map, its XY scaled by `normal_scale`. Both left
    /// out of a manifest without a map (older manifests keep their bytes).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub normal_tex: Option<TexRef>,
    #[serde(default = "one", skip_serializing_if = "is_one", with = "real")]
    pub normal_scale: f32,
}

/// `KHR_materials_sheen`: a velvet-like layer of fibres (the Charlie distribution)
/// over the material, below a clear coat.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Sheen {
    /// Linear sheen colour (texture RGB, sRGB, multiplies it).
    #[serde(with = "vec3")]
    pub color: Vec3,
    pub color_tex: Option<TexRef>,
    /// Sheen perceptual roughness (texture A multiplies it).
    #[serde(with = "real")]
    pub roughness: f32,
    pub roughness_tex: Option<TexRef>,
}

/// `KHR_materials_anisotropy`: the specular lobe stretched along a direction in the
/// tangent plane (brushed metal).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Anisotropy {
    /// In [0, 1] (texture B multiplies it).
    #[serde(with = "real")]
    pub strength: f32,
    /// Radians, counter-clockwise from the tangent, applied to the direction.
    #[serde(with = "real")]
    pub rotation: f32,
    /// RG: the direction in tangent space in [-1, 1]; B: strength.
    pub tex: Option<TexRef>,
}

/// `KHR_materials_iridescence`: a thin dielectric film over the material whose
/// interference colours its specular reflection (soap bubbles, oil, beetles).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Iridescence {
    /// Strength in [0, 1] mixing the film's Fresnel term in (texture R multiplies it).
    #[serde(with = "real")]
    pub factor: f32,
    pub tex: Option<TexRef>,
    /// Refraction index of the film.
    #[serde(with = "real")]
    pub ior: f32,
    /// Film thickness in nanometres: `thickness_max` without a texture, else
    /// `mix(thickness_min, thickness_max, texture G)`.
    #[serde(with = "real")]
    pub thickness_min: f32,
    #[serde(with = "real")]
    pub thickness_max: f32,
    pub thickness_tex: Option<TexRef>,
}

/// `KHR_materials_volume`: the medium inside a transmissive object, attenuating light
/// by Beer-Lambert over the distance travelled inside.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Volume {
    /// Linear colour white light becomes after `attenuation_distance` in the medium.
    #[serde(with = "vec3")]
    pub attenuation_color: Vec3,
    /// Distance at which white light has become `attenuation_color` (infinite: clear).
    #[serde(with = "real")]
    pub attenuation_distance: f32,
}

impl Volume {
    /// Per-channel attenuation coefficient `-ln(color) / distance` (0 for a clear
    /// medium, infinite for a black channel).
    pub fn sigma(&self) -> Vec3 {
        let d = self.attenuation_distance;
        if d.is_nan() || d <= 0.0 || d.is_infinite() {
            return Vec3::ZERO;
        }
        let c = self.attenuation_color.clamp(Vec3::ZERO, Vec3::ONE);
        Vec3::new(-c.x.ln(), -c.y.ln(), -c.z.ln()) / d
    }

    /// Transmittance over `distance` inside the medium.
    pub fn transmittance(&self, distance: f32) -> Vec3 {
        let s = self.sigma() * distance.max(0.0);
        Vec3::new((-s.x).exp(), (-s.y).exp(), (-s.z).exp())
    }

    /// True when the medium absorbs anything.
    pub fn absorbs(&self) -> bool {
        self.sigma().max_element() > 0.0
    }
}

/// How alpha is interpreted (glTF `alphaMode`). In a manifest, an object tagged by
/// `mode` (`{"mode":"mask","cutoff":0.5}`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "mode", rename_all = "snake_case")]
pub enum AlphaMode {
    Opaque,
    /// Cut-out: the surface exists where alpha >= cutoff.
    Mask {
        #[serde(with = "real")]
        cutoff: f32,
    },
    /// Blend is rendered as stochastic transparency: a hit is kept with probability alpha,
    /// decided by a hash of (pixel, sample, triangle), so the image converges to the
    /// blended look and stays deterministic.
    Blend,
}

/// A glTF PBR metallic-roughness material.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Material {
    pub name: String,
    /// Linear RGBA base colour factor.
    #[serde(with = "vec4")]
    pub base_color: Vec4,
    pub base_color_tex: Option<TexRef>,
    #[serde(with = "real")]
    pub metallic: f32,
    #[serde(with = "real")]
    pub roughness: f32,
    /// Roughness in G, metallic in B (glTF packing).
    pub metallic_roughness_tex: Option<TexRef>,
    pub normal_tex: Option<TexRef>,
    #[serde(with = "real")]
    pub normal_scale: f32,
    /// Linear emitted radiance factor, already multiplied by emissive strength.
    #[serde(with = "vec3")]
    pub emissive: Vec3,
    pub emissive_tex: Option<TexRef>,
    /// `KHR_materials_transmission` factor (0 = opaque).
    #[serde(with = "real")]
    pub transmission: f32,
    pub transmission_tex: Option<TexRef>,
    /// `KHR_materials_ior` (default 1.5).
    #[serde(with = "real")]
    pub ior: f32,
    /// `KHR_materials_specular` factor (default 1; 0 gives pure Lambert for dielectrics).
    #[serde(with = "real")]
    pub specular: f32,
    pub specular_tex: Option<TexRef>,
    /// `KHR_materials_specular` colour factor (linear).
    #[serde(with = "vec3")]
    pub specular_color: Vec3,
    pub specular_color_tex: Option<TexRef>,
    pub alpha_mode: AlphaMode,
    pub double_sided: bool,
    // The glTF extensions below are left out of a manifest when absent, so manifests
    // of scenes without them keep their bytes (and their checksums), and manifests
    // written before them load.
    /// `KHR_materials_unlit`: the surface shows its base colour as is, lit by nothing
    /// and lighting nothing.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub unlit: bool,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub clearcoat: Option<Clearcoat>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sheen: Option<Sheen>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub anisotropy: Option<Anisotropy>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub volume: Option<Volume>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub iridescence: Option<Iridescence>,
    /// `KHR_materials_dispersion`: 20 / Abbe number (0: the index is the same for every
    /// wavelength). Only transmission shows it.
    #[serde(default, skip_serializing_if = "is_zero", with = "real")]
    pub dispersion: f32,
}

impl Default for Material {
    /// The glTF default material: white, fully metallic, fully rough.
    fn default() -> Self {
        Material {
            name: "default".to_string(),
            base_color: Vec4::ONE,
            base_color_tex: None,
            metallic: 1.0,
            roughness: 1.0,
            metallic_roughness_tex: None,
            normal_tex: None,
            normal_scale: 1.0,
            emissive: Vec3::ZERO,
            emissive_tex: None,
            transmission: 0.0,
            transmission_tex: None,
            ior: 1.5,
            specular: 1.0,
            specular_tex: None,
            specular_color: Vec3::ONE,
            specular_color_tex: None,
            alpha_mode: AlphaMode::Opaque,
            double_sided: false,
            unlit: false,
            clearcoat: None,
            sheen: None,
            anisotropy: None,
            volume: None,
            iridescence: None,
            dispersion: 0.0,
        }
    }
}

impl Material {
    /// A pure Lambertian diffuse material (no specular lobe), used by procedural scenes
    /// and by the Mitsuba comparison.
    pub fn lambert(name: &str, albedo: Vec3) -> Material {
        Material {
            name: name.to_string(),
            base_color: albedo.extend(1.0),
            metallic: 0.0,
            roughness: 1.0,
            specular: 0.0,
            double_sided: true,
            ..Material::default()
        }
    }

    /// An emitter with a black Lambert base.
    pub fn emitter(name: &str, radiance: Vec3) -> Material {
        Material {
            emissive: radiance,
            ..Material::lambert(name, Vec3::ZERO)
        }
    }

    /// A dielectric (glass) with the given IOR.
    pub fn glass(name: &str, ior: f32) -> Material {
        Material {
            name: name.to_string(),
            base_color: Vec4::ONE,
            metallic: 0.0,
            roughness: 0.0,
            transmission: 1.0,
            ior,
            double_sided: true,
            ..Material::default()
        }
    }

    /// A metal with the given colour and roughness (0 = perfect mirror).
    pub fn metal(name: &str, color: Vec3, roughness: f32) -> Material {
        Material {
            name: name.to_string(),
            base_color: color.extend(1.0),
            metallic: 1.0,
            roughness,
            double_sided: true,
            ..Material::default()
        }
    }

    /// True when the material can reflect specularly anywhere on its surface.
    pub fn has_specular(&self) -> bool {
        let metal = self.metallic > 0.0 || self.metallic_roughness_tex.is_some();
        let dielectric_spec = self.metallic < 1.0
            && (self.specular > 0.0 || self.specular_tex.is_some())
            && self.specular_color.max_element() > 0.0;
        metal || dielectric_spec || self.has_transmission()
    }

    pub fn has_transmission(&self) -> bool {
        self.transmission > 0.0
    }

    /// Unlit materials do not emit: they show their base colour to whoever looks, but
    /// are not light sources (what a rasteriser's unlit material does).
    pub fn has_emission(&self) -> bool {
        !self.unlit && self.emissive.max_element() > 0.0
    }

    pub fn has_textures(&self) -> bool {
        self.texture_refs().next().is_some()
    }

    pub fn has_alpha(&self) -> bool {
        !matches!(self.alpha_mode, AlphaMode::Opaque)
    }

    pub fn has_clearcoat(&self) -> bool {
        !self.unlit && self.clearcoat.is_some_and(|c| c.factor > 0.0)
    }

    pub fn has_sheen(&self) -> bool {
        !self.unlit && self.sheen.is_some_and(|s| s.color.max_element() > 0.0)
    }

    pub fn has_anisotropy(&self) -> bool {
        !self.unlit && self.anisotropy.is_some_and(|a| a.strength > 0.0)
    }

    pub fn has_iridescence(&self) -> bool {
        !self.unlit && self.iridescence.is_some_and(|i| i.factor > 0.0)
    }

    /// A transmissive material whose index depends on the wavelength.
    pub fn has_dispersion(&self) -> bool {
        !self.unlit && self.has_transmission() && self.dispersion > 0.0
    }

    /// A transmissive material whose inside absorbs.
    pub fn has_volume(&self) -> bool {
        !self.unlit && self.has_transmission() && self.volume.is_some_and(|v| v.absorbs())
    }

    /// Every texture slot in use, for validation and effect analysis.
    pub fn texture_refs(&self) -> impl Iterator<Item = TexRef> + '_ {
        [
            self.base_color_tex,
            self.metallic_roughness_tex,
            self.normal_tex,
            self.emissive_tex,
            self.transmission_tex,
            self.specular_tex,
            self.specular_color_tex,
            self.clearcoat.and_then(|c| c.tex),
            self.clearcoat.and_then(|c| c.roughness_tex),
            self.clearcoat.and_then(|c| c.normal_tex),
            self.sheen.and_then(|s| s.color_tex),
            self.sheen.and_then(|s| s.roughness_tex),
            self.anisotropy.and_then(|a| a.tex),
            self.iridescence.and_then(|i| i.tex),
            self.iridescence.and_then(|i| i.thickness_tex),
        ]
        .into_iter()
        .flatten()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A reference reads the set it is marked with, and its transform applies to that.
    #[test]
    fn a_reference_reads_its_own_set() {
        let at = TexCoords {
            first: Vec2::new(0.25, 0.5),
            second: Vec2::new(0.75, 0.125),
        };
        let first = TexRef::new(0);
        let second = TexRef {
            tex_coord: 1,
            second_uv: true,
            ..TexRef::new(0)
        };
        assert_eq!(first.uv(at), at.first);
        assert_eq!(second.uv(at), at.second);
        let moved = TexRef {
            transform: Some(Affine2::from_translation(Vec2::new(1.0, 2.0))),
            ..second
        };
        assert_eq!(moved.uv(at), Vec2::new(1.75, 2.125));
    }
}

//! Materials: the glTF 2.0 metallic-roughness model and the extensions dray supports.
//!
//! Factors are stored as glTF gives them; textures multiply them at shading time.
//! Emission is stored already multiplied by `KHR_materials_emissive_strength`.

use glam::{Vec3, Vec4};

/// A reference from a material slot to a texture in [`crate::scene::Scene::textures`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TexRef {
    /// Index into `Scene::textures`.
    pub texture: u32,
    /// Which UV set the texture reads. dray keeps one UV set per vertex (`TEXCOORD_0`);
    /// loaders warn when a texture asks for another.
    pub tex_coord: u32,
}

/// How alpha is interpreted (glTF `alphaMode`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum AlphaMode {
    Opaque,
    /// Cut-out: the surface exists where alpha >= cutoff.
    Mask {
        cutoff: f32,
    },
    /// Blend is rendered as stochastic transparency: a hit is kept with probability alpha,
    /// decided by a hash of (pixel, sample, triangle), so the image converges to the
    /// blended look and stays deterministic.
    Blend,
}

/// A glTF PBR metallic-roughness material.
#[derive(Clone, Debug, PartialEq)]
pub struct Material {
    pub name: String,
    /// Linear RGBA base colour factor.
    pub base_color: Vec4,
    pub base_color_tex: Option<TexRef>,
    pub metallic: f32,
    pub roughness: f32,
    /// Roughness in G, metallic in B (glTF packing).
    pub metallic_roughness_tex: Option<TexRef>,
    pub normal_tex: Option<TexRef>,
    pub normal_scale: f32,
    /// Linear emitted radiance factor, already multiplied by emissive strength.
    pub emissive: Vec3,
    pub emissive_tex: Option<TexRef>,
    /// `KHR_materials_transmission` factor (0 = opaque).
    pub transmission: f32,
    pub transmission_tex: Option<TexRef>,
    /// `KHR_materials_ior` (default 1.5).
    pub ior: f32,
    /// `KHR_materials_specular` factor (default 1; 0 gives pure Lambert for dielectrics).
    pub specular: f32,
    pub specular_tex: Option<TexRef>,
    /// `KHR_materials_specular` colour factor (linear).
    pub specular_color: Vec3,
    pub specular_color_tex: Option<TexRef>,
    pub alpha_mode: AlphaMode,
    pub double_sided: bool,
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

    pub fn has_emission(&self) -> bool {
        self.emissive.max_element() > 0.0
    }

    pub fn has_textures(&self) -> bool {
        self.texture_refs().next().is_some()
    }

    pub fn has_alpha(&self) -> bool {
        !matches!(self.alpha_mode, AlphaMode::Opaque)
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
        ]
        .into_iter()
        .flatten()
    }
}

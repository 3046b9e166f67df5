//! [`BsdfParams`]: the shading inputs of the BSDF at one point, as glTF and its extensions
//! name them, before [`super::Bsdf::new`] sanitises them into its lobes.

use glam::Vec3;

use crate::material::Material;

/// Shading inputs of the BSDF at one point (factors already multiplied by textures).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BsdfParams {
    /// Linear base colour (albedo for dielectrics, F0 for metals, transmission tint).
    pub base_color: Vec3,
    pub metallic: f32,
    /// Perceptual roughness; GGX alpha is its square.
    pub roughness: f32,
    /// `KHR_materials_specular` factor: scales the dielectric specular lobe (F90).
    pub specular: f32,
    /// `KHR_materials_specular` colour: tints the dielectric F0.
    pub specular_color: Vec3,
    /// `KHR_materials_transmission` factor.
    pub transmission: f32,
    /// `KHR_materials_ior`.
    pub ior: f32,
    /// `KHR_materials_clearcoat` factor (0: no coat) and perceptual roughness.
    pub clearcoat: f32,
    pub clearcoat_roughness: f32,
    /// The coat's own shading normal (`clearcoatNormalTexture`), zero when it has none
    /// (it then uses the shading normal `n`).
    pub clearcoat_normal: Vec3,
    /// `KHR_materials_sheen` colour (black: no sheen) and roughness.
    pub sheen_color: Vec3,
    pub sheen_roughness: f32,
    /// `KHR_materials_anisotropy` strength (0: isotropic) and its direction in world
    /// space (the GGX lobe is stretched along it: `alpha_t = mix(alpha, 1, strength^2)`).
    pub anisotropy: f32,
    pub anisotropy_direction: Vec3,
    /// `KHR_materials_iridescence` strength (0: no film), the film's refraction index
    /// and its thickness in nanometres (0: no film).
    pub iridescence: f32,
    pub iridescence_ior: f32,
    pub iridescence_thickness: f32,
}

impl Default for BsdfParams {
    /// glTF defaults: white, fully metallic, fully rough, specular 1, ior 1.5.
    fn default() -> Self {
        BsdfParams {
            base_color: Vec3::ONE,
            metallic: 1.0,
            roughness: 1.0,
            specular: 1.0,
            specular_color: Vec3::ONE,
            transmission: 0.0,
            ior: 1.5,
            clearcoat: 0.0,
            clearcoat_roughness: 0.0,
            clearcoat_normal: Vec3::ZERO,
            sheen_color: Vec3::ZERO,
            sheen_roughness: 0.0,
            anisotropy: 0.0,
            anisotropy_direction: Vec3::ZERO,
            iridescence: 0.0,
            iridescence_ior: crate::iridescence::DEFAULT_IOR,
            iridescence_thickness: 0.0,
        }
    }
}

impl BsdfParams {
    /// The material's factors, ignoring textures (callers with UVs multiply textures in).
    pub fn from_material(m: &Material) -> BsdfParams {
        BsdfParams {
            base_color: m.base_color.truncate(),
            metallic: m.metallic,
            roughness: m.roughness,
            specular: m.specular,
            specular_color: m.specular_color,
            transmission: m.transmission,
            ior: m.ior,
            clearcoat: m.clearcoat.map_or(0.0, |c| c.factor),
            clearcoat_roughness: m.clearcoat.map_or(0.0, |c| c.roughness),
            // The coat's normal map needs the surface's tangent frame too.
            clearcoat_normal: Vec3::ZERO,
            sheen_color: m.sheen.map_or(Vec3::ZERO, |s| s.color),
            sheen_roughness: m.sheen.map_or(0.0, |s| s.roughness),
            // The direction needs the surface's tangent frame ([`crate::surface`]).
            anisotropy: 0.0,
            anisotropy_direction: Vec3::ZERO,
            iridescence: m.iridescence.map_or(0.0, |i| i.factor),
            iridescence_ior: m
                .iridescence
                .map_or(crate::iridescence::DEFAULT_IOR, |i| i.ior),
            iridescence_thickness: m.iridescence.map_or(0.0, |i| i.thickness_max),
        }
    }
}

//! The parts of glTF extensions the `gltf` crate does not type for dray: texture
//! transforms on any texture slot, and the material extensions it does not know
//! (`KHR_materials_clearcoat`, `KHR_materials_sheen`, `KHR_materials_anisotropy`,
//! `KHR_materials_iridescence`, `KHR_materials_dispersion`), read from their JSON.
//!
//! Values are taken as the extensions' schemas give them, with their defaults; a value
//! of the wrong JSON type counts as absent (the default), as the crate treats the
//! extensions it does know. Range checks are left to shading, which clamps.

use glam::{Affine2, Vec2, Vec3};
use serde_json::Value;

/// A texture slot read from JSON: texture index, UV set and transform.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SlotJson {
    pub index: usize,
    pub tex_coord: u32,
    pub transform: Option<TextureTransform>,
}

/// `KHR_texture_transform` on one texture slot.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TextureTransform {
    pub offset: [f32; 2],
    pub rotation: f32,
    pub scale: [f32; 2],
    /// Overrides the slot's `texCoord` when given.
    pub tex_coord: Option<u32>,
}

impl TextureTransform {
    /// The UV map `translation * rotation * scale` of the extension. Its rotation turns
    /// UVs by `rotation` radians counter-clockwise in the image, whose V axis points down:
    /// `u' = cos u + sin v`, `v' = -sin u + cos v` (the extension's example, which uses
    /// the lower-left quadrant turned clockwise, checks the sign). `None` when the
    /// transform is the identity (so the lookup keeps its bits) or not finite.
    pub fn affine(&self) -> Option<Affine2> {
        let finite = self.offset.iter().chain(&self.scale).all(|x| x.is_finite())
            && self.rotation.is_finite();
        if !finite {
            return None;
        }
        let identity =
            self.offset == [0.0, 0.0] && self.rotation == 0.0 && self.scale == [1.0, 1.0];
        if identity {
            return None;
        }
        Some(Affine2::from_scale_angle_translation(
            Vec2::from(self.scale),
            -self.rotation,
            Vec2::from(self.offset),
        ))
    }

    /// True when some value is not finite (the transform is then ignored, with a warning).
    pub fn is_malformed(&self) -> bool {
        !(self.offset.iter().chain(&self.scale).all(|x| x.is_finite()) && self.rotation.is_finite())
    }

    /// The transform in a slot's `extensions` object, if any.
    pub fn from_extensions(extensions: Option<&serde_json::Map<String, Value>>) -> Option<Self> {
        let t = extensions?.get("KHR_texture_transform")?;
        Some(TextureTransform {
            offset: vec2(t.get("offset")).unwrap_or([0.0, 0.0]),
            rotation: number(t.get("rotation")).unwrap_or(0.0),
            scale: vec2(t.get("scale")).unwrap_or([1.0, 1.0]),
            tex_coord: t
                .get("texCoord")
                .and_then(Value::as_u64)
                .and_then(|v| u32::try_from(v).ok()),
        })
    }
}

/// A `textureInfo` object: `{"index": i, "texCoord": k, "extensions": {...}}`.
pub fn slot(v: Option<&Value>) -> Option<SlotJson> {
    let v = v?;
    let index = usize::try_from(v.get("index")?.as_u64()?).ok()?;
    let tex_coord = v
        .get("texCoord")
        .and_then(Value::as_u64)
        .and_then(|k| u32::try_from(k).ok())
        .unwrap_or(0);
    let transform =
        TextureTransform::from_extensions(v.get("extensions").and_then(Value::as_object));
    Some(SlotJson {
        index,
        tex_coord,
        transform,
    })
}

/// `KHR_materials_clearcoat` as written in a material's extensions.
#[derive(Clone, Debug, PartialEq)]
pub struct ClearcoatJson {
    pub factor: f32,
    pub texture: Option<SlotJson>,
    pub roughness: f32,
    pub roughness_texture: Option<SlotJson>,
    pub normal_texture: Option<SlotJson>,
    /// `clearcoatNormalTexture.scale`.
    pub normal_scale: f32,
}

pub fn clearcoat(v: &Value) -> ClearcoatJson {
    ClearcoatJson {
        factor: number(v.get("clearcoatFactor")).unwrap_or(0.0),
        texture: slot(v.get("clearcoatTexture")),
        roughness: number(v.get("clearcoatRoughnessFactor")).unwrap_or(0.0),
        roughness_texture: slot(v.get("clearcoatRoughnessTexture")),
        normal_texture: slot(v.get("clearcoatNormalTexture")),
        normal_scale: v
            .get("clearcoatNormalTexture")
            .and_then(|t| number(t.get("scale")))
            .unwrap_or(1.0),
    }
}

/// `KHR_materials_sheen` as written in a material's extensions.
#[derive(Clone, Debug, PartialEq)]
pub struct SheenJson {
    pub color: Vec3,
    pub color_texture: Option<SlotJson>,
    pub roughness: f32,
    pub roughness_texture: Option<SlotJson>,
}

pub fn sheen(v: &Value) -> SheenJson {
    SheenJson {
        color: vec3(v.get("sheenColorFactor")).map_or(Vec3::ZERO, Vec3::from),
        color_texture: slot(v.get("sheenColorTexture")),
        roughness: number(v.get("sheenRoughnessFactor")).unwrap_or(0.0),
        roughness_texture: slot(v.get("sheenRoughnessTexture")),
    }
}

/// `KHR_materials_anisotropy` as written in a material's extensions.
#[derive(Clone, Debug, PartialEq)]
pub struct AnisotropyJson {
    pub strength: f32,
    pub rotation: f32,
    pub texture: Option<SlotJson>,
}

pub fn anisotropy(v: &Value) -> AnisotropyJson {
    AnisotropyJson {
        strength: number(v.get("anisotropyStrength")).unwrap_or(0.0),
        rotation: number(v.get("anisotropyRotation")).unwrap_or(0.0),
        texture: slot(v.get("anisotropyTexture")),
    }
}

/// `KHR_materials_iridescence` as written in a material's extensions.
#[derive(Clone, Debug, PartialEq)]
pub struct IridescenceJson {
    pub factor: f32,
    pub texture: Option<SlotJson>,
    pub ior: f32,
    pub thickness_min: f32,
    pub thickness_max: f32,
    pub thickness_texture: Option<SlotJson>,
}

pub fn iridescence(v: &Value) -> IridescenceJson {
    IridescenceJson {
        factor: number(v.get("iridescenceFactor")).unwrap_or(0.0),
        texture: slot(v.get("iridescenceTexture")),
        // The ratified schema spells it `iridescenceIor`; drafts wrote `iridescenceIOR`.
        ior: number(v.get("iridescenceIor"))
            .or_else(|| number(v.get("iridescenceIOR")))
            .unwrap_or(1.3),
        thickness_min: number(v.get("iridescenceThicknessMinimum")).unwrap_or(100.0),
        thickness_max: number(v.get("iridescenceThicknessMaximum")).unwrap_or(400.0),
        thickness_texture: slot(v.get("iridescenceThicknessTexture")),
    }
}

/// `KHR_materials_dispersion`'s `dispersion` (20 / Abbe number; default 0).
pub fn dispersion(v: &Value) -> f32 {
    number(v.get("dispersion")).unwrap_or(0.0)
}

fn number(v: Option<&Value>) -> Option<f32> {
    v?.as_f64().map(|x| x as f32)
}

fn vec2(v: Option<&Value>) -> Option<[f32; 2]> {
    match v?.as_array()?.as_slice() {
        [a, b] => Some([a.as_f64()? as f32, b.as_f64()? as f32]),
        _ => None,
    }
}

fn vec3(v: Option<&Value>) -> Option<[f32; 3]> {
    match v?.as_array()?.as_slice() {
        [a, b, c] => Some([a.as_f64()? as f32, b.as_f64()? as f32, c.as_f64()? as f32]),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rotation_follows_the_extensions_example() {
        // offset (0, 1), rotation 90 degrees, scale 0.5: the lower-left quadrant of the
        // image, turned clockwise.
        let t = TextureTransform {
            offset: [0.0, 1.0],
            rotation: std::f32::consts::FRAC_PI_2,
            scale: [0.5, 0.5],
            tex_coord: None,
        };
        let a = t.affine().unwrap();
        for (uv, want) in [
            ([0.0, 0.0], [0.0, 1.0]),
            ([1.0, 0.0], [0.0, 0.5]),
            ([0.0, 1.0], [0.5, 1.0]),
            ([1.0, 1.0], [0.5, 0.5]),
        ] {
            let got = a.transform_point2(Vec2::from(uv));
            assert!((got - Vec2::from(want)).length() < 1e-6, "{uv:?}: {got}");
        }
        let id = TextureTransform {
            offset: [0.0, 0.0],
            rotation: 0.0,
            scale: [1.0, 1.0],
            tex_coord: Some(1),
        };
        assert!(id.affine().is_none());
    }
}

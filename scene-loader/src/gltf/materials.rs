//! Materials: the core metallic-roughness model and the `KHR_materials_*` extensions dray
//! renders, their texture slots (with `KHR_texture_transform`), and the at most two UV
//! sets a material's textures read.

use dray_core::material::{
    AlphaMode, Anisotropy, Clearcoat, Iridescence, Material, Sheen, TexRef, Volume,
};
use glam::{Vec3, Vec4};

use super::Loader;
use crate::gltf_ext::{self, SlotJson, TextureTransform};

/// The UV sets a material's textures read: every slot reads `first` except those marked
/// [`TexRef::second_uv`], which read `second`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub(super) struct UvSets {
    pub(super) first: u32,
    pub(super) second: Option<u32>,
}

/// Every texture slot of `m` in use, named as in glTF, in [`Material::texture_refs`]'s
/// order.
fn named_slots(m: &mut Material) -> Vec<(&'static str, &mut TexRef)> {
    let Material {
        base_color_tex,
        metallic_roughness_tex,
        normal_tex,
        emissive_tex,
        transmission_tex,
        specular_tex,
        specular_color_tex,
        clearcoat,
        sheen,
        anisotropy,
        iridescence,
        ..
    } = m;
    let mut slots = vec![
        ("baseColorTexture", base_color_tex.as_mut()),
        ("metallicRoughnessTexture", metallic_roughness_tex.as_mut()),
        ("normalTexture", normal_tex.as_mut()),
        ("emissiveTexture", emissive_tex.as_mut()),
        ("transmissionTexture", transmission_tex.as_mut()),
        ("specularTexture", specular_tex.as_mut()),
        ("specularColorTexture", specular_color_tex.as_mut()),
    ];
    if let Some(c) = clearcoat {
        slots.push(("clearcoatTexture", c.tex.as_mut()));
        slots.push(("clearcoatRoughnessTexture", c.roughness_tex.as_mut()));
        slots.push(("clearcoatNormalTexture", c.normal_tex.as_mut()));
    }
    if let Some(sh) = sheen {
        slots.push(("sheenColorTexture", sh.color_tex.as_mut()));
        slots.push(("sheenRoughnessTexture", sh.roughness_tex.as_mut()));
    }
    if let Some(a) = anisotropy {
        slots.push(("anisotropyTexture", a.tex.as_mut()));
    }
    if let Some(ir) = iridescence {
        slots.push(("iridescenceTexture", ir.tex.as_mut()));
        slots.push(("iridescenceThicknessTexture", ir.thickness_tex.as_mut()));
    }
    slots
        .into_iter()
        .filter_map(|(name, t)| Some((name, t?)))
        .collect()
}

impl Loader<'_> {
    /// Convert every glTF material, in order, so glTF material `i` is scene material `i`.
    pub(super) fn load_materials(&mut self) {
        let doc = self.doc;
        for m in doc.materials() {
            let name = m
                .name()
                .map(str::to_string)
                .unwrap_or_else(|| format!("material #{}", m.index().unwrap_or(0)));
            let pbr = m.pbr_metallic_roughness();
            let mut mat = Material {
                name: name.clone(),
                base_color: Vec4::from(pbr.base_color_factor()),
                metallic: pbr.metallic_factor(),
                roughness: pbr.roughness_factor(),
                emissive: Vec3::from(m.emissive_factor()) * m.emissive_strength().unwrap_or(1.0),
                alpha_mode: match m.alpha_mode() {
                    gltf::material::AlphaMode::Opaque => AlphaMode::Opaque,
                    gltf::material::AlphaMode::Mask => AlphaMode::Mask {
                        cutoff: m.alpha_cutoff().unwrap_or(0.5),
                    },
                    gltf::material::AlphaMode::Blend => AlphaMode::Blend,
                },
                double_sided: m.double_sided(),
                ..Material::default()
            };
            mat.base_color_tex = self.tex_ref(&name, "baseColorTexture", pbr.base_color_texture());
            mat.metallic_roughness_tex = self.tex_ref(
                &name,
                "metallicRoughnessTexture",
                pbr.metallic_roughness_texture(),
            );
            if let Some(normal) = m.normal_texture() {
                mat.normal_scale = normal.scale();
                mat.normal_tex = self.tex_slot(
                    &name,
                    "normalTexture",
                    normal.texture().index(),
                    normal.tex_coord(),
                    TextureTransform::from_extensions(normal.extensions()),
                );
            }
            mat.emissive_tex = self.tex_ref(&name, "emissiveTexture", m.emissive_texture());
            if let Some(t) = m.transmission() {
                mat.transmission = t.transmission_factor();
                mat.transmission_tex =
                    self.tex_ref(&name, "transmissionTexture", t.transmission_texture());
            }
            if let Some(ior) = m.ior() {
                mat.ior = ior;
            }
            if let Some(s) = m.specular() {
                mat.specular = s.specular_factor();
                mat.specular_tex = self.tex_ref(&name, "specularTexture", s.specular_texture());
                mat.specular_color = Vec3::from(s.specular_color_factor());
                mat.specular_color_tex =
                    self.tex_ref(&name, "specularColorTexture", s.specular_color_texture());
            }
            if let Some(v) = m.volume() {
                mat.volume = Some(Volume {
                    attenuation_color: Vec3::from(v.attenuation_color()),
                    attenuation_distance: v.attenuation_distance(),
                });
            }
            self.layer_extensions(&m, &name, &mut mat);
            mat.unlit = m.unlit();
            let sets = self.choose_uv_sets(&mut mat);
            self.uv_sets.push(sets);
            self.scene.materials.push(mat);
        }
    }

    /// The extensions the `gltf` crate does not type, read from their JSON: the layers
    /// over the base (`KHR_materials_clearcoat`, `_sheen`, `_iridescence`), the
    /// anisotropy of its lobe and the dispersion of its glass.
    fn layer_extensions(&mut self, m: &gltf::Material<'_>, name: &str, mat: &mut Material) {
        if let Some(c) = m.extension_value("KHR_materials_clearcoat") {
            let c = gltf_ext::clearcoat(c);
            mat.clearcoat = Some(Clearcoat {
                factor: c.factor,
                tex: self.tex_json(name, "clearcoatTexture", c.texture),
                roughness: c.roughness,
                roughness_tex: self.tex_json(
                    name,
                    "clearcoatRoughnessTexture",
                    c.roughness_texture,
                ),
                normal_tex: self.tex_json(name, "clearcoatNormalTexture", c.normal_texture),
                normal_scale: c.normal_scale,
            });
        }
        if let Some(sh) = m.extension_value("KHR_materials_sheen") {
            let sh = gltf_ext::sheen(sh);
            mat.sheen = Some(Sheen {
                color: sh.color,
                color_tex: self.tex_json(name, "sheenColorTexture", sh.color_texture),
                roughness: sh.roughness,
                roughness_tex: self.tex_json(name, "sheenRoughnessTexture", sh.roughness_texture),
            });
        }
        if let Some(a) = m.extension_value("KHR_materials_anisotropy") {
            let a = gltf_ext::anisotropy(a);
            mat.anisotropy = Some(Anisotropy {
                strength: a.strength,
                rotation: a.rotation,
                tex: self.tex_json(name, "anisotropyTexture", a.texture),
            });
        }
        if let Some(ir) = m.extension_value("KHR_materials_iridescence") {
            let ir = gltf_ext::iridescence(ir);
            mat.iridescence = Some(Iridescence {
                factor: ir.factor,
                tex: self.tex_json(name, "iridescenceTexture", ir.texture),
                ior: ir.ior,
                thickness_min: ir.thickness_min,
                thickness_max: ir.thickness_max,
                thickness_tex: self.tex_json(
                    name,
                    "iridescenceThicknessTexture",
                    ir.thickness_texture,
                ),
            });
        }
        if let Some(d) = m.extension_value("KHR_materials_dispersion") {
            mat.dispersion = gltf_ext::dispersion(d);
        }
    }

    pub(super) fn tex_ref(
        &mut self,
        material: &str,
        slot: &str,
        info: Option<gltf::texture::Info<'_>>,
    ) -> Option<TexRef> {
        let info = info?;
        let transform = info.texture_transform().map(|t| TextureTransform {
            offset: t.offset(),
            rotation: t.rotation(),
            scale: t.scale(),
            tex_coord: t.tex_coord(),
        });
        self.tex_slot(
            material,
            slot,
            info.texture().index(),
            info.tex_coord(),
            transform,
        )
    }

    /// A texture slot the `gltf` crate does not type (an extension's), from its JSON.
    pub(super) fn tex_json(
        &mut self,
        material: &str,
        slot: &str,
        json: Option<SlotJson>,
    ) -> Option<TexRef> {
        let s = json?;
        if s.index >= self.scene.textures.len() {
            self.warn(format!(
                "{}: material {material:?} {slot} refers to texture {}, which does not exist; \
                 the slot is ignored",
                self.path.display(),
                s.index
            ));
            return None;
        }
        self.tex_slot(material, slot, s.index, s.tex_coord, s.transform)
    }

    /// A texture reference with `KHR_texture_transform` applied (its `texCoord`
    /// overrides the slot's, as the extension says).
    pub(super) fn tex_slot(
        &mut self,
        material: &str,
        slot: &str,
        texture: usize,
        tex_coord: u32,
        transform: Option<TextureTransform>,
    ) -> Option<TexRef> {
        if transform.is_some_and(|t| t.is_malformed()) {
            self.warn(format!(
                "{}: material {material:?} {slot}: KHR_texture_transform has a value that \
                 is not finite; the transform is ignored",
                self.path.display()
            ));
        }
        Some(TexRef {
            texture: u32::try_from(texture).ok()?,
            tex_coord: transform.and_then(|t| t.tex_coord).unwrap_or(tex_coord),
            // Set by `choose_uv_sets` once every slot is known.
            second_uv: false,
            transform: transform.and_then(|t| t.affine()),
        })
    }

    /// The UV sets the mesh stores for triangles of `material`: the one its base colour
    /// reads (else its first slot's), and the first other set a slot names, if any. Each
    /// slot is marked with the one it reads ([`TexRef::second_uv`]). A slot naming a
    /// third set reads the first, with a warning: a vertex keeps at most two sets, which
    /// covers the files seen in practice (a second set serves light maps or ambient
    /// occlusion, and the Sample Models use at most two).
    pub(super) fn choose_uv_sets(&mut self, material: &mut Material) -> UvSets {
        let first = material
            .base_color_tex
            .or_else(|| material.texture_refs().next())
            .map_or(0, |t| t.tex_coord);
        let mut second = None;
        let mut ignored = Vec::new();
        for (slot, t) in named_slots(material) {
            let k = t.tex_coord;
            if k == first {
                continue;
            }
            if second.is_none_or(|s| s == k) {
                second = Some(k);
                t.second_uv = true;
            } else {
                ignored.push((slot, k));
                t.tex_coord = first;
            }
        }
        for (slot, k) in ignored {
            self.warn(format!(
                "{}: material {:?} {slot} reads TEXCOORD_{k}, a third UV set after \
                 TEXCOORD_{first} and TEXCOORD_{}; dray keeps at most two per vertex, so it \
                 reads TEXCOORD_{first}",
                self.path.display(),
                material.name,
                second.unwrap_or(first),
            ));
        }
        UvSets { first, second }
    }

    pub(super) fn default_material(&mut self) -> u32 {
        if let Some(i) = self.default_material {
            return i;
        }
        let i = self.scene.materials.len() as u32;
        self.scene.materials.push(Material::default());
        self.default_material = Some(i);
        i
    }
}

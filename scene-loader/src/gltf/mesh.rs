//! Meshes: each instanced mesh decoded once into local-space primitives (attributes,
//! morph targets at the pose's weights, strips and fans as lists, tangents generated where
//! a normal map or anisotropy needs them), then emitted per instance through the
//! validation gate ([`crate::validate::add_primitive`]).

use std::borrow::Cow;

use dray_core::material::TexRef;
use glam::{DMat3, DMat4, Vec2, Vec3, Vec4};
use gltf::json;

use super::Loader;
use super::nodes::Placements;
use crate::error::Result;
use crate::validate::{self, Origin, Primitive};

/// One mesh primitive decoded into local-space arrays, ready to be instanced.
pub(super) struct DecodedPrimitive {
    pub(super) index: usize,
    pub(super) positions: Vec<Vec3>,
    pub(super) normals: Option<Vec<Vec3>>,
    pub(super) tangents: Option<Vec<Vec4>>,
    pub(super) uvs: Option<Vec<Vec2>>,
    /// The second UV set, read only when the material's textures name two.
    pub(super) uvs2: Option<Vec<Vec2>>,
    /// The source's numbers of `uvs` and `uvs2` (`TEXCOORD_n`).
    pub(super) uv_sets: [u32; 2],
    /// `COLOR_0` as linear RGBA.
    pub(super) colors: Option<Vec<Vec4>>,
    /// Triangle list (strips and fans already converted).
    pub(super) indices: Vec<u32>,
    pub(super) material: u32,
}

impl Loader<'_> {
    /// Decode each instanced mesh once and emit it for each of its instances.
    pub(super) fn load_meshes(&mut self, mut placements: Placements) -> Result<()> {
        // Group instances by mesh (stable, so instances keep their walk order) so each
        // mesh is decoded once and dropped before the next.
        placements.meshes.sort_by_key(|&(mesh, _, _)| mesh);
        let doc = self.doc;
        let mut start = 0;
        while let Some(&(mesh_index, _, _)) = placements.meshes.get(start) {
            let end = placements
                .meshes
                .get(start..)
                .unwrap_or_default()
                .iter()
                .position(|&(m, _, _)| m != mesh_index)
                .map_or(placements.meshes.len(), |n| start + n);
            let mesh = doc
                .meshes()
                .nth(mesh_index)
                .ok_or_else(|| self.error(format!("mesh {mesh_index} does not exist")))?;
            let name = mesh
                .name()
                .map(str::to_string)
                .unwrap_or_else(|| format!("mesh #{mesh_index}"));
            let group = placements.meshes.get(start..end).unwrap_or_default();
            // Instances whose nodes give the same morph weights (nearly always all of
            // them: node weights are rare) share one decoded copy.
            let mut emitted = vec![false; group.len()];
            for (first, (_, _, node_weights)) in group.iter().enumerate() {
                if emitted.get(first).copied().unwrap_or(true) {
                    continue;
                }
                crate::cancel::check()?;
                let weights = node_weights.as_deref().or(mesh.weights());
                let prims = self.decode_mesh(&mesh, &name, weights)?;
                for (k, (_, world, w)) in group.iter().enumerate().skip(first) {
                    if w != node_weights || emitted.get(k).copied().unwrap_or(true) {
                        continue;
                    }
                    if let Some(e) = emitted.get_mut(k) {
                        *e = true;
                    }
                    for prim in &prims {
                        self.emit(&name, prim, *world)?;
                    }
                }
            }
            start = end;
        }
        Ok(())
    }

    /// Decode every triangle primitive of `mesh` in its local space, with the morph
    /// `weights` applied (the rest pose the file shows), and tangents generated where a
    /// normal map needs them and the file gives none.
    pub(super) fn decode_mesh(
        &mut self,
        mesh: &gltf::Mesh<'_>,
        name: &str,
        weights: Option<&[f32]>,
    ) -> Result<Vec<DecodedPrimitive>> {
        let mut out = Vec::new();
        for prim in mesh.primitives() {
            if let Some(decoded) = self.decode_primitive(mesh, &prim, name, weights)? {
                out.push(decoded);
            }
        }
        Ok(out)
    }

    /// One primitive of `mesh` (named `name`) decoded, or `None` when it is not made of
    /// triangles (skipped with a warning).
    fn decode_primitive(
        &mut self,
        mesh: &gltf::Mesh<'_>,
        prim: &gltf::Primitive<'_>,
        name: &str,
        weights: Option<&[f32]>,
    ) -> Result<Option<DecodedPrimitive>> {
        use gltf::mesh::{Mode, Semantic};
        let origin = Origin {
            path: self.path,
            mesh: name,
            primitive: prim.index(),
        };
        let mode = prim.mode();
        if !matches!(
            mode,
            Mode::Triangles | Mode::TriangleStrip | Mode::TriangleFan
        ) {
            self.warn(format!(
                "{}: mesh {name:?} primitive {}: mode {mode:?} is not triangles; skipped",
                self.path.display(),
                prim.index()
            ));
            return Ok(None);
        }
        let (positions, normals, tangents) = self.read_vertices(mesh, prim, origin, weights)?;
        let material = self.primitive_material(prim, origin)?;
        // The UV sets this primitive's material reads (TEXCOORD_0 unless its
        // textures ask for another, and a second only when they name two).
        let sets = self
            .uv_sets
            .get(material as usize)
            .copied()
            .unwrap_or_default();
        let uvs = self.read_uvs(prim, origin, sets.first)?;
        let uvs2 = match sets.second {
            Some(set) => self.read_uvs(prim, origin, set)?,
            None => None,
        };
        let colors = match prim.get(&Semantic::Colors(0)) {
            Some(a) => Some(
                self.read_colors(a.index())
                    .map_err(|m| origin.error(format!("COLOR_0: {m}")))?,
            ),
            None => None,
        };
        let raw_indices = match prim.indices() {
            Some(acc) => self
                .read_indices(acc.index())
                .map_err(|m| origin.error(format!("indices: {m}")))?,
            None => {
                let n = u32::try_from(positions.len())
                    .map_err(|_| origin.error("too many vertices for 32-bit indices"))?;
                (0..n).collect()
            }
        };
        let indices = match mode {
            Mode::TriangleStrip => validate::strip_to_list(&raw_indices),
            Mode::TriangleFan => validate::fan_to_list(&raw_indices),
            _ => raw_indices,
        };
        let mut decoded = DecodedPrimitive {
            index: prim.index(),
            positions,
            normals,
            tangents,
            uvs,
            uvs2,
            uv_sets: [sets.first, sets.second.unwrap_or(sets.first)],
            colors,
            indices,
            material,
        };
        self.generate_tangents(&mut decoded, name, sets.first);
        Ok(Some(decoded))
    }

    /// A primitive's POSITION, NORMAL and TANGENT, moved by its morph targets at
    /// `weights` when it has both.
    #[allow(clippy::type_complexity)] // the three vertex attributes, as decoded
    fn read_vertices(
        &mut self,
        mesh: &gltf::Mesh<'_>,
        prim: &gltf::Primitive<'_>,
        origin: Origin<'_>,
        weights: Option<&[f32]>,
    ) -> Result<(Vec<Vec3>, Option<Vec<Vec3>>, Option<Vec<Vec4>>)> {
        use gltf::mesh::Semantic;
        let attr = |semantic: Semantic| prim.get(&semantic).map(|a| a.index());
        let err = |what: &str, m: String| origin.error(format!("{what}: {m}"));
        let pos_acc = attr(Semantic::Positions)
            .ok_or_else(|| origin.error("primitive has no POSITION attribute"))?;
        let mut positions: Vec<Vec3> = self
            .read_accessor::<f32>(pos_acc, 3)
            .map_err(|m| err("POSITION", m))?
            .chunks_exact(3)
            .map(Vec3::from_slice)
            .collect();
        let mut normals = match attr(Semantic::Normals) {
            Some(a) => Some(
                self.read_accessor::<f32>(a, 3)
                    .map_err(|m| err("NORMAL", m))?
                    .chunks_exact(3)
                    .map(Vec3::from_slice)
                    .collect::<Vec<_>>(),
            ),
            None => None,
        };
        let mut tangents = match attr(Semantic::Tangents) {
            Some(a) => Some(
                self.read_accessor::<f32>(a, 4)
                    .map_err(|m| err("TANGENT", m))?
                    .chunks_exact(4)
                    .map(Vec4::from_slice)
                    .collect::<Vec<_>>(),
            ),
            None => None,
        };
        let targets = self
            .root
            .meshes
            .get(mesh.index())
            .and_then(|m| m.primitives.get(prim.index()))
            .and_then(|p| p.targets.as_deref());
        if let (Some(targets), Some(weights)) = (targets, weights) {
            self.apply_morph_targets(
                origin,
                targets,
                weights,
                &mut positions,
                &mut normals,
                &mut tangents,
            )?;
        }
        Ok((positions, normals, tangents))
    }

    /// The scene material of a primitive: its own, checked, or the default material.
    fn primitive_material(
        &mut self,
        prim: &gltf::Primitive<'_>,
        origin: Origin<'_>,
    ) -> Result<u32> {
        Ok(match prim.material().index() {
            Some(i) => u32::try_from(i)
                .ok()
                .filter(|&i| (i as usize) < self.root.materials.len())
                .ok_or_else(|| origin.error(format!("material {i} does not exist")))?,
            None => self.default_material(),
        })
    }

    /// A primitive's `TEXCOORD_<set>`, if it has one.
    fn read_uvs(
        &self,
        prim: &gltf::Primitive<'_>,
        origin: Origin<'_>,
        set: u32,
    ) -> Result<Option<Vec<Vec2>>> {
        match prim.get(&gltf::mesh::Semantic::TexCoords(set)) {
            Some(a) => Ok(Some(
                self.read_accessor::<f32>(a.index(), 2)
                    .map_err(|m| origin.error(format!("TEXCOORD_{set}: {m}")))?
                    .chunks_exact(2)
                    .map(Vec2::from_slice)
                    .collect::<Vec<_>>(),
            )),
            None => Ok(None),
        }
    }

    /// Tangents for a primitive without TANGENT whose material needs them: for a normal
    /// map (the material's or its clear coat's), from the UV set that map reads, and for
    /// an anisotropic lobe (its direction is given in tangent space) from the first set
    /// (`first_set`). MikkTSpace may split vertices; every attribute follows the split.
    /// Without NORMAL or that UV set the map is ignored there, with a warning.
    fn generate_tangents(&mut self, p: &mut DecodedPrimitive, name: &str, first_set: u32) {
        let normal_map = self.scene.materials.get(p.material as usize).and_then(|m| {
            m.normal_tex.or(m.clearcoat.and_then(|c| c.normal_tex)).or(m
                .has_anisotropy()
                .then_some(TexRef {
                    tex_coord: first_set,
                    ..TexRef::new(0)
                }))
        });
        let (Some(map), None) = (normal_map, &p.tangents) else {
            return;
        };
        let frame_uvs = if map.second_uv { &p.uvs2 } else { &p.uvs };
        match (&mut p.normals, frame_uvs) {
            (Some(ns), Some(us)) => {
                // MikkTSpace reads what shading will read (cleaned values),
                // with V pointing up as in the tools that bake normal maps:
                // glTF's V points down the image, and a normal map's green
                // channel points up it ("+Y is up", glTF 2.0 normalTexture).
                // Without the flip every bitangent sign would be inverted
                // (three.js negates w after MikkTSpace for the same reason).
                let clean_ns: Vec<Vec3> = ns.iter().map(|&n| validate::clean_normal(n)).collect();
                let clean_us: Vec<Vec2> = us
                    .iter()
                    .map(|&u| {
                        let c = validate::clean_uv(u);
                        Vec2::new(c.x, 1.0 - c.y)
                    })
                    .collect();
                let (generated, split) =
                    crate::tangents::generate(&p.positions, &clean_ns, &clean_us, &mut p.indices);
                split.apply(&mut p.positions);
                split.apply(ns);
                if let Some(us) = p.uvs.as_mut() {
                    split.apply(us);
                }
                if let Some(us) = p.uvs2.as_mut() {
                    split.apply(us);
                }
                if let Some(cs) = p.colors.as_mut() {
                    split.apply(cs);
                }
                p.tangents = Some(generated);
            }
            _ => self.warn(format!(
                "{}: mesh {name:?} primitive {}: its material has a normal map or an \
                 anisotropic lobe but the primitive has no TANGENT, and no NORMAL or \
                 TEXCOORD_{} to generate tangents from; its normal map is ignored there, \
                 and so is its anisotropy",
                self.path.display(),
                p.index,
                map.tex_coord
            )),
        }
    }

    /// Add the morph targets' displacements, each times its weight, to the base
    /// attributes: a file's rest pose is its mesh at the default weights (glTF 2.0,
    /// "Morph Targets"), and an animation dray does not play would start from it. A
    /// weight of zero adds nothing, so an unweighted mesh keeps its bits.
    #[allow(clippy::too_many_arguments)] // the one primitive's attributes being moved
    pub(super) fn apply_morph_targets(
        &mut self,
        origin: Origin<'_>,
        targets: &[json::mesh::MorphTarget],
        weights: &[f32],
        positions: &mut [Vec3],
        normals: &mut Option<Vec<Vec3>>,
        tangents: &mut Option<Vec<Vec4>>,
    ) -> Result<()> {
        if weights.len() != targets.len() {
            self.warn(format!(
                "{}: mesh {:?} primitive {}: {} morph weights for {} morph targets; the \
                 missing ones are taken as 0 and the extra ones ignored",
                self.path.display(),
                origin.mesh,
                origin.primitive,
                weights.len(),
                targets.len()
            ));
        }
        let n = positions.len();
        for (t, (target, &weight)) in targets.iter().zip(weights).enumerate() {
            if weight == 0.0 {
                continue;
            }
            // One mesh may have hundreds of thousands of targets (issue 45: 200,000 of
            // them ran on for 20 s of CPU after CancelJob): look at the flag each time.
            crate::cancel::check()?;
            let read = |acc: Option<json::Index<json::Accessor>>, what: &str| {
                let Some(acc) = acc else {
                    return Ok(None);
                };
                let what = format!("morph target {t} {what}");
                let deltas: Vec<Vec3> = self
                    .read_accessor::<f32>(acc.value(), 3)
                    .map_err(|m| origin.error(format!("{what}: {m}")))?
                    .chunks_exact(3)
                    .map(Vec3::from_slice)
                    .collect();
                if deltas.len() != n {
                    return Err(origin.error(format!(
                        "{what} has {} entries but POSITION has {n}",
                        deltas.len()
                    )));
                }
                Ok(Some(deltas))
            };
            if let Some(d) = read(target.positions, "POSITION")? {
                for (p, d) in positions.iter_mut().zip(d) {
                    *p += weight * d;
                }
            }
            if let (Some(d), Some(ns)) = (read(target.normals, "NORMAL")?, normals.as_mut()) {
                for (v, d) in ns.iter_mut().zip(d) {
                    *v += weight * d;
                }
            }
            if let (Some(d), Some(ts)) = (read(target.tangents, "TANGENT")?, tangents.as_mut()) {
                for (v, d) in ts.iter_mut().zip(d) {
                    *v += (weight * d).extend(0.0);
                }
            }
        }
        Ok(())
    }

    /// Transform one decoded primitive by `world` and push it through the validation gate.
    pub(super) fn emit(
        &mut self,
        mesh_name: &str,
        prim: &DecodedPrimitive,
        world: DMat4,
    ) -> Result<()> {
        // Most instances sit under identity transforms; keep their data bit for bit.
        let identity = world == DMat4::IDENTITY;
        let linear = DMat3::from_mat4(world);
        let det = linear.determinant();
        // Normals follow the inverse transpose; a singular matrix gives non-finite
        // normals, which the gate turns into "absent".
        let normal_matrix = linear.inverse().transpose();
        let positions: Cow<'_, [Vec3]> = if identity {
            Cow::Borrowed(&prim.positions)
        } else {
            prim.positions
                .iter()
                .map(|p| world.transform_point3(p.as_dvec3()).as_vec3())
                .collect()
        };
        let normals: Option<Cow<'_, [Vec3]>> = prim.normals.as_ref().map(|ns| {
            if identity {
                Cow::Borrowed(ns.as_slice())
            } else {
                ns.iter()
                    .map(|n| (normal_matrix * n.as_dvec3()).as_vec3())
                    .collect()
            }
        });
        // A mirroring transform flips handedness, so the bitangent sign flips with it.
        let w_sign = if det < 0.0 { -1.0 } else { 1.0 };
        let tangents: Option<Cow<'_, [Vec4]>> = prim.tangents.as_ref().map(|ts| {
            if identity {
                Cow::Borrowed(ts.as_slice())
            } else {
                ts.iter()
                    .map(|t| {
                        let xyz = (linear * t.truncate().as_dvec3())
                            .normalize_or_zero()
                            .as_vec3();
                        xyz.extend(t.w * w_sign)
                    })
                    .collect()
            }
        });
        // Mirroring also turns counter-clockwise triangles clockwise; swap two corners
        // so front faces stay front faces.
        let indices: Cow<'_, [u32]> = if det < 0.0 {
            let mut flipped = prim.indices.clone();
            for tri in flipped.chunks_exact_mut(3) {
                tri.swap(1, 2);
            }
            Cow::Owned(flipped)
        } else {
            Cow::Borrowed(&prim.indices)
        };
        let origin = Origin {
            path: self.path,
            mesh: mesh_name,
            primitive: prim.index,
        };
        validate::add_primitive(
            &mut self.scene.mesh,
            &mut self.scene.stats,
            origin,
            Primitive {
                positions: &positions,
                normals: normals.as_deref(),
                tangents: tangents.as_deref(),
                uvs: prim.uvs.as_deref(),
                uvs2: prim.uvs2.as_deref(),
                uv_sets: prim.uv_sets,
                colors: prim.colors.as_deref(),
                indices: &indices,
                material: prim.material,
            },
        )
    }
}

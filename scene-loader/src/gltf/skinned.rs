//! Skinned mesh instances: the joint matrices of a skin from the node walk's world
//! transforms and the inverse bind matrices, applied to the decoded mesh by
//! [`crate::skin`].

use glam::DMat4;

use super::nodes::SkinnedInstance;
use super::{Loader, format_error};
use crate::error::Result;

impl Loader<'_> {
    /// Decode one skinned instance's mesh and move its vertices by its skin's joints
    /// ([`crate::skin`]): joint matrices from the joints' world transforms (as the walk,
    /// and any animation, left them) and the inverse bind matrices (identity when
    /// absent).
    pub(super) fn load_skinned(
        &mut self,
        instance: &SkinnedInstance,
        node_world: &std::collections::HashMap<usize, DMat4>,
    ) -> Result<()> {
        crate::cancel::check()?;
        let doc = self.doc;
        let node = &instance.node_name;
        let skin = doc.skins().nth(instance.skin).ok_or_else(|| {
            self.error(format!(
                "node {node}: skin {} does not exist",
                instance.skin
            ))
        })?;
        let mesh = doc
            .meshes()
            .nth(instance.mesh)
            .ok_or_else(|| self.error(format!("mesh {} does not exist", instance.mesh)))?;
        let joints: Vec<gltf::Node<'_>> = skin.joints().collect();
        let inverse_bind: Vec<f32> = match skin.inverse_bind_matrices() {
            Some(acc) => self.read_accessor(acc.index(), 16).map_err(|m| {
                self.error(format!("skin {}: inverseBindMatrices: {m}", skin.index()))
            })?,
            None => Vec::new(),
        };
        if !inverse_bind.is_empty() && inverse_bind.len() < joints.len() * 16 {
            return Err(self.error(format!(
                "skin {}: {} inverse bind matrices for {} joints",
                skin.index(),
                inverse_bind.len() / 16,
                joints.len()
            )));
        }
        let mut matrices = Vec::with_capacity(joints.len());
        for (j, joint) in joints.iter().enumerate() {
            let Some(world) = node_world.get(&joint.index()) else {
                return Err(self.error(format!(
                    "skin {}: joint node {} is not in the scene",
                    skin.index(),
                    joint.index()
                )));
            };
            let ibm = inverse_bind
                .get(j * 16..j * 16 + 16)
                .map_or(DMat4::IDENTITY, |m| {
                    DMat4::from_cols_array(&std::array::from_fn(|k| f64::from(m[k])))
                });
            let m = *world * ibm;
            if !m.is_finite() {
                return Err(self.error(format!(
                    "skin {}: joint {j} has a matrix that is not finite",
                    skin.index()
                )));
            }
            matrices.push(m);
        }
        let name = mesh
            .name()
            .map(str::to_string)
            .unwrap_or_else(|| format!("mesh #{}", instance.mesh));
        let weights = instance.weights.as_deref().or(mesh.weights());
        let prims = self.decode_mesh(&mesh, &name, weights)?;
        for mut prim in prims {
            let Some(source) = mesh.primitives().nth(prim.index) else {
                continue;
            };
            let at = |m: String| {
                format_error(
                    self.path,
                    format!("mesh {name:?} primitive {}: {m}", prim.index),
                )
            };
            let mut influences: Vec<crate::skin::Influences> =
                vec![Vec::new(); prim.positions.len()];
            for set in 0..2 {
                let joints_acc = source.get(&gltf::mesh::Semantic::Joints(set));
                let weights_acc = source.get(&gltf::mesh::Semantic::Weights(set));
                let (Some(ja), Some(wa)) = (joints_acc, weights_acc) else {
                    if set == 0 {
                        return Err(at("skinned, but has no JOINTS_0 and WEIGHTS_0".into()));
                    }
                    break;
                };
                let js: Vec<u32> = self.read_accessor(ja.index(), 4).map_err(at)?;
                let ws: Vec<f32> = self.read_accessor(wa.index(), 4).map_err(at)?;
                if js.len() != prim.positions.len() * 4 || ws.len() != js.len() {
                    return Err(at(format!(
                        "JOINTS_{set}/WEIGHTS_{set} have {}/{} elements for {} vertices",
                        js.len() / 4,
                        ws.len() / 4,
                        prim.positions.len()
                    )));
                }
                for (v, inf) in influences.iter_mut().enumerate() {
                    for k in 0..4 {
                        inf.push((js[v * 4 + k], ws[v * 4 + k]));
                    }
                }
            }
            crate::skin::skin(
                &matrices,
                &influences,
                &mut prim.positions,
                prim.normals.as_deref_mut(),
                prim.tangents.as_deref_mut(),
            )
            .map_err(|e| at(e.to_string()))?;
            self.emit(&name, &prim, DMat4::IDENTITY)?;
        }
        Ok(())
    }
}

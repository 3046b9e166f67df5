//! The scene graph: the chosen scene's node hierarchy walked in f64 (bounded in depth and
//! in visits), collecting mesh and skinned instances with their world transforms, and the
//! cameras and `KHR_lights_punctual` lights the nodes carry.

use dray_core::camera::{Camera, Projection};
use dray_core::light::Light;
use glam::{DMat4, DQuat, DVec3, Vec3};

use super::{Loader, MAX_NODE_DEPTH, MAX_NODE_VISITS};
use crate::animation::NodePose;
use crate::error::Result;

/// Everything the node walk found.
#[derive(Default)]
pub(super) struct Placements {
    /// Per mesh instance: mesh index, world matrix, and the node's morph weights (which
    /// override the mesh's).
    pub(super) meshes: Vec<(usize, DMat4, Option<Vec<f32>>)>,
    /// Per skinned mesh instance: its node, mesh, skin and morph weights (the node's
    /// transform does not apply to a skin).
    pub(super) skinned: Vec<SkinnedInstance>,
    /// Every visited node's world matrix, for the joints of the skins.
    pub(super) node_world: std::collections::HashMap<usize, DMat4>,
}

/// A mesh placed by a skin ([`crate::skin`]).
pub(super) struct SkinnedInstance {
    pub(super) node_name: String,
    pub(super) mesh: usize,
    pub(super) skin: usize,
    pub(super) weights: Option<Vec<f32>>,
}

impl Loader<'_> {
    /// Walk the chosen scene, composing transforms in f64, and collect mesh instances,
    /// cameras and lights.
    pub(super) fn walk_nodes(&mut self) -> Result<Placements> {
        let doc = self.doc;
        let roots: Vec<gltf::Node<'_>> = match doc.default_scene().or_else(|| doc.scenes().next()) {
            Some(scene) => scene.nodes().collect(),
            None => {
                let mut is_child = vec![false; self.root.nodes.len()];
                for node in doc.nodes() {
                    for child in node.children() {
                        if let Some(c) = is_child.get_mut(child.index()) {
                            *c = true;
                        }
                    }
                }
                doc.nodes()
                    .filter(|n| !is_child.get(n.index()).copied().unwrap_or(false))
                    .collect()
            }
        };

        let mut placements = Placements::default();
        let mut visits = 0usize;
        // Reverse so that popping visits nodes in document order.
        let mut stack: Vec<(gltf::Node<'_>, DMat4, usize)> = roots
            .into_iter()
            .rev()
            .map(|n| (n, DMat4::IDENTITY, 0))
            .collect();
        while let Some((node, parent, depth)) = stack.pop() {
            visits += 1;
            let node_name = node
                .name()
                .map(|n| format!("{n:?}"))
                .unwrap_or_else(|| format!("#{}", node.index()));
            if depth > MAX_NODE_DEPTH {
                return Err(self.error(format!(
                    "node {node_name}: hierarchy is deeper than {MAX_NODE_DEPTH} levels (does it \
                     contain a cycle?)"
                )));
            }
            if visits > MAX_NODE_VISITS {
                return Err(self.error(format!(
                    "node hierarchy expands to more than {MAX_NODE_VISITS} node instances"
                )));
            }
            let posed = self.pose.nodes.get(&node.index());
            let world = parent * local_matrix(&node, posed);
            if !world.is_finite() {
                return Err(self.error(format!(
                    "node {node_name}: transform is not finite (check matrix, rotation, scale)"
                )));
            }
            placements.node_world.entry(node.index()).or_insert(world);
            if let Some(mesh) = node.mesh() {
                match node.skin() {
                    Some(skin) => placements.skinned.push(SkinnedInstance {
                        node_name: node_name.clone(),
                        mesh: mesh.index(),
                        skin: skin.index(),
                        weights: node_weights(&node, posed),
                    }),
                    None => {
                        placements
                            .meshes
                            .push((mesh.index(), world, node_weights(&node, posed)))
                    }
                }
            }
            if let Some(camera) = node.camera() {
                self.add_camera(&camera, world);
            }
            if let Some(light) = node.light() {
                self.add_light(&light, &node_name, world);
            }
            let children: Vec<_> = node.children().collect();
            stack.extend(children.into_iter().rev().map(|c| (c, world, depth + 1)));
        }
        Ok(placements)
    }

    pub(super) fn add_camera(&mut self, camera: &gltf::Camera<'_>, world: DMat4) {
        let name = camera
            .name()
            .map(str::to_string)
            .unwrap_or_else(|| format!("camera #{}", camera.index()));
        let (projection, znear) = match camera.projection() {
            gltf::camera::Projection::Perspective(p) => (
                Projection::Perspective {
                    yfov: p.yfov(),
                    aspect: p.aspect_ratio(),
                },
                p.znear(),
            ),
            gltf::camera::Projection::Orthographic(o) => (
                Projection::Orthographic {
                    xmag: o.xmag(),
                    ymag: o.ymag(),
                },
                o.znear(),
            ),
        };
        self.scene.cameras.push(Camera {
            name,
            transform: world.as_mat4(),
            projection,
            znear,
            lens: None,
        });
    }

    pub(super) fn add_light(
        &mut self,
        light: &gltf::khr_lights_punctual::Light<'_>,
        node_name: &str,
        world: DMat4,
    ) {
        use gltf::khr_lights_punctual::Kind;
        let power = Vec3::from(light.color()) * light.intensity();
        let position = world.transform_point3(DVec3::ZERO).as_vec3();
        let direction = world
            .transform_vector3(DVec3::NEG_Z)
            .normalize_or_zero()
            .as_vec3();
        let needs_direction = !matches!(light.kind(), Kind::Point);
        if needs_direction && direction == Vec3::ZERO {
            self.warn(format!(
                "{}: light on node {node_name} has a degenerate orientation; skipped",
                self.path.display()
            ));
            return;
        }
        let light = match light.kind() {
            Kind::Directional => Light::Directional {
                direction,
                irradiance: power,
            },
            Kind::Point => Light::Point {
                position,
                intensity: power,
            },
            Kind::Spot {
                inner_cone_angle,
                outer_cone_angle,
            } => Light::Spot {
                position,
                direction,
                intensity: power,
                inner_cone: inner_cone_angle,
                outer_cone: outer_cone_angle,
            },
        };
        self.scene.lights.push(light);
    }
}

/// A node's local transform in f64. Rotations are renormalised: exporters write
/// quaternions rounded to a few digits.
/// The node's local transform, with what an animation sets at the requested time in
/// place of the file's values (glTF animates only nodes with decomposed transforms).
fn local_matrix(node: &gltf::Node<'_>, posed: Option<&NodePose>) -> DMat4 {
    match node.transform() {
        gltf::scene::Transform::Matrix { matrix } => {
            DMat4::from_cols_array_2d(&matrix.map(|col| col.map(f64::from)))
        }
        gltf::scene::Transform::Decomposed {
            translation,
            rotation,
            scale,
        } => {
            let [x, y, z, w] = rotation.map(f64::from);
            let pose = posed.cloned().unwrap_or_default();
            DMat4::from_scale_rotation_translation(
                pose.scale.unwrap_or(DVec3::from(scale.map(f64::from))),
                pose.rotation
                    .unwrap_or(DQuat::from_xyzw(x, y, z, w))
                    .normalize(),
                pose.translation
                    .unwrap_or(DVec3::from(translation.map(f64::from))),
            )
        }
    }
}

/// The node's morph weights: the animation's at the requested time, else the node's own
/// (either overrides the mesh's).
fn node_weights(node: &gltf::Node<'_>, posed: Option<&NodePose>) -> Option<Vec<f32>> {
    posed
        .and_then(|p| p.weights.clone())
        .or_else(|| node.weights().map(<[f32]>::to_vec))
}

//! Linear blend skinning (glTF 2.0 §3.7.3): each vertex of a skinned mesh is moved by the
//! weighted sum of its joints' matrices, `world(joint) · inverseBindMatrix(joint)`, and
//! the mesh node's own transform is ignored, as the specification asks. With the joints
//! where the file puts them this is the pose the file shows; with an animation sampled at
//! a time ([`crate::animation`]) the joints move and the skin follows.
//!
//! The loader does this once per skinned instance, in f64, and hands the result on as
//! world-space triangles, so the rest of dray never sees a skin.

use glam::{DMat3, DMat4, Vec3, Vec4};

/// A vertex's joints and weights: up to 8 influences (`JOINTS_0`/`WEIGHTS_0` and
/// `JOINTS_1`/`WEIGHTS_1`).
pub type Influences = Vec<(u32, f32)>;

/// Why a primitive cannot be skinned; the loader names the mesh and primitive.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum SkinError {
    #[error("vertex {vertex} uses joint {joint}, but the skin has {joints} joints")]
    JointOutOfRange {
        vertex: usize,
        joint: u32,
        joints: usize,
    },
    #[error("vertex {vertex} has a weight that is not a finite number >= 0")]
    BadWeight { vertex: usize },
}

/// Move `positions`, `normals` and `tangents` (tangents keep their handedness sign) by
/// the blend of `joint_matrices` each vertex's `influences` give. Weights are used as
/// the file stores them (the specification asks exporters to normalise them); a vertex
/// whose weights sum to 0 stays where it is.
pub fn skin(
    joint_matrices: &[DMat4],
    influences: &[Influences],
    positions: &mut [Vec3],
    mut normals: Option<&mut [Vec3]>,
    mut tangents: Option<&mut [Vec4]>,
) -> Result<(), SkinError> {
    for (v, inf) in influences.iter().enumerate() {
        let mut m = DMat4::ZERO;
        let mut total = 0.0f64;
        for &(joint, weight) in inf {
            if !(weight.is_finite() && weight >= 0.0) {
                return Err(SkinError::BadWeight { vertex: v });
            }
            if weight == 0.0 {
                continue;
            }
            let j = joint_matrices
                .get(joint as usize)
                .ok_or(SkinError::JointOutOfRange {
                    vertex: v,
                    joint,
                    joints: joint_matrices.len(),
                })?;
            m += *j * f64::from(weight);
            total += f64::from(weight);
        }
        if total == 0.0 {
            continue;
        }
        let linear = DMat3::from_mat4(m);
        if let Some(p) = positions.get_mut(v) {
            *p = m.transform_point3(p.as_dvec3()).as_vec3();
        }
        if let Some(n) = normals.as_deref_mut().and_then(|ns| ns.get_mut(v)) {
            let normal_matrix = linear.inverse().transpose();
            *n = (normal_matrix * n.as_dvec3()).normalize_or_zero().as_vec3();
        }
        if let Some(t) = tangents.as_deref_mut().and_then(|ts| ts.get_mut(v)) {
            let xyz = (linear * t.truncate().as_dvec3())
                .normalize_or_zero()
                .as_vec3();
            *t = xyz.extend(t.w);
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DVec3;

    #[test]
    fn a_vertex_follows_its_joints_in_proportion_to_their_weights() {
        let joints = [
            DMat4::IDENTITY,
            DMat4::from_translation(DVec3::new(2.0, 0.0, 0.0)),
        ];
        let influences = vec![
            vec![(0, 1.0)],
            vec![(1, 1.0)],
            vec![(0, 0.5), (1, 0.5)],
            vec![],
        ];
        let mut p = vec![Vec3::Y; 4];
        skin(&joints, &influences, &mut p, None, None).unwrap();
        assert_eq!(
            p,
            vec![
                Vec3::Y,
                Vec3::new(2.0, 1.0, 0.0),
                Vec3::new(1.0, 1.0, 0.0),
                Vec3::Y
            ]
        );
    }

    #[test]
    fn normals_and_tangents_turn_with_the_joint() {
        let joints = [DMat4::from_rotation_z(std::f64::consts::FRAC_PI_2)];
        let mut p = vec![Vec3::X];
        let mut n = vec![Vec3::X];
        let mut t = vec![Vec4::new(0.0, 1.0, 0.0, -1.0)];
        skin(
            &joints,
            &[vec![(0, 1.0)]],
            &mut p,
            Some(&mut n),
            Some(&mut t),
        )
        .unwrap();
        assert!((p[0] - Vec3::Y).length() < 1e-6, "{p:?}");
        assert!((n[0] - Vec3::Y).length() < 1e-6, "{n:?}");
        assert!(
            (t[0] - Vec4::new(-1.0, 0.0, 0.0, -1.0)).length() < 1e-6,
            "{t:?}"
        );
    }

    #[test]
    fn bad_joints_and_weights_are_refused() {
        let mut p = vec![Vec3::ZERO];
        assert_eq!(
            skin(&[DMat4::IDENTITY], &[vec![(3, 1.0)]], &mut p, None, None),
            Err(SkinError::JointOutOfRange {
                vertex: 0,
                joint: 3,
                joints: 1
            })
        );
        assert_eq!(
            skin(
                &[DMat4::IDENTITY],
                &[vec![(0, f32::NAN)]],
                &mut p,
                None,
                None
            ),
            Err(SkinError::BadWeight { vertex: 0 })
        );
    }
}

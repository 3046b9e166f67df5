//! Small mesh builders the generators share: quads, boxes and icospheres.
//!
//! They produce plain indexed triangle lists ([`MeshData`]) in object space; generators
//! place them with [`MeshData::transformed`] and emit them through the validation gate.

use std::collections::HashMap;

use glam::{Affine3A, Mat3, Vec3};

/// An indexed triangle list with optional per-vertex normals (empty = none, so shading
/// uses the geometric normal).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct MeshData {
    pub positions: Vec<Vec3>,
    pub normals: Vec<Vec3>,
    /// Three indices per triangle.
    pub indices: Vec<u32>,
}

impl MeshData {
    pub fn triangle_count(&self) -> usize {
        self.indices.len() / 3
    }

    /// A copy moved by `xf`; normals are carried by the inverse transpose so non-uniform
    /// scales keep them perpendicular to the surface.
    pub fn transformed(&self, xf: Affine3A) -> MeshData {
        let normal_matrix = Mat3::from(xf.matrix3).inverse().transpose();
        MeshData {
            positions: self
                .positions
                .iter()
                .map(|&p| xf.transform_point3(p))
                .collect(),
            normals: self
                .normals
                .iter()
                .map(|&n| (normal_matrix * n).normalize_or_zero())
                .collect(),
            indices: self.indices.clone(),
        }
    }

    /// Append `other`, offsetting its indices. Both must agree on having normals.
    pub fn append(&mut self, other: &MeshData) {
        let base = self.positions.len() as u32;
        self.positions.extend_from_slice(&other.positions);
        self.normals.extend_from_slice(&other.normals);
        self.indices.extend(other.indices.iter().map(|i| i + base));
    }
}

/// A flat quad `a b c d` (in order around its boundary), split along `a c` and wound so
/// its geometric normal points along `facing`. Callers give the facing instead of relying
/// on the corner order because measured data (the Cornell box) is not consistently wound.
pub fn quad(corners: [Vec3; 4], facing: Vec3) -> MeshData {
    let [a, b, c, d] = corners;
    let mut normal = ((b - a).cross(c - a) + (c - a).cross(d - a)).normalize_or_zero();
    let indices = if normal.dot(facing) < 0.0 {
        normal = -normal;
        vec![0, 2, 1, 0, 3, 2]
    } else {
        vec![0, 1, 2, 0, 2, 3]
    };
    MeshData {
        positions: corners.to_vec(),
        normals: vec![normal; 4],
        indices,
    }
}

/// An axis-aligned box with outward flat normals; `bottom: false` leaves out the -Y face
/// (buildings standing on the ground never show it, and it would only cost triangles).
pub fn cuboid(min: Vec3, max: Vec3, bottom: bool) -> MeshData {
    let corner = |x: bool, y: bool, z: bool| {
        Vec3::new(
            if x { max.x } else { min.x },
            if y { max.y } else { min.y },
            if z { max.z } else { min.z },
        )
    };
    let (f, t) = (false, true);
    let mut faces = vec![
        (
            [
                corner(t, f, f),
                corner(t, t, f),
                corner(t, t, t),
                corner(t, f, t),
            ],
            Vec3::X,
        ),
        (
            [
                corner(f, f, f),
                corner(f, f, t),
                corner(f, t, t),
                corner(f, t, f),
            ],
            Vec3::NEG_X,
        ),
        (
            [
                corner(f, t, f),
                corner(f, t, t),
                corner(t, t, t),
                corner(t, t, f),
            ],
            Vec3::Y,
        ),
        (
            [
                corner(f, f, t),
                corner(t, f, t),
                corner(t, t, t),
                corner(f, t, t),
            ],
            Vec3::Z,
        ),
        (
            [
                corner(f, f, f),
                corner(f, t, f),
                corner(t, t, f),
                corner(t, f, f),
            ],
            Vec3::NEG_Z,
        ),
    ];
    if bottom {
        faces.push((
            [
                corner(f, f, f),
                corner(t, f, f),
                corner(t, f, t),
                corner(f, f, t),
            ],
            Vec3::NEG_Y,
        ));
    }
    let mut mesh = MeshData::default();
    for (corners, facing) in faces {
        mesh.append(&quad(corners, facing));
    }
    mesh
}

/// A unit icosphere: the icosahedron with each triangle split into four `subdivisions`
/// times (20 * 4^n triangles; n = 2 gives 320), vertices pushed onto the sphere and shared
/// between neighbouring triangles, normals equal to positions. Preferred over a UV sphere
/// because its triangles are nearly uniform, with no slivers at the poles.
pub fn icosphere(subdivisions: u32) -> MeshData {
    let t = (1.0 + 5f32.sqrt()) * 0.5;
    let mut positions: Vec<Vec3> = [
        (-1.0, t, 0.0),
        (1.0, t, 0.0),
        (-1.0, -t, 0.0),
        (1.0, -t, 0.0),
        (0.0, -1.0, t),
        (0.0, 1.0, t),
        (0.0, -1.0, -t),
        (0.0, 1.0, -t),
        (t, 0.0, -1.0),
        (t, 0.0, 1.0),
        (-t, 0.0, -1.0),
        (-t, 0.0, 1.0),
    ]
    .iter()
    .map(|&(x, y, z)| Vec3::new(x, y, z).normalize())
    .collect();
    let mut faces: Vec<[u32; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..subdivisions {
        let mut midpoints: HashMap<(u32, u32), u32> = HashMap::new();
        let mut midpoint = |a: u32, b: u32, positions: &mut Vec<Vec3>| -> u32 {
            let key = (a.min(b), a.max(b));
            *midpoints.entry(key).or_insert_with(|| {
                let p = (positions[a as usize] + positions[b as usize]).normalize();
                positions.push(p);
                (positions.len() - 1) as u32
            })
        };
        let mut next = Vec::with_capacity(faces.len() * 4);
        for &[a, b, c] in &faces {
            let ab = midpoint(a, b, &mut positions);
            let bc = midpoint(b, c, &mut positions);
            let ca = midpoint(c, a, &mut positions);
            next.extend_from_slice(&[[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]);
        }
        faces = next;
    }
    MeshData {
        normals: positions.clone(),
        positions,
        indices: faces.into_iter().flatten().collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn outward(mesh: &MeshData, center: Vec3) -> bool {
        mesh.indices.chunks_exact(3).all(|t| {
            let [a, b, c] = [0, 1, 2].map(|k| mesh.positions[t[k] as usize]);
            let n = (b - a).cross(c - a);
            n.dot((a + b + c) / 3.0 - center) > 0.0
        })
    }

    #[test]
    fn icosphere_counts_and_winding() {
        let s = icosphere(2);
        assert_eq!(s.triangle_count(), 320);
        assert_eq!(s.positions.len(), 162);
        assert!(outward(&s, Vec3::ZERO));
    }

    #[test]
    fn cuboid_faces_point_out() {
        let b = cuboid(Vec3::ZERO, Vec3::new(1.0, 2.0, 3.0), true);
        assert_eq!(b.triangle_count(), 12);
        assert!(outward(&b, Vec3::new(0.5, 1.0, 1.5)));
        assert_eq!(cuboid(Vec3::ZERO, Vec3::ONE, false).triangle_count(), 10);
    }
}

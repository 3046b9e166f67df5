//! MikkTSpace tangents for primitives that have a normal map but no `TANGENT` attribute.
//!
//! The glTF specification says a client should generate MikkTSpace tangents then, since
//! that is the frame the normal map was baked in (Blender, Substance and xNormal all bake
//! in it); any other frame bends the map's normals the wrong way. The generation is done
//! by `bevy_mikktspace`, a port of the reference implementation that gives its bits.
//!
//! MikkTSpace gives a tangent per triangle corner. Corners that share a vertex nearly
//! always agree; where they do not (mirrored UVs meeting at a shared vertex, for one),
//! the vertex is split, so every corner keeps the tangent MikkTSpace gave it. A corner
//! MikkTSpace gives nothing (a triangle with degenerate UVs and no neighbour to borrow
//! from) takes its vertex's tangent from the other corners there, if any.

use bevy_mikktspace::{Geometry, TangentSpace, generate_tangents};
use glam::{Vec2, Vec3, Vec4};

/// One primitive as MikkTSpace reads it, and the tangents it writes back per corner.
struct Corners<'a> {
    positions: &'a [Vec3],
    normals: &'a [Vec3],
    uvs: &'a [Vec2],
    indices: &'a [u32],
    /// One per index; zero where MikkTSpace had nothing to give (a degenerate triangle
    /// with no usable neighbour), which shading reads as "no tangent".
    tangents: Vec<Vec4>,
}

impl Corners<'_> {
    fn vertex(&self, face: usize, vert: usize) -> usize {
        self.indices.get(face * 3 + vert).map_or(0, |&i| i as usize)
    }
}

impl Geometry for Corners<'_> {
    fn num_faces(&self) -> usize {
        self.indices.len() / 3
    }

    fn num_vertices_of_face(&self, _face: usize) -> usize {
        3
    }

    fn position(&self, face: usize, vert: usize) -> [f32; 3] {
        let v = self.vertex(face, vert);
        self.positions
            .get(v)
            .copied()
            .unwrap_or_default()
            .to_array()
    }

    fn normal(&self, face: usize, vert: usize) -> [f32; 3] {
        let v = self.vertex(face, vert);
        self.normals.get(v).copied().unwrap_or_default().to_array()
    }

    fn tex_coord(&self, face: usize, vert: usize) -> [f32; 2] {
        let v = self.vertex(face, vert);
        self.uvs.get(v).copied().unwrap_or_default().to_array()
    }

    fn set_tangent(&mut self, tangent: Option<TangentSpace>, face: usize, vert: usize) {
        if let Some(slot) = self.tangents.get_mut(face * 3 + vert) {
            *slot = tangent.map_or(Vec4::ZERO, |t| Vec4::from(t.tangent_encoded()));
        }
    }
}

/// A vertex array grows by the vertices [`generate`] split off: `sources[k]` is the
/// vertex that new vertex `len + k` copies.
#[derive(Debug, Default, PartialEq)]
pub struct Split {
    pub sources: Vec<u32>,
}

impl Split {
    /// Append the copies to one attribute array.
    pub fn apply<T: Copy>(&self, values: &mut Vec<T>) {
        let copies: Vec<T> = self
            .sources
            .iter()
            .filter_map(|&s| values.get(s as usize).copied())
            .collect();
        values.extend(copies);
    }
}

/// MikkTSpace tangents for the triangle list `indices` over `positions`, `normals` and
/// `uvs` (one of each per vertex; non-finite values are read as zero by the caller's
/// cleaning). Returns one tangent per vertex (xyz, w = bitangent sign, as glTF's
/// `TANGENT`) after splitting vertices whose corners disagree: `indices` is rewritten to
/// point at the copies, and the caller applies the returned [`Split`] to every other
/// attribute array so they stay one per vertex.
pub fn generate(
    positions: &[Vec3],
    normals: &[Vec3],
    uvs: &[Vec2],
    indices: &mut [u32],
) -> (Vec<Vec4>, Split) {
    let mut corners = Corners {
        positions,
        normals,
        uvs,
        indices,
        tangents: vec![Vec4::ZERO; indices.len()],
    };
    // The crate's error type has no variants: generation cannot fail.
    let _ = generate_tangents(&mut corners);
    let per_corner = corners.tangents;

    let n = positions.len();
    let mut tangents: Vec<Option<Vec4>> = vec![None; n];
    let mut split = Split::default();
    // Copies made so far per source vertex, so corners that agree with a copy reuse it.
    let mut copies: Vec<(u32, u32)> = Vec::new();
    for (slot, &t) in indices.iter_mut().zip(&per_corner) {
        if t == Vec4::ZERO {
            // No opinion (a degenerate UV triangle MikkTSpace could not place): the
            // corner takes whatever tangent its vertex gets from its other corners.
            continue;
        }
        let v = *slot as usize;
        match tangents.get(v).copied().flatten() {
            None => {
                if let Some(s) = tangents.get_mut(v) {
                    *s = Some(t);
                }
            }
            Some(have) if have == t => {}
            Some(_) => {
                let existing = copies
                    .iter()
                    .find(|&&(src, copy)| {
                        src as usize == v
                            && tangents.get(copy as usize).copied().flatten() == Some(t)
                    })
                    .map(|&(_, copy)| copy);
                let copy = match existing {
                    Some(c) => c,
                    None => {
                        let c = (n + split.sources.len()) as u32;
                        split.sources.push(*slot);
                        tangents.push(Some(t));
                        copies.push((*slot, c));
                        c
                    }
                };
                *slot = copy;
            }
        }
    }
    let tangents = tangents
        .into_iter()
        .map(|t| t.unwrap_or(Vec4::ZERO))
        .collect();
    (tangents, split)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A unit quad in the XY plane facing +Z, UVs along X and Y.
    fn quad() -> (Vec<Vec3>, Vec<Vec3>, Vec<Vec2>, Vec<u32>) {
        let p = vec![
            Vec3::new(0.0, 0.0, 0.0),
            Vec3::new(1.0, 0.0, 0.0),
            Vec3::new(1.0, 1.0, 0.0),
            Vec3::new(0.0, 1.0, 0.0),
        ];
        let n = vec![Vec3::Z; 4];
        let uv = vec![
            Vec2::new(0.0, 0.0),
            Vec2::new(1.0, 0.0),
            Vec2::new(1.0, 1.0),
            Vec2::new(0.0, 1.0),
        ];
        (p, n, uv, vec![0, 1, 2, 0, 2, 3])
    }

    #[test]
    fn tangent_follows_u_and_sign_follows_the_uv_orientation() {
        let (p, n, uv, mut idx) = quad();
        let (t, split) = generate(&p, &n, &uv, &mut idx);
        assert!(split.sources.is_empty());
        assert_eq!(idx, [0, 1, 2, 0, 2, 3]);
        for t in &t {
            assert!((t.truncate() - Vec3::X).length() < 1e-5, "{t}");
            assert_eq!(t.w, 1.0);
        }
        // Mirror V: the bitangent flips, so w does.
        let flipped: Vec<Vec2> = uv.iter().map(|u| Vec2::new(u.x, 1.0 - u.y)).collect();
        let (t, _) = generate(&p, &n, &flipped, &mut idx);
        assert!(t.iter().all(|t| t.w == -1.0), "{t:?}");
    }

    #[test]
    fn vertices_whose_corners_disagree_are_split() {
        // Two triangles sharing edge 0-2, the second with U mirrored: vertex 0 and 2 get
        // two different tangents, one per side.
        let p = vec![
            Vec3::new(0.0, 0.0, 0.0),
            Vec3::new(1.0, 0.0, 0.0),
            Vec3::new(0.0, 1.0, 0.0),
            Vec3::new(-1.0, 0.0, 0.0),
        ];
        let n = vec![Vec3::Z; 4];
        let uv = vec![
            Vec2::new(0.0, 0.0),
            Vec2::new(1.0, 0.0),
            Vec2::new(0.0, 1.0),
            Vec2::new(1.0, 0.0),
        ];
        let mut idx = vec![0, 1, 2, 0, 2, 3];
        let (t, split) = generate(&p, &n, &uv, &mut idx);
        assert_eq!(split.sources, [0, 2]);
        assert_eq!(idx, [0, 1, 2, 4, 5, 3]);
        assert_eq!(t.len(), 6);
        assert!(
            t[0].truncate().dot(Vec3::X) > 0.99 && t[0].w == 1.0,
            "{t:?}"
        );
        assert!(t[4].truncate().dot(Vec3::NEG_X) > 0.99, "{t:?}");
        let mut pos = p.clone();
        split.apply(&mut pos);
        assert_eq!(pos[4], p[0]);
        assert_eq!(pos[5], p[2]);
    }
}

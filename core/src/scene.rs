//! The scene every actor shares: world-space triangles with per-vertex attributes,
//! materials, textures, punctual lights and cameras.
//!
//! Loaders flatten the node hierarchy into one world-space [`Mesh`]; instancing is
//! expanded. Attributes a primitive lacks are stored as zero vectors, which shading reads
//! as "absent" (zero normal: use the geometric normal; zero tangent: build a frame).

use glam::{Vec2, Vec3, Vec4};

use crate::camera::Camera;
use crate::light::Light;
use crate::material::Material;
use crate::texture::Texture;

/// Indexed triangles in world space.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mesh {
    pub positions: Vec<Vec3>,
    /// Per-vertex shading normals; zero where the source had none.
    pub normals: Vec<Vec3>,
    /// Per-vertex tangents (xyz, w = bitangent sign); zero where the source had none.
    pub tangents: Vec<Vec4>,
    /// Per-vertex texture coordinates: the first UV set its triangle's material reads
    /// (`TEXCOORD_0` unless its textures name another); zero where the source had none.
    pub uvs: Vec<Vec2>,
    /// Per-vertex second UV set, for the triangles whose material's texture slots name
    /// two sets ([`crate::material::TexRef::second_uv`]); zero elsewhere. Empty when no
    /// vertex has a nonzero one, so scenes whose materials read one set each (nearly
    /// all) spend no memory on it: empty means zero everywhere.
    pub uvs2: Vec<Vec2>,
    /// Per-vertex linear RGBA colour (glTF `COLOR_0`), multiplying the base colour; white
    /// where the source had none. Empty when no vertex has one, so scenes without vertex
    /// colours (nearly all) spend no memory on them: empty means white everywhere.
    pub colors: Vec<Vec4>,
    pub indices: Vec<[u32; 3]>,
    /// Per-triangle index into `Scene::materials`.
    pub material: Vec<u32>,
}

impl Mesh {
    pub fn triangle_count(&self) -> usize {
        self.indices.len()
    }

    /// Append vertices with no attributes other than position and return the index of the
    /// first one.
    pub fn push_vertices(&mut self, positions: &[Vec3]) -> u32 {
        let base = self.positions.len() as u32;
        self.positions.extend_from_slice(positions);
        self.normals.resize(self.positions.len(), Vec3::ZERO);
        self.tangents.resize(self.positions.len(), Vec4::ZERO);
        self.uvs.resize(self.positions.len(), Vec2::ZERO);
        if !self.uvs2.is_empty() {
            self.uvs2.resize(self.positions.len(), Vec2::ZERO);
        }
        if !self.colors.is_empty() {
            self.colors.resize(self.positions.len(), Vec4::ONE);
        }
        base
    }

    /// Append per-vertex colours for the vertices from `first` on (`colors` holds one per
    /// vertex from `first`, or is `None` for white), keeping [`Mesh::colors`] empty while
    /// every vertex is white. Call after the positions are appended.
    pub fn extend_colors(&mut self, first: usize, colors: Option<&[Vec4]>) {
        match colors {
            Some(cs) if self.colors.is_empty() && cs.iter().all(|&c| c == Vec4::ONE) => {}
            Some(cs) => {
                self.colors.resize(first, Vec4::ONE);
                self.colors.extend_from_slice(cs);
            }
            None if self.colors.is_empty() => {}
            None => self.colors.resize(self.positions.len(), Vec4::ONE),
        }
    }

    /// Append second-set UVs for the vertices from `first` on (`uvs2` holds one per
    /// vertex from `first`, or is `None` for none), keeping [`Mesh::uvs2`] empty while
    /// every one is zero (bit for bit: `-0.0` is kept). Call after the positions are
    /// appended.
    pub fn extend_uvs2(&mut self, first: usize, uvs2: Option<&[Vec2]>) {
        let zero = |u: &Vec2| u.x.to_bits() == 0 && u.y.to_bits() == 0;
        match uvs2 {
            Some(us) if self.uvs2.is_empty() && us.iter().all(zero) => {}
            Some(us) => {
                self.uvs2.resize(first, Vec2::ZERO);
                self.uvs2.extend_from_slice(us);
            }
            None if self.uvs2.is_empty() => {}
            None => self.uvs2.resize(self.positions.len(), Vec2::ZERO),
        }
    }

    /// The three corner positions of triangle `tri`.
    #[inline]
    pub fn corners(&self, tri: usize) -> [Vec3; 3] {
        let [a, b, c] = self.indices[tri];
        [
            self.positions[a as usize],
            self.positions[b as usize],
            self.positions[c as usize],
        ]
    }

    /// Axis-aligned bounds of all vertices referenced by triangles.
    pub fn bounds(&self) -> (Vec3, Vec3) {
        let mut lo = Vec3::splat(f32::INFINITY);
        let mut hi = Vec3::splat(f32::NEG_INFINITY);
        for tri in &self.indices {
            for &i in tri {
                let p = self.positions[i as usize];
                lo = lo.min(p);
                hi = hi.max(p);
            }
        }
        if lo.x > hi.x {
            (Vec3::ZERO, Vec3::ZERO)
        } else {
            (lo, hi)
        }
    }

    /// Append another mesh, offsetting its material indices by `material_offset`.
    pub fn append(&mut self, other: &Mesh, material_offset: u32) {
        let base = self.positions.len() as u32;
        self.positions.extend_from_slice(&other.positions);
        self.normals.extend_from_slice(&other.normals);
        self.tangents.extend_from_slice(&other.tangents);
        self.uvs.extend_from_slice(&other.uvs);
        let uvs2 = (!other.uvs2.is_empty()).then_some(other.uvs2.as_slice());
        self.extend_uvs2(base as usize, uvs2);
        let colors = (!other.colors.is_empty()).then_some(other.colors.as_slice());
        self.extend_colors(base as usize, colors);
        self.indices
            .extend(other.indices.iter().map(|t| t.map(|i| i + base)));
        self.material
            .extend(other.material.iter().map(|m| m + material_offset));
    }
}

/// Counts a loader reports about what it read.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct LoadStats {
    /// Triangles dropped because they had zero area (or repeated indices).
    pub degenerate_triangles: u64,
    /// Human-readable warnings (ignored optional extensions, unsupported features).
    pub warnings: Vec<String>,
}

#[derive(Clone, Debug, Default, PartialEq)]
pub struct Scene {
    pub name: String,
    pub mesh: Mesh,
    pub materials: Vec<Material>,
    pub textures: Vec<Texture>,
    pub lights: Vec<Light>,
    pub cameras: Vec<Camera>,
    /// Constant environment radiance the scene asks for, if any. `None` lets the renderer
    /// choose its default (black with lights or emitters, a constant sky otherwise).
    pub environment: Option<Vec3>,
    pub stats: LoadStats,
}

impl Scene {
    pub fn bounds(&self) -> (Vec3, Vec3) {
        self.mesh.bounds()
    }

    /// Translate every vertex, light and camera by `offset` (in f32, as a scene authored
    /// far from the origin would be stored).
    pub fn translate(&mut self, offset: Vec3) {
        for p in &mut self.mesh.positions {
            *p += offset;
        }
        for l in &mut self.lights {
            match l {
                Light::Point { position, .. } | Light::Spot { position, .. } => *position += offset,
                Light::Directional { .. } => {}
            }
        }
        for c in &mut self.cameras {
            c.transform = glam::Mat4::from_translation(offset) * c.transform;
        }
    }
}

/// Why a scene has no camera to give.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CameraChoiceError {
    #[error("{which:?} not found in the scene (cameras: {known})")]
    NotFound { which: String, known: String },
    #[error("{name:?} is malformed (non-finite or degenerate transform or projection)")]
    Malformed { name: String },
}

impl Scene {
    /// The camera `which` names (an index or a name), the scene's first, or one framing
    /// `bounds` when the scene has none: the one choice `dray render` and the coordinator
    /// make, so a job renders through the same camera wherever it runs.
    pub fn choose_camera(
        &self,
        which: Option<&str>,
        bounds: (Vec3, Vec3),
        aspect: f32,
    ) -> Result<Camera, CameraChoiceError> {
        let cam = match which {
            Some(w) => {
                let by_index = w.parse::<usize>().ok().and_then(|i| self.cameras.get(i));
                match by_index.or_else(|| self.cameras.iter().find(|c| c.name == w)) {
                    Some(c) => c.clone(),
                    None => {
                        let names: Vec<String> = self
                            .cameras
                            .iter()
                            .enumerate()
                            .map(|(i, c)| format!("{i}:{}", c.name))
                            .collect();
                        return Err(CameraChoiceError::NotFound {
                            which: w.to_string(),
                            known: if names.is_empty() {
                                "none".to_string()
                            } else {
                                names.join(", ")
                            },
                        });
                    }
                }
            }
            None => match self.cameras.first() {
                Some(c) => c.clone(),
                None => Camera::framing(bounds.0, bounds.1, aspect),
            },
        };
        if !cam.is_valid() {
            return Err(CameraChoiceError::Malformed { name: cam.name });
        }
        Ok(cam)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The second UV set costs nothing until a vertex has a nonzero one (a `-0.0` counts),
    /// and from then on has one entry per vertex, zero where none was given.
    #[test]
    fn a_second_uv_set_is_stored_only_when_used() {
        let mut m = Mesh::default();
        m.push_vertices(&[Vec3::ZERO, Vec3::X]);
        m.extend_uvs2(0, Some(&[Vec2::ZERO, Vec2::ZERO]));
        m.extend_uvs2(2, None);
        assert!(m.uvs2.is_empty());
        m.push_vertices(&[Vec3::Y]);
        m.extend_uvs2(2, Some(&[Vec2::new(-0.0, 0.0)]));
        assert_eq!(m.uvs2.len(), 3);
        assert_eq!(m.uvs2[2].x.to_bits(), (-0.0f32).to_bits());
        m.push_vertices(&[Vec3::Z]);
        assert_eq!(m.uvs2.len(), 4);
        let mut whole = Mesh::default();
        whole.push_vertices(&[Vec3::ONE]);
        whole.append(&m, 0);
        assert_eq!(whole.uvs2.len(), 5);
        assert_eq!(whole.uvs2[0], Vec2::ZERO);
        let mut plain = Mesh::default();
        plain.push_vertices(&[Vec3::ONE]);
        plain.append(&Mesh::default(), 0);
        assert!(plain.uvs2.is_empty());
    }
}

//! The one gate every loader pushes primitives through: it checks positions and indices,
//! drops degenerate triangles (counting them) and appends the rest to the scene mesh.

use std::path::Path;

use dray_core::scene::{LoadStats, Mesh};
use glam::{Vec2, Vec3, Vec4};

use crate::error::{Result, SceneError};

/// Where a primitive came from, for error messages.
#[derive(Clone, Copy, Debug)]
pub struct Origin<'a> {
    pub path: &'a Path,
    pub mesh: &'a str,
    pub primitive: usize,
}

impl Origin<'_> {
    pub fn error(&self, message: impl Into<String>) -> SceneError {
        SceneError::Primitive {
            path: self.path.to_path_buf(),
            mesh: self.mesh.to_string(),
            primitive: self.primitive,
            message: message.into(),
        }
    }
}

/// One primitive's data, already in world space. Optional attributes, when present, must
/// have one entry per position.
pub struct Primitive<'a> {
    pub positions: &'a [Vec3],
    pub normals: Option<&'a [Vec3]>,
    pub tangents: Option<&'a [Vec4]>,
    pub uvs: Option<&'a [Vec2]>,
    /// The second UV set, for primitives whose material's textures read two
    /// ([`dray_core::material::TexRef::second_uv`]); `None` for all others.
    pub uvs2: Option<&'a [Vec2]>,
    /// The source's numbers of the two sets (`TEXCOORD_n`), for messages.
    pub uv_sets: [u32; 2],
    /// Linear RGBA vertex colours (glTF `COLOR_0`; RGB sources with alpha 1).
    pub colors: Option<&'a [Vec4]>,
    /// Triangle-list indices (three per triangle).
    pub indices: &'a [u32],
    pub material: u32,
}

/// Validate `prim` and append it to `mesh`. Non-finite normals, tangents and UVs are
/// replaced by zero ("absent"); non-finite positions and bad indices are errors.
pub fn add_primitive(
    mesh: &mut Mesh,
    stats: &mut LoadStats,
    origin: Origin<'_>,
    prim: Primitive<'_>,
) -> Result<()> {
    crate::cancel::check()?;
    let n = prim.positions.len();
    check_positions(origin, prim.positions)?;
    let check_len = |name: &str, len: Option<usize>| -> Result<()> {
        match len {
            Some(l) if l != n => Err(origin.error(format!(
                "attribute {name} has {l} entries but POSITION has {n}"
            ))),
            _ => Ok(()),
        }
    };
    check_len("NORMAL", prim.normals.map(<[_]>::len))?;
    check_len("TANGENT", prim.tangents.map(<[_]>::len))?;
    let [set, set2] = prim.uv_sets;
    check_len(&format!("TEXCOORD_{set}"), prim.uvs.map(<[_]>::len))?;
    check_len(&format!("TEXCOORD_{set2}"), prim.uvs2.map(<[_]>::len))?;
    check_len("COLOR_0", prim.colors.map(<[_]>::len))?;
    if !prim.indices.len().is_multiple_of(3) {
        return Err(origin.error(format!(
            "index count {} is not a multiple of 3",
            prim.indices.len()
        )));
    }
    if let Some((i, &v)) = prim
        .indices
        .iter()
        .enumerate()
        .find(|&(_, &v)| v as usize >= n)
    {
        return Err(origin.error(format!(
            "index {i} refers to vertex {v} but there are only {n} vertices"
        )));
    }
    if mesh.positions.len() + n > u32::MAX as usize {
        return Err(origin.error("scene exceeds 4 billion vertices"));
    }

    let base = mesh.positions.len() as u32;
    mesh.positions.extend_from_slice(prim.positions);
    match prim.normals {
        Some(ns) => mesh.normals.extend(ns.iter().map(|&v| clean_normal(v))),
        None => mesh.normals.resize(mesh.positions.len(), Vec3::ZERO),
    }
    match prim.tangents {
        Some(ts) => mesh.tangents.extend(
            ts.iter()
                .map(|&v| if v.is_finite() { v } else { Vec4::ZERO }),
        ),
        None => mesh.tangents.resize(mesh.positions.len(), Vec4::ZERO),
    }
    match prim.uvs {
        Some(us) => mesh.uvs.extend(us.iter().map(|&v| clean_uv(v))),
        None => mesh.uvs.resize(mesh.positions.len(), Vec2::ZERO),
    }
    let uvs2: Option<Vec<Vec2>> = prim
        .uvs2
        .map(|us| us.iter().map(|&v| clean_uv(v)).collect());
    mesh.extend_uvs2(base as usize, uvs2.as_deref());
    let colors: Option<Vec<Vec4>> = prim
        .colors
        .map(|cs| cs.iter().map(|&c| clean_color(c)).collect());
    mesh.extend_colors(base as usize, colors.as_deref());
    for tri in prim.indices.chunks_exact(3) {
        let [a, b, c] = [tri[0], tri[1], tri[2]];
        let corners = [
            prim.positions[a as usize],
            prim.positions[b as usize],
            prim.positions[c as usize],
        ];
        if is_degenerate([a, b, c], corners) {
            stats.degenerate_triangles += 1;
            continue;
        }
        mesh.indices.push([a + base, b + base, c + base]);
        mesh.material.push(prim.material);
    }
    Ok(())
}

/// The largest coordinate magnitude a vertex may have. Far beyond any real scene, and
/// small enough that the products of two coordinates (edge cross products, areas,
/// squared distances) and the scene's extent stay finite in f32: coordinates near the f32
/// range (3e38) overflow as soon as two are added or multiplied.
pub const MAX_COORDINATE: f32 = 1e18;

/// The error for the first vertex with a NaN or infinite position, or a coordinate
/// beyond ±[`MAX_COORDINATE`], if any: such a vertex would poison bounds, areas and BVH
/// builds, so it is refused rather than dropped.
pub fn check_positions(origin: Origin<'_>, positions: &[Vec3]) -> Result<()> {
    let bad = |p: &Vec3| !p.is_finite() || p.abs().max_element() > MAX_COORDINATE;
    match positions.iter().enumerate().find(|(_, p)| bad(p)) {
        Some((i, p)) if !p.is_finite() => {
            Err(origin.error(format!("vertex {i} has a non-finite position {p}")))
        }
        Some((i, _)) => Err(origin.error(format!(
            "vertex {i} has a coordinate beyond ±{MAX_COORDINATE:e}, the largest dray accepts \
             (larger ones overflow f32 in areas and distances)"
        ))),
        None => Ok(()),
    }
}

/// A shading normal as the mesh stores it: unit length, or zero ("absent") when it is
/// not finite or has no direction. Loaders that stream triangles use it too, so they
/// store exactly what [`add_primitive`] would.
pub fn clean_normal(v: Vec3) -> Vec3 {
    if v.is_finite() { v } else { Vec3::ZERO }.normalize_or_zero()
}

/// A texture coordinate as the mesh stores it: zero ("absent") when not finite.
pub fn clean_uv(v: Vec2) -> Vec2 {
    if v.is_finite() { v } else { Vec2::ZERO }
}

/// A vertex colour as the mesh stores it: white when not finite (a colour that cannot
/// be shown should not blacken or poison the surface), otherwise as given.
pub fn clean_color(v: Vec4) -> Vec4 {
    if v.is_finite() { v } else { Vec4::ONE }
}

/// Whether a triangle is dropped as degenerate: a repeated index, or zero area in f32.
/// (One definition, so every loader and stream drops and counts the same triangles.)
pub fn is_degenerate(indices: [u32; 3], corners: [Vec3; 3]) -> bool {
    let [a, b, c] = indices;
    let [pa, pb, pc] = corners;
    a == b || b == c || a == c || (pb - pa).cross(pc - pa) == Vec3::ZERO
}

/// Convert a triangle strip into a triangle list, keeping winding consistent.
pub fn strip_to_list(strip: &[u32]) -> Vec<u32> {
    let mut out = Vec::with_capacity(strip.len().saturating_sub(2) * 3);
    for i in 2..strip.len() {
        if i % 2 == 0 {
            out.extend_from_slice(&[strip[i - 2], strip[i - 1], strip[i]]);
        } else {
            out.extend_from_slice(&[strip[i - 1], strip[i - 2], strip[i]]);
        }
    }
    out
}

/// Convert a triangle fan into a triangle list.
pub fn fan_to_list(fan: &[u32]) -> Vec<u32> {
    let mut out = Vec::with_capacity(fan.len().saturating_sub(2) * 3);
    for i in 2..fan.len() {
        out.extend_from_slice(&[fan[0], fan[i - 1], fan[i]]);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn origin() -> Origin<'static> {
        Origin {
            path: Path::new("test.gltf"),
            mesh: "m",
            primitive: 0,
        }
    }

    #[test]
    fn rejects_nan_and_bad_index_and_drops_degenerates() {
        let mut mesh = Mesh::default();
        let mut stats = LoadStats::default();
        let p = [Vec3::ZERO, Vec3::X, Vec3::Y, Vec3::new(2.0, 0.0, 0.0)];
        let prim = |idx: &'static [u32]| Primitive {
            positions: &[],
            normals: None,
            tangents: None,
            uvs: None,
            uvs2: None,
            uv_sets: [0, 1],
            colors: None,
            indices: idx,
            material: 0,
        };
        let mut ok = prim(&[0, 1, 2, 0, 1, 3, 0, 0, 1]);
        ok.positions = &p;
        add_primitive(&mut mesh, &mut stats, origin(), ok).unwrap();
        assert_eq!(mesh.indices.len(), 1);
        assert_eq!(stats.degenerate_triangles, 2);

        let mut bad = prim(&[0, 1, 7]);
        bad.positions = &p;
        let err = add_primitive(&mut mesh, &mut stats, origin(), bad).unwrap_err();
        assert!(
            err.to_string().contains("index 2 refers to vertex 7"),
            "{err}"
        );

        let nan = [Vec3::ZERO, Vec3::new(f32::NAN, 0.0, 0.0), Vec3::Y];
        let mut bad = prim(&[0, 1, 2]);
        bad.positions = &nan;
        let err = add_primitive(&mut mesh, &mut stats, origin(), bad).unwrap_err();
        assert!(
            err.to_string()
                .contains("vertex 1 has a non-finite position"),
            "{err}"
        );
    }

    #[test]
    fn strips_and_fans() {
        assert_eq!(strip_to_list(&[0, 1, 2, 3]), vec![0, 1, 2, 2, 1, 3]);
        assert_eq!(fan_to_list(&[0, 1, 2, 3]), vec![0, 1, 2, 0, 2, 3]);
    }
}

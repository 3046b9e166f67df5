//! [`PlySource`]: a PLY file as a [`TriangleSource`], so `dray partition` can cut a scan
//! far larger than the scene it would make in memory.
//!
//! Loading a PLY whole costs the file's bytes, four attribute arrays per vertex and the
//! index and material arrays, several times the file size. A pass of the stream keeps
//! only what random access by face index needs: the positions, plus the normals and
//! texture coordinates when the file has them, and reads the faces one at a time through
//! the same parser ([`crate::ply::read_body`]) the loader uses. Each pass re-opens the
//! file, so nothing is held between the package writer's passes.
//!
//! The triangles are exactly those of [`crate::ply::load_ply`]'s mesh, in the same order
//! with the same global ids: same fan triangulation (shared code), same attribute
//! clean-up and degenerate test ([`crate::validate`]), same errors (out-of-range index,
//! non-finite position, empty scene), so a package written from the stream is the
//! package written from the loaded scene, byte for byte.

use std::path::{Path, PathBuf};

use dray_core::scene::Scene;
use glam::{Vec2, Vec3, Vec4};

use crate::error::{Result, SceneError};
use crate::partition::{SourceTriangle, TriangleSource};
use crate::ply::{self, Body, Stop, Vertices};
use crate::validate::{self, Origin};

/// A PLY file streamed face by face (see the module docs).
pub struct PlySource {
    path: PathBuf,
    /// The scene without its triangles, as [`crate::load`] would report it.
    tables: Scene,
    /// Set for files whose faces come before their vertices: a stream cannot resolve
    /// those, so the scene is loaded whole instead (legal but rare).
    loaded: bool,
}

impl PlySource {
    /// Check the whole file once (so every error [`crate::load`] would give is given
    /// here, before a package directory is touched) and gather the tables: name,
    /// material, warnings and the degenerate-triangle count.
    pub fn open(path: &Path) -> Result<PlySource> {
        if ply::faces_before_vertices(path)? {
            return Ok(PlySource {
                path: path.to_path_buf(),
                tables: ply::load_ply(path)?,
                loaded: true,
            });
        }
        let pass = pass(path, &mut |_| Ok(()))?;
        if pass.triangles == 0 {
            return Err(SceneError::Empty {
                path: path.to_path_buf(),
            });
        }
        let mut tables = ply::tables(path, pass.warnings);
        tables.stats.degenerate_triangles = pass.degenerate;
        Ok(PlySource {
            path: path.to_path_buf(),
            tables,
            loaded: false,
        })
    }

    /// The scene without its triangles: what the package manifest stores.
    pub fn tables(&self) -> &Scene {
        &self.tables
    }
}

impl TriangleSource for PlySource {
    fn for_each_triangle(&self, f: &mut dyn FnMut(&SourceTriangle) -> Result<()>) -> Result<()> {
        if self.loaded {
            return self.tables.for_each_triangle(f);
        }
        pass(&self.path, f).map(drop)
    }
}

/// What one pass found.
struct Pass {
    triangles: u64,
    degenerate: u64,
    warnings: Vec<String>,
}

/// One pass over the file, handing every kept triangle to `f`.
fn pass(path: &Path, f: &mut dyn FnMut(&SourceTriangle) -> Result<()>) -> Result<Pass> {
    let mesh = ply::mesh_name(path);
    let origin = Origin {
        path,
        mesh: &mesh,
        primitive: 0,
    };
    let mut body = Emit {
        origin,
        f,
        vertices: Vertices::default(),
        bad_position: None,
        next_id: 0,
        degenerate: 0,
    };
    let warnings = ply::read_file(path, &mut body)?;
    // The loader checks positions after parsing the whole file, so a malformed face
    // after a NaN vertex is reported first there too.
    if let Some(e) = body.bad_position.take() {
        return Err(e);
    }
    Ok(Pass {
        triangles: body.next_id,
        degenerate: body.degenerate,
        warnings,
    })
}

/// The stream's [`Body`]: resolves each triangle's corners and hands it on.
struct Emit<'a, 'f> {
    origin: Origin<'a>,
    f: &'f mut dyn FnMut(&SourceTriangle) -> Result<()>,
    /// Normals already cleaned as the loader stores them.
    vertices: Vertices,
    /// The loader's error for a non-finite position; set, it stops emitting (the pass
    /// fails at its end).
    bad_position: Option<SceneError>,
    /// The next kept triangle's global id (its index in the loaded mesh).
    next_id: u64,
    degenerate: u64,
}

impl Body for Emit<'_, '_> {
    fn vertices(&mut self, mut v: Vertices) -> std::result::Result<(), Stop> {
        self.bad_position = validate::check_positions(self.origin, &v.positions).err();
        if let Some(ns) = &mut v.normals {
            ns.iter_mut().for_each(|n| *n = validate::clean_normal(*n));
        }
        if let Some(us) = &mut v.uvs {
            us.iter_mut().for_each(|u| *u = validate::clean_uv(*u));
        }
        self.vertices = v;
        Ok(())
    }

    fn triangle(&mut self, tri: [u32; 3]) -> std::result::Result<(), Stop> {
        if self.bad_position.is_some() {
            return Ok(());
        }
        let v = &self.vertices;
        // Indices are range-checked by the parser against the header's vertex count,
        // which is the length of `positions` (the vertex element precedes the faces).
        let get = |k: usize| tri.get(k).map(|&i| i as usize).unwrap_or(0);
        let lookup3 = |a: &[Vec3]| std::array::from_fn(|k| a.get(get(k)).copied());
        let positions: [Option<Vec3>; 3] = lookup3(&v.positions);
        let [Some(p0), Some(p1), Some(p2)] = positions else {
            return Err(self
                .origin
                .error(format!("triangle {tri:?} refers to a vertex not read"))
                .into());
        };
        let corners = [p0, p1, p2];
        if validate::is_degenerate(tri, corners) {
            self.degenerate += 1;
            return Ok(());
        }
        let id = u32::try_from(self.next_id).map_err(|_| {
            self.origin
                .error("more than 4 billion triangles cannot be given 32-bit global ids")
        })?;
        let normals = match &v.normals {
            Some(ns) => lookup3(ns).map(|n| n.unwrap_or(Vec3::ZERO)),
            None => [Vec3::ZERO; 3],
        };
        let uvs = match &v.uvs {
            Some(us) => std::array::from_fn(|k| us.get(get(k)).copied().unwrap_or(Vec2::ZERO)),
            None => [Vec2::ZERO; 3],
        };
        let t = SourceTriangle {
            id,
            material: 0,
            positions: corners,
            normals,
            tangents: [Vec4::ZERO; 3],
            uvs,
            uvs2: [Vec2::ZERO; 3],
            colors: [Vec4::ONE; 3],
        };
        (self.f)(&t)?;
        self.next_id += 1;
        Ok(())
    }
}

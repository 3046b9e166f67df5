//! The sink that streams: each primitive a generator emits goes through the validation
//! gate into a scratch mesh, is handed to the consumer triangle by triangle, and is then
//! forgotten, so memory is one primitive however large the scene.
//!
//! It validates with the very function the in-memory [`Builder`](super::Builder) uses
//! ([`add_primitive`]) and reads the scratch mesh back with the very function that reads
//! an in-memory scene ([`Mesh`]'s [`TriangleSource`]), so a streamed triangle is the
//! in-memory triangle by construction: same degenerates dropped, same normalised normals,
//! same zero attributes. Only the ids need work: they continue across primitives.

use std::path::Path;

use dray_core::scene::{LoadStats, Mesh};
use glam::Vec3;

use super::Sink;
use crate::error::Result;
use crate::partition::{SourceTriangle, TriangleSource};
use crate::validate::{Origin, Primitive, add_primitive};

/// Forwards every kept triangle to `f`, numbered from 0 in emission order (the index the
/// triangle has in the in-memory scene).
pub(crate) struct StreamSink<'a> {
    spec: &'a str,
    generator: &'static str,
    primitives: usize,
    scratch: Mesh,
    stats: LoadStats,
    next_id: u64,
    f: &'a mut dyn FnMut(&SourceTriangle) -> Result<()>,
}

impl<'a> StreamSink<'a> {
    pub(crate) fn new(
        spec: &'a str,
        generator: &'static str,
        f: &'a mut dyn FnMut(&SourceTriangle) -> Result<()>,
    ) -> Self {
        StreamSink {
            spec,
            generator,
            primitives: 0,
            scratch: Mesh::default(),
            stats: LoadStats::default(),
            next_id: 0,
            f,
        }
    }

    /// Triangles dropped as degenerate so far (what the in-memory scene's stats record).
    pub(crate) fn degenerate_triangles(&self) -> u64 {
        self.stats.degenerate_triangles
    }
}

/// Empty `mesh`, keeping its allocations for the next primitive.
fn clear(mesh: &mut Mesh) {
    mesh.positions.clear();
    mesh.normals.clear();
    mesh.tangents.clear();
    mesh.uvs.clear();
    mesh.indices.clear();
    mesh.material.clear();
}

impl Sink for StreamSink<'_> {
    fn add_triangles(
        &mut self,
        positions: &[Vec3],
        normals: Option<&[Vec3]>,
        indices: &[u32],
        material: u32,
    ) -> Result<()> {
        let origin = Origin {
            path: Path::new(self.spec),
            mesh: self.generator,
            primitive: self.primitives,
        };
        self.primitives += 1;
        clear(&mut self.scratch);
        add_primitive(
            &mut self.scratch,
            &mut self.stats,
            origin,
            Primitive {
                positions,
                normals,
                tangents: None,
                uvs: None,
                uvs2: None,
                uv_sets: [0, 1],
                colors: None,
                indices,
                material,
            },
        )?;
        let first = self.next_id;
        self.next_id += self.scratch.indices.len() as u64;
        if self.next_id > u32::MAX as u64 {
            return Err(
                origin.error("more than 4 billion triangles cannot be given 32-bit global ids")
            );
        }
        let f = &mut *self.f;
        self.scratch.for_each_triangle(&mut |t| {
            let mut t = *t;
            // In range: first + local id < next_id <= u32::MAX, checked above.
            t.id = (first + t.id as u64) as u32;
            f(&t)
        })
    }
}

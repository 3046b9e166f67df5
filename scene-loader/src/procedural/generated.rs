//! Generators that can make their scene in memory or stream it, from one description.
//!
//! A [`Generator`] is split along what streaming needs: the tables (materials, lights,
//! environment) that do not depend on the triangles, the triangles themselves, emitted
//! into any [`Sink`] identically every time, and the camera, which is framed on the
//! triangles' bounds. [`make`] runs it once into a [`Builder`]; [`GeneratedSource`] runs it
//! once to learn the bounds and degenerate count, then again on every read, through a
//! [`StreamSink`]. Both are the same code over the same emission, so the streamed scene
//! is the in-memory one by construction.

use dray_core::camera::Camera;
use dray_core::scene::Scene;
use glam::Vec3;

use super::{Builder, Sink, StreamSink, no_triangles};
use crate::error::Result;
use crate::partition::{SourceTriangle, TriangleSource};

/// A procedural scene described so that it can be emitted any number of times.
pub(crate) trait Generator {
    /// The generator's name in error messages (`"soup"`).
    fn name(&self) -> &'static str;

    /// Everything but the triangles and the cameras: the materials the triangles refer
    /// to by index, lights and environment, in a scene named `spec`.
    fn tables(&self, spec: &str) -> Scene;

    /// About how many triangles [`emit`](Self::emit) makes, without making them: an
    /// upper estimate for admission control, which must answer before anything is built.
    fn triangle_estimate(&self) -> u64;

    /// Emit every triangle, in the same order on every call.
    fn emit(&self, spec: &str, sink: &mut dyn Sink) -> Result<()>;

    /// Emit into the in-memory builder. The default is [`emit`](Self::emit); a generator
    /// may override it to group its output into fewer primitives (sharing more vertices
    /// in memory), as long as every triangle, with its attributes, and the triangle order
    /// stay the same.
    fn build(&self, spec: &str, builder: &mut Builder<'_>) -> Result<()> {
        self.emit(spec, builder)
    }

    /// The cameras, given the bounds of the finished triangles.
    fn cameras(&self, lo: Vec3, hi: Vec3) -> Vec<Camera>;
}

/// The scene `spec` made in memory by `generator`, in one pass.
pub(crate) fn make(spec: &str, generator: &dyn Generator) -> Result<Scene> {
    let mut b = Builder::with_tables(spec, generator.name(), generator.tables(spec));
    generator.build(spec, &mut b)?;
    let (lo, hi) = b.bounds();
    for camera in generator.cameras(lo, hi) {
        b.camera(camera);
    }
    b.finish()
}

/// A generated scene as a stream: the generator and the tables, never the triangles.
/// Partitioning reads it as a [`TriangleSource`], each read re-running the generator, so
/// memory is one primitive (a chunk of soup, a building, a slab of isosurface) whatever
/// the scene's size.
pub struct GeneratedSource {
    spec: String,
    generator: Box<dyn Generator>,
    /// Everything but the mesh, including the degenerate count and the framed camera.
    tables: Scene,
}

impl GeneratedSource {
    /// Run `generator` once without keeping its triangles, for what the tables need from
    /// them: the bounds (camera framing) and the degenerate count (the scene's stats).
    pub(crate) fn plan(spec: &str, generator: Box<dyn Generator>) -> Result<Self> {
        let _span = tracing::info_span!("plan", spec).entered();
        let mut tables = generator.tables(spec);
        let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
        let mut triangles = 0u64;
        let degenerate = run(spec, generator.as_ref(), &mut |t| {
            for p in t.positions {
                lo = lo.min(p);
                hi = hi.max(p);
            }
            triangles += 1;
            Ok(())
        })?;
        if triangles == 0 {
            return Err(no_triangles(spec));
        }
        tables.stats.degenerate_triangles += degenerate;
        tables.cameras.extend(generator.cameras(lo, hi));
        tracing::info!(triangles, "planned");
        Ok(GeneratedSource {
            spec: spec.to_string(),
            generator,
            tables,
        })
    }

    /// The scene without its triangles.
    pub fn tables(&self) -> &Scene {
        &self.tables
    }
}

/// Stream `generator`'s triangles to `f`; returns how many were dropped as degenerate.
fn run(
    spec: &str,
    generator: &dyn Generator,
    f: &mut dyn FnMut(&SourceTriangle) -> Result<()>,
) -> Result<u64> {
    let mut sink = StreamSink::new(spec, generator.name(), f);
    generator.emit(spec, &mut sink)?;
    Ok(sink.degenerate_triangles())
}

impl TriangleSource for GeneratedSource {
    fn for_each_triangle(&self, f: &mut dyn FnMut(&SourceTriangle) -> Result<()>) -> Result<()> {
        run(&self.spec, self.generator.as_ref(), f).map(|_| ())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::procedural::{generate, stream};

    fn no_files(spec: &str) -> Result<Scene> {
        Err(crate::procedural::spec_error(spec, "not procedural"))
    }

    fn triangles(source: &dyn TriangleSource) -> Vec<SourceTriangle> {
        let mut v = Vec::new();
        source
            .for_each_triangle(&mut |t| {
                v.push(*t);
                Ok(())
            })
            .unwrap();
        v
    }

    /// The stream is the in-memory scene triangle for triangle, with the same tables. The
    /// soup is the smallest with a degenerate triangle (dropped from both and counted in
    /// both stats) and spans two chunks; the isosurfaces span many slabs.
    #[test]
    fn streams_equal_the_scenes_made_in_memory() {
        for spec in ["soup:90483", "city:3", "iso:heart:30", "iso:metaballs:25"] {
            let scene = generate(spec, &no_files).unwrap().unwrap();
            let source = stream(spec, &no_files).unwrap().unwrap();
            let mut tables = scene.clone();
            tables.mesh = Default::default();
            assert!(*source.tables() == tables, "{spec}: tables differ");
            let (streamed, made) = (triangles(&source), triangles(&scene));
            assert_eq!(streamed.len(), made.len(), "{spec}");
            assert!(streamed == made, "{spec}: triangles differ");
        }
        let soup = generate("soup:90483", &no_files).unwrap().unwrap();
        assert_eq!(soup.stats.degenerate_triangles, 1);
    }

    #[test]
    fn only_large_generators_stream() {
        for spec in ["cornell", "spheres:3", "scene.gltf"] {
            assert!(stream(spec, &no_files).unwrap().is_none(), "{spec}");
        }
        for spec in ["soup:0", "city:x", "iso:nope"] {
            let e = stream(spec, &no_files).err().unwrap().to_string();
            assert!(e.contains(spec), "{e}");
        }
    }
}

//! PLY import: `dray_scene::ply::load_ply` (whole file) and `ply_stream::PlySource` (the
//! streaming reader `dray partition` uses), on the same file.
//!
//! The input is the file. Oracles besides "no panic, no huge allocation": the loaded
//! scene keeps the loader invariants (`dray_fuzz::check_scene`), and the two readers
//! agree as their docs promise: both fail or both succeed, and then hand over the same
//! triangles, bit for bit, in the same order, with the same degenerate count.

#![no_main]

use dray_fuzz::{Scratch, check_scene};
use dray_scene::partition::{SourceTriangle, TriangleSource};
use dray_scene::ply::load_ply;
use dray_scene::ply_stream::PlySource;
use libfuzzer_sys::fuzz_target;

fuzz_target!(init: dray_fuzz::init("ply"), |data: &[u8]| {
    let scratch = Scratch::fresh();
    let path = scratch.write("scan.ply", data);
    let loaded = load_ply(&path);
    let stream = PlySource::open(&path);
    match (&loaded, &stream) {
        (Ok(scene), Ok(source)) => {
            check_scene(scene);
            assert_eq!(
                scene.stats.degenerate_triangles,
                source.tables().stats.degenerate_triangles,
                "degenerate counts differ"
            );
            let from_scene = triangles(scene);
            let from_stream = triangles(source);
            assert_eq!(from_scene.len(), from_stream.len(), "triangle counts differ");
            assert!(from_scene == from_stream, "the stream's triangles differ from the loader's");
        }
        (Err(_), Err(_)) => {}
        (Ok(_), Err(e)) => panic!("load_ply succeeds but PlySource::open fails: {e}"),
        (Err(e), Ok(_)) => panic!("PlySource::open succeeds but load_ply fails: {e}"),
    }
    if let Err(e) = &loaded {
        let _ = e.to_string();
    }
});

/// Every triangle as bits (so NaN compares equal to itself and -0 differs from 0).
fn triangles(source: &dyn TriangleSource) -> Vec<Vec<u32>> {
    let mut out = Vec::new();
    source
        .for_each_triangle(&mut |t: &SourceTriangle| {
            let mut bits = vec![t.id, t.material];
            for c in 0..3 {
                bits.extend(t.positions[c].to_array().map(f32::to_bits));
                bits.extend(t.normals[c].to_array().map(f32::to_bits));
                bits.extend(t.tangents[c].to_array().map(f32::to_bits));
                bits.extend(t.uvs[c].to_array().map(f32::to_bits));
            }
            out.push(bits);
            Ok(())
        })
        .expect("a triangle source that opened hands over its triangles");
    out
}

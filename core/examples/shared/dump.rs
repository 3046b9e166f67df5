//! The files `dray bench-rays --dump-mesh/--dump-rays` write (little-endian f32 records),
//! read back by the core's examples (`trace_dump`, `build_time`).

use dray_core::scene::Mesh;
use glam::Vec3;

/// Every f32 of `path`; exits with a message when it cannot be read.
pub fn read_f32s(path: &str) -> Vec<f32> {
    let bytes = std::fs::read(path).unwrap_or_else(|e| {
        eprintln!("cannot read {path}: {e}");
        std::process::exit(2);
    });
    bytes
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect()
}

/// The triangle soup of a `--dump-mesh` file (nine floats a triangle) as a mesh.
pub fn read_mesh(path: &str) -> Mesh {
    let pts: Vec<Vec3> = read_f32s(path)
        .chunks_exact(3)
        .map(|c| Vec3::new(c[0], c[1], c[2]))
        .collect();
    let mut mesh = Mesh::default();
    mesh.push_vertices(&pts);
    let t = pts.len() as u32 / 3;
    mesh.indices = (0..t).map(|i| [3 * i, 3 * i + 1, 3 * i + 2]).collect();
    mesh.material = vec![0; t as usize];
    mesh
}

//! Admission by memory: before a job is accepted, estimate what it will need at the
//! coordinator and refuse it (RESOURCE_EXHAUSTED) above `--max-job-bytes`, so that a job
//! within every per-field limit still cannot take the machine down inside SubmitJob.
//!
//! The estimate covers what grows with the request:
//! - the film: integer sums per pixel, plus the encoded image GetImage builds;
//! - a scene file: its size, plus what its compressed glTF views declare they decode to
//!   ([`dray_scene::gltf::declared_expansion`]), times [`IMPORT_FACTOR`] (meshes, the BVH
//!   or the partition built from it), and for `grid:<file>:XxYxZ` that times the copies;
//! - a procedural scene: the generator's own triangle estimate
//!   ([`dray_scene::procedural::triangle_estimate`]) times [`PROCEDURAL_BYTES_PER_TRIANGLE`].
//!   The generators' caps (200M triangles) keep a typo from asking for terabytes, but
//!   a scene within them can still need far more than the machine has.
//!
//! Scene packages are read domain by domain on the workers, so they are not estimated
//! here beyond the film.

use tonic::Status;

/// The default `--max-job-bytes`, defined with the limits it is one of.
pub use crate::validate::default_max_job_bytes;
use crate::validate::{Limits, Validated};

/// Bytes per pixel: 3 x i64 sums, plus room for an encoded EXR (RGB f32) of the image.
pub const FILM_BYTES_PER_PIXEL: u64 = 24 + 12;
/// A scene file grows about this much once imported and built (meshes with normals and
/// uvs, the BVH, partition buffers).
pub const IMPORT_FACTOR: u64 = 16;

/// Peak bytes per triangle while a procedural scene is made and prepared, measured as
/// the whole process's maximum RSS of `dray render` (2M-triangle soup: 800 B; 2.9M
/// triangle gyroid: 450 B; 1.9M-triangle city: 670 B). The soup's (no shared
/// vertices) is the bound.
pub const PROCEDURAL_BYTES_PER_TRIANGLE: u64 = 800;

/// The estimate, in bytes, of what job `v` needs at the coordinator.
pub fn estimate(v: &Validated) -> u64 {
    let film = u64::from(v.spec.width)
        .saturating_mul(u64::from(v.spec.height))
        .saturating_mul(FILM_BYTES_PER_PIXEL);
    film.saturating_add(scene_bytes(&v.scene_spec, v.package.is_some()))
}

/// The imported size of the scene `spec` (a canonical file path or a procedural spec).
fn scene_bytes(spec: &str, package: bool) -> u64 {
    if package {
        return 0;
    }
    if let Some(triangles) = dray_scene::procedural::triangle_estimate(spec) {
        return triangles.saturating_mul(PROCEDURAL_BYTES_PER_TRIANGLE);
    }
    if let Some(rest) = spec.strip_prefix("grid:") {
        // grid:<scene>:XxYxZ, the scene itself possibly a file.
        if let Some((inner, dims)) = rest.rsplit_once(':') {
            let copies = dims
                .split('x')
                .map(|d| d.parse::<u64>().unwrap_or(1))
                .fold(1u64, |a, d| a.saturating_mul(d.max(1)));
            return scene_bytes(inner, false).saturating_mul(copies);
        }
        return 0;
    }
    match std::fs::metadata(spec) {
        // What compressed views decode to counts as if it were in the file: a small
        // file whose views expand a thousandfold is priced at what it will take.
        Ok(m) if m.is_file() => m
            .len()
            .saturating_add(dray_scene::gltf::declared_expansion(std::path::Path::new(
                spec,
            )))
            .saturating_mul(IMPORT_FACTOR),
        _ => 0,
    }
}

/// Refuse `v` if its estimate exceeds the limit.
pub fn admit(v: &Validated, limits: &Limits) -> Result<(), Status> {
    let need = estimate(v);
    if need > limits.max_job_bytes {
        return Err(Status::resource_exhausted(format!(
            "the job needs about {} MiB at the coordinator (image {}x{}, scene {}), more \
             than its --max-job-bytes of {} MiB",
            need >> 20,
            v.spec.width,
            v.spec.height,
            crate::text::bounded(&v.spec.scene),
            limits.max_job_bytes >> 20
        )));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A small glTF whose compressed views declare gigabytes (a decompression bomb,
    /// issue 45) is priced at what it declares, so admission refuses it before the
    /// loader allocates anything; the same file without the views is priced by size.
    #[test]
    fn compressed_views_are_priced_at_their_declared_size() {
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("bomb.gltf");
        let view = r#"{"buffer":0,"byteLength":16,"extensions":{"EXT_meshopt_compression":
            {"buffer":0,"byteLength":16,"byteStride":16,"count":33554432,"mode":"ATTRIBUTES"}}}"#;
        let views = [view; 12].join(",");
        let json = format!(
            r#"{{"asset":{{"version":"2.0"}},"buffers":[{{"byteLength":16}}],"bufferViews":[{views}]}}"#
        );
        std::fs::write(&f, &json).unwrap();
        let p = f.display().to_string();
        let declared = 12u64 * 33_554_432 * 16;
        assert_eq!(
            scene_bytes(&p, false),
            (json.len() as u64 + declared) * IMPORT_FACTOR
        );
        let plain = dir.path().join("plain.gltf");
        std::fs::write(&plain, r#"{"asset":{"version":"2.0"}}"#).unwrap();
        let p = plain.display().to_string();
        assert_eq!(scene_bytes(&p, false), 27 * IMPORT_FACTOR);
    }

    #[test]
    fn grid_copies_multiply_a_file() {
        let dir = std::env::temp_dir().join(format!("dray-admission-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let f = dir.join("m.ply");
        std::fs::write(&f, vec![0u8; 1000]).unwrap();
        let p = f.display().to_string();
        assert_eq!(scene_bytes(&p, false), 1000 * IMPORT_FACTOR);
        assert_eq!(
            scene_bytes(&format!("grid:{p}:2x3x4"), false),
            24 * 1000 * IMPORT_FACTOR
        );
        assert_eq!(scene_bytes(&p, true), 0);
        assert!(scene_bytes("cornell", false) < 1 << 20);
        // A soup within the generators' cap that no laptop could hold.
        assert_eq!(
            scene_bytes("soup:100000000", false),
            100_000_000 * PROCEDURAL_BYTES_PER_TRIANGLE
        );
        assert_eq!(
            scene_bytes("grid:soup:1000:2x2x2", false),
            8 * scene_bytes("soup:1000", false)
        );
        assert!(scene_bytes("iso:gyroid:2048", false) > 32 << 30);
        assert!(scene_bytes("city:1024", false) > 64 << 30);
        assert_eq!(
            scene_bytes("spheres:10", false),
            3202 * PROCEDURAL_BYTES_PER_TRIANGLE
        );
        assert!(default_max_job_bytes() > 0);
        let _ = std::fs::remove_dir_all(&dir);
    }
}

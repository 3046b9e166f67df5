//! One entry point for every scene spec: a procedural name (`cornell`, `spheres:N`, …)
//! or a path to a `.gltf`, `.glb`, `.ply` or `.obj` file.

use std::path::Path;

use dray_core::scene::Scene;

use crate::animation::AnimationTime;
use crate::error::{Result, SceneError};

/// Load the scene `spec` names.
pub fn load(spec: &str) -> Result<Scene> {
    load_at(spec, None)
}

/// [`load`] at a moment of the file's animation (glTF only: other formats and
/// procedural scenes have none, and `time` changes nothing for them). A `grid:` of a
/// file poses the file at `time` and replicates the posed model (each copy at the same
/// moment), so a frame range over a grid animates every copy.
pub fn load_at(spec: &str, time: Option<&AnimationTime>) -> Result<Scene> {
    let _span = tracing::info_span!("load_scene", spec).entered();
    if let Some(scene) = crate::procedural::generate(spec, &|inner| load_at(inner, time))? {
        return Ok(scene);
    }
    let path = Path::new(spec);
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
        .unwrap_or_default();
    if !path.exists() {
        return Err(SceneError::NotFound {
            spec: spec.to_string(),
            suggestion: crate::suggest::suggest(spec),
        });
    }
    let mut scene = match ext.as_str() {
        "gltf" | "glb" => crate::gltf::load_gltf_at(path, time)?,
        "ply" => crate::ply::load_ply(path)?,
        "obj" => crate::obj::load_obj(path)?,
        _ => {
            return Err(SceneError::UnknownFormat {
                path: path.to_path_buf(),
            });
        }
    };
    if scene.mesh.indices.is_empty() {
        return Err(SceneError::Empty {
            path: path.to_path_buf(),
        });
    }
    crate::factors::check_factors(path, &mut scene)?;
    Ok(scene)
}

/// The file whose animation a time applies to in `spec`: the spec itself when it is a
/// file, the innermost scene of a `grid:` (nested or not) when that is a file, and `None`
/// for a procedural scene, which has no animation.
pub fn animated_file(spec: &str) -> Option<&str> {
    let mut rest = spec;
    while let Some(inner) = rest.strip_prefix("grid:") {
        rest = inner.rsplit_once(':').map_or(inner, |(scene, _dims)| scene);
    }
    (!crate::procedural::is_procedural(rest)).then_some(rest)
}

#[cfg(test)]
mod tests {
    use super::animated_file;

    #[test]
    fn the_animated_file_of_a_grid_is_its_innermost_scene() {
        assert_eq!(animated_file("a.gltf"), Some("a.gltf"));
        assert_eq!(animated_file("grid:a.gltf:2x1x1"), Some("a.gltf"));
        assert_eq!(
            animated_file("grid:grid:d/a.glb:2x2x2:3x1x1"),
            Some("d/a.glb")
        );
        assert_eq!(animated_file("grid:cornell:2x2x2"), None);
        assert_eq!(animated_file("cornell"), None);
    }
}

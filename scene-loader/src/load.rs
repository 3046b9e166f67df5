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
/// procedural scenes have none, and `time` changes nothing for them).
pub fn load_at(spec: &str, time: Option<&AnimationTime>) -> Result<Scene> {
    let _span = tracing::info_span!("load_scene", spec).entered();
    if let Some(scene) = crate::procedural::generate(spec, &load)? {
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

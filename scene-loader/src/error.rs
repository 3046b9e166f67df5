//! Errors a scene can fail to load with. Every message names the file and, where it
//! applies, the mesh, primitive and index at fault.

use std::path::PathBuf;

#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    // The reason is in the message, not also a `source`: error reports that print the
    // chain (anyhow's `{:#}`) would print it twice.
    #[error("{path}: cannot read: {error}")]
    Io {
        path: PathBuf,
        error: std::io::Error,
    },
    /// A spec that is neither a file nor a procedural scene name.
    #[error("{spec}: no such file, and not a procedural scene name (cornell, cornell:mirror, cornell:glass, spheres:N, soup:N, grid:<scene>:XxYxZ, city:N, iso:<field>:<res>){}", did_you_mean(.suggestion))]
    NotFound {
        spec: String,
        /// The closest procedural name or file next to the path, if one is close.
        suggestion: Option<String>,
    },
    #[error("{path}: unrecognised scene format (expected .gltf, .glb, .ply or .obj)")]
    UnknownFormat { path: PathBuf },
    #[error("{path}: {message}")]
    Format { path: PathBuf, message: String },
    /// A problem inside one primitive of one mesh.
    #[error("{path}: mesh {mesh:?} primitive {primitive}: {message}")]
    Primitive {
        path: PathBuf,
        mesh: String,
        primitive: usize,
        message: String,
    },
    #[error("{path}: required extension {extension} is not supported")]
    UnsupportedExtension { path: PathBuf, extension: String },
    #[error("procedural scene {spec:?}: {message}")]
    Procedural { spec: String, message: String },
    #[error("{path}: scene has no triangles")]
    Empty { path: PathBuf },
    /// The load was cancelled ([`crate::cancel::load_cancellable`]).
    #[error("loading was cancelled")]
    Cancelled,
}

fn did_you_mean(suggestion: &Option<String>) -> String {
    suggestion
        .as_ref()
        .map(|s| format!("; did you mean {s:?}?"))
        .unwrap_or_default()
}

pub type Result<T> = std::result::Result<T, SceneError>;

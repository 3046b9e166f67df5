//! Errors a scene can fail to load with. Every message names the file and, where it
//! applies, the mesh, primitive and index at fault.

use std::path::PathBuf;

#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    #[error("{path}: cannot read: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
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

pub type Result<T> = std::result::Result<T, SceneError>;

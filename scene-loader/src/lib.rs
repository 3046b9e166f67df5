//! Scene import for dray: glTF 2.0, PLY and OBJ files and procedural scenes, with
//! validation and effect analysis.

pub mod animation;
pub mod cancel;
pub mod effects;
pub mod error;
pub mod factors;
pub mod gltf;
mod gltf_ext;
mod load;
pub mod meshopt;
pub mod obj;
pub mod partition;
pub mod ply;
pub mod ply_stream;
pub mod private_fs;
pub mod procedural;
pub mod reference;
pub mod skin;
pub mod suggest;
pub mod tangents;
pub mod translate;
pub mod validate;

pub use cancel::load_cancellable;
pub use error::{Result, SceneError};
pub use load::{animated_file, load, load_at};

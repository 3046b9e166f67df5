//! Scene import for dray: glTF 2.0, PLY and OBJ files and procedural scenes, with
//! validation and effect analysis.

pub mod error;
pub mod validate;

pub use error::{Result, SceneError};

//! dray's tracing core.
//!
//! Everything a single ray needs lives here: the scene representation every actor shares
//! ([`scene`]), the BVH and the one watertight leaf test ([`bvh`], [`intersect`]),
//! counter-based sampling ([`sampling`]), materials and BSDFs ([`material`], [`bsdf`]),
//! lights ([`light`]), cameras ([`camera`]), the integrators' per-ray steps
//! ([`integrator`]), the exact, order-free film ([`film`]), the display transform of its
//! 8-bit images (exposure, tone curve: [`display`]) and the credit that tells when a tile
//! is complete ([`credit`]).

pub mod adaptive;
pub mod aov;
pub mod bsdf;
pub mod camera;
pub mod clamp;
pub mod effects;
pub mod light;
pub mod material;
pub mod scene;
pub mod texture;

pub use glam::{Mat4, Vec2, Vec3, Vec4};
pub mod bvh;
pub mod credit;
pub mod dispersion;
pub mod display;
pub mod distribution;
pub mod domain;
pub mod env_map;
pub mod env_map_file;
pub mod exposure;
pub mod film;
pub mod frames;
pub mod integrator;
pub mod intersect;
pub mod iridescence;
pub mod kind_set;
pub mod light_sampler;
pub mod light_samples;
pub mod lighting;
pub mod passes;
pub mod ray;
pub mod render;
pub mod sampling;
pub mod sheen;
pub mod sun;
pub mod surface;
pub mod tiles;
pub mod tonemap;
pub mod trace;
pub mod view;
pub mod wall;

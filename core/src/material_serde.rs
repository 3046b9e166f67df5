//! The JSON form of [`crate::material`]'s types, as a scene package's manifest stores
//! them (dray-scene's `partition::manifest`), and [`Real`], the exact `f32` encoding
//! every float of a manifest is written in.
//!
//! The material types derive serde through the field helpers here rather than through
//! glam's own serde, whose floats are `f32` text: the manifest's floats are [`Real`]s, and
//! its bytes (and so every package checksum) must not change with how glam prints.
//! The format is the manifest's promise: a field added to a material type needs
//! `#[serde(default, skip_serializing_if = ...)]` so that manifests of materials without
//! it keep their bytes, and older manifests still load (dray-scene's
//! `material_json_is_pinned` test holds the bytes).

use std::fmt;

use glam::{Affine2, Vec3, Vec4};
use serde::de::{self, Visitor};
use serde::{Deserialize, Deserializer, Serialize, Serializer};

/// An `f32` that survives JSON exactly.
///
/// Written as the f64 of the same value (exact), so any JSON reader, even one that rounds
/// the last f64 digit, gets back a double within a few f64 ulps of an f32, which rounds
/// back to that very f32. Non-finite values, which JSON numbers cannot hold, are written
/// as the strings `"inf"`, `"-inf"` and `"nan"`. Exactness matters: workers that load a
/// package must shade with the same bits as the embedded renderer that never wrote one.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Real(pub f32);

impl Serialize for Real {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        let v = self.0;
        if v.is_finite() {
            s.serialize_f64(v as f64)
        } else if v.is_nan() {
            s.serialize_str("nan")
        } else if v > 0.0 {
            s.serialize_str("inf")
        } else {
            s.serialize_str("-inf")
        }
    }
}

impl<'de> Deserialize<'de> for Real {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct V;
        impl Visitor<'_> for V {
            type Value = Real;
            fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
                f.write_str("a number, \"inf\", \"-inf\" or \"nan\"")
            }
            fn visit_f64<E: de::Error>(self, v: f64) -> Result<Real, E> {
                let r = v as f32;
                if v.is_finite() && !r.is_finite() {
                    return Err(E::custom(format!("{v} is out of f32 range")));
                }
                Ok(Real(r))
            }
            fn visit_u64<E: de::Error>(self, v: u64) -> Result<Real, E> {
                Ok(Real(v as f32))
            }
            fn visit_i64<E: de::Error>(self, v: i64) -> Result<Real, E> {
                Ok(Real(v as f32))
            }
            fn visit_str<E: de::Error>(self, v: &str) -> Result<Real, E> {
                match v {
                    "inf" => Ok(Real(f32::INFINITY)),
                    "-inf" => Ok(Real(f32::NEG_INFINITY)),
                    "nan" => Ok(Real(f32::NAN)),
                    _ => Err(E::invalid_value(de::Unexpected::Str(v), &self)),
                }
            }
        }
        d.deserialize_any(V)
    }
}

/// `#[serde(with = "real")]`: an `f32` field as a [`Real`].
pub mod real {
    use super::*;

    pub fn serialize<S: Serializer>(v: &f32, s: S) -> Result<S::Ok, S::Error> {
        Real(*v).serialize(s)
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<f32, D::Error> {
        Real::deserialize(d).map(|r| r.0)
    }
}

/// `#[serde(with = "vec3")]`: a `Vec3` as an array of three [`Real`]s.
pub mod vec3 {
    use super::*;

    pub fn serialize<S: Serializer>(v: &Vec3, s: S) -> Result<S::Ok, S::Error> {
        v.to_array().map(Real).serialize(s)
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Vec3, D::Error> {
        <[Real; 3]>::deserialize(d).map(|a| Vec3::from_array(a.map(|r| r.0)))
    }
}

/// `#[serde(with = "vec4")]`: a `Vec4` as an array of four [`Real`]s.
pub mod vec4 {
    use super::*;

    pub fn serialize<S: Serializer>(v: &Vec4, s: S) -> Result<S::Ok, S::Error> {
        v.to_array().map(Real).serialize(s)
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Vec4, D::Error> {
        <[Real; 4]>::deserialize(d).map(|a| Vec4::from_array(a.map(|r| r.0)))
    }
}

/// `#[serde(with = "affine2_opt")]`: an optional `Affine2` as the six [`Real`]s of its
/// columns (`x_axis`, `y_axis`, `translation`), or null.
pub mod affine2_opt {
    use super::*;

    pub fn serialize<S: Serializer>(v: &Option<Affine2>, s: S) -> Result<S::Ok, S::Error> {
        v.map(|a| a.to_cols_array().map(Real)).serialize(s)
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Option<Affine2>, D::Error> {
        Option::<[Real; 6]>::deserialize(d)
            .map(|a| a.map(|a| Affine2::from_cols_array(&a.map(|r| r.0))))
    }
}

/// The default of a factor left out when it is 1 (`#[serde(default = ...)]`).
pub fn one() -> f32 {
    1.0
}

/// Whether a factor is exactly 1, bit for bit.
pub fn is_one(v: &f32) -> bool {
    v.to_bits() == 1f32.to_bits()
}

/// Whether a factor is exactly +0, bit for bit (-0 is written).
pub fn is_zero(v: &f32) -> bool {
    v.to_bits() == 0f32.to_bits()
}

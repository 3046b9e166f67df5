//! The ranges a loaded scene's material factors and light intensities must lie in
//! (docs/numerics.md "Scene input"), checked once per file after any loader has run.
//!
//! A non-finite factor (glTF allows `emissiveStrength: 1e39`, which is infinite as an
//! `f32`) would otherwise reach the integrators and turn into contributions the film
//! drops by the thousand; an out-of-range one (metallic 2, a negative colour) makes BSDF
//! weights negative or greater than one and the estimate meaningless. Both are errors
//! naming the material. Emission that is finite but brighter than the film's largest
//! contribution renders, clamped where it is seen directly, and is reported as a warning.
//! A scene may have at most `MAX_PUNCTUAL_LIGHTS` punctual lights, for which the credit
//! of the deepest ray trees is sized.

use std::path::Path;

use dray_core::film::MAX_CONTRIBUTION;
use dray_core::light::{Light, MAX_PUNCTUAL_LIGHTS};
use dray_core::material::{AlphaMode, Material};
use dray_core::scene::Scene;
use glam::Vec3;

use crate::error::{Result, SceneError};

/// The largest emitted radiance or light intensity accepted. Light sampling multiplies
/// it by areas (up to the square of the largest accepted scene extent), 4π and inverse
/// pdfs; below this bound those products stay well inside `f32`.
pub const MAX_EMISSION: f32 = 1.0e20;

/// Check every material and light of `scene`, loaded from `path`. Emission above
/// [`MAX_CONTRIBUTION`] adds a warning to `scene.stats.warnings`.
pub fn check_factors(path: &Path, scene: &mut Scene) -> Result<()> {
    for (i, m) in scene.materials.iter().enumerate() {
        check_material(m).map_err(|message| SceneError::Format {
            path: path.to_path_buf(),
            message: format!("material {i} ({:?}): {message}", m.name),
        })?;
        let e = m.emissive.max_element();
        if e > MAX_CONTRIBUTION {
            scene.stats.warnings.push(format!(
                "material {i} ({:?}): emission {e} is above the film's largest contribution \
                 ({MAX_CONTRIBUTION}); where it is seen directly it is clamped (counted in \
                 the summary as clamped contributions)",
                m.name
            ));
        }
    }
    if scene.lights.len() > MAX_PUNCTUAL_LIGHTS as usize {
        return Err(SceneError::Format {
            path: path.to_path_buf(),
            message: format!(
                "{} punctual lights, more than the {MAX_PUNCTUAL_LIGHTS} a scene may have \
                 (every hit sends a shadow ray to each)",
                scene.lights.len()
            ),
        });
    }
    for (i, l) in scene.lights.iter().enumerate() {
        let (what, v) = match l {
            Light::Point { intensity, .. } | Light::Spot { intensity, .. } => {
                ("intensity", *intensity)
            }
            Light::Directional { irradiance, .. } => ("irradiance", *irradiance),
        };
        colour(what, v, MAX_EMISSION).map_err(|message| SceneError::Format {
            path: path.to_path_buf(),
            message: format!("light {i}: {message}"),
        })?;
    }
    Ok(())
}

/// Why `m` is out of range, if it is.
fn check_material(m: &Material) -> std::result::Result<(), String> {
    colour("baseColorFactor", m.base_color.truncate(), 1.0)?;
    unit("baseColorFactor alpha", m.base_color.w)?;
    unit("metallicFactor", m.metallic)?;
    unit("roughnessFactor", m.roughness)?;
    unit("transmissionFactor", m.transmission)?;
    unit("specularFactor", m.specular)?;
    colour(
        "emission (emissiveFactor x emissiveStrength)",
        m.emissive,
        MAX_EMISSION,
    )?;
    colour("specularColorFactor", m.specular_color, f32::MAX)?;
    if !m.normal_scale.is_finite() {
        return Err(format!(
            "normalTexture scale {} is not finite",
            m.normal_scale
        ));
    }
    if !(m.ior.is_finite() && m.ior >= 1.0) {
        return Err(format!("ior {} is not a finite number >= 1", m.ior));
    }
    if let AlphaMode::Mask { cutoff } = m.alpha_mode
        && !(cutoff.is_finite() && cutoff >= 0.0)
    {
        return Err(format!("alphaCutoff {cutoff} is not a finite number >= 0"));
    }
    Ok(())
}

/// `v` in [0, 1].
fn unit(what: &str, v: f32) -> std::result::Result<(), String> {
    if (0.0..=1.0).contains(&v) {
        Ok(())
    } else {
        Err(format!("{what} {v} is outside [0, 1]"))
    }
}

/// Every component of `v` finite and in [0, `max`].
fn colour(what: &str, v: Vec3, max: f32) -> std::result::Result<(), String> {
    if v.is_finite() && v.min_element() >= 0.0 && v.max_element() <= max {
        Ok(())
    } else {
        Err(format!(
            "{what} ({}, {}, {}) is not finite and within [0, {max}]",
            v.x, v.y, v.z
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec4;

    fn scene_with(m: Material) -> Scene {
        Scene {
            materials: vec![Material::default(), m],
            ..Scene::default()
        }
    }

    fn error_of(m: Material) -> String {
        match check_factors(Path::new("s.gltf"), &mut scene_with(m)) {
            Err(e) => e.to_string(),
            Ok(()) => String::new(),
        }
    }

    fn named(name: &str) -> Material {
        Material {
            name: name.into(),
            ..Material::default()
        }
    }

    #[test]
    fn non_finite_and_out_of_range_factors_are_errors_naming_the_material() {
        let cases: Vec<(Material, &str)> = vec![
            (
                Material {
                    emissive: Vec3::new(1.0, f32::INFINITY, 0.0),
                    ..named("lamp")
                },
                "emission",
            ),
            (
                Material {
                    emissive: Vec3::splat(2.0e20),
                    ..named("lamp")
                },
                "emission",
            ),
            (
                Material {
                    emissive: Vec3::new(0.0, -1.0, 0.0),
                    ..named("lamp")
                },
                "emission",
            ),
            (
                Material {
                    base_color: Vec4::new(0.5, f32::NAN, 0.5, 1.0),
                    ..named("lamp")
                },
                "baseColorFactor",
            ),
            (
                Material {
                    base_color: Vec4::new(0.5, 1.5, 0.5, 1.0),
                    ..named("lamp")
                },
                "baseColorFactor",
            ),
            (
                Material {
                    metallic: 2.0,
                    ..named("lamp")
                },
                "metallicFactor",
            ),
            (
                Material {
                    roughness: -0.1,
                    ..named("lamp")
                },
                "roughnessFactor",
            ),
            (
                Material {
                    transmission: f32::NAN,
                    ..named("lamp")
                },
                "transmissionFactor",
            ),
            (
                Material {
                    ior: 0.5,
                    ..named("lamp")
                },
                "ior",
            ),
            (
                Material {
                    specular_color: Vec3::splat(f32::NEG_INFINITY),
                    ..named("lamp")
                },
                "specularColorFactor",
            ),
            (
                Material {
                    normal_scale: f32::NAN,
                    ..named("lamp")
                },
                "normalTexture",
            ),
            (
                Material {
                    alpha_mode: AlphaMode::Mask { cutoff: f32::NAN },
                    ..named("lamp")
                },
                "alphaCutoff",
            ),
        ];
        for (m, field) in cases {
            let e = error_of(m);
            assert!(e.starts_with("s.gltf: material 1 (\"lamp\"): "), "{e}");
            assert!(e.contains(field), "{field}: {e}");
        }
    }

    #[test]
    fn bright_emission_loads_with_a_warning_and_ordinary_materials_silently() {
        let mut s = scene_with(Material {
            emissive: Vec3::splat(1.0e8),
            ..named("sun")
        });
        check_factors(Path::new("s.gltf"), &mut s).expect("finite emission loads");
        assert_eq!(s.stats.warnings.len(), 1);
        assert!(
            s.stats.warnings[0].contains("\"sun\""),
            "{:?}",
            s.stats.warnings
        );
        let mut s = scene_with(Material {
            emissive: Vec3::splat(MAX_CONTRIBUTION),
            ior: 1.0,
            ..named("lamp")
        });
        check_factors(Path::new("s.gltf"), &mut s).expect("in range");
        assert!(s.stats.warnings.is_empty());
    }

    #[test]
    fn at_most_the_credit_sized_number_of_punctual_lights() {
        let light = Light::Directional {
            direction: Vec3::NEG_Z,
            irradiance: Vec3::ONE,
        };
        let mut s = Scene {
            lights: vec![light.clone(); MAX_PUNCTUAL_LIGHTS as usize],
            ..Scene::default()
        };
        check_factors(Path::new("s.gltf"), &mut s).expect("the most lights load");
        s.lights.push(light);
        let e = check_factors(Path::new("s.gltf"), &mut s)
            .expect_err("one light too many")
            .to_string();
        assert!(e.contains("65537 punctual lights"), "{e}");
    }

    #[test]
    fn lights_must_be_finite_and_non_negative() {
        for bad in [f32::INFINITY, f32::NAN, -1.0, 1.0e30] {
            let mut s = Scene {
                lights: vec![Light::Point {
                    position: Vec3::ZERO,
                    intensity: Vec3::new(1.0, bad, 1.0),
                }],
                ..Scene::default()
            };
            let e = check_factors(Path::new("s.gltf"), &mut s)
                .expect_err("bad light")
                .to_string();
            assert!(e.contains("light 0: intensity"), "{e}");
        }
    }
}

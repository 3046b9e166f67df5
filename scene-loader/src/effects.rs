//! Effect analysis: which light-transport effects a scene calls for, so integrators
//! spawn only the ray kinds that can change the image.

use dray_core::effects::{Effect, Effects};
use dray_core::lighting::Lighting;
use dray_core::scene::Scene;
use glam::Vec3;

/// The effects `scene` needs when rendered with constant environment radiance
/// `environment`. Materials no triangle uses do not count.
pub fn analyze(scene: &Scene, environment: Vec3) -> Effects {
    let mut used = vec![false; scene.materials.len()];
    for &m in &scene.mesh.material {
        if let Some(u) = used.get_mut(m as usize) {
            *u = true;
        }
    }
    let materials = scene
        .materials
        .iter()
        .zip(&used)
        .filter(|(_, u)| **u)
        .map(|(m, _)| m);
    let mut fx = Effects::NONE;
    for m in materials {
        if m.unlit {
            // Only its base colour (and alpha) is read: no lobe, no emission.
            fx.set(Effect::Unlit, true);
            if m.base_color_tex.is_some() {
                fx.set(Effect::Textures, true);
            }
            if m.has_alpha() {
                fx.set(Effect::Alpha, true);
            }
            continue;
        }
        if m.has_specular() {
            fx.set(Effect::Specular, true);
        }
        if m.has_transmission() {
            fx.set(Effect::Transmission, true);
        }
        if m.has_emission() {
            fx.set(Effect::Emission, true);
        }
        if m.has_textures() {
            fx.set(Effect::Textures, true);
        }
        if m.has_alpha() {
            fx.set(Effect::Alpha, true);
        }
        if m.has_clearcoat() {
            fx.set(Effect::Clearcoat, true);
        }
        if m.has_sheen() {
            fx.set(Effect::Sheen, true);
        }
        if m.has_anisotropy() {
            fx.set(Effect::Anisotropy, true);
        }
        if m.has_volume() {
            fx.set(Effect::Volume, true);
        }
        if m.has_iridescence() {
            fx.set(Effect::Iridescence, true);
        }
        if m.has_dispersion() {
            fx.set(Effect::Dispersion, true);
        }
    }
    if !scene.lights.is_empty() || fx.contains(Effect::Emission) {
        fx.set(Effect::DirectLight, true);
    }
    if environment.max_element() > 0.0 {
        fx.set(Effect::Environment, true);
    }
    fx
}

/// The default environment: what the scene asks for if anything (procedural scenes set
/// a dim sky); otherwise black when the scene has lights or emitters (they light it), and
/// a uniform white sky of radiance [`DEFAULT_SKY`] so an unlit model still renders.
///
/// Emission driven by a texture (a glowing label, a screen) is surface detail rather than
/// a light source: a model whose only emission is textured still gets the default sky.
pub fn default_environment(scene: &Scene) -> Vec3 {
    if let Some(env) = scene.environment {
        return env;
    }
    let emitters = scene
        .materials
        .iter()
        .any(|m| m.has_emission() && m.emissive_tex.is_none());
    if scene.lights.is_empty() && !emitters {
        Vec3::splat(DEFAULT_SKY)
    } else {
        Vec3::ZERO
    }
}

/// Radiance of the default sky for scenes with no lights.
pub const DEFAULT_SKY: f32 = 1.0;

/// [`default_environment`] for `scene` lit by the job's `lighting` as well: a sun is a
/// light like the scene's own, so it makes the default sky black (the scene's own
/// environment, when it names one, still wins).
pub fn default_environment_lit(scene: &Scene, lighting: &Lighting) -> Vec3 {
    if lighting.any() && scene.environment.is_none() {
        Vec3::ZERO
    } else {
        default_environment(scene)
    }
}

/// [`analyze`] for `scene` lit by the job's `lighting` as well: a sun is the effect
/// [`Effect::Sun`], an environment map [`Effect::EnvMap`], and each needs direct light
/// (the light sample each shaded hit takes). Without them neither effect is on, so a
/// job without them pays nothing.
pub fn analyze_lit(scene: &Scene, environment: Vec3, lighting: &Lighting) -> Effects {
    let mut fx = analyze(scene, environment);
    if lighting.sun.is_some() {
        fx.set(Effect::Sun, true);
        fx.set(Effect::DirectLight, true);
    }
    if lighting.env_map.is_some() {
        fx.set(Effect::EnvMap, true);
        fx.set(Effect::DirectLight, true);
    }
    fx
}

#[cfg(test)]
mod tests {
    use super::*;
    use dray_core::material::Material;
    use dray_core::scene::Mesh;

    fn one_tri(m: Material) -> Scene {
        let mut mesh = Mesh::default();
        mesh.push_vertices(&[Vec3::ZERO, Vec3::X, Vec3::Y]);
        mesh.indices.push([0, 1, 2]);
        mesh.material.push(0);
        Scene {
            mesh,
            materials: vec![m],
            ..Scene::default()
        }
    }

    #[test]
    fn lambert_without_lights_needs_only_environment() {
        let s = one_tri(Material::lambert("w", Vec3::splat(0.8)));
        let env = default_environment(&s);
        let fx = analyze(&s, env);
        assert_eq!(fx.names(), vec!["environment"]);
    }

    #[test]
    fn glass_needs_transmission_and_emitter_needs_direct_light() {
        assert!(
            analyze(&one_tri(Material::glass("g", 1.5)), Vec3::ZERO).contains(Effect::Transmission)
        );
        let fx = analyze(&one_tri(Material::emitter("e", Vec3::ONE)), Vec3::ZERO);
        assert!(fx.contains(Effect::Emission) && fx.contains(Effect::DirectLight));
        assert!(!fx.contains(Effect::Specular));
    }
}

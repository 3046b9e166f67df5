//! Which light-transport effects a scene calls for.
//!
//! The scene loader analyses a scene once and reports an [`Effects`] set; integrators
//! consult it before spawning a ray kind, so a scene with no transmissive material never
//! traces a refraction ray. `--effects` can force an effect on or off for experiments.

use serde::Serialize;

/// One effect a scene may call for.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Effect {
    /// Punctual lights or emissive triangles exist: direct light with shadow rays.
    DirectLight,
    /// Some material has a specular lobe (metallic or dielectric reflection).
    Specular,
    /// Some material transmits light (KHR_materials_transmission).
    Transmission,
    /// Some triangle emits light.
    Emission,
    /// Some material reads a texture.
    Textures,
    /// Some material is alpha-masked or blended: cut-outs in traversal.
    Alpha,
    /// The environment radiance is not black.
    Environment,
    /// Some material is unlit (`KHR_materials_unlit`): it shows its base colour.
    Unlit,
    /// Some material has a clear coat (`KHR_materials_clearcoat`).
    Clearcoat,
    /// Some material has a sheen layer (`KHR_materials_sheen`).
    Sheen,
    /// Some material has an anisotropic specular lobe (`KHR_materials_anisotropy`).
    Anisotropy,
    /// Some transmissive material absorbs inside (`KHR_materials_volume`).
    Volume,
    /// Some material has a thin-film layer (`KHR_materials_iridescence`).
    Iridescence,
    /// Some transmissive material disperses light (`KHR_materials_dispersion`).
    Dispersion,
    /// The job spec adds a sun (`--sun`): one more light sample per hit, and bounce
    /// rays leaving the scene look for its disk.
    Sun,
    /// The job spec adds an environment map (`--env-map`): one more light sample per
    /// hit, and rays leaving the scene look it up.
    EnvMap,
}

impl Effect {
    pub const ALL: [Effect; 16] = [
        Effect::DirectLight,
        Effect::Specular,
        Effect::Transmission,
        Effect::Emission,
        Effect::Textures,
        Effect::Alpha,
        Effect::Environment,
        Effect::Unlit,
        Effect::Clearcoat,
        Effect::Sheen,
        Effect::Anisotropy,
        Effect::Volume,
        Effect::Iridescence,
        Effect::Dispersion,
        Effect::Sun,
        Effect::EnvMap,
    ];

    fn bit(self) -> u16 {
        1 << (self as u8)
    }

    pub fn name(self) -> &'static str {
        match self {
            Effect::DirectLight => "direct_light",
            Effect::Specular => "specular",
            Effect::Transmission => "transmission",
            Effect::Emission => "emission",
            Effect::Textures => "textures",
            Effect::Alpha => "alpha",
            Effect::Environment => "environment",
            Effect::Unlit => "unlit",
            Effect::Clearcoat => "clearcoat",
            Effect::Sheen => "sheen",
            Effect::Anisotropy => "anisotropy",
            Effect::Volume => "volume",
            Effect::Iridescence => "iridescence",
            Effect::Dispersion => "dispersion",
            Effect::Sun => "sun",
            Effect::EnvMap => "env_map",
        }
    }

    pub fn from_name(name: &str) -> Option<Effect> {
        Effect::ALL.into_iter().find(|e| e.name() == name)
    }
}

/// A set of [`Effect`]s.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub struct Effects(u16);

impl Effects {
    pub const NONE: Effects = Effects(0);

    pub fn contains(self, e: Effect) -> bool {
        self.0 & e.bit() != 0
    }

    pub fn set(&mut self, e: Effect, on: bool) {
        if on {
            self.0 |= e.bit();
        } else {
            self.0 &= !e.bit();
        }
    }

    pub fn with(mut self, e: Effect) -> Effects {
        self.set(e, true);
        self
    }

    pub fn iter(self) -> impl Iterator<Item = Effect> {
        Effect::ALL.into_iter().filter(move |e| self.contains(*e))
    }

    pub fn names(self) -> Vec<&'static str> {
        self.iter().map(Effect::name).collect()
    }
}

impl Serialize for Effects {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_seq(self.names())
    }
}

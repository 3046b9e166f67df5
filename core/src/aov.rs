//! AOVs ("arbitrary output variables", `--aov albedo,normal,depth,samples`): what a
//! denoiser (Intel OIDN takes albedo and normal) or a compositor (depth) needs besides
//! the beauty image, written as more channels of the `--exr` file.
//!
//! Each is a property of a camera ray's first hit, averaged over the pixel's samples:
//! - `albedo` (`albedo.R/G/B`): the base colour there, textures and vertex colours
//!   applied, in [0, 1];
//! - `normal` (`normal.X/Y/Z`): the shading normal there, in world space, turned toward
//!   the camera (as Cycles' normal pass); an average of unit vectors, so shorter than 1
//!   where the samples see different surfaces;
//! - `depth` (`depth.Z`): the distance from the camera to the hit (from its position,
//!   or its image plane for an orthographic camera: `Camera::depth_of`), averaged
//!   over the samples that hit something; `+inf` where none did (OpenEXR's and Nuke's
//!   convention for "nothing there", what a compositor's Z-defocus expects);
//! - `samples` (`samples.Y`): the samples each pixel took (every pixel takes `spp`
//!   today; adaptive sampling will make it vary).
//!
//! A sample whose camera ray leaves the scene adds zero albedo and normal (what OIDN
//! expects of background pixels) and nothing to depth.
//!
//! The sums are fixed-point integers like the film's (`crate::film`), so a pixel's AOVs
//! are the same bits however its samples were split over threads, workers and passes.

use glam::Vec3;

use crate::film::FIXED_SCALE;

/// One AOV a job can ask for.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Aov {
    Albedo = 0,
    Normal = 1,
    Depth = 2,
    Samples = 3,
}

impl Aov {
    pub const ALL: [Aov; 4] = [Aov::Albedo, Aov::Normal, Aov::Depth, Aov::Samples];

    /// The one spelling of each name (the flag, `JobSpec.aovs`, the EXR's layer).
    pub const fn name(self) -> &'static str {
        match self {
            Aov::Albedo => "albedo",
            Aov::Normal => "normal",
            Aov::Depth => "depth",
            Aov::Samples => "samples",
        }
    }

    pub fn from_name(name: &str) -> Option<Aov> {
        Aov::ALL.into_iter().find(|a| a.name() == name)
    }

    /// Its channels in the EXR, "layer.channel".
    pub const fn channels(self) -> &'static [&'static str] {
        match self {
            Aov::Albedo => &["albedo.R", "albedo.G", "albedo.B"],
            Aov::Normal => &["normal.X", "normal.Y", "normal.Z"],
            Aov::Depth => &["depth.Z"],
            Aov::Samples => &["samples.Y"],
        }
    }
}

/// A set of AOVs (empty by default: nothing recorded, nothing paid).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub struct AovSet(u8);

/// A list of AOV names that is not one: the name that is wrong and why.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum AovError {
    #[error("unknown AOV {0:?} (expected albedo, normal, depth or samples)")]
    Unknown(String),
    #[error("AOV {0:?} is named twice")]
    Twice(String),
}

impl AovSet {
    pub const NONE: AovSet = AovSet(0);

    pub fn with(self, aov: Aov) -> AovSet {
        AovSet(self.0 | 1 << aov as u8)
    }

    pub fn contains(self, aov: Aov) -> bool {
        self.0 & (1 << aov as u8) != 0
    }

    pub fn is_empty(self) -> bool {
        self.0 == 0
    }

    /// Whether tracing must record first hits: any AOV but `samples`, which needs none.
    pub fn records_hits(self) -> bool {
        self.contains(Aov::Albedo) || self.contains(Aov::Normal) || self.contains(Aov::Depth)
    }

    /// The set's AOVs in [`Aov::ALL`]'s order.
    pub fn iter(self) -> impl Iterator<Item = Aov> {
        Aov::ALL.into_iter().filter(move |&a| self.contains(a))
    }

    /// The names, in [`Aov::ALL`]'s order (`JobSpec.aovs` as the coordinator keeps it).
    pub fn names(self) -> Vec<String> {
        self.iter().map(|a| a.name().to_string()).collect()
    }

    /// The set `names` spells, each name once.
    pub fn parse<S: AsRef<str>>(names: &[S]) -> Result<AovSet, AovError> {
        let mut set = AovSet::NONE;
        for n in names {
            let n = n.as_ref();
            let a = Aov::from_name(n).ok_or_else(|| AovError::Unknown(n.to_string()))?;
            if set.contains(a) {
                return Err(AovError::Twice(n.to_string()));
            }
            set = set.with(a);
        }
        Ok(set)
    }
}

/// What a camera ray's first hit gives the AOVs.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FirstHit {
    pub albedo: Vec3,
    pub normal: Vec3,
    /// Distance from the camera (`crate::camera::Camera::depth_of`).
    pub depth: f32,
}

/// Words of one pixel's AOV sums: albedo (3), normal (3), depth, hits.
pub const AOV_WORDS: usize = 8;
/// The largest depth summed (2^22, as the film's largest contribution): at the most
/// samples a job takes (2^16) a pixel's depth sum stays below 2^62.
pub const MAX_DEPTH_SUMMED: f32 = (1u32 << 22) as f32;

/// `x` in fixed point (24 fractional bits), rounded half away from zero; `x` is finite
/// and at most [`MAX_DEPTH_SUMMED`] in size.
fn fixed(x: f32) -> i64 {
    (f64::from(x) * FIXED_SCALE).round() as i64
}

impl FirstHit {
    /// Its contribution to a pixel's AOV sums, or `None` when a value is not finite
    /// (dropped, as the film drops non-finite radiance). Albedo is clamped to [0, 1],
    /// the normal to unit length, depth to [0, MAX_DEPTH_SUMMED]: bounded values, so
    /// no sum of at most 2^16 samples can overflow, signed or not, and their integer
    /// sums are exact in any order.
    pub fn to_fixed(&self) -> Option<[i64; AOV_WORDS]> {
        if !(self.albedo.is_finite() && self.normal.is_finite() && self.depth.is_finite()) {
            return None;
        }
        let a = self.albedo.clamp(Vec3::ZERO, Vec3::ONE);
        let n = self.normal.clamp_length_max(1.0);
        let d = self.depth.clamp(0.0, MAX_DEPTH_SUMMED);
        Some([
            fixed(a.x),
            fixed(a.y),
            fixed(a.z),
            fixed(n.x),
            fixed(n.y),
            fixed(n.z),
            fixed(d),
            1,
        ])
    }
}

/// Add `b` to `a`, word by word. Wrapping: the values are bounded so no sum overflows
/// (see [`FirstHit::to_fixed`]), and wrapping addition is associative even for the
/// normals' negative words, where saturation would not be.
#[inline]
pub fn add_aov_sums(a: &mut [i64; AOV_WORDS], b: &[i64; AOV_WORDS]) {
    for (x, y) in a.iter_mut().zip(b) {
        *x = x.wrapping_add(*y);
    }
}

/// Per-pixel AOV sums of an image.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct AovFilm {
    pub set: AovSet,
    sums: Vec<[i64; AOV_WORDS]>,
}

impl AovFilm {
    pub fn new(set: AovSet, pixels: usize) -> AovFilm {
        AovFilm {
            set,
            sums: vec![[0; AOV_WORDS]; pixels],
        }
    }

    /// The bytes its sums take in memory.
    pub fn heap_bytes(&self) -> u64 {
        (self.sums.len() as u64).saturating_mul(std::mem::size_of::<[i64; AOV_WORDS]>() as u64)
    }

    /// Add fixed-point sums to `pixel` (out-of-range pixels are ignored).
    #[inline]
    pub fn add_fixed(&mut self, pixel: u32, value: &[i64; AOV_WORDS]) {
        if let Some(s) = self.sums.get_mut(pixel as usize) {
            add_aov_sums(s, value);
        }
    }

    pub fn sum_fixed(&self, pixel: u32) -> [i64; AOV_WORDS] {
        self.sums
            .get(pixel as usize)
            .copied()
            .unwrap_or([0; AOV_WORDS])
    }

    /// Set `pixel`'s sums (a pixel put back as it was at a pass boundary).
    pub fn set_fixed(&mut self, pixel: u32, value: [i64; AOV_WORDS]) {
        if let Some(s) = self.sums.get_mut(pixel as usize) {
            *s = value;
        }
    }

    pub fn merge(&mut self, other: &AovFilm) {
        for (a, b) in self.sums.iter_mut().zip(&other.sums) {
            add_aov_sums(a, b);
        }
    }

    /// The channels of the set's AOVs for an image of `spp` samples per pixel, as
    /// (name, one value per pixel), in [`Aov::ALL`]'s order. `stops` is the film's
    /// per-pixel samples where adaptive sampling stopped a pixel early (0: `spp`).
    pub fn channels(&self, spp: u32, stops: Option<&[u32]>) -> Vec<(&'static str, Vec<f32>)> {
        let samples = |p: usize| -> u32 {
            match stops.and_then(|s| s.get(p)) {
                Some(&n) if n > 0 => n,
                _ => spp.max(1),
            }
        };
        let mean = |w: usize| -> Vec<f32> {
            self.sums
                .iter()
                .enumerate()
                .map(|(p, s)| (s[w] as f64 / (FIXED_SCALE * f64::from(samples(p)))) as f32)
                .collect()
        };
        let mut out = Vec::new();
        for aov in self.set.iter() {
            let names = aov.channels();
            match aov {
                Aov::Albedo => (0..3).for_each(|k| out.push((names[k], mean(k)))),
                Aov::Normal => (0..3).for_each(|k| out.push((names[k], mean(3 + k)))),
                Aov::Depth => out.push((
                    names[0],
                    self.sums
                        .iter()
                        .map(|s| match s[7] {
                            0 => f32::INFINITY,
                            hits => (s[6] as f64 / FIXED_SCALE / hits as f64) as f32,
                        })
                        .collect(),
                )),
                Aov::Samples => out.push((
                    names[0],
                    (0..self.sums.len()).map(|p| samples(p) as f32).collect(),
                )),
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_parse_once_each() {
        let set = AovSet::parse(&["depth", "albedo"]).expect("valid");
        assert!(set.contains(Aov::Albedo) && set.contains(Aov::Depth));
        assert!(!set.contains(Aov::Normal) && set.records_hits());
        assert_eq!(set.names(), ["albedo", "depth"]);
        assert!(!AovSet::parse(&["samples"]).expect("samples").records_hits());
        assert_eq!(
            AovSet::parse(&["albedo", "albedo"]),
            Err(AovError::Twice("albedo".into()))
        );
        let e = AovSet::parse(&["alpha"]).expect_err("unknown");
        assert_eq!(
            e.to_string(),
            "unknown AOV \"alpha\" (expected albedo, normal, depth or samples)"
        );
        assert!(AovSet::parse::<&str>(&[]).expect("none").is_empty());
    }

    #[test]
    fn sums_average_over_samples_and_depth_over_hits() {
        let set = AovSet::parse(&["albedo", "normal", "depth", "samples"]).expect("all");
        let mut film = AovFilm::new(set, 2);
        let hit = FirstHit {
            albedo: Vec3::new(0.5, 2.0, -1.0),
            normal: Vec3::new(0.0, -1.0, 0.0),
            depth: 3.0,
        };
        let f = hit.to_fixed().expect("finite");
        // Pixel 0: two samples hit, two missed; pixel 1: every sample missed.
        film.add_fixed(0, &f);
        film.add_fixed(0, &f);
        let ch = film.channels(4, None);
        let get = |name: &str| ch.iter().find(|c| c.0 == name).expect(name).1.clone();
        assert_eq!(get("albedo.R"), [0.25, 0.0]);
        assert_eq!(get("albedo.G"), [0.5, 0.0], "clamped to 1");
        assert_eq!(get("albedo.B"), [0.0, 0.0], "clamped to 0");
        assert_eq!(get("normal.Y"), [-0.5, 0.0]);
        assert_eq!(get("depth.Z"), [3.0, f32::INFINITY]);
        assert_eq!(get("samples.Y"), [4.0, 4.0]);
        let nan = FirstHit {
            depth: f32::NAN,
            ..hit
        };
        assert_eq!(nan.to_fixed(), None);
    }
}

//! Tone curves: how exposed linear radiance, which has no upper bound, becomes display
//! values in [0, 1] before the sRGB encoding of an 8-bit image (PNG, JPEG). The EXR
//! output never passes through here: it stays linear radiance.
//!
//! - `clamp`: no curve; values above 1 clip. What dray wrote before it had curves, and
//!   with exposure 0 still the same bytes.
//! - `reinhard`: Reinhard et al. 2002's global operator `x / (1 + x)`, per channel (as
//!   three.js and Bevy apply it): never clips, but flattens contrast and washes out
//!   highlights.
//! - `aces`: the ACES filmic reference rendering and output transforms (RRT + sRGB ODT),
//!   as fitted by Stephen Hill (the "ACES fitted" curve of three.js and the BakingLab),
//!   with its 1/0.6 exposure. Contrasty and saturated: it crushes shadows.
//! - `agx`: Troy Sobotka's AgX as Blender (4.0 and later) makes it by default: a
//!   16.5-stop log encoding around mid-grey in a slightly desaturated Rec.2020 space,
//!   then a sigmoid (Benjamin Wrensch's polynomial fit, as three.js and Filament use).
//!
//! The default for 8-bit output is [`Tonemap::DEFAULT`] (`agx`): it keeps 6.5 stops
//! above mid-grey before anything reaches white, with a soft shoulder, and keeps the
//! shadows open (a sunlit wall, the shade beside it and a lamp's glow in one image, as
//! photometric glTF scenes have); very bright saturated light goes towards white instead
//! of clipping per channel; and it is what Blender shows a glTF scene with, so an image
//! from dray looks like the one the scene was made with. Numbers: docs/exposure.md.

use glam::{Mat3, Vec3};

/// A tone curve (see the module documentation).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Tonemap {
    Clamp,
    Reinhard,
    Aces,
    Agx,
}

/// A tone curve name that is not one of [`Tonemap::NAMES`].
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("unknown tone curve {0:?} (expected clamp, reinhard, aces or agx)")]
pub struct UnknownTonemap(pub String);

impl Tonemap {
    /// Every curve, in the order help texts list them.
    pub const ALL: [Tonemap; 4] = [
        Tonemap::Clamp,
        Tonemap::Reinhard,
        Tonemap::Aces,
        Tonemap::Agx,
    ];
    /// Their names, as the `--tonemap` flag and `GetImageRequest.tonemap` take them.
    pub const NAMES: [&'static str; 4] = ["clamp", "reinhard", "aces", "agx"];
    /// The curve of 8-bit output when none is named (why: the module documentation).
    pub const DEFAULT: Tonemap = Tonemap::Agx;

    pub fn name(self) -> &'static str {
        match self {
            Tonemap::Clamp => "clamp",
            Tonemap::Reinhard => "reinhard",
            Tonemap::Aces => "aces",
            Tonemap::Agx => "agx",
        }
    }

    /// The curve named `s`; the empty string is [`Tonemap::DEFAULT`] (proto3's unset
    /// string).
    pub fn parse(s: &str) -> Result<Tonemap, UnknownTonemap> {
        if s.is_empty() {
            return Ok(Tonemap::DEFAULT);
        }
        Tonemap::ALL
            .into_iter()
            .find(|t| t.name() == s)
            .ok_or_else(|| UnknownTonemap(s.to_string()))
    }

    /// Display-linear RGB for exposed linear sRGB radiance `c`. Only `clamp` returns
    /// values outside [0, 1] (the sRGB encoding clamps them, as it always has).
    #[inline]
    pub fn apply(self, c: Vec3) -> Vec3 {
        match self {
            Tonemap::Clamp => c,
            Tonemap::Reinhard => {
                let c = c.max(Vec3::ZERO);
                c / (Vec3::ONE + c)
            }
            Tonemap::Aces => aces_fitted(c),
            Tonemap::Agx => agx(c),
        }
    }
}

impl std::fmt::Display for Tonemap {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for Tonemap {
    type Err = UnknownTonemap;
    fn from_str(s: &str) -> Result<Tonemap, UnknownTonemap> {
        Tonemap::parse(s)
    }
}

/// sRGB to ACES AP1 with the RRT's saturation (Hill's `ACESInputMat`), column-major.
const ACES_INPUT: Mat3 = Mat3::from_cols(
    Vec3::new(0.59719, 0.07600, 0.02840),
    Vec3::new(0.35458, 0.90834, 0.13383),
    Vec3::new(0.04823, 0.01566, 0.83777),
);
/// The ODT's saturation, AP1 back to sRGB (Hill's `ACESOutputMat`), column-major.
const ACES_OUTPUT: Mat3 = Mat3::from_cols(
    Vec3::new(1.60475, -0.10208, -0.00327),
    Vec3::new(-0.53108, 1.10813, -0.07276),
    Vec3::new(-0.07367, -0.00605, 1.07602),
);

/// Stephen Hill's fit of ACES RRT + sRGB ODT, with the 1/0.6 exposure that fit assumes
/// (so mid-grey 0.18 comes out near display 0.18, as with the other curves).
fn aces_fitted(c: Vec3) -> Vec3 {
    let v = ACES_INPUT * (c.max(Vec3::ZERO) / 0.6);
    let a = v * (v + 0.024_578_6) - 0.000_090_537;
    let b = v * (0.983_729 * v + 0.432_951) + 0.238_081;
    (ACES_OUTPUT * (a / b)).clamp(Vec3::ZERO, Vec3::ONE)
}

/// Linear sRGB to linear Rec.2020, column-major.
const SRGB_TO_REC2020: Mat3 = Mat3::from_cols(
    Vec3::new(0.6274, 0.0691, 0.0164),
    Vec3::new(0.3293, 0.9195, 0.0880),
    Vec3::new(0.0433, 0.0113, 0.8956),
);
/// Linear Rec.2020 to linear sRGB, column-major.
const REC2020_TO_SRGB: Mat3 = Mat3::from_cols(
    Vec3::new(1.6605, -0.1246, -0.0182),
    Vec3::new(-0.5876, 1.1329, -0.1006),
    Vec3::new(-0.0728, -0.0083, 1.1187),
);
/// AgX's inset (Blender's, in Rec.2020), column-major.
const AGX_INSET: Mat3 = Mat3::from_cols(
    Vec3::new(0.856_627_2, 0.137_318_97, 0.111_898_21),
    Vec3::new(0.095_121_24, 0.761_242, 0.076_799_42),
    Vec3::new(0.048_251_606, 0.101_439_04, 0.811_302_4),
);
/// AgX's outset (the inverse of Filament's `AgXOutsetMatrixInv`), column-major.
const AGX_OUTSET: Mat3 = Mat3::from_cols(
    Vec3::new(1.127_100_6, -0.141_329_76, -0.141_329_76),
    Vec3::new(-0.110_606_64, 1.157_823_7, -0.110_606_64),
    Vec3::new(-0.016_493_939, -0.016_493_939, 1.251_936_4),
);
/// AgX's log range: mid-grey (0.18) 10 stops down to 6.5 stops up.
const AGX_MIN_EV: f32 = -12.473_93;
const AGX_MAX_EV: f32 = 4.026_069;

/// AgX (base look): log encoding, sigmoid, back to linear with the 2.2 power Blender's
/// view transform uses, then to sRGB primaries and clipped to the gamut.
fn agx(c: Vec3) -> Vec3 {
    let v = AGX_INSET * (SRGB_TO_REC2020 * c);
    let v = v.max(Vec3::splat(1e-10));
    let v = v.to_array().map(|x| {
        let t = ((x.log2() - AGX_MIN_EV) / (AGX_MAX_EV - AGX_MIN_EV)).clamp(0.0, 1.0);
        agx_sigmoid(t)
    });
    let v = AGX_OUTSET * Vec3::from_array(v);
    let v = v.max(Vec3::ZERO).powf(2.2);
    (REC2020_TO_SRGB * v).clamp(Vec3::ZERO, Vec3::ONE)
}

/// Wrensch's sixth-order polynomial fit of AgX's default contrast sigmoid on [0, 1].
#[inline]
fn agx_sigmoid(x: f32) -> f32 {
    let x2 = x * x;
    let x4 = x2 * x2;
    15.5 * x4 * x2 - 40.14 * x4 * x + 31.96 * x4 - 6.868 * x2 * x + 0.4298 * x2 + 0.1191 * x
        - 0.00232
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip_and_empty_is_the_default() {
        for (t, n) in Tonemap::ALL.into_iter().zip(Tonemap::NAMES) {
            assert_eq!(t.name(), n);
            assert_eq!(Tonemap::parse(n), Ok(t));
        }
        assert_eq!(Tonemap::parse(""), Ok(Tonemap::DEFAULT));
        let e = Tonemap::parse("ACES").expect_err("names are lower case");
        assert!(e.to_string().contains("\"ACES\""), "{e}");
        assert!(
            e.to_string().contains("clamp, reinhard, aces or agx"),
            "{e}"
        );
    }

    #[test]
    fn clamp_is_the_identity() {
        for c in [Vec3::ZERO, Vec3::new(0.2, 1.5, -1.0), Vec3::splat(1e9)] {
            assert_eq!(Tonemap::Clamp.apply(c), c);
        }
    }

    #[test]
    fn curves_are_monotonic_bounded_and_keep_grey_grey() {
        for t in [Tonemap::Reinhard, Tonemap::Aces, Tonemap::Agx] {
            let mut last = -1.0f32;
            let mut x = 1e-6f32;
            while x < 1e6 {
                let y = t.apply(Vec3::splat(x));
                assert!(
                    y.min_element() >= 0.0 && y.max_element() <= 1.0,
                    "{t} {x}: {y}"
                );
                let spread = y.max_element() - y.min_element();
                assert!(spread < 0.02, "{t} turns grey {x} into {y}");
                assert!(y.y >= last - 1e-6, "{t} is not monotonic at {x}: {y}");
                last = y.y;
                x *= 1.1;
            }
            assert!(t.apply(Vec3::splat(1e6)).y > 0.99, "{t} reaches white");
            assert!(t.apply(Vec3::ZERO).max_element() < 0.01, "{t}");
            let neg = t.apply(Vec3::splat(-5.0));
            assert!(neg.is_finite() && neg.min_element() >= 0.0, "{t}: {neg}");
            let nan = t.apply(Vec3::splat(f32::NAN));
            assert!(nan.is_finite(), "{t}: {nan}");
        }
    }

    #[test]
    fn mid_grey_stays_near_mid_grey() {
        // Exposed mid-grey (0.18) comes out within a stop of display mid-grey on every
        // curve, so an automatic exposure that targets 0.18 gives a mid-grey image.
        for t in Tonemap::ALL {
            let y = t.apply(Vec3::splat(0.18)).y;
            assert!((0.09..=0.36).contains(&y), "{t}: 0.18 -> {y}");
        }
    }

    #[test]
    fn agx_sends_bright_saturated_light_to_white() {
        // A saturated red emitter 8 stops over mid-grey: clamp clips it to pure red,
        // AgX to a near-white with a red tint.
        let hot = Vec3::new(0.18 * 256.0, 0.0, 0.0);
        assert_eq!(Tonemap::Clamp.apply(hot).min(Vec3::ONE), Vec3::X);
        let y = Tonemap::Agx.apply(hot);
        assert!(y.x > 0.9 && y.y > 0.3 && y.x > y.y, "{y}");
    }
}

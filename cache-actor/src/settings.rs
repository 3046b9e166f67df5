//! The knobs of one job attempt, validated once when its walls open: the ray cache's
//! (`RayCacheSettings`) and the probability hit maps' (`PhmSettings`).
//!
//! Both arrive from the coordinator over the network, so every field is checked here
//! and turned into a typed value; the actors then never see a NaN radius, a threshold
//! outside [0, 1] or an unknown mode, and a bad job is refused with the field's name
//! instead of misbehaving later.

use dray_core::integrator::RayKind;
use dray_core::kind_set::KindSet;
use dray_core::wall::PhmBins;
use dray_proto::v1::{PhmSettings, RayCacheSettings};

/// The angle used when `angle_deg` is absent, in degrees.
pub const DEFAULT_ANGLE_DEG: f32 = 10.0;

/// The largest coarse pass (`coarse` x `coarse` camera rays).
pub const MAX_COARSE: u32 = 4096;

/// Which stored crossing answers a lookup when several are in range.
///
/// Every mode is a pure function of the *set* of entries in range (never of the order
/// they were stored in), so two cache hosts that received the same tickets in different
/// orders give the same answers.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Retrieve {
    /// The entry with the smallest key ([`crate::store::EntryKey`]): "the earliest
    /// stored" in the deterministic order of the rays that made the entries.
    First,
    /// The entry whose crossing point is closest; ties go to the smallest key.
    Nearest,
    /// The mean radiance of every entry in range, summed in key order.
    Average,
}

impl Retrieve {
    /// The name used in `RayCacheSettings.retrieve`.
    pub fn name(self) -> &'static str {
        match self {
            Retrieve::First => "first",
            Retrieve::Nearest => "nearest",
            Retrieve::Average => "average",
        }
    }
}

/// Why `RayCacheSettings` was refused; each names the offending field.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SettingsError {
    #[error("settings: missing (the coordinator fills in the defaults)")]
    Missing,
    #[error("settings: neither ray_cache settings nor phm (the walls would answer nothing)")]
    Neither,
    #[error("settings.radius must be finite and >= 0, got {0}")]
    Radius(f32),
    #[error("settings.angle_deg must be in (0, 90], got {0}")]
    Angle(f32),
    #[error("settings.retrieve must be \"first\", \"nearest\" or \"average\", got {0:?}")]
    Retrieve(String),
    #[error("settings.coarse must be at most {MAX_COARSE}, got {0}")]
    Coarse(u32),
    #[error(
        "settings.kinds: unknown ray kind {0:?} (expected one of {kinds})",
        kinds = RayKind::help_list(&RayKind::RADIANCE)
    )]
    Kinds(String),
    #[error("phm.res must be in 1..={MAX_PHM_RES}, got {0}")]
    PhmRes(u32),
    #[error("phm.dirs must be in 1..={MAX_PHM_DIRS}, got {0}")]
    PhmDirs(u32),
    #[error("phm.prior must be finite and >= 0, got {0}")]
    PhmPrior(f32),
    #[error("phm.miss must be in [0, 0.5], got {0}")]
    PhmMiss(f32),
    #[error("phm.hit must be in [0.5, 1], got {0}")]
    PhmHit(f32),
    #[error("phm.mode must be \"consistent\" or \"inconsistent\", got {0:?}")]
    PhmMode(String),
    #[error("phm.reprobe must be in [0, 1], got {0}")]
    PhmReprobe(f32),
    #[error(
        "phm.kinds: unknown ray kind {0:?} (expected one of {kinds})",
        kinds = RayKind::help_list(&RayKind::ALL)
    )]
    PhmKinds(String),
}

/// Validated ray-cache settings of one job attempt.
#[derive(Clone, Debug, PartialEq)]
pub struct CacheSettings {
    /// Lookup radius on the wall, scene units; 0 never answers.
    pub radius: f32,
    /// Largest angle between the ray and a stored direction, degrees, in (0, 90].
    pub angle_deg: f32,
    /// `cos(angle_deg)`, computed once in f64: a stored direction `s` qualifies when
    /// `dot(d, s) >= cos_min`.
    pub cos_min: f64,
    /// Which entry answers when several are in range.
    pub retrieve: Retrieve,
    /// Coarse pass size (0: none). Kept for the statistics; the cache host does not
    /// trace.
    pub coarse: u32,
    /// Ray kinds the workers look up, as a bit mask over `RayKind as u8`. The workers
    /// choose which rays to send (the `options` of each lookup); the host only checks
    /// that the job names real kinds.
    pub kinds: u8,
    /// Whether tickets of main-pass rays store radiance when they close. With `false`
    /// only tickets opened by coarse-pass rays (`FLAG_COARSE` in the ray record) store,
    /// so the main pass reads caches that the coarse pass filled and froze: the same job
    /// gives the same bits every run. Until the coarse pass runs, that means nothing is
    /// stored and every lookup misses (the exact image).
    pub fill: bool,
}

impl CacheSettings {
    /// Validate the coordinator's settings.
    pub fn from_proto(s: Option<&RayCacheSettings>) -> Result<CacheSettings, SettingsError> {
        let s = s.ok_or(SettingsError::Missing)?;
        if !(s.radius.is_finite() && s.radius >= 0.0) {
            return Err(SettingsError::Radius(s.radius));
        }
        let angle_deg = s.angle_deg.unwrap_or(DEFAULT_ANGLE_DEG);
        // Written so that NaN fails too.
        if !(angle_deg > 0.0 && angle_deg <= 90.0) {
            return Err(SettingsError::Angle(angle_deg));
        }
        let retrieve = match s.retrieve.as_str() {
            "" | "nearest" => Retrieve::Nearest,
            "first" => Retrieve::First,
            "average" => Retrieve::Average,
            other => return Err(SettingsError::Retrieve(other.to_string())),
        };
        if s.coarse > MAX_COARSE {
            return Err(SettingsError::Coarse(s.coarse));
        }
        let kinds = parse_kinds(&s.kinds)?;
        Ok(CacheSettings {
            radius: s.radius,
            angle_deg,
            cos_min: f64::from(angle_deg).to_radians().cos(),
            retrieve,
            coarse: s.coarse,
            kinds,
            fill: s.fill.unwrap_or(s.coarse == 0),
        })
    }

    /// Whether `kind` is one the job looks up.
    pub fn looks_up(&self, kind: RayKind) -> bool {
        self.kinds & (1 << kind as u8) != 0
    }
}

/// `"camera,diffuse"` → bit mask ([`KindSet`]); empty means all four cacheable kinds.
fn parse_kinds(s: &str) -> Result<u8, SettingsError> {
    let kinds = KindSet::parse(s, &RayKind::RADIANCE).map_err(|e| SettingsError::Kinds(e.name))?;
    Ok(if kinds.is_empty() {
        KindSet::cache_default()
    } else {
        kinds
    }
    .bits())
}

/// Texels per wall edge used when `phm.res` is absent, and the largest accepted.
pub const DEFAULT_PHM_RES: u32 = 4;
pub const MAX_PHM_RES: u32 = 64;
/// Direction bins used when `phm.dirs` is absent (Bolstad's 12), and the most accepted.
pub const DEFAULT_PHM_DIRS: u32 = 12;
pub const MAX_PHM_DIRS: u32 = 256;
/// Prior weight (in rays on each side of 0.5) when `phm.prior` is absent.
pub const DEFAULT_PHM_PRIOR: f32 = 100.0;
/// Decision thresholds when `phm.miss` / `phm.hit` are absent.
pub const DEFAULT_PHM_MISS: f32 = 0.1;
pub const DEFAULT_PHM_HIT: f32 = 0.9;
/// Re-probe rate of decided cells (consistent mode) when `phm.reprobe` is absent.
pub const DEFAULT_PHM_REPROBE: f32 = 0.1;

/// Whether a hit map's decisions are final.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PhmMode {
    /// Decided cells keep being probed at rate `reprobe` and follow their counts, so a
    /// decision the evidence contradicts is corrected. It does not converge to the exact
    /// image: a cell whose true hit rate lies at or below `miss` (or at or above `hit`)
    /// stays decided, and the rays it skips (or occludes) that would have gone the other
    /// way keep their bias at any sample count.
    Consistent,
    /// A cell that has decided never changes again (Bolstad's original scheme): no
    /// probes are spent on decided cells, at the price of keeping early mistakes.
    Inconsistent,
}

impl PhmMode {
    /// The name used in `PhmSettings.mode`.
    pub fn name(self) -> &'static str {
        match self {
            PhmMode::Consistent => "consistent",
            PhmMode::Inconsistent => "inconsistent",
        }
    }
}

/// Validated hit-map settings of one job attempt.
#[derive(Clone, Debug, PartialEq)]
pub struct HitMapSettings {
    /// How every wall's map is binned; the workers bin the same way.
    pub bins: PhmBins,
    /// Prior weight: a cell starts as `prior` hits and `prior` misses. Finite, >= 0.
    pub prior: f32,
    /// A cell with hit probability `p <= miss` predicts a miss; `p >= hit` a hit.
    /// `0 <= miss <= 0.5 <= hit <= 1`.
    pub miss: f32,
    pub hit: f32,
    pub mode: PhmMode,
    /// Consistent mode: the fraction of rays at decided cells probed anyway, [0, 1].
    pub reprobe: f32,
    /// Ray kinds that consult the maps, a bit mask over `RayKind as u8`. As for the
    /// ray cache, the workers choose which rays carry option bit 2; the host only
    /// checks that the job names real kinds.
    pub kinds: u8,
}

impl HitMapSettings {
    /// Validate the coordinator's settings, filling in the defaults of absent fields.
    pub fn from_proto(s: &PhmSettings) -> Result<HitMapSettings, SettingsError> {
        let res = s.res.unwrap_or(DEFAULT_PHM_RES);
        if !(1..=MAX_PHM_RES).contains(&res) {
            return Err(SettingsError::PhmRes(res));
        }
        let dirs = s.dirs.unwrap_or(DEFAULT_PHM_DIRS);
        if !(1..=MAX_PHM_DIRS).contains(&dirs) {
            return Err(SettingsError::PhmDirs(dirs));
        }
        let prior = s.prior.unwrap_or(DEFAULT_PHM_PRIOR);
        if !(prior.is_finite() && prior >= 0.0) {
            return Err(SettingsError::PhmPrior(prior));
        }
        // Written so that NaN fails too.
        let miss = s.miss.unwrap_or(DEFAULT_PHM_MISS);
        if !(0.0..=0.5).contains(&miss) {
            return Err(SettingsError::PhmMiss(miss));
        }
        let hit = s.hit.unwrap_or(DEFAULT_PHM_HIT);
        if !(0.5..=1.0).contains(&hit) {
            return Err(SettingsError::PhmHit(hit));
        }
        let mode = match s.mode.as_str() {
            "" | "consistent" => PhmMode::Consistent,
            "inconsistent" => PhmMode::Inconsistent,
            other => return Err(SettingsError::PhmMode(other.to_string())),
        };
        let reprobe = s.reprobe.unwrap_or(DEFAULT_PHM_REPROBE);
        if !(0.0..=1.0).contains(&reprobe) {
            return Err(SettingsError::PhmReprobe(reprobe));
        }
        Ok(HitMapSettings {
            bins: PhmBins::new(res, dirs),
            prior,
            miss,
            hit,
            mode,
            reprobe,
            kinds: parse_phm_kinds(&s.kinds)?,
        })
    }

    /// Whether `kind` is one the job consults the maps for.
    pub fn consults(&self, kind: RayKind) -> bool {
        self.kinds & (1 << kind as u8) != 0
    }
}

/// `"shadow,ambient_occlusion"` → bit mask over every kind ([`KindSet`]); empty means
/// shadow rays only (the source's use).
fn parse_phm_kinds(s: &str) -> Result<u8, SettingsError> {
    let kinds = KindSet::parse(s, &RayKind::ALL).map_err(|e| SettingsError::PhmKinds(e.name))?;
    Ok(if kinds.is_empty() {
        KindSet::phm_default()
    } else {
        kinds
    }
    .bits())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn proto(radius: f32) -> RayCacheSettings {
        RayCacheSettings {
            radius,
            ..Default::default()
        }
    }

    #[test]
    fn defaults_fill_in() {
        let s = CacheSettings::from_proto(Some(&proto(0.5))).unwrap();
        assert_eq!(s.angle_deg, DEFAULT_ANGLE_DEG);
        assert_eq!(s.retrieve, Retrieve::Nearest);
        assert!(s.fill);
        assert!(s.looks_up(RayKind::Camera) && s.looks_up(RayKind::Diffuse));
        assert!(!s.looks_up(RayKind::Shadow));
        assert!((s.cos_min - 10f64.to_radians().cos()).abs() < 1e-15);
    }

    #[test]
    fn bad_fields_are_named() {
        let bad = [
            (proto(-1.0), "settings.radius"),
            (proto(f32::NAN), "settings.radius"),
            (proto(f32::INFINITY), "settings.radius"),
            (
                RayCacheSettings {
                    angle_deg: Some(0.0),
                    ..proto(1.0)
                },
                "settings.angle_deg",
            ),
            (
                RayCacheSettings {
                    angle_deg: Some(90.5),
                    ..proto(1.0)
                },
                "settings.angle_deg",
            ),
            (
                RayCacheSettings {
                    angle_deg: Some(f32::NAN),
                    ..proto(1.0)
                },
                "settings.angle_deg",
            ),
            (
                RayCacheSettings {
                    retrieve: "best".into(),
                    ..proto(1.0)
                },
                "settings.retrieve",
            ),
            (
                RayCacheSettings {
                    coarse: 4097,
                    ..proto(1.0)
                },
                "settings.coarse",
            ),
            (
                RayCacheSettings {
                    kinds: "camera,shadow".into(),
                    ..proto(1.0)
                },
                "settings.kinds",
            ),
        ];
        for (p, field) in bad {
            let e = CacheSettings::from_proto(Some(&p)).unwrap_err();
            assert!(e.to_string().starts_with(field), "{e}");
        }
        assert_eq!(
            CacheSettings::from_proto(None).unwrap_err(),
            SettingsError::Missing
        );
    }

    #[test]
    fn edges_are_accepted() {
        let p = RayCacheSettings {
            angle_deg: Some(90.0),
            retrieve: "average".into(),
            coarse: 4096,
            kinds: " camera , diffuse,camera,".into(),
            fill: Some(false),
            ..proto(0.0)
        };
        let s = CacheSettings::from_proto(Some(&p)).unwrap();
        assert_eq!(s.retrieve, Retrieve::Average);
        assert!(!s.fill);
        assert!(s.looks_up(RayKind::Camera) && !s.looks_up(RayKind::Reflection));
    }

    #[test]
    fn phm_defaults_fill_in() {
        let s = HitMapSettings::from_proto(&PhmSettings::default()).unwrap();
        assert_eq!(s.bins, PhmBins::new(4, 12));
        assert_eq!(s.bins.cells(), 192);
        assert_eq!((s.prior, s.miss, s.hit, s.reprobe), (100.0, 0.1, 0.9, 0.1));
        assert_eq!(s.mode, PhmMode::Consistent);
        assert!(s.consults(RayKind::Shadow));
        assert!(!s.consults(RayKind::AmbientOcclusion) && !s.consults(RayKind::Camera));
    }

    #[test]
    fn phm_edges_are_accepted() {
        let p = PhmSettings {
            res: Some(64),
            dirs: Some(256),
            prior: Some(0.0),
            miss: Some(0.5),
            hit: Some(0.5),
            mode: "inconsistent".into(),
            reprobe: Some(1.0),
            kinds: "camera,ambient_occlusion, shadow,".into(),
            ..Default::default()
        };
        let s = HitMapSettings::from_proto(&p).unwrap();
        assert_eq!(s.mode, PhmMode::Inconsistent);
        assert!(s.consults(RayKind::Camera) && s.consults(RayKind::AmbientOcclusion));
        assert!(!s.consults(RayKind::Diffuse));
        let p = PhmSettings {
            res: Some(1),
            dirs: Some(1),
            miss: Some(0.0),
            hit: Some(1.0),
            reprobe: Some(0.0),
            mode: "consistent".into(),
            ..Default::default()
        };
        let s = HitMapSettings::from_proto(&p).unwrap();
        assert_eq!(s.bins.cells(), 1);
    }

    #[test]
    fn bad_phm_fields_are_named() {
        let base = PhmSettings::default;
        let bad = [
            (
                PhmSettings {
                    res: Some(0),
                    ..base()
                },
                "phm.res",
            ),
            (
                PhmSettings {
                    res: Some(65),
                    ..base()
                },
                "phm.res",
            ),
            (
                PhmSettings {
                    dirs: Some(0),
                    ..base()
                },
                "phm.dirs",
            ),
            (
                PhmSettings {
                    dirs: Some(257),
                    ..base()
                },
                "phm.dirs",
            ),
            (
                PhmSettings {
                    prior: Some(-1.0),
                    ..base()
                },
                "phm.prior",
            ),
            (
                PhmSettings {
                    prior: Some(f32::INFINITY),
                    ..base()
                },
                "phm.prior",
            ),
            (
                PhmSettings {
                    prior: Some(f32::NAN),
                    ..base()
                },
                "phm.prior",
            ),
            (
                PhmSettings {
                    miss: Some(-0.1),
                    ..base()
                },
                "phm.miss",
            ),
            (
                PhmSettings {
                    miss: Some(0.6),
                    ..base()
                },
                "phm.miss",
            ),
            (
                PhmSettings {
                    miss: Some(f32::NAN),
                    ..base()
                },
                "phm.miss",
            ),
            (
                PhmSettings {
                    hit: Some(0.4),
                    ..base()
                },
                "phm.hit",
            ),
            (
                PhmSettings {
                    hit: Some(1.01),
                    ..base()
                },
                "phm.hit",
            ),
            (
                PhmSettings {
                    hit: Some(f32::NAN),
                    ..base()
                },
                "phm.hit",
            ),
            (
                PhmSettings {
                    mode: "sometimes".into(),
                    ..base()
                },
                "phm.mode",
            ),
            (
                PhmSettings {
                    reprobe: Some(1.5),
                    ..base()
                },
                "phm.reprobe",
            ),
            (
                PhmSettings {
                    reprobe: Some(f32::NAN),
                    ..base()
                },
                "phm.reprobe",
            ),
            (
                PhmSettings {
                    kinds: "shadow,light".into(),
                    ..base()
                },
                "phm.kinds",
            ),
        ];
        for (p, field) in bad {
            let e = HitMapSettings::from_proto(&p).unwrap_err();
            assert!(e.to_string().starts_with(field), "{field}: {e}");
        }
    }
}

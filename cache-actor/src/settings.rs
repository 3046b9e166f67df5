//! A job's cache knobs, parsed once into typed values: the ray cache's
//! (`RayCacheSettings`), the probability hit maps' (`PhmSettings`) and the coarse pass's
//! sampling (`JobSpec.coarse_sampling`), with every default and bound defined here.
//!
//! Strings stay on the wire (the protos are unchanged); every reader parses them here
//! and then matches on the enums:
//! - the coordinator, when a job is submitted: it refuses a bad field by name
//!   (`INVALID_ARGUMENT` with these messages) and writes the resolved settings back into
//!   the spec ([`WallSettings::to_proto`]), so GetJob, the workers and the cache hosts
//!   all read the same values;
//! - the worker, when it plans a job (which kinds ask the caches and maps, the maps'
//!   binning, fill, the coarse pass);
//! - the cache host, when its walls open: the actors then never see a NaN radius, a
//!   threshold outside [0, 1] or an unknown mode.
//!
//! This module is in dray-cache because it is the lowest crate that both the
//! coordinator and the worker depend on and that knows the protobuf types; dray-core
//! (below everything, and used without a cluster by `dray render`) knows no protobuf.
//! dray-cache depends only on dray-core, dray-proto, dray-net and dray-sync, so the
//! dependency graph stays acyclic. The bounds are in [`crate::bounds`].

use dray_core::integrator::RayKind;
use dray_core::kind_set::KindSet;
use dray_core::wall::PhmBins;
use dray_proto::v1::{PhmSettings, RayCacheSettings};

pub use crate::bounds::{MAX_COARSE, MAX_PHM_DIRS, MAX_PHM_RES};

/// A knob whose values are names: the names are defined once, by the enum.
pub trait Named: Copy + PartialEq + Sized + 'static {
    /// Every value, in the order the help and the messages list them.
    const ALL: &'static [Self];
    /// The value's name on the wire and on the command line.
    fn name(self) -> &'static str;
    /// The value named `name`, if any (names are case-sensitive).
    fn from_name(name: &str) -> Option<Self> {
        Self::ALL.iter().copied().find(|v| v.name() == name)
    }
    /// The names for a message: "a, b or c".
    fn choices() -> String {
        let names: Vec<&str> = Self::ALL.iter().map(|v| v.name()).collect();
        match names.split_last() {
            Some((last, [])) => last.to_string(),
            Some((last, rest)) => format!("{} or {last}", rest.join(", ")),
            None => String::new(),
        }
    }
}

/// `value`, or `default` when it is empty (an absent string on the wire).
fn named_or<T: Named>(value: &str, default: T) -> Option<T> {
    if value.is_empty() {
        Some(default)
    } else {
        T::from_name(value)
    }
}

/// The angle used when `angle_deg` is absent, in degrees.
pub const DEFAULT_ANGLE_DEG: f32 = 10.0;

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
    /// When `retrieve` is absent.
    pub const DEFAULT: Retrieve = Retrieve::Nearest;

    /// The name used in `RayCacheSettings.retrieve`.
    pub const fn name(self) -> &'static str {
        match self {
            Retrieve::First => "first",
            Retrieve::Nearest => "nearest",
            Retrieve::Average => "average",
        }
    }
}

impl Named for Retrieve {
    const ALL: &'static [Retrieve] = &[Retrieve::First, Retrieve::Nearest, Retrieve::Average];
    fn name(self) -> &'static str {
        Retrieve::name(self)
    }
}

/// Where a job's walls (each holding its ray cache and its hit map) are placed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Placement {
    /// Every worker holds a replica of every wall (the default): dray's own for ray
    /// caches, after Bolstad 2017's per-server map proxies for hit maps.
    Sender,
    /// Each wall once, beside its domain's owner.
    Remote,
}

impl Placement {
    /// When `placement` is absent (and, for the hit maps, the job has no ray cache).
    pub const DEFAULT: Placement = Placement::Sender;

    /// The name used in `RayCacheSettings.placement` and `PhmSettings.placement`.
    pub const fn name(self) -> &'static str {
        match self {
            Placement::Sender => "sender",
            Placement::Remote => "remote",
        }
    }
}

impl Named for Placement {
    const ALL: &'static [Placement] = &[Placement::Sender, Placement::Remote];
    fn name(self) -> &'static str {
        Placement::name(self)
    }
}

/// Where each coarse-pass ray goes through its coarse pixel (`JobSpec.coarse_sampling`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CoarseSampling {
    /// Through the coarse pixel's centre (the default).
    Centres,
    /// Through a random point of the coarse pixel (Little 2011's recommendation).
    Random,
}

impl CoarseSampling {
    /// When a job with a coarse pass leaves `coarse_sampling` empty.
    pub const DEFAULT: CoarseSampling = CoarseSampling::Centres;

    /// The name used in `JobSpec.coarse_sampling`.
    pub const fn name(self) -> &'static str {
        match self {
            CoarseSampling::Centres => "centres",
            CoarseSampling::Random => "random",
        }
    }

    /// `JobSpec.coarse_sampling`; empty means the default.
    pub fn from_proto(s: &str) -> Result<CoarseSampling, SettingsError> {
        named_or(s, CoarseSampling::DEFAULT)
            .ok_or_else(|| SettingsError::CoarseSampling(s.to_string()))
    }
}

impl Named for CoarseSampling {
    const ALL: &'static [CoarseSampling] = &[CoarseSampling::Centres, CoarseSampling::Random];
    fn name(self) -> &'static str {
        CoarseSampling::name(self)
    }
}

/// Why a job's cache settings were refused; each message starts with the field's name
/// in the `JobSpec`.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SettingsError {
    #[error("settings: neither ray_cache settings nor phm (the walls would answer nothing)")]
    Neither,
    #[error("ray_cache.radius must be finite and >= 0, got {0}")]
    Radius(f32),
    #[error("ray_cache.angle_deg must be in (0, 90] degrees, got {0}")]
    Angle(f32),
    #[error("ray_cache.retrieve must be {choices}, got {0:?}", choices = Retrieve::choices())]
    Retrieve(String),
    #[error("ray_cache.coarse must be in 0..={MAX_COARSE}, got {0}")]
    Coarse(u32),
    #[error(
        "ray_cache.kinds: {0:?} cannot be cached (expected one of {kinds}; shadow and ao rays \
         carry no radiance of their own)",
        kinds = RayKind::help_list(&RayKind::RADIANCE)
    )]
    Kinds(String),
    #[error("ray_cache.placement must be {choices}, got {0:?}", choices = Placement::choices())]
    Placement(String),
    #[error(
        "coarse_sampling must be {choices}, got {0:?}",
        choices = CoarseSampling::choices()
    )]
    CoarseSampling(String),
    #[error("phm.res must be in 1..={MAX_PHM_RES} texels, got {0}")]
    PhmRes(u32),
    #[error("phm.dirs must be in 1..={MAX_PHM_DIRS} bins, got {0}")]
    PhmDirs(u32),
    #[error("phm.prior must be finite and >= 0, got {0}")]
    PhmPrior(f32),
    #[error("phm.miss must be in [0, 0.5], got {0}")]
    PhmMiss(f32),
    #[error("phm.hit must be in [0.5, 1], got {0}")]
    PhmHit(f32),
    #[error("phm.mode must be {choices}, got {0:?}", choices = PhmMode::choices())]
    PhmMode(String),
    #[error("phm.reprobe must be in [0, 1], got {0}")]
    PhmReprobe(f32),
    #[error("phm.merge must be at least 1 outcome, got 0")]
    PhmMerge,
    #[error(
        "phm.kinds: unknown ray kind {0:?} (expected one of {kinds})",
        kinds = RayKind::help_list(&RayKind::ALL)
    )]
    PhmKinds(String),
    #[error("phm.placement must be {choices}, got {0:?}", choices = Placement::choices())]
    PhmPlacement(String),
    #[error(
        "phm.placement {p:?} and ray_cache.placement {c:?} must agree: a wall's actor holds \
         its cache and its map",
        p = .phm.name(),
        c = .ray_cache.name()
    )]
    PlacementsDisagree {
        phm: Placement,
        ray_cache: Placement,
    },
    #[error(
        "phm.shade needs phm.placement \"remote\", got {p:?}: the cells' radiance sums are \
         not merged between the copies of sender placement",
        p = .0.name()
    )]
    PhmShadePlacement(Placement),
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
    /// Coarse pass size (`coarse` x `coarse` camera rays; 0: none).
    pub coarse: u32,
    /// Ray kinds the workers look up. The workers choose which rays to send (the
    /// `options` of each lookup); the host only checks that the job names real kinds.
    pub kinds: KindSet,
    /// Whether tickets of main-pass rays store radiance when they close. With `false`
    /// only tickets opened by coarse-pass rays (`FLAG_COARSE` in the ray record) store,
    /// so the main pass reads caches that the coarse pass filled and froze: the same job
    /// gives the same bits every run. Until the coarse pass runs, that means nothing is
    /// stored and every lookup misses (the exact image).
    pub fill: bool,
    /// Where the walls are.
    pub placement: Placement,
}

impl CacheSettings {
    /// What ray caches look up when `kinds` names none: every kind that carries
    /// radiance (shadow and AO rays carry none of their own, so there is nothing to
    /// cache).
    pub fn default_kinds() -> KindSet {
        KindSet::cache_default()
    }

    /// Parse and check `RayCacheSettings`, filling in the defaults of absent fields:
    /// `angle_deg` 10, `retrieve` nearest, `kinds` all four cacheable kinds, `fill` true
    /// without a coarse pass and false with one, `placement` sender.
    pub fn from_proto(s: &RayCacheSettings) -> Result<CacheSettings, SettingsError> {
        if !(s.radius.is_finite() && s.radius >= 0.0) {
            return Err(SettingsError::Radius(s.radius));
        }
        let angle_deg = s.angle_deg.unwrap_or(DEFAULT_ANGLE_DEG);
        // Written so that NaN fails too.
        if !(angle_deg > 0.0 && angle_deg <= 90.0) {
            return Err(SettingsError::Angle(angle_deg));
        }
        let retrieve = named_or(&s.retrieve, Retrieve::DEFAULT)
            .ok_or_else(|| SettingsError::Retrieve(s.retrieve.clone()))?;
        if s.coarse > MAX_COARSE {
            return Err(SettingsError::Coarse(s.coarse));
        }
        let kinds = KindSet::parse_or(&s.kinds, &RayKind::RADIANCE, Self::default_kinds())
            .map_err(|e| SettingsError::Kinds(e.name))?;
        let placement = named_or(&s.placement, Placement::DEFAULT)
            .ok_or_else(|| SettingsError::Placement(s.placement.clone()))?;
        Ok(CacheSettings {
            radius: s.radius,
            angle_deg,
            cos_min: f64::from(angle_deg).to_radians().cos(),
            retrieve,
            coarse: s.coarse,
            kinds,
            // A coarse pass fills the caches, which then stay frozen (the same bits every
            // run; dray's default, where Little 2011 keeps inserting during the render,
            // which `fill=true` does); without one, the main pass must fill them or they
            // stay empty.
            fill: s.fill.unwrap_or(s.coarse == 0),
            placement,
        })
    }

    /// The settings with every field written out (kinds in canonical order, without
    /// duplicates): what the coordinator puts back in the job's spec.
    pub fn to_proto(&self) -> RayCacheSettings {
        RayCacheSettings {
            radius: self.radius,
            angle_deg: Some(self.angle_deg),
            retrieve: self.retrieve.name().into(),
            coarse: self.coarse,
            kinds: self.kinds.names(),
            fill: Some(self.fill),
            placement: self.placement.name().into(),
        }
    }

    /// Whether `kind` is one the job looks up.
    pub fn looks_up(&self, kind: RayKind) -> bool {
        self.kinds.contains(kind)
    }
}

/// Texels per wall edge used when `phm.res` is absent.
pub const DEFAULT_PHM_RES: u32 = 4;
/// Direction bins used when `phm.dirs` is absent (Bolstad's 12).
pub const DEFAULT_PHM_DIRS: u32 = 12;
/// Prior weight (in rays on each side of 0.5) when `phm.prior` is absent.
pub const DEFAULT_PHM_PRIOR: f32 = 100.0;
/// Decision thresholds when `phm.miss` / `phm.hit` are absent.
pub const DEFAULT_PHM_MISS: f32 = 0.1;
pub const DEFAULT_PHM_HIT: f32 = 0.9;
/// Re-probe rate of decided cells (consistent mode) when `phm.reprobe` is absent.
pub const DEFAULT_PHM_REPROBE: f32 = 0.1;
/// Outcomes a worker gathers before a merge (sender placement) when `phm.merge` is
/// absent.
pub const DEFAULT_PHM_MERGE: u32 = 4096;

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
    /// When `mode` is absent.
    pub const DEFAULT: PhmMode = PhmMode::Consistent;

    /// The name used in `PhmSettings.mode`.
    pub const fn name(self) -> &'static str {
        match self {
            PhmMode::Consistent => "consistent",
            PhmMode::Inconsistent => "inconsistent",
        }
    }
}

impl Named for PhmMode {
    const ALL: &'static [PhmMode] = &[PhmMode::Consistent, PhmMode::Inconsistent];
    fn name(self) -> &'static str {
        PhmMode::name(self)
    }
}

/// Validated hit-map settings of one job attempt.
#[derive(Clone, Debug, PartialEq)]
pub struct HitMapSettings {
    /// How every wall's map is binned; the workers bin the same way.
    pub bins: PhmBins,
    /// The direction bins asked for (`bins` has at least this many).
    pub dirs: u32,
    /// Prior weight: a cell starts as `prior` hits and `prior` misses. Finite, >= 0.
    pub prior: f32,
    /// A cell with hit probability `p <= miss` predicts a miss; `p >= hit` a hit.
    /// `0 <= miss <= 0.5 <= hit <= 1`.
    pub miss: f32,
    pub hit: f32,
    pub mode: PhmMode,
    /// Consistent mode: the fraction of rays at decided cells probed anyway, [0, 1].
    pub reprobe: f32,
    /// Ray kinds that consult the maps. As for the ray cache, the workers choose which
    /// rays carry option bit 2; the host only checks that the job names real kinds.
    pub kinds: KindSet,
    /// Where the walls are.
    pub placement: Placement,
    /// Sender placement: outcomes a worker gathers before it merges them into the
    /// other copies of the maps (at least 1).
    pub merge: u32,
    /// A predicted hit answers non-occlusion rays too, with the mean radiance the cell's
    /// probes returned (Bolstad 2017's averaged shading; docs/caches.md "Averaged
    /// shading"). Remote placement only: the sums live in the wall's one map.
    pub shade: bool,
}

impl HitMapSettings {
    /// What hit maps serve when `kinds` names none: shadow rays (the source's use).
    pub fn default_kinds() -> KindSet {
        KindSet::phm_default()
    }

    /// Parse and check `PhmSettings`, filling in the defaults of absent fields
    /// (docs/caches.md): res 4, dirs 12, prior 100, miss 0.1, hit 0.9, mode consistent,
    /// reprobe 0.1, kinds shadow, merge 4096, shade off, and `placement` (absent) the
    /// `default_placement` (see [`WallSettings::from_proto`]).
    pub fn from_proto(
        s: &PhmSettings,
        default_placement: Placement,
    ) -> Result<HitMapSettings, SettingsError> {
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
        let mode = named_or(&s.mode, PhmMode::DEFAULT)
            .ok_or_else(|| SettingsError::PhmMode(s.mode.clone()))?;
        let reprobe = s.reprobe.unwrap_or(DEFAULT_PHM_REPROBE);
        if !(0.0..=1.0).contains(&reprobe) {
            return Err(SettingsError::PhmReprobe(reprobe));
        }
        let merge = s.merge.unwrap_or(DEFAULT_PHM_MERGE);
        if merge == 0 {
            return Err(SettingsError::PhmMerge);
        }
        let kinds = KindSet::parse_or(&s.kinds, &RayKind::ALL, Self::default_kinds())
            .map_err(|e| SettingsError::PhmKinds(e.name))?;
        let placement = named_or(&s.placement, default_placement)
            .ok_or_else(|| SettingsError::PhmPlacement(s.placement.clone()))?;
        let shade = s.shade.unwrap_or(false);
        if shade && placement != Placement::Remote {
            return Err(SettingsError::PhmShadePlacement(placement));
        }
        Ok(HitMapSettings {
            bins: PhmBins::new(res, dirs),
            dirs,
            prior,
            miss,
            hit,
            mode,
            reprobe,
            kinds,
            placement,
            merge,
            shade,
        })
    }

    /// The settings with every field written out: what the coordinator puts back in
    /// the job's spec.
    pub fn to_proto(&self) -> PhmSettings {
        PhmSettings {
            res: Some(self.bins.res),
            dirs: Some(self.dirs),
            prior: Some(self.prior),
            miss: Some(self.miss),
            hit: Some(self.hit),
            mode: self.mode.name().into(),
            reprobe: Some(self.reprobe),
            kinds: self.kinds.names(),
            placement: self.placement.name().into(),
            merge: Some(self.merge),
            // Absent when off, so a job without it reads back as it was submitted.
            shade: self.shade.then_some(true),
        }
    }

    /// Whether `kind` is one the job consults the maps for.
    pub fn consults(&self, kind: RayKind) -> bool {
        self.kinds.contains(kind)
    }
}

/// A job's walls: its ray cache and its hit maps, either of which may be absent.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct WallSettings {
    pub ray_cache: Option<CacheSettings>,
    pub phm: Option<HitMapSettings>,
}

impl WallSettings {
    /// Parse both. The hit maps' placement defaults to the ray cache's when the job has
    /// one (else sender), and the two must agree: a wall's actor holds both its cache
    /// and its map.
    pub fn from_proto(
        ray_cache: Option<&RayCacheSettings>,
        phm: Option<&PhmSettings>,
    ) -> Result<WallSettings, SettingsError> {
        let ray_cache = ray_cache.map(CacheSettings::from_proto).transpose()?;
        let cache_placement = ray_cache.as_ref().map(|c| c.placement);
        let phm = phm
            .map(|p| HitMapSettings::from_proto(p, cache_placement.unwrap_or(Placement::DEFAULT)))
            .transpose()?;
        if let (Some(c), Some(p)) = (cache_placement, &phm)
            && c != p.placement
        {
            return Err(SettingsError::PlacementsDisagree {
                phm: p.placement,
                ray_cache: c,
            });
        }
        Ok(WallSettings { ray_cache, phm })
    }

    /// Both with every field written out (see [`CacheSettings::to_proto`]).
    pub fn to_proto(&self) -> (Option<RayCacheSettings>, Option<PhmSettings>) {
        (
            self.ray_cache.as_ref().map(CacheSettings::to_proto),
            self.phm.as_ref().map(HitMapSettings::to_proto),
        )
    }

    /// Where the walls are; `None` without walls.
    pub fn placement(&self) -> Option<Placement> {
        match (&self.ray_cache, &self.phm) {
            (Some(c), _) => Some(c.placement),
            (None, Some(p)) => Some(p.placement),
            (None, None) => None,
        }
    }

    /// The coarse pass's size (0: none, as without a ray cache).
    pub fn coarse(&self) -> u32 {
        self.ray_cache.as_ref().map_or(0, |c| c.coarse)
    }

    /// The kinds that look up the ray caches (none without them).
    pub fn cached_kinds(&self) -> KindSet {
        self.ray_cache
            .as_ref()
            .map_or(KindSet::default(), |c| c.kinds)
    }

    /// The kinds that consult the hit maps (none without them).
    pub fn phm_kinds(&self) -> KindSet {
        self.phm.as_ref().map_or(KindSet::default(), |p| p.kinds)
    }
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
        let s = CacheSettings::from_proto(&proto(0.5)).unwrap();
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
            (proto(-1.0), "ray_cache.radius"),
            (proto(f32::NAN), "ray_cache.radius"),
            (proto(f32::INFINITY), "ray_cache.radius"),
            (
                RayCacheSettings {
                    angle_deg: Some(0.0),
                    ..proto(1.0)
                },
                "ray_cache.angle_deg",
            ),
            (
                RayCacheSettings {
                    angle_deg: Some(90.5),
                    ..proto(1.0)
                },
                "ray_cache.angle_deg",
            ),
            (
                RayCacheSettings {
                    angle_deg: Some(f32::NAN),
                    ..proto(1.0)
                },
                "ray_cache.angle_deg",
            ),
            (
                RayCacheSettings {
                    retrieve: "best".into(),
                    ..proto(1.0)
                },
                "ray_cache.retrieve",
            ),
            (
                RayCacheSettings {
                    coarse: 4097,
                    ..proto(1.0)
                },
                "ray_cache.coarse",
            ),
            (
                RayCacheSettings {
                    kinds: "camera,shadow".into(),
                    ..proto(1.0)
                },
                "ray_cache.kinds",
            ),
        ];
        for (p, field) in bad {
            let e = CacheSettings::from_proto(&p).unwrap_err();
            assert!(e.to_string().starts_with(field), "{e}");
        }
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
        let s = CacheSettings::from_proto(&p).unwrap();
        assert_eq!(s.retrieve, Retrieve::Average);
        assert!(!s.fill);
        assert!(s.looks_up(RayKind::Camera) && !s.looks_up(RayKind::Reflection));
    }

    #[test]
    fn phm_defaults_fill_in() {
        let s = HitMapSettings::from_proto(&PhmSettings::default(), Placement::DEFAULT).unwrap();
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
        let s = HitMapSettings::from_proto(&p, Placement::DEFAULT).unwrap();
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
        let s = HitMapSettings::from_proto(&p, Placement::DEFAULT).unwrap();
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
            (
                PhmSettings {
                    shade: Some(true),
                    ..base()
                },
                "phm.shade",
            ),
            (
                PhmSettings {
                    shade: Some(true),
                    placement: "sender".into(),
                    ..base()
                },
                "phm.shade",
            ),
        ];
        for (p, field) in bad {
            let e = HitMapSettings::from_proto(&p, Placement::DEFAULT).unwrap_err();
            assert!(e.to_string().starts_with(field), "{field}: {e}");
        }
    }

    #[test]
    fn shade_is_off_unless_asked_and_needs_remote_placement() {
        let off = HitMapSettings::from_proto(&PhmSettings::default(), Placement::Remote).unwrap();
        assert!(!off.shade);
        assert_eq!(off.to_proto().shade, None, "absent when off");
        let p = PhmSettings {
            shade: Some(true),
            placement: "remote".into(),
            ..Default::default()
        };
        let on = HitMapSettings::from_proto(&p, Placement::Sender).unwrap();
        assert!(on.shade);
        assert_eq!(on.to_proto().shade, Some(true));
        assert_eq!(
            HitMapSettings::from_proto(&on.to_proto(), Placement::Sender),
            Ok(on)
        );
        // The ray cache's remote placement is the maps' default: shade is accepted.
        let rc = RayCacheSettings {
            placement: "remote".into(),
            ..Default::default()
        };
        let p = PhmSettings {
            shade: Some(true),
            ..Default::default()
        };
        assert!(
            WallSettings::from_proto(Some(&rc), Some(&p))
                .unwrap()
                .phm
                .unwrap()
                .shade
        );
        let e = WallSettings::from_proto(None, Some(&p)).unwrap_err();
        assert_eq!(
            e.to_string(),
            "phm.shade needs phm.placement \"remote\", got \"sender\": the cells' radiance \
             sums are not merged between the copies of sender placement"
        );
    }

    /// What the coordinator writes back reads as the same settings: the resolved spec
    /// the workers and cache hosts parse again is the one it checked.
    #[test]
    fn written_out_settings_parse_back_to_themselves() {
        let rc = RayCacheSettings {
            radius: 0.25,
            kinds: " diffuse,camera,,diffuse ".into(),
            coarse: 16,
            ..Default::default()
        };
        let phm = PhmSettings {
            dirs: Some(7),
            kinds: "ambient_occlusion,shadow".into(),
            ..Default::default()
        };
        let w = WallSettings::from_proto(Some(&rc), Some(&phm)).unwrap();
        let (rc2, phm2) = w.to_proto();
        let rc2 = rc2.unwrap();
        assert_eq!(rc2.kinds, "camera,diffuse");
        assert_eq!((rc2.fill, rc2.placement.as_str()), (Some(false), "sender"));
        let phm2 = phm2.unwrap();
        assert_eq!((phm2.dirs, phm2.merge), (Some(7), Some(DEFAULT_PHM_MERGE)));
        let again = WallSettings::from_proto(Some(&rc2), Some(&phm2)).unwrap();
        assert_eq!(again, w);
        assert_eq!(w.placement(), Some(Placement::Sender));
        assert_eq!(w.coarse(), 16);
    }

    #[test]
    fn the_maps_follow_the_caches_placement_and_must_agree_with_it() {
        let remote = RayCacheSettings {
            placement: "remote".into(),
            ..Default::default()
        };
        let w = WallSettings::from_proto(Some(&remote), Some(&PhmSettings::default())).unwrap();
        assert_eq!(w.phm.map(|p| p.placement), Some(Placement::Remote));
        let alone = WallSettings::from_proto(None, Some(&PhmSettings::default())).unwrap();
        assert_eq!(alone.placement(), Some(Placement::Sender));
        let sender = PhmSettings {
            placement: "sender".into(),
            ..Default::default()
        };
        let e = WallSettings::from_proto(Some(&remote), Some(&sender)).unwrap_err();
        assert!(
            e.to_string().starts_with(
                "phm.placement \"sender\" and ray_cache.placement \"remote\" must agree"
            ),
            "{e}"
        );
        let nearby = PhmSettings {
            placement: "nearby".into(),
            ..Default::default()
        };
        let e = WallSettings::from_proto(None, Some(&nearby)).unwrap_err();
        assert_eq!(
            e.to_string(),
            "phm.placement must be sender or remote, got \"nearby\""
        );
    }

    #[test]
    fn names_are_parsed_from_one_list() {
        assert_eq!(Retrieve::choices(), "first, nearest or average");
        assert_eq!(Retrieve::from_name("average"), Some(Retrieve::Average));
        assert_eq!(Retrieve::from_name("Nearest"), None);
        assert_eq!(CoarseSampling::from_proto(""), Ok(CoarseSampling::Centres));
        assert_eq!(
            CoarseSampling::from_proto("random"),
            Ok(CoarseSampling::Random)
        );
        let e = CoarseSampling::from_proto("jitter").unwrap_err();
        assert_eq!(
            e.to_string(),
            "coarse_sampling must be centres or random, got \"jitter\""
        );
    }
}

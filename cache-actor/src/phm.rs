//! One wall's probability hit map (Bolstad 2017): per cell (a texel on the wall times a
//! direction bin into the domain), how many rays entering the domain there hit
//! something inside it and how many went through.
//!
//! The map turns those counts into advice for the next ray through the cell. With
//! `p = (hits + prior) / (hits + misses + 2 prior)`, a cell with `p <= miss` predicts
//! that rays pass the domain untouched (they skip it, and the domain's owner never sees
//! them), one with `p >= hit` predicts that they hit inside (an occlusion ray is then
//! occluded without being traced), and anything between is undecided: its rays are
//! traced as *probes*, whose outcomes the domain's owner reports back to teach the map.
//!
//! Two modes, as in the source:
//! - consistent: a decided cell follows its counts (it can change its mind), and a
//!   deterministic fraction `reprobe` of its rays is probed anyway, so a decision its
//!   counts come to contradict is eventually corrected (a cell whose true hit rate lies
//!   past a threshold stays decided, and keeps the bias of the rays it answers);
//! - inconsistent: once a cell has decided, it ignores further outcomes, which freezes
//!   its counts and so its decision. Freezing the counts instead of storing a separate
//!   decision means a cell never un-decides, even one decided by its prior alone (a
//!   `miss` of 0.5 decides every fresh cell).
//!
//! Whether a ray is re-probed is a hash of the ray's bits, never a random draw, so the
//! same ray at the same map state gets the same answer on every run and every host.
//!
//! With `shade` (Bolstad 2017's averaged shading), a cell that predicts a hit answers
//! rays of the other kinds too, with the mean radiance its probes returned
//! ([`crate::shading`]), once it has learned one; until then they are probed.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, OnceLock};

use dray_core::integrator::RayKind;
use dray_core::ray::RayRecord;
use dray_core::wall::{self, PhmBins};
use glam::Vec3;

use crate::settings::{HitMapSettings, PhmMode};
use crate::shading::Shading;

/// Maps of at most this many cells keep a dense array of counts (8 bytes a cell, at
/// most 512 KiB a wall). Larger maps (up to 64 x 64 texels x 264 direction bins, 1 Mi
/// cells) keep only the cells that have learned something, so a host's memory follows
/// the outcomes it received rather than the settings' worst case times its walls.
pub const DENSE_MAX_CELLS: u32 = 1 << 16;

/// `shade`: the tickets a cell that predicts a hit asks for, at most, to learn the
/// radiance its rays return. Its mean rests on those of them that closed untainted.
pub const SHADE_TICKETS: u64 = 32;

/// One cell's outcomes. Saturating: a cell that has seen four billion outcomes of a
/// kind has decided long ago, and overflow must not flip it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Counts {
    pub hits: u32,
    pub misses: u32,
}

/// What a cell predicts.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Decision {
    Undecided,
    /// Rays through the cell pass the domain untouched.
    Miss,
    /// Rays through the cell hit something in the domain.
    Hit,
}

/// What the map says about one ray.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Advice {
    /// The ray has no cell (it does not cross the wall's plane, or its direction is
    /// zero): the map says nothing, and the ray cannot be a probe (its outcome could
    /// not be binned).
    Unplaced,
    /// Skip the domain behind the wall (outcome 3).
    Skip,
    /// An occlusion ray at a cell that predicts a hit: occluded (outcome 4).
    Occlude,
    /// `shade`: a ray of another kind at a cell that predicts a hit, answered with the
    /// mean radiance the cell's probes returned (outcome 5).
    Shade([f32; 3]),
    /// Trace the ray (as the ray cache answers it) and report its outcome: a probe.
    Probe,
    /// Trace the ray, but not as a probe: its cell has decided in an inconsistent map
    /// (which ignores outcomes from then on), and the decision cannot answer this ray
    /// (a predicted hit, and the ray is not an occlusion ray). Its outcome would be
    /// sent only to be dropped.
    Trace,
}

/// What an outcome did to the map.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Learned {
    /// Added to the cell's counts.
    Counted,
    /// The cell has decided and the map is inconsistent: ignored.
    Frozen,
    /// The cell is beyond the map: ignored.
    OutOfRange,
}

/// Dense counts, shared between a wall's actor (their only writer) and the tracing
/// threads that consult the map in place ([`MapView`]). Each cell is one `u64` (hits in
/// the low half, misses in the high half), so a reader always sees a pair the writer
/// stored. Allocated on the first outcome: a map that never learns costs nothing.
type DenseCells = Arc<OnceLock<Box<[AtomicU64]>>>;

/// The memory of one dense cell: its counts packed in a `u64` ([`Cells`]). A job's
/// maps hold at most their cells times this (a dense map's counts, allocated on its first
/// outcome; a sparse map holds only the cells that learned, with a hash table's overhead).
pub const BYTES_PER_CELL: u64 = std::mem::size_of::<u64>() as u64;

fn pack(c: Counts) -> u64 {
    u64::from(c.hits) | u64::from(c.misses) << 32
}

fn unpack(x: u64) -> Counts {
    Counts {
        hits: x as u32,
        misses: (x >> 32) as u32,
    }
}

fn dense_get(cells: &DenseCells, cell: u32) -> Counts {
    cells
        .get()
        .and_then(|v| v.get(usize::try_from(cell).ok()?))
        .map_or_else(Counts::default, |a| unpack(a.load(Ordering::Relaxed)))
}

/// Cell counts: dense for maps of at most [`DENSE_MAX_CELLS`] cells (which may be
/// consulted in place), sparse above.
#[derive(Debug)]
enum Cells {
    Dense(DenseCells),
    Sparse(HashMap<u32, Counts>),
}

impl Cells {
    fn new(n: u32) -> Cells {
        if n <= DENSE_MAX_CELLS {
            Cells::Dense(Arc::new(OnceLock::new()))
        } else {
            Cells::Sparse(HashMap::new())
        }
    }

    fn get(&self, cell: u32) -> Counts {
        match self {
            Cells::Dense(d) => dense_get(d, cell),
            Cells::Sparse(m) => m.get(&cell).copied().unwrap_or_default(),
        }
    }

    /// Set the counts of `cell` (< `n`, checked by the caller) to `f` of their current
    /// value. Only the wall's actor writes, so a load and a store are enough.
    fn update(&mut self, cell: u32, n: u32, f: impl FnOnce(Counts) -> Counts) {
        match self {
            Cells::Dense(d) => {
                let v = d.get_or_init(|| (0..n).map(|_| AtomicU64::new(0)).collect());
                if let Some(a) = usize::try_from(cell).ok().and_then(|i| v.get(i)) {
                    a.store(
                        pack(f(unpack(a.load(Ordering::Relaxed)))),
                        Ordering::Relaxed,
                    );
                }
            }
            Cells::Sparse(m) => {
                let c = m.entry(cell).or_default();
                *c = f(*c);
            }
        }
    }

    /// Every cell that holds counts (the others are fresh).
    fn held(&self) -> Box<dyn Iterator<Item = Counts> + '_> {
        match self {
            Cells::Dense(d) => match d.get() {
                Some(v) => Box::new(v.iter().map(|a| unpack(a.load(Ordering::Relaxed)))),
                None => Box::new(std::iter::empty()),
            },
            Cells::Sparse(m) => Box::new(m.values().copied()),
        }
    }
}

/// How a map bins rays and decides: everything about it but its counts.
#[derive(Clone, Copy, Debug)]
struct MapRule {
    bins: PhmBins,
    /// The box of the domain the wall belongs to, and the wall's face of it: what
    /// [`PhmBins::cell`] bins against, exactly as the workers do.
    lo: Vec3,
    hi: Vec3,
    face: u32,
    wall: u32,
    prior: f64,
    miss: f64,
    hit: f64,
    mode: PhmMode,
    reprobe: f64,
    shade: bool,
}

impl MapRule {
    fn len(&self) -> u32 {
        self.bins.cells()
    }

    fn cell_of(&self, origin: Vec3, dir: Vec3) -> Option<u32> {
        self.bins
            .cell(self.lo, self.hi, self.face, origin, dir)
            .filter(|&c| c < self.len())
    }

    fn probability(&self, c: Counts) -> f64 {
        let hits = f64::from(c.hits);
        let total = hits + f64::from(c.misses) + 2.0 * self.prior;
        if total > 0.0 {
            (hits + self.prior) / total
        } else {
            0.5
        }
    }

    fn decide(&self, c: Counts) -> Decision {
        let mut p = self.probability(c);
        if self.prior > 0.0 {
            p = p.clamp(f64::MIN_POSITIVE, 1.0 - f64::EPSILON);
        }
        if p <= self.miss {
            Decision::Miss
        } else if p >= self.hit {
            Decision::Hit
        } else {
            Decision::Undecided
        }
    }

    fn reprobes(&self, ray: &RayRecord) -> bool {
        self.mode == PhmMode::Consistent && reprobe_draw(ray, self.wall) < self.reprobe
    }

    /// Whether a predicted hit may answer rays of `kind` with averaged shading.
    fn shades(&self, kind: RayKind) -> bool {
        self.shade && !kind.is_occlusion()
    }

    /// The advice for `ray`, from the counts of its cell and (`shade`) the mean
    /// radiance its probes returned, if any.
    fn advise(
        &self,
        ray: &RayRecord,
        counts: impl FnOnce(u32) -> Counts,
        mean: impl FnOnce(u32) -> Option<[f32; 3]>,
    ) -> Advice {
        let Some(cell) = self.cell_of(ray.origin, ray.dir) else {
            return Advice::Unplaced;
        };
        let decision = self.decide(counts(cell));
        if decision == Decision::Undecided || self.reprobes(ray) {
            return Advice::Probe;
        }
        match decision {
            Decision::Miss => Advice::Skip,
            Decision::Hit if ray.kind.is_occlusion() => Advice::Occlude,
            Decision::Hit if self.shades(ray.kind) => match mean(cell) {
                Some(rgb) => Advice::Shade(rgb),
                // Nothing learned yet: the ray is probed so the cell can learn (its
                // outcome ignored by an inconsistent map, its radiance still taken).
                None if self.mode == PhmMode::Inconsistent => Advice::Trace,
                None => Advice::Probe,
            },
            _ if self.mode == PhmMode::Inconsistent => Advice::Trace,
            _ => Advice::Probe,
        }
    }
}

/// Consults of a map made in place through its [`MapView`]s, counted where they happen
/// and added to the wall's statistics when it closes.
#[derive(Debug, Default)]
pub struct Consults {
    pub lookups: AtomicU64,
    pub unplaced: AtomicU64,
    pub skipped: AtomicU64,
    pub occluded: AtomicU64,
    pub probes: AtomicU64,
}

/// A read-only view of one wall's map for the tracing threads of the worker in the
/// map's own process (sender placement): they consult it in place, with no message to
/// the wall's actor and no wait for an answer. What the actor learns (from outcomes
/// and merges) shows in the view at once. Dense maps only.
#[derive(Clone, Debug)]
pub struct MapView {
    rule: MapRule,
    cells: DenseCells,
    consults: Arc<Consults>,
}

impl MapView {
    /// The map's advice for `ray` at its wall, counted as the actor counts a lookup.
    /// A probe is counted when the ray does go on into the domain ([`Self::probed`]):
    /// a ray the ray cache answers is not one.
    pub fn consult(&self, ray: &RayRecord) -> Advice {
        let c = &self.consults;
        c.lookups.fetch_add(1, Ordering::Relaxed);
        // A view has no radiance sums (they live with the actor, which the rays that
        // may be shaded go to: see [`Self::shades`]), so it never shades.
        let advice = self
            .rule
            .advise(ray, |cell| dense_get(&self.cells, cell), |_| None);
        let counter = match advice {
            Advice::Unplaced => &c.unplaced,
            Advice::Skip => &c.skipped,
            Advice::Occlude => &c.occluded,
            Advice::Probe | Advice::Trace | Advice::Shade(_) => return advice,
        };
        counter.fetch_add(1, Ordering::Relaxed);
        advice
    }

    /// Count a ray the map asked to probe that went on into the domain.
    pub fn probed(&self) {
        self.consults.probes.fetch_add(1, Ordering::Relaxed);
    }

    /// The wall the map belongs to.
    pub fn wall(&self) -> u32 {
        self.rule.wall
    }

    /// Whether the map may answer rays of `kind` with averaged shading (`shade`, and a
    /// kind that carries radiance). Such rays must ask the wall's actor, which holds
    /// the radiance sums and opens the tickets that teach them, not the view.
    pub fn shades(&self, kind: RayKind) -> bool {
        self.rule.shades(kind)
    }
}

/// The hit map of one wall.
#[derive(Debug)]
pub struct HitMap {
    rule: MapRule,
    cells: Cells,
    consults: Arc<Consults>,
    /// `shade`: the radiance the cells' probes returned.
    shading: Shading,
}

impl HitMap {
    /// An empty map (every cell at its prior) for `wall`, whose domain is `[lo, hi]`.
    pub fn new(settings: &HitMapSettings, wall: u32, lo: Vec3, hi: Vec3) -> HitMap {
        let rule = MapRule {
            bins: settings.bins,
            lo,
            hi,
            face: wall::wall_face(wall),
            wall,
            prior: f64::from(settings.prior),
            miss: f64::from(settings.miss),
            hit: f64::from(settings.hit),
            mode: settings.mode,
            reprobe: f64::from(settings.reprobe),
            shade: settings.shade,
        };
        HitMap {
            cells: Cells::new(rule.len()),
            rule,
            consults: Arc::default(),
            shading: Shading::default(),
        }
    }

    /// A view for consulting the map in place, sharing its counts; `None` for a map too
    /// large for dense counts (its rays ask the actor).
    pub fn view(&self) -> Option<MapView> {
        match &self.cells {
            Cells::Dense(d) => Some(MapView {
                rule: self.rule,
                cells: d.clone(),
                consults: self.consults.clone(),
            }),
            Cells::Sparse(_) => None,
        }
    }

    /// The consults made through the map's views.
    pub fn consults(&self) -> &Consults {
        &self.consults
    }

    /// Cells in the map.
    pub fn len(&self) -> u32 {
        self.rule.len()
    }

    /// Never true (a map has at least one cell); for clippy's `len` convention.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The cell of a ray entering through this wall, as the workers bin it.
    pub fn cell_of(&self, origin: Vec3, dir: Vec3) -> Option<u32> {
        self.rule.cell_of(origin, dir)
    }

    /// The counts of `cell` (fresh counts for a cell beyond the map).
    pub fn counts(&self, cell: u32) -> Counts {
        self.cells.get(cell)
    }

    /// The hit probability of counts `c`: the prior's 0.5 weighted by `prior` rays on
    /// each side; 0.5 when there is neither prior nor outcome.
    pub fn probability(&self, c: Counts) -> f64 {
        self.rule.probability(c)
    }

    /// What counts `c` decide. With a positive prior the true `p` is strictly inside
    /// (0, 1), but in f64 a tiny prior next to billions of outcomes rounds to exactly 0
    /// or 1; clamping keeps thresholds of 0 and 1 from ever deciding then, as the
    /// settings promise.
    pub fn decide(&self, c: Counts) -> Decision {
        self.rule.decide(c)
    }

    /// The current decision of `cell`. Inconsistent maps need nothing more: a decided
    /// cell's counts no longer change, so neither does this.
    pub fn decision(&self, cell: u32) -> Decision {
        self.decide(self.cells.get(cell))
    }

    /// Whether a ray at a decided cell is probed anyway: consistent maps only, for a
    /// fraction `reprobe` of rays picked by [`reprobe_draw`].
    pub fn reprobes(&self, ray: &RayRecord) -> bool {
        self.rule.reprobes(ray)
    }

    /// The map's advice for `ray`, reaching this wall. A ray's kind only matters for
    /// predicted hits: only occlusion rays can be answered by "something is in the
    /// way"; others are traced at such cells, as probes while the cell can still learn
    /// (consistent maps), plainly once it cannot (inconsistent maps), unless the map
    /// shades: then they are answered with the mean radiance the cell's probes
    /// returned, once it has one.
    pub fn advise(&self, ray: &RayRecord) -> Advice {
        self.rule.advise(
            ray,
            |cell| self.cells.get(cell),
            |cell| self.shading.mean(cell),
        )
    }

    /// Whether the map may answer rays of `kind` with averaged shading: probes of
    /// that kind should then carry a ticket to this wall, so their radiance is learned.
    pub fn shades(&self, kind: RayKind) -> bool {
        self.rule.shades(kind)
    }

    /// The cell whose averaged shading `ray` (a ray the map traces, of a kind it
    /// shades) should teach, by carrying a ticket, noted as asked: only a cell that
    /// predicts a hit (the only cells that shade), and only its first
    /// [`SHADE_TICKETS`] rays. Tickets cost bytes (a ray batch carries its rays'
    /// tickets, the descendants' too, and each ticket is returned): asking every probe
    /// for one cost 1.3-1.5x the bytes the maps move without `shade` (cornell, path,
    /// 16 spp, 96² and 128², 8 domains on 4 workers).
    pub fn ask_shading(&mut self, ray: &RayRecord) -> Option<u32> {
        let cell = self.cell_of(ray.origin, ray.dir)?;
        let wanted =
            self.decision(cell) == Decision::Hit && self.shading.cell(cell).asked < SHADE_TICKETS;
        wanted.then(|| {
            self.shading.ask(cell);
            cell
        })
    }

    /// Add the radiance a probe that entered through `cell` returned (its ticket
    /// closed cleanly) to the cell's averaged shading; false when refused (a cell
    /// beyond the map, radiance not finite and non-negative).
    pub fn learn_shading(&mut self, cell: u32, rgb: [f32; 3]) -> bool {
        cell < self.len() && self.shading.add(cell, rgb)
    }

    /// The cells' averaged shading.
    pub fn shading(&self) -> &Shading {
        &self.shading
    }

    /// Learn one probe's outcome: whether it hit something inside the domain.
    pub fn learn(&mut self, cell: u32, hit: bool) -> Learned {
        self.merge(cell, u32::from(hit), u32::from(!hit))
    }

    /// Merge another copy's outcomes at `cell` (sender placement: `hits` and `misses`
    /// seen there by another worker since its last merge). The counts are added as if
    /// learned one by one, except that an inconsistent map's cell that has already
    /// decided takes none of them (it is frozen), and one still undecided takes them
    /// all: a merge is one event, so a cell does not freeze half-way through it.
    pub fn merge(&mut self, cell: u32, hits: u32, misses: u32) -> Learned {
        let n = self.len();
        if cell >= n {
            return Learned::OutOfRange;
        }
        if self.rule.mode == PhmMode::Inconsistent && self.decision(cell) != Decision::Undecided {
            return Learned::Frozen;
        }
        self.cells.update(cell, n, |c| Counts {
            hits: c.hits.saturating_add(hits),
            misses: c.misses.saturating_add(misses),
        });
        Learned::Counted
    }

    /// Cells whose current decision is a hit, and a miss.
    pub fn decided(&self) -> (u64, u64) {
        let (mut hit, mut miss, mut held) = (0u64, 0u64, 0u64);
        let mut count = |d: Decision, n: u64| match d {
            Decision::Hit => hit += n,
            Decision::Miss => miss += n,
            Decision::Undecided => {}
        };
        for c in self.cells.held() {
            held += 1;
            count(self.decide(c), 1);
        }
        // The cells without counts all decide as a fresh cell does.
        let fresh = u64::from(self.len()).saturating_sub(held);
        count(self.decide(Counts::default()), fresh);
        (hit, miss)
    }
}

/// A uniform number in [0, 1) made from the bits of `ray` (pixel, sample, depth, kind,
/// origin and direction) and the wall: the same ray at the same wall always draws the
/// same number, on any host, in any run. SplitMix64's finaliser mixes each word in.
pub fn reprobe_draw(ray: &RayRecord, wall: u32) -> f64 {
    let o = ray.origin.to_array().map(f32::to_bits);
    let d = ray.dir.to_array().map(f32::to_bits);
    let words = [
        u64::from(ray.pixel) << 32 | u64::from(ray.sample),
        u64::from(ray.depth) << 40 | u64::from(ray.kind as u8) << 32 | u64::from(wall),
        u64::from(o[0]) << 32 | u64::from(o[1]),
        u64::from(o[2]) << 32 | u64::from(d[0]),
        u64::from(d[1]) << 32 | u64::from(d[2]),
    ];
    let h = words.iter().fold(0x9e37_79b9_7f4a_7c15u64, |h, &w| {
        mix(h ^ w).wrapping_add(0x9e37_79b9_7f4a_7c15)
    });
    // The top 53 bits, as a double in [0, 1).
    (h >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
}

/// SplitMix64's finaliser: a bijection on u64 with full avalanche.
fn mix(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

#[cfg(test)]
mod tests {
    use super::*;
    use dray_core::credit::Credit;
    use dray_proto::v1::PhmSettings;

    fn settings(edit: impl FnOnce(&mut PhmSettings)) -> HitMapSettings {
        let mut p = PhmSettings::default();
        edit(&mut p);
        HitMapSettings::from_proto(&p, crate::settings::Placement::DEFAULT).unwrap()
    }

    /// Wall 4: face -z of domain 0, the unit cube.
    fn map(s: &HitMapSettings) -> HitMap {
        HitMap::new(s, 4, Vec3::ZERO, Vec3::ONE)
    }

    /// A shadow ray entering the unit cube through its -z face at (u, v).
    fn ray(u: f32, v: f32, pixel: u32) -> RayRecord {
        RayRecord {
            credit: Credit::from_wire(1),
            origin: Vec3::new(u, v, -1.0),
            dir: Vec3::new(0.0, 0.0, 1.0),
            tmax: f32::INFINITY,
            weight: Vec3::ONE,
            bsdf_pdf: 0.0,
            pixel,
            sample: 0,
            depth: 1,
            kind: RayKind::Shadow,
            flags: 0,
        }
    }

    fn cell(m: &HitMap, r: &RayRecord) -> u32 {
        m.cell_of(r.origin, r.dir).unwrap()
    }

    #[test]
    fn the_prior_alone_is_undecided() {
        let m = map(&settings(|_| {}));
        assert_eq!(m.len(), 192);
        let r = ray(0.5, 0.5, 0);
        assert_eq!(m.decision(cell(&m, &r)), Decision::Undecided);
        assert_eq!(m.probability(Counts::default()), 0.5);
        assert_eq!(m.advise(&r), Advice::Probe);
        assert_eq!(m.decided(), (0, 0));
        // No prior, no outcomes: 0.5 too.
        let m = map(&settings(|p| p.prior = Some(0.0)));
        assert_eq!(m.probability(Counts::default()), 0.5);
        assert_eq!(m.decision(0), Decision::Undecided);
    }

    #[test]
    fn enough_misses_decide_a_miss() {
        let mut m = map(&settings(|_| {}));
        let r = ray(0.3, 0.6, 0);
        let c = cell(&m, &r);
        // 100 / (n + 200) <= 0.1 from n = 800 misses on.
        for _ in 0..799 {
            assert_eq!(m.learn(c, false), Learned::Counted);
        }
        assert_eq!(m.decision(c), Decision::Undecided);
        m.learn(c, false);
        assert_eq!(m.decision(c), Decision::Miss);
        // Most rays skip; the ones the hash picks are re-probed.
        let advice: Vec<Advice> = (0..1000).map(|i| m.advise(&ray(0.3, 0.6, i))).collect();
        let skips = advice.iter().filter(|a| **a == Advice::Skip).count();
        let probes = advice.iter().filter(|a| **a == Advice::Probe).count();
        assert_eq!(skips + probes, 1000);
        assert!((50..150).contains(&probes), "{probes}");
        // Other cells are untouched.
        let other = ray(0.9, 0.1, 0);
        assert_eq!(m.decision(cell(&m, &other)), Decision::Undecided);
        assert_eq!(m.decided(), (0, 1));
    }

    #[test]
    fn hits_answer_occlusion_rays_only() {
        let s = settings(|p| {
            p.prior = Some(1.0);
            p.reprobe = Some(0.0);
            p.kinds = "camera,shadow".into();
        });
        let mut m = map(&s);
        let r = ray(0.5, 0.5, 0);
        let c = cell(&m, &r);
        // (n + 1) / (n + 2) >= 0.9 from n = 8.
        for _ in 0..8 {
            m.learn(c, true);
        }
        assert_eq!(m.decision(c), Decision::Hit);
        assert_eq!(m.advise(&r), Advice::Occlude);
        let ao = RayRecord {
            kind: RayKind::AmbientOcclusion,
            ..r
        };
        assert_eq!(m.advise(&ao), Advice::Occlude);
        let cam = RayRecord {
            kind: RayKind::Camera,
            ..r
        };
        assert_eq!(m.advise(&cam), Advice::Probe);
        assert_eq!(m.decided(), (1, 0));
    }

    #[test]
    fn shading_maps_answer_other_kinds_at_predicted_hits_once_they_have_a_mean() {
        for mode in [PhmMode::Consistent, PhmMode::Inconsistent] {
            let s = settings(|p| {
                p.prior = Some(1.0);
                p.reprobe = Some(0.0);
                p.mode = mode.name().into();
                p.kinds = "camera,diffuse,shadow".into();
                p.placement = "remote".into();
                p.shade = Some(true);
            });
            let mut m = map(&s);
            let view = m.view().unwrap();
            let shadow = ray(0.5, 0.5, 0);
            let cam = RayRecord {
                kind: RayKind::Camera,
                ..shadow
            };
            let c = cell(&m, &cam);
            assert!(m.shades(RayKind::Camera) && m.shades(RayKind::Diffuse));
            assert!(!m.shades(RayKind::Shadow) && !m.shades(RayKind::AmbientOcclusion));
            assert!(view.shades(RayKind::Camera) && !view.shades(RayKind::Shadow));
            // Undecided: probed, whatever the cell has learned of radiance.
            assert!(m.learn_shading(c, [1.0, 2.0, 3.0]));
            assert_eq!(m.advise(&cam), Advice::Probe);
            // Decided a hit, with a mean: the camera ray is shaded with it.
            for _ in 0..8 {
                m.learn(c, true);
            }
            assert!(m.learn_shading(c, [3.0, 2.0, 1.0]));
            assert_eq!(m.advise(&cam), Advice::Shade([2.0, 2.0, 2.0]), "{mode:?}");
            assert_eq!(m.advise(&shadow), Advice::Occlude);
            // The view has no sums: it never shades.
            let traced = match mode {
                PhmMode::Consistent => Advice::Probe,
                PhmMode::Inconsistent => Advice::Trace,
            };
            assert_eq!(view.consult(&cam), traced);
            // Another decided cell without a mean: traced (probed while it can learn).
            let other = RayRecord {
                kind: RayKind::Diffuse,
                ..ray(0.1, 0.9, 0)
            };
            let o = cell(&m, &other);
            assert_ne!(o, c);
            for _ in 0..8 {
                m.learn(o, true);
            }
            assert_eq!(m.advise(&other), traced, "{mode:?}");
            // Refused: beyond the map, or not a radiance.
            assert!(!m.learn_shading(m.len(), [1.0; 3]));
            assert!(!m.learn_shading(o, [f32::NAN, 0.0, 0.0]));
            assert_eq!(m.advise(&other), traced);
            assert_eq!(m.shading().len(), 1);
        }
        // Consistent re-probes are still probes, not shaded.
        let s = settings(|p| {
            p.prior = Some(1.0);
            p.reprobe = Some(1.0);
            p.kinds = "camera".into();
            p.placement = "remote".into();
            p.shade = Some(true);
        });
        let mut m = map(&s);
        let cam = RayRecord {
            kind: RayKind::Camera,
            ..ray(0.5, 0.5, 0)
        };
        let c = cell(&m, &cam);
        for _ in 0..8 {
            m.learn(c, true);
        }
        m.learn_shading(c, [1.0; 3]);
        assert_eq!(m.advise(&cam), Advice::Probe);
        // Without shade a mean changes nothing.
        let s = settings(|p| {
            p.prior = Some(1.0);
            p.reprobe = Some(0.0);
            p.kinds = "camera".into();
        });
        let mut m = map(&s);
        for _ in 0..8 {
            m.learn(c, true);
        }
        m.learn_shading(c, [1.0; 3]);
        assert!(!m.shades(RayKind::Camera));
        assert_eq!(m.advise(&cam), Advice::Probe);
    }

    #[test]
    fn inconsistent_maps_freeze_and_consistent_ones_follow_the_counts() {
        for mode in [PhmMode::Consistent, PhmMode::Inconsistent] {
            let s = settings(|p| {
                p.prior = Some(1.0);
                p.mode = mode.name().into();
            });
            let mut m = map(&s);
            // 1 / (n + 2) <= 0.1 from n = 8 misses.
            for _ in 0..8 {
                assert_eq!(m.learn(7, false), Learned::Counted);
            }
            assert_eq!(m.decision(7), Decision::Miss);
            // Hits arrive after the decision.
            let after: Vec<Learned> = (0..100).map(|_| m.learn(7, true)).collect();
            match mode {
                PhmMode::Inconsistent => {
                    assert!(after.iter().all(|l| *l == Learned::Frozen));
                    assert_eq!(m.counts(7), Counts { hits: 0, misses: 8 });
                    assert_eq!(m.decision(7), Decision::Miss);
                    assert_eq!(m.decided(), (0, 1));
                }
                PhmMode::Consistent => {
                    assert!(after.iter().all(|l| *l == Learned::Counted));
                    // 101 / 110 >= 0.9: the cell changed its mind.
                    assert_eq!(m.decision(7), Decision::Hit);
                    assert_eq!(m.decided(), (1, 0));
                }
            }
        }
    }

    #[test]
    fn frozen_cells_do_not_ask_for_probes() {
        for mode in [PhmMode::Consistent, PhmMode::Inconsistent] {
            let s = settings(|p| {
                p.prior = Some(1.0);
                p.reprobe = Some(0.0);
                p.mode = mode.name().into();
                p.kinds = "camera,shadow".into();
            });
            let mut m = map(&s);
            let cam = RayRecord {
                kind: RayKind::Camera,
                ..ray(0.5, 0.5, 0)
            };
            let c = cell(&m, &cam);
            assert_eq!(m.advise(&cam), Advice::Probe, "undecided cells probe");
            for _ in 0..8 {
                m.learn(c, true);
            }
            assert_eq!(m.decision(c), Decision::Hit);
            // A camera ray cannot be occluded: it is traced either way, but only a
            // consistent map can still learn from its outcome.
            let want = match mode {
                PhmMode::Consistent => Advice::Probe,
                PhmMode::Inconsistent => Advice::Trace,
            };
            assert_eq!(m.advise(&cam), want, "{mode:?}");
            if mode == PhmMode::Inconsistent {
                assert_eq!(m.learn(c, false), Learned::Frozen);
            }
        }
    }

    #[test]
    fn inconsistent_maps_never_reprobe() {
        let s = settings(|p| {
            p.prior = Some(0.0);
            p.mode = "inconsistent".into();
            p.reprobe = Some(1.0);
        });
        let mut m = map(&s);
        let r = ray(0.5, 0.5, 0);
        m.learn(cell(&m, &r), false);
        assert!((0..200).all(|i| m.advise(&ray(0.5, 0.5, i)) == Advice::Skip));
    }

    #[test]
    fn reprobe_rate_and_determinism() {
        for rate in [0.0f32, 0.1, 0.5, 1.0] {
            let s = settings(|p| {
                p.prior = Some(0.0);
                p.reprobe = Some(rate);
            });
            let mut m = map(&s);
            let base = ray(0.5, 0.5, 0);
            m.learn(cell(&m, &base), false);
            let n = 20_000u32;
            let mut probed = 0u32;
            for i in 0..n {
                // Distinct rays: pixel, sample and a slightly moved origin.
                let mut r = ray(0.5 + (i % 7) as f32 * 1e-4, 0.5, i / 3);
                r.sample = i % 3;
                let first = m.advise(&r);
                assert_eq!(first, m.advise(&r), "the same ray, the same answer");
                if first == Advice::Probe {
                    probed += 1;
                }
            }
            let got = f64::from(probed) / f64::from(n);
            assert!((got - f64::from(rate)).abs() < 0.015, "rate {rate}: {got}");
        }
        // The draw depends on the wall too, and stays in [0, 1).
        let r = ray(0.5, 0.5, 9);
        assert_ne!(reprobe_draw(&r, 4), reprobe_draw(&r, 5));
        assert_eq!(reprobe_draw(&r, 4), reprobe_draw(&r, 4));
        assert!((0..1000).all(|w| (0.0..1.0).contains(&reprobe_draw(&r, w))));
    }

    #[test]
    fn thresholds_zero_and_one_never_decide() {
        for prior in [100.0f32, 1.0, 1e-30, f32::from_bits(1)] {
            let s = settings(|p| {
                p.prior = Some(prior);
                p.miss = Some(0.0);
                p.hit = Some(1.0);
            });
            let mut m = map(&s);
            for c in [
                Counts::default(),
                Counts {
                    hits: u32::MAX,
                    misses: 0,
                },
                Counts {
                    hits: 0,
                    misses: u32::MAX,
                },
            ] {
                assert_eq!(m.decide(c), Decision::Undecided, "prior {prior}, {c:?}");
            }
            for _ in 0..1000 {
                m.learn(3, false);
                m.learn(5, true);
            }
            assert_eq!(
                (m.decision(3), m.decision(5)),
                (Decision::Undecided, Decision::Undecided)
            );
            assert_eq!(m.decided(), (0, 0));
        }
        // Without a prior, certainty does decide at 0 and 1.
        let mut m = map(&settings(|p| {
            p.prior = Some(0.0);
            p.miss = Some(0.0);
            p.hit = Some(1.0);
        }));
        m.learn(3, false);
        m.learn(5, true);
        assert_eq!(
            (m.decision(3), m.decision(5)),
            (Decision::Miss, Decision::Hit)
        );
    }

    #[test]
    fn a_miss_threshold_of_one_half_decides_fresh_cells_for_good() {
        let mut m = map(&settings(|p| {
            p.miss = Some(0.5);
            p.mode = "inconsistent".into();
        }));
        assert_eq!(m.decided(), (0, 192));
        assert_eq!(m.learn(0, true), Learned::Frozen);
        assert_eq!(m.decision(0), Decision::Miss);
    }

    #[test]
    fn counts_saturate_and_bad_cells_are_refused() {
        let mut m = map(&settings(|p| {
            p.res = Some(1);
            p.dirs = Some(1);
        }));
        assert_eq!(m.len(), 1);
        assert_eq!(m.learn(1, true), Learned::OutOfRange);
        assert_eq!(m.learn(u32::MAX, true), Learned::OutOfRange);
        assert_eq!(m.merge(0, u32::MAX - 1, 0), Learned::Counted);
        assert_eq!(m.learn(0, true), Learned::Counted);
        assert_eq!(m.learn(0, true), Learned::Counted);
        assert_eq!(m.counts(0).hits, u32::MAX);
        // Rays the map cannot bin.
        let mut r = ray(0.5, 0.5, 0);
        r.dir = Vec3::X;
        assert_eq!(m.advise(&r), Advice::Unplaced);
        r.dir = Vec3::ZERO;
        assert_eq!(m.advise(&r), Advice::Unplaced);
    }

    #[test]
    fn merges_add_counts_and_frozen_cells_take_none() {
        for mode in ["consistent", "inconsistent"] {
            let s = settings(|p| p.mode = mode.into());
            let mut learned = map(&s);
            let mut merged = map(&s);
            for _ in 0..30 {
                learned.learn(5, false);
            }
            learned.learn(5, true);
            assert_eq!(merged.merge(5, 1, 30), Learned::Counted);
            assert_eq!(merged.counts(5), learned.counts(5), "{mode}");
            assert_eq!(merged.merge(merged.len(), 1, 1), Learned::OutOfRange);
        }
        // Prior 1, miss 0.1: 20 misses decide a miss; an inconsistent map then takes
        // no more, a consistent one keeps counting.
        let frozen = settings(|p| {
            p.mode = "inconsistent".into();
            p.prior = Some(1.0);
        });
        let mut m = map(&frozen);
        assert_eq!(m.merge(2, 0, 20), Learned::Counted);
        assert_eq!(m.decision(2), Decision::Miss);
        assert_eq!(m.merge(2, 50, 0), Learned::Frozen);
        assert_eq!(
            m.counts(2),
            Counts {
                hits: 0,
                misses: 20
            }
        );
        let mut c = map(&settings(|p| p.prior = Some(1.0)));
        c.merge(2, 0, 20);
        assert_eq!(c.merge(2, 50, 0), Learned::Counted);
        assert_eq!(
            c.counts(2),
            Counts {
                hits: 50,
                misses: 20
            }
        );
        assert_eq!(c.merge(2, u32::MAX, 0), Learned::Counted);
        assert_eq!(c.counts(2).hits, u32::MAX, "counts saturate");
    }

    #[test]
    fn large_maps_hold_only_what_they_learned() {
        let mut m = map(&settings(|p| {
            p.res = Some(64);
            p.dirs = Some(256);
            p.prior = Some(1.0);
        }));
        assert!(m.len() > DENSE_MAX_CELLS);
        let last = m.len() - 1;
        for _ in 0..20 {
            m.learn(last, false);
            m.learn(0, true);
        }
        assert!(matches!(&m.cells, Cells::Sparse(c) if c.len() == 2));
        assert_eq!(m.decided(), (1, 1));
        assert_eq!(m.decision(last), Decision::Miss);
        assert_eq!(m.decision(1), Decision::Undecided);
        assert!(
            m.view().is_none(),
            "sparse maps are consulted by message only"
        );
    }

    #[test]
    fn views_see_what_the_map_learns_and_count_their_consults() {
        let s = settings(|p| {
            p.prior = Some(1.0);
            p.reprobe = Some(0.0);
        });
        let mut m = map(&s);
        let view = m.view().expect("dense maps have views");
        assert_eq!(view.wall(), 4);
        let r = ray(0.3, 0.6, 0);
        let c = cell(&m, &r);
        assert_eq!(view.consult(&r), Advice::Probe);
        view.probed();
        // 1 / (n + 2) <= 0.1 from 8 misses: the view skips the ray as the map does.
        for _ in 0..8 {
            m.learn(c, false);
        }
        assert_eq!(view.consult(&r), Advice::Skip);
        assert_eq!(view.consult(&r), m.advise(&r));
        let mut sideways = r;
        sideways.dir = Vec3::X;
        assert_eq!(view.consult(&sideways), Advice::Unplaced);
        let n = m.consults();
        let get = |a: &AtomicU64| a.load(Ordering::Relaxed);
        assert_eq!(
            (
                get(&n.lookups),
                get(&n.probes),
                get(&n.skipped),
                get(&n.unplaced)
            ),
            (4, 1, 2, 1)
        );
    }
}

//! One wall's radiance store: crossing points on the wall (2-D), each with the direction
//! and the radiance that came back through its ticket, queried by radius and angle.
//!
//! Every query of a job has the same radius, so the store is a uniform grid of square
//! cells as wide as that radius (a fixed-radius near-neighbour search, which is what a
//! grid does best): a query reads the 2 x 2 to 3 x 3 cells its circle touches, and an
//! insert appends to one cell. A cell keeps what a query reads of its entries together
//! ([`Hot`], 48 bytes: point, direction, radiance, the key's leading fields), so a query scans
//! memory in order instead of chasing an index per candidate; the rest of an entry is
//! read only for the entries that are in range and must be ordered. Nothing is allocated
//! per query: `first` and `nearest` keep their best candidate, and `average` sorts into a
//! buffer the store keeps between queries. (Before this grid, a k-d tree with one-by-one
//! inserts and a `Vec` per query cost several times more per lookup and per insert:
//! docs/history/2026-11-26-lean-tickets.md.)
//!
//! Answers must not depend on the order entries arrived in (tickets close in whatever
//! order the cluster's timing gives), so every choice between entries uses a total
//! order over what the entries *are* ([`EntryKey`], then their bits). The grid only finds
//! candidates (a superset, with slack for rounding); whether a point is in range is
//! decided exactly, in f64. Points are compared by value after folding `-0.0` into
//! `+0.0`, and non-finite points never enter.

use std::cell::Cell;
use std::cmp::Ordering;
use std::collections::HashMap;

use dray_core::ray::RayRecord;
use glam::Vec3;

use crate::settings::Retrieve;

/// Entries a wall holds by default; more are dropped and counted, so a flood of tickets
/// cannot exhaust the host's memory (about 130 bytes an entry).
pub const DEFAULT_MAX_ENTRIES: usize = 1 << 22;

/// The bytes one stored entry takes in a wall's store: the entry itself and the part of
/// it a query reads, kept in its cell ([`Hot`]). What `JobStats.cache_bytes_per_process`
/// multiplies entries by (Little 2011 reports each process's cache memory); the cells'
/// index (12 bytes an occupied cell) and the vectors' spare capacity come on top.
pub const ENTRY_BYTES: u64 = (std::mem::size_of::<Entry>() + std::mem::size_of::<Hot>()) as u64;

/// The cell edge of a store made without a radius ([`WallStore::new`]), scene units.
/// Any edge gives the same answers; one near the query radius gives them fastest.
pub const DEFAULT_CELL: f32 = 1.0 / 64.0;

/// Relative slack on the radius when choosing the cells a query reads: the exact test
/// in f64 can accept a point a few ulps beyond the radius, which must still be read.
const CELL_SLACK: f64 = 1e-6;

type FastState = foldhash::fast::FixedState;

/// A deterministic identity of the ray that made an entry: the ray's pixel, sample,
/// depth and kind, then the bit patterns of its origin and direction. Two runs of the
/// same job make the same keys whatever the timing, which is what "first" and the
/// tie-breaks need.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct EntryKey {
    pub pixel: u32,
    pub sample: u32,
    pub depth: u16,
    pub kind: u8,
    pub origin: [u32; 3],
    pub dir: [u32; 3],
}

impl EntryKey {
    /// The key of the entry `ray` would make.
    pub fn of(ray: &RayRecord) -> EntryKey {
        EntryKey {
            pixel: ray.pixel,
            sample: ray.sample,
            depth: ray.depth,
            kind: ray.kind as u8,
            origin: ray.origin.to_array().map(f32::to_bits),
            dir: ray.dir.to_array().map(f32::to_bits),
        }
    }
}

/// One stored crossing.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Entry {
    pub key: EntryKey,
    /// Crossing point in wall coordinates.
    pub point: [f32; 2],
    /// Unit direction of the ray that crossed.
    pub dir: Vec3,
    /// Radiance seen along that ray, linear RGB.
    pub radiance: [f32; 3],
}

/// The total order used for every choice between entries: the key first, then the
/// remaining bits, so even entries made by the same ray twice order the same way.
type EntryOrder = (EntryKey, [u32; 2], [u32; 3], [u32; 3]);

impl Entry {
    fn order(&self) -> EntryOrder {
        (
            self.key,
            self.point.map(f32::to_bits),
            self.dir.to_array().map(f32::to_bits),
            self.radiance.map(f32::to_bits),
        )
    }
}

/// What a query reads of an entry, stored in the entry's cell: all it needs unless two
/// candidates share a pixel and sample (then their keys are compared in full).
#[derive(Clone, Copy, Debug)]
struct Hot {
    point: [f32; 2],
    dir: [f32; 3],
    /// The leading fields of the entry's key, `(pixel << 32) | sample`: the order of two
    /// entries is the order of these unless they are equal.
    lead: u64,
    radiance: [f32; 3],
    /// Index into `WallStore::entries`.
    index: u32,
}

/// What a query asks for.
#[derive(Clone, Copy, Debug)]
pub struct Query {
    /// Crossing point in wall coordinates.
    pub point: [f32; 2],
    /// Unit direction of the ray.
    pub dir: Vec3,
    /// Radius in wall coordinates, inclusive; 0 never hits.
    pub radius: f32,
    /// Smallest accepted `dot(dir, stored dir)`.
    pub cos_min: f64,
    pub retrieve: Retrieve,
}

/// Why an entry was not stored.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum InsertError {
    #[error("the wall's store is full")]
    Full,
    #[error("crossing point or direction is not finite")]
    NotFinite,
}

/// One wall's store.
pub struct WallStore {
    /// Cell edge, scene units (positive and finite).
    cell: f64,
    /// Occupied cells: [`cell_key`] → index into `lists`. Small (12 bytes a cell), so a
    /// wall's index stays in a core's cache while the lists are read.
    cells: HashMap<u64, u32, FastState>,
    /// Each occupied cell's entries, their [`Hot`] parts in the order they arrived (which
    /// no answer depends on).
    lists: Vec<Vec<Hot>>,
    entries: Vec<Entry>,
    max_entries: usize,
    /// Entries refused because the store was full.
    pub dropped: u64,
}

thread_local! {
    /// `average`'s candidates, kept between queries so a query allocates nothing once
    /// the buffer has grown to the largest neighbourhood seen. Per thread, so that the
    /// store can be read by several threads at once (the wall's actor and, through
    /// [`crate::StoreView`], the tracing threads of the worker in its process).
    static SCRATCH: Cell<Vec<Hot>> = const { Cell::new(Vec::new()) };
}

impl Default for WallStore {
    fn default() -> Self {
        WallStore::new(DEFAULT_MAX_ENTRIES)
    }
}

/// `-0.0` → `+0.0`; `None` for a non-finite coordinate.
fn canonical(p: [f32; 2]) -> Option<[f32; 2]> {
    // Adding +0.0 turns -0.0 into +0.0 and leaves every other value alone.
    let p = p.map(|x| x + 0.0);
    p.iter().all(|x| x.is_finite()).then_some(p)
}

/// The hash key of cell (column, row).
fn cell_key((x, y): (i32, i32)) -> u64 {
    u64::from(x as u32) << 32 | u64::from(y as u32)
}

/// Where a query stands while it scans candidates.
enum Pick {
    /// `first` and `nearest`: the best so far, with its squared distance.
    Best(Option<(f64, Hot)>),
    /// `average`: every candidate in range.
    All(Vec<Hot>),
}

impl WallStore {
    /// An empty store holding at most `max_entries` entries (capped at `u32::MAX`),
    /// with cells of [`DEFAULT_CELL`].
    pub fn new(max_entries: usize) -> WallStore {
        WallStore::for_radius(max_entries, DEFAULT_CELL)
    }

    /// An empty store whose queries will mostly have this radius: its cells are that
    /// wide. A radius that is not a positive finite number (a job whose caches only
    /// fill) gets cells of [`DEFAULT_CELL`]. Answers never depend on the cell size.
    pub fn for_radius(max_entries: usize, radius: f32) -> WallStore {
        let cell = if radius.is_finite() && radius > 0.0 {
            radius
        } else {
            DEFAULT_CELL
        };
        WallStore {
            cell: f64::from(cell),
            cells: HashMap::default(),
            lists: Vec::new(),
            entries: Vec::new(),
            max_entries: max_entries.min(u32::MAX as usize),
            dropped: 0,
        }
    }

    /// Entries stored.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// The column (or row) of coordinate `x`: monotonic in `x`, saturating at the ends
    /// of `i32` (cells there are merely larger: answers stay exact).
    fn coord(&self, x: f64) -> i32 {
        (x / self.cell).floor() as i32
    }

    /// Store `entry`. A full store drops it (and counts it); a non-finite point or
    /// direction is refused, since it could never be found.
    pub fn insert(&mut self, mut entry: Entry) -> Result<(), InsertError> {
        let point = canonical(entry.point).ok_or(InsertError::NotFinite)?;
        if !entry.dir.is_finite() {
            return Err(InsertError::NotFinite);
        }
        if self.entries.len() >= self.max_entries {
            self.dropped += 1;
            return Err(InsertError::Full);
        }
        entry.point = point;
        // Cannot truncate: `max_entries` is at most u32::MAX.
        let index = self.entries.len() as u32;
        self.entries.push(entry);
        let at = (
            self.coord(f64::from(point[0])),
            self.coord(f64::from(point[1])),
        );
        let lists = &mut self.lists;
        let list = *self.cells.entry(cell_key(at)).or_insert_with(|| {
            lists.push(Vec::new());
            // At most one list per entry, so this fits a u32 too.
            (lists.len() - 1) as u32
        });
        let Some(list) = self.lists.get_mut(list as usize) else {
            // Cannot happen: every index in `cells` was pushed above.
            return Ok(());
        };
        list.push(Hot {
            point,
            dir: entry.dir.to_array(),
            lead: u64::from(entry.key.pixel) << 32 | u64::from(entry.key.sample),
            radiance: entry.radiance,
            index,
        });
        Ok(())
    }

    /// The total order of two stored entries (see [`EntryOrder`]), from their hot parts
    /// when those differ.
    fn cmp_entries(&self, a: &Hot, b: &Hot) -> Ordering {
        a.lead.cmp(&b.lead).then_with(|| {
            match (
                self.entries.get(a.index as usize),
                self.entries.get(b.index as usize),
            ) {
                (Some(x), Some(y)) => x.order().cmp(&y.order()),
                // Cannot happen (every hot part indexes its entry); any order will do.
                _ => a.index.cmp(&b.index),
            }
        })
    }

    /// The radiance answering `q`, or `None` for a miss.
    pub fn lookup(&self, q: &Query) -> Option<[f32; 3]> {
        if q.radius.is_nan() || q.radius <= 0.0 || self.entries.is_empty() || !q.dir.is_finite() {
            return None;
        }
        let point = canonical(q.point)?;
        let r = f64::from(q.radius);
        let r2 = r * r;
        let dir = q.dir.as_dvec3();
        let (px, py) = (f64::from(point[0]), f64::from(point[1]));

        let mut pick = match q.retrieve {
            Retrieve::Average => {
                let mut v = SCRATCH.take();
                v.clear();
                Pick::All(v)
            }
            Retrieve::First | Retrieve::Nearest => Pick::Best(None),
        };
        let mut scan = |cell: &[Hot]| {
            for h in cell {
                let du = f64::from(h.point[0]) - px;
                let dv = f64::from(h.point[1]) - py;
                let d2 = du * du + dv * dv;
                if d2 > r2 {
                    continue;
                }
                let d = glam::DVec3::new(
                    f64::from(h.dir[0]),
                    f64::from(h.dir[1]),
                    f64::from(h.dir[2]),
                );
                if dir.dot(d) < q.cos_min {
                    continue;
                }
                match &mut pick {
                    Pick::All(v) => v.push(*h),
                    Pick::Best(best) => {
                        let better = match best {
                            None => true,
                            Some((bd, b)) => {
                                let by_distance = match q.retrieve {
                                    Retrieve::Nearest => d2.total_cmp(bd),
                                    _ => Ordering::Equal,
                                };
                                by_distance.then_with(|| self.cmp_entries(h, b)) == Ordering::Less
                            }
                        };
                        if better {
                            *best = Some((d2, *h));
                        }
                    }
                }
            }
        };

        // The cells the circle's bounding square touches, with slack for rounding; when
        // there are more of them than occupied cells (a radius far larger than the
        // cells), every occupied cell instead.
        let reach = r * (1.0 + CELL_SLACK);
        let (x0, x1) = (self.coord(px - reach), self.coord(px + reach));
        let (y0, y1) = (self.coord(py - reach), self.coord(py + reach));
        let span = |lo: i32, hi: i32| (i64::from(hi) - i64::from(lo) + 1) as u64;
        let reads = span(x0, x1).saturating_mul(span(y0, y1));
        if reads > self.lists.len() as u64 {
            for list in &self.lists {
                scan(list);
            }
        } else {
            for x in x0..=x1 {
                for y in y0..=y1 {
                    if let Some(list) = self
                        .cells
                        .get(&cell_key((x, y)))
                        .and_then(|&i| self.lists.get(i as usize))
                    {
                        scan(list);
                    }
                }
            }
        }

        match pick {
            Pick::Best(best) => best.map(|(_, h)| h.radiance),
            Pick::All(mut v) => {
                let answer = self.average(&mut v);
                SCRATCH.set(v);
                answer
            }
        }
    }

    /// The mean radiance of `in_range`, summed in the entries' order (so the same set
    /// gives the same bits whatever order it was found in).
    fn average(&self, in_range: &mut [Hot]) -> Option<[f32; 3]> {
        if in_range.is_empty() {
            return None;
        }
        in_range.sort_unstable_by(|a, b| self.cmp_entries(a, b));
        let mut sum = [0f64; 3];
        for h in in_range.iter() {
            for (s, c) in sum.iter_mut().zip(h.radiance) {
                *s += f64::from(c);
            }
        }
        let n = in_range.len() as f64;
        Some(sum.map(|s| (s / n) as f32))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// docs/caches.md "Statistics" quotes this size.
    #[test]
    fn an_entry_takes_116_bytes() {
        assert_eq!(ENTRY_BYTES, 116);
    }

    fn key(pixel: u32) -> EntryKey {
        EntryKey {
            pixel,
            sample: 0,
            depth: 0,
            kind: 0,
            origin: [0; 3],
            dir: [0; 3],
        }
    }

    fn entry(pixel: u32, point: [f32; 2], dir: Vec3, radiance: f32) -> Entry {
        Entry {
            key: key(pixel),
            point,
            dir: dir.normalize(),
            radiance: [radiance, radiance * 0.5, radiance * 0.25],
        }
    }

    fn query(point: [f32; 2], radius: f32, retrieve: Retrieve) -> Query {
        Query {
            point,
            dir: Vec3::X,
            radius,
            cos_min: 10f64.to_radians().cos(),
            retrieve,
        }
    }

    /// A small deterministic generator (SplitMix64), so the tests need no extra crates.
    struct Rng(u64);
    impl Rng {
        fn next(&mut self) -> u64 {
            self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            z ^ (z >> 31)
        }
        fn unit(&mut self) -> f32 {
            (self.next() >> 40) as f32 / (1u64 << 24) as f32
        }
    }

    fn entries() -> Vec<Entry> {
        let mut rng = Rng(7);
        let mut out = Vec::new();
        for i in 0..2000 {
            // Clustered points, with many exact duplicates, and some slanted directions.
            let point = if i % 3 == 0 {
                [0.5, 0.5]
            } else {
                [rng.unit(), rng.unit()]
            };
            let dir = Vec3::new(1.0, rng.unit() * 0.3 - 0.15, rng.unit() * 0.3 - 0.15);
            out.push(entry((i * 7919) % 1000, point, dir, rng.unit() * 10.0));
        }
        out
    }

    #[test]
    fn answers_do_not_depend_on_insertion_order() {
        let es = entries();
        let mut forward = WallStore::default();
        let mut backward = WallStore::default();
        for e in &es {
            forward.insert(*e).unwrap();
        }
        for e in es.iter().rev() {
            backward.insert(*e).unwrap();
        }
        let mut rng = Rng(99);
        let mut hits = 0;
        for i in 0..500 {
            let point = if i % 5 == 0 {
                [0.5, 0.5]
            } else {
                [rng.unit(), rng.unit()]
            };
            for retrieve in [Retrieve::First, Retrieve::Nearest, Retrieve::Average] {
                for radius in [0.001, 0.02, 0.2] {
                    let q = query(point, radius, retrieve);
                    let a = forward.lookup(&q).map(|r| r.map(f32::to_bits));
                    let b = backward.lookup(&q).map(|r| r.map(f32::to_bits));
                    assert_eq!(a, b, "{point:?} {retrieve:?} {radius}");
                    hits += usize::from(a.is_some());
                }
            }
        }
        assert!(hits > 1000, "the test should mostly hit: {hits}");
    }

    /// The answer by definition: every entry read, in range decided in f64, choices by
    /// the entries' total order.
    fn reference(es: &[Entry], q: &Query) -> Option<[f32; 3]> {
        let p = canonical(q.point)?;
        let r2 = f64::from(q.radius) * f64::from(q.radius);
        let mut c: Vec<(f64, &Entry)> = es
            .iter()
            .filter_map(|e| {
                let e_p = canonical(e.point)?;
                let du = f64::from(e_p[0]) - f64::from(p[0]);
                let dv = f64::from(e_p[1]) - f64::from(p[1]);
                let d2 = du * du + dv * dv;
                let cos = q.dir.as_dvec3().dot(e.dir.as_dvec3());
                (q.radius > 0.0 && d2 <= r2 && cos >= q.cos_min).then_some((d2, e))
            })
            .collect();
        c.sort_by(|a, b| match q.retrieve {
            Retrieve::Nearest => a.0.total_cmp(&b.0).then(a.1.order().cmp(&b.1.order())),
            _ => a.1.order().cmp(&b.1.order()),
        });
        match q.retrieve {
            Retrieve::First | Retrieve::Nearest => c.first().map(|(_, e)| e.radiance),
            Retrieve::Average => (!c.is_empty()).then(|| {
                let mut sum = [0f64; 3];
                for (_, e) in &c {
                    for (s, v) in sum.iter_mut().zip(e.radiance) {
                        *s += f64::from(v);
                    }
                }
                sum.map(|s| (s / c.len() as f64) as f32)
            }),
        }
    }

    #[test]
    fn any_cell_size_gives_the_answers_of_a_full_scan() {
        let es = entries();
        let mut rng = Rng(41);
        // Cells far smaller than, near, and far larger than the radii; and a radius that
        // covers the whole wall (every occupied cell read).
        for cell in [1e-12, 1e-4, 0.003, 0.02, 0.5, 1e6] {
            let mut s = WallStore::for_radius(DEFAULT_MAX_ENTRIES, cell);
            for e in &es {
                s.insert(*e).unwrap();
            }
            for i in 0..300 {
                let point = if i % 7 == 0 {
                    [0.5, 0.5]
                } else {
                    [rng.unit() * 1.2 - 0.1, rng.unit() * 1.2 - 0.1]
                };
                for retrieve in [Retrieve::First, Retrieve::Nearest, Retrieve::Average] {
                    for radius in [0.001, 0.02, 0.2, 3.0, f32::MAX] {
                        let q = query(point, radius, retrieve);
                        let want = reference(&es, &q).map(|r| r.map(f32::to_bits));
                        let got = s.lookup(&q).map(|r| r.map(f32::to_bits));
                        assert_eq!(got, want, "cell {cell} {point:?} {retrieve:?} {radius}");
                    }
                }
            }
        }
    }

    #[test]
    fn retrieval_modes_pick_as_documented() {
        let mut s = WallStore::default();
        // Nearest is pixel 9 (distance 0.1); first is pixel 1 (smallest key).
        s.insert(entry(9, [0.1, 0.0], Vec3::X, 1.0)).unwrap();
        s.insert(entry(1, [0.0, 0.3], Vec3::X, 2.0)).unwrap();
        s.insert(entry(5, [0.2, 0.0], Vec3::X, 6.0)).unwrap();
        let at = |s: &WallStore, retrieve| s.lookup(&query([0.0, 0.0], 0.5, retrieve));
        assert_eq!(at(&s, Retrieve::Nearest), Some([1.0, 0.5, 0.25]));
        assert_eq!(at(&s, Retrieve::First), Some([2.0, 1.0, 0.5]));
        assert_eq!(at(&s, Retrieve::Average), Some([3.0, 1.5, 0.75]));
        // Equal distances: the smaller key wins.
        s.insert(entry(4, [-0.1, 0.0], Vec3::X, 4.0)).unwrap();
        assert_eq!(at(&s, Retrieve::Nearest), Some([4.0, 2.0, 1.0]));
    }

    #[test]
    fn angle_filters() {
        let mut s = WallStore::default();
        // 20 degrees off the query direction: outside 10, inside 30.
        let a = 20f32.to_radians();
        s.insert(entry(1, [0.0, 0.0], Vec3::new(a.cos(), a.sin(), 0.0), 1.0))
            .unwrap();
        let mut q = query([0.0, 0.0], 1.0, Retrieve::Nearest);
        assert_eq!(s.lookup(&q), None);
        q.cos_min = 30f64.to_radians().cos();
        assert!(s.lookup(&q).is_some());
        // Opposite direction never qualifies, even at 90 degrees.
        let mut s = WallStore::default();
        s.insert(entry(1, [0.0, 0.0], -Vec3::X, 1.0)).unwrap();
        q.cos_min = 90f64.to_radians().cos();
        assert_eq!(s.lookup(&q), None);
    }

    #[test]
    fn radius_is_inclusive_and_zero_never_hits() {
        let mut s = WallStore::default();
        s.insert(entry(1, [0.5, 0.0], Vec3::X, 1.0)).unwrap();
        assert!(
            s.lookup(&query([0.0, 0.0], 0.5, Retrieve::Nearest))
                .is_some()
        );
        assert!(
            s.lookup(&query([0.0, 0.0], 0.499_999_97, Retrieve::Nearest))
                .is_none()
        );
        // A 3-4-5 triangle: exactly on the circle.
        s.insert(entry(2, [3.0, 4.0], Vec3::X, 2.0)).unwrap();
        assert_eq!(
            s.lookup(&query([0.0, 0.0], 5.0, Retrieve::First)),
            Some([1.0, 0.5, 0.25])
        );
        assert_eq!(
            s.lookup(&query([-0.5, 0.0], 5.0, Retrieve::Nearest)),
            Some([1.0, 0.5, 0.25])
        );
        assert!(
            s.lookup(&query([3.0, 4.0 + 0.2], 0.19, Retrieve::Nearest))
                .is_none()
        );
        // Radius 0 never hits, not even at the exact point.
        assert_eq!(s.lookup(&query([0.5, 0.0], 0.0, Retrieve::Nearest)), None);
    }

    #[test]
    fn many_entries_at_one_point_do_not_panic() {
        let mut s = WallStore::default();
        for i in 0..10_000 {
            s.insert(entry(i, [0.25, 0.75], Vec3::X, 1.0)).unwrap();
            // Negative zero and positive zero are the same point.
            s.insert(entry(i, [-0.0, 0.0], Vec3::X, 1.0)).unwrap();
            s.insert(entry(i, [0.0, -0.0], Vec3::X, 1.0)).unwrap();
        }
        assert_eq!(s.len(), 30_000);
        assert_eq!(s.lists.len(), 2);
        let q = query([0.25, 0.75], 1e-6, Retrieve::Average);
        assert_eq!(s.lookup(&q), Some([1.0, 0.5, 0.25]));
        let q = query([-0.0, -0.0], 1e-6, Retrieve::First);
        assert_eq!(s.lookup(&q), Some([1.0, 0.5, 0.25]));
    }

    #[test]
    fn points_sharing_one_coordinate_do_not_panic() {
        // Many distinct points on a few lines (shared x, or shared y), in a scrambled
        // order: kiddo's bucket splits must cope with long runs of equal coordinates.
        let mut rng = Rng(3);
        let mut s = WallStore::default();
        let mut t = WallStore::default();
        let mut n = 0;
        for i in 0..20_000u32 {
            let line = (rng.next() % 3) as f32;
            let along = (rng.next() % 5000) as f32 * 1e-3;
            s.insert(entry(i, [line, along], Vec3::X, 1.0)).unwrap();
            t.insert(entry(i, [along, line], Vec3::X, 1.0)).unwrap();
            n += 1;
        }
        assert_eq!((s.len(), t.len()), (n, n));
        let q = query([1.0, 2.5], 1e-3, Retrieve::Average);
        let u = query([2.5, 1.0], 1e-3, Retrieve::Average);
        assert_eq!(s.lookup(&q), t.lookup(&u));
    }

    #[test]
    fn bad_points_and_a_full_store_are_refused() {
        let mut s = WallStore::new(2);
        assert_eq!(
            s.insert(entry(1, [f32::NAN, 0.0], Vec3::X, 1.0)),
            Err(InsertError::NotFinite)
        );
        assert_eq!(
            s.insert(entry(1, [f32::INFINITY, 0.0], Vec3::X, 1.0)),
            Err(InsertError::NotFinite)
        );
        s.insert(entry(1, [0.0, 0.0], Vec3::X, 1.0)).unwrap();
        s.insert(entry(2, [1.0, 0.0], Vec3::X, 1.0)).unwrap();
        assert_eq!(
            s.insert(entry(3, [2.0, 0.0], Vec3::X, 1.0)),
            Err(InsertError::Full)
        );
        assert_eq!(s.dropped, 1);
        // NaN queries miss instead of reaching the tree.
        let q = query([f32::NAN, 0.0], 1.0, Retrieve::Nearest);
        assert_eq!(s.lookup(&q), None);
        let mut q = query([0.0, 0.0], 1.0, Retrieve::Nearest);
        q.dir = Vec3::NAN;
        assert_eq!(s.lookup(&q), None);
    }
}

//! One wall's radiance store: crossing points on the wall (2-D), each with the direction
//! and the radiance that came back through its ticket, queried by radius and angle.
//!
//! A k-d tree (kiddo 5) finds the crossing points near a query. Two of kiddo's limits
//! shape this module:
//! - Its fixed-size leaf buckets cannot split more items than a bucket holds at the
//!   *exact same point*, and it panics instead. Rays from one camera through one pixel
//!   all cross a wall at nearby, often identical, points, so the tree holds each
//!   distinct point once, and the point indexes a list of the entries stored there.
//! - Its comparisons need ordered floats: NaN must never reach it, and `-0.0`/`+0.0`
//!   (equal to kiddo, different bits to a hash map) are folded into `+0.0`.
//!
//! Answers must not depend on the order entries arrived in (tickets close in whatever
//! order the cluster's timing gives), so every choice between entries uses a total
//! order over what the entries *are* ([`EntryKey`], then their bits), and kiddo's
//! floating-point distance only finds candidates: whether a point is in range is
//! decided again here, exactly, in f64.

use std::collections::HashMap;

use dray_core::ray::RayRecord;
use glam::Vec3;
use kiddo::{KdTree, SquaredEuclidean};

use crate::settings::Retrieve;

/// Entries a wall holds by default; more are dropped and counted, so a flood of tickets
/// cannot exhaust the host's memory (about 80 bytes an entry).
pub const DEFAULT_MAX_ENTRIES: usize = 1 << 22;

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

/// What a lookup asks for.
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
    /// One item per distinct point; the item is the index into `points`.
    tree: KdTree<f32, 2>,
    /// Distinct points and the indices (into `entries`) stored at each.
    points: Vec<([f32; 2], Vec<u32>)>,
    /// Point bits → index into `points`.
    point_index: HashMap<[u32; 2], u32>,
    entries: Vec<Entry>,
    max_entries: usize,
    /// Entries refused because the store was full.
    pub dropped: u64,
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

impl WallStore {
    /// An empty store holding at most `max_entries` entries (capped at `u32::MAX`).
    pub fn new(max_entries: usize) -> WallStore {
        WallStore {
            tree: KdTree::new(),
            points: Vec::new(),
            point_index: HashMap::new(),
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

    /// Store `entry`. A full store drops it (and counts it); a non-finite point or
    /// direction is refused, since it could never be found and would break the tree.
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
        let bits = point.map(f32::to_bits);
        match self.point_index.get(&bits) {
            Some(&p) => {
                if let Some((_, list)) = self.points.get_mut(p as usize) {
                    list.push(index);
                }
            }
            None => {
                // At most one point per entry, so this fits a u32 too.
                let p = self.points.len() as u32;
                self.points.push((point, vec![index]));
                self.point_index.insert(bits, p);
                self.tree.add(&point, u64::from(p));
            }
        }
        Ok(())
    }

    /// The radiance answering `q`, or `None` for a miss.
    pub fn lookup(&self, q: &Query) -> Option<[f32; 3]> {
        if q.radius.is_nan() || q.radius <= 0.0 || self.entries.is_empty() || !q.dir.is_finite() {
            return None;
        }
        let point = canonical(q.point)?;
        let r = f64::from(q.radius);
        let r2 = r * r;
        // kiddo measures in f32: ask it for a slightly larger radius so rounding can only
        // add candidates, then decide exactly below. (A huge radius becomes +inf, which
        // kiddo handles as "everything".)
        let slack = r * (1.0 + 1e-4);
        let query_r2 = (slack * slack) as f32;
        let dir = q.dir.as_dvec3();

        let mut best: Option<(f64, &Entry)> = None;
        let mut in_range: Vec<&Entry> = Vec::new();
        for nn in self
            .tree
            .within_unsorted::<SquaredEuclidean>(&point, query_r2)
        {
            let Some((p, list)) = self.points.get(nn.item as usize) else {
                continue;
            };
            let du = f64::from(p[0]) - f64::from(point[0]);
            let dv = f64::from(p[1]) - f64::from(point[1]);
            let d2 = du * du + dv * dv;
            if d2 > r2 {
                continue;
            }
            for e in list.iter().filter_map(|&i| self.entries.get(i as usize)) {
                if dir.dot(e.dir.as_dvec3()) < q.cos_min {
                    continue;
                }
                match q.retrieve {
                    Retrieve::Average => in_range.push(e),
                    Retrieve::First => {
                        if best.is_none_or(|(_, b)| e.order() < b.order()) {
                            best = Some((d2, e));
                        }
                    }
                    Retrieve::Nearest => {
                        let closer = best.is_none_or(|(bd, b)| {
                            d2.total_cmp(&bd).then_with(|| e.order().cmp(&b.order()))
                                == std::cmp::Ordering::Less
                        });
                        if closer {
                            best = Some((d2, e));
                        }
                    }
                }
            }
        }
        match q.retrieve {
            Retrieve::First | Retrieve::Nearest => best.map(|(_, e)| e.radiance),
            Retrieve::Average => {
                if in_range.is_empty() {
                    return None;
                }
                in_range.sort_unstable_by_key(|e| e.order());
                let mut sum = [0f64; 3];
                for e in &in_range {
                    for (s, c) in sum.iter_mut().zip(e.radiance) {
                        *s += f64::from(c);
                    }
                }
                let n = in_range.len() as f64;
                Some(sum.map(|s| (s / n) as f32))
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
        assert_eq!(s.points.len(), 2);
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

//! Pre-splitting: before the binned-SAH build (`build`), the triangles whose boxes are
//! poor fits (long, thin, diagonal ones: a box much larger than its triangle) are cut
//! along spatial planes into fragments, each with the tight box of its part of the
//! triangle, and every fragment goes into the build as its own reference to the same
//! triangle. The tree then has smaller, less overlapping boxes where those triangles are,
//! which a ray's traversal feels as fewer node visits and leaf tests.
//!
//! The method is Embree's (`kernels/builders/primrefgen_presplit.h`, its "fast spatial
//! presplit" SAH builder; Karras & Aila 2013 split triangles the same way before an LBVH
//! build): a 1024³ grid over the scene; each triangle's priority is
//! `(box area − triangle's projected area) × 1.5^level)^¼`, where `level` is the highest
//! Morton bit in which the box's two corner cells differ (a box crossing a coarse grid
//! plane splits there first, so fragments of neighbours line up); a budget of extra
//! references (Embree's default +20%) is shared in proportion to priority, each chosen
//! triangle getting a power of two of pieces (2 to 32), cut recursively at the coarsest
//! grid plane its current fragment crosses. When the pieces come to more than the budget,
//! the triangles of lowest priority are left whole.
//!
//! A fragment's box is the bounds of the triangle clipped to the plane's side, met with
//! the box being cut (as Embree's `splitPolygon`), but computed in f64 and rounded
//! outwards to f32: a fragment box never leaves out a point of the triangle in its part,
//! whatever the coordinates' magnitude, so the union of a triangle's fragment boxes holds
//! the whole triangle (tested), which is all the node test's conservativeness needs (see
//! `super`'s doc). Every step is deterministic (no parallel float sums), so a build gives
//! the same references, and the same tree, on any number of threads.

use glam::{DVec3, Vec3, Vec3A};
use obvhs::aabb::Aabb;
use rayon::prelude::*;

/// Cells of the splitting grid per axis (Embree's `GRID_SIZE`).
const GRID: u32 = 1024;
/// Most pieces a triangle is cut into (Embree's `MAX_PRESPLITS_PER_PRIMITIVE`).
const MAX_PIECES: usize = 32;
/// The weight of a coarser split plane in the priority (Embree's
/// `PRIORITY_SPLIT_POS_WEIGHT`).
const LEVEL_WEIGHT: f64 = 1.5;
/// Primitives per deterministic partial sum of the priorities.
const SUM_CHUNK: usize = 4096;

/// The references pre-splitting makes from `boxes` (one per primitive): `boxes` with a
/// split primitive's box replaced by its first fragment's, then the further fragments'
/// boxes, and for those (`count..`) the primitive each refers to. No split leaves
/// `extra` empty and `boxes` as they were.
pub(super) struct Refs {
    pub boxes: Vec<Aabb>,
    pub extra: Vec<u32>,
}

impl Refs {
    /// The primitive of reference `r`, with `count` primitives.
    #[inline]
    pub fn primitive(&self, r: u32, count: u32) -> u32 {
        if r < count {
            r
        } else {
            self.extra[(r - count) as usize]
        }
    }
}

/// The splitting grid: `GRID` cells per axis over the scene's box, its longest side
/// (cells are cubes, as Embree's).
struct Grid {
    base: DVec3,
    extent: f64,
}

impl Grid {
    /// The grid cells of a box's corners, shrunk by a fifth of a cell at each end (so a
    /// box that only touches a cell does not count as crossing into it), each axis with
    /// no extent taking its lower cell for both.
    fn cells(&self, b: &Aabb) -> ([u32; 3], [u32; 3]) {
        let scale = f64::from(GRID) / self.extent;
        let top = f64::from(GRID - 1);
        let mut lo = [0u32; 3];
        let mut hi = [0u32; 3];
        for a in 0..3 {
            let gl = (f64::from(b.min[a]) - self.base[a]) * scale + 0.2;
            let gu = (f64::from(b.max[a]) - self.base[a]) * scale - 0.2;
            let il = gl.floor().clamp(0.0, top) as u32;
            let iu = gu.floor().clamp(0.0, top) as u32;
            lo[a] = il;
            hi[a] = if gl >= gu { il } else { iu.max(il) };
        }
        (lo, hi)
    }

    /// The Morton codes of a box's corner cells.
    fn codes(&self, b: &Aabb) -> (u32, u32) {
        let (lo, hi) = self.cells(b);
        (interleave(lo), interleave(hi))
    }

    /// Where to cut `b`: the coarsest grid plane it crosses (the highest bit in which its
    /// corners' Morton codes differ gives the level and the axis), as an f32 strictly
    /// inside `b` on that axis; `None` when it lies within one cell.
    fn split_pos(&self, b: &Aabb) -> Option<(usize, f32)> {
        let (lo, hi) = self.cells(b);
        let diff = interleave(lo) ^ interleave(hi);
        if diff == 0 {
            return None;
        }
        let bit = 31 - diff.leading_zeros();
        let (level, axis) = (bit / 3, (bit % 3) as usize);
        let cell = hi[axis] & !((1u32 << level) - 1);
        let pos = (self.base[axis] + f64::from(cell) * self.extent / f64::from(GRID)) as f32;
        (b.min[axis] < pos && pos < b.max[axis]).then_some((axis, pos))
    }
}

/// Bits of `c[0]` at 3i, `c[1]` at 3i+1, `c[2]` at 3i+2 (ten bits each).
fn interleave(c: [u32; 3]) -> u32 {
    fn spread(mut x: u32) -> u32 {
        x &= 0x3ff;
        x = (x | x << 16) & 0x0300_00ff;
        x = (x | x << 8) & 0x0300_f00f;
        x = (x | x << 4) & 0x030c_30c3;
        (x | x << 2) & 0x0924_9249
    }
    spread(c[0]) | spread(c[1]) << 1 | spread(c[2]) << 2
}

/// A triangle's splitting priority (Embree's `compute_priority`, in f64 so that no
/// area overflows): zero for a box within one cell or a triangle of no area.
fn priority(grid: &Grid, b: &Aabb, tri: &[DVec3; 3]) -> f32 {
    let (lo, hi) = grid.codes(b);
    if lo == hi {
        return 0.0;
    }
    let d = (Vec3::from(b.max).as_dvec3() - Vec3::from(b.min).as_dvec3()).max(DVec3::ZERO);
    let box_area = 2.0 * (d.x * d.y + d.y * d.z + d.z * d.x);
    let n = (tri[1] - tri[0]).cross(tri[2] - tri[0]);
    let tri_area = n.x.abs() + n.y.abs() + n.z.abs();
    if tri_area.is_nan() || tri_area <= 0.0 || !box_area.is_finite() {
        return 0.0;
    }
    let level = 31 - (lo ^ hi).leading_zeros();
    let p = ((box_area - tri_area).max(0.0) * LEVEL_WEIGHT.powi(level as i32))
        .sqrt()
        .sqrt();
    if p.is_finite() { p as f32 } else { 0.0 }
}

/// The largest f32 at most `x`.
fn down(x: f64) -> f32 {
    let f = x as f32;
    if f64::from(f) > x { f.next_down() } else { f }
}

/// The smallest f32 at least `x`.
fn up(x: f64) -> f32 {
    let f = x as f32;
    if f64::from(f) < x { f.next_up() } else { f }
}

/// Cut fragment box `b` of triangle `tri` at `pos` on `axis`: the boxes of the parts of
/// the triangle on each side, within `b`, or `None` for a side the triangle does not
/// reach within `b`.
///
/// Each side's bounds are those of the corners on that side and the points where edges
/// cross the plane. A crossing point is interpolated in f64 (the corners are f32, exact
/// in f64), its error bounded by 2^-45 of its edge's coordinates (the arithmetic's is
/// below 2^-50), and that allowance is added outside before rounding outwards to f32; on
/// the cut axis the point is the plane itself, exactly.
fn clip(tri: &[DVec3; 3], b: &Aabb, axis: usize, pos: f32) -> [Option<Aabb>; 2] {
    let p = f64::from(pos);
    let empty = (DVec3::INFINITY, DVec3::NEG_INFINITY);
    let mut sides = [empty, empty];
    let grow = |s: &mut (DVec3, DVec3), lo: DVec3, hi: DVec3| {
        s.0 = s.0.min(lo);
        s.1 = s.1.max(hi);
    };
    for i in 0..3 {
        let (v0, v1) = (tri[i], tri[(i + 1) % 3]);
        let (d0, d1) = (v0[axis], v1[axis]);
        if d0 <= p {
            grow(&mut sides[0], v0, v0);
        }
        if d0 >= p {
            grow(&mut sides[1], v0, v0);
        }
        if (d0 < p && p < d1) || (d1 < p && p < d0) {
            let t = (p - d0) / (d1 - d0);
            let mut c = v0 + (v1 - v0) * t;
            let mut err = (v0.abs() + v1.abs()) * 2f64.powi(-45);
            c[axis] = p;
            err[axis] = 0.0;
            for s in &mut sides {
                grow(s, c - err, c + err);
            }
        }
    }
    sides.map(|(lo, hi)| {
        let lo = Vec3A::new(down(lo.x), down(lo.y), down(lo.z)).max(b.min);
        let hi = Vec3A::new(up(hi.x), up(hi.y), up(hi.z)).min(b.max);
        lo.cmple(hi).all().then(|| Aabb::new(lo, hi))
    })
}

/// Up to [`MAX_PIECES`] fragment boxes.
struct Pieces {
    boxes: [Aabb; MAX_PIECES],
    len: usize,
}

/// Cut fragment `b` of `tri` into up to `pieces` (a power of two, at most the room left
/// in `out`), halving the count at each cut (Embree's `splitPrimitive`). A fragment
/// within one grid cell stays whole; a cut one side of which the triangle does not reach
/// keeps the other side's (tighter) box whole.
fn split_into(grid: &Grid, tri: &[DVec3; 3], b: Aabb, pieces: usize, out: &mut Pieces) {
    if pieces > 1
        && let Some((axis, pos)) = grid.split_pos(&b)
    {
        match clip(tri, &b, axis, pos) {
            [Some(l), Some(r)] => {
                split_into(grid, tri, l, pieces / 2, out);
                split_into(grid, tri, r, pieces - pieces / 2, out);
                return;
            }
            [Some(one), None] | [None, Some(one)] => {
                out.boxes[out.len] = one;
                out.len += 1;
                return;
            }
            [None, None] => {}
        }
    }
    out.boxes[out.len] = b;
    out.len += 1;
}

/// The fragments of a triangle with box `b` cut into up to `pieces`.
fn pieces_of(grid: &Grid, tri: &[DVec3; 3], b: Aabb, pieces: usize) -> Pieces {
    let mut out = Pieces {
        boxes: [Aabb::empty(); MAX_PIECES],
        len: 0,
    };
    split_into(grid, tri, b, pieces.min(MAX_PIECES), &mut out);
    out
}

/// Pre-split the primitives whose boxes are `boxes` (triangle `i`'s corners are
/// `corners(i)`), adding at most `budget` references per primitive (0 splits nothing).
/// The result keeps fewer than 2^31 references, as the build requires.
pub(super) fn presplit(
    boxes: Vec<Aabb>,
    corners: impl Fn(u32) -> [Vec3; 3] + Sync,
    budget: f32,
) -> Refs {
    let n = boxes.len();
    let none = |boxes: Vec<Aabb>| Refs {
        boxes,
        extra: Vec::new(),
    };
    let room = ((1usize << 31) - 1).saturating_sub(n);
    let budget = if budget.is_finite() && budget > 0.0 {
        ((f64::from(budget) * n as f64) as usize).min(room)
    } else {
        0
    };
    if budget == 0 {
        return none(boxes);
    }
    let scene = boxes.iter().fold(Aabb::empty(), |a, b| a.union(b));
    let extent = (scene.max - scene.min).max_element();
    if !(extent > 0.0 && extent.is_finite()) {
        return none(boxes);
    }
    let grid = Grid {
        base: Vec3::from(scene.min).as_dvec3(),
        extent: f64::from(extent),
    };
    let tri = |i: u32| corners(i).map(|c| c.as_dvec3());
    let priorities: Vec<f32> = boxes
        .par_iter()
        .enumerate()
        .map(|(i, b)| priority(&grid, b, &tri(i as u32)))
        .collect();
    // Partial sums over fixed chunks, added in order: the same total on any pool.
    let partial: Vec<f64> = priorities
        .par_chunks(SUM_CHUNK)
        .map(|c| c.iter().map(|&p| f64::from(p)).sum::<f64>())
        .collect();
    let total: f64 = partial.iter().sum();
    if !(total > 0.0 && total.is_finite()) {
        return none(boxes);
    }
    // Pieces per primitive: its share of the budget, as the next power of two (2 to 32),
    // none below a share of one reference.
    let share = budget as f64 / total;
    let wanted = |p: f32| -> usize {
        let rel = f64::from(p) * share;
        if rel < 1.0 {
            1
        } else {
            1usize << (rel.log2().ceil() as u32).clamp(1, MAX_PIECES.trailing_zeros())
        }
    };
    let mut chosen: Vec<u32> = (0..n as u32)
        .into_par_iter()
        .filter(|&i| wanted(priorities[i as usize]) > 1)
        .collect();
    if chosen.is_empty() {
        return none(boxes);
    }
    // Primitive `i`'s fragments (cut twice, to count and to keep, as Embree does:
    // holding them all between would cost more memory than cutting costs time).
    let fragments_of = |i: u32| {
        pieces_of(
            &grid,
            &tri(i),
            boxes[i as usize],
            wanted(priorities[i as usize]),
        )
    };
    // The references each chosen primitive adds, then the highest priorities kept
    // within the budget (ties to the lower index).
    let added: Vec<u32> = chosen
        .par_iter()
        .map(|&i| fragments_of(i).len as u32 - 1)
        .collect();
    let mut rank: Vec<u32> = (0..chosen.len() as u32).collect();
    rank.par_sort_unstable_by(|&a, &b| {
        let (pa, pb) = (chosen[a as usize], chosen[b as usize]);
        priorities[pb as usize]
            .total_cmp(&priorities[pa as usize])
            .then(pa.cmp(&pb))
    });
    let mut used = 0usize;
    let mut keep = vec![false; chosen.len()];
    for &k in &rank {
        let a = added[k as usize] as usize;
        if used + a > budget {
            break;
        }
        used += a;
        keep[k as usize] = true;
    }
    drop(rank);
    drop(added);
    let mut k = 0;
    chosen.retain(|_| {
        k += 1;
        keep[k - 1]
    });
    drop(keep);
    // The fragments, in primitive order; the first replaces the primitive's box.
    let fragments: Vec<(u32, Aabb)> = chosen
        .par_iter()
        .flat_map_iter(|&i| {
            let p = fragments_of(i);
            (0..p.len).map(move |j| (i, p.boxes[j]))
        })
        .collect();
    drop(priorities);
    let mut boxes = boxes;
    let mut extra = Vec::with_capacity(fragments.len() - chosen.len());
    boxes.reserve_exact(fragments.len() - chosen.len());
    let mut last = u32::MAX;
    for (i, b) in fragments {
        if i == last {
            boxes.push(b);
            extra.push(i);
        } else {
            boxes[i as usize] = b;
            last = i;
        }
    }
    Refs { boxes, extra }
}

#[cfg(test)]
mod tests {
    use super::super::build::tests::{depth, leaves, uniforms};
    use super::super::build::{MAX_DEPTH, build};
    use super::*;

    fn tri_box(t: &[Vec3; 3]) -> Aabb {
        let lo = t[0].min(t[1]).min(t[2]);
        let hi = t[0].max(t[1]).max(t[2]);
        Aabb::new(Vec3A::from(lo), Vec3A::from(hi))
    }

    /// Long skinny triangles across the scene, small ones, flat axis-aligned ones and
    /// degenerate ones (a point, a line), `scale` across and `shift` from the origin.
    fn soup(n: usize, scale: f32, shift: Vec3, seed: u64) -> Vec<[Vec3; 3]> {
        let mut next = uniforms(seed);
        let mut p = || Vec3::new(next(), next(), next());
        (0..n)
            .map(|i| {
                let (a, b, c) = (p(), p(), p());
                let t = match i % 5 {
                    // A sliver from one side of the scene to the other.
                    0 => [a, b, a + (c - a) * 0.01],
                    1 => [a, a + (b - a) * 0.05, a + (c - a) * 0.05],
                    // Flat in z.
                    2 => [a, Vec3::new(b.x, b.y, a.z), Vec3::new(c.x, c.y, a.z)],
                    3 => [a, a, a],
                    _ => [a, b, a + (b - a) * 0.5],
                };
                t.map(|v| v * scale + shift)
            })
            .collect()
    }

    /// Whether `b` holds `p`, give or take 2^-40 of `p`'s coordinates (the rounding of
    /// computing `p` in f64, far below an f32 step).
    fn contains(b: &Aabb, p: DVec3) -> bool {
        (0..3).all(|a| {
            let e = p[a].abs() * 2f64.powi(-40);
            f64::from(b.min[a]) <= p[a] + e && p[a] - e <= f64::from(b.max[a])
        })
    }

    /// Every triangle's references: their boxes lie within its box, and every point of
    /// the triangle (corners, edge points, inner points, computed in f64) lies in one of
    /// them; the budget holds; skinny triangles do get split. At several scales and far
    /// from the origin, where f32 rounding of the crossing points alone would miss.
    #[test]
    fn fragments_cover_their_triangle_within_its_box() {
        let cases = [
            (1.0, Vec3::ZERO),
            (1e6, Vec3::ZERO),
            (1.0, Vec3::new(1e6, -3e5, 7e4)),
            (1e-3, Vec3::new(-2.0, 5.0, 1e3)),
        ];
        for (scale, shift) in cases {
            let tris = soup(4000, scale, shift, 0x1234_5678);
            let boxes: Vec<Aabb> = tris.iter().map(tri_box).collect();
            let refs = presplit(boxes.clone(), |i| tris[i as usize], 2.0);
            let n = tris.len() as u32;
            assert_eq!(refs.boxes.len(), tris.len() + refs.extra.len());
            assert!(refs.extra.len() <= 8000, "{}", refs.extra.len());
            assert!(refs.extra.len() > 600, "{}", refs.extra.len());
            let mut of: Vec<Vec<Aabb>> = vec![Vec::new(); tris.len()];
            for r in 0..refs.boxes.len() as u32 {
                of[refs.primitive(r, n) as usize].push(refs.boxes[r as usize]);
            }
            let mut next = uniforms(99);
            for (i, t) in tris.iter().enumerate() {
                let whole = &boxes[i];
                for b in &of[i] {
                    assert!(
                        b.min.cmpge(whole.min).all() && b.max.cmple(whole.max).all(),
                        "{scale} {shift}: triangle {i}'s fragment {b:?} outside {whole:?}"
                    );
                }
                let [a, b, c] = t.map(|v| v.as_dvec3());
                let mut points = vec![a, b, c, (a + b) * 0.5, (b + c) * 0.5, (c + a) * 0.5];
                for _ in 0..40 {
                    let (u, v) = (f64::from(next()), f64::from(next()));
                    let (u, v) = if u + v > 1.0 {
                        (1.0 - u, 1.0 - v)
                    } else {
                        (u, v)
                    };
                    points.push(a + (b - a) * u + (c - a) * v);
                    points.push(a + (b - a) * u);
                }
                for p in points {
                    assert!(
                        of[i].iter().any(|f| contains(f, p)),
                        "{scale} {shift}: point {p} of triangle {i} in no fragment"
                    );
                }
            }
        }
    }

    /// Nothing to split: no budget, one primitive's box a point, every box within one
    /// cell; and a budget of zero returns the boxes as they came.
    #[test]
    fn degenerate_inputs_split_nothing() {
        let tris = soup(500, 1.0, Vec3::ZERO, 7);
        let boxes: Vec<Aabb> = tris.iter().map(tri_box).collect();
        let refs = presplit(boxes.clone(), |i| tris[i as usize], 0.0);
        assert!(refs.extra.is_empty());
        assert_eq!(refs.boxes, boxes);
        let point = [Vec3::splat(3.0); 3];
        let refs = presplit(vec![tri_box(&point); 100], |_| point, 0.3);
        assert!(refs.extra.is_empty());
        let nan = presplit(vec![tri_box(&point)], |_| point, f32::NAN);
        assert!(nan.extra.is_empty());
    }

    /// The references do not depend on the pool's size.
    #[test]
    fn the_same_references_on_any_pool() {
        let tris = soup(30_000, 1.0, Vec3::ZERO, 3);
        let boxes: Vec<Aabb> = tris.iter().map(tri_box).collect();
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .expect("a pool");
            pool.install(|| presplit(boxes.clone(), |i| tris[i as usize], 0.3))
        };
        let (a, b) = (run(1), run(3));
        assert_eq!(a.boxes, b.boxes);
        assert_eq!(a.extra, b.extra);
        assert!(!a.extra.is_empty());
    }

    /// Coincident slivers (every fragment of each the same as the others'), nested ones
    /// sharing a centre, and slivers near the largest coordinates accelerator space
    /// holds (2^100, whose box areas overflow f32): the references still build a tree
    /// within [`MAX_DEPTH`] holding every reference once.
    #[test]
    fn degenerate_and_huge_inputs_stay_within_the_depth_limit() {
        let sliver = [
            Vec3::ZERO,
            Vec3::new(1000.0, 700.0, 300.0),
            Vec3::new(1.0, 0.0, 2.0),
        ];
        let coincident = vec![sliver; 20_000];
        let nested: Vec<[Vec3; 3]> = (1..=20_000)
            .map(|i| sliver.map(|v| (v - Vec3::splat(300.0)) * i as f32))
            .collect();
        let big = 2f32.powi(99);
        let huge = soup(20_000, big, Vec3::splat(-big * 0.5), 11);
        for tris in [coincident, nested, huge] {
            let boxes: Vec<Aabb> = tris.iter().map(tri_box).collect();
            // A budget of two a triangle: equal priorities share it (a smaller one
            // gives none of them a whole reference, and splits nothing).
            let refs = presplit(boxes, |i| tris[i as usize], 2.0);
            let n = tris.len() as u32;
            assert!(refs.extra.len() > 5_000, "{}", refs.extra.len());
            assert!(refs.extra.len() <= 40_000, "{}", refs.extra.len());
            let total = refs.boxes.len();
            let bvh = build(refs.boxes.clone());
            assert!(depth(&bvh) <= MAX_DEPTH, "{}", depth(&bvh));
            assert_eq!(leaves(&bvh), (0..total as u32).collect::<Vec<_>>());
            let mut covered = vec![false; tris.len()];
            (0..total as u32).for_each(|r| covered[refs.primitive(r, n) as usize] = true);
            assert!(covered.iter().all(|&c| c));
        }
    }

    #[test]
    fn interleave_puts_x_lowest() {
        assert_eq!(interleave([1, 0, 0]), 1);
        assert_eq!(interleave([0, 1, 0]), 2);
        assert_eq!(interleave([0, 0, 1]), 4);
        assert_eq!(interleave([0x3ff, 0, 0]), 0x0924_9249);
        assert_eq!(interleave([0x3ff; 3]), 0x3fff_ffff);
    }
}

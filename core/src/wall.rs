//! Walls: the faces of domains, where ray caches live (docs/caches.md "Walls").
//!
//! A wall is one face of one domain, seen by the rays that *enter* the domain through it:
//! wall `6 * domain + face`, faces in the order -x, +x, -y, +y, -z, +z. A face shared by
//! two domains is therefore two walls, one per direction of crossing, and each caches
//! the radiance seen looking into its own domain. Walls on the scene bounds are *outer*
//! walls: camera rays from outside the scene cross them first.
//!
//! Everything here is a pure function of a ray's bits and the domain boxes, so the
//! worker that sends a ray to a wall and the cache actor that answers it agree on the
//! wall and on the crossing point without sending either.

use glam::Vec3;

/// Faces per domain, and walls per domain.
pub const FACES: u32 = 6;

/// The wall index of `face` (0..6: -x, +x, -y, +y, -z, +z) of `domain`.
#[inline]
pub fn wall_index(domain: u32, face: u32) -> u32 {
    domain * FACES + face
}

/// The domain a wall belongs to (the one its rays enter).
#[inline]
pub fn wall_domain(wall: u32) -> u32 {
    wall / FACES
}

/// The face of a wall (0..6).
#[inline]
pub fn wall_face(wall: u32) -> u32 {
    wall % FACES
}

/// The face through which a ray `(origin, dir)` enters the box `[lo, hi]` from
/// outside: the slab entered last (the largest entry distance); on an edge or a corner
/// the lowest such axis. A ray moving in +x enters through the -x face (face 0).
/// `None` when the direction is zero.
pub fn entry_face(lo: Vec3, hi: Vec3, origin: Vec3, dir: Vec3) -> Option<u32> {
    let mut best: Option<(f32, u32)> = None;
    for a in 0..3 {
        let d = dir[a];
        if d == 0.0 || d.is_nan() {
            continue;
        }
        let (plane, face) = if d > 0.0 {
            (lo[a], 2 * a as u32)
        } else {
            (hi[a], 2 * a as u32 + 1)
        };
        let t = (plane - origin[a]) / d;
        if t.is_nan() {
            continue;
        }
        match best {
            Some((bt, _)) if t <= bt => {}
            _ => best = Some((t, face)),
        }
    }
    best.map(|(_, f)| f)
}

/// The plane and 2-D frame of one wall: where a ray crosses it, in wall coordinates.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WallFrame {
    /// The axis the wall is perpendicular to (0, 1, 2).
    pub axis: usize,
    /// The wall's plane: `p[axis] == pos`.
    pub pos: f32,
    /// The two in-plane axes, in increasing order: wall coordinates are
    /// `(p[u] - origin_u, p[v] - origin_v)`.
    pub u: usize,
    pub v: usize,
    /// The wall's lower corner in its own coordinates' axes.
    pub origin_u: f32,
    pub origin_v: f32,
    /// The wall's extent along u and v.
    pub size_u: f32,
    pub size_v: f32,
}

impl WallFrame {
    /// The frame of `face` of the box `[lo, hi]`.
    pub fn new(lo: Vec3, hi: Vec3, face: u32) -> WallFrame {
        let axis = (face / 2).min(2) as usize;
        let pos = if face.is_multiple_of(2) {
            lo[axis]
        } else {
            hi[axis]
        };
        let (u, v) = match axis {
            0 => (1, 2),
            1 => (0, 2),
            _ => (0, 1),
        };
        WallFrame {
            axis,
            pos,
            u,
            v,
            origin_u: lo[u],
            origin_v: lo[v],
            size_u: hi[u] - lo[u],
            size_v: hi[v] - lo[v],
        }
    }

    /// Where the ray `(origin, dir)` crosses the wall's plane, in wall coordinates;
    /// `None` for a ray parallel to the plane or a non-finite result.
    pub fn crossing(&self, origin: Vec3, dir: Vec3) -> Option<[f32; 2]> {
        let d = dir[self.axis];
        if d == 0.0 {
            return None;
        }
        let t = (self.pos - origin[self.axis]) / d;
        let pu = origin[self.u] + dir[self.u] * t - self.origin_u;
        let pv = origin[self.v] + dir[self.v] * t - self.origin_v;
        (pu.is_finite() && pv.is_finite()).then_some([pu, pv])
    }
}

/// Whether `face` of the domain box `[lo, hi]` lies on the scene bounds
/// `[scene_lo, scene_hi]`: an outer wall.
pub fn is_outer(scene_lo: Vec3, scene_hi: Vec3, lo: Vec3, hi: Vec3, face: u32) -> bool {
    let axis = (face / 2).min(2) as usize;
    if face.is_multiple_of(2) {
        lo[axis] <= scene_lo[axis]
    } else {
        hi[axis] >= scene_hi[axis]
    }
}

/// How a wall's probability hit map is binned: `res` x `res` texels on the wall times
/// direction bins over the hemisphere looking into the domain, `rings` bands of equal
/// cos(theta) (so of equal solid angle) times `sectors` azimuth sectors. The worker that
/// reports a probe's outcome and the actor that keeps the map bin with this one
/// function, so they agree without sending the cell with the ray.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PhmBins {
    pub res: u32,
    pub rings: u32,
    pub sectors: u32,
}

impl PhmBins {
    /// Bins for `res` texels per edge and at least `dirs` direction bins:
    /// rings = round(sqrt(dirs / 2)) (at least 1), sectors = ceil(dirs / rings); the
    /// source's 12 gives 2 rings of 6 sectors.
    pub fn new(res: u32, dirs: u32) -> PhmBins {
        let dirs = dirs.max(1);
        let rings = ((dirs as f64 / 2.0).sqrt().round() as u32).max(1);
        PhmBins {
            res: res.max(1),
            rings,
            sectors: dirs.div_ceil(rings),
        }
    }

    /// Direction bins per texel.
    pub fn dirs(&self) -> u32 {
        self.rings * self.sectors
    }

    /// Cells in one wall's map.
    pub fn cells(&self) -> u32 {
        self.res * self.res * self.dirs()
    }

    /// The cell of a ray `(origin, dir)` entering through `face` of the box `[lo, hi]`;
    /// `None` when it does not cross the face's plane or is not finite.
    pub fn cell(&self, lo: Vec3, hi: Vec3, face: u32, origin: Vec3, dir: Vec3) -> Option<u32> {
        let frame = WallFrame::new(lo, hi, face);
        let [pu, pv] = frame.crossing(origin, dir)?;
        let len = dir.length();
        if !(len > 0.0 && len.is_finite()) {
            return None;
        }
        let d = dir / len;
        let texel = |p: f32, size: f32| -> u32 {
            if size > 0.0 {
                ((p / size * self.res as f32).floor().max(0.0) as u32).min(self.res - 1)
            } else {
                0
            }
        };
        let (tu, tv) = (texel(pu, frame.size_u), texel(pv, frame.size_v));
        // Inward: a ray entering the low face moves towards +axis.
        let inward = if face.is_multiple_of(2) { 1.0 } else { -1.0 };
        let cos = (d[frame.axis] * inward).clamp(0.0, 1.0);
        let ring = (((1.0 - cos) * self.rings as f32) as u32).min(self.rings - 1);
        let phi = d[frame.v].atan2(d[frame.u]); // (-pi, pi]
        let turn = (phi + std::f32::consts::PI) / std::f32::consts::TAU;
        let sector = ((turn * self.sectors as f32) as u32).min(self.sectors - 1);
        Some(((tv * self.res + tu) * self.rings + ring) * self.sectors + sector)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn entry_faces_follow_the_direction() {
        let (lo, hi) = (Vec3::ZERO, Vec3::ONE);
        let cases = [
            (Vec3::new(-1.0, 0.5, 0.5), Vec3::X, 0),
            (Vec3::new(2.0, 0.5, 0.5), -Vec3::X, 1),
            (Vec3::new(0.5, -1.0, 0.5), Vec3::Y, 2),
            (Vec3::new(0.5, 2.0, 0.5), -Vec3::Y, 3),
            (Vec3::new(0.5, 0.5, -1.0), Vec3::Z, 4),
            (Vec3::new(0.5, 0.5, 2.0), -Vec3::Z, 5),
        ];
        for (o, d, face) in cases {
            assert_eq!(entry_face(lo, hi, o, d), Some(face), "{o} {d}");
        }
        // A slanted ray enters through the slab it reaches last.
        let o = Vec3::new(-0.1, -2.0, 0.5);
        let d = Vec3::new(0.2, 1.0, 0.0);
        assert_eq!(entry_face(lo, hi, o, d), Some(2));
        assert_eq!(entry_face(lo, hi, o, Vec3::ZERO), None);
    }

    #[test]
    fn crossings_are_in_wall_coordinates() {
        let (lo, hi) = (Vec3::new(1.0, 2.0, 3.0), Vec3::new(2.0, 4.0, 6.0));
        let f = WallFrame::new(lo, hi, 5);
        assert_eq!((f.axis, f.pos, f.u, f.v), (2, 6.0, 0, 1));
        assert_eq!((f.size_u, f.size_v), (1.0, 2.0));
        let o = Vec3::new(1.25, 3.0, 10.0);
        assert_eq!(f.crossing(o, -Vec3::Z), Some([0.25, 1.0]));
        assert_eq!(f.crossing(o, Vec3::X), None);
        assert_eq!(wall_index(7, 5), 47);
        assert_eq!((wall_domain(47), wall_face(47)), (7, 5));
        assert!(is_outer(Vec3::ZERO, Vec3::splat(6.0), lo, hi, 5));
        assert!(!is_outer(Vec3::ZERO, Vec3::splat(6.0), lo, hi, 4));
    }

    #[test]
    fn phm_cells_cover_the_map() {
        let b = PhmBins::new(4, 12);
        assert_eq!((b.rings, b.sectors, b.dirs(), b.cells()), (2, 6, 12, 192));
        assert_eq!(PhmBins::new(1, 1).cells(), 1);
        let (lo, hi) = (Vec3::ZERO, Vec3::ONE);
        let mut seen = std::collections::HashSet::new();
        // Rays into the -z face (face 4) from below, over the face and the hemisphere.
        for i in 0..40 {
            for j in 0..40 {
                for k in 0..24 {
                    let (u, v) = ((i as f32 + 0.5) / 40.0, (j as f32 + 0.5) / 40.0);
                    let a = k as f32 / 24.0 * std::f32::consts::TAU;
                    let dir = Vec3::new(a.cos() * 0.7, a.sin() * 0.7, 0.3 + (k % 3) as f32);
                    let origin = Vec3::new(u, v, 0.0) - dir;
                    let c = b.cell(lo, hi, 4, origin, dir).expect("a cell");
                    assert!(c < b.cells());
                    seen.insert(c);
                }
            }
        }
        assert_eq!(seen.len() as u32, b.cells(), "every cell is reachable");
        assert_eq!(b.cell(lo, hi, 4, Vec3::ZERO, Vec3::X), None);
    }
}

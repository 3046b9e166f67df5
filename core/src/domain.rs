//! Walking a ray through spatial domains, front to back.
//!
//! Domains are the leaves of a kd tree of axis-aligned split planes; a uniform grid is the
//! special case with regular planes. Each plane's crossing distance is computed once, by
//! one expression, and handed to both sides, so the intervals a ray spends in successive
//! domains abut exactly: (t0, t1], (t1, t2], … tile the ray's interval with no gap and no
//! overlap. With triangles assigned to every domain their (slightly expanded) box touches,
//! the first domain to report a hit inside its interval gives the same hit as one BVH over
//! the whole scene: same distance, same triangle.

use glam::Vec3;

/// The part of the ray origin's magnitude [`DomainTree::walk`] adds to the bounds'
/// margin: 16 times the rounding of a slab distance (about 2^-21 of the magnitudes).
const ORIGIN_MARGIN: f32 = 1.0 / (1u32 << 17) as f32;

/// A node of the domain tree.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum DomainNode {
    Leaf {
        domain: u32,
    },
    /// Points with `p[axis] < pos` go to `below`, others to `above`.
    Split {
        axis: u8,
        pos: f32,
        below: u32,
        above: u32,
    },
}

/// The domain layout every worker holds: scene bounds and a kd tree of split planes.
#[derive(Clone, Debug, PartialEq)]
pub struct DomainTree {
    pub lo: Vec3,
    pub hi: Vec3,
    /// Node 0 is the root.
    pub nodes: Vec<DomainNode>,
}

/// The part of a ray inside one domain: `t0 < t <= t1`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Span {
    pub domain: u32,
    pub t0: f32,
    pub t1: f32,
}

impl DomainTree {
    /// The domain of a layout of one domain (the embedded default), which holds the
    /// whole scene: every ray's span in it is its whole interval (see [`Self::walk`]).
    pub fn single(&self) -> Option<u32> {
        match self.nodes.as_slice() {
            [DomainNode::Leaf { domain }] => Some(*domain),
            _ => None,
        }
    }

    /// A uniform `dims` grid over [lo, hi]; domains are numbered x fastest, then y, then z.
    pub fn grid(lo: Vec3, hi: Vec3, dims: [u32; 3]) -> DomainTree {
        let dims = dims.map(|d| d.max(1));
        let mut t = DomainTree {
            lo,
            hi,
            nodes: Vec::new(),
        };
        let plane =
            |axis: usize, i: u32| lo[axis] + (hi[axis] - lo[axis]) * (i as f32 / dims[axis] as f32);
        // Build recursively over index ranges, splitting the axis with the most cells.
        fn build(
            t: &mut DomainTree,
            range: [(u32, u32); 3],
            dims: [u32; 3],
            plane: &dyn Fn(usize, u32) -> f32,
        ) -> u32 {
            let me = t.nodes.len() as u32;
            t.nodes.push(DomainNode::Leaf { domain: 0 });
            let widths = range.map(|(a, b)| b - a);
            let axis = (0..3).max_by_key(|&a| (widths[a], 2 - a)).unwrap_or(0);
            if widths[axis] <= 1 {
                let [x, y, z] = range.map(|(a, _)| a);
                t.nodes[me as usize] = DomainNode::Leaf {
                    domain: x + dims[0] * (y + dims[1] * z),
                };
                return me;
            }
            let mid = range[axis].0 + widths[axis] / 2;
            let mut lower = range;
            lower[axis].1 = mid;
            let mut upper = range;
            upper[axis].0 = mid;
            let below = build(t, lower, dims, plane);
            let above = build(t, upper, dims, plane);
            t.nodes[me as usize] = DomainNode::Split {
                axis: axis as u8,
                pos: plane(axis, mid),
                below,
                above,
            };
            me
        }
        build(
            &mut t,
            [(0, dims[0]), (0, dims[1]), (0, dims[2])],
            dims,
            &plane,
        );
        t
    }

    pub fn domain_count(&self) -> usize {
        self.nodes
            .iter()
            .filter(|n| matches!(n, DomainNode::Leaf { .. }))
            .count()
    }

    /// The box of every domain, indexed by domain id.
    pub fn domain_bounds(&self) -> Vec<(Vec3, Vec3)> {
        let mut out = vec![(Vec3::ZERO, Vec3::ZERO); self.domain_count()];
        let mut stack = vec![(0u32, self.lo, self.hi)];
        while let Some((n, lo, hi)) = stack.pop() {
            match self.nodes.get(n as usize) {
                Some(DomainNode::Leaf { domain }) => {
                    if let Some(o) = out.get_mut(*domain as usize) {
                        *o = (lo, hi);
                    }
                }
                Some(DomainNode::Split {
                    axis,
                    pos,
                    below,
                    above,
                }) => {
                    let a = *axis as usize;
                    let (mut bhi, mut alo) = (hi, lo);
                    bhi[a] = *pos;
                    alo[a] = *pos;
                    stack.push((*below, lo, bhi));
                    stack.push((*above, alo, hi));
                }
                None => {}
            }
        }
        out
    }

    /// The domain containing `p` (points on a plane go above it); `None` outside the bounds.
    pub fn locate(&self, p: Vec3) -> Option<u32> {
        if !(p.cmpge(self.lo).all() && p.cmple(self.hi).all()) {
            return None;
        }
        let mut n = 0u32;
        loop {
            match *self.nodes.get(n as usize)? {
                DomainNode::Leaf { domain } => return Some(domain),
                DomainNode::Split {
                    axis,
                    pos,
                    below,
                    above,
                } => {
                    n = if p[axis as usize] < pos { below } else { above };
                }
            }
        }
    }

    /// Call `visit` for each domain the ray (origin, dir) passes through within
    /// (tmin, tmax], in order along the ray, until `visit` returns false. The bounds are
    /// widened by `pad` (scene units) so rounding cannot drop the first or last domain.
    /// A layout of one domain visits it with the whole (tmin, tmax], hit or miss.
    pub fn walk(
        &self,
        origin: Vec3,
        dir: Vec3,
        tmin: f32,
        tmax: f32,
        pad: f32,
        mut visit: impl FnMut(Span) -> bool,
    ) {
        if let [DomainNode::Leaf { domain }] = self.nodes.as_slice() {
            // One domain (the embedded default) holds the whole scene: the ray's whole
            // interval is its span, as in one BVH over the scene, and no box is clipped.
            visit(Span {
                domain: *domain,
                t0: tmin,
                t1: tmax,
            });
            return;
        }
        let dir = dir + Vec3::ZERO; // fold -0.0 so signs agree with comparisons
        let inv = Vec3::ONE / dir;
        // `bound - origin` rounds to the larger magnitude of the two, so a margin relative
        // to the scene alone vanishes for a far origin: grow it with the origin's too.
        let pad = pad + origin.abs().max_element() * ORIGIN_MARGIN;
        let lo = self.lo - Vec3::splat(pad);
        let hi = self.hi + Vec3::splat(pad);
        let (mut t0, mut t1) = (tmin, tmax);
        for a in 0..3 {
            if dir[a] == 0.0 {
                if origin[a] < lo[a] || origin[a] > hi[a] {
                    return;
                }
                continue;
            }
            let (mut ta, mut tb) = ((lo[a] - origin[a]) * inv[a], (hi[a] - origin[a]) * inv[a]);
            if ta > tb {
                std::mem::swap(&mut ta, &mut tb);
            }
            t0 = t0.max(ta);
            t1 = t1.min(tb);
        }
        if t0.is_nan() || t1.is_nan() || t0 > t1 {
            return;
        }
        // The first span starts at the ray's own tmin (exclusive) when the origin is inside.
        let start = if t0 <= tmin { tmin } else { t0 };
        let mut stack = WalkStack::new();
        stack.push((0, start, t1));
        while let Some((n, a, b)) = stack.pop() {
            match self.nodes.get(n as usize) {
                None => return,
                Some(DomainNode::Leaf { domain }) => {
                    if !visit(Span {
                        domain: *domain,
                        t0: a,
                        t1: b,
                    }) {
                        return;
                    }
                }
                Some(&DomainNode::Split {
                    axis,
                    pos,
                    below,
                    above,
                }) => {
                    let ax = axis as usize;
                    let o = origin[ax];
                    // The origin's side decides near and far; on the plane, the direction does.
                    let near_is_below = if o < pos {
                        true
                    } else if o > pos {
                        false
                    } else {
                        dir[ax] < 0.0
                    };
                    let (near, far) = if near_is_below {
                        (below, above)
                    } else {
                        (above, below)
                    };
                    if dir[ax] == 0.0 || o == pos {
                        // Parallel to the plane, or leaving it: the ray never crosses it.
                        stack.push((near, a, b));
                        continue;
                    }
                    let ts = (pos - o) * inv[ax];
                    if ts.is_nan() || ts >= b || ts < 0.0 {
                        stack.push((near, a, b));
                    } else if ts <= a {
                        stack.push((far, a, b));
                    } else {
                        stack.push((far, ts, b));
                        stack.push((near, a, ts));
                    }
                }
            }
        }
    }
}

/// One domain's part of a ray and where the ray goes after it: what a worker that owns
/// `span.domain` needs to trace a ray it received, with no state carried on the ray.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hop {
    /// The ray's interval inside the domain.
    pub span: Span,
    /// The next domain on the ray that `wanted` accepts, if any; `None` means the ray
    /// leaves the scene after this domain.
    pub next: Option<u32>,
}

impl DomainTree {
    /// The first domain on the ray that `wanted` accepts (e.g. "has triangles") with its
    /// span, and the next wanted domain after it: the same [`Hop`] that
    /// [`DomainTree::hop`] gives for that domain, in one walk. Skipping empty domains
    /// changes no result: they can neither hit nor block.
    pub fn first_hop(
        &self,
        origin: Vec3,
        dir: Vec3,
        tmin: f32,
        tmax: f32,
        pad: f32,
        wanted: impl Fn(u32) -> bool,
    ) -> Option<Hop> {
        let mut found: Option<Hop> = None;
        self.walk(origin, dir, tmin, tmax, pad, |s| {
            if !wanted(s.domain) {
                return true;
            }
            match &mut found {
                None => {
                    found = Some(Hop {
                        span: s,
                        next: None,
                    });
                    true
                }
                Some(h) => {
                    h.next = Some(s.domain);
                    false
                }
            }
        });
        found
    }

    /// Where `domain` lies on the ray, and the next wanted domain after it. The walk is
    /// redone from the ray's own origin, so the span is bit for bit the one a walk over
    /// every domain gives ([`crate::trace::DomainSet`]), wherever the ray is traced.
    /// `None` when the ray does not pass through `domain`.
    #[allow(clippy::too_many_arguments)]
    pub fn hop(
        &self,
        origin: Vec3,
        dir: Vec3,
        tmin: f32,
        tmax: f32,
        pad: f32,
        domain: u32,
        wanted: impl Fn(u32) -> bool,
    ) -> Option<Hop> {
        let mut found: Option<Hop> = None;
        self.walk(origin, dir, tmin, tmax, pad, |s| match &mut found {
            None => {
                if s.domain == domain {
                    found = Some(Hop {
                        span: s,
                        next: None,
                    });
                }
                true
            }
            Some(h) => {
                if wanted(s.domain) {
                    h.next = Some(s.domain);
                    false
                } else {
                    true
                }
            }
        });
        found
    }
}

/// The walk's stack of (node, t0, t1): on the call stack while it is as deep as any
/// balanced tree of 2^32 domains gets, on the heap only beyond. A walk runs once or twice
/// for every ray a worker traces, so it must not allocate.
struct WalkStack {
    inline: [(u32, f32, f32); 34],
    len: usize,
    spill: Vec<(u32, f32, f32)>,
}

impl WalkStack {
    fn new() -> WalkStack {
        WalkStack {
            inline: [(0, 0.0, 0.0); 34],
            len: 0,
            spill: Vec::new(),
        }
    }

    #[inline]
    fn push(&mut self, e: (u32, f32, f32)) {
        if self.len < self.inline.len() {
            self.inline[self.len] = e;
            self.len += 1;
        } else {
            self.spill.push(e);
        }
    }

    #[inline]
    fn pop(&mut self) -> Option<(u32, f32, f32)> {
        if let Some(e) = self.spill.pop() {
            return Some(e);
        }
        if self.len == 0 {
            return None;
        }
        self.len -= 1;
        Some(self.inline[self.len])
    }
}

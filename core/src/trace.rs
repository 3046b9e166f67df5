//! What the integrator's steps need from geometry: the closest accepted hit and whether
//! anything accepted blocks a ray. One BVH over the whole scene answers both; so does a
//! set of domains, each with its own BVH, walked front to back — with the same answers.

use crate::bvh::{Accel, Hit, QueryRay};
use crate::domain::DomainTree;
use crate::intersect::TriangleHit;

pub trait Trace: Sync {
    /// Closest hit in (tmin, tmax] that `accept` agrees to; ties go to the lower triangle id.
    fn closest(
        &self,
        ray: &QueryRay,
        accept: &mut dyn FnMut(u32, &TriangleHit) -> bool,
    ) -> Option<Hit>;
    /// Whether any hit in (tmin, tmax) is accepted.
    fn occluded(&self, ray: &QueryRay, accept: &mut dyn FnMut(u32, &TriangleHit) -> bool) -> bool;
}

impl Trace for Accel {
    fn closest(
        &self,
        ray: &QueryRay,
        accept: &mut dyn FnMut(u32, &TriangleHit) -> bool,
    ) -> Option<Hit> {
        Accel::closest(self, ray, accept)
    }
    fn occluded(&self, ray: &QueryRay, accept: &mut dyn FnMut(u32, &TriangleHit) -> bool) -> bool {
        Accel::occluded(self, ray, accept)
    }
}

/// Domains held in one process: the layout and one BVH per domain, built with scene-wide
/// triangle ids. The embedded mode's stand-in for workers owning domains.
pub struct DomainSet {
    pub tree: DomainTree,
    /// Indexed by domain id.
    pub accels: Vec<Accel>,
    /// How far the layout's outer bounds are widened when walking (scene units); the same
    /// margin the partitioner used when assigning triangles to domains.
    pub pad: f32,
}

impl Trace for DomainSet {
    fn closest(
        &self,
        ray: &QueryRay,
        accept: &mut dyn FnMut(u32, &TriangleHit) -> bool,
    ) -> Option<Hit> {
        let mut found = None;
        self.tree
            .walk(ray.origin, ray.dir, ray.tmin, ray.tmax, self.pad, |span| {
                if let Some(a) = self.accels.get(span.domain as usize) {
                    let sub = QueryRay {
                        tmin: span.t0,
                        tmax: span.t1,
                        ..*ray
                    };
                    found = a.closest(&sub, &mut *accept);
                }
                found.is_none()
            });
        found
    }

    fn occluded(&self, ray: &QueryRay, accept: &mut dyn FnMut(u32, &TriangleHit) -> bool) -> bool {
        let mut blocked = false;
        self.tree
            .walk(ray.origin, ray.dir, ray.tmin, ray.tmax, self.pad, |span| {
                if let Some(a) = self.accels.get(span.domain as usize) {
                    // Occlusion tests are open at both ends, but a hit exactly on a wall
                    // between two spans must still count: close every span but the last.
                    let tmax = if span.t1 < ray.tmax && span.t1.is_finite() && span.t1 >= 0.0 {
                        f32::from_bits(span.t1.to_bits() + 1)
                    } else {
                        span.t1
                    };
                    let sub = QueryRay {
                        tmin: span.t0,
                        tmax,
                        ..*ray
                    };
                    blocked = a.occluded(&sub, &mut *accept);
                }
                !blocked
            });
        blocked
    }
}

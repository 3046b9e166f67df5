//! What the integrator's steps need from geometry: the closest accepted hit and whether
//! anything accepted blocks a ray. One BVH over the whole scene answers both; so does a
//! set of domains, each with its own BVH, walked front to back — with the same answers.

use crate::bvh::{Accel, Hit, QueryRay};
use crate::domain::{DomainTree, Span};
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
                    found = closest_in_span(a, ray, &span, &mut *accept);
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
                    blocked = occluded_in_span(a, ray, &span, &mut *accept);
                }
                !blocked
            });
        blocked
    }
}

/// The closest accepted hit of `ray` inside one domain's span: the one test both the
/// embedded [`DomainSet`] and a worker owning the domain run, so they agree bit for bit.
#[inline]
pub fn closest_in_span(
    accel: &Accel,
    ray: &QueryRay,
    span: &Span,
    accept: &mut dyn FnMut(u32, &TriangleHit) -> bool,
) -> Option<Hit> {
    let sub = QueryRay {
        tmin: span.t0,
        tmax: span.t1,
        ..*ray
    };
    accel.closest(&sub, accept)
}

/// Whether anything accepted blocks `ray` inside one domain's span. Occlusion tests are
/// open at both ends, but a hit exactly on a wall between two spans must still count, so
/// every span but the ray's last is closed by one ulp.
#[inline]
pub fn occluded_in_span(
    accel: &Accel,
    ray: &QueryRay,
    span: &Span,
    accept: &mut dyn FnMut(u32, &TriangleHit) -> bool,
) -> bool {
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
    accel.occluded(&sub, accept)
}

/// One domain's BVH limited to the ray's span inside that domain: what a worker owning
/// the domain traces a ray against. It answers exactly as [`DomainSet`] does for that
/// span, because both call [`closest_in_span`] and [`occluded_in_span`].
pub struct SpanTrace<'a> {
    pub accel: &'a Accel,
    pub span: Span,
}

impl Trace for SpanTrace<'_> {
    #[inline]
    fn closest(
        &self,
        ray: &QueryRay,
        accept: &mut dyn FnMut(u32, &TriangleHit) -> bool,
    ) -> Option<Hit> {
        closest_in_span(self.accel, ray, &self.span, accept)
    }

    #[inline]
    fn occluded(&self, ray: &QueryRay, accept: &mut dyn FnMut(u32, &TriangleHit) -> bool) -> bool {
        occluded_in_span(self.accel, ray, &self.span, accept)
    }
}

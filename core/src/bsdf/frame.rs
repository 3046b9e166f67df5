//! The local shading frame for one `wo`: which side of the surface `wo` is on, the
//! shading normal on that side (or the geometric one when `wo` is below it), the tangent
//! an anisotropic lobe is stretched along, and the relative refraction index.

use glam::Vec3;

use super::{Bsdf, COS_EPS, unit};

/// Local shading frame for one `wo`: `n` is the shading normal on `wo`'s side.
#[derive(Clone, Copy, Debug)]
pub(super) struct Frame {
    pub(super) t: Vec3,
    pub(super) b: Vec3,
    pub(super) n: Vec3,
    /// Geometric normal on `wo`'s side.
    pub(super) ng: Vec3,
    /// `eta(wi side) / eta(wo side)` for refraction.
    pub(super) etap: f32,
    /// `wo` is on the side `ng` (as passed) points to: the outside of a transmissive
    /// object, where its clear coat is.
    pub(super) outside: bool,
}

impl Frame {
    pub(super) fn local(&self, v: Vec3) -> Vec3 {
        Vec3::new(v.dot(self.t), v.dot(self.b), v.dot(self.n))
    }

    pub(super) fn world(&self, v: Vec3) -> Vec3 {
        self.t * v.x + self.b * v.y + self.n * v.z
    }
}

impl Bsdf {
    /// The local frame for `wo`, or `None` when `wo` is degenerate or tangent to the surface.
    pub(super) fn frame(&self, wo: Vec3) -> Option<(Frame, Vec3)> {
        if !self.valid {
            return None;
        }
        let wo = unit(wo)?;
        let cg = wo.dot(self.ng);
        if !(cg.abs() >= COS_EPS) {
            return None;
        }
        let outside = cg > 0.0;
        let (ng, mut n) = if outside {
            (self.ng, self.n)
        } else {
            (-self.ng, -self.n)
        };
        if wo.dot(n) < COS_EPS {
            // wo below the shading hemisphere: fall back to the geometric normal.
            n = ng;
        }
        // An anisotropic lobe is stretched along its direction: the frame follows it.
        // (Isotropic lobes skip the projection: a square root and a division per hit.)
        let along = if self.ggx.aniso {
            unit(self.ggx.aniso_t - n * n.dot(self.ggx.aniso_t))
        } else {
            None
        };
        let (t, b) = match along {
            Some(t) => (t, n.cross(t)),
            None => n.any_orthonormal_pair(),
        };
        let etap = if outside {
            self.transmission.eta
        } else {
            1.0 / self.transmission.eta
        };
        let fr = Frame {
            t,
            b,
            n,
            ng,
            etap,
            outside,
        };
        let wo_l = fr.local(wo);
        if !(wo_l.z >= COS_EPS) {
            return None;
        }
        Some((fr, wo_l))
    }
}

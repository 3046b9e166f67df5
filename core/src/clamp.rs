//! `--clamp-indirect`: a radiance clamp on light that reached the eye by more than one
//! surface (Cycles' "Clamp Indirect", pbrt-v4's `maxcomponentvalue` limited to indirect
//! light). Fireflies are rare paths of huge weight (a diffuse bounce that finds a small
//! bright light through glass, a caustic); clamping each such contribution trades a
//! little energy (the image gets darker where those paths carry light) for much less
//! variance. Direct light (emitters seen by the camera, light at the first hit) is never
//! clamped, so a lit scene keeps its look.
//!
//! The integrators are non-recursive: a sample's radiance arrives as many separate
//! contributions, one per light-carrying event (an emitter hit, an unblocked shadow ray, a
//! miss into the sky). The clamp applies to each of them alone, so it is a pure function
//! of the ray that carries it and the image keeps the same bits wherever the ray is
//! traced.

use glam::Vec3;

/// Scale `value` so that its largest component is at most `limit` (hue kept, as pbrt-v4
/// does), when the light it carries was reflected by `bounces` >= 2 surfaces on its way
/// to the eye (light reflected by one surface is direct light at the first hit).
/// Returns the value to add and whether it was clamped. Never raises a component: the
/// factor is at most 1.
#[inline]
pub fn clamp_indirect(limit: Option<f32>, bounces: u32, value: Vec3) -> (Vec3, bool) {
    match limit {
        Some(limit) if bounces >= 2 => {
            let m = value.max_element();
            // A non-finite value goes on to be counted and dropped by the film, not
            // turned into a finite one here (`m > limit` is false for NaN).
            if m > limit && m.is_finite() {
                (value * (limit / m), true)
            } else {
                (value, false)
            }
        }
        _ => (value, false),
    }
}

/// Whether `limit` is a clamp a job accepts (finite and above zero), or why not.
pub fn check_limit(limit: f32) -> Result<f32, String> {
    if limit.is_finite() && limit > 0.0 {
        Ok(limit)
    } else {
        Err(format!("must be a finite number above 0, got {limit}"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_indirect_light_above_the_limit_is_scaled() {
        let v = Vec3::new(8.0, 4.0, 0.0);
        assert_eq!(clamp_indirect(None, 5, v), (v, false));
        assert_eq!(clamp_indirect(Some(2.0), 1, v), (v, false));
        assert_eq!(clamp_indirect(Some(2.0), 0, v), (v, false));
        assert_eq!(clamp_indirect(Some(10.0), 2, v), (v, false));
        assert_eq!(
            clamp_indirect(Some(2.0), 2, v),
            (Vec3::new(2.0, 1.0, 0.0), true)
        );
        let (nan, clamped) = clamp_indirect(Some(2.0), 3, Vec3::NAN);
        assert!(nan.is_nan() && !clamped);
        let inf = Vec3::new(f32::INFINITY, 1.0, 0.0);
        assert_eq!(clamp_indirect(Some(2.0), 3, inf), (inf, false));
    }

    #[test]
    fn limits() {
        assert_eq!(check_limit(4.0), Ok(4.0));
        for bad in [0.0, -1.0, f32::NAN, f32::INFINITY] {
            let e = check_limit(bad).expect_err("bad");
            assert!(e.contains("finite number above 0"), "{e}");
        }
    }
}

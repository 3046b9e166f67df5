//! Moving a loaded scene (`dray render --translate`, `JobSpec.translate`) within the
//! coordinates an imported scene may have.
//!
//! Files are checked at import: no coordinate beyond ±[`MAX_COORDINATE`]. A translation
//! applied afterwards could undo that (`--translate 1e25,0,0` moved the Cornell box to
//! where the BVH's boxes have infinite areas), so the moved scene is held to the same
//! bound, and an offset that breaks it is refused before anything moves.

use dray_core::light::Light;
use dray_core::scene::Scene;
use glam::Vec3;

use crate::validate::MAX_COORDINATE;

/// Why a scene cannot be moved by an offset.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TranslateError {
    /// The offset itself is NaN or infinite.
    #[error("the offset ({}, {}, {}) is not finite", .offset.x, .offset.y, .offset.z)]
    NotFinite { offset: Vec3 },
    /// A vertex or light would land beyond the bound.
    #[error(
        "moves {what} to ({:e}, {:e}, {:e}), beyond ±{MAX_COORDINATE:e}, the largest coordinate \
         dray accepts (larger ones overflow f32 in areas and distances)",
        .to.x, .to.y, .to.z
    )]
    OutOfRange { what: String, to: Vec3 },
}

/// Where `p` lands, if within the bound.
fn moved(p: Vec3, offset: Vec3) -> Option<Vec3> {
    let to = p + offset;
    (to.is_finite() && to.abs().max_element() <= MAX_COORDINATE).then_some(to)
}

/// Move `scene` by `offset` (vertices, point and spot lights, cameras), unless a vertex
/// or a light would land beyond ±[`MAX_COORDINATE`]: then the scene is left as it was
/// and the error names the first one.
pub fn translate(scene: &mut Scene, offset: Vec3) -> Result<(), TranslateError> {
    if !offset.is_finite() {
        return Err(TranslateError::NotFinite { offset });
    }
    let out = |what: String, p: Vec3| TranslateError::OutOfRange {
        what,
        to: p + offset,
    };
    if let Some((i, &p)) = scene
        .mesh
        .positions
        .iter()
        .enumerate()
        .find(|(_, p)| moved(**p, offset).is_none())
    {
        return Err(out(format!("vertex {i}"), p));
    }
    for (i, l) in scene.lights.iter().enumerate() {
        if let Light::Point { position, .. } | Light::Spot { position, .. } = l
            && moved(*position, offset).is_none()
        {
            return Err(out(format!("light {i}"), *position));
        }
    }
    scene.translate(offset);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn offsets_that_leave_the_bound_are_refused_and_move_nothing() {
        let mut scene = crate::load("cornell").unwrap();
        let before = scene.mesh.positions.clone();
        for offset in [
            Vec3::new(1e25, 0.0, 0.0),
            Vec3::new(0.0, 1e22, 0.0),
            Vec3::new(0.0, 0.0, -3e38),
            Vec3::new(2e18, 0.0, 0.0),
        ] {
            let e = translate(&mut scene, offset).unwrap_err();
            assert!(matches!(e, TranslateError::OutOfRange { .. }), "{e}");
            assert!(e.to_string().contains("beyond ±1e18"), "{e}");
            assert_eq!(scene.mesh.positions, before);
        }
        let e = translate(&mut scene, Vec3::new(f32::NAN, 0.0, 0.0)).unwrap_err();
        assert!(e.to_string().contains("not finite"), "{e}");
        translate(&mut scene, Vec3::new(1e17, 0.0, 0.0)).unwrap();
        assert_eq!(
            scene.mesh.positions[0],
            before[0] + Vec3::new(1e17, 0.0, 0.0)
        );
    }
}

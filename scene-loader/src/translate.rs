//! Moving a loaded scene (`dray render --translate`, `JobSpec.translate`) within the
//! coordinates an imported scene may have.
//!
//! Files are checked at import: no coordinate beyond ±[`MAX_COORDINATE`]. A translation
//! applied afterwards could undo that (`--translate 1e25,0,0` moved the Cornell box to
//! where the BVH's boxes have infinite areas), so the moved scene is held to the same
//! bound, and an offset that breaks it is refused before anything moves.
//!
//! Far from the origin f32 coordinates are coarse (steps of 1/16 at 1e6), and a small
//! triangle's corners can round onto one line or point. Such a triangle can never be
//! hit (the watertight test rejects zero area), so it is dropped and counted with the
//! loaders' degenerate triangles, as if the file had held it so, instead of filling the
//! BVH with boxes that every ray near it must open (docs/numerics.md "Far from the
//! origin").

use dray_core::light::Light;
use dray_core::scene::Scene;
use glam::Vec3;

use crate::validate::{MAX_COORDINATE, is_degenerate};

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
    /// Every triangle rounds to zero area where the offset puts it.
    #[error("moves the scene so far that every one of its triangles rounds to zero area")]
    Collapsed,
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
    let keep: Vec<bool> = (0..scene.mesh.indices.len())
        .map(|t| {
            let corners = scene.mesh.corners(t).map(|p| p + offset);
            !is_degenerate(scene.mesh.indices[t], corners)
        })
        .collect();
    if !scene.mesh.indices.is_empty() && !keep.contains(&true) {
        return Err(TranslateError::Collapsed);
    }
    scene.translate(offset);
    let mut flags = keep.iter();
    scene
        .mesh
        .indices
        .retain(|_| flags.next().copied().unwrap_or(true));
    let mut flags = keep.iter();
    scene
        .mesh
        .material
        .retain(|_| flags.next().copied().unwrap_or(true));
    scene.stats.degenerate_triangles += keep.iter().filter(|k| !**k).count() as u64;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn triangles_that_round_to_zero_area_are_dropped_and_counted() {
        let mut scene = crate::load("spheres:30").unwrap();
        let triangles = scene.mesh.indices.len();
        let before = scene.stats.degenerate_triangles;
        translate(&mut scene, Vec3::splat(1.0e6)).unwrap();
        let dropped = scene.stats.degenerate_triangles - before;
        assert!(dropped > 0, "some triangles collapse at 1e6");
        assert_eq!(scene.mesh.indices.len() as u64 + dropped, triangles as u64);
        assert_eq!(scene.mesh.material.len(), scene.mesh.indices.len());
        for t in 0..scene.mesh.indices.len() {
            assert!(!is_degenerate(scene.mesh.indices[t], scene.mesh.corners(t)));
        }
        // Near the origin nothing collapses.
        let mut near = crate::load("spheres:30").unwrap();
        translate(&mut near, Vec3::splat(10.0)).unwrap();
        assert_eq!(near.mesh.indices.len(), triangles);
    }

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

//! The boxes a job's cache hosts need to find walls and crossing points: the scene
//! bounds and every domain's box, as OpenWalls carries them (six floats each: min x, y,
//! z, then max x, y, z).
//!
//! Taken from the package's [`DomainTree`](dray_core::domain::DomainTree), the structure
//! the workers walk rays with, so the coordinator, the workers and the cache hosts agree
//! on every wall to the bit.

use dray_scene::partition::DomainLayout;

/// Scene and domain boxes of one job, in OpenWalls' layout.
#[derive(Clone, Debug, PartialEq)]
pub struct WallGeometry {
    /// Min x, y, z, max x, y, z of the scene bounds.
    pub scene_bounds: [f32; 6],
    /// Six floats per domain, by domain index.
    pub domain_bounds: Vec<f32>,
}

impl WallGeometry {
    /// The boxes of `layout`, as the workers see them.
    pub fn of(layout: &DomainLayout) -> WallGeometry {
        let tree = layout.to_domain_tree();
        let b = layout.scene_bounds();
        let domain_bounds = tree
            .domain_bounds()
            .into_iter()
            .flat_map(|(lo, hi)| [lo.x, lo.y, lo.z, hi.x, hi.y, hi.z])
            .collect();
        WallGeometry {
            scene_bounds: [b.min.x, b.min.y, b.min.z, b.max.x, b.max.y, b.max.z],
            domain_bounds,
        }
    }

    /// Domains described.
    pub fn domains(&self) -> u32 {
        (self.domain_bounds.len() / 6) as u32
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use dray_scene::partition::{Aabb, LayoutSpec};
    use glam::Vec3;

    #[test]
    fn boxes_of_a_grid() {
        let bounds = Aabb {
            min: Vec3::ZERO,
            max: Vec3::new(2.0, 1.0, 1.0),
        };
        let layout =
            DomainLayout::build(bounds, &LayoutSpec::Grid([2, 1, 1]), &mut []).expect("layout");
        let g = WallGeometry::of(&layout);
        assert_eq!(g.scene_bounds, [0.0, 0.0, 0.0, 2.0, 1.0, 1.0]);
        assert_eq!(g.domains(), 2);
        let mut boxes: Vec<&[f32]> = g.domain_bounds.chunks(6).collect();
        boxes.sort_by(|a, b| a[0].total_cmp(&b[0]));
        assert_eq!(boxes[0], [0.0, 0.0, 0.0, 1.0, 1.0, 1.0]);
        assert_eq!(boxes[1], [1.0, 0.0, 0.0, 2.0, 1.0, 1.0]);
    }
}

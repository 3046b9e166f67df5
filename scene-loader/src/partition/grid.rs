//! The uniform grid layout: `X x Y x Z` equal cells over the scene bounds.
//!
//! The layout of Little's ray-cache thesis: regular walls make wall caches easy to
//! address, at the price of unbalanced domains where geometry clusters. Domain `d` is the
//! cell `(x, y, z)` with `d = x + X * (y + Y * z)`.
//!
//! Wall coordinates are computed once and stored; cell boxes, point location and overlap
//! queries all read the stored walls, so they agree exactly. Interior walls use the very
//! expression of [`dray_core::domain::DomainTree::grid`], so a worker that builds its ray
//! walker from the bounds and cell counts gets the same planes, bit for bit, as
//! [`Grid::tree_nodes`] gives from the stored walls.

use dray_core::domain::DomainNode;
use glam::Vec3;

use super::layout::Aabb;

#[derive(Clone, Debug, PartialEq)]
pub struct Grid {
    /// Cells per axis.
    pub dims: [u32; 3],
    /// Per axis, `dims[a] + 1` non-decreasing wall coordinates from the bounds' min to
    /// their max (both exact).
    pub walls: [Vec<f32>; 3],
}

impl Grid {
    /// The grid of `dims` cells over `bounds`.
    pub fn new(bounds: &Aabb, dims: [u32; 3]) -> Grid {
        let walls = std::array::from_fn(|a| {
            let (lo, hi, n) = (bounds.min[a], bounds.max[a], dims[a]);
            let mut w: Vec<f32> = (0..=n)
                .map(|i| {
                    if i == 0 {
                        lo
                    } else if i == n {
                        hi
                    } else {
                        // Keep in step with dray_core::domain::DomainTree::grid.
                        lo + (hi - lo) * (i as f32 / n as f32)
                    }
                })
                .collect();
            // Rounding is monotone, so ascending order never needs fixing, and only
            // rounding right next to `hi` could step past it; clamping makes both
            // invariants local instead of an argument about rounding.
            for i in 1..w.len() {
                w[i] = w[i].max(w[i - 1]).min(hi);
            }
            w
        });
        Grid { dims, walls }
    }

    /// Cell counts for a grid of exactly `n` cells whose cells are as close to cubes as
    /// the scene's proportions allow. Flat axes (extent below 1e-6 of the largest) are
    /// never split; among the factorisations of `n` the one with the smallest ratio of
    /// longest to shortest cell side wins (ties: the most cells along X, then Y).
    pub fn dims_for_count(n: u32, extent: Vec3) -> [u32; 3] {
        let n = n.max(1);
        let largest = extent.max_element().max(f32::MIN_POSITIVE) as f64;
        let flat = extent.to_array().map(|e| (e as f64) <= largest * 1e-6);
        let mut best = ([n, 1, 1], f64::INFINITY);
        for x in (1..=n).rev().filter(|x| n.is_multiple_of(*x)) {
            let rest = n / x;
            for y in (1..=rest).rev().filter(|y| rest.is_multiple_of(*y)) {
                let dims = [x, y, rest / y];
                if (0..3).any(|a| flat[a] && dims[a] > 1) {
                    continue;
                }
                let sides: Vec<f64> = (0..3)
                    .filter(|&a| !flat[a])
                    .map(|a| extent[a] as f64 / dims[a] as f64)
                    .collect();
                let hi = sides.iter().cloned().fold(0.0, f64::max);
                let lo = sides.iter().cloned().fold(f64::INFINITY, f64::min);
                let cost = hi / lo;
                if cost < best.1 {
                    best = (dims, cost);
                }
            }
        }
        best.0
    }

    pub fn domain_count(&self) -> u32 {
        self.dims.iter().product()
    }

    /// The domain index of cell `c`.
    pub fn index(&self, c: [u32; 3]) -> u32 {
        c[0] + self.dims[0] * (c[1] + self.dims[1] * c[2])
    }

    /// The cell of domain `d`.
    pub fn cell(&self, d: u32) -> [u32; 3] {
        let [x, y, _] = self.dims;
        [d % x, (d / x) % y, d / (x * y)]
    }

    /// Every cell box, in domain order.
    pub fn boxes(&self) -> Vec<Aabb> {
        (0..self.domain_count())
            .map(|d| {
                let c = self.cell(d);
                let lo = std::array::from_fn(|a| self.walls[a][c[a] as usize]);
                let hi = std::array::from_fn(|a| self.walls[a][c[a] as usize + 1]);
                Aabb::new(Vec3::from_array(lo), Vec3::from_array(hi))
            })
            .collect()
    }

    /// The cell holding `p`, which must lie in the bounds: per axis, the number of
    /// interior walls at or below `p`, so a point on a wall goes to the cell above it.
    pub fn locate(&self, p: Vec3) -> u32 {
        let c = std::array::from_fn(|a| {
            let w = &self.walls[a];
            w[1..w.len() - 1].partition_point(|&x| x <= p[a]) as u32
        });
        self.index(c)
    }

    /// Append (ascending) the cells whose box grown by `eps` overlaps `query`.
    pub fn overlapping(&self, query: &Aabb, eps: f32, out: &mut Vec<u32>) {
        let mut range = [(0u32, 0u32); 3];
        for (a, r) in range.iter_mut().enumerate() {
            let w = &self.walls[a];
            let n = w.len() - 1;
            // Cell i spans [w[i] - eps, w[i+1] + eps]; both ends are non-decreasing in i.
            let first = w[1..].partition_point(|&x| x + eps < query.min[a]);
            let end = w[..n].partition_point(|&x| x - eps <= query.max[a]);
            if first >= end {
                return;
            }
            *r = (first as u32, end as u32);
        }
        for z in range[2].0..range[2].1 {
            for y in range[1].0..range[1].1 {
                for x in range[0].0..range[0].1 {
                    out.push(self.index([x, y, z]));
                }
            }
        }
    }

    /// The grid as a kd tree of split planes (the form dray-core's ray walker takes):
    /// each node splits the axis with the most cells (ties: X, then Y) at its middle
    /// wall, the structure [`dray_core::domain::DomainTree::grid`] builds.
    pub fn tree_nodes(&self) -> Vec<DomainNode> {
        let mut nodes = Vec::new();
        self.build_tree(&mut nodes, self.dims.map(|n| (0, n)));
        nodes
    }

    fn build_tree(&self, nodes: &mut Vec<DomainNode>, range: [(u32, u32); 3]) -> u32 {
        let me = nodes.len() as u32;
        nodes.push(DomainNode::Leaf { domain: 0 });
        let widths = range.map(|(a, b)| b - a);
        let axis = (0..3).max_by_key(|&a| (widths[a], 2 - a)).unwrap_or(0);
        if widths[axis] <= 1 {
            nodes[me as usize] = DomainNode::Leaf {
                domain: self.index(range.map(|(a, _)| a)),
            };
            return me;
        }
        let mid = range[axis].0 + widths[axis] / 2;
        let (mut lower, mut upper) = (range, range);
        lower[axis].1 = mid;
        upper[axis].0 = mid;
        let below = self.build_tree(nodes, lower);
        let above = self.build_tree(nodes, upper);
        nodes[me as usize] = DomainNode::Split {
            axis: axis as u8,
            pos: self.walls[axis][mid as usize],
            below,
            above,
        };
        me
    }

    /// Check a grid read from a manifest: sizes, finiteness, order and end walls.
    pub fn validate(&self, bounds: &Aabb) -> Result<(), String> {
        let count: u64 = self.dims.iter().map(|&d| d as u64).product();
        if self.dims.contains(&0) || count > super::layout::MAX_DOMAINS as u64 {
            return Err(format!(
                "grid {}x{}x{} is out of range",
                self.dims[0], self.dims[1], self.dims[2]
            ));
        }
        for a in 0..3 {
            let w = &self.walls[a];
            if w.len() != self.dims[a] as usize + 1 {
                return Err(format!(
                    "axis {a} has {} walls, expected {}",
                    w.len(),
                    self.dims[a] + 1
                ));
            }
            if w[0] != bounds.min[a] || w[w.len() - 1] != bounds.max[a] {
                return Err(format!("axis {a}: the end walls are not the bounds"));
            }
            if w.iter().any(|x| !x.is_finite()) || w.windows(2).any(|p| p[0] > p[1]) {
                return Err(format!("axis {a}: walls are not finite and ascending"));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dims_for_count_prefers_cubes_and_skips_flat_axes() {
        assert_eq!(Grid::dims_for_count(8, Vec3::ONE), [2, 2, 2]);
        assert_eq!(Grid::dims_for_count(8, Vec3::new(8.0, 1.0, 1.0)), [8, 1, 1]);
        assert_eq!(Grid::dims_for_count(4, Vec3::new(1.0, 0.0, 1.0)), [2, 1, 2]);
        assert_eq!(Grid::dims_for_count(7, Vec3::ONE), [7, 1, 1]);
        let d = Grid::dims_for_count(12, Vec3::new(4.0, 3.0, 1.0));
        assert_eq!(d.iter().product::<u32>(), 12);
    }

    #[test]
    fn same_planes_as_the_core_walker() {
        use dray_core::domain::DomainTree;
        let b = Aabb::new(Vec3::new(-0.1, 0.3, 1.0e-3), Vec3::new(0.7, 1.1, 3.3));
        for dims in [[3, 5, 7], [1, 1, 1], [4, 1, 2], [16, 16, 3]] {
            let g = Grid::new(&b, dims);
            let core = DomainTree::grid(b.min, b.max, dims);
            assert_eq!(g.tree_nodes(), core.nodes, "{dims:?}");
        }
    }

    #[test]
    fn locate_on_walls_goes_up() {
        let g = Grid::new(&Aabb::new(Vec3::ZERO, Vec3::splat(4.0)), [4, 2, 1]);
        assert_eq!(g.locate(Vec3::new(1.0, 0.0, 0.0)), 1);
        assert_eq!(g.locate(Vec3::new(0.999, 0.0, 0.0)), 0);
        assert_eq!(g.locate(Vec3::new(4.0, 4.0, 4.0)), g.index([3, 1, 0]));
        assert_eq!(g.locate(Vec3::new(0.0, 2.0, 0.0)), g.index([0, 1, 0]));
    }

    #[test]
    fn overlapping_includes_wall_neighbours() {
        let g = Grid::new(&Aabb::new(Vec3::ZERO, Vec3::splat(4.0)), [4, 1, 1]);
        let mut out = Vec::new();
        let q = Aabb::new(Vec3::new(1.0, 1.0, 1.0), Vec3::new(1.0, 1.0, 1.0));
        g.overlapping(&q, 1e-5, &mut out);
        assert_eq!(out, vec![0, 1]);
        out.clear();
        let q = Aabb::new(Vec3::new(1.5, 1.0, 1.0), Vec3::new(3.5, 1.0, 1.0));
        g.overlapping(&q, 1e-5, &mut out);
        assert_eq!(out, vec![1, 2, 3]);
        out.clear();
        let q = Aabb::new(Vec3::new(5.0, 1.0, 1.0), Vec3::new(6.0, 1.0, 1.0));
        g.overlapping(&q, 1e-5, &mut out);
        assert!(out.is_empty());
    }
}

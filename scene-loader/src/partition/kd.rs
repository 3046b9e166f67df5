//! The kd layout: the bounds split recursively so every domain holds about the same
//! number of triangles.
//!
//! A node that must become `n` domains splits its longest axis so the left side gets
//! `floor(n/2)` domains and the right side the rest, at the matching quantile of the
//! triangle centroids inside it (the median when `n` is even). `n` need not be a power of
//! two: counts stay proportional to domains at every level. If the quantile falls on the
//! node's boundary along that axis (every centroid in one plane), the next-longest axis is
//! tried, and failing all, the longest axis is cut in the middle.
//!
//! Centroids come from a sample (see [`super::survey`]): all of them for scenes up to the
//! sample size, a uniform reservoir sample beyond, which keeps memory bounded and still
//! places quantiles within a fraction of a percent.
//!
//! The tree is stored in pre-order (children after their parent, leaves numbered left to
//! right), which makes a stored tree easy to check for shape: see [`KdTree::boxes`].

use glam::Vec3;

use super::layout::Aabb;

/// The deepest tree accepted. Built trees are at most 17 deep (each split halves the
/// domain count, and there are at most 65536); the bound lets traversal use a fixed stack.
pub const MAX_DEPTH: usize = 64;

#[derive(Clone, Copy, Debug, PartialEq)]
pub enum KdNode {
    /// A point goes left when `p[axis] < pos`; the left child's box ends at `pos` and the
    /// right child's starts there.
    Split {
        axis: u8,
        pos: f32,
        left: u32,
        right: u32,
    },
    Leaf {
        domain: u32,
    },
}

#[derive(Clone, Debug, PartialEq)]
pub struct KdTree {
    /// Node 0 is the root.
    pub nodes: Vec<KdNode>,
}

impl KdTree {
    /// Split `bounds` into `n >= 1` domains balanced over `centroids` (reordered).
    pub fn build(bounds: &Aabb, centroids: &mut [Vec3], n: u32) -> KdTree {
        let mut tree = KdTree { nodes: Vec::new() };
        let mut next_domain = 0;
        tree.build_node(bounds, centroids, n.max(1), &mut next_domain);
        tree
    }

    fn build_node(&mut self, node_box: &Aabb, samples: &mut [Vec3], n: u32, next: &mut u32) -> u32 {
        let index = self.nodes.len() as u32;
        if n == 1 {
            self.nodes.push(KdNode::Leaf { domain: *next });
            *next += 1;
            return index;
        }
        let k = n / 2;
        let (axis, pos) = choose_split(node_box, samples, k, n);
        // Same rule as `locate`: strictly below the plane goes left.
        let mut mid = 0;
        for i in 0..samples.len() {
            if samples[i][axis] < pos {
                samples.swap(i, mid);
                mid += 1;
            }
        }
        let (left_samples, right_samples) = samples.split_at_mut(mid);
        let (mut left_box, mut right_box) = (*node_box, *node_box);
        left_box.max[axis] = pos;
        right_box.min[axis] = pos;
        self.nodes.push(KdNode::Leaf { domain: u32::MAX }); // placeholder
        let left = self.build_node(&left_box, left_samples, k, next);
        let right = self.build_node(&right_box, right_samples, n - k, next);
        self.nodes[index as usize] = KdNode::Split {
            axis: axis as u8,
            pos,
            left,
            right,
        };
        index
    }

    /// The leaf holding `p` (which must lie in the bounds).
    pub fn locate(&self, p: Vec3) -> u32 {
        let mut i = 0;
        loop {
            match self.nodes[i] {
                KdNode::Leaf { domain } => return domain,
                KdNode::Split {
                    axis,
                    pos,
                    left,
                    right,
                } => i = if p[axis as usize] < pos { left } else { right } as usize,
            }
        }
    }

    /// Append (ascending) the leaves whose box grown by `eps` overlaps `query`.
    pub fn overlapping(&self, query: &Aabb, eps: f32, out: &mut Vec<u32>) {
        // A leaf's grown box is the intersection of its ancestors' half-spaces, each moved
        // out by eps, so testing each split against its moved plane is exact. Depth-first
        // with at most one pending sibling per level: a fixed stack (checked trees are at
        // most MAX_DEPTH deep) keeps this allocation-free, as it runs per triangle.
        let mut stack = [0u32; MAX_DEPTH + 2];
        let mut len = 1;
        while len > 0 {
            len -= 1;
            match self.nodes[stack[len] as usize] {
                KdNode::Leaf { domain } => out.push(domain),
                KdNode::Split {
                    axis,
                    pos,
                    left,
                    right,
                } => {
                    let a = axis as usize;
                    // Right first, so the left subtree (lower domains) pops first.
                    if query.max[a] >= pos - eps {
                        stack[len] = right;
                        len += 1;
                    }
                    if query.min[a] <= pos + eps {
                        stack[len] = left;
                        len += 1;
                    }
                }
            }
        }
    }

    /// The leaf boxes in domain order, after checking the tree's shape: node 0 is the
    /// root, every other node has exactly one parent that comes before it (so the tree is
    /// connected and acyclic), it is at most [`MAX_DEPTH`] deep, split planes lie inside
    /// their node's box, and the leaves' domains are exactly `0..leaves`. A tree read from a file is only used after this.
    pub fn boxes(&self, bounds: &Aabb) -> Result<Vec<Aabb>, String> {
        let len = self.nodes.len();
        if len == 0 || len > 2 * super::layout::MAX_DOMAINS as usize {
            return Err(format!("kd tree has {len} nodes"));
        }
        let mut has_parent = vec![false; len];
        let mut leaves = 0usize;
        for (i, node) in self.nodes.iter().enumerate() {
            match *node {
                KdNode::Split {
                    axis,
                    pos,
                    left,
                    right,
                } => {
                    if axis > 2 || !pos.is_finite() {
                        return Err(format!("kd node {i}: bad axis {axis} or plane {pos}"));
                    }
                    for c in [left as usize, right as usize] {
                        if c <= i || c >= len || has_parent[c] {
                            return Err(format!("kd node {i}: bad child {c}"));
                        }
                        has_parent[c] = true;
                    }
                }
                KdNode::Leaf { .. } => leaves += 1,
            }
        }
        if let Some(orphan) = (1..len).find(|&i| !has_parent[i]) {
            return Err(format!("kd node {orphan} is not reachable from the root"));
        }
        let mut boxes: Vec<Option<Aabb>> = vec![None; leaves];
        let mut stack = vec![(0usize, *bounds, 0usize)];
        while let Some((i, b, depth)) = stack.pop() {
            if depth > MAX_DEPTH {
                return Err(format!("kd tree is deeper than {MAX_DEPTH}"));
            }
            match self.nodes[i] {
                KdNode::Leaf { domain } => {
                    let slot = boxes
                        .get_mut(domain as usize)
                        .ok_or_else(|| format!("kd leaf {i}: domain {domain} out of range"))?;
                    if slot.is_some() {
                        return Err(format!("kd domain {domain} appears twice"));
                    }
                    *slot = Some(b);
                }
                KdNode::Split {
                    axis,
                    pos,
                    left,
                    right,
                } => {
                    let a = axis as usize;
                    if !(b.min[a] <= pos && pos <= b.max[a]) {
                        return Err(format!("kd node {i}: plane {pos} outside its box"));
                    }
                    let (mut lb, mut rb) = (b, b);
                    lb.max[a] = pos;
                    rb.min[a] = pos;
                    stack.push((left as usize, lb, depth + 1));
                    stack.push((right as usize, rb, depth + 1));
                }
            }
        }
        // Every leaf was visited (all nodes reachable) and domains are distinct and below
        // `leaves`, so every slot is filled.
        Ok(boxes.into_iter().flatten().collect())
    }
}

/// The split axis and plane for a node that becomes `n` domains, `k` of them on the left.
fn choose_split(node_box: &Aabb, samples: &mut [Vec3], k: u32, n: u32) -> (usize, f32) {
    let extent = node_box.extent();
    let mut axes = [0usize, 1, 2];
    // Longest first; ties keep X before Y before Z (a stable sort).
    axes.sort_by(|&a, &b| extent[b].total_cmp(&extent[a]));
    if !samples.is_empty() {
        let m = (samples.len() as u64 * k as u64 / n as u64) as usize;
        let m = m.min(samples.len() - 1);
        for &axis in &axes {
            if extent[axis] <= 0.0 {
                break;
            }
            let (_, q, _) = samples.select_nth_unstable_by(m, |p, q| p[axis].total_cmp(&q[axis]));
            let q = q[axis];
            if node_box.min[axis] < q && q < node_box.max[axis] {
                return (axis, q);
            }
        }
    }
    let axis = axes[0];
    let mid = ((node_box.min[axis] as f64 + node_box.max[axis] as f64) * 0.5) as f32;
    (axis, mid.clamp(node_box.min[axis], node_box.max[axis]))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn non_power_of_two_counts_are_proportional() {
        let b = Aabb::new(Vec3::ZERO, Vec3::new(10.0, 1.0, 1.0));
        let mut pts: Vec<Vec3> = (0..3000)
            .map(|i| Vec3::new((i as f32 + 0.5) / 300.0, 0.5, 0.5))
            .collect();
        let tree = KdTree::build(&b, &mut pts, 3);
        let boxes = tree.boxes(&b).unwrap();
        assert_eq!(boxes.len(), 3);
        let mut counts = [0; 3];
        for i in 0..3000 {
            counts[tree.locate(Vec3::new((i as f32 + 0.5) / 300.0, 0.5, 0.5)) as usize] += 1;
        }
        assert_eq!(counts, [1000, 1000, 1000]);
    }

    #[test]
    fn degenerate_samples_fall_back_to_other_axes() {
        let b = Aabb::new(Vec3::ZERO, Vec3::new(2.0, 1.0, 1.0));
        // All centroids on x = 0 (the box's lower face): the split must use y or z.
        let mut pts: Vec<Vec3> = (0..100)
            .map(|i| Vec3::new(0.0, i as f32 / 100.0, 0.3))
            .collect();
        let tree = KdTree::build(&b, &mut pts, 2);
        match tree.nodes[0] {
            KdNode::Split { axis, .. } => assert_eq!(axis, 1),
            n => panic!("{n:?}"),
        }
        // No samples at all: a midpoint split of the longest axis.
        let tree = KdTree::build(&b, &mut [], 2);
        assert!(matches!(tree.nodes[0], KdNode::Split { axis: 0, pos, .. } if pos == 1.0));
    }

    #[test]
    fn malformed_trees_are_rejected() {
        let b = Aabb::new(Vec3::ZERO, Vec3::ONE);
        let bad = [
            vec![],
            vec![KdNode::Split {
                axis: 0,
                pos: 0.5,
                left: 0,
                right: 1,
            }],
            vec![
                KdNode::Split {
                    axis: 0,
                    pos: 0.5,
                    left: 1,
                    right: 2,
                },
                KdNode::Leaf { domain: 0 },
                KdNode::Leaf { domain: 0 },
            ],
            vec![
                KdNode::Split {
                    axis: 0,
                    pos: 1.5,
                    left: 1,
                    right: 2,
                },
                KdNode::Leaf { domain: 0 },
                KdNode::Leaf { domain: 1 },
            ],
            vec![
                KdNode::Split {
                    axis: 3,
                    pos: 0.5,
                    left: 1,
                    right: 2,
                },
                KdNode::Leaf { domain: 0 },
                KdNode::Leaf { domain: 1 },
            ],
            vec![KdNode::Leaf { domain: 0 }, KdNode::Leaf { domain: 1 }],
            vec![KdNode::Leaf { domain: 5 }],
        ];
        for t in bad {
            let tree = KdTree { nodes: t.clone() };
            assert!(tree.boxes(&b).is_err(), "{t:?}");
        }
        // A chain deeper than MAX_DEPTH: valid in shape, refused for its depth.
        let chain = |depth: u32| {
            let mut nodes = Vec::new();
            for i in 0..depth {
                let next = nodes.len() as u32;
                nodes.push(KdNode::Split {
                    axis: 0,
                    pos: 0.0,
                    left: next + 1,
                    right: next + 2,
                });
                nodes.push(KdNode::Leaf { domain: i });
            }
            nodes.push(KdNode::Leaf { domain: depth });
            KdTree { nodes }
        };
        assert_eq!(
            chain(MAX_DEPTH as u32).boxes(&b).unwrap().len(),
            MAX_DEPTH + 1
        );
        assert!(chain(MAX_DEPTH as u32 + 1).boxes(&b).is_err());
    }
}

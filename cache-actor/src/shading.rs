//! Averaged shading of a hit map's cells (`phm.shade`; Bolstad 2017 returns it for
//! predicted hits): per cell, the running sum and count of the radiance that probes
//! entering the domain there brought back, so that a ray at a cell that predicts a hit
//! can be answered with their mean instead of being traced.
//!
//! The radiance comes from tickets (crate::tickets): a probe of a kind that carries
//! radiance leaves its wall with a ticket, and when the ticket closes cleanly its
//! `sum / weight` is added here. A ticket any of whose descendants was answered by a
//! cache or a map (tainted) adds nothing: radiance resting on a prediction must not
//! feed the predictions.
//!
//! Why a sparse table: only cells that predict hits for rays of these kinds ever need
//! a mean, and a map may have a million cells; a cell costs [`BYTES_PER_SHADED_CELL`]
//! plus the table's overhead once it has learned, nothing before.
//!
//! Why f64 sums: a cell may average millions of returns of very different sizes (a
//! light seen directly beside a dark wall), and the mean must not drift with the order
//! they arrived in more than f64 rounding does.

use std::collections::HashMap;

/// One cell's radiance returned so far.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct CellShading {
    /// Sum of the radiance returned, per channel.
    pub sum: [f64; 3],
    /// Returns added.
    pub count: u64,
    /// Tickets asked for: rays that went on from the cell carrying one, to teach it.
    pub asked: u64,
}

/// The memory of one cell's sums (without the table's overhead).
pub const BYTES_PER_SHADED_CELL: u64 = std::mem::size_of::<CellShading>() as u64;

impl CellShading {
    /// Add one returned radiance. Not finite or negative radiance is refused (the
    /// tickets never close with it, but a mean must not be poisoned by one bad value);
    /// false then.
    pub fn add(&mut self, rgb: [f32; 3]) -> bool {
        if !rgb.iter().all(|c| c.is_finite() && *c >= 0.0) {
            return false;
        }
        for (s, c) in self.sum.iter_mut().zip(rgb) {
            *s += f64::from(c);
        }
        self.count = self.count.saturating_add(1);
        true
    }

    /// The mean radiance returned, once there is any.
    pub fn mean(&self) -> Option<[f32; 3]> {
        if self.count == 0 {
            return None;
        }
        let n = self.count as f64;
        Some(self.sum.map(|s| (s / n) as f32))
    }
}

/// The running sums of one map's cells, by cell.
#[derive(Debug, Default)]
pub struct Shading {
    cells: HashMap<u32, CellShading>,
}

impl Shading {
    /// Note that a ray entering through `cell` goes on with a ticket to teach it.
    pub fn ask(&mut self, cell: u32) {
        let c = self.cells.entry(cell).or_default();
        c.asked = c.asked.saturating_add(1);
    }

    /// Add `rgb`, returned by a probe that entered through `cell`; false when refused.
    pub fn add(&mut self, cell: u32, rgb: [f32; 3]) -> bool {
        let mut c = self.cells.get(&cell).copied().unwrap_or_default();
        if !c.add(rgb) {
            return false;
        }
        self.cells.insert(cell, c);
        true
    }

    /// The mean radiance `cell`'s probes returned; `None` before any.
    pub fn mean(&self, cell: u32) -> Option<[f32; 3]> {
        self.cells.get(&cell).and_then(CellShading::mean)
    }

    /// The sums of `cell`.
    pub fn cell(&self, cell: u32) -> CellShading {
        self.cells.get(&cell).copied().unwrap_or_default()
    }

    /// Cells holding sums.
    pub fn len(&self) -> usize {
        self.cells.len()
    }

    pub fn is_empty(&self) -> bool {
        self.cells.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_mean_is_the_running_sum_over_the_count() {
        let mut s = Shading::default();
        assert_eq!(s.mean(3), None, "no returns, no mean");
        assert!(s.add(3, [1.0, 2.0, 0.0]));
        assert_eq!(s.mean(3), Some([1.0, 2.0, 0.0]));
        assert!(s.add(3, [3.0, 0.0, 0.5]));
        assert!(s.add(3, [2.0, 1.0, 0.25]));
        assert_eq!(s.mean(3), Some([2.0, 1.0, 0.25]));
        assert_eq!(s.cell(3).count, 3);
        assert_eq!(s.cell(3).sum, [6.0, 3.0, 0.75]);
        // Tickets asked are counted apart: they change no mean.
        s.ask(3);
        s.ask(5);
        assert_eq!((s.cell(3).asked, s.cell(5).asked), (1, 1));
        assert_eq!((s.mean(3), s.mean(5)), (Some([2.0, 1.0, 0.25]), None));
        // Other cells are untouched.
        assert_eq!(s.mean(4), None);
        assert_eq!(s.len(), 2);
    }

    #[test]
    fn bad_radiance_is_refused_and_leaves_the_mean() {
        let mut s = Shading::default();
        s.add(0, [1.0, 1.0, 1.0]);
        for bad in [
            [f32::NAN, 0.0, 0.0],
            [0.0, f32::INFINITY, 0.0],
            [0.0, 0.0, -1.0],
        ] {
            assert!(!s.add(0, bad), "{bad:?}");
            assert!(!s.add(9, bad), "{bad:?}");
        }
        assert_eq!(s.mean(0), Some([1.0; 3]));
        assert_eq!(s.cell(0).count, 1);
        assert_eq!(s.mean(9), None, "a refused first return creates no cell");
        assert_eq!(s.len(), 1);
    }

    #[test]
    fn the_mean_does_not_depend_on_the_order_of_returns_beyond_rounding() {
        let values: Vec<[f32; 3]> = (0..1000)
            .map(|i| {
                let x = (i as f32 * 0.37).sin().abs() * 1e3_f32.powf((i % 5) as f32 - 2.0);
                [x, x * 0.5, 1.0]
            })
            .collect();
        let (mut fwd, mut back) = (Shading::default(), Shading::default());
        for v in &values {
            fwd.add(1, *v);
        }
        for v in values.iter().rev() {
            back.add(1, *v);
        }
        let (a, b) = (fwd.mean(1).unwrap(), back.mean(1).unwrap());
        for (x, y) in a.iter().zip(b) {
            assert!(((x - y) / x).abs() < 1e-6, "{a:?} {b:?}");
        }
        assert_eq!(a[2], 1.0);
    }
}

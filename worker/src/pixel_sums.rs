//! Pixel sums waiting to be reported, merged by pixel.
//!
//! A worker's contributions used to travel one entry per shading event: a 640x480 image
//! at 16 samples sent some ten million (pixel, R, G, B) entries, and encoding, sending
//! and decoding them cost more than a fifth of a one-worker render. Between two reports
//! most entries land on the same few tiles' pixels, so merging them here shrinks a report
//! many times over. The sums are non-negative fixed-point integers added with saturating
//! arithmetic (`dray_core::film::add_sums`), which is then associative and commutative:
//! merging on the worker gives the coordinator the very same bits as sending every entry.
//!
//! AOV sums (`dray_core::aov`, eight words a pixel) merge the same way: their values are
//! bounded so that no sum comes near the limits, where the addition is exact.

use std::collections::HashMap;

/// A deterministic fast hash: pixel indices are not attacker-chosen keys.
type FastState = foldhash::fast::FixedState;

/// Fixed-point sums of `N` words (RGB, or a pixel's AOVs) by sum key, each key once:
/// the pixel in the low 32 bits, and for a job tracing passes ahead the pass above it
/// (`crate::tracer::pass_tag`).
#[derive(Debug)]
pub struct PixelSums<const N: usize = 3> {
    sums: HashMap<u64, [i64; N], FastState>,
}

impl<const N: usize> Default for PixelSums<N> {
    fn default() -> Self {
        PixelSums {
            sums: HashMap::default(),
        }
    }
}

impl<const N: usize> PixelSums<N> {
    /// Add `value` to `key`'s sum (saturating, as `dray_core::film::add_sums`).
    pub fn add(&mut self, key: u64, value: [i64; N]) {
        let s = self.sums.entry(key).or_insert([0; N]);
        for (a, b) in s.iter_mut().zip(value) {
            *a = a.saturating_add(b);
        }
    }

    /// Add every entry of `entries`.
    pub fn extend(&mut self, entries: &[(u64, [i64; N])]) {
        self.sums.reserve(entries.len().min(1 << 16));
        for &(p, v) in entries {
            self.add(p, v);
        }
    }

    /// Add every sum of `other`.
    pub fn absorb(&mut self, other: PixelSums<N>) {
        if self.sums.is_empty() {
            self.sums = other.sums;
            return;
        }
        for (p, v) in other.sums {
            self.add(p, v);
        }
    }

    /// Pixels with a sum.
    pub fn len(&self) -> usize {
        self.sums.len()
    }

    /// Whether no pixel has a sum.
    pub fn is_empty(&self) -> bool {
        self.sums.is_empty()
    }

    /// All sums as (key, sum), in no particular order, leaving this empty.
    pub fn drain(&mut self) -> Vec<(u64, [i64; N])> {
        self.sums.drain().collect()
    }

    /// Take out the sums `keep` says no to (by key), leaving the rest here.
    pub fn split_off(&mut self, keep: impl Fn(u64) -> bool) -> Vec<(u64, [i64; N])> {
        let mut out = Vec::new();
        self.sums.retain(|&k, v| {
            let stay = keep(k);
            if !stay {
                out.push((k, *v));
            }
            stay
        });
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn merged_sums_equal_entry_by_entry_sums() {
        let entries: Vec<(u64, [i64; 3])> = (0..1000u32)
            .map(|i| {
                (
                    u64::from(i % 37),
                    [i as i64, (i as i64) << 45, i64::MAX - i as i64],
                )
            })
            .collect();
        let mut merged = PixelSums::default();
        merged.extend(&entries[..400]);
        merged.extend(&entries[400..]);
        assert_eq!(merged.len(), 37);
        // Exact sums, saturated once at the end: what any grouping gives.
        let mut exact = [[0i128; 3]; 37];
        for (p, v) in &entries {
            for c in 0..3 {
                exact[*p as usize][c] += i128::from(v[c]);
            }
        }
        let expect = exact.map(|s| s.map(|c| c.min(i128::from(i64::MAX)) as i64));
        assert!(
            expect
                .iter()
                .any(|s| s[1] < i64::MAX && s[1] > 1 << 45 && s[2] == i64::MAX)
        );
        let mut got = merged.drain();
        got.sort_unstable_by_key(|e| e.0);
        assert!(merged.is_empty());
        for (p, v) in got {
            assert_eq!(v, expect[p as usize], "pixel {p}");
        }
    }
}

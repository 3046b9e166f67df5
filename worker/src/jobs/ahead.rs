//! What a job tracing passes ahead holds back (`JobSetup.passes_ahead`;
//! docs/architecture.md "Passes", "Trace ahead").
//!
//! The coordinator deals a pass when the one before is complete (its barrier), and
//! counts every sum and credit it receives in the pass it is in. Under a memory budget
//! each pass would then walk every domain again; a worker tracing ahead makes a tile's
//! later passes' camera rays right behind its current ones, so every pass goes through a
//! resident domain in the same visit. What those rays hand back carries their pass
//! (`crate::tracer::pass_tag`); this keeps a later pass's share, sums and credit
//! together, until the worker hears that the job is in that pass, and then lets it go
//! into the next report. The coordinator receives what it would have without tracing
//! ahead, in the same pass: the same film, pass images and retries.

use std::collections::BTreeMap;

use dray_core::aov::AOV_WORDS;
use dray_core::credit::Credit;

use super::report::Report;
use crate::pixel_sums::PixelSums;
use crate::tracer::pass_tag::{split_sum_key, split_tile_key};

/// The passes a job's actor holds back.
#[derive(Debug)]
pub(crate) struct Ahead {
    /// Passes camera rays may be made for beyond the job's.
    passes_ahead: u32,
    /// The pass the job is in, as far as this worker has heard.
    pass: u32,
    /// Results of later passes, by pass.
    held: BTreeMap<u32, Held>,
}

#[derive(Debug, Default)]
struct Held {
    sums: PixelSums,
    aovs: PixelSums<AOV_WORDS>,
    credits: Vec<(u32, Credit)>,
}

impl Ahead {
    /// A job in pass `pass` whose workers may trace `passes_ahead` passes beyond it.
    pub(crate) fn new(passes_ahead: u32, pass: u32) -> Ahead {
        Ahead {
            passes_ahead,
            pass,
            held: BTreeMap::new(),
        }
    }

    /// The last pass whose camera rays may be made now.
    pub(crate) fn open_through(&self) -> u32 {
        self.pass.saturating_add(self.passes_ahead)
    }

    /// Take the results of passes beyond the job's out of `report` and hold them.
    pub(crate) fn hold(&mut self, report: &mut Report) {
        let pass = self.pass;
        for (key, v) in report.sums.split_off(|k| split_sum_key(k).0 <= pass) {
            self.held
                .entry(split_sum_key(key).0)
                .or_default()
                .sums
                .add(key, v);
        }
        for (key, v) in report.aovs.split_off(|k| split_sum_key(k).0 <= pass) {
            self.held
                .entry(split_sum_key(key).0)
                .or_default()
                .aovs
                .add(key, v);
        }
        let held = &mut self.held;
        report.credits.retain(|&(key, credit)| {
            let p = split_tile_key(key).0;
            if p <= pass {
                return true;
            }
            held.entry(p).or_default().credits.push((key, credit));
            false
        });
    }

    /// The job is in pass `pass`: what is held of passes up to it goes into `report`.
    /// False when that is no news.
    pub(crate) fn enter(&mut self, pass: u32, report: &mut Report) -> bool {
        if pass <= self.pass {
            return false;
        }
        self.pass = pass;
        let later = self.held.split_off(&(pass + 1));
        for (_, h) in std::mem::replace(&mut self.held, later) {
            report.sums.absorb(h.sums);
            report.aovs.absorb(h.aovs);
            report.credits.extend(h.credits);
        }
        true
    }

    /// Sums held (for logs and tests).
    pub(crate) fn held_sums(&self) -> usize {
        self.held.values().map(|h| h.sums.len()).sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::tracer::pass_tag::{sum_key, tile_key};

    fn credit(n: u64) -> Credit {
        Credit::from_wire(n)
    }

    /// A report with one sum and one credit in each of `passes`.
    fn report_of(passes: &[u32]) -> Report {
        let mut r = Report::default();
        for &p in passes {
            r.sums
                .add(sum_key(10 + p, tile_key(0, p)), [i64::from(p) + 1; 3]);
            r.credits.push((tile_key(3, p), credit(u64::from(p) + 1)));
        }
        r
    }

    #[test]
    fn later_passes_are_held_until_the_job_is_in_them_and_nothing_is_lost() {
        let mut a = Ahead::new(8, 0);
        let mut r = report_of(&[0, 1, 2]);
        a.hold(&mut r);
        assert_eq!(r.credits, vec![(tile_key(3, 0), credit(1))]);
        assert_eq!(r.sums.len(), 1);
        assert_eq!(a.held_sums(), 2);
        assert_eq!(a.open_through(), 8);
        // Pass 1 starts: pass 1's share comes out, pass 2's stays.
        let mut next = Report::default();
        assert!(a.enter(1, &mut next));
        assert!(!a.enter(1, &mut next), "no news");
        assert_eq!(next.credits, vec![(tile_key(3, 1), credit(2))]);
        let sums = next.sums.drain();
        assert_eq!(sums, vec![(sum_key(11, tile_key(0, 1)), [2; 3])]);
        // Results of pass 1 arriving now pass straight through.
        let mut late = report_of(&[1]);
        a.hold(&mut late);
        assert_eq!(late.credits.len(), 1);
        let mut last = Report::default();
        assert!(a.enter(2, &mut last));
        assert_eq!(last.credits, vec![(tile_key(3, 2), credit(3))]);
        assert_eq!(a.held_sums(), 0);
    }
}

//! Which reports of a job's current attempt were applied, per worker: a report is
//! applied at most once per `(worker, job, attempt, sequence)`, so a worker may retry a
//! call whose answer it lost ([`super::report`]). Sequences start at 1 for each attempt,
//! so a new attempt forgets them all.

use std::collections::{BTreeSet, HashMap};

/// Sequences of one (worker, job) already applied: everything up to `upto`, plus the
/// ones above it that arrived out of order. Stays small when reports arrive in order.
#[derive(Default, Debug)]
pub struct SeqWindow {
    upto: u64,
    above: BTreeSet<u64>,
}

impl SeqWindow {
    /// Whether sequence `s` was applied.
    pub fn contains(&self, s: u64) -> bool {
        s <= self.upto || self.above.contains(&s)
    }

    /// Record sequence `s` as applied.
    pub fn insert(&mut self, s: u64) {
        if s <= self.upto {
            return;
        }
        self.above.insert(s);
        while self.above.remove(&(self.upto + 1)) {
            self.upto += 1;
        }
    }
}

/// The sequences applied per worker in a job's current attempt.
#[derive(Default, Debug)]
pub struct Sequences {
    by_worker: HashMap<String, SeqWindow>,
}

impl Sequences {
    /// Whether `worker`'s sequence `s` was applied.
    pub fn contains(&self, worker: &str, s: u64) -> bool {
        self.by_worker.get(worker).is_some_and(|w| w.contains(s))
    }

    /// Record `worker`'s sequence `s` as applied.
    pub fn insert(&mut self, worker: &str, s: u64) {
        match self.by_worker.get_mut(worker) {
            Some(w) => w.insert(s),
            None => self
                .by_worker
                .entry(worker.to_string())
                .or_default()
                .insert(s),
        }
    }

    /// A new attempt: its sequences start again at 1.
    pub fn clear(&mut self) {
        self.by_worker.clear();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn seq_window_dedupes_in_and_out_of_order() {
        let mut w = SeqWindow::default();
        assert!(!w.contains(1));
        w.insert(1);
        w.insert(3);
        assert!(w.contains(1) && w.contains(3) && !w.contains(2));
        w.insert(2);
        assert_eq!(w.upto, 3);
        assert!(w.above.is_empty());
        assert!(w.contains(2) && !w.contains(4));
    }

    #[test]
    fn sequences_are_per_worker_and_forgotten_by_a_new_attempt() {
        let mut s = Sequences::default();
        s.insert("w1", 1);
        assert!(s.contains("w1", 1) && !s.contains("w2", 1));
        s.clear();
        assert!(!s.contains("w1", 1));
    }
}

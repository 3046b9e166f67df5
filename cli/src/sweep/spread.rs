//! How much a setting's measures moved between `--repeat` rounds: the least and the most
//! of its render time, its bytes between processes and its error against the exact
//! image.
//!
//! Times move with the machine's load; bytes and errors move only where the render is
//! not the same every time. The frozen ray caches and the exact render give the same
//! image and bytes each round. Hit maps (Bolstad 2017: "maps learn differently each run")
//! and caches filled during the render learn from whichever rays arrive first, so their
//! traffic and image change between rounds. The spread shows by how much, beside the
//! medians the rows report.

use super::metrics::Errors;

/// The least and the most of one measure over the rounds.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Range {
    pub min: f64,
    pub max: f64,
}

impl Range {
    fn one(x: f64) -> Range {
        Range { min: x, max: x }
    }

    fn add(&mut self, x: f64) {
        self.min = self.min.min(x);
        self.max = self.max.max(x);
    }
}

/// A setting's ranges over the rounds (one round: each range is its value).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Spread {
    pub render_s: Range,
    pub bytes_total: Range,
    pub rmse: Range,
    pub flip: Range,
}

impl Spread {
    /// The first round's values.
    pub fn first(render_s: f64, bytes_total: u64, errors: &Errors) -> Spread {
        Spread {
            render_s: Range::one(render_s),
            bytes_total: Range::one(bytes_total as f64),
            rmse: Range::one(errors.rmse),
            flip: Range::one(errors.flip),
        }
    }

    /// One more round.
    pub fn add(&mut self, render_s: f64, bytes_total: u64, errors: &Errors) {
        self.render_s.add(render_s);
        self.bytes_total.add(bytes_total as f64);
        self.rmse.add(errors.rmse);
        self.flip.add(errors.flip);
    }
}

/// The CSV columns of a spread, in the order [`cells`] gives them.
pub const COLUMNS: [&str; 8] = [
    "render_s_min",
    "render_s_max",
    "bytes_total_min",
    "bytes_total_max",
    "rmse_min",
    "rmse_max",
    "flip_min",
    "flip_max",
];

/// The cells of [`COLUMNS`].
pub fn cells(s: &Spread) -> Vec<String> {
    vec![
        format!("{:.4}", s.render_s.min),
        format!("{:.4}", s.render_s.max),
        format!("{}", s.bytes_total.min as u64),
        format!("{}", s.bytes_total.max as u64),
        s.rmse.min.to_string(),
        s.rmse.max.to_string(),
        s.flip.min.to_string(),
        s.flip.max.to_string(),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn errors(rmse: f64, flip: f64) -> Errors {
        Errors {
            rmse,
            rmse_linear: rmse,
            psnr: 0.0,
            flip,
        }
    }

    #[test]
    fn a_spread_holds_the_least_and_the_most_of_each_measure() {
        let mut s = Spread::first(1.0, 100, &errors(0.02, 0.03));
        assert_eq!(s.flip, Range::one(0.03));
        s.add(0.8, 120, &errors(0.01, 0.05));
        s.add(1.2, 90, &errors(0.03, 0.04));
        assert_eq!(s.render_s, Range { min: 0.8, max: 1.2 });
        assert_eq!(
            s.bytes_total,
            Range {
                min: 90.0,
                max: 120.0
            }
        );
        assert_eq!(
            s.rmse,
            Range {
                min: 0.01,
                max: 0.03
            }
        );
        assert_eq!(
            s.flip,
            Range {
                min: 0.03,
                max: 0.05
            }
        );
        let c = cells(&s);
        assert_eq!(c.len(), COLUMNS.len());
        assert_eq!(&c[..4], ["0.8000", "1.2000", "90", "120"]);
    }
}

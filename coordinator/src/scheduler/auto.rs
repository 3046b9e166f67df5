//! `auto`, the default schedule: where a job's data lives, chosen once when the job
//! starts, from the scene's resident size and the budgets of the workers it starts on
//! (issue 40). Navrátil et al. 2012, and every production farm, replicate the data that
//! fits and keep ray exchange for data that does not:
//!
//! - the scene **fits** every worker's budget (0 = unlimited, so an unbudgeted cluster
//!   always fits): [`Schedule::Replicated`]. Every worker holds the whole scene (one
//!   domain unless the job asked for more) and traces whole paths for the tiles it is
//!   dealt; no ray leaves the worker that made it, so nothing is exchanged, nothing is
//!   loaded twice per pass and no round moves anything.
//! - it **does not fit** some worker: [`Schedule::Dynamic`] over owned domains, rays
//!   moving between owners, as before `auto` (with `replicate` when the job asks for it).
//! - a job with **ray caches or hit maps** keeps the dynamic schedule: its walls are the
//!   walls between owned domains ([`crate::caches`]), which replication has none of.
//!
//! Pure: the same inputs give the same choice, and the reason says which input decided
//! it, for `--stats`, GetJob (`JobStats.placement`) and the dashboard.

use dray_core::scene::Scene;
use dray_scene::partition::manifest::Manifest;
use dray_scene::partition::resident::{load_reserve, resident_bytes};

use super::policy::{Schedule, ScheduleRequest};

/// What the workers would hold of a scene, as their stores count it
/// ([`resident_bytes`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SceneSize {
    /// Every piece resident at once.
    pub bytes: u64,
    /// The largest piece a worker loads in one go (its load needs [`load_reserve`] of
    /// it beside the pieces already resident).
    pub largest: u64,
}

impl SceneSize {
    /// A scene not yet cut: one piece, every triangle in one BVH.
    pub fn of_scene(scene: &Scene) -> SceneSize {
        let m = &scene.mesh;
        let t = m.indices.len() as u64;
        let bytes = resident_bytes(m.positions.len() as u64, t, t, !m.uvs2.is_empty());
        SceneSize {
            bytes,
            largest: bytes,
        }
    }

    /// A scene package: its domains, each its own piece.
    pub fn of_manifest(manifest: &Manifest) -> SceneSize {
        manifest
            .domains
            .iter()
            .map(|d| resident_bytes(d.vertices, d.triangles, d.triangles, d.uvs2))
            .fold(
                SceneSize {
                    bytes: 0,
                    largest: 0,
                },
                |s, b| SceneSize {
                    bytes: s.bytes.saturating_add(b),
                    largest: s.largest.max(b),
                },
            )
    }

    /// Whether a worker with `budget` bytes (0 = unlimited) holds all of it: the
    /// scheduler's own rule ([`super::policy`] `capacity`): a quarter of a budget is for
    /// rays, and the last piece loads beside the others with room for its peak.
    pub fn fits(&self, budget: u64) -> bool {
        if budget == 0 {
            return true;
        }
        let others = self.bytes.saturating_sub(self.largest);
        others.saturating_add(load_reserve(self.largest)) <= budget / 4 * 3
    }
}

/// What `auto` (or a forced schedule) decided, and why.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Choice {
    /// The schedule the job runs with.
    pub schedule: Schedule,
    /// One line: what decided it (`JobStats.placement`).
    pub reason: String,
}

/// The job's features that decide beside the sizes.
#[derive(Clone, Copy, Debug, Default)]
pub struct JobNeeds {
    /// The job has ray caches or hit maps (they live on the walls of owned domains).
    pub walls: bool,
}

/// The schedule for a job asking for `request`, on workers with `budgets` (id and
/// budget, in job order; 0 = unlimited), of a scene of `size`.
pub fn choose(
    request: ScheduleRequest,
    size: SceneSize,
    budgets: &[(String, u64)],
    needs: JobNeeds,
) -> Choice {
    let replicate = match request {
        ScheduleRequest::Forced(s) => {
            return Choice {
                schedule: s,
                reason: format!("{}: forced by the job (--schedule {})", s.name(), s.name()),
            };
        }
        ScheduleRequest::Auto { replicate } => replicate,
    };
    let dynamic = Schedule::Dynamic { replicate };
    if needs.walls {
        return Choice {
            schedule: dynamic,
            reason: "dynamic (auto): the job's ray caches or hit maps live on the walls of \
                     owned domains"
                .to_string(),
        };
    }
    let scene = mb(size.bytes);
    if let Some((id, budget)) = budgets.iter().find(|(_, b)| !size.fits(*b)) {
        return Choice {
            schedule: dynamic,
            reason: format!(
                "dynamic (auto): the scene ({scene} resident) does not fit worker {id}'s \
                 budget ({}, three quarters for the scene): domains owned, rays moved",
                mb(*budget)
            ),
        };
    }
    let tightest = budgets
        .iter()
        .map(|(_, b)| *b)
        .filter(|&b| b > 0)
        .min()
        .map_or_else(|| "unlimited".to_string(), mb);
    Choice {
        schedule: Schedule::Replicated,
        reason: format!(
            "replicated (auto): the scene ({scene} resident) fits every worker's budget \
             (smallest {tightest}): each holds all of it, no rays exchanged"
        ),
    }
}

/// `bytes` in MB with two decimals (decimal units, as `--memory-budget` reads).
fn mb(bytes: u64) -> String {
    format!("{:.2} MB", bytes as f64 / 1e6)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn size(bytes: u64) -> SceneSize {
        SceneSize {
            bytes,
            largest: bytes,
        }
    }

    fn workers(budgets: &[u64]) -> Vec<(String, u64)> {
        budgets
            .iter()
            .enumerate()
            .map(|(i, &b)| (format!("w{i}"), b))
            .collect()
    }

    #[test]
    fn a_scene_that_fits_every_worker_is_replicated() {
        let auto = ScheduleRequest::Auto { replicate: false };
        let c = choose(
            auto,
            size(1_000_000),
            &workers(&[0, 0, 0]),
            JobNeeds::default(),
        );
        assert_eq!(c.schedule, Schedule::Replicated);
        assert!(c.reason.contains("unlimited"), "{}", c.reason);
        // 1 MB loads with a 1.55 MB peak; three quarters of 2.1 MB is 1.575 MB.
        let c = choose(
            auto,
            size(1_000_000),
            &workers(&[0, 2_100_000]),
            JobNeeds::default(),
        );
        assert_eq!(c.schedule, Schedule::Replicated);
        assert!(c.reason.contains("2.10 MB"), "{}", c.reason);
    }

    #[test]
    fn one_worker_too_small_makes_it_dynamic_and_is_named() {
        let auto = ScheduleRequest::Auto { replicate: true };
        let c = choose(
            auto,
            size(1_000_000),
            &workers(&[0, 2_000_000, 0]),
            JobNeeds::default(),
        );
        assert_eq!(c.schedule, Schedule::Dynamic { replicate: true });
        assert!(c.reason.contains("w1"), "{}", c.reason);
    }

    #[test]
    fn walls_and_forced_schedules_win() {
        let auto = ScheduleRequest::Auto { replicate: false };
        let c = choose(auto, size(10), &workers(&[0]), JobNeeds { walls: true });
        assert_eq!(c.schedule, Schedule::Dynamic { replicate: false });
        let forced = ScheduleRequest::Forced(Schedule::Domain);
        let c = choose(forced, size(10), &workers(&[0]), JobNeeds::default());
        assert_eq!(c.schedule, Schedule::Domain);
        assert!(c.reason.contains("forced"), "{}", c.reason);
    }

    /// Pieces load one at a time: the others resident, the largest with its reserve.
    #[test]
    fn a_package_fits_by_its_pieces() {
        let s = SceneSize {
            bytes: 4_000,
            largest: 1_000,
        };
        // 3,000 resident + 1,550 for the load = 4,550 <= 3/4 of 6,100 (4,575).
        assert!(s.fits(6_100));
        assert!(!s.fits(6_000));
        assert!(s.fits(0));
    }
}

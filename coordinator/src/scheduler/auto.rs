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
//!   moving between owners, as before `auto`.
//! - **in between**: it does not fit some worker, but the workers' budgets together hold
//!   more domains than the package has (each worker's capacity counted as the dynamic
//!   rounds count it, [`slots`]): the dynamic schedule with hot-domain replication
//!   (`Dynamic { replicate: true }`), so the rounds copy the most-wanted resident domains
//!   to idle workers in the room left over (Navrátil et al. 2012's replication, decided
//!   from memory here and from queue reports by the rounds, not a flag a user must know).
//!   The job's `--replicate` still turns it on whatever the room; `--schedule dynamic`
//!   still forces it off.
//! - a job with **ray caches or hit maps** keeps the dynamic schedule: its walls are the
//!   walls between owned domains ([`crate::caches`]), which replication has none of.
//!
//! Pure: the same inputs give the same choice, and the reason says which input decided
//! it, for `--stats`, GetJob (`JobStats.placement`) and the dashboard.

use dray_core::scene::Scene;
use dray_scene::partition::manifest::Manifest;
use dray_scene::partition::resident::{load_reserve, resident_bytes};

use super::policy::{Schedule, ScheduleRequest, slots};

/// What the workers would hold of a scene, as their stores count it
/// ([`resident_bytes`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SceneSize {
    /// Every piece resident at once.
    pub bytes: u64,
    /// The largest piece a worker loads in one go (its load needs [`load_reserve`] of
    /// it beside the pieces already resident).
    pub largest: u64,
    /// Pieces (domains of a package; 1 for a scene not yet cut).
    pub pieces: u32,
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
            pieces: 1,
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
                    pieces: 0,
                },
                |s, b| SceneSize {
                    bytes: s.bytes.saturating_add(b),
                    largest: s.largest.max(b),
                    pieces: s.pieces.saturating_add(1),
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

    /// The size of one domain once cut into `domains` (the pieces' own sizes for a
    /// package; an even share of the scene for a scene not cut yet, which the kd layout
    /// cuts into pieces of about equal triangle counts).
    fn domain_bytes(&self, domains: u32) -> u64 {
        if self.pieces > 1 || domains <= 1 {
            return self.largest;
        }
        self.bytes.div_ceil(u64::from(domains))
    }
}

/// What `auto` (or a forced schedule) decided, and why.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Choice {
    /// The schedule the job runs with.
    pub schedule: Schedule,
    /// One line: what decided it (`JobStats.placement`).
    pub reason: String,
    /// The scene's size as decided on: a worker that joins a replicated job later takes
    /// part only if its budget holds it.
    pub scene: SceneSize,
}

/// The job's features that decide beside the sizes.
#[derive(Clone, Copy, Debug, Default)]
pub struct JobNeeds {
    /// The job has ray caches or hit maps (they live on the walls of owned domains).
    pub walls: bool,
    /// Domains the scene is cut into if it is not replicated (the package's count, or
    /// what the job asks for or is given by default): what the room for copies is
    /// counted in.
    pub domains: u32,
}

/// The schedule for a job asking for `request`, on workers with `budgets` (id and
/// budget, in job order; 0 = unlimited), of a scene of `size`.
pub fn choose(
    request: ScheduleRequest,
    size: SceneSize,
    budgets: &[(String, u64)],
    needs: JobNeeds,
) -> Choice {
    let choice = |schedule, reason: String| Choice {
        schedule,
        reason,
        scene: size,
    };
    let asked = match request {
        ScheduleRequest::Forced(s) => {
            return choice(
                s,
                format!("{}: forced by the job (--schedule {})", s.name(), s.name()),
            );
        }
        ScheduleRequest::Auto { replicate } => replicate,
    };
    if needs.walls {
        return choice(
            Schedule::Dynamic { replicate: asked },
            "dynamic (auto): the job's ray caches or hit maps live on the walls of owned \
             domains"
                .to_string(),
        );
    }
    let scene = mb(size.bytes);
    if let Some((id, budget)) = budgets.iter().find(|(_, b)| !size.fits(*b)) {
        let why = format!(
            "the scene ({scene} resident) does not fit worker {id}'s budget ({}, three \
             quarters for the scene): domains owned, rays moved",
            mb(*budget)
        );
        let room = Room::of(size, budgets, needs.domains);
        let reason = match (asked, room.copies()) {
            (true, _) => {
                format!("dynamic (auto): {why}; hot domains copied as asked (--replicate)")
            }
            (false, true) => format!(
                "dynamic (auto): {why}; hot-domain replication: the workers' budgets hold \
                 {} domains of {} at once, so the hottest are copied to idle workers",
                room.describe(),
                needs.domains
            ),
            (false, false) => format!(
                "dynamic (auto): {why}; no room for copies (the workers' budgets hold {} \
                 domains of {})",
                room.describe(),
                needs.domains
            ),
        };
        return choice(
            Schedule::Dynamic {
                replicate: asked || room.copies(),
            },
            reason,
        );
    }
    let tightest = budgets
        .iter()
        .map(|(_, b)| *b)
        .filter(|&b| b > 0)
        .min()
        .map_or_else(|| "unlimited".to_string(), mb);
    choice(
        Schedule::Replicated,
        format!(
            "replicated (auto): the scene ({scene} resident) fits every worker's budget \
             (smallest {tightest}): each holds all of it, no rays exchanged"
        ),
    )
}

/// The room the workers' budgets leave for a scene cut into domains: how many domains
/// they hold at once, counted per worker as the dynamic rounds count it ([`slots`]).
#[derive(Clone, Copy, Debug)]
struct Room {
    /// Domains held at once over every budgeted worker (None if some worker has no
    /// budget: room without bound).
    slots: Option<u64>,
    domains: u32,
    workers: usize,
}

impl Room {
    fn of(size: SceneSize, budgets: &[(String, u64)], domains: u32) -> Room {
        let piece = size.domain_bytes(domains);
        let slots = budgets.iter().try_fold(0u64, |sum, (_, b)| {
            slots(*b, piece).map(|s| sum.saturating_add(s as u64))
        });
        Room {
            slots,
            domains,
            workers: budgets.len(),
        }
    }

    /// Whether there is room for a copy of some domain beyond one of each: replicas need
    /// two workers, and one slot more than the package's domains.
    fn copies(&self) -> bool {
        self.workers >= 2 && self.slots.is_none_or(|s| s > u64::from(self.domains))
    }

    fn describe(&self) -> String {
        self.slots
            .map_or_else(|| "any number of".to_string(), |s| s.to_string())
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
            pieces: 1,
        }
    }

    fn needs(domains: u32) -> JobNeeds {
        JobNeeds {
            walls: false,
            domains,
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
        let c = choose(auto, size(1_000_000), &workers(&[0, 0, 0]), needs(8));
        assert_eq!(c.schedule, Schedule::Replicated);
        assert!(c.reason.contains("unlimited"), "{}", c.reason);
        // 1 MB loads with a 1.55 MB peak; three quarters of 2.1 MB is 1.575 MB.
        let c = choose(auto, size(1_000_000), &workers(&[0, 2_100_000]), needs(8));
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
            needs(8),
        );
        assert_eq!(c.schedule, Schedule::Dynamic { replicate: true });
        assert!(c.reason.contains("w1"), "{}", c.reason);
        assert!(c.reason.contains("as asked"), "{}", c.reason);
    }

    /// In between: the scene does not fit one worker, but the budgets together hold more
    /// domains than the package has, so auto copies hot domains; with no room it does
    /// not, and `--schedule dynamic` never does.
    #[test]
    fn room_beyond_one_copy_of_each_domain_turns_on_hot_domain_replication() {
        let auto = ScheduleRequest::Auto { replicate: false };
        // 8 MB in 8 domains of 1 MB (each loads with a 1.55 MB peak): a 4 MB budget
        // (3 MB for domains) holds 2, a 6 MB one (4.5 MB) holds 3.
        let eight = size(8_000_000);
        let c = choose(auto, eight, &workers(&[4_000_000; 4]), needs(8));
        assert_eq!(c.schedule, Schedule::Dynamic { replicate: false });
        assert!(c.reason.contains("no room for copies"), "{}", c.reason);
        assert!(c.reason.contains("hold 8 domains of 8"), "{}", c.reason);
        let c = choose(auto, eight, &workers(&[6_000_000; 4]), needs(8));
        assert_eq!(c.schedule, Schedule::Dynamic { replicate: true });
        assert!(c.reason.contains("hot-domain replication"), "{}", c.reason);
        assert!(c.reason.contains("hold 12 domains of 8"), "{}", c.reason);
        // A worker without a budget is room without bound; one worker has nowhere to
        // copy to.
        let c = choose(auto, eight, &workers(&[4_000_000, 0]), needs(8));
        assert_eq!(c.schedule, Schedule::Dynamic { replicate: true });
        let c = choose(auto, eight, &workers(&[6_000_000]), needs(8));
        assert_eq!(c.schedule, Schedule::Dynamic { replicate: false });
        let forced = ScheduleRequest::Forced(Schedule::Dynamic { replicate: false });
        let c = choose(forced, eight, &workers(&[6_000_000; 4]), needs(8));
        assert_eq!(c.schedule, Schedule::Dynamic { replicate: false });
        // A package's own pieces count, not an even share.
        let pkg = SceneSize {
            bytes: 8_000_000,
            largest: 2_000_000,
            pieces: 8,
        };
        let c = choose(auto, pkg, &workers(&[6_000_000; 4]), needs(8));
        assert_eq!(c.schedule, Schedule::Dynamic { replicate: false });
        assert_eq!(c.scene, pkg);
    }

    #[test]
    fn walls_and_forced_schedules_win() {
        let auto = ScheduleRequest::Auto { replicate: false };
        let c = choose(
            auto,
            size(10),
            &workers(&[0]),
            JobNeeds {
                walls: true,
                domains: 8,
            },
        );
        assert_eq!(c.schedule, Schedule::Dynamic { replicate: false });
        let forced = ScheduleRequest::Forced(Schedule::Domain);
        let c = choose(forced, size(10), &workers(&[0]), needs(8));
        assert_eq!(c.schedule, Schedule::Domain);
        assert!(c.reason.contains("forced"), "{}", c.reason);
    }

    /// Pieces load one at a time: the others resident, the largest with its reserve.
    #[test]
    fn a_package_fits_by_its_pieces() {
        let s = SceneSize {
            bytes: 4_000,
            largest: 1_000,
            pieces: 4,
        };
        // 3,000 resident + 1,550 for the load = 4,550 <= 3/4 of 6,100 (4,575).
        assert!(s.fits(6_100));
        assert!(!s.fits(6_000));
        assert!(s.fits(0));
    }
}

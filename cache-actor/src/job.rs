//! One open job attempt on this host: its validated settings (a ray cache, hit maps or
//! both) and domain layout, and the handles of its wall actors.
//!
//! `OpenWalls` is checked in full here before any actor starts, so a bad request
//! changes nothing; after that the layout is immutable and the only thing that grows
//! is the set of walls (a re-open of the same attempt may add walls).

use std::collections::HashMap;
use std::sync::atomic::{AtomicU32, AtomicU64};
use std::sync::{Arc, RwLock};

use dray_core::wall::{self, WallFrame};
use dray_proto::v1::OpenWallsRequest;
use glam::Vec3;

use crate::actor::WallHandle;
use crate::error::HostError;
use crate::settings::{CacheSettings, HitMapSettings, SettingsError, WallSettings};
use crate::ticket_id;

/// Walls one job attempt may open on one host: an actor each, so this bounds the tasks
/// a single request can start (a 64 x 64 x 64 grid has 1.5 Mi walls in all, spread over
/// many hosts). As many as a ticket id can name.
pub const MAX_WALLS_PER_JOB: usize = ticket_id::MAX_WALLS as usize;

/// The scene and domain boxes of a job, validated: finite, `lo <= hi`.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Layout {
    pub scene: (Vec3, Vec3),
    pub domains: Vec<(Vec3, Vec3)>,
}

impl Layout {
    /// The frame of `wall` and whether it lies on the scene bounds; `None` for a wall
    /// beyond the layout.
    pub fn wall(&self, wall: u32) -> Option<(WallFrame, bool)> {
        let (lo, hi) = self.domain_of(wall)?;
        let face = wall::wall_face(wall);
        let (slo, shi) = self.scene;
        Some((
            WallFrame::new(lo, hi, face),
            wall::is_outer(slo, shi, lo, hi, face),
        ))
    }

    /// The box of the domain `wall` belongs to; `None` for a wall beyond the layout.
    pub fn domain_of(&self, wall: u32) -> Option<(Vec3, Vec3)> {
        let domain = usize::try_from(wall::wall_domain(wall)).ok()?;
        self.domains.get(domain).copied()
    }
}

/// A validated `OpenWallsRequest`.
#[derive(Debug)]
pub(crate) struct OpenPlan {
    /// The ray cache; `None` when the job has none.
    pub settings: Option<CacheSettings>,
    /// The hit maps; `None` when the job has none.
    pub phm: Option<HitMapSettings>,
    pub layout: Layout,
    /// Sorted, without duplicates.
    pub walls: Vec<u32>,
    /// The replica these walls are (0: the walls' only actors).
    pub replica: u32,
}

/// Check an `OpenWallsRequest` completely.
pub(crate) fn plan(req: &OpenWallsRequest) -> Result<OpenPlan, HostError> {
    if req.job_id.is_empty() {
        return Err(HostError::NoJobId);
    }
    if req.settings.is_none() && req.phm.is_none() {
        return Err(SettingsError::Neither.into());
    }
    let WallSettings {
        ray_cache: settings,
        phm,
    } = WallSettings::from_proto(req.settings.as_ref(), req.phm.as_ref())?;
    if req.scene_bounds.len() != 6 {
        return Err(HostError::SceneBounds(format!(
            "expected 6 floats, got {}",
            req.scene_bounds.len()
        )));
    }
    let scene = parse_box(&req.scene_bounds).map_err(HostError::SceneBounds)?;
    let n = req.domain_bounds.len();
    if n == 0 || !n.is_multiple_of(6) {
        return Err(HostError::DomainBounds(format!(
            "expected 6 floats per domain and at least one domain, got {n} floats"
        )));
    }
    let domains = req
        .domain_bounds
        .chunks_exact(6)
        .enumerate()
        .map(|(i, b)| parse_box(b).map_err(|e| HostError::DomainBounds(format!("domain {i}: {e}"))))
        .collect::<Result<Vec<_>, _>>()?;
    let mut walls = req.walls.clone();
    walls.sort_unstable();
    walls.dedup();
    if walls.len() > MAX_WALLS_PER_JOB {
        return Err(HostError::TooManyWalls {
            count: walls.len(),
            max: MAX_WALLS_PER_JOB,
        });
    }
    if req.replica > ticket_id::MAX_REPLICAS {
        return Err(HostError::Replica {
            replica: req.replica,
            max: ticket_id::MAX_REPLICAS,
        });
    }
    let layout = Layout { scene, domains };
    if let Some(&wall) = walls.iter().find(|&&w| layout.wall(w).is_none()) {
        return Err(HostError::WallOutOfRange {
            wall,
            domains: layout.domains.len(),
        });
    }
    // A wall of a layout with more than 2^20 / 6 domains: its tickets' ids could not
    // name it. Sorted: the last wall is the largest.
    if let Some(&wall) = walls.last().filter(|&&w| w >= ticket_id::MAX_WALLS) {
        return Err(HostError::WallIndex {
            wall,
            max: ticket_id::MAX_WALLS,
        });
    }
    Ok(OpenPlan {
        settings,
        phm,
        layout,
        walls,
        replica: req.replica,
    })
}

/// Six floats (min x, y, z, max x, y, z) → a box; finite, each min <= max.
fn parse_box(b: &[f32]) -> Result<(Vec3, Vec3), String> {
    let [x0, y0, z0, x1, y1, z1] = b else {
        return Err(format!("expected 6 floats, got {}", b.len()));
    };
    let (lo, hi) = (Vec3::new(*x0, *y0, *z0), Vec3::new(*x1, *y1, *z1));
    if !(lo.is_finite() && hi.is_finite()) {
        return Err(format!("not finite: {b:?}"));
    }
    if !lo.cmple(hi).all() {
        return Err(format!("min exceeds max: {b:?}"));
    }
    Ok((lo, hi))
}

/// An open job attempt, shared by the host's table and the streams using it.
#[derive(Debug)]
pub(crate) struct JobAttempt {
    pub job_id: String,
    pub attempt: u32,
    pub settings: Option<Arc<CacheSettings>>,
    pub phm: Option<Arc<HitMapSettings>>,
    pub layout: Layout,
    /// The replica of the walls this host holds (sender placement), 0 for none: put in
    /// every ticket this host issues, checked on every return. A re-open may renumber
    /// it (a host before this one failed to open, before any ticket was issued).
    pub replica: AtomicU32,
    /// The wall actors. Read on every request (briefly, to clone handles); written only
    /// when a re-open adds walls.
    pub walls: RwLock<HashMap<u32, WallHandle>>,
    /// Ticket returns naming a wall this host does not serve for the attempt.
    pub stray_returns: AtomicU64,
    /// Hit-map outcomes naming a wall this host does not serve for the attempt.
    pub stray_outcomes: AtomicU64,
}

impl JobAttempt {
    /// Handles of the given walls (`None` for walls not served), taken under a brief
    /// read lock so no lock is held while sending to the actors.
    pub fn handles<I: IntoIterator<Item = u32>>(&self, walls: I) -> Vec<Option<WallHandle>> {
        let map = dray_sync::read(&self.walls);
        walls.into_iter().map(|w| map.get(&w).cloned()).collect()
    }

    /// Every wall and its handle.
    pub fn all_handles(&self) -> Vec<(u32, WallHandle)> {
        let map = dray_sync::read(&self.walls);
        map.iter().map(|(w, h)| (*w, h.clone())).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use dray_proto::v1::{PhmSettings, RayCacheSettings};

    fn request() -> OpenWallsRequest {
        OpenWallsRequest {
            job_id: "j".into(),
            attempt: 1,
            settings: Some(RayCacheSettings {
                radius: 0.1,
                ..Default::default()
            }),
            scene_bounds: vec![0.0, 0.0, 0.0, 2.0, 1.0, 1.0],
            domain_bounds: vec![
                0.0, 0.0, 0.0, 1.0, 1.0, 1.0, //
                1.0, 0.0, 0.0, 2.0, 1.0, 1.0,
            ],
            walls: vec![11, 0, 1, 0],
            phm: None,
            replica: 0,
        }
    }

    #[test]
    fn a_good_request_plans() {
        let p = plan(&request()).unwrap();
        assert_eq!(p.walls, vec![0, 1, 11]);
        // Domain 0's -x face is on the scene bounds, its +x face is not.
        assert!(p.layout.wall(0).unwrap().1);
        assert!(!p.layout.wall(1).unwrap().1);
        assert!(p.layout.wall(12).is_none());
        assert!(p.layout.wall(u32::MAX).is_none());
        assert_eq!(
            p.layout.domain_of(7),
            Some((Vec3::X, Vec3::new(2.0, 1.0, 1.0)))
        );
        assert!(p.settings.is_some() && p.phm.is_none());
    }

    #[test]
    fn either_settings_or_phm_is_enough() {
        let mut r = request();
        r.settings = None;
        r.phm = Some(PhmSettings::default());
        let p = plan(&r).unwrap();
        assert!(p.settings.is_none());
        assert_eq!(p.phm.map(|s| s.bins.cells()), Some(192));
        r.settings = request().settings;
        let p = plan(&r).unwrap();
        assert!(p.settings.is_some() && p.phm.is_some());
        r.phm = Some(PhmSettings {
            hit: Some(0.2),
            ..Default::default()
        });
        let e = plan(&r).unwrap_err();
        assert!(e.to_string().starts_with("phm.hit"), "{e}");
        assert_eq!(e.code(), tonic::Code::InvalidArgument);
    }

    #[test]
    fn bad_requests_name_the_field() {
        type Edit = Box<dyn Fn(&mut OpenWallsRequest)>;
        let cases: Vec<(Edit, &str)> = vec![
            (Box::new(|r| r.job_id.clear()), "job_id"),
            (Box::new(|r| r.settings = None), "settings"),
            (
                Box::new(|r| r.scene_bounds.pop().map(drop).unwrap_or(())),
                "scene_bounds",
            ),
            (Box::new(|r| r.scene_bounds[0] = f32::NAN), "scene_bounds"),
            (Box::new(|r| r.scene_bounds[0] = 5.0), "scene_bounds"),
            (Box::new(|r| r.domain_bounds.clear()), "domain_bounds"),
            (Box::new(|r| r.domain_bounds.push(1.0)), "domain_bounds"),
            (
                Box::new(|r| r.domain_bounds[7] = f32::INFINITY),
                "domain_bounds",
            ),
            (Box::new(|r| r.walls.push(12)), "walls"),
            (Box::new(|r| r.walls.push(u32::MAX)), "walls"),
            // Walls of a layout with that many domains, but beyond what a ticket id names.
            (
                Box::new(|r| {
                    let domains = ticket_id::MAX_WALLS as usize / 6 + 1;
                    r.domain_bounds = [0.0, 0.0, 0.0, 1.0, 1.0, 1.0].repeat(domains);
                    r.walls.push(ticket_id::MAX_WALLS);
                }),
                "walls: wall 1048576 cannot be named",
            ),
        ];
        for (edit, field) in cases {
            let mut r = request();
            edit(&mut r);
            let e = plan(&r).unwrap_err();
            assert!(e.to_string().starts_with(field), "{field}: {e}");
            assert_eq!(e.code(), tonic::Code::InvalidArgument);
        }
    }
}

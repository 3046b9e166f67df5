//! Job groups: a spec with `frames` ("A..B[:STEP]") and `fps` becomes one ordinary job
//! per frame, each with `time` = frame / fps and its own image (issue 42).
//!
//! Nothing else in the coordinator knows about groups: each frame is submitted, run,
//! stored, retried after a lost worker and fetched like any job. The group lives in the
//! frames' ids, `<group id>-f<frame>` with a group id `grp-<n>-<nonce>` minted like a
//! job id, so a job taken back from the store after a restart is in its group again
//! with no column added to the store, and `Job.group` is read from the id
//! ([`member_of`]).
//!
//! The group is submitted whole or not at all (`Coordinator::submit_group`, in
//! `crate::service`, beside the SubmitJob it repeats per frame): the range and the frame
//! rate are checked and room for every frame under `--max-jobs` is made sure of before
//! the first frame is accepted, and should a later frame be refused (a store that cannot
//! write), the frames accepted before it are cancelled. This file holds what groups are
//! made of (ids, frames, the shared layout) and depends on no service.
//!
//! **Static geometry stays warm.** The frames of a group are cut with one layout
//! ([`GroupLayouts`]): the first frame cut makes it, and every later frame whose bounds
//! are the same (its moving meshes stay within the still ones) is cut with it instead
//! of its own (a kd split would move with the moving mesh's centroids). A domain that
//! no moving mesh touches then has the same file in every frame's package, and a
//! worker that loaded it for one frame finds it resident for the next (it keys loaded
//! domains by their content, `Manifest::domain_contents`): only the domains a moving
//! mesh touches are loaded and built again. Domains never change the image, and the
//! bounds, which the light powers read, are the frame's own: each frame is the bits of
//! a lone job at its time.

use std::collections::VecDeque;
use std::sync::{Arc, Mutex, MutexGuard};

use dray_core::frames::{FrameRange, check_fps, frame_time};
use dray_core::scene::Scene;
use dray_proto::v1::{JobGroupMember, JobSpec};
use dray_scene::partition::{DomainLayout, LayoutSpec};
use tonic::Status;

use crate::text::bounded;

const GROUP_PREFIX: &str = "grp-";
const FRAME_INFIX: &str = "-f";
/// The longest `frames` text read ("4294967295..4294967295:4294967295" is 34 bytes).
const MAX_FRAMES_BYTES: usize = 64;

/// A new group's id, from the job table's counter and nonce.
pub fn group_id(n: u64, nonce: u32) -> String {
    format!("{GROUP_PREFIX}{n}-{nonce:08x}")
}

/// The id of `frame`'s job in `group`.
pub fn frame_id(group: &str, frame: u32) -> String {
    format!("{group}{FRAME_INFIX}{frame}")
}

/// The group and frame a job id names, for a frame's job; `None` for a lone job.
pub fn member_of(id: &str) -> Option<JobGroupMember> {
    if !id.starts_with(GROUP_PREFIX) {
        return None;
    }
    let (group, frame) = id.rsplit_once(FRAME_INFIX)?;
    if frame.is_empty() || !frame.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    Some(JobGroupMember {
        group_id: group.to_string(),
        frame: frame.parse().ok()?,
    })
}

/// Groups whose layout is kept: the frames of a group are cut one after another or
/// side by side soon after it is submitted, so the last few groups suffice.
const KEPT_GROUPS: usize = 8;

/// One group's layout, made by its first frame cut (see "Static geometry stays warm").
type GroupLayout = Arc<Mutex<Option<(LayoutSpec, DomainLayout)>>>;

/// The layouts the frames of recent groups are cut with.
#[derive(Default)]
pub struct GroupLayouts {
    groups: Mutex<VecDeque<(String, GroupLayout)>>,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

impl GroupLayouts {
    /// The layout to cut `scene`, a frame of `group`, with for `spec`: the group's, when
    /// it was made for `spec` and `scene` has its bounds; else `None` (cut as any job),
    /// and the first frame's own layout becomes the group's. Frames cut side by side wait
    /// for the first to make it. Blocking (reads the scene's triangles).
    pub fn layout_for(
        &self,
        group: &str,
        scene: &Scene,
        spec: &LayoutSpec,
    ) -> dray_scene::error::Result<Option<DomainLayout>> {
        let slot = {
            let mut groups = lock(&self.groups);
            match groups.iter().find(|(g, _)| g == group) {
                Some((_, slot)) => slot.clone(),
                None => {
                    let slot = GroupLayout::default();
                    groups.push_back((group.to_string(), slot.clone()));
                    if groups.len() > KEPT_GROUPS {
                        groups.pop_front();
                    }
                    slot
                }
            }
        };
        let mut kept = lock(&slot);
        match kept.as_ref() {
            Some((kept_spec, layout)) if kept_spec == spec => {
                let bounds = dray_scene::partition::survey(&scene.mesh, 0)?.bounds;
                let same = bounds == layout.scene_bounds();
                tracing::debug!(group, same, "a frame's bounds against its group's layout");
                Ok(same.then(|| layout.clone()))
            }
            Some(_) => Ok(None),
            None => {
                let layout = DomainLayout::for_source(&scene.mesh, spec)?;
                *kept = Some((*spec, layout.clone()));
                Ok(Some(layout))
            }
        }
    }
}

fn invalid(m: String) -> Status {
    Status::invalid_argument(m)
}

/// The frames of a group spec and each frame's spec (`time` = frame / fps; `frames`
/// and `fps` cleared), in frame order. INVALID_ARGUMENT naming the field for a bad
/// range, a missing or bad frame rate, or a `time` beside `frames`.
pub fn expand(spec: &JobSpec) -> Result<Vec<(u32, JobSpec)>, Status> {
    if spec.frames.len() > MAX_FRAMES_BYTES {
        return Err(invalid(format!(
            "frames: {} is not a frame range (expected A..B or A..B:STEP)",
            bounded(&spec.frames)
        )));
    }
    let range = FrameRange::parse(&spec.frames).map_err(|e| invalid(format!("frames: {e}")))?;
    let fps = spec.fps.ok_or_else(|| {
        invalid(format!(
            "fps: required with frames {} (frames a second: frame f is at f / fps seconds)",
            bounded(&spec.frames)
        ))
    })?;
    check_fps(fps).map_err(|e| invalid(format!("fps: {e}")))?;
    if let Some(t) = spec.time {
        return Err(invalid(format!(
            "time: {t} is given with frames {} (each frame's job has time = frame / fps)",
            bounded(&spec.frames)
        )));
    }
    Ok(range
        .frames()
        .map(|frame| {
            let mut one = spec.clone();
            one.frames.clear();
            one.fps = None;
            one.time = Some(frame_time(frame, fps));
            (frame, one)
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_frame_id_names_its_group_and_frame() {
        let g = group_id(7, 0xabc);
        assert_eq!(g, "grp-7-00000abc");
        let m = member_of(&frame_id(&g, 12)).unwrap();
        assert_eq!((m.group_id.as_str(), m.frame), (g.as_str(), 12));
        assert_eq!(member_of("job-3-00000abc"), None);
        assert_eq!(member_of(&g), None);
        assert_eq!(member_of("grp-1-00000abc-fx"), None);
    }

    fn one_frame() -> JobSpec {
        let mut spec = JobSpec::default();
        (spec.scene, spec.width, spec.height, spec.spp) = ("cornell".into(), 8, 8, 1);
        spec
    }

    /// A coordinator restarted on its store lists each frame in its group again: the
    /// group is in the id, which the store keeps.
    #[test]
    fn a_frame_taken_back_from_the_store_is_in_its_group() {
        use dray_proto::v1::{JobState, JobStats};
        let table = crate::jobs::JobTable::new();
        let stored = |id: &str| crate::store::StoredJob {
            id: id.into(),
            spec: JobSpec {
                time: Some(0.5),
                ..one_frame()
            },
            resolved: None,
            state: JobState::Succeeded,
            error: String::new(),
            submitted_at: std::time::SystemTime::now(),
            finished_at: None,
            elapsed: None,
            stats: JobStats::default(),
            attempt: None,
            image: None,
            dropped: None,
            tiles: Vec::new(),
            events: Vec::new(),
            retried_from: None,
        };
        table.restore(vec![stored("grp-4-0000beef-f12"), stored("job-5-0000beef")]);
        let group = |id: &str| table.get(id).and_then(|j| j.to_job().group);
        assert_eq!(
            group("grp-4-0000beef-f12"),
            Some(JobGroupMember {
                group_id: "grp-4-0000beef".into(),
                frame: 12
            })
        );
        assert_eq!(group("job-5-0000beef"), None);
        // A new group after the restart has an id of its own.
        assert_ne!(table.new_group_id(), "grp-4-0000beef");
    }

    #[test]
    fn a_range_expands_to_one_spec_per_frame_at_its_time() {
        let spec = JobSpec {
            scene: "a.gltf".into(),
            frames: "2..8:3".into(),
            fps: Some(4.0),
            animation: "walk".into(),
            ..Default::default()
        };
        let jobs = expand(&spec).unwrap();
        let got: Vec<(u32, Option<f64>)> = jobs.iter().map(|(f, s)| (*f, s.time)).collect();
        assert_eq!(got, [(2, Some(0.5)), (5, Some(1.25)), (8, Some(2.0))]);
        assert!(
            jobs.iter()
                .all(|(_, s)| s.frames.is_empty() && s.fps.is_none() && s.animation == "walk")
        );
    }

    #[test]
    fn bad_groups_are_refused_naming_the_field() {
        let msg = |frames: &str, fps: Option<f64>, time: Option<f64>| {
            let spec = JobSpec {
                frames: frames.into(),
                fps,
                time,
                ..Default::default()
            };
            expand(&spec).unwrap_err().message().to_string()
        };
        assert!(msg("5..1", Some(24.0), None).starts_with("frames: \"5..1\": the range ends"));
        assert!(msg("1..", Some(24.0), None).starts_with("frames: \"1..\" is not a frame range"));
        assert!(msg("1..4:0", Some(24.0), None).contains("step must be at least 1"));
        assert!(msg("1..4", Some(0.0), None).starts_with("fps: the frame rate must be"));
        assert!(msg("1..4", None, None).starts_with("fps: required with frames"));
        assert!(msg("1..4", Some(24.0), Some(1.0)).starts_with("time: 1 is given with frames"));
        assert!(msg(&"1".repeat(100), Some(24.0), None).contains("(100 bytes)"));
    }
}

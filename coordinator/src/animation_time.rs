//! The moment of a job's glTF animation (`JobSpec.time`, `JobSpec.animation`): checked
//! with the spec's other fields, then handed to the scene loader by
//! `crate::validate::prepare`, so the coordinator cuts the posed scene and every worker
//! traces the posed package (the workers never load the file themselves).
//!
//! A group of frames (`JobSpec.frames`, `fps`) is expanded by `crate::job_group` into
//! jobs with one `time` each before it reaches here: a spec that still carries `frames`
//! is one that skipped SubmitJob's expansion, and is refused.

use dray_proto::v1::JobSpec;
use dray_scene::animation::AnimationTime;
use tonic::Status;

use crate::text::bounded;

/// Check `time`, `animation`, `frames` and `fps` of a single job's spec: the moment to
/// load, or `None` for the rest pose.
pub fn check(spec: &JobSpec) -> Result<Option<AnimationTime>, Status> {
    let bad = |m: String| Err(Status::invalid_argument(m));
    if !spec.frames.is_empty() {
        return bad(format!(
            "frames: {} makes a job group, one job per frame, which SubmitJob expands; \
             submit it with SubmitJob (this call takes one job: give `time` instead)",
            bounded(&spec.frames)
        ));
    }
    if let Some(fps) = spec.fps {
        return bad(format!(
            "fps: {fps} frames a second without `frames` (give `time` in seconds for one \
             frame)"
        ));
    }
    match spec.time {
        Some(t) if !t.is_finite() => bad(format!("time: must be finite seconds, got {t}")),
        Some(seconds) => Ok(Some(AnimationTime {
            seconds,
            animation: Some(spec.animation.clone()).filter(|a| !a.is_empty()),
        })),
        None if !spec.animation.is_empty() => bad(format!(
            "animation: {} is given without `time` or `frames` (the moment to sample it)",
            bounded(&spec.animation)
        )),
        None => Ok(None),
    }
}

/// Refuse, before SubmitJob answers, an animation the scene's file does not have: its
/// names are read from the file's JSON alone (`dray_scene::gltf::animation_names`), with
/// the loader's own rule for which one a name or index chooses, so the message is the
/// one the load would give, but the job is never accepted. `scene_spec` is the resolved
/// spec (a path under the scene root, or a `grid:` of one), `given` the client's. A
/// scene with no file (procedural) or a file that is not glTF is left to the load.
pub fn check_named(
    time: Option<&AnimationTime>,
    scene_spec: &str,
    given: &str,
) -> Result<(), Status> {
    let Some(want) = time.and_then(|t| t.animation.as_deref()) else {
        return Ok(());
    };
    let Some(file) = dray_scene::animated_file(scene_spec) else {
        return Err(Status::invalid_argument(format!(
            "animation: {} is named, but {} is a procedural scene, which has no animations",
            bounded(want),
            bounded(given)
        )));
    };
    let Some(names) = dray_scene::gltf::animation_names(std::path::Path::new(file)) else {
        return Ok(());
    };
    let shown = dray_scene::animated_file(given).unwrap_or(given);
    dray_scene::animation::choose(&names, want)
        .map(|_| ())
        .map_err(|m| Status::invalid_argument(format!("animation: {}: {m}", bounded(shown))))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec() -> JobSpec {
        JobSpec {
            scene: "cornell".into(),
            ..Default::default()
        }
    }

    #[test]
    fn a_time_and_an_animation_are_the_moment_to_load() {
        let s = JobSpec {
            time: Some(0.5),
            animation: "walk".into(),
            ..spec()
        };
        assert_eq!(
            check(&s).unwrap(),
            Some(AnimationTime {
                seconds: 0.5,
                animation: Some("walk".into())
            })
        );
        assert_eq!(check(&spec()).unwrap(), None);
    }

    #[test]
    fn what_cannot_be_a_moment_is_refused_naming_the_field() {
        let msg = |s: JobSpec| check(&s).unwrap_err().message().to_string();
        assert!(
            msg(JobSpec {
                time: Some(f64::NAN),
                ..spec()
            })
            .starts_with("time: must be finite")
        );
        assert!(
            msg(JobSpec {
                animation: "walk".into(),
                ..spec()
            })
            .starts_with("animation: \"walk\" is given without `time`")
        );
        assert!(
            msg(JobSpec {
                fps: Some(24.0),
                ..spec()
            })
            .starts_with("fps: 24 frames a second without `frames`")
        );
        assert!(
            msg(JobSpec {
                frames: "1..3".into(),
                ..spec()
            })
            .starts_with("frames: \"1..3\" makes a job group")
        );
    }
}

//! `--time`, `--animation`, `--frames` and `--fps`: which moment of a glTF animation a
//! job renders, or which frames a job group renders (`JobSpec.time`, `animation`,
//! `frames`, `fps`), shared by `dray render` and `dray submit` through
//! [`crate::job_flags::JobFlags`].

use anyhow::{Result, bail};
use clap::Args;
use dray_core::frames::{FrameRange, check_fps};

#[derive(Args, Debug, Clone, Default)]
pub struct AnimationFlags {
    /// Render the scene's glTF animation at this many seconds: node translations,
    /// rotations, scales and morph weights as their keyframes give them then (before
    /// the first key the first, after the last the last; skins follow their joints).
    /// Default: the file's rest pose. On workers the coordinator cuts the posed scene.
    #[arg(
        long,
        value_name = "SECONDS",
        allow_hyphen_values = true,
        conflicts_with = "frames"
    )]
    #[arg(help_heading = crate::help_heading::ANIMATION)]
    pub time: Option<f64>,
    /// The animation --time or --frames samples, by name or index (default: the first;
    /// a file may hold one per action, "Idle", "Walk", …, which are not played together).
    #[arg(long, value_name = "NAME")]
    #[arg(help_heading = crate::help_heading::ANIMATION)]
    pub animation: Option<String>,
    /// Render frames A to B inclusive (every STEP-th), one image each, frame f at
    /// f / --fps seconds: a job group, one ordinary job per frame. --output and --exr
    /// are patterns: a run of # is the frame number zero-padded to its length
    /// (out.####.png: out.0001.png); a name without # gets ".NNNN" (the frame, 4 digits)
    /// before its extension (out.png: out.0001.png).
    #[arg(long, value_name = "A..B[:STEP]", value_parser = parse_frames, requires = "fps")]
    #[arg(help_heading = crate::help_heading::ANIMATION)]
    pub frames: Option<FrameRange>,
    /// Frames a second for --frames (above 0; 24, 25, 30, 23.976, ...).
    #[arg(long, value_name = "N", value_parser = parse_fps, requires = "frames")]
    #[arg(help_heading = crate::help_heading::ANIMATION)]
    pub fps: Option<f64>,
}

/// `--frames A..B[:STEP]`, refused as a usage error with the range's own words.
fn parse_frames(s: &str) -> Result<FrameRange, String> {
    FrameRange::parse(s).map_err(|e| e.to_string())
}

/// `--fps N`: finite and above 0.
fn parse_fps(s: &str) -> Result<f64, String> {
    let v: f64 = s
        .parse()
        .map_err(|_| format!("{s:?} is not a number of frames a second"))?;
    check_fps(v).map_err(|e| e.to_string())
}

impl AnimationFlags {
    /// What clap cannot say: --animation needs a moment, and --time a finite one.
    pub fn check(&self) -> Result<()> {
        if self.animation.is_some() && self.time.is_none() && self.frames.is_none() {
            bail!("--animation: give --time or --frames (the moment to sample it)");
        }
        if let Some(t) = self.time
            && !t.is_finite()
        {
            bail!("--time {t}: give finite seconds");
        }
        Ok(())
    }

    /// The `frames` text of a JobSpec (empty for one job).
    pub fn frames_text(&self) -> String {
        self.frames
            .map(|r| format!("{}..{}:{}", r.start, r.end, r.step))
            .unwrap_or_default()
    }

    /// The moment to load in this process (`dray render`), for one job.
    pub fn moment(&self) -> Option<dray_scene::animation::AnimationTime> {
        self.time
            .map(|seconds| dray_scene::animation::AnimationTime {
                seconds,
                animation: self.animation.clone(),
            })
    }
}

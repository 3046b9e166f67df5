//! Frame ranges of an animation: `A..B[:STEP]` at `fps` frames a second, one job (one
//! image) per frame (`dray render/submit --frames`, `JobSpec.frames`/`fps`).
//!
//! One parser for the CLI and the coordinator, so a range means the same frames
//! wherever it is read and is refused with the same words. Frame `f` is the moment
//! `f / fps` seconds into the animation; the range is inclusive at both ends, as a
//! render farm's (Blender's `1..24` is 24 frames).

/// The most frames one range may make: a group's jobs are ordinary jobs, each counted
/// against the coordinator's `--max-jobs`, so larger ranges are cut by the caller.
pub const MAX_FRAMES: u32 = 10_000;

/// Why a range or a frame rate is refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FramesError {
    #[error(
        "{0:?} is not a frame range: expected A..B or A..B:STEP (frames A to B inclusive, e.g. 1..24 or 0..100:5)"
    )]
    Syntax(String),
    #[error("{text:?}: frame {value:?} is not a whole number of at least 0")]
    Frame { text: String, value: String },
    #[error("{text:?}: the range ends before it starts ({end} < {start})")]
    Backwards { text: String, start: u32, end: u32 },
    #[error("{text:?}: the step must be at least 1")]
    ZeroStep { text: String },
    #[error("{text:?} makes {count} frames, more than {MAX_FRAMES} in one range")]
    TooMany { text: String, count: u64 },
    #[error("the frame rate must be finite and above 0 frames a second, got {0}")]
    Fps(f64),
}

/// A parsed `A..B[:STEP]`: frames `start`, `start + step`, … up to `end` inclusive.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FrameRange {
    pub start: u32,
    pub end: u32,
    pub step: u32,
}

impl FrameRange {
    /// Parse `A..B` or `A..B:STEP` (digits only, no spaces, no signs).
    pub fn parse(text: &str) -> Result<FrameRange, FramesError> {
        let (range, step) = match text.split_once(':') {
            Some((r, s)) => (r, Some(s)),
            None => (text, None),
        };
        let (a, b) = range
            .split_once("..")
            .ok_or_else(|| FramesError::Syntax(text.to_string()))?;
        let number = |v: &str| -> Result<u32, FramesError> {
            if v.is_empty() {
                return Err(FramesError::Syntax(text.to_string()));
            }
            v.parse::<u32>()
                .ok()
                .filter(|_| v.bytes().all(|c| c.is_ascii_digit()))
                .ok_or_else(|| FramesError::Frame {
                    text: text.to_string(),
                    value: v.to_string(),
                })
        };
        let (start, end) = (number(a)?, number(b)?);
        let step = match step {
            Some(s) => number(s)?,
            None => 1,
        };
        if end < start {
            return Err(FramesError::Backwards {
                text: text.to_string(),
                start,
                end,
            });
        }
        if step == 0 {
            return Err(FramesError::ZeroStep {
                text: text.to_string(),
            });
        }
        let count = u64::from(end - start) / u64::from(step) + 1;
        if count > u64::from(MAX_FRAMES) {
            return Err(FramesError::TooMany {
                text: text.to_string(),
                count,
            });
        }
        Ok(FrameRange { start, end, step })
    }

    /// The frames, in order.
    pub fn frames(self) -> impl Iterator<Item = u32> {
        (self.start..=self.end).step_by(self.step as usize)
    }

    /// How many frames the range makes.
    pub fn len(self) -> u32 {
        (self.end - self.start) / self.step + 1
    }

    /// Never: a range has at least its first frame.
    pub fn is_empty(self) -> bool {
        false
    }
}

/// Check a frame rate: finite and above 0.
pub fn check_fps(fps: f64) -> Result<f64, FramesError> {
    if fps.is_finite() && fps > 0.0 {
        Ok(fps)
    } else {
        Err(FramesError::Fps(fps))
    }
}

/// The moment of `frame` at `fps`, in seconds: one division in f64, so every process
/// that renders the frame samples the animation at the same bits.
pub fn frame_time(frame: u32, fps: f64) -> f64 {
    f64::from(frame) / fps
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ranges_are_inclusive_with_an_optional_step() {
        let r = FrameRange::parse("1..3").unwrap();
        assert_eq!(r.frames().collect::<Vec<_>>(), [1, 2, 3]);
        assert_eq!(r.len(), 3);
        let r = FrameRange::parse("0..10:4").unwrap();
        assert_eq!(r.frames().collect::<Vec<_>>(), [0, 4, 8]);
        assert_eq!(r.len(), 3);
        assert_eq!(FrameRange::parse("7..7").unwrap().len(), 1);
    }

    #[test]
    fn bad_ranges_are_refused_naming_what_is_wrong() {
        let err = |t: &str| FrameRange::parse(t).unwrap_err().to_string();
        assert!(err("5..1").contains("ends before it starts (1 < 5)"));
        assert!(err("1..").contains("not a frame range"));
        assert!(err("..4").contains("not a frame range"));
        assert!(err("1-4").contains("not a frame range"));
        assert!(err("1..4:0").contains("step must be at least 1"));
        assert!(err("-1..4").contains("\"-1\" is not a whole number"));
        assert!(err("1..+4").contains("\"+4\" is not a whole number"));
        assert!(err("0..20000").contains("more than 10000"));
        assert!(check_fps(0.0).unwrap_err().to_string().contains("above 0"));
        assert!(check_fps(f64::NAN).is_err());
        assert!(check_fps(-24.0).is_err());
        assert_eq!(check_fps(24.0), Ok(24.0));
    }

    #[test]
    fn a_frame_time_is_frame_over_fps() {
        assert_eq!(frame_time(12, 24.0), 0.5);
        assert_eq!(frame_time(0, 30.0), 0.0);
    }
}

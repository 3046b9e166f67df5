//! The pose an animation gives the nodes at a time: its channels read through the
//! accessors, checked and sampled ([`crate::animation`] does the sampling).

use super::{Loader, format_error};
use crate::animation::{AnimationTime, Channel, Interpolation, Pose, Target};
use crate::error::Result;

impl Loader<'_> {
    /// The pose of the animation `time` names at `time.seconds`: its channels decoded,
    /// checked and sampled. A file without animations renders its rest pose (warned); an
    /// animation asked for by a name or index the file does not have is an error.
    pub(super) fn pose_at(&mut self, time: &AnimationTime) -> Result<Pose> {
        if !time.seconds.is_finite() {
            return Err(self.error(format!(
                "animation time {} s is not a finite number",
                time.seconds
            )));
        }
        let doc = self.doc;
        let animations: Vec<gltf::Animation<'_>> = doc.animations().collect();
        if animations.is_empty() {
            if time.animation.is_some() {
                return Err(self.error("has no animations to choose from"));
            }
            self.warn(format!(
                "{}: has no animations; every time shows the rest pose",
                self.path.display()
            ));
            return Ok(Pose::default());
        }
        let label = |a: &gltf::Animation<'_>| {
            a.name()
                .map(|n| format!("{n:?}"))
                .unwrap_or_else(|| format!("#{}", a.index()))
        };
        let chosen = match time.animation.as_deref() {
            None => &animations[0],
            Some(want) => {
                let names: Vec<Option<String>> = animations
                    .iter()
                    .map(|a| a.name().map(str::to_string))
                    .collect();
                &animations[crate::animation::choose(&names, want).map_err(|m| self.error(m))?]
            }
        };
        let name = label(chosen);
        let mut channels = Vec::new();
        for channel in chosen.channels() {
            let sampler = channel.sampler();
            let target = match channel.target().property() {
                gltf::animation::Property::Translation => Target::Translation,
                gltf::animation::Property::Rotation => Target::Rotation,
                gltf::animation::Property::Scale => Target::Scale,
                gltf::animation::Property::MorphTargetWeights => Target::Weights,
            };
            let interpolation = match sampler.interpolation() {
                gltf::animation::Interpolation::Linear => Interpolation::Linear,
                gltf::animation::Interpolation::Step => Interpolation::Step,
                gltf::animation::Interpolation::CubicSpline => Interpolation::CubicSpline,
            };
            let at = |m: String| {
                format_error(
                    self.path,
                    format!("animation {name} channel {}: {m}", channel.index()),
                )
            };
            let times: Vec<f32> = self.read_accessor(sampler.input().index(), 1).map_err(at)?;
            let dims = match target {
                Target::Translation | Target::Scale => 3,
                Target::Rotation => 4,
                Target::Weights => 1,
            };
            let values: Vec<f32> = self
                .read_accessor(sampler.output().index(), dims)
                .map_err(at)?;
            let per_key = if interpolation == Interpolation::CubicSpline {
                3
            } else {
                1
            };
            let width = match target {
                // One scalar per morph target per element.
                Target::Weights => values.len() / (times.len() * per_key).max(1),
                _ => dims,
            };
            let c = Channel {
                node: channel.target().node().index(),
                target,
                interpolation,
                times,
                values,
                width,
            };
            c.check().map_err(|e| at(e.to_string()))?;
            channels.push(c);
        }
        Ok(Pose::sample(&channels, time.seconds))
    }
}

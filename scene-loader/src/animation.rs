//! glTF animations sampled at one moment: the node transforms (translation, rotation,
//! scale) and morph-target weights a frame sees (glTF 2.0 §3.11, Appendix C).
//!
//! A frame of an animation is an ordinary scene: the loader asks [`Pose`] for each
//! node's local transform and weights instead of the file's rest values, and everything
//! after (flattening, morphing, partitioning) is unchanged. Sampling is a pure function
//! of the keyframes and the time, in f64, so every process that loads the same frame gets
//! the same bits.
//!
//! Which animation: a file may hold several (an exporter writes one per action: "Idle",
//! "Walk", …, each driving the same nodes), so one is chosen, the first unless named;
//! playing them all at once would mix actions. Times before the first key hold the first
//! value and after the last the last (glTF leaves looping to the application). Skinned
//! meshes follow the joints' animated nodes ([`crate::skin`]).

use std::collections::HashMap;

use glam::{DQuat, DVec3};

/// The moment to sample: `seconds` into `animation` (a name or an index into the file's
/// animations; `None` for the first).
#[derive(Clone, Debug, PartialEq)]
pub struct AnimationTime {
    pub seconds: f64,
    pub animation: Option<String>,
}

/// The index of the animation `want` names among a file's animations (`names`, each
/// `None` when unnamed): the first with that name, else `want` read as an index. The
/// error lists what the file has, so a typo can be fixed from the message alone. One
/// rule for the loader and for SubmitJob's check of the JSON alone
/// ([`crate::gltf::animation_names`]), so they never disagree.
pub fn choose(names: &[Option<String>], want: &str) -> Result<usize, String> {
    if names.is_empty() {
        return Err("has no animations to choose from".into());
    }
    names
        .iter()
        .position(|n| n.as_deref() == Some(want))
        .or_else(|| want.parse::<usize>().ok().filter(|&i| i < names.len()))
        .ok_or_else(|| format!("no animation {want:?} (the file has {})", listed(names)))
}

/// The animations of a file as a message lists them: names quoted, unnamed ones by index.
pub fn listed(names: &[Option<String>]) -> String {
    let label = |(i, n): (usize, &Option<String>)| match n {
        Some(n) => format!("{n:?}"),
        None => format!("#{i}"),
    };
    names
        .iter()
        .enumerate()
        .map(label)
        .collect::<Vec<_>>()
        .join(", ")
}

/// How a sampler interpolates between keys.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Interpolation {
    Linear,
    Step,
    /// Hermite: each key stores (in-tangent, value, out-tangent).
    CubicSpline,
}

/// Which property a channel drives.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Target {
    Translation,
    Rotation,
    Scale,
    Weights,
}

/// One channel's keys, decoded: `times` ascending, `values` flat with `width` numbers per
/// element (3 for translation and scale, 4 for rotation (x, y, z, w), the morph-target
/// count for weights), three elements per key for cubic splines.
#[derive(Clone, Debug)]
pub struct Channel {
    pub node: usize,
    pub target: Target,
    pub interpolation: Interpolation,
    pub times: Vec<f32>,
    pub values: Vec<f32>,
    pub width: usize,
}

/// Why a channel cannot be sampled; the loader adds the file and animation.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ChannelError {
    #[error("sampler has no keyframes")]
    NoKeys,
    #[error("keyframe times are not finite and ascending (key {0})")]
    Times(usize),
    #[error(
        "{values} output values for {keys} keys of {width} numbers each ({per_key} elements a key)"
    )]
    Count {
        values: usize,
        keys: usize,
        width: usize,
        per_key: usize,
    },
    #[error("an output value is not finite")]
    NotFinite,
}

impl Channel {
    /// Check the keys once, so that sampling cannot fail or index out of range.
    pub fn check(&self) -> Result<(), ChannelError> {
        if self.times.is_empty() {
            return Err(ChannelError::NoKeys);
        }
        for (i, w) in self.times.windows(2).enumerate() {
            // Ascending, and NaN (which compares as nothing) refused with it.
            if w[0].partial_cmp(&w[1]) != Some(std::cmp::Ordering::Less) {
                return Err(ChannelError::Times(i + 1));
            }
        }
        if !self.times[0].is_finite() || !self.times[self.times.len() - 1].is_finite() {
            return Err(ChannelError::Times(0));
        }
        let per_key = match self.interpolation {
            Interpolation::CubicSpline => 3,
            _ => 1,
        };
        if self.width == 0 || self.values.len() != self.times.len() * per_key * self.width {
            return Err(ChannelError::Count {
                values: self.values.len(),
                keys: self.times.len(),
                width: self.width,
                per_key,
            });
        }
        if self.values.iter().any(|v| !v.is_finite()) {
            return Err(ChannelError::NotFinite);
        }
        Ok(())
    }

    /// The channel's value at `t` seconds (`width` numbers), after [`Channel::check`].
    /// Rotations are normalised quaternions (spherical interpolation for linear keys).
    pub fn sample(&self, t: f64) -> Vec<f64> {
        let n = self.times.len();
        let per_key = if self.interpolation == Interpolation::CubicSpline {
            3
        } else {
            1
        };
        // The value element (not a tangent) of key k.
        let value = |k: usize| -> Vec<f64> {
            let at = (k * per_key + usize::from(per_key == 3)) * self.width;
            self.values[at..at + self.width]
                .iter()
                .map(|&v| f64::from(v))
                .collect()
        };
        let first = f64::from(self.times[0]);
        let last = f64::from(self.times[n - 1]);
        let out = if n == 1 || t <= first {
            value(0)
        } else if t >= last {
            value(n - 1)
        } else {
            // The key interval holding t: times[k] <= t < times[k + 1].
            let k = self.times.partition_point(|&x| f64::from(x) <= t) - 1;
            let (t0, t1) = (f64::from(self.times[k]), f64::from(self.times[k + 1]));
            let dt = t1 - t0;
            let s = (t - t0) / dt;
            match self.interpolation {
                Interpolation::Step => value(k),
                Interpolation::Linear if self.target == Target::Rotation => {
                    let (a, b) = (quat(&value(k)), quat(&value(k + 1)));
                    let q = a.slerp(b, s);
                    vec![q.x, q.y, q.z, q.w]
                }
                Interpolation::Linear => {
                    let (a, b) = (value(k), value(k + 1));
                    a.iter().zip(&b).map(|(a, b)| a + (b - a) * s).collect()
                }
                Interpolation::CubicSpline => {
                    // Appendix C: p(s) = (2s³ - 3s² + 1) v_k + (s³ - 2s² + s) dt b_k
                    //                  + (-2s³ + 3s²) v_k+1 + (s³ - s²) dt a_k+1,
                    // b_k the out-tangent of key k, a_k+1 the in-tangent of key k + 1.
                    let element = |k: usize, e: usize| -> &[f32] {
                        let at = (k * 3 + e) * self.width;
                        &self.values[at..at + self.width]
                    };
                    let (s2, s3) = (s * s, s * s * s);
                    let (h00, h10) = (2.0 * s3 - 3.0 * s2 + 1.0, s3 - 2.0 * s2 + s);
                    let (h01, h11) = (-2.0 * s3 + 3.0 * s2, s3 - s2);
                    (0..self.width)
                        .map(|c| {
                            let v0 = f64::from(element(k, 1)[c]);
                            let b0 = f64::from(element(k, 2)[c]);
                            let v1 = f64::from(element(k + 1, 1)[c]);
                            let a1 = f64::from(element(k + 1, 0)[c]);
                            h00 * v0 + h10 * dt * b0 + h01 * v1 + h11 * dt * a1
                        })
                        .collect()
                }
            }
        };
        if self.target == Target::Rotation {
            let q = quat(&out).normalize();
            vec![q.x, q.y, q.z, q.w]
        } else {
            out
        }
    }
}

fn quat(v: &[f64]) -> DQuat {
    DQuat::from_xyzw(v[0], v[1], v[2], v[3])
}

/// What the animation sets on one node; `None` keeps the file's value.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct NodePose {
    pub translation: Option<DVec3>,
    pub rotation: Option<DQuat>,
    pub scale: Option<DVec3>,
    pub weights: Option<Vec<f32>>,
}

/// Every animated node's pose at one moment.
#[derive(Clone, Debug, Default)]
pub struct Pose {
    pub nodes: HashMap<usize, NodePose>,
}

impl Pose {
    /// Sample `channels` (each already checked) at `t` seconds. A later channel on the
    /// same node and property replaces an earlier one.
    pub fn sample(channels: &[Channel], t: f64) -> Pose {
        let mut nodes: HashMap<usize, NodePose> = HashMap::new();
        for c in channels {
            let v = c.sample(t);
            let pose = nodes.entry(c.node).or_default();
            match c.target {
                Target::Translation => pose.translation = Some(DVec3::new(v[0], v[1], v[2])),
                Target::Rotation => pose.rotation = Some(quat(&v)),
                Target::Scale => pose.scale = Some(DVec3::new(v[0], v[1], v[2])),
                Target::Weights => pose.weights = Some(v.iter().map(|&w| w as f32).collect()),
            }
        }
        Pose { nodes }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn channel(
        target: Target,
        interpolation: Interpolation,
        times: &[f32],
        values: &[f32],
        width: usize,
    ) -> Channel {
        let c = Channel {
            node: 0,
            target,
            interpolation,
            times: times.to_vec(),
            values: values.to_vec(),
            width,
        };
        c.check().expect("valid channel");
        c
    }

    #[test]
    fn linear_keys_interpolate_and_clamp_at_the_ends() {
        let c = channel(
            Target::Translation,
            Interpolation::Linear,
            &[1.0, 3.0],
            &[0.0, 0.0, 0.0, 4.0, 2.0, -2.0],
            3,
        );
        assert_eq!(c.sample(2.0), vec![2.0, 1.0, -1.0]);
        assert_eq!(c.sample(0.0), vec![0.0, 0.0, 0.0]);
        assert_eq!(c.sample(10.0), vec![4.0, 2.0, -2.0]);
        assert_eq!(c.sample(1.5), vec![1.0, 0.5, -0.5]);
    }

    #[test]
    fn step_keys_hold_until_the_next_key() {
        let c = channel(
            Target::Weights,
            Interpolation::Step,
            &[0.0, 1.0, 2.0],
            &[0.0, 1.0, 0.5],
            1,
        );
        assert_eq!(c.sample(0.999), vec![0.0]);
        assert_eq!(c.sample(1.0), vec![1.0]);
        assert_eq!(c.sample(1.7), vec![1.0]);
        assert_eq!(c.sample(2.5), vec![0.5]);
    }

    #[test]
    fn rotations_slerp_at_constant_angular_speed() {
        // 0 to 90 degrees about +Y over one second: a quarter second is 22.5 degrees.
        let h = std::f32::consts::FRAC_1_SQRT_2;
        let c = channel(
            Target::Rotation,
            Interpolation::Linear,
            &[0.0, 1.0],
            &[0.0, 0.0, 0.0, 1.0, 0.0, h, 0.0, h],
            4,
        );
        let v = c.sample(0.25);
        let q = DQuat::from_xyzw(v[0], v[1], v[2], v[3]);
        let want = DQuat::from_rotation_y(22.5f64.to_radians());
        assert!(q.angle_between(want) < 1e-6, "{q:?} vs {want:?}");
        assert!((q.length() - 1.0).abs() < 1e-12);
    }

    #[test]
    fn cubic_splines_follow_the_hermite_curve() {
        // One component, keys (t=0, v=0, out-tangent 1) and (t=2, v=2, in-tangent 1): the
        // straight line v = t, which the Hermite basis reproduces exactly.
        let c = channel(
            Target::Weights,
            Interpolation::CubicSpline,
            &[0.0, 2.0],
            // key 0: in, value, out; key 1: in, value, out
            &[0.0, 0.0, 1.0, 1.0, 2.0, 0.0],
            1,
        );
        for t in [0.0, 0.5, 1.0, 1.5, 2.0] {
            assert!(
                (c.sample(t)[0] - t).abs() < 1e-12,
                "t {t}: {:?}",
                c.sample(t)
            );
        }
        // Zero tangents: smoothstep between the values, 0.5 at the midpoint and 0.15625
        // (3s² - 2s³ at s = 1/4) a quarter of the way.
        let c = channel(
            Target::Weights,
            Interpolation::CubicSpline,
            &[0.0, 1.0],
            &[0.0, 0.0, 0.0, 0.0, 1.0, 0.0],
            1,
        );
        assert!((c.sample(0.5)[0] - 0.5).abs() < 1e-12);
        assert!((c.sample(0.25)[0] - 0.15625).abs() < 1e-12);
    }

    #[test]
    fn bad_keys_are_refused() {
        let bad = |times: &[f32], values: &[f32], interpolation| {
            Channel {
                node: 0,
                target: Target::Weights,
                interpolation,
                times: times.to_vec(),
                values: values.to_vec(),
                width: 1,
            }
            .check()
        };
        assert_eq!(
            bad(&[], &[], Interpolation::Linear),
            Err(ChannelError::NoKeys)
        );
        assert_eq!(
            bad(&[1.0, 1.0], &[0.0, 1.0], Interpolation::Linear),
            Err(ChannelError::Times(1))
        );
        assert_eq!(
            bad(&[0.0, f32::NAN], &[0.0, 1.0], Interpolation::Linear),
            Err(ChannelError::Times(1))
        );
        assert!(matches!(
            bad(&[0.0, 1.0], &[0.0, 1.0], Interpolation::CubicSpline),
            Err(ChannelError::Count { .. })
        ));
        assert_eq!(
            bad(&[0.0], &[f32::INFINITY], Interpolation::Step),
            Err(ChannelError::NotFinite)
        );
    }

    #[test]
    fn later_channels_on_the_same_property_win_and_others_combine() {
        let mut a = channel(
            Target::Translation,
            Interpolation::Step,
            &[0.0],
            &[1.0, 0.0, 0.0],
            3,
        );
        let mut b = channel(
            Target::Translation,
            Interpolation::Step,
            &[0.0],
            &[2.0, 0.0, 0.0],
            3,
        );
        let s = channel(
            Target::Scale,
            Interpolation::Step,
            &[0.0],
            &[3.0, 3.0, 3.0],
            3,
        );
        a.node = 4;
        b.node = 4;
        let pose = Pose::sample(&[a, b, s], 0.0);
        assert_eq!(pose.nodes[&4].translation, Some(DVec3::new(2.0, 0.0, 0.0)));
        assert_eq!(pose.nodes[&0].scale, Some(DVec3::splat(3.0)));
    }
}

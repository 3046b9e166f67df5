//! `--ray-cache KEY=VALUE,...`: the ray-cache knobs of `dray render` and `dray submit`,
//! parsed into `JobSpec.ray_cache` (and `JobSpec.coarse_sampling`, the one knob that is
//! not a `RayCacheSettings` field).
//!
//! Only the syntax is checked here (known keys, a `=`, values of the right type), each
//! error one line naming the key; the ranges are the coordinator's to check, so the rules
//! live in one place (it answers INVALID_ARGUMENT naming `ray_cache.<field>`, which both
//! commands print as it is). Keys the flag leaves out keep the coordinator's defaults.

use dray_core::integrator::RayKind;
use dray_proto::v1::RayCacheSettings;

/// The flag's help, shared by `dray render` and `dray submit`.
pub fn help() -> String {
    format!(
        "Ray caches on domain walls (Little 2011): rays crossing a wall may \
be answered from radiance cached there instead of being traced (an approximation; the \
image is no longer exact). Comma-separated KEY=VALUE pairs: radius=R (lookup radius on the \
wall, scene units; 0, the default, never answers, the caches only fill), angle-deg=A \
(largest angle between a ray and a cached direction, degrees in (0, 90], default 10), \
retrieve=first|nearest|average (which cached ray answers, default nearest), coarse=N (a \
coarse pass of N x N camera rays, traced exactly first to fill the caches; default 0, \
none), kinds=K+K... (ray kinds looked up, joined with +, from {}; default all of them), \
fill=true|false (whether the main pass stores what it learns; default false with a coarse pass, which then fills the caches and they stay \
frozen, the same bits every run; true without one), \
placement=sender|remote (sender, the default: every worker holds a replica of every wall \
and looks rays up in its own memory, so a hit sends nothing; remote: each wall once, beside \
its domain's owner, every lookup a round trip), coarse-sampling=centres|random (where the \
coarse pass's rays cross their coarse pixels: the centre, the default, or a random point, \
as Little 2011 recommends; the same bits on any number of workers). `--ray-cache on` \
takes every default. \
Caches run on cache hosts: in every worker process (default) or stand-alone `dray cache` \
processes (which hold each wall once).",
        RayKind::help_list(&RayKind::RADIANCE)
    )
}

/// The keys, in the order the help gives them.
pub const KEYS: [&str; 8] = [
    "radius",
    "angle-deg",
    "retrieve",
    "coarse",
    "kinds",
    "fill",
    "placement",
    "coarse-sampling",
];

/// What `--ray-cache` sets: the job's `RayCacheSettings` and its `coarse_sampling`
/// (empty: the coordinator's default).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RayCacheFlag {
    pub settings: RayCacheSettings,
    pub coarse_sampling: String,
}

/// Parse `--ray-cache` into settings; errors name the key (clap prefixes the flag).
pub fn parse_ray_cache(s: &str) -> Result<RayCacheFlag, String> {
    let mut rc = RayCacheSettings::default();
    let mut coarse_sampling = String::new();
    for (key, value) in crate::kv_flag::pairs(s, &KEYS)? {
        let number = |what: &str| format!("{key}: {value:?} is not {what}");
        match key {
            "radius" => rc.radius = value.parse().map_err(|_| number("a number"))?,
            "angle-deg" => {
                rc.angle_deg = Some(value.parse().map_err(|_| number("a number of degrees"))?)
            }
            "retrieve" => {
                if value.is_empty() {
                    return Err(format!("{key}: empty (first, nearest or average)"));
                }
                rc.retrieve = value.to_string();
            }
            "coarse" => rc.coarse = value.parse().map_err(|_| number("a whole number"))?,
            "kinds" => rc.kinds = crate::kv_flag::kinds(key, value, &RayKind::RADIANCE)?,
            "fill" => {
                rc.fill = Some(match value {
                    "true" => true,
                    "false" => false,
                    _ => return Err(number("true or false")),
                })
            }
            "placement" => {
                if value.is_empty() {
                    return Err(format!("{key}: empty (sender or remote)"));
                }
                rc.placement = value.to_string();
            }
            "coarse-sampling" => {
                if value.is_empty() {
                    return Err(format!("{key}: empty (centres or random)"));
                }
                coarse_sampling = value.to_string();
            }
            other => {
                return Err(format!("unknown key {other:?} (keys: {})", KEYS.join(", ")));
            }
        }
    }
    Ok(RayCacheFlag {
        settings: rc,
        coarse_sampling,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pairs_and_defaults() {
        assert_eq!(parse_ray_cache("on"), Ok(RayCacheFlag::default()));
        assert_eq!(
            parse_ray_cache("radius=0.005").map(|f| f.settings),
            Ok(RayCacheSettings {
                radius: 0.005,
                ..Default::default()
            })
        );
        let all = parse_ray_cache(
            "radius=0.01, angle-deg=5,retrieve=average,coarse=0,kinds=camera+diffuse,fill=false,placement=remote,coarse-sampling=random",
        )
        .unwrap();
        assert_eq!(all.coarse_sampling, "random");
        assert_eq!(
            all.settings,
            RayCacheSettings {
                radius: 0.01,
                angle_deg: Some(5.0),
                retrieve: "average".into(),
                coarse: 0,
                kinds: "camera,diffuse".into(),
                fill: Some(false),
                placement: "remote".into(),
            }
        );
        // Ranges are the coordinator's to check: these parse.
        assert_eq!(parse_ray_cache("radius=-1").unwrap().settings.radius, -1.0);
        assert_eq!(
            parse_ray_cache("retrieve=best").unwrap().settings.retrieve,
            "best"
        );
        assert_eq!(
            parse_ray_cache("kinds=shadow").unwrap().settings.kinds,
            "shadow"
        );
        assert_eq!(
            parse_ray_cache("coarse-sampling=jitter")
                .unwrap()
                .coarse_sampling,
            "jitter"
        );
    }

    #[test]
    fn errors_name_the_key() {
        for (arg, want) in [
            ("radius=x", "radius: \"x\" is not a number"),
            ("angle-deg=ten", "angle-deg:"),
            ("coarse=-1", "coarse:"),
            ("coarse=1.5", "coarse:"),
            ("fill=yes", "fill: \"yes\" is not true or false"),
            ("kinds=camera+", "kinds:"),
            ("kinds=", "kinds:"),
            ("retrieve=", "retrieve:"),
            ("placement=", "placement:"),
            ("coarse-sampling=", "coarse-sampling:"),
            ("radius", "radius: missing =VALUE"),
            ("radius=1,radius=2", "radius: given twice"),
            ("radius=1,,fill=true", "an empty pair"),
            ("size=3", "unknown key \"size\""),
            ("kinds=camera,diffuse", "\"diffuse\" is not KEY=VALUE"),
            ("", "empty"),
            ("off", "\"off\" is not KEY=VALUE"),
        ] {
            let e = parse_ray_cache(arg).expect_err(arg);
            assert!(e.starts_with(want), "{arg:?}: {e:?}");
            assert!(!e.contains('\n'), "one line: {e:?}");
        }
    }
}

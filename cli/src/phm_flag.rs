//! `--phm KEY=VALUE,...`: the probability-hit-map knobs of `dray render` and
//! `dray submit`, parsed into `JobSpec.phm`.
//!
//! As for `--ray-cache`, only the syntax is checked here (known keys, a `=`, values of
//! the right type), each error one line naming the key; the ranges are the
//! coordinator's to check (INVALID_ARGUMENT naming `phm.<field>`). Keys left out keep
//! the coordinator's defaults.

use dray_core::integrator::RayKind;
use dray_proto::v1::PhmSettings;

/// The flag's help, shared by `dray render` and `dray submit`.
pub fn help() -> String {
    format!(
        "Probability hit maps on domain walls (Bolstad 2017): a ray \
entering a domain whose map predicts a miss skips it, and an occlusion ray whose map \
predicts a hit is occluded, without tracing (an approximation; the image is no longer \
exact); with shade=true, other rays at a predicted hit are answered with the mean radiance \
the cell's probes returned. Comma-separated KEY=VALUE pairs: res=N (texels per wall edge, 1..=64, default 4), \
dirs=N (direction bins over the hemisphere, 1..=256, default 12), prior=W (weight of the \
prior 0.5 in rays, default 100), miss=P and hit=P (thresholds, 0 <= miss <= 0.5 <= hit <= \
1, default 0.1 and 0.9; miss=0,hit=1 never decides: the exact image), \
mode=consistent|inconsistent (keep probing decided cells, or make decisions final; \
default consistent), reprobe=F (consistent mode: fraction of rays at decided cells traced \
anyway, default 0.1), kinds=K+K... (ray kinds that ask the maps, joined with +, from \
{}; default shadow), \
placement=sender|remote (sender: every worker holds a copy of every wall's map and \
consults it in its own process, and outcomes are merged into the other copies in \
batches; remote: each map once, beside its domain's owner, a round trip per ray; default \
the ray cache's placement, else sender), merge=N (sender placement: outcomes a worker \
gathers before merging them into the other copies, default 4096), shade=true|false (a \
predicted hit answers camera, reflection, refraction and diffuse rays of the given kinds \
with the mean radiance that probes entering there returned, Bolstad's averaged shading; \
needs placement=remote; default false). `--phm on` takes every default. Maps live on the cache hosts, beside the ray caches.",
        RayKind::help_list(&RayKind::ALL)
    )
}

/// The keys, in the order the help gives them.
pub const KEYS: [&str; 11] = [
    "res",
    "dirs",
    "prior",
    "miss",
    "hit",
    "mode",
    "reprobe",
    "kinds",
    "placement",
    "merge",
    "shade",
];

/// Parse `--phm` into settings; errors name the key (clap prefixes the flag).
pub fn parse_phm(s: &str) -> Result<PhmSettings, String> {
    let mut p = PhmSettings::default();
    for (key, value) in crate::kv_flag::pairs(s, &KEYS)? {
        let not = |what: &str| format!("{key}: {value:?} is not {what}");
        let whole = || value.parse::<u32>().map_err(|_| not("a whole number"));
        let number = || value.parse::<f32>().map_err(|_| not("a number"));
        match key {
            "res" => p.res = Some(whole()?),
            "dirs" => p.dirs = Some(whole()?),
            "prior" => p.prior = Some(number()?),
            "miss" => p.miss = Some(number()?),
            "hit" => p.hit = Some(number()?),
            "reprobe" => p.reprobe = Some(number()?),
            "merge" => p.merge = Some(whole()?),
            "shade" => p.shade = Some(value.parse::<bool>().map_err(|_| not("true or false"))?),
            "placement" => {
                if value.is_empty() {
                    return Err(format!("{key}: empty (sender or remote)"));
                }
                p.placement = value.to_string();
            }
            "mode" => {
                if value.is_empty() {
                    return Err(format!("{key}: empty (consistent or inconsistent)"));
                }
                p.mode = value.to_string();
            }
            "kinds" => p.kinds = crate::kv_flag::kinds(key, value, &RayKind::ALL)?,
            other => {
                return Err(format!("unknown key {other:?} (keys: {})", KEYS.join(", ")));
            }
        }
    }
    Ok(p)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pairs_and_defaults() {
        assert_eq!(parse_phm("on"), Ok(PhmSettings::default()));
        let all = parse_phm(
            "res=8,dirs=32,prior=50,miss=0.05,hit=0.95,mode=inconsistent,reprobe=0.2,kinds=shadow+camera,placement=remote,merge=100,shade=true",
        )
        .unwrap();
        assert_eq!(
            all,
            PhmSettings {
                res: Some(8),
                dirs: Some(32),
                prior: Some(50.0),
                miss: Some(0.05),
                hit: Some(0.95),
                mode: "inconsistent".into(),
                reprobe: Some(0.2),
                kinds: "shadow,camera".into(),
                placement: "remote".into(),
                merge: Some(100),
                shade: Some(true),
            }
        );
        // Ranges are the coordinator's to check: these parse.
        assert_eq!(parse_phm("miss=0.9").unwrap().miss, Some(0.9));
        assert_eq!(parse_phm("shade=false").unwrap().shade, Some(false));
        assert_eq!(parse_phm("on").unwrap().shade, None, "absent: off");
    }

    #[test]
    fn errors_name_the_key() {
        for (arg, want) in [
            ("res=x", "res: \"x\" is not a whole number"),
            ("dirs=-1", "dirs:"),
            ("prior=lots", "prior:"),
            ("hit=", "hit:"),
            ("mode=", "mode:"),
            ("placement=", "placement:"),
            ("merge=many", "merge:"),
            ("shade=yes", "shade: \"yes\" is not true or false"),
            ("shade=", "shade:"),
            ("kinds=shadow+", "kinds:"),
            ("miss", "miss: missing =VALUE"),
            ("res=1,res=2", "res: given twice"),
            ("size=3", "unknown key \"size\""),
            ("", "empty"),
        ] {
            let e = parse_phm(arg).expect_err(arg);
            assert!(e.starts_with(want), "{arg:?}: {e:?}");
            assert!(!e.contains('\n'), "one line: {e:?}");
        }
    }
}

//! The `KEY=VALUE,...` syntax shared by `--ray-cache` and `--phm`: `on` (every default),
//! or comma-separated pairs of known keys, each at most once. Each flag reads its own
//! values; this only splits, so both flags word their errors the same way.

use dray_core::integrator::RayKind;

/// The pairs of `s` (none for `on`), trimmed; errors are one line naming the key.
pub fn pairs<'a>(s: &'a str, keys: &[&str]) -> Result<Vec<(&'a str, &'a str)>, String> {
    let s = s.trim();
    if s == "on" {
        return Ok(Vec::new());
    }
    if s.is_empty() {
        return Err("empty (give KEY=VALUE pairs, or `on` for every default)".into());
    }
    let mut out: Vec<(&str, &str)> = Vec::new();
    for pair in s.split(',').map(str::trim) {
        let Some((key, value)) = pair.split_once('=') else {
            return Err(if pair.is_empty() {
                "an empty pair (two commas in a row?)".to_string()
            } else if keys.contains(&pair) {
                format!("{pair}: missing =VALUE")
            } else {
                format!(
                    "{pair:?} is not KEY=VALUE (keys: {}; join kinds with +, not ,)",
                    keys.join(", ")
                )
            });
        };
        let (key, value) = (key.trim(), value.trim());
        if !keys.contains(&key) {
            return Err(format!("unknown key {key:?} (keys: {})", keys.join(", ")));
        }
        if out.iter().any(|(k, _)| *k == key) {
            return Err(format!("{key}: given twice"));
        }
        out.push((key, value));
    }
    Ok(out)
}

/// A `kinds` value: names joined with `+`, written back joined with `,` (the JobSpec's
/// form); `choices` are the kinds the flag takes, listed in the error.
pub fn kinds(key: &str, value: &str, choices: &[RayKind]) -> Result<String, String> {
    if value.is_empty() || value.split('+').any(|k| k.trim().is_empty()) {
        return Err(format!(
            "{key}: {value:?} needs kind names joined with + ({})",
            RayKind::help_list(choices)
        ));
    }
    Ok(value
        .split('+')
        .map(str::trim)
        .collect::<Vec<_>>()
        .join(","))
}

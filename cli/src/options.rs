//! Parsing and checking of command-line values that clap cannot check alone.

use anyhow::{Context, Result, bail};
use dray_core::effects::{Effect, Effects};
use glam::Vec3;

/// Parse "R,G,B" (or a single value for grey) into finite, non-negative radiance.
pub fn parse_vec3(what: &str, s: &str) -> Result<Vec3> {
    let parts: Vec<&str> = s.split(',').map(str::trim).collect();
    let vals: Vec<f32> = parts
        .iter()
        .map(|p| {
            p.parse::<f32>()
                .with_context(|| format!("{what}: {p:?} is not a number"))
        })
        .collect::<Result<_>>()?;
    let v = match vals.as_slice() {
        [g] => Vec3::splat(*g),
        [x, y, z] => Vec3::new(*x, *y, *z),
        _ => bail!("{what}: expected R,G,B (three comma-separated numbers), got {s:?}"),
    };
    if !v.is_finite() {
        bail!("{what}: values must be finite, got {s:?}");
    }
    Ok(v)
}

/// Apply `--effects` overrides such as "+specular,-transmission" (a bare name means on).
pub fn apply_effects(mut fx: Effects, spec: &str) -> Result<Effects> {
    for item in spec.split(',').map(str::trim).filter(|s| !s.is_empty()) {
        let (on, name) = match item.as_bytes()[0] {
            b'+' => (true, &item[1..]),
            b'-' => (false, &item[1..]),
            _ => (true, item),
        };
        let Some(e) = Effect::from_name(name) else {
            let known: Vec<&str> = Effect::ALL.iter().map(|e| e.name()).collect();
            bail!(
                "--effects: unknown effect {name:?} (known: {})",
                known.join(", ")
            );
        };
        fx.set(e, on);
    }
    Ok(fx)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn vec3_and_effects() {
        assert_eq!(
            parse_vec3("--env", "1,2,3").unwrap(),
            Vec3::new(1.0, 2.0, 3.0)
        );
        assert_eq!(parse_vec3("--env", "0.5").unwrap(), Vec3::splat(0.5));
        assert!(parse_vec3("--env", "1,2").is_err());
        assert!(parse_vec3("--env", "a,b,c").is_err());
        assert!(parse_vec3("--env", "inf,0,0").is_err());
        let fx = apply_effects(Effects::NONE, "+specular,transmission,-specular").unwrap();
        assert_eq!(fx.names(), vec!["transmission"]);
        assert!(apply_effects(Effects::NONE, "+bogus").is_err());
    }
}

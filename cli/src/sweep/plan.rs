//! `dray sweep`'s plan: what `--vary` keys mean, the settings their values combine into,
//! and each setting's `dray render` (or `dray submit`) argument list.
//!
//! A setting is never described twice: its arguments are the sweep's own render flags
//! (the words the user typed, so every flag means what it means to `dray render`) with
//! the varied flags replaced, parsed by the very clap definitions `dray render` and
//! `dray submit` use. So every flag is accepted, defaulted and checked in one place, and
//! a bad value is found by parsing all settings before anything is rendered.

use anyhow::{Result, bail};
use clap::{Arg, ArgAction, CommandFactory, Parser};

use crate::render_cmd::RenderArgs;
use crate::submit_cmd::SubmitArgs;

/// The knobs of `--ray-cache`, as `ray-cache.<knob>` keys vary them.
pub const RAY_CACHE_KNOBS: [&str; 8] = crate::ray_cache_flag::KEYS;
/// The knobs of `--phm`, as `phm.<knob>` keys vary them.
pub const PHM_KNOBS: [&str; crate::phm_flag::KEYS.len()] = crate::phm_flag::KEYS;

/// Flags a sweep sets itself or that make no sense to vary: the files a render writes
/// (the sweep writes its own into `--out`), the whole `--ray-cache`/`--phm` values (their
/// knobs vary instead), and the image size (every setting is compared pixel by pixel with
/// the exact image).
const NOT_VARIED: [&str; 9] = [
    "output",
    "exr",
    "stats",
    "quiet",
    "help",
    "ray-cache",
    "phm",
    "width",
    "height",
];

/// `dray render`'s flags as a parser of their own, to parse a setting's arguments.
#[derive(Parser, Debug)]
#[command(name = "dray render", no_binary_name = true)]
pub struct RenderCli {
    #[command(flatten)]
    pub args: RenderArgs,
}

/// `dray submit`'s flags as a parser of their own, for sweeps on a coordinator.
#[derive(Parser, Debug)]
#[command(name = "dray submit", no_binary_name = true)]
pub struct SubmitCli {
    #[command(flatten)]
    pub args: SubmitArgs,
}

/// What a `--vary` key varies.
#[derive(Clone, Debug, PartialEq)]
pub enum Key {
    /// A knob of `--ray-cache`, folded into its value.
    RayCache(String),
    /// A knob of `--phm`, folded into its value.
    Phm(String),
    /// A render flag by long name; `switch` for flags that take no value (true/false).
    Flag { name: String, switch: bool },
}

/// One `--vary KEY=V1,V2,...`.
#[derive(Clone, Debug, PartialEq)]
pub struct Vary {
    /// The key as given (the CSV column's name).
    pub name: String,
    pub key: Key,
    pub values: Vec<String>,
}

/// One render flag as typed: `--name VALUE`, `--name=VALUE`, a switch, or a positional
/// (`long` None).
#[derive(Clone, Debug, PartialEq)]
pub struct Item {
    pub long: Option<String>,
    pub tokens: Vec<String>,
}

impl Item {
    fn flag(name: &str, value: Option<&str>) -> Item {
        let mut tokens = vec![format!("--{name}")];
        tokens.extend(value.map(str::to_string));
        Item {
            long: Some(name.to_string()),
            tokens,
        }
    }

    /// The value of a `--name VALUE` or `--name=VALUE` item.
    fn value(&self) -> Option<&str> {
        match self.tokens.as_slice() {
            [flag] => flag.split_once('=').map(|(_, v)| v),
            [_, v] => Some(v),
            _ => None,
        }
    }
}

/// Where the renders run.
#[derive(Clone, Debug, PartialEq)]
pub enum Target {
    /// In this process, as `dray render`.
    Embedded,
    /// On the coordinator at this address, as `dray submit --coordinator ADDR`.
    Coordinator(String),
}

/// A render's arguments, parsed by the command that will run it.
#[derive(Debug)]
pub enum Job {
    Render(Box<RenderArgs>),
    Submit(Box<SubmitArgs>),
}

impl Job {
    /// The flags that describe the image, whichever command runs it.
    pub fn flags(&self) -> &crate::job_flags::JobFlags {
        match self {
            Job::Render(a) => &a.job,
            Job::Submit(a) => &a.job,
        }
    }
}

/// One render of the sweep.
#[derive(Debug)]
pub struct Setting {
    /// "exact", or the varied keys and values: `ray-cache.radius=0.003 spp=4`.
    pub name: String,
    /// One value per `--vary`, in their order (the exact render's: the base value of a
    /// varied flag, empty for a knob).
    pub values: Vec<String>,
    /// The render's arguments, after the command name.
    pub tokens: Vec<String>,
    /// The image's file name in the output directory.
    pub file: String,
    pub job: Job,
}

/// The whole sweep: the exact render, then every combination of the varied values.
#[derive(Debug)]
pub struct Plan {
    pub varies: Vec<Vary>,
    /// The render flags as typed, without the sweep's own.
    pub base: Vec<String>,
    pub exact: Setting,
    pub settings: Vec<Setting>,
}

/// The sweep's own flags, removed from the render flags.
/// Flags of `dray sweep` itself (not render flags): never part of a setting.
const SWEEP_FLAGS: [&str; 9] = [
    "vary",
    "out",
    "coordinator",
    "repeat",
    "no-warmup",
    "auth-token-file",
    "tls-cert",
    "tls-key",
    "tls-ca",
];

/// Group `tokens` into flags and positionals, using `cmd`'s arguments to know which flags
/// take a value (a value is the next token even when it starts with `-`, as clap does for
/// flags that allow it, e.g. `--exposure -2`).
pub fn items(cmd: &clap::Command, tokens: &[String]) -> Vec<Item> {
    let mut out = Vec::new();
    let mut rest_positional = false;
    let mut i = 0;
    while i < tokens.len() {
        let t = &tokens[i];
        i += 1;
        if rest_positional || t == "-" || !t.starts_with('-') {
            out.push(Item {
                long: None,
                tokens: vec![t.clone()],
            });
            continue;
        }
        if t == "--" {
            rest_positional = true;
            out.push(Item {
                long: None,
                tokens: vec![t.clone()],
            });
            continue;
        }
        let (arg, attached): (Option<&Arg>, bool) = if let Some(long) = t.strip_prefix("--") {
            let name = long.split_once('=').map_or(long, |(n, _)| n);
            (
                cmd.get_arguments().find(|a| a.get_long() == Some(name)),
                long.contains('='),
            )
        } else {
            // A short flag, possibly with its value attached (-q, -xVALUE).
            let mut chars = t[1..].chars();
            let c = chars.next();
            (
                c.and_then(|c| cmd.get_arguments().find(|a| a.get_short() == Some(c))),
                chars.next().is_some(),
            )
        };
        let long = arg
            .and_then(|a| a.get_long())
            .map(str::to_string)
            .or_else(|| {
                t.strip_prefix("--")
                    .map(|l| l.split_once('=').map_or(l, |(n, _)| n).to_string())
            });
        let mut item = Item {
            long,
            tokens: vec![t.clone()],
        };
        if let Some(a) = arg
            && takes_value(a)
            && !attached
            && i < tokens.len()
        {
            item.tokens.push(tokens[i].clone());
            i += 1;
        }
        out.push(item);
    }
    out
}

fn takes_value(a: &Arg) -> bool {
    a.get_action().takes_values()
}

/// The render flags among the words after `dray sweep`: the sweep's own flags removed.
/// Flags naming output files are refused: the sweep writes its own into `--out`.
pub fn render_tokens(cmd: &clap::Command, tokens: &[String]) -> Result<Vec<String>> {
    let mut out = Vec::new();
    for item in items(cmd, tokens) {
        match item.long.as_deref() {
            Some(name) if SWEEP_FLAGS.contains(&name) => {}
            Some(name @ ("output" | "exr" | "stats")) => bail!(
                "--{name}: dray sweep writes its images and results into --out DIR (drop --{name})"
            ),
            _ => out.extend(item.tokens),
        }
    }
    Ok(out)
}

/// Split a `--vary` value list: commas, or semicolons when there are any (for values that
/// hold commas themselves, such as `env=1,1,1;0.5,0.5,0.5`).
fn split_values(list: &str) -> Vec<String> {
    let sep = if list.contains(';') { ';' } else { ',' };
    list.split(sep).map(|v| v.trim().to_string()).collect()
}

/// Parse one `--vary KEY=V1,V2,...`: the key must name a knob or a render flag, and the
/// list must hold values, none empty.
pub fn parse_vary(spec: &str, render: &clap::Command, target: &Target) -> Result<Vary> {
    let Some((name, list)) = spec.split_once('=') else {
        bail!("--vary {spec}: expected KEY=V1,V2,... (e.g. spp=1,4 or ray-cache.radius=0,0.01)");
    };
    let name = name.trim();
    let key = if let Some(knob) = name.strip_prefix("ray-cache.") {
        if !RAY_CACHE_KNOBS.contains(&knob) {
            bail!(
                "--vary {name}: unknown ray-cache knob {knob:?} (knobs: {})",
                RAY_CACHE_KNOBS.join(", ")
            );
        }
        Key::RayCache(knob.to_string())
    } else if let Some(knob) = name.strip_prefix("phm.") {
        if !PHM_KNOBS.contains(&knob) {
            bail!(
                "--vary {name}: unknown phm knob {knob:?} (knobs: {})",
                PHM_KNOBS.join(", ")
            );
        }
        Key::Phm(knob.to_string())
    } else if name == "ray-cache" || name == "phm" {
        bail!(
            "--vary {name}: vary its knobs instead, e.g. {name}.{}",
            if name == "phm" { "miss" } else { "radius" }
        );
    } else if NOT_VARIED.contains(&name) {
        bail!(
            "--vary {name}: cannot be varied (every setting keeps the exact render's image \
             size and writes its files into --out)"
        );
    } else {
        let Some(arg) = render
            .get_arguments()
            .find(|a| a.get_long() == Some(name) && !a.is_positional())
        else {
            bail!(
                "--vary {name}: unknown key (expected ray-cache.<knob>, phm.<knob> or a dray \
                 render flag such as spp, max-depth, workers)"
            );
        };
        if let Target::Coordinator(_) = target
            && !SubmitCli::command()
                .get_arguments()
                .any(|a| a.get_long() == Some(name))
        {
            bail!(
                "--vary {name}: only for renders in this process (with --coordinator, the \
                 cluster's workers run every job)"
            );
        }
        Key::Flag {
            name: name.to_string(),
            switch: !takes_value(arg),
        }
    };
    let values = split_values(list);
    if list.trim().is_empty() {
        bail!("--vary {name}: no values (expected {name}=V1,V2,...)");
    }
    if values.len() > MAX_SETTINGS {
        bail!(
            "--vary {name}: {} values, more than the {MAX_SETTINGS} settings one sweep renders",
            values.len()
        );
    }
    if values.iter().any(String::is_empty) {
        bail!("--vary {name}: an empty value in {list:?}");
    }
    if let Key::Flag { switch: true, .. } = key
        && let Some(v) = values.iter().find(|v| *v != "true" && *v != "false")
    {
        bail!("--vary {name}: {v:?} is not true or false (it is a switch)");
    }
    for (i, v) in values.iter().enumerate() {
        if values[..i].contains(v) {
            bail!("--vary {name}: {v:?} is given twice");
        }
    }
    Ok(Vary {
        name: name.to_string(),
        key,
        values,
    })
}

/// The most settings one sweep renders (the product of the `--vary` value counts).
pub const MAX_SETTINGS: usize = 1024;

/// The longest error text a sweep prints: values can be arbitrarily long input.
const MAX_ERROR_CHARS: usize = 400;

/// `text` cut to [`MAX_ERROR_CHARS`] characters, saying how long it was.
fn cut(text: &str) -> String {
    if text.chars().count() <= MAX_ERROR_CHARS {
        return text.to_string();
    }
    let head: String = text.chars().take(MAX_ERROR_CHARS).collect();
    format!("{head}... ({} bytes in all)", text.len())
}

/// Every combination of the varied values, the first `--vary` varying slowest.
pub fn combinations(varies: &[Vary]) -> Vec<Vec<String>> {
    let mut out: Vec<Vec<String>> = vec![Vec::new()];
    for v in varies {
        out = out
            .into_iter()
            .flat_map(|prefix| {
                v.values.iter().map(move |value| {
                    let mut c = prefix.clone();
                    c.push(value.clone());
                    c
                })
            })
            .collect();
    }
    out
}

/// A `KEY=VALUE,...` flag value (`--ray-cache`, `--phm`) with `knobs` set: existing keys
/// keep their place and take the new value, new keys follow. `on` (every default) is an
/// empty list.
pub fn merge_knobs(base: Option<&str>, knobs: &[(&str, &str)]) -> String {
    let mut pairs: Vec<(String, String)> = base
        .map(str::trim)
        .filter(|b| *b != "on" && !b.is_empty())
        .map(|b| {
            b.split(',')
                .map(|p| {
                    let (k, v) = p.split_once('=').unwrap_or((p, ""));
                    (k.trim().to_string(), v.trim().to_string())
                })
                .collect()
        })
        .unwrap_or_default();
    for (k, v) in knobs {
        match pairs.iter_mut().find(|(pk, _)| pk == k) {
            Some(p) => p.1 = v.to_string(),
            None => pairs.push((k.to_string(), v.to_string())),
        }
    }
    if pairs.is_empty() {
        return "on".into();
    }
    pairs
        .iter()
        .map(|(k, v)| format!("{k}={v}"))
        .collect::<Vec<_>>()
        .join(",")
}

/// The render arguments of one setting: `base` with the varied flags' occurrences
/// replaced by `values` (one per `varies`), and the varied knobs folded into `--ray-cache`
/// and `--phm`. `exact` drops `--ray-cache` and `--phm` altogether.
pub fn setting_tokens(
    cmd: &clap::Command,
    base: &[String],
    varies: &[Vary],
    values: &[String],
    exact: bool,
) -> Vec<String> {
    let base_items = items(cmd, base);
    let mut rc = Vec::new();
    let mut phm = Vec::new();
    let mut flags = Vec::new();
    for (v, value) in varies.iter().zip(values) {
        match &v.key {
            Key::RayCache(k) => rc.push((k.as_str(), value.as_str())),
            Key::Phm(k) => phm.push((k.as_str(), value.as_str())),
            Key::Flag { name, switch } => flags.push((name.as_str(), *switch, value.as_str())),
        }
    }
    let last_value = |name: &str| {
        base_items
            .iter()
            .rev()
            .find(|i| i.long.as_deref() == Some(name))
            .and_then(Item::value)
            .map(str::to_string)
    };
    let mut out: Vec<Item> = base_items
        .iter()
        .filter(|i| match i.long.as_deref() {
            Some(n @ ("ray-cache" | "phm")) => {
                !exact && (n != "ray-cache" || rc.is_empty()) && (n != "phm" || phm.is_empty())
            }
            Some(n) => !flags.iter().any(|(f, _, _)| *f == n),
            None => true,
        })
        .cloned()
        .collect();
    // Flags go before any `--`, after which everything is positional.
    let at = out
        .iter()
        .position(|i| i.long.is_none() && i.tokens == ["--"])
        .unwrap_or(out.len());
    let mut added = Vec::new();
    for (name, switch, value) in flags {
        if !switch {
            added.push(Item::flag(name, Some(value)));
        } else if value == "true" {
            added.push(Item::flag(name, None));
        }
    }
    if !exact {
        if !rc.is_empty() {
            let v = merge_knobs(last_value("ray-cache").as_deref(), &rc);
            added.push(Item::flag("ray-cache", Some(&v)));
        }
        if !phm.is_empty() {
            let v = merge_knobs(last_value("phm").as_deref(), &phm);
            added.push(Item::flag("phm", Some(&v)));
        }
    }
    out.splice(at..at, added);
    out.into_iter().flat_map(|i| i.tokens).collect()
}

/// The value a flag has among `base` (its last occurrence; "true"/"false" for a switch),
/// or clap's default for it.
pub fn base_value(cmd: &clap::Command, base: &[String], name: &str) -> String {
    let Some(arg) = cmd.get_arguments().find(|a| a.get_long() == Some(name)) else {
        return String::new();
    };
    let given = items(cmd, base)
        .into_iter()
        .rev()
        .find(|i| i.long.as_deref() == Some(name));
    if !takes_value(arg) {
        return matches!(arg.get_action(), ArgAction::SetTrue)
            .then(|| given.is_some().to_string())
            .unwrap_or_default();
    }
    match given.as_ref().and_then(Item::value) {
        Some(v) => v.to_string(),
        None => arg
            .get_default_values()
            .first()
            .map(|v| v.to_string_lossy().into_owned())
            .unwrap_or_default(),
    }
}

/// A file name for a setting: letters, digits, `.`, `-` and `_` only (`=` becomes `-`,
/// a space `_`), at most 100 characters.
pub fn file_stem(setting: &str) -> String {
    let s: String = setting
        .chars()
        .map(|c| match c {
            'a'..='z' | 'A'..='Z' | '0'..='9' | '.' | '-' | '_' => c,
            '=' => '-',
            '+' => 'p',
            _ => '_',
        })
        .take(100)
        .collect();
    let s = s.trim_start_matches('.').to_string();
    if s.is_empty() { "setting".into() } else { s }
}

/// clap's error as one line, without its `error: ` prefix.
fn clap_line(e: &clap::Error) -> String {
    let text = e.to_string();
    text.lines()
        .next()
        .unwrap_or("invalid arguments")
        .trim_start_matches("error: ")
        .to_string()
}

/// Parse and check one render's arguments as the command that will run them does, with
/// the checks `dray render` makes before rendering and the coordinator's knob checks, so
/// a bad value fails here rather than after hours of other settings.
pub fn check(tokens: &[String], target: &Target) -> Result<Job, String> {
    let render = RenderCli::try_parse_from(tokens)
        .map_err(|e| clap_line(&e))?
        .args;
    crate::render_cmd::check_args(&render).map_err(|e| one_line(&e))?;
    let job = match target {
        Target::Embedded => Job::Render(Box::new(render)),
        Target::Coordinator(addr) => {
            let mut t = tokens.to_vec();
            t.extend(["--coordinator".to_string(), addr.clone()]);
            let submit = SubmitCli::try_parse_from(&t)
                .map_err(|e| clap_line(&e))?
                .args;
            Job::Submit(Box::new(submit))
        }
    };
    let f = job.flags();
    let mut spec = f
        .job_spec(f.scene.clone(), 0, "", "")
        .map_err(|e| one_line(&e))?;
    dray_coordinator::validate::check_caches(&mut spec).map_err(|s| s.message().to_string())?;
    Ok(job)
}

fn one_line(e: &anyhow::Error) -> String {
    e.chain()
        .map(|c| c.to_string())
        .collect::<Vec<_>>()
        .join(": ")
}

impl Plan {
    /// The plan for the render flags `base` (as typed, the sweep's own removed) and the
    /// `--vary` specs: every key and value checked, alone and in combination, before
    /// anything renders. Errors are one line naming the key or the setting.
    pub fn new(base: Vec<String>, vary: &[String], target: &Target) -> Result<Plan> {
        Plan::checked(base, vary, target).map_err(|e| anyhow::anyhow!("{}", cut(&e.to_string())))
    }

    fn checked(base: Vec<String>, vary: &[String], target: &Target) -> Result<Plan> {
        let cmd = RenderCli::command();
        let mut varies: Vec<Vary> = Vec::new();
        for spec in vary {
            let v = parse_vary(spec, &cmd, target)?;
            if varies.iter().any(|o| o.name == v.name) {
                bail!("--vary {}: given twice (list its values once)", v.name);
            }
            varies.push(v);
        }
        // Counted before anything is made: 1000 values on each of two keys would start a
        // million renders.
        let count = varies
            .iter()
            .try_fold(1usize, |n, v| n.checked_mul(v.values.len()))
            .filter(|&n| n <= MAX_SETTINGS);
        if count.is_none() {
            let sizes: Vec<String> = varies
                .iter()
                .map(|v| format!("{} {}", v.values.len(), cut(&v.name)))
                .collect();
            bail!(
                "--vary: {} make more than {MAX_SETTINGS} settings, the most one sweep renders \
                 (split it into several sweeps)",
                sizes.join(" x ")
            );
        }
        let exact_tokens = setting_tokens(&cmd, &base, &[], &[], true);
        let job = check(&exact_tokens, target).map_err(|e| match target {
            Target::Embedded => anyhow::anyhow!("{e}"),
            Target::Coordinator(_) => anyhow::anyhow!("with --coordinator: {e}"),
        })?;
        let exact_values = varies
            .iter()
            .map(|v| match &v.key {
                Key::Flag { name, .. } => base_value(&cmd, &base, name),
                _ => String::new(),
            })
            .collect();
        let exact = Setting {
            name: "exact".into(),
            values: exact_values,
            tokens: exact_tokens,
            file: "exact.png".into(),
            job,
        };
        // Each value alone first, so an error names the key and the value.
        for v in &varies {
            for value in &v.values {
                let t = setting_tokens(
                    &cmd,
                    &base,
                    std::slice::from_ref(v),
                    std::slice::from_ref(value),
                    false,
                );
                check(&t, target).map_err(|e| anyhow::anyhow!("--vary {}={value}: {e}", v.name))?;
            }
        }
        let mut settings: Vec<Setting> = Vec::new();
        let mut files = vec!["exact".to_string()];
        for values in combinations(&varies) {
            let name = if varies.is_empty() {
                "base".to_string()
            } else {
                varies
                    .iter()
                    .zip(&values)
                    .map(|(v, value)| format!("{}={value}", v.name))
                    .collect::<Vec<_>>()
                    .join(" ")
            };
            let tokens = setting_tokens(&cmd, &base, &varies, &values, false);
            let job = check(&tokens, target).map_err(|e| anyhow::anyhow!("setting {name}: {e}"))?;
            let stem = file_stem(&name);
            let mut file = stem.clone();
            let mut n = 2;
            while files.contains(&file) {
                file = format!("{stem}_{n}");
                n += 1;
            }
            files.push(file.clone());
            settings.push(Setting {
                name,
                values,
                tokens,
                file: format!("{file}.png"),
                job,
            });
        }
        Ok(Plan {
            varies,
            base,
            exact,
            settings,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn s(v: &[&str]) -> Vec<String> {
        v.iter().map(|s| s.to_string()).collect()
    }

    fn cmd() -> clap::Command {
        RenderCli::command()
    }

    #[test]
    fn combinations_are_the_cartesian_product() {
        let r = cmd();
        let a = parse_vary("ray-cache.radius=0,0.2", &r, &Target::Embedded).unwrap();
        let b = parse_vary("spp=1,2,4", &r, &Target::Embedded).unwrap();
        let c = combinations(&[a, b]);
        assert_eq!(c.len(), 6);
        assert_eq!(c[0], s(&["0", "1"]));
        assert_eq!(c[1], s(&["0", "2"]));
        assert_eq!(c[3], s(&["0.2", "1"]));
        assert_eq!(c[5], s(&["0.2", "4"]));
        assert_eq!(combinations(&[]), vec![Vec::<String>::new()]);
    }

    #[test]
    fn keys_and_values() {
        let r = cmd();
        let e = Target::Embedded;
        let v = parse_vary("phm.miss=0.05,0.1", &r, &e).unwrap();
        assert_eq!(v.key, Key::Phm("miss".into()));
        let v = parse_vary("max-depth=1;2", &r, &e).unwrap();
        assert_eq!(
            v.key,
            Key::Flag {
                name: "max-depth".into(),
                switch: false
            }
        );
        assert_eq!(v.values, s(&["1", "2"]));
        let v = parse_vary("env=1,1,1;0.5", &r, &e).unwrap();
        assert_eq!(v.values, s(&["1,1,1", "0.5"]));
        let v = parse_vary("replicate=true,false", &r, &e).unwrap();
        assert!(matches!(v.key, Key::Flag { switch: true, .. }));
        for (spec, want) in [
            ("bogus=1", "--vary bogus: unknown key"),
            ("spp=", "--vary spp: no values"),
            ("spp", "--vary spp: expected KEY=V1,V2"),
            ("spp=1,,2", "--vary spp: an empty value"),
            ("spp=1,1", "--vary spp: \"1\" is given twice"),
            (
                "ray-cache.size=1",
                "--vary ray-cache.size: unknown ray-cache knob",
            ),
            ("phm.bogus=1", "--vary phm.bogus: unknown phm knob"),
            ("ray-cache=on", "--vary ray-cache: vary its knobs"),
            ("width=8,16", "--vary width: cannot be varied"),
            ("output=a.png", "--vary output: cannot be varied"),
            (
                "replicate=yes",
                "--vary replicate: \"yes\" is not true or false",
            ),
        ] {
            let err = parse_vary(spec, &r, &e).expect_err(spec).to_string();
            assert!(err.starts_with(want), "{spec}: {err}");
            assert!(!err.contains('\n'), "{err}");
        }
        let c = Target::Coordinator("127.0.0.1:1".into());
        let err = parse_vary("workers=1,2", &r, &c).unwrap_err().to_string();
        assert!(
            err.starts_with("--vary workers: only for renders in this process"),
            "{err}"
        );
        assert!(parse_vary("spp=1,2", &r, &c).is_ok());
    }

    #[test]
    fn knobs_merge_into_the_base_value() {
        assert_eq!(merge_knobs(None, &[("radius", "0.2")]), "radius=0.2");
        assert_eq!(merge_knobs(Some("on"), &[("radius", "0.2")]), "radius=0.2");
        assert_eq!(
            merge_knobs(
                Some("radius=0.1,kinds=camera"),
                &[("radius", "0.2"), ("fill", "false")]
            ),
            "radius=0.2,kinds=camera,fill=false"
        );
        assert_eq!(merge_knobs(Some("on"), &[]), "on");
    }

    #[test]
    fn setting_arguments_replace_the_varied_flags() {
        let r = cmd();
        let base = s(&[
            "cornell",
            "--spp=2",
            "--width",
            "32",
            "--ray-cache",
            "angle-deg=5",
            "-q",
            "--exposure",
            "-1",
        ]);
        let e = Target::Embedded;
        let varies = vec![
            parse_vary("ray-cache.radius=0,0.2", &r, &e).unwrap(),
            parse_vary("spp=1,4", &r, &e).unwrap(),
            parse_vary("replicate=true,false", &r, &e).unwrap(),
        ];
        let t = setting_tokens(&r, &base, &varies, &s(&["0.2", "4", "true"]), false);
        assert_eq!(
            t,
            s(&[
                "cornell",
                "--width",
                "32",
                "-q",
                "--exposure",
                "-1",
                "--spp",
                "4",
                "--replicate",
                "--ray-cache",
                "angle-deg=5,radius=0.2"
            ])
        );
        let t = setting_tokens(&r, &base, &varies, &s(&["0", "1", "false"]), false);
        assert!(!t.contains(&"--replicate".to_string()), "{t:?}");
        // The exact render: no caches, no maps, the base values.
        let t = setting_tokens(&r, &base, &[], &[], true);
        assert_eq!(
            t,
            s(&[
                "cornell",
                "--spp=2",
                "--width",
                "32",
                "-q",
                "--exposure",
                "-1"
            ])
        );
        assert_eq!(base_value(&r, &base, "spp"), "2");
        assert_eq!(base_value(&r, &base, "max-depth"), "5");
        assert_eq!(base_value(&r, &base, "replicate"), "false");
        // A base without --ray-cache gets one.
        let t = setting_tokens(&r, &s(&["cornell"]), &varies[..1], &s(&["0.2"]), false);
        assert_eq!(t, s(&["cornell", "--ray-cache", "radius=0.2"]));
    }

    #[test]
    fn plans_check_every_value_before_rendering() {
        let e = Target::Embedded;
        let base = s(&["cornell", "--width", "8", "--height", "8", "--workers", "2"]);
        let p = Plan::new(base.clone(), &s(&["ray-cache.radius=0,0.2", "spp=1,2"]), &e).unwrap();
        assert_eq!(p.exact.name, "exact");
        assert_eq!(p.exact.values, s(&["", "16"]));
        assert_eq!(p.settings.len(), 4);
        assert_eq!(p.settings[1].name, "ray-cache.radius=0 spp=2");
        assert_eq!(p.settings[1].file, "ray-cache.radius-0_spp-2.png");
        let Job::Render(a) = &p.settings[3].job else {
            panic!("embedded")
        };
        assert_eq!(a.job.spp, 2);
        assert_eq!(
            a.job.ray_cache.as_ref().map(|r| r.settings.radius),
            Some(0.2)
        );
        for (vary, want) in [
            (vec!["spp=1,0"], "--vary spp=0: --spp 0 is out of range"),
            (vec!["max-depth=x"], "--vary max-depth=x: invalid value 'x'"),
            (
                vec!["ray-cache.radius=-1"],
                "--vary ray-cache.radius=-1: ray_cache.radius must be",
            ),
            (
                vec!["ray-cache.retrieve=best"],
                "--vary ray-cache.retrieve=best: ray_cache.retrieve",
            ),
            (
                vec!["ray-cache.radius=x"],
                "--vary ray-cache.radius=x: invalid value",
            ),
            (vec!["spp=1", "spp=2"], "--vary spp: given twice"),
            (
                vec!["workers=0", "ray-cache.radius=0.1"],
                "setting workers=0 ray-cache.radius=0.1: --ray-cache needs worker actors",
            ),
        ] {
            let err = Plan::new(base.clone(), &s(&vary), &e)
                .expect_err(want)
                .to_string();
            assert!(err.starts_with(want), "{vary:?}: {err}");
            assert!(!err.contains('\n'), "{err}");
        }
        // No --vary: the base flags as one setting.
        let p = Plan::new(base, &[], &e).unwrap();
        assert_eq!(p.settings.len(), 1);
        assert_eq!(p.settings[0].name, "base");
    }

    #[test]
    fn sweep_flags_and_output_files_leave_the_render_flags() {
        let cmd = crate::sweep_cmd::SweepCli::command();
        let t = render_tokens(
            &cmd,
            &s(&[
                "cornell",
                "--vary",
                "spp=1,2",
                "--out=d",
                "--spp",
                "2",
                "--coordinator",
                "h:1",
            ]),
        )
        .unwrap();
        assert_eq!(t, s(&["cornell", "--spp", "2"]));
        let err = render_tokens(&cmd, &s(&["cornell", "--output", "x.png"])).unwrap_err();
        assert!(
            err.to_string().starts_with("--output: dray sweep writes"),
            "{err}"
        );
    }

    #[test]
    fn file_names() {
        assert_eq!(
            file_stem("ray-cache.radius=0.003 spp=4"),
            "ray-cache.radius-0.003_spp-4"
        );
        assert_eq!(
            file_stem("ray-cache.kinds=camera+diffuse"),
            "ray-cache.kinds-camerapdiffuse"
        );
        assert_eq!(file_stem("env=1,1,1"), "env-1_1_1");
        assert_eq!(file_stem("..//"), "__");
    }

    /// docs/security.md "Hardening, second round", item 12: a 1000 x 1000 `--vary` started
    /// a million renders, and a 100 KB
    /// value came back whole in the error.
    #[test]
    fn sweeps_are_capped_and_errors_cut() {
        let e = Target::Embedded;
        let list = |n: usize| (1..=n).map(|i| i.to_string()).collect::<Vec<_>>().join(",");
        let big = [
            format!("spp={}", list(1000)),
            format!("seed={}", list(1000)),
        ];
        let err = Plan::new(vec!["cornell".into()], &big, &e)
            .unwrap_err()
            .to_string();
        assert!(err.contains("more than 1024 settings"), "{err}");
        assert!(err.contains("1000 spp x 1000 seed"), "{err}");
        let one = [format!("seed={}", list(2_000_000))];
        let err = Plan::new(vec!["cornell".into()], &one, &e)
            .unwrap_err()
            .to_string();
        assert!(err.contains("2000000 values"), "{err}");
        // Within the cap it plans.
        let fine = [format!("spp={}", list(32)), format!("seed={}", list(32))];
        assert_eq!(
            Plan::new(vec!["cornell".into()], &fine, &e)
                .unwrap()
                .settings
                .len(),
            1024
        );
        // A 100 KB value is cut in the error.
        let long = [format!("spp={}", "9".repeat(100_000))];
        let err = Plan::new(vec!["cornell".into()], &long, &e)
            .unwrap_err()
            .to_string();
        assert!(err.len() < 600, "{} bytes: {}", err.len(), &err[..200]);
        assert!(err.contains("bytes in all"), "{err}");
    }
}

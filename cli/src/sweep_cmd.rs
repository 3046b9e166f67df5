//! `dray sweep`: price every knob. Render the exact image once (the render flags with ray
//! caches and hit maps off), then every combination of the `--vary` values, and write
//! what each costs in error for what it saves in time: `results.csv`, `table.md`,
//! `pareto.png` and every image, into `--out`.
//!
//! Every render is the one `dray render` (in this process) or `dray submit` (with
//! `--coordinator`) would make from the same flags: the settings' arguments are parsed by
//! those commands' own definitions (`crate::sweep::plan`), and rendered by their own code.
//! So a sweep measures exactly what a user would run, with one difference in this
//! process: the scene, the in-process actors, the package and the domains they built are
//! kept from one setting to the next (`crate::warm`), as a warm cluster's workers keep
//! theirs, so a setting's time is its own work, not a cold start's; the `domain_loads`
//! and `domains_warm` columns show it.

use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, anyhow};
use clap::{Args, CommandFactory, Parser};
use dray_core::display::Display;
use dray_core::exposure::Exposure;
use dray_proto::v1::ImageFormat;
use dray_proto::v1::render_service_client::RenderServiceClient;
use serde_json::Value;

use crate::render_cmd::RenderArgs;
use crate::submit_cmd;
use crate::sweep::metrics::{self, Picture};
use crate::sweep::pareto::{self, Point};
use crate::sweep::plan::{Job, Plan, Setting, Target};
use crate::sweep::report::{self, Row};
use crate::sweep::spread::Spread;
use crate::warm::WarmProcess;

/// The flag's long help.
const VARY_HELP: &str = "A knob to vary, with its values: KEY=V1,V2,... (semicolons \
instead of commas when values hold commas: env=1,1,1;0.5). Repeat for more knobs: every \
combination is rendered. KEY is ray-cache.<knob> (radius, angle-deg, retrieve, coarse, \
kinds, fill), folded into --ray-cache; phm.<knob> (res, dirs, prior, miss, hit, mode, \
reprobe, kinds), folded into --phm; or a dray render flag's long name without dashes \
(spp, max-depth, integrator, workers, schedule, ...), which replaces that flag. Switches \
take true,false.";

#[derive(Args, Debug)]
#[command(
    mut_arg("output", |a| a.hide(true)),
    mut_arg("exr", |a| a.hide(true)),
    mut_arg("stats", |a| a.hide(true))
)]
pub struct SweepArgs {
    /// The render flags: the exact render uses them with ray caches and hit maps off,
    /// every setting with its varied values.
    #[command(flatten)]
    pub render: RenderArgs,
    /// A knob to vary: KEY=V1,V2,... (ray-cache.<knob>, phm.<knob> or a render flag such
    /// as spp; --help says more).
    #[arg(long, value_name = "KEY=V1,V2,...", long_help = VARY_HELP)]
    #[arg(help_heading = crate::help_heading::SWEEP)]
    pub vary: Vec<String>,
    /// Directory for results.csv, table.md, pareto.png and the images (created if
    /// missing; files of the same names are replaced).
    #[arg(long, value_name = "DIR")]
    #[arg(help_heading = crate::help_heading::SWEEP)]
    pub out: PathBuf,
    /// Render every setting on this coordinator (host:port or http://host:port), as
    /// `dray submit` does, instead of in this process.
    #[arg(long, value_name = "ADDR")]
    #[arg(help_heading = crate::help_heading::SWEEP)]
    pub coordinator: Option<String>,
    /// Render every setting (the exact one included) N times, in N interleaved rounds,
    /// and report the median times: this machine's noise then moves every setting
    /// alike. Errors and statistics are those of the first round.
    #[arg(long, value_name = "N", default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=100))]
    #[arg(help_heading = crate::help_heading::SWEEP)]
    pub repeat: u32,
    /// Do not render the exact job once, unmeasured, before the sweep. Workers (a
    /// cluster's, or this process's, which the sweep keeps between settings) keep the
    /// last package's domains resident between jobs, so without the warm-up the first
    /// render alone would pay for loading them.
    #[arg(long)]
    #[arg(help_heading = crate::help_heading::SWEEP)]
    pub no_warmup: bool,
    /// With --coordinator: the API token to present.
    #[command(flatten, next_help_heading = crate::help_heading::SWEEP)]
    pub api_token: crate::net_flags::ApiTokenArgs,
    /// With --coordinator: TLS.
    #[command(flatten)]
    pub tls: crate::net_flags::TlsArgs,
}

/// The sweep's flags as a parser of their own: the plan groups the words typed after
/// `dray sweep` with it.
#[derive(Parser, Debug)]
#[command(name = "dray sweep", no_binary_name = true)]
pub struct SweepCli {
    #[command(flatten)]
    pub args: SweepArgs,
}

/// The words after `dray sweep`, as typed. The plan needs the words, not clap's parsed
/// values: a setting is the same words with the varied flags replaced, parsed again by
/// `dray render`'s definitions, so defaults and checks are never restated here.
fn words_after_sweep() -> Result<Vec<String>> {
    let args: Vec<String> = std::env::args_os()
        .skip(1)
        .map(|a| {
            a.into_string()
                .map_err(|a| anyhow!("argument {a:?} is not valid UTF-8"))
        })
        .collect::<Result<_>>()?;
    let at = args
        .iter()
        .position(|a| a == "sweep")
        .context("dray sweep: cannot find the sweep command among the arguments")?;
    Ok(args[at + 1..].to_vec())
}

pub fn run(a: SweepArgs) -> Result<()> {
    let words = words_after_sweep()?;
    let base = crate::sweep::plan::render_tokens(&SweepCli::command(), &words)?;
    let net = crate::net_flags::client_options(a.api_token.token()?, &a.tls)?;
    let target = match &a.coordinator {
        Some(addr) => Target::Coordinator(addr.clone()),
        None => Target::Embedded,
    };
    let plan = Plan::new(base, &a.vary, &target)?;
    let rounds = Rounds {
        repeat: a.repeat,
        warmup: !a.no_warmup,
    };
    sweep(&plan, &a.out, &target, &net, a.render.job.quiet, rounds)
}

/// How often every setting is rendered.
#[derive(Clone, Copy, Debug)]
struct Rounds {
    /// Interleaved rounds; times are medians over them.
    repeat: u32,
    /// Render the exact job once, unmeasured, first.
    warmup: bool,
}

/// The median of `v` (not empty).
fn median(v: &mut [f64]) -> f64 {
    v.sort_unstable_by(f64::total_cmp);
    let n = v.len();
    if n == 0 {
        0.0
    } else if n % 2 == 1 {
        v[n / 2]
    } else {
        (v[n / 2 - 1] + v[n / 2]) / 2.0
    }
}

/// What one render gives the sweep.
struct Output {
    picture: Picture,
    /// The render's `--stats` JSON.
    stats: Value,
    wall_s: f64,
    render_s: f64,
    /// CPU seconds of the processes that ran it ([`report::Row::cpu_s`]).
    cpu_s: f64,
}

impl Output {
    /// Every byte between processes: the stats' `traffic.total`.
    fn bytes_total(&self) -> u64 {
        self.stats["traffic"]["total"].as_u64().unwrap_or(0)
    }
}

/// Where the renders run: here (with what is kept between them), or on a coordinator
/// through one connection.
enum Renderer {
    Embedded(Box<WarmProcess>),
    Remote(Box<Remote>),
}

/// A connection to a coordinator, and the runtime it lives on.
struct Remote {
    rt: tokio::runtime::Runtime,
    client: RenderServiceClient<dray_net::AuthChannel>,
    url: String,
}

impl Renderer {
    fn new(plan: &Plan, target: &Target, net: &dray_net::ClientOptions) -> Result<Renderer> {
        match target {
            Target::Embedded => {
                // Cache hosts from the start when any setting has caches or maps, so the
                // exact render and the cached ones share one set of actors.
                let mut cache_hosts = false;
                for s in &plan.settings {
                    if let Job::Render(a) = &s.job {
                        cache_hosts |= crate::embedded::wants_cache_hosts(a)?;
                    }
                }
                Ok(Renderer::Embedded(Box::new(WarmProcess::new(cache_hosts))))
            }
            Target::Coordinator(addr) => {
                let url = net.url(addr);
                let rt = tokio::runtime::Builder::new_current_thread()
                    .enable_all()
                    .build()
                    .context("cannot start the async runtime")?;
                let client = rt.block_on(submit_cmd::connect(net, &url))?;
                Ok(Renderer::Remote(Box::new(Remote { rt, client, url })))
            }
        }
    }

    /// Render `s`, write its PNG to `png`; `label` names it on the progress bar.
    fn render(&mut self, s: &Setting, png: &Path, label: &str, show: bool) -> Result<Output> {
        match (self, &s.job) {
            (Renderer::Embedded(warm), Job::Render(a)) => render_here(a, png, label, show, warm),
            (Renderer::Remote(r), Job::Submit(a)) => {
                let Remote { rt, client, url } = &mut **r;
                let spec = submit_cmd::job_spec(a)?;
                let display = a.job.display();
                if show {
                    // `dray submit`'s progress view names the job, not the setting.
                    eprintln!("dray sweep: {label}");
                }
                let start = Instant::now();
                let (png_bytes, wall, exr_bytes, job) = rt.block_on(async {
                    let (id, _) = submit_cmd::run_job(
                        client,
                        spec,
                        url,
                        !show,
                        "dray sweep",
                        submit_cmd::RECONNECT_WAIT,
                        None,
                    )
                    .await?;
                    let png =
                        submit_cmd::fetch(client, &id, ImageFormat::Png, display, url).await?;
                    // The clock stops with the image in hand: the EXR and the statistics
                    // are fetched for the comparison, not part of the render.
                    let wall = start.elapsed();
                    let exr =
                        submit_cmd::fetch(client, &id, ImageFormat::Exr, display, url).await?;
                    let job = submit_cmd::get_job(client, &id, url).await?;
                    anyhow::Ok((png, wall, exr, job))
                })?;
                std::fs::write(png, &png_bytes)
                    .with_context(|| format!("cannot write {}", png.display()))?;
                let stats = serde_json::to_value(submit_cmd::SubmitStats::of(&job, url, wall))
                    .context("cannot encode statistics")?;
                Ok(Output {
                    picture: decode(&exr_bytes, metric_display(&a.job))?,
                    render_s: stats["job_time_s"].as_f64().unwrap_or(0.0),
                    cpu_s: job.stats.as_ref().map_or(0.0, |s| s.cpu_seconds),
                    stats,
                    wall_s: wall.as_secs_f64(),
                })
            }
            _ => Err(anyhow!(
                "internal error: a setting parsed for another target"
            )),
        }
    }
}

/// A render in this process, as `dray render` makes it, with a progress bar of its own.
fn render_here(
    a: &RenderArgs,
    png: &Path,
    label: &str,
    show: bool,
    warm: &mut WarmProcess,
) -> Result<Output> {
    // A spinner while the scene loads and the actors start, a bar once tiles are known.
    let bar = show.then(|| {
        let b = indicatif::ProgressBar::new_spinner();
        b.set_style(
            indicatif::ProgressStyle::with_template("{spinner} {prefix} starting {elapsed}")
                .unwrap_or_else(|_| indicatif::ProgressStyle::default_spinner()),
        );
        b.set_prefix(label.to_string());
        b.enable_steady_tick(Duration::from_millis(120));
        b
    });
    let tiles_known = std::sync::Once::new();
    // Every actor runs in this process: its CPU clock across the render is the render's
    // CPU, over the same span as its wall time.
    let cpu_before = dray_net::cpu::process_cpu_seconds();
    let progress = |done: usize, total: usize| {
        if let Some(b) = &bar {
            tiles_known.call_once(|| {
                b.set_style(
                    indicatif::ProgressStyle::with_template(
                        "{spinner} {prefix} [{bar:30}] {pos}/{len} tiles {elapsed}",
                    )
                    .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
                    .progress_chars("=> "),
                );
            });
            b.set_length(total as u64);
            b.set_position(done as u64);
        }
    };
    let r = crate::render_cmd::render_with(a, &progress, Some(warm));
    let cpu_s = dray_net::cpu::process_cpu_seconds() - cpu_before;
    if let Some(b) = &bar {
        b.finish_and_clear();
    }
    let r = r?;
    let spp = a.job.spp;
    a.job
        .display()
        .write(&r.film, spp, png)
        .with_context(|| format!("cannot write {}", png.display()))?;
    let linear = r.film.linear(spp);
    Ok(Output {
        picture: Picture::new(
            r.film.width,
            r.film.height,
            metric_display(&a.job).develop_linear(&linear).srgb8,
            linear.iter().flat_map(|v| v.to_array()).collect(),
        )?,
        stats: serde_json::to_value(&r.summary).context("cannot encode statistics")?,
        wall_s: r.summary.wall_time_s,
        render_s: r.summary.render_time_s,
        cpu_s,
    })
}

/// How the sweep's sRGB metrics (`rmse`, `flip`) see an image: at the fixed exposure
/// given (0 with `--exposure auto`) and no tone curve, as before dray had either. The
/// images written get the display transform a user asked for, but the metrics must not
/// change with it: every setting's automatic exposure differs from the exact image's by
/// a hair, which would count as error, and a curve changes what 1/255 means.
fn metric_display(job: &crate::job_flags::JobFlags) -> Display {
    match job.exposure {
        Exposure::Stops(ev) => Display::fixed(ev),
        Exposure::Auto => Display::fixed(0.0),
    }
}

/// The picture of the EXR (linear radiance) a coordinator sent, its sRGB through
/// `metric` as [`render_here`] makes it from the film (the EXR holds the film's linear
/// values exactly).
fn decode(exr: &[u8], metric: Display) -> Result<Picture> {
    use exr::prelude::{ReadChannels, ReadLayers};
    let (w, h, pixels) = exr::prelude::read()
        .no_deep_data()
        .largest_resolution_level()
        .rgba_channels(
            |size, _| {
                let (w, h) = (size.width(), size.height());
                (w, h, vec![glam::Vec3::ZERO; w * h])
            },
            |(w, _, px): &mut (usize, usize, Vec<glam::Vec3>),
             pos,
             (r, g, b, _): (f32, f32, f32, f32)| {
                px[pos.y() * *w + pos.x()] = glam::Vec3::new(r, g, b);
            },
        )
        .first_valid_layer()
        .all_attributes()
        .from_buffered(std::io::Cursor::new(exr))
        .context("cannot decode the EXR the coordinator sent")?
        .layer_data
        .channel_data
        .pixels;
    let size = |n: usize| u32::try_from(n).context("the EXR the coordinator sent is too large");
    Picture::new(
        size(w)?,
        size(h)?,
        metric.develop_linear(&pixels).srgb8,
        pixels.iter().flat_map(|v| v.to_array()).collect(),
    )
}

/// A word as a shell would need it: quoted when it holds anything but plain characters.
fn shell_word(w: &str) -> String {
    if !w.is_empty()
        && w.chars()
            .all(|c| c.is_ascii_alphanumeric() || "-_=.,:/+@%".contains(c))
    {
        w.to_string()
    } else {
        format!("'{}'", w.replace('\'', "'\\''"))
    }
}

/// Words joined as a shell command line.
fn shell_line(words: &[String]) -> String {
    words
        .iter()
        .map(|w| shell_word(w))
        .collect::<Vec<_>>()
        .join(" ")
}

/// Render the plan and write the results; on a failed render, what was measured so far is
/// still written before the error is returned.
/// One row of the results: setting `s` rendered as `o`, with its errors against the
/// exact image.
fn row(s: &Setting, o: &Output, errors: metrics::Errors) -> Row {
    Row {
        setting: s.name.clone(),
        values: s.values.clone(),
        wall_s: o.wall_s,
        render_s: o.render_s,
        cpu_s: o.cpu_s,
        bytes_total: o.bytes_total(),
        stats: o.stats.clone(),
        spread: Spread::first(o.render_s, o.bytes_total(), &errors),
        errors,
        image: s.file.clone(),
        args: shell_line(&s.tokens),
    }
}

/// What the sweep's loop shares: the renderer, where images go, how to label a render.
struct Sweeper<'a> {
    renderer: Renderer,
    /// The first round's exact image, which every later round's renders are compared
    /// with (the spread of their errors).
    exact: Option<Picture>,
    out: &'a Path,
    total: usize,
    show: bool,
    quiet: bool,
}

impl Sweeper<'_> {
    fn label(&self, i: usize, s: &Setting) -> String {
        format!("[{}/{}] {}", i + 1, self.total, s.name)
    }

    /// The exact render once, not measured, so that the first measured render does not
    /// pay for cold caches and loads.
    fn warm_up(&mut self, exact: &Setting) -> Result<()> {
        let png = self.out.join(format!("warmup-{}", exact.file));
        let o = self
            .renderer
            .render(exact, &png, "warm-up (exact, not measured)", self.show)
            .context("the warm-up render")?;
        let _ = std::fs::remove_file(&png);
        if !self.quiet {
            eprintln!(
                "dray sweep: warm-up (exact, not measured): wall {:.3} s",
                o.wall_s
            );
        }
        Ok(())
    }

    /// The first round: the exact render, then every setting against it. A failed
    /// setting ends the round; the rows before it are kept and the error returned beside
    /// them.
    fn first_round(&mut self, plan: &Plan) -> Result<(Vec<Row>, Option<anyhow::Error>)> {
        let label = self.label(0, &plan.exact);
        let exact = self
            .renderer
            .render(
                &plan.exact,
                &self.out.join(&plan.exact.file),
                &label,
                self.show,
            )
            .context("the exact render")?;
        if !self.quiet {
            eprintln!("dray sweep: {label}: wall {:.3} s", exact.wall_s);
        }
        let mut rows = vec![row(
            &plan.exact,
            &exact,
            metrics::compare(&exact.picture, &exact.picture)?,
        )];
        for (i, s) in plan.settings.iter().enumerate() {
            let label = self.label(i + 1, s);
            let result = self
                .renderer
                .render(s, &self.out.join(&s.file), &label, self.show)
                .and_then(|o| {
                    let errors = metrics::compare(&exact.picture, &o.picture)?;
                    Ok((o, errors))
                });
            let (o, errors) = match result {
                Ok(r) => r,
                Err(e) => return Ok((rows, Some(e.context(format!("setting {}", s.name))))),
            };
            if !self.quiet {
                eprintln!(
                    "dray sweep: {label}: wall {:.3} s ({:.2}x), rmse {:.5}, flip {:.5}",
                    o.wall_s,
                    report::speedup(exact.wall_s, o.wall_s),
                    errors.rmse,
                    errors.flip
                );
            }
            rows.push(row(s, &o, errors));
        }
        self.exact = Some(exact.picture);
        Ok((rows, None))
    }

    /// More rounds, interleaved: each row's times become the medians over the rounds,
    /// its bytes too (rounded: counts are whole); its spread takes in every round's
    /// time, bytes and error against the first round's exact image.
    fn more_rounds(&mut self, plan: &Plan, rows: &mut [Row], repeat: u32) -> Option<anyhow::Error> {
        let mut walls: Vec<Vec<f64>> = rows.iter().map(|r| vec![r.wall_s]).collect();
        let mut renders: Vec<Vec<f64>> = rows.iter().map(|r| vec![r.render_s]).collect();
        let mut cpus: Vec<Vec<f64>> = rows.iter().map(|r| vec![r.cpu_s]).collect();
        let mut bytes: Vec<Vec<f64>> = rows.iter().map(|r| vec![r.bytes_total as f64]).collect();
        let all: Vec<&Setting> = std::iter::once(&plan.exact)
            .chain(plan.settings.iter())
            .collect();
        let mut failure = None;
        'rounds: for round in 2..=repeat {
            for (i, s) in all.iter().enumerate() {
                let png = self.out.join(format!("round-{}", s.file));
                let what = format!("{} (round {round}/{repeat})", self.label(i, s));
                match self.renderer.render(s, &png, &what, self.show) {
                    Ok(o) => {
                        if let Some(exact) = &self.exact {
                            match metrics::compare(exact, &o.picture) {
                                Ok(errors) => {
                                    rows[i].spread.add(o.render_s, o.bytes_total(), &errors)
                                }
                                Err(e) => {
                                    failure = Some(
                                        e.context(format!("setting {} in round {round}", s.name)),
                                    );
                                    break 'rounds;
                                }
                            }
                        }
                        walls[i].push(o.wall_s);
                        renders[i].push(o.render_s);
                        cpus[i].push(o.cpu_s);
                        bytes[i].push(o.bytes_total() as f64);
                        if !self.quiet {
                            eprintln!("dray sweep: {what}: wall {:.3} s", o.wall_s);
                        }
                    }
                    Err(e) => {
                        failure = Some(e.context(format!("setting {} in round {round}", s.name)));
                        break 'rounds;
                    }
                }
                let _ = std::fs::remove_file(&png);
            }
        }
        for (i, row) in rows.iter_mut().enumerate() {
            row.wall_s = median(&mut walls[i]);
            row.render_s = median(&mut renders[i]);
            row.cpu_s = median(&mut cpus[i]);
            row.bytes_total = median(&mut bytes[i]).round() as u64;
        }
        failure
    }
}

/// results.csv, table.md and pareto.png in `out`; their paths.
fn write_results(
    plan: &Plan,
    out: &Path,
    rows: &[Row],
    repeat: u32,
) -> Result<[std::path::PathBuf; 3]> {
    let names: Vec<String> = rows.iter().map(|r| r.setting.clone()).collect();
    let points: Vec<Point> = rows
        .iter()
        .zip(pareto::labels(&names))
        .map(|(r, label)| Point {
            label,
            wall_s: r.wall_s,
            error: r.errors.flip,
        })
        .collect();
    let front = pareto::front(&points);
    let keys: Vec<String> = plan.varies.iter().map(|v| v.name.clone()).collect();
    let csv = out.join("results.csv");
    std::fs::write(&csv, report::csv(&keys, rows, &front))
        .with_context(|| format!("cannot write {}", csv.display()))?;
    let table = out.join("table.md");
    let base = shell_line(&plan.base);
    std::fs::write(
        &table,
        report::table(&plan.exact.job.flags().scene, &base, rows, &front, repeat),
    )
    .with_context(|| format!("cannot write {}", table.display()))?;
    let font = pareto::find_font();
    if font.is_none() {
        eprintln!(
            "dray sweep: no TrueType font found (set DRAY_FONT to a .ttf file); pareto.png \
             has no text"
        );
    }
    let plot = out.join("pareto.png");
    pareto::draw(&points, font, &plot)?;
    Ok([csv, table, plot])
}

fn sweep(
    plan: &Plan,
    out: &Path,
    target: &Target,
    net: &dray_net::ClientOptions,
    quiet: bool,
    rounds: Rounds,
) -> Result<()> {
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    let mut sweeper = Sweeper {
        renderer: Renderer::new(plan, target, net)?,
        exact: None,
        out,
        total: plan.settings.len() + 1,
        show: !quiet && std::io::stderr().is_terminal(),
        quiet,
    };
    if rounds.warmup {
        sweeper.warm_up(&plan.exact)?;
    }
    let (mut rows, mut failure) = sweeper.first_round(plan)?;
    if failure.is_none() && rounds.repeat > 1 {
        failure = sweeper.more_rounds(plan, &mut rows, rounds.repeat);
    }
    let [csv, table, plot] = write_results(plan, out, &rows, rounds.repeat)?;
    if let Some(e) = failure {
        let chain: Vec<String> = e.chain().map(|c| c.to_string()).collect();
        return Err(anyhow!(
            "{} (the results of the {} renders before it are in {})",
            chain.join(": "),
            rows.len(),
            out.display()
        ));
    }
    if !quiet {
        eprintln!(
            "dray sweep: wrote {}, {}, {} and {} images ({}, ...) in {}",
            csv.display(),
            table.display(),
            plot.display(),
            rows.len(),
            plan.exact.file,
            out.display()
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn medians() {
        assert_eq!(median(&mut [3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(&mut [4.0, 1.0, 2.0, 3.0]), 2.5);
        assert_eq!(median(&mut [5.0]), 5.0);
    }

    #[test]
    fn shell_words() {
        assert_eq!(shell_word("--spp"), "--spp");
        assert_eq!(
            shell_word("radius=0.1,kinds=camera+diffuse"),
            "radius=0.1,kinds=camera+diffuse"
        );
        assert_eq!(shell_word("a b"), "'a b'");
        assert_eq!(shell_word("it's"), "'it'\\''s'");
        assert_eq!(shell_word(""), "''");
    }

    #[test]
    fn decodes_what_a_coordinator_sends() {
        // A 2x1 film written as `dray submit` would receive it.
        let mut film = dray_core::film::Film::new(2, 1);
        film.add(0, glam::Vec3::new(0.25, 0.5, 2.0));
        let dir = std::env::temp_dir().join(format!("dray-sweep-decode-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        film.write_exr(&dir.join("a.exr"), 1).unwrap();
        let exr = std::fs::read(dir.join("a.exr")).unwrap();
        let p = decode(&exr, Display::fixed(0.0)).unwrap();
        assert_eq!((p.width, p.height), (2, 1));
        // The metrics' sRGB is the old fixed encoding of the film, exactly.
        assert_eq!(p.srgb8, film.srgb8(1, 1.0));
        let p = decode(&exr, Display::fixed(-1.0)).unwrap();
        assert_eq!(p.srgb8, film.srgb8(1, 0.5));
        let want: Vec<f32> = film.linear(1).iter().flat_map(|v| v.to_array()).collect();
        assert_eq!(p.linear, want);
        let _ = std::fs::remove_dir_all(&dir);
    }
}

//! `--frames A..B[:STEP] --fps N`: one image per frame, frame f at f / fps seconds.
//!
//! `dray render --frames` renders the frames one after another in this process, each
//! exactly as `dray render --time f/fps` would (so each frame is the same bits as that
//! command). The in-process coordinator and workers are kept from frame to frame
//! (`crate::warm`), as a cluster's are: each frame's scene is loaded and posed, the
//! coordinator cuts it with the last frame's layout when its bounds are the same, and
//! the domains no moving mesh touches keep their content
//! (`MemoryPackages::cut`), so the workers find them and their BVHs resident; only the
//! domains a moving mesh touches are built again. Each frame's `--stats` counts them
//! (`domain_loads`, `domains_warm`).
//! `dray submit --frames` sends one spec with `frames` and `fps`; the coordinator makes
//! it a job group, one ordinary job per frame (`JobSpec.frames`, `Job.group`), and this
//! follows the frames' jobs in order, writing each frame's image as it is done.
//!
//! Output names: [`frame_path`].

use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{Context, Result, anyhow, bail};
use dray_core::display::Display;
use dray_core::frames::{FrameRange, frame_time};
use dray_proto::v1::{ImageFormat, JobSpec, JobState, SubmitJobRequest};

use crate::render_cmd::RenderArgs;
use crate::submit_cmd::{Reconnect, SubmitArgs, SubmitStats};

/// Frame digits when the name has no run of `#` to say how many.
const DEFAULT_DIGITS: usize = 4;

/// The file of `frame` for the name `pattern`: the last run of `#` in its file name
/// becomes the frame number zero-padded to the run's length (`out.####.png` and frame 1:
/// `out.0001.png`; a longer number is written whole); a name without `#` gets
/// `.NNNN` before its extension (`out.png`: `out.0001.png`; `out`: `out.0001`).
pub fn frame_path(pattern: &Path, frame: u32) -> PathBuf {
    let Some(name) = pattern.file_name().and_then(|n| n.to_str()) else {
        return pattern.to_path_buf();
    };
    let new = match name.rfind('#') {
        Some(last) => {
            let first = name[..=last].trim_end_matches('#').len();
            let width = last + 1 - first;
            format!("{}{frame:0width$}{}", &name[..first], &name[last + 1..])
        }
        None => match name.rfind('.').filter(|&i| i > 0) {
            Some(dot) => format!("{}.{frame:0DEFAULT_DIGITS$}{}", &name[..dot], &name[dot..]),
            None => format!("{name}.{frame:0DEFAULT_DIGITS$}"),
        },
    };
    pattern.with_file_name(new)
}

/// `dray render --frames`: each frame rendered and written as `dray render --time`.
pub fn render_frames(mut a: RenderArgs) -> Result<()> {
    let Some(range) = a.job.anim.frames.take() else {
        bail!("--frames: no frame range");
    };
    let fps = a
        .job
        .anim
        .fps
        .take()
        .ok_or_else(|| anyhow!("--frames needs --fps"))?;
    let (output, exr, stats) = (a.job.output.clone(), a.job.exr.clone(), a.stats.clone());
    let _span = tracing::info_span!("frames", frames = range.len(), fps).entered();
    // A traffic trace records one render: such a run starts its actors per frame.
    let mut warm = a
        .trace_out
        .is_none()
        .then(|| crate::warm::WarmProcess::new(false));
    for frame in range.frames() {
        a.job.anim.time = Some(frame_time(frame, fps));
        a.job.output = frame_path(&output, frame);
        a.job.exr = exr.as_deref().map(|p| frame_path(p, frame));
        a.stats = stats.as_deref().map(|p| frame_path(p, frame));
        if !a.job.quiet {
            eprintln!(
                "dray render: frame {frame} ({} of {}) at {} s",
                (frame - range.start) / range.step + 1,
                range.len(),
                frame_time(frame, fps)
            );
        }
        crate::render_cmd::run_one_with(&a, warm.as_mut())
            .with_context(|| format!("frame {frame}"))?;
    }
    Ok(())
}

/// `dray submit --frames`: submit the group, then follow its jobs in frame order and
/// write each frame's PNG (and EXR, and statistics) under its frame's name. Ctrl-C
/// cancels every frame's job.
pub async fn submit_frames(
    a: SubmitArgs,
    spec: JobSpec,
    url: String,
    range: FrameRange,
) -> Result<()> {
    if a.preview.is_some() {
        bail!("--preview: not with --frames (each frame's job has its own image)");
    }
    let started = std::time::Instant::now();
    let net = crate::net_flags::client_options(a.api_token.token()?, &a.tls)?;
    let url = net.url(&url);
    let mut client = crate::submit_cmd::connect(&net, &url).await?;
    let response = client
        .submit_job(SubmitJobRequest { spec: Some(spec) })
        .await
        .map_err(|s| crate::submit_cmd::rpc_error("SubmitJob", &url, s))?
        .into_inner();
    let ids = response.job_ids;
    if ids.len() != range.len() as usize {
        bail!(
            "the coordinator made {} jobs of the {} frames {}..{}:{} (is it older than \
             job groups?)",
            ids.len(),
            range.len(),
            range.start,
            range.end,
            range.step
        );
    }
    if !a.job.quiet {
        eprintln!(
            "dray submit: job group {} of {} frames accepted by {url}",
            response.group_id,
            ids.len()
        );
    }
    let follow = follow_frames(&a, client.clone(), &url, range, &ids, started);
    tokio::select! {
        r = follow => r,
        _ = tokio::signal::ctrl_c() => {
            for id in &ids {
                crate::submit_cmd::cancel(&mut client.clone(), id).await;
            }
            bail!("interrupted: the job group {}'s jobs cancelled", response.group_id)
        }
    }
}

async fn follow_frames(
    a: &SubmitArgs,
    mut client: dray_proto::v1::render_service_client::RenderServiceClient<dray_net::AuthChannel>,
    url: &str,
    range: FrameRange,
    ids: &[String],
    started: std::time::Instant,
) -> Result<()> {
    let again = Reconnect {
        who: "dray submit",
        wait: Duration::from_secs(a.reconnect_wait),
    };
    for (frame, id) in range.frames().zip(ids) {
        let last = crate::submit_cmd::watch(
            client.clone(),
            id,
            url,
            a.job.quiet,
            Reconnect {
                who: "dray submit",
                wait: again.wait,
            },
        )
        .await?;
        match last.state() {
            JobState::Succeeded => {}
            JobState::Failed => bail!(
                "frame {frame} (job {id}) failed: {}",
                last.error.replace('\n', " ")
            ),
            other => bail!(
                "frame {frame} (job {id}) ended {}",
                other.as_str_name().trim_start_matches("JOB_STATE_")
            ),
        }
        let png = crate::submit_cmd::across_restarts(url, &again, "GetImage", || {
            crate::submit_cmd::image(client.clone(), id, ImageFormat::Png, a.job.display())
        })
        .await?;
        let path = frame_path(&a.job.output, frame);
        std::fs::write(&path, &png).with_context(|| format!("cannot write {}", path.display()))?;
        if let Some(exr) = &a.job.exr {
            let data = crate::submit_cmd::across_restarts(url, &again, "GetImage", || {
                crate::submit_cmd::image(client.clone(), id, ImageFormat::Exr, Display::default())
            })
            .await?;
            let p = frame_path(exr, frame);
            std::fs::write(&p, &data).with_context(|| format!("cannot write {}", p.display()))?;
        }
        if let Some(stats) = &a.stats {
            let job = crate::submit_cmd::get_job(&mut client, id, url).await?;
            let json = serde_json::to_string_pretty(&SubmitStats::of(&job, url, started.elapsed()))
                .context("cannot encode statistics")?;
            let p = frame_path(stats, frame);
            std::fs::write(&p, json + "\n")
                .with_context(|| format!("cannot write {}", p.display()))?;
        }
        if !a.job.quiet {
            eprintln!(
                "dray submit: frame {frame} (job {id}) done, {} rays traced; wrote {}",
                last.rays_traced,
                path.display()
            );
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_run_of_hashes_is_the_zero_padded_frame() {
        let p = |s: &str, f: u32| frame_path(Path::new(s), f).to_string_lossy().into_owned();
        assert_eq!(p("out.####.png", 1), "out.0001.png");
        assert_eq!(p("dir/shot_##.png", 7), "dir/shot_07.png");
        assert_eq!(p("a#b.##.png", 123), "a#b.123.png");
        assert_eq!(p("out.png", 12), "out.0012.png");
        assert_eq!(p("frames/out", 3), "frames/out.0003");
        assert_eq!(p(".hidden", 3), ".hidden.0003");
    }
}

//! `dray submit --preview FILE`: the running job's image, rewritten as each progressive
//! pass lands (WatchImage). The file is replaced atomically (written beside it, then
//! renamed), so a viewer that reloads it never reads half a PNG.

use std::path::{Path, PathBuf};

use dray_core::display::Display;
use dray_net::AuthChannel;
use dray_proto::v1::render_service_client::RenderServiceClient;
use dray_proto::v1::{ImageFormat, WatchImageRequest};

/// Follow job `id`'s images into `path` until the job ends or the task is aborted. A
/// failure (the stream broke, the file cannot be written) is said once and ends the
/// preview; the job goes on.
pub fn spawn(
    mut client: RenderServiceClient<AuthChannel>,
    id: String,
    path: PathBuf,
    display: Display,
    quiet: bool,
) -> tokio::task::JoinHandle<()> {
    tokio::spawn(async move {
        let (exposure, tonemap) = crate::submit_cmd::wire_display(display);
        let req = WatchImageRequest {
            job_id: id,
            format: ImageFormat::Png as i32,
            exposure,
            tonemap,
            min_interval: None,
        };
        let mut stream = match client.watch_image(req).await {
            Ok(s) => s.into_inner(),
            Err(e) => {
                eprintln!(
                    "dray submit: no preview: WatchImage failed: {}",
                    e.message()
                );
                return;
            }
        };
        loop {
            match stream.message().await {
                Ok(Some(img)) => {
                    if let Err(e) = replace(&path, &img.data) {
                        eprintln!("dray submit: no more preview: {e}");
                        return;
                    }
                    if !quiet && !img.r#final {
                        eprintln!(
                            "dray submit: preview {} ({} of {} passes, {} spp)",
                            path.display(),
                            img.passes_done,
                            img.passes_total,
                            img.samples
                        );
                    }
                }
                Ok(None) => return,
                // The job failed or was cancelled (the main watch says so), or the
                // coordinator went away.
                Err(_) => return,
            }
        }
    })
}

/// Write `data` to `path` through a temporary file beside it.
fn replace(path: &Path, data: &[u8]) -> Result<(), String> {
    let mut tmp = path.as_os_str().to_owned();
    tmp.push(".part");
    let tmp = PathBuf::from(tmp);
    std::fs::write(&tmp, data).map_err(|e| format!("cannot write {}: {e}", tmp.display()))?;
    std::fs::rename(&tmp, path)
        .map_err(|e| format!("cannot move {} to {}: {e}", tmp.display(), path.display()))
}

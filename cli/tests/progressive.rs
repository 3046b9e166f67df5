//! Progressive jobs and the cluster listing on a real `dray cluster --workers 2`: a
//! running job's image can be fetched (GetImage on RUNNING, WatchImage pushing one image
//! per pass) and sharpens pass by pass, its final image is `dray render`'s bit for bit,
//! `dray submit --preview` rewrites a PNG as passes land, and ListWorkers shows the
//! workers with the domains they own while the job runs.

mod common;
mod support;

use std::time::Duration;

use dray_proto::v1::render_service_client::RenderServiceClient;
use dray_proto::v1::{
    GetImageRequest, GetJobRequest, ImageFormat, JobSpec, JobState, ListWorkersRequest,
    SubmitJobRequest, WatchImageRequest,
};
use support::{WorkerCluster, dray};

const W: u32 = 64;
const H: u32 = 48;
const SPP: u32 = 256;

fn spec() -> JobSpec {
    JobSpec {
        scene: "cornell".into(),
        width: W,
        height: H,
        spp: SPP,
        integrator: "path".into(),
        domains: 4,
        schedule: "domain".into(),
        ..Default::default()
    }
}

#[test]
fn a_running_job_shows_each_pass_and_ends_with_the_exact_image() {
    let dir = common::tmp("progressive");
    let cluster = WorkerCluster::start(2, 0, &dir, &[]);
    let rt = tokio::runtime::Runtime::new().expect("runtime");
    let url = format!("http://{}", cluster.addr);
    let (images, listing, running_image) = rt.block_on(async {
        let mut c = RenderServiceClient::connect(url.clone())
            .await
            .expect("connect")
            .max_decoding_message_size(64 << 20);
        let id = c
            .submit_job(SubmitJobRequest { spec: Some(spec()) })
            .await
            .expect("submit")
            .into_inner()
            .job_id;
        let mut stream = c
            .watch_image(WatchImageRequest {
                job_id: id.clone(),
                format: ImageFormat::Exr as i32,
                exposure: None,
                tonemap: String::new(),
                min_interval: Some(prost_types::Duration {
                    seconds: 0,
                    nanos: 50_000_000,
                }),
            })
            .await
            .expect("WatchImage")
            .into_inner();
        let mut images = Vec::new();
        let mut listing = None;
        let mut running_image = None;
        while let Some(img) = tokio::time::timeout(Duration::from_secs(300), stream.message())
            .await
            .expect("an image within 300 s")
            .expect("WatchImage stream")
        {
            if !img.r#final && listing.is_none() {
                // The job is running: the cluster listing shows it, and GetImage answers
                // with the image of the passes so far.
                listing = Some(
                    c.list_workers(ListWorkersRequest::default())
                        .await
                        .expect("ListWorkers")
                        .into_inner(),
                );
                running_image = c
                    .get_image(GetImageRequest {
                        job_id: id.clone(),
                        format: ImageFormat::Png as i32,
                        ..Default::default()
                    })
                    .await
                    .ok()
                    .map(|r| r.into_inner());
            }
            images.push(img);
        }
        let job = c
            .get_job(GetJobRequest { job_id: id.clone() })
            .await
            .expect("GetJob")
            .into_inner()
            .job
            .expect("a job");
        let progress = job.progress.expect("progress");
        assert_eq!(progress.state(), JobState::Succeeded);
        assert_eq!(progress.samples_done, SPP);
        assert_eq!(progress.passes_done, progress.passes_total);
        (images, listing, running_image)
    });

    // Doubling passes: 1, 2, 4, ... 256 spp, 9 passes; WatchImage may skip passes that
    // land within its interval, never the final image.
    let last = images.last().expect("at least the final image");
    assert!(last.r#final, "the stream ends with the final image");
    assert_eq!(
        (last.samples, last.passes_done, last.passes_total),
        (SPP, 9, 9)
    );
    let previews: Vec<_> = images.iter().filter(|i| !i.r#final).collect();
    assert!(
        !previews.is_empty(),
        "no pass image before the final one: {:?}",
        images.iter().map(|i| i.samples).collect::<Vec<_>>()
    );
    assert!(previews.windows(2).all(|w| w[0].samples < w[1].samples));
    assert!(
        previews
            .iter()
            .all(|p| p.samples < SPP && p.data != last.data)
    );

    // The final image is `dray render`'s, bit for bit (linear EXR: no tone mapping).
    let exr = dir.join("render.exr");
    let out = dray()
        .args(["render", "cornell", "--width", &W.to_string(), "--height"])
        .arg(H.to_string())
        .args([
            "--spp",
            &SPP.to_string(),
            "--integrator",
            "path",
            "--domains",
            "4",
        ])
        .arg("--exr")
        .arg(&exr)
        .arg("--output")
        .arg(dir.join("render.png"))
        .arg("-q")
        .output()
        .expect("dray render");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        std::fs::read(&exr).expect("render.exr") == last.data,
        "the progressive job's final image differs from dray render's"
    );

    let running = running_image.expect("GetImage answered while the job ran");
    assert!(!running.r#final && running.samples > 0 && running.samples < SPP);
    assert_eq!(&running.data[1..4], b"PNG");

    // ListWorkers while the job ran: both workers, the job's four domains owned.
    // Two workers fit the default page (100): one page is the whole cluster, and says so.
    let listing = listing.expect("a listing while the job ran");
    assert_eq!(listing.workers.len(), 2, "{listing:?}");
    assert!(listing.next_page_token.is_empty(), "{listing:?}");
    for w in &listing.workers {
        assert!(w.endpoint.starts_with("http://"), "{w:?}");
        assert!(w.threads > 0);
        assert_ne!(w.state, "silent", "{w:?}");
    }
    if let Some(job) = listing.jobs.first() {
        assert_eq!(job.domains.len(), 4, "{job:?}");
        let ids: Vec<&str> = listing
            .workers
            .iter()
            .map(|w| w.worker_id.as_str())
            .collect();
        for d in &job.domains {
            assert!(
                !d.worker_ids.is_empty() && d.worker_ids.iter().all(|o| ids.contains(&o.as_str())),
                "domain {} owned by {:?}, workers {ids:?}",
                d.domain,
                d.worker_ids
            );
        }
        let owned: usize = listing
            .workers
            .iter()
            .map(|w| w.domains.iter().filter(|d| d.owned).count())
            .sum();
        assert!(owned >= 4, "{listing:?}");
        assert!(listing.workers.iter().any(|w| w.state == "busy"));
    } else {
        // The job ended between the pass image and the listing (a loaded machine): the
        // listing must then show no job on the workers either.
        assert!(
            listing.workers.iter().all(|w| w.jobs.is_empty()),
            "{listing:?}"
        );
    }

    // `dray submit --preview`: the file is rewritten as passes land and ends as the
    // final image.
    let preview = dir.join("preview.png");
    let output = dir.join("submit.png");
    let out = dray()
        .args(["submit", "cornell", "--coordinator", &cluster.addr])
        .args([
            "--width", "48", "--height", "32", "--spp", "16", "--passes", "4",
        ])
        .arg("--preview")
        .arg(&preview)
        .arg("--output")
        .arg(&output)
        .output()
        .expect("dray submit");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    assert!(
        std::fs::read(&preview).expect("the preview file") == std::fs::read(&output).expect("png"),
        "the preview ends as the final image"
    );
    assert!(!dir.join("preview.png.part").exists());
}

#[test]
fn passes_are_checked_and_named() {
    let dir = common::tmp("passes-bad");
    let out = dray()
        .args([
            "render", "cornell", "--width", "8", "--height", "8", "--spp", "4",
        ])
        .args(["--passes", "5", "--output"])
        .arg(dir.join("x.png"))
        .output()
        .expect("dray render");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(stderr.contains("passes"), "{stderr}");
}

//! The job store survives a SIGKILL in the middle of its writes: a child process (this
//! test binary run again) writes jobs, committed tiles and finished images as fast as it
//! can and is killed; the store then opens, every write the child saw confirmed is there,
//! no tile is torn (each holds exactly the sums written) and no image is torn (each named
//! image decodes to exactly the film written).

use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};

use dray_coordinator::store::{CommittedTile, JobStore, Op};
use dray_core::film::Film;
use dray_proto::v1::{JobSpec, JobState};

const CHILD_ENV: &str = "DRAY_STORE_KILL_CHILD";
/// Pixels of each tile and each image (8 x 8).
const PIXELS: u32 = 64;

fn sums(job: u32, tile: u32) -> Vec<[i64; 3]> {
    (0..PIXELS)
        .map(|p| {
            let v = i64::from(job) * 1_000_003 + i64::from(tile) * 7919 + i64::from(p);
            [v, -v, v.wrapping_mul(0x9E37_79B9)]
        })
        .collect()
}

fn film(job: u32) -> Film {
    let mut f = Film::new(8, 8);
    for (p, s) in sums(job, 99).into_iter().enumerate() {
        f.add_fixed(p as u32, s);
    }
    f.nonfinite = u64::from(job);
    f
}

fn spec(job: u32) -> JobSpec {
    JobSpec {
        scene: "cornell".into(),
        width: 8,
        height: 8,
        spp: 1,
        seed: u64::from(job),
        ..Default::default()
    }
}

/// The child: write until killed, saying on stdout which jobs are confirmed on disk.
fn child(dir: &str) {
    let (store, _) = JobStore::open(std::path::Path::new(dir)).expect("open the store");
    for job in 0u32.. {
        let id = format!("job-{job}");
        store.post(Op::Insert {
            id: id.clone(),
            spec: spec(job),
            submitted_ms: 1,
        });
        store.post(Op::Tiles {
            id: id.clone(),
            tiles: (0..4)
                .map(|t| CommittedTile {
                    tile: t,
                    sums: sums(job, t),
                    passes: Some(t),
                    aovs: None,
                    stopped_at: None,
                })
                .collect(),
        });
        if job.is_multiple_of(3) {
            // As a succeeding job does: the image on disk first, then the row naming it.
            store.keep_image(&id, &film(job)).expect("write the image");
            store.post(Op::Finish {
                id: id.clone(),
                state: JobState::Succeeded,
                error: String::new(),
                finished_ms: 2,
                elapsed_ms: 3,
                stats: Box::default(),
                image: true,
            });
        }
        if job % 8 == 7 {
            assert!(store.flush(), "the writes so far are on disk");
            println!("confirmed {job}");
        }
    }
}

#[test]
fn a_kill_during_writes_tears_nothing() {
    if let Ok(dir) = std::env::var(CHILD_ENV) {
        child(&dir);
        return;
    }
    let dir = tempfile::tempdir().expect("tempdir");
    let mut c = Command::new(std::env::current_exe().expect("this test binary"))
        .args([
            "--exact",
            "a_kill_during_writes_tears_nothing",
            "--nocapture",
        ])
        .env(CHILD_ENV, dir.path())
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .expect("spawn the writer");
    let out = c.stdout.take().expect("stdout");
    let mut confirmed = None;
    for line in BufReader::new(out).lines() {
        let Ok(line) = line else { break };
        if let Some(n) = line.strip_prefix("confirmed ") {
            confirmed = n.trim().parse::<u32>().ok();
            if confirmed.is_some_and(|n| n >= 200) {
                break;
            }
        }
    }
    // SAFETY: kill(2) on our own child, not yet reaped.
    unsafe {
        libc::kill(c.id() as i32, libc::SIGKILL);
    }
    let _ = c.wait();
    let confirmed = confirmed.expect("the writer confirmed nothing");

    let (_store, jobs) = JobStore::open(dir.path()).expect("the store opens after the kill");
    assert!(
        jobs.len() as u32 > confirmed,
        "{} jobs kept, {confirmed} were confirmed",
        jobs.len()
    );
    let mut images = 0;
    for j in &jobs {
        let n: u32 = j.id["job-".len()..].parse().expect("job number");
        assert_eq!(j.spec, spec(n), "{}", j.id);
        if j.state == JobState::Succeeded {
            let file = j.image.as_ref().expect("a succeeded job names its image");
            let got = dray_coordinator::store::image_file::read(file).expect("a whole image");
            assert_eq!(got, film(n), "{}", j.id);
            assert!(j.tiles.is_empty(), "an ended job keeps no tiles");
            images += 1;
        } else {
            assert!(
                !n.is_multiple_of(3) || n > confirmed,
                "{}: confirmed as ended, found {:?}",
                j.id,
                j.state
            );
            for t in &j.tiles {
                assert_eq!(t.sums, sums(n, t.tile), "{} tile {}", j.id, t.tile);
                assert_eq!(t.passes, Some(t.tile), "{} tile {} passes", j.id, t.tile);
            }
            if n <= confirmed {
                assert_eq!(j.tiles.len(), 4, "{}: a confirmed tile is missing", j.id);
            }
        }
    }
    assert!(images > 0);
}

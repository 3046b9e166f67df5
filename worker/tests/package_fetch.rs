//! The worker's package fetcher against a `dray.v1.PackageService` over real gRPC (a
//! tonic server on a loopback port) that misbehaves on purpose: a stream that breaks
//! mid-file is resumed from the bytes already on disk; a corrupted or truncated transfer
//! is caught by the checksum or the length, loudly, and nothing unverified is left where
//! the package's files go; a refusal is not retried.

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use dray_proto::v1::package_service_server::{PackageService, PackageServiceServer};
use dray_proto::v1::{FetchFileRequest, FileChunk};
use dray_worker::package_fetch::{
    Expected, FetchError, FetchMode, MAX_FAILURES, MAX_MANIFEST_BYTES, PackageFetcher, expected_of,
};
use tonic::{Request, Response, Status};

/// What the fake coordinator does wrong.
#[derive(Clone, Default)]
struct Faults {
    /// Break the first call's stream (UNAVAILABLE) after this many bytes.
    break_first_after: Option<u64>,
    /// Flip a byte of what is sent at this offset.
    corrupt_at: Option<usize>,
    /// End every stream cleanly at this offset (the file announced stays whole).
    end_at: Option<u64>,
    /// Announce (and send) only the first N bytes, as if its file were truncated.
    truncated_to: Option<usize>,
    /// Refuse every call with NOT_FOUND.
    refuse: bool,
    /// Announce this total size in every chunk (a hostile coordinator's "file").
    announce: Option<u64>,
}

#[derive(Clone)]
struct Fake {
    data: Arc<Vec<u8>>,
    chunk: usize,
    faults: Faults,
    /// The offset of every call.
    calls: Arc<Mutex<Vec<u64>>>,
}

#[tonic::async_trait]
impl PackageService for Fake {
    type FetchFileStream = tokio_stream::Iter<std::vec::IntoIter<Result<FileChunk, Status>>>;

    async fn fetch_file(
        &self,
        r: Request<FetchFileRequest>,
    ) -> Result<Response<Self::FetchFileStream>, Status> {
        let r = r.into_inner();
        let n = {
            let mut calls = self.calls.lock().unwrap();
            calls.push(r.offset);
            calls.len()
        };
        if self.faults.refuse {
            return Err(Status::not_found(format!(
                "{:?} is not in the package",
                r.path
            )));
        }
        let mut data = self.data.to_vec();
        if let Some(at) = self.faults.corrupt_at {
            data[at] ^= 0x40;
        }
        if let Some(len) = self.faults.truncated_to {
            data.truncate(len);
        }
        // The checksum the manifest records: of the whole, undamaged file.
        let xxh3 = expected_of(&self.data).xxh3;
        let total = self.faults.announce.unwrap_or(data.len() as u64);
        let stop = self
            .faults
            .end_at
            .unwrap_or(total)
            .min(total)
            .min(data.len() as u64);
        let mut msgs = Vec::new();
        let mut at = r.offset;
        while at < stop {
            if n == 1
                && let Some(b) = self.faults.break_first_after
                && at >= b
            {
                msgs.push(Err(Status::unavailable("connection reset (test)")));
                break;
            }
            let end = (at + self.chunk as u64).min(stop);
            msgs.push(Ok(FileChunk {
                offset: at,
                data: data[at as usize..end as usize].to_vec(),
                total_bytes: total,
                xxh3: xxh3.clone(),
            }));
            at = end;
        }
        Ok(Response::new(tokio_stream::iter(msgs)))
    }
}

/// A fake coordinator serving `data` with `faults`, and a fetcher of it caching in a
/// fresh directory.
struct Setup {
    rt: tokio::runtime::Runtime,
    fetcher: Arc<PackageFetcher>,
    calls: Arc<Mutex<Vec<u64>>>,
    dir: PathBuf,
}

fn setup(name: &str, data: &[u8], faults: Faults) -> Setup {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    let calls = Arc::new(Mutex::new(Vec::new()));
    let fake = Fake {
        data: Arc::new(data.to_vec()),
        chunk: 1000,
        faults,
        calls: calls.clone(),
    };
    let listener = rt
        .block_on(tokio::net::TcpListener::bind("127.0.0.1:0"))
        .unwrap();
    let addr = listener.local_addr().unwrap();
    rt.spawn(
        tonic::transport::Server::builder()
            .add_service(PackageServiceServer::new(fake))
            .serve_with_incoming(tokio_stream::wrappers::TcpListenerStream::new(listener)),
    );
    let channel = rt
        .block_on(
            tonic::transport::Endpoint::from_shared(format!("http://{addr}"))
                .unwrap()
                .connect(),
        )
        .unwrap();
    let dir = std::env::temp_dir().join(format!("dray-fetch-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let fetcher = PackageFetcher::new(
        dray_net::ClientOptions::plain().wrap(channel),
        rt.handle().clone(),
        Some(dir.clone()),
        FetchMode::Always,
    )
    .unwrap();
    Setup {
        rt,
        fetcher: Arc::new(fetcher),
        calls,
        dir,
    }
}

impl Setup {
    /// Fetch `name` as a file of `expected` (blocking, from this non-runtime thread, as
    /// a worker's tracing thread does).
    fn fetch(&self, name: &str, expected: &Expected) -> Result<(), FetchError> {
        self.fetcher
            .fetch_file("job-1", "", &self.dir, name, expected)
    }

    fn calls(&self) -> Vec<u64> {
        self.calls.lock().unwrap().clone()
    }
}

impl Drop for Setup {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.dir);
        let _ = &self.rt;
    }
}

/// 10 000 bytes that are not all alike.
fn payload() -> Vec<u8> {
    (0..10_000u32)
        .map(|i| (i.wrapping_mul(2_654_435_761) >> 13) as u8)
        .collect()
}

fn nothing_left(dir: &Path, name: &str) {
    assert!(!dir.join(name).exists(), "an unverified {name} was kept");
    assert!(
        !dir.join(format!("{name}.part")).exists(),
        "a damaged partial {name} was kept"
    );
}

#[test]
fn a_broken_stream_is_resumed_from_the_bytes_received() {
    let data = payload();
    let s = setup(
        "resume",
        &data,
        Faults {
            break_first_after: Some(3000),
            ..Faults::default()
        },
    );
    s.fetch("domain-00000.bin", &expected_of(&data)).unwrap();
    assert_eq!(std::fs::read(s.dir.join("domain-00000.bin")).unwrap(), data);
    assert_eq!(s.calls(), vec![0, 3000], "resumed at the break, not from 0");
    assert!(!s.dir.join("domain-00000.bin.part").exists());
    // Whole and verified: not fetched again.
    s.fetch("domain-00000.bin", &expected_of(&data)).unwrap();
    assert_eq!(s.calls().len(), 2);
}

#[test]
fn a_partial_file_left_by_an_earlier_run_is_resumed() {
    let data = payload();
    let s = setup("leftover", &data, Faults::default());
    std::fs::write(s.dir.join("emitters.bin.part"), &data[..4321]).unwrap();
    s.fetch("emitters.bin", &expected_of(&data)).unwrap();
    assert_eq!(std::fs::read(s.dir.join("emitters.bin")).unwrap(), data);
    assert_eq!(s.calls(), vec![4321]);
}

#[test]
fn a_corrupted_transfer_fails_the_checksum_loudly() {
    let data = payload();
    let s = setup(
        "corrupt",
        &data,
        Faults {
            corrupt_at: Some(5555),
            ..Faults::default()
        },
    );
    let e = s
        .fetch("domain-00003.bin", &expected_of(&data))
        .unwrap_err();
    assert!(matches!(e, FetchError::Checksum { .. }), "{e:?}");
    let text = e.to_string();
    assert!(
        text.contains("CHECKSUM MISMATCH") && text.contains("domain-00003.bin"),
        "{text}"
    );
    nothing_left(&s.dir, "domain-00003.bin");
}

#[test]
fn a_stream_that_keeps_ending_early_is_an_error_not_a_file() {
    let data = payload();
    let s = setup(
        "ends-early",
        &data,
        Faults {
            end_at: Some(7000),
            ..Faults::default()
        },
    );
    let e = s
        .fetch("domain-00001.bin", &expected_of(&data))
        .unwrap_err();
    assert!(matches!(e, FetchError::Broken { bytes: 7000, .. }), "{e:?}");
    assert!(e.to_string().contains("domain-00001.bin"), "{e}");
    let calls = s.calls();
    assert_eq!(calls.len() as u32, MAX_FAILURES, "{calls:?}");
    assert!(calls[1..].iter().all(|&o| o == 7000), "{calls:?}");
    assert!(!s.dir.join("domain-00001.bin").exists());
}

#[test]
fn a_truncated_file_is_caught_by_its_size_or_its_checksum() {
    let data = payload();
    let s = setup(
        "truncated",
        &data,
        Faults {
            truncated_to: Some(6000),
            ..Faults::default()
        },
    );
    // A domain file: the manifest gives its size, which the coordinator contradicts.
    let e = s
        .fetch("domain-00002.bin", &expected_of(&data))
        .unwrap_err();
    assert!(matches!(e, FetchError::Mismatch { .. }), "{e:?}");
    nothing_left(&s.dir, "domain-00002.bin");
    // The manifest: its size is not known beforehand, its checksum is.
    let manifest = Expected {
        bytes: None,
        xxh3: expected_of(&data).xxh3,
    };
    let e = s.fetch("manifest.json", &manifest).unwrap_err();
    assert!(
        matches!(e, FetchError::Checksum { bytes: 6000, .. }),
        "{e:?}"
    );
    nothing_left(&s.dir, "manifest.json");
}

#[test]
fn a_refusal_is_not_retried() {
    let data = payload();
    let s = setup(
        "refused",
        &data,
        Faults {
            refuse: true,
            ..Faults::default()
        },
    );
    let e = s
        .fetch("domain-00000.bin", &expected_of(&data))
        .unwrap_err();
    assert!(
        matches!(
            e,
            FetchError::Refused {
                code: tonic::Code::NotFound,
                ..
            }
        ),
        "{e:?}"
    );
    assert_eq!(s.calls(), vec![0]);
}

/// docs/security.md "Hardening, second round", item 9: a coordinator announcing a 1 TiB
/// manifest (whose size nothing
/// declares beforehand) made a worker write 600 MB before it gave up, and the partial
/// file stayed. The announced size is now refused before a byte is written.
#[test]
fn an_oversized_manifest_is_refused_before_a_byte_is_written() {
    let data = payload();
    let s = setup(
        "huge-manifest",
        &data,
        Faults {
            announce: Some(1 << 40),
            ..Faults::default()
        },
    );
    let manifest = Expected {
        bytes: None,
        xxh3: expected_of(&data).xxh3,
    };
    let e = s.fetch("manifest.json", &manifest).unwrap_err();
    assert!(
        matches!(e, FetchError::TooLarge { bytes, .. } if bytes == 1 << 40),
        "{e:?}"
    );
    assert!(
        e.to_string().contains(&MAX_MANIFEST_BYTES.to_string()),
        "{e}"
    );
    assert_eq!(s.calls(), vec![0], "not retried");
    nothing_left(&s.dir, "manifest.json");
}

/// A manifest just over the bound is refused; the bound itself is not a file the worker
/// must hold whole in memory (it is streamed to disk), only a cap on disk use.
#[test]
fn a_manifest_of_the_bound_plus_one_is_refused() {
    let data = payload();
    let s = setup(
        "bound-manifest",
        &data,
        Faults {
            announce: Some(MAX_MANIFEST_BYTES + 1),
            ..Faults::default()
        },
    );
    let manifest = Expected {
        bytes: None,
        xxh3: expected_of(&data).xxh3,
    };
    let e = s.fetch("manifest.json", &manifest).unwrap_err();
    assert!(matches!(e, FetchError::TooLarge { .. }), "{e:?}");
    nothing_left(&s.dir, "manifest.json");
}

/// A size the manifest declares beyond the cache's free space is refused before any
/// call is made, and leaves nothing.
#[test]
fn a_declared_size_beyond_the_free_space_is_refused_before_fetching() {
    let data = payload();
    let s = setup("no-room", &data, Faults::default());
    let e = s
        .fetch(
            "domain-00000.bin",
            &Expected {
                bytes: Some(1 << 62),
                xxh3: expected_of(&data).xxh3,
            },
        )
        .unwrap_err();
    assert!(matches!(e, FetchError::TooLarge { .. }), "{e:?}");
    assert!(e.to_string().contains("free"), "{e}");
    assert!(s.calls().is_empty(), "{:?}", s.calls());
    nothing_left(&s.dir, "domain-00000.bin");
}

/// A fetch that fails for any reason leaves no partial file (here: a stream that keeps
/// ending early, whose bytes were kept before).
#[test]
fn a_failed_fetch_leaves_no_partial_file() {
    let data = payload();
    let s = setup(
        "no-partial",
        &data,
        Faults {
            end_at: Some(5000),
            ..Faults::default()
        },
    );
    let e = s
        .fetch("domain-00004.bin", &expected_of(&data))
        .unwrap_err();
    assert!(matches!(e, FetchError::Broken { .. }), "{e:?}");
    nothing_left(&s.dir, "domain-00004.bin");
}

/// Run `script` with `sh -c` as user and group 65534 (nobody); None when impossible here
/// (not root, or no setpriv), said loudly, and a failure under CI (`CI=true`).
fn as_other_user(script: &str) -> Option<std::process::Output> {
    // SAFETY: geteuid has no preconditions.
    let root = unsafe { libc::geteuid() } == 0;
    let setpriv = Path::new("/usr/bin/setpriv").exists() || Path::new("/bin/setpriv").exists();
    if !root || !setpriv {
        let why = if root {
            "setpriv is missing"
        } else {
            "not running as root"
        };
        if std::env::var("CI").as_deref() == Ok("true") {
            panic!("a second local user is needed for this test under CI, but {why}");
        }
        eprintln!("SKIPPED (second-user part): {why}; cannot act as another local user");
        return None;
    }
    Some(
        std::process::Command::new("setpriv")
            .args([
                "--reuid=65534",
                "--regid=65534",
                "--clear-groups",
                "sh",
                "-c",
            ])
            .arg(script)
            .output()
            .expect("run setpriv"),
    )
}

/// docs/security.md "Hardening, second round", item 1: in a cache directory another local
/// user can write to (a shared
/// --package-cache, or the old predictable default), that user plants `NAME.part` as a
/// symlink to a file of ours. The fetch must not write through it.
#[test]
fn a_symlink_planted_at_a_partial_file_is_not_followed() {
    let data = payload();
    let s = setup("planted-part", &data, Faults::default());
    use std::os::unix::fs::PermissionsExt;
    std::fs::set_permissions(&s.dir, std::fs::Permissions::from_mode(0o777)).unwrap();
    let victim = std::env::temp_dir().join(format!("dray-victim-{}", std::process::id()));
    std::fs::write(&victim, b"precious").unwrap();
    std::fs::set_permissions(&victim, std::fs::Permissions::from_mode(0o600)).unwrap();
    let part = s.dir.join("domain-00000.bin.part");
    let planted_by_other = as_other_user(&format!("ln -s {} {}", victim.display(), part.display()))
        .is_some_and(|o| o.status.success());
    if !planted_by_other {
        std::os::unix::fs::symlink(&victim, &part).unwrap();
    }
    assert!(
        std::fs::symlink_metadata(&part)
            .unwrap()
            .file_type()
            .is_symlink()
    );
    let e = s
        .fetch("domain-00000.bin", &expected_of(&data))
        .unwrap_err();
    assert!(matches!(e, FetchError::Io { .. }), "{e:?}");
    assert_eq!(
        std::fs::read(&victim).unwrap(),
        b"precious",
        "written through the link"
    );
    assert!(
        std::fs::symlink_metadata(&part).is_err(),
        "the link is removed"
    );
    // The next fetch makes a file of its own there.
    s.fetch("domain-00000.bin", &expected_of(&data)).unwrap();
    assert_eq!(std::fs::read(s.dir.join("domain-00000.bin")).unwrap(), data);
    assert_eq!(std::fs::read(&victim).unwrap(), b"precious");
    let _ = std::fs::remove_file(&victim);
}

/// docs/security.md "Hardening, second round", item 1: the default cache is a new private
/// directory (random name, 0700,
/// ours), which another local user cannot write in, and it goes with the fetcher.
#[test]
fn the_default_cache_is_private_and_goes_with_its_fetcher() {
    use std::os::unix::fs::{MetadataExt, PermissionsExt};
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .unwrap();
    let _in_rt = rt.enter();
    // Never called: the cache is made when the fetcher is.
    let channel = tonic::transport::Endpoint::from_static("http://127.0.0.1:9").connect_lazy();
    let fetcher = PackageFetcher::new(
        dray_net::ClientOptions::plain().wrap(channel),
        rt.handle().clone(),
        None,
        FetchMode::Always,
    )
    .unwrap();
    let root = fetcher.root().to_path_buf();
    let m = std::fs::symlink_metadata(&root).unwrap();
    assert!(m.is_dir() && !m.file_type().is_symlink());
    // SAFETY: geteuid has no preconditions.
    assert_eq!(m.uid(), unsafe { libc::geteuid() });
    assert_eq!(m.permissions().mode() & 0o777, 0o700);
    let name = root.file_name().unwrap().to_string_lossy().into_owned();
    assert!(
        name.starts_with("dray-worker-") && name.ends_with("-packages"),
        "{name}"
    );
    assert!(!name.contains(&std::process::id().to_string()), "{name}");
    if let Some(out) = as_other_user(&format!(
        "mkdir {0}/0123456789abcdef; ln -s /etc/passwd {0}/x.part",
        root.display()
    )) {
        assert!(!out.status.success());
        assert!(
            std::fs::read_dir(&root).unwrap().next().is_none(),
            "the other user wrote in it"
        );
    }
    drop(fetcher);
    assert!(!root.exists(), "the default cache outlived its fetcher");
}

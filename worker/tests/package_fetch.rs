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
    Expected, FetchError, FetchMode, MAX_FAILURES, PackageFetcher, expected_of,
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
        let total = data.len() as u64;
        let stop = self.faults.end_at.unwrap_or(total).min(total);
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

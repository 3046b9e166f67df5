//! `dray.v1.PackageService`: the files of a running job's scene package, streamed to
//! workers that do not see the coordinator's disk (no shared volume), see package.proto.
//!
//! **What may be served.** Only a file of the package of a job running on workers, and
//! only while it runs, named by its plain file name: `manifest.json` or a file the
//! manifest lists (its domain files, `emitters.bin`, `textures.bin`). The name is checked
//! lexically (one normal path component: no separator, no `..`, nothing absolute) *and*
//! must be listed by the manifest, the path must be a regular file (not a symlink, device
//! or FIFO) inside the package directory, and the file opened must be the one checked.
//! So no request, however it is spelt, reads anything outside the package directory.
//!
//! **The environment map.** A job with `lighting.env_map` has one more file: its map,
//! served by the name its setup gives it (`JobSetup.env_map.name`,
//! `env-map-<xxh3>.<ext>`), read from the path the coordinator resolved under its scene
//! root when it accepted the job (a regular file, its size checked against the setup's),
//! with the checksum it computed then. Only that name, only for that job, only while it
//! runs.
//! The service is a cluster service (`dray_net::auth` classes it by path): the cluster
//! token is required and the API token refused.
//!
//! **Memory.** A stream reads its file one chunk ([`CHUNK_BYTES`]) at a time and holds at
//! most [`CHUNKS_AHEAD`] chunks not yet sent, so a slow worker costs a few MiB, not the
//! file.
//!
//! **Checksums.** Every chunk carries the whole file's size and XXH3-64 as the manifest
//! records them (for the manifest itself, the package checksum the job's setup carries),
//! not recomputed from the disk: a file damaged on the coordinator's disk is then caught
//! by the worker's check, as a damaged transfer is. A file whose size differs from its
//! manifest entry is refused at once (DATA_LOSS).

use std::collections::HashMap;
use std::os::unix::fs::MetadataExt;
use std::path::{Component, Path, PathBuf};
use std::sync::{Arc, Mutex, MutexGuard};

use dray_proto::v1::package_service_server::PackageService;
use dray_proto::v1::{FetchFileRequest, FileChunk};
use dray_scene::partition::manifest::MANIFEST_FILE;
use dray_scene::partition::memory::is_memory_package;
use dray_scene::partition::open_package;
use tokio_stream::wrappers::ReceiverStream;
use tonic::{Request, Response, Status};

use crate::job::JobRegistry;

/// Largest `FileChunk.data`: small enough for gRPC's default 4 MiB message limit with
/// room to spare, large enough that per-message costs vanish.
pub const CHUNK_BYTES: usize = 1 << 20;

/// Chunks a stream reads ahead of what the worker has taken.
pub const CHUNKS_AHEAD: usize = 2;

/// Longest file name accepted (every name of a package is far shorter).
const MAX_NAME: usize = 255;

/// A file the service may send: its size and checksum, as the manifest records them
/// (`None` for the manifest itself, whose size is what is on disk).
#[derive(Clone, Debug)]
struct Listed {
    bytes: Option<u64>,
    xxh3: String,
}

/// The files of one job's package, read from its manifest once.
#[derive(Debug)]
struct Files {
    dir: PathBuf,
    checksum: String,
    files: HashMap<String, Listed>,
}

/// The tonic `PackageService` over the coordinator's running jobs.
#[derive(Clone)]
pub struct PackageApi {
    jobs: Arc<JobRegistry>,
    /// File tables by job id, dropped once the job no longer runs.
    tables: Arc<Mutex<HashMap<String, Arc<Files>>>>,
}

impl PackageApi {
    /// Serve the packages of the jobs `jobs` runs.
    pub fn new(jobs: Arc<JobRegistry>) -> PackageApi {
        PackageApi {
            jobs,
            tables: Arc::new(Mutex::new(HashMap::new())),
        }
    }

    fn lock(&self) -> MutexGuard<'_, HashMap<String, Arc<Files>>> {
        dray_sync::lock(&self.tables)
    }

    /// The file table of running job `job` (read from its manifest on first use).
    async fn files(&self, job: &str) -> Result<Arc<Files>, Status> {
        let Some((path, checksum)) = self.jobs.package(job) else {
            // Forget the tables of jobs that ended.
            self.lock().retain(|id, _| self.jobs.contains(id));
            return Err(Status::not_found(format!(
                "job {job:?} is not running on workers: there is no package to fetch"
            )));
        };
        if is_memory_package(&path) {
            return Err(Status::failed_precondition(format!(
                "job {job:?}'s package is held in the coordinator's memory, not on disk"
            )));
        }
        if let Some(t) = self.lock().get(job)
            && t.checksum == checksum
        {
            return Ok(t.clone());
        }
        let table = tokio::task::spawn_blocking(move || read_files(Path::new(&path), checksum))
            .await
            .map_err(|e| Status::internal(format!("manifest reading task died: {e}")))??;
        let table = Arc::new(table);
        let mut g = self.lock();
        g.retain(|id, _| self.jobs.contains(id));
        g.insert(job.to_string(), table.clone());
        Ok(table)
    }
}

/// The manifest's list of files, with the manifest itself.
fn read_files(dir: &Path, checksum: String) -> Result<Files, Status> {
    let pkg = open_package(dir).map_err(|e| {
        Status::data_loss(format!(
            "the job's package cannot be read on the coordinator: {e}"
        ))
    })?;
    let m = pkg.manifest();
    let mut files = HashMap::new();
    files.insert(
        MANIFEST_FILE.to_string(),
        Listed {
            bytes: None,
            xxh3: checksum.clone(),
        },
    );
    for e in m.domains.iter().chain(m.emitters.iter()) {
        files.insert(
            e.file.clone(),
            Listed {
                bytes: Some(e.bytes),
                xxh3: e.xxh3.clone(),
            },
        );
    }
    if let Some(t) = &m.textures_file {
        files.insert(
            t.file.clone(),
            Listed {
                bytes: Some(t.bytes),
                xxh3: t.xxh3.clone(),
            },
        );
    }
    Ok(Files {
        dir: dir.to_path_buf(),
        checksum,
        files,
    })
}

/// `path` if it is one plain file name (what every file of a package has): not empty,
/// no directory part, no `.` or `..`, not absolute, no NUL.
pub fn plain_file_name(path: &str) -> Result<&str, Status> {
    let bad = |why: &str| {
        Status::invalid_argument(format!(
            "path {:?}: {why}; name a file of the package, e.g. \"{MANIFEST_FILE}\"",
            path.chars().take(80).collect::<String>()
        ))
    };
    if path.is_empty() {
        return Err(bad("empty"));
    }
    if path.len() > MAX_NAME {
        return Err(bad("too long"));
    }
    if path.contains(['/', '\\', '\0']) {
        return Err(bad(
            "only a file name of the package directory may be fetched (no directories)",
        ));
    }
    let mut components = Path::new(path).components();
    match (components.next(), components.next()) {
        (Some(Component::Normal(_)), None) => Ok(path),
        _ => Err(bad("not a plain file name")),
    }
}

/// Open `name` in the package directory `dir`: a regular file (no symlink, device or
/// FIFO) whose real path is inside `dir`, checked again on the open file. Blocking.
fn open_in(dir: &Path, name: &str) -> Result<(std::fs::File, u64), Status> {
    let path = dir.join(name);
    let lost = |why: String| Status::data_loss(format!("package file {name:?}: {why}"));
    let before = std::fs::symlink_metadata(&path).map_err(|e| match e.kind() {
        std::io::ErrorKind::NotFound => Status::not_found(format!(
            "package file {name:?} is listed by the manifest but missing on the coordinator"
        )),
        _ => lost(e.to_string()),
    })?;
    if !before.file_type().is_file() {
        return Err(lost(
            "not a regular file (symlinks, directories, devices and FIFOs are never served)".into(),
        ));
    }
    let real_dir = dir.canonicalize().map_err(|e| lost(e.to_string()))?;
    let real = path.canonicalize().map_err(|e| lost(e.to_string()))?;
    if real.parent() != Some(real_dir.as_path()) {
        return Err(lost("not inside the package directory".into()));
    }
    let file = std::fs::File::open(&real).map_err(|e| lost(e.to_string()))?;
    let after = file.metadata().map_err(|e| lost(e.to_string()))?;
    if !after.is_file() || after.ino() != before.ino() || after.dev() != before.dev() {
        return Err(lost("replaced while being opened".into()));
    }
    Ok((file, after.len()))
}

#[tonic::async_trait]
impl PackageService for PackageApi {
    type FetchFileStream = ReceiverStream<Result<FileChunk, Status>>;

    async fn fetch_file(
        &self,
        r: Request<FetchFileRequest>,
    ) -> Result<Response<Self::FetchFileStream>, Status> {
        let r = r.into_inner();
        let name = plain_file_name(&r.path)?.to_string();
        if name.starts_with(crate::lighting::ENV_MAP_FILE_PREFIX) {
            return self.fetch_env_map(r, name).await;
        }
        let files = self.files(&r.job_id).await?;
        if !r.package_checksum.is_empty() && r.package_checksum != files.checksum {
            return Err(Status::failed_precondition(format!(
                "job {:?} runs package {}, not {}",
                r.job_id, files.checksum, r.package_checksum
            )));
        }
        let Some(listed) = files.files.get(&name).cloned() else {
            return Err(Status::not_found(format!(
                "{name:?} is not a file of job {:?}'s package",
                r.job_id
            )));
        };
        let dir = files.dir.clone();
        let name2 = name.clone();
        let (file, len) = tokio::task::spawn_blocking(move || open_in(&dir, &name2))
            .await
            .map_err(|e| Status::internal(format!("file opening task died: {e}")))??;
        if let Some(expected) = listed.bytes
            && expected != len
        {
            return Err(Status::data_loss(format!(
                "package file {name:?} is {len} bytes on the coordinator, but its manifest \
                 records {expected}"
            )));
        }
        if r.offset > len {
            return Err(Status::out_of_range(format!(
                "offset {} is past the end of {name:?} ({len} bytes)",
                r.offset
            )));
        }
        let (tx, rx) = tokio::sync::mpsc::channel(CHUNKS_AHEAD);
        tokio::spawn(send_file(file, name, r.offset, len, listed.xxh3, tx));
        Ok(Response::new(ReceiverStream::new(rx)))
    }
}

impl PackageApi {
    /// FetchFile of job `r.job_id`'s environment map, named `name`.
    async fn fetch_env_map(
        &self,
        r: FetchFileRequest,
        name: String,
    ) -> Result<Response<ReceiverStream<Result<FileChunk, Status>>>, Status> {
        let Some((_, checksum)) = self.jobs.package(&r.job_id) else {
            return Err(Status::not_found(format!(
                "job {:?} is not running on workers: there is no environment map to fetch",
                r.job_id
            )));
        };
        if !r.package_checksum.is_empty() && r.package_checksum != checksum {
            return Err(Status::failed_precondition(format!(
                "job {:?} runs package {checksum}, not {}",
                r.job_id, r.package_checksum
            )));
        }
        let file = self
            .jobs
            .env_map(&r.job_id)
            .filter(|f| f.name == name)
            .ok_or_else(|| {
                Status::not_found(format!(
                    "{name:?} is not the environment map of job {:?}",
                    r.job_id
                ))
            })?;
        if is_memory_package(&file.path) {
            return Err(Status::failed_precondition(format!(
                "job {:?}'s environment map is held in the coordinator's memory, not on disk",
                r.job_id
            )));
        }
        let path = PathBuf::from(&file.path);
        let (dir, base) = match (path.parent(), path.file_name().and_then(|n| n.to_str())) {
            (Some(d), Some(b)) => (d.to_path_buf(), b.to_string()),
            _ => {
                return Err(Status::internal(
                    "the environment map's path has no file name",
                ));
            }
        };
        let (f, len) = tokio::task::spawn_blocking(move || open_in(&dir, &base))
            .await
            .map_err(|e| Status::internal(format!("file opening task died: {e}")))??;
        if len != file.bytes {
            return Err(Status::data_loss(format!(
                "the environment map is {len} bytes on the coordinator, but was {} when the \
                 job was accepted (it changed since)",
                file.bytes
            )));
        }
        if r.offset > len {
            return Err(Status::out_of_range(format!(
                "offset {} is past the end of {name:?} ({len} bytes)",
                r.offset
            )));
        }
        let (tx, rx) = tokio::sync::mpsc::channel(CHUNKS_AHEAD);
        tokio::spawn(send_file(f, name, r.offset, len, file.xxh3, tx));
        Ok(Response::new(ReceiverStream::new(rx)))
    }
}

/// Send `file[offset..len]` in chunks of at most [`CHUNK_BYTES`], until done or the
/// worker hangs up. Each chunk is read on a blocking thread (positioned reads, so the
/// file is shared, not moved); none is held while the worker is slow to take chunks.
async fn send_file(
    file: std::fs::File,
    name: String,
    offset: u64,
    len: u64,
    xxh3: String,
    tx: tokio::sync::mpsc::Sender<Result<FileChunk, Status>>,
) {
    let chunk = |at: u64, data: Vec<u8>| FileChunk {
        offset: at,
        data,
        total_bytes: len,
        xxh3: xxh3.clone(),
    };
    if offset == len {
        let _ = tx.send(Ok(chunk(offset, Vec::new()))).await;
        return;
    }
    let file = Arc::new(file);
    let mut at = offset;
    while at < len {
        let want = (len - at).min(CHUNK_BYTES as u64) as usize;
        let f = file.clone();
        let read = tokio::task::spawn_blocking(move || {
            use std::os::unix::fs::FileExt;
            let mut buf = vec![0u8; want];
            f.read_exact_at(&mut buf, at).map(|()| buf)
        })
        .await;
        let data = match read {
            Ok(Ok(buf)) => buf,
            Ok(Err(e)) => {
                let why = if e.kind() == std::io::ErrorKind::UnexpectedEof {
                    format!("{name:?} became shorter than {len} bytes while being sent")
                } else {
                    format!("{name:?}: cannot read at byte {at}: {e}")
                };
                let _ = tx.send(Err(Status::data_loss(why))).await;
                return;
            }
            Err(e) => {
                let _ = tx
                    .send(Err(Status::internal(format!(
                        "file reading task died: {e}"
                    ))))
                    .await;
                return;
            }
        };
        if tx.send(Ok(chunk(at, data))).await.is_err() {
            // The worker hung up; it resumes with a new call if it wants the rest.
            return;
        }
        at += want as u64;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_plain_file_names_pass() {
        for ok in ["manifest.json", "domain-00001.bin", "textures.bin"] {
            assert!(plain_file_name(ok).is_ok(), "{ok}");
        }
        for bad in [
            "",
            ".",
            "..",
            "../manifest.json",
            "/etc/passwd",
            "a/b",
            "a\\b",
            "x\0y",
            "./manifest.json",
        ] {
            let e = plain_file_name(bad).expect_err(bad);
            assert_eq!(e.code(), tonic::Code::InvalidArgument, "{bad}");
        }
        assert!(plain_file_name(&"x".repeat(300)).is_err());
    }

    #[test]
    fn symlinks_and_outside_files_are_never_opened() {
        let root = std::env::temp_dir().join(format!("dray-pkgsvc-{}", std::process::id()));
        let dir = root.join("pkg");
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(root.join("secret"), b"secret").unwrap();
        std::fs::write(dir.join("ok.bin"), b"12345").unwrap();
        std::os::unix::fs::symlink(root.join("secret"), dir.join("link.bin")).unwrap();
        std::fs::create_dir_all(dir.join("sub.bin")).unwrap();
        let (_, len) = open_in(&dir, "ok.bin").unwrap();
        assert_eq!(len, 5);
        for name in ["link.bin", "sub.bin"] {
            let e = open_in(&dir, name).expect_err(name);
            assert_eq!(e.code(), tonic::Code::DataLoss, "{name}: {e:?}");
        }
        assert_eq!(
            open_in(&dir, "missing.bin").unwrap_err().code(),
            tonic::Code::NotFound
        );
        let _ = std::fs::remove_dir_all(&root);
    }
}

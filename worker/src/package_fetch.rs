//! Scene packages fetched from the coordinator (`dray.v1.PackageService`), for workers
//! that do not see the coordinator's disk: no shared volume, another machine, another
//! container.
//!
//! **When.** A job's setup names the package directory as the coordinator sees it. With
//! [`FetchMode::Auto`] (the default) a worker reads it there when that directory holds the
//! job's manifest (a shared volume), and fetches it otherwise; [`FetchMode::Always`]
//! fetches even when the path exists, [`FetchMode::Never`] only reads the shared path.
//!
//! **What, and when.** The manifest first (at job setup, checked against the setup's
//! package checksum), then the files every domain shares (emitters, textures), then each
//! domain file when the domain store first loads that domain, on the tracing thread that
//! needs it: a worker downloads only the domains it traces. A job's environment map is
//! one more file of its package here, fetched at setup (`crate::env_map`).
//!
//! **Where.** Under a cache directory, one sub-directory per package named by its
//! manifest checksum, so later jobs of the same package (a sweep, a retried attempt)
//! find the files there. The directories of packages no open job uses are removed when a
//! job of another package opens, except the most recently released one (the same "one
//! idle package" rule as the domain store's): the cache holds at most the packages of
//! the open jobs and one more.
//!
//! **How.** File by file, in chunks of at most 1 MiB written straight to `NAME.part`
//! (memory: one chunk). A stream that breaks is resumed from the partial file's length;
//! only repeated failures without progress give up. The whole file's XXH3-64 is then
//! checked against the manifest's (the setup's package checksum for the manifest) before
//! it is renamed into place, so a file in the cache is always whole and verified; a
//! mismatch discards the partial file and fails the job loudly, naming the file. A fetch
//! that fails, however, removes its partial file (a partial file left by a process that
//! died is resumed by the next fetch).
//!
//! **Bounds.** The coordinator is not trusted with the worker's disk: the manifest, whose
//! size nothing declares beforehand, may be at most [`MAX_MANIFEST_BYTES`]; every size
//! the coordinator announces (and every size the manifest declares) is checked against
//! that bound or the manifest's, and against the cache's free space, before a byte is
//! written.
//!
//! **Trust.** The default cache is a private directory (random name, mode 0700, made
//! atomically, removed when the fetcher drops: see `dray_scene::private_fs`), so no other
//! local user can plant files or symlinks in it. In every cache, a package folder that
//! exists must be a real directory, and partial files are opened without following
//! symlinks.
//!
//! The fetch is blocking (tracing and setup threads call it); the network calls run on
//! the worker's async runtime through its handle.

use std::collections::HashMap;
use std::fs::{File, OpenOptions};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use dray_net::AuthChannel;
use dray_proto::v1::package_service_client::PackageServiceClient;
use dray_proto::v1::{FetchFileRequest, FileChunk};
use dray_scene::partition::Package;
use dray_scene::partition::checksum::{HashingReader, from_hex, to_hex};
use dray_scene::partition::manifest::MANIFEST_FILE;
use dray_sync::lock;
use tonic::Code;

/// Consecutive failed calls, each without a byte of progress, after which a fetch gives
/// up (a call that delivers bytes resets the count).
pub const MAX_FAILURES: u32 = 5;

/// Pause after the first failed call; doubled after each further one.
const FIRST_BACKOFF: Duration = Duration::from_millis(100);

/// Suffix of a file being downloaded.
const PART: &str = ".part";

/// The largest manifest a worker fetches (64 MiB). Nothing declares a manifest's size
/// beforehand, so without a bound a coordinator could make a worker write until its disk
/// is full. A manifest holds per-domain entries of a few hundred bytes, per-material and
/// per-light descriptions: 64 MiB is hundreds of thousands of domains. (A package read
/// from a shared path is bounded by the package reader's own limit.)
pub const MAX_MANIFEST_BYTES: u64 = 64 << 20;

/// When a worker fetches a job's package instead of reading it at the setup's path.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum FetchMode {
    /// Read the package at the setup's path when it is there (the right manifest);
    /// fetch it otherwise.
    #[default]
    Auto,
    /// Always fetch, even when the path exists here.
    Always,
    /// Never fetch: the package must be at the setup's path (a shared volume).
    Never,
}

impl FetchMode {
    /// The mode's name, as [`FetchMode::from_name`] reads it.
    pub fn name(self) -> &'static str {
        match self {
            FetchMode::Auto => "auto",
            FetchMode::Always => "always",
            FetchMode::Never => "never",
        }
    }

    /// The mode named `name` ("auto", "always", "never").
    pub fn from_name(name: &str) -> Option<FetchMode> {
        match name {
            "auto" => Some(FetchMode::Auto),
            "always" => Some(FetchMode::Always),
            "never" => Some(FetchMode::Never),
            _ => None,
        }
    }
}

/// Why a package file could not be fetched.
#[derive(Debug, thiserror::Error)]
pub enum FetchError {
    #[error(
        "fetching {file} of job {job}'s package from the coordinator: refused ({code:?}): {message}"
    )]
    Refused {
        job: String,
        file: String,
        code: Code,
        message: String,
    },
    #[error(
        "fetching {file} of job {job}'s package from the coordinator: gave up after {failures} failed attempts without progress ({bytes} bytes received): {message}"
    )]
    Broken {
        job: String,
        file: String,
        failures: u32,
        bytes: u64,
        message: String,
    },
    #[error(
        "fetching {file}: the coordinator sends {found_bytes} bytes with checksum {found}, but the manifest records {expected_bytes} with checksum {expected}"
    )]
    Mismatch {
        file: String,
        found_bytes: u64,
        found: String,
        expected_bytes: String,
        expected: String,
    },
    #[error(
        "fetching {file}: CHECKSUM MISMATCH: the {bytes} bytes received hash to {found}, the manifest records {expected}; the transfer or the coordinator's copy is damaged (the download was discarded)"
    )]
    Checksum {
        file: String,
        bytes: u64,
        found: String,
        expected: String,
    },
    #[error("fetching {file}: the coordinator broke the protocol: {message}")]
    Protocol { file: String, message: String },
    #[error(
        "fetching {file}: the coordinator announces {bytes} bytes, more than {limit}; refused before writing"
    )]
    TooLarge {
        file: String,
        bytes: u64,
        limit: String,
    },
    #[error("package cache {path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("the job setup's package checksum {0:?} is not 16 hex digits")]
    PackageId(String),
    #[error("domain {0} is not in the package's manifest")]
    NoDomain(u32),
    #[error(
        "package cache {0}: another worker is using it ({LOCK_FILE} there is locked); give each worker its own --package-cache"
    )]
    InUse(PathBuf),
}

/// The file in a given cache directory that its worker holds locked while it runs: two
/// workers writing the same partial files would corrupt each other's downloads.
pub const LOCK_FILE: &str = ".dray-worker.lock";

/// Lock `root`'s [`LOCK_FILE`] for this process (an advisory lock the OS drops when the
/// process ends, however it ends), or say that another worker holds it.
fn lock_cache(root: &Path) -> Result<std::fs::File, FetchError> {
    let path = root.join(LOCK_FILE);
    let file = dray_scene::private_fs::no_follow(
        std::fs::OpenOptions::new()
            .create(true)
            .truncate(false)
            .write(true),
    )
    .open(&path)
    .map_err(io_err(&path))?;
    match file.try_lock() {
        Ok(()) => Ok(file),
        Err(std::fs::TryLockError::WouldBlock) => Err(FetchError::InUse(root.to_path_buf())),
        Err(std::fs::TryLockError::Error(e)) => Err(io_err(&path)(e)),
    }
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> FetchError + '_ {
    move |source| FetchError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// What a file must be: its size when known beforehand, and its XXH3-64 (hex).
#[derive(Clone, Debug)]
pub struct Expected {
    pub bytes: Option<u64>,
    pub xxh3: String,
}

/// Which packages the cache holds for whom (see the module's "Where").
#[derive(Default)]
struct Leases {
    in_use: HashMap<String, usize>,
    idle: Option<String>,
}

/// The worker's package cache and its client of the coordinator's `PackageService`.
pub struct PackageFetcher {
    client: PackageServiceClient<AuthChannel>,
    rt: tokio::runtime::Handle,
    root: PathBuf,
    /// The private directory this process made for itself when no cache was given;
    /// removed when dropped.
    _owned: Option<tempfile::TempDir>,
    mode: FetchMode,
    /// One lock per file being fetched, so two jobs never write the same partial file.
    files: Mutex<HashMap<PathBuf, Arc<Mutex<()>>>>,
    leases: Mutex<Leases>,
    /// [`LOCK_FILE`], locked for as long as this fetcher lives (a given directory only).
    _held: Option<std::fs::File>,
}

impl PackageFetcher {
    /// A fetcher calling the coordinator over `channel` (its calls run on `rt`), caching
    /// under `root`, or, when `None`, under a new private directory of this process in
    /// the system's temp directory (random name, 0700), removed when the fetcher is
    /// dropped.
    pub fn new(
        channel: AuthChannel,
        rt: tokio::runtime::Handle,
        root: Option<PathBuf>,
        mode: FetchMode,
    ) -> Result<PackageFetcher, FetchError> {
        let (root, owned) = match root {
            Some(r) => (r, None),
            None => {
                // Unique per fetcher (several workers may share a process), and never a
                // directory another user made beforehand.
                let dir = dray_scene::private_fs::private_temp_dir("dray-worker-", "-packages")
                    .map_err(io_err(&std::env::temp_dir()))?;
                (dir.path().to_path_buf(), Some(dir))
            }
        };
        let held = if owned.is_some() {
            None
        } else {
            // A directory given is checked now, so a bad one fails the worker at start.
            std::fs::create_dir_all(&root).map_err(io_err(&root))?;
            Some(lock_cache(&root)?)
        };
        // Absolute, so a relative --package-cache means the worker's working directory
        // at start, whatever happens later.
        let root = std::path::absolute(&root).map_err(io_err(&root))?;
        Ok(PackageFetcher {
            client: PackageServiceClient::new(channel),
            rt,
            root,
            _owned: owned,
            mode,
            files: Mutex::new(HashMap::new()),
            leases: Mutex::new(Leases::default()),
            _held: held,
        })
    }

    /// The cache directory.
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// When this fetcher fetches.
    pub fn mode(&self) -> FetchMode {
        self.mode
    }

    /// Whether a job whose package is at `path` (as the coordinator sees it), with
    /// manifest checksum `checksum`, is fetched rather than read there.
    pub fn should_fetch(&self, path: &Path, checksum: &str) -> bool {
        match self.mode {
            FetchMode::Never => false,
            FetchMode::Always => true,
            FetchMode::Auto => !holds_package(path, checksum),
        }
    }

    /// Open job `job_id`'s package `checksum` in the cache, fetching its manifest if
    /// the cache does not hold it yet. Blocking.
    pub fn open(
        self: &Arc<Self>,
        job_id: &str,
        checksum: &str,
    ) -> Result<RemotePackage, FetchError> {
        if from_hex(checksum).is_none() {
            return Err(FetchError::PackageId(checksum.to_string()));
        }
        let dir = self.root.join(checksum);
        self.take_lease(checksum);
        // From here the lease is returned when `remote` is dropped, error or not.
        let remote = RemotePackage {
            fetcher: self.clone(),
            job_id: job_id.to_string(),
            checksum: checksum.to_string(),
            dir,
        };
        package_dir(&remote.dir)?;
        remote.fetch(
            MANIFEST_FILE,
            &Expected {
                bytes: None,
                xxh3: checksum.to_string(),
            },
        )?;
        Ok(remote)
    }

    /// Mark `checksum` in use, and remove the cached packages nobody uses except the
    /// idle one.
    fn take_lease(&self, checksum: &str) {
        let mut g = lock(&self.leases);
        *g.in_use.entry(checksum.to_string()).or_default() += 1;
        if g.idle.as_deref() == Some(checksum) {
            g.idle = None;
        }
        let Ok(entries) = std::fs::read_dir(&self.root) else {
            return;
        };
        for e in entries.flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            // Only what this cache made: package directories are named by checksum.
            if from_hex(&name).is_none()
                || g.in_use.contains_key(&name)
                || g.idle.as_deref() == Some(name.as_str())
            {
                continue;
            }
            self.remove_package(&name);
        }
    }

    /// One user of `checksum` is done with it; the last makes it the idle package.
    fn return_lease(&self, checksum: &str) {
        let mut g = lock(&self.leases);
        let Some(n) = g.in_use.get_mut(checksum) else {
            return;
        };
        *n -= 1;
        if *n > 0 {
            return;
        }
        g.in_use.remove(checksum);
        if let Some(old) = g.idle.replace(checksum.to_string())
            && old != checksum
            && !g.in_use.contains_key(&old)
        {
            self.remove_package(&old);
        }
    }

    fn remove_package(&self, checksum: &str) {
        let dir = self.root.join(checksum);
        if let Err(e) = std::fs::remove_dir_all(&dir)
            && e.kind() != std::io::ErrorKind::NotFound
        {
            tracing::warn!(dir = %dir.display(), "cannot remove a cached package: {e}");
        }
        lock(&self.files).retain(|p, _| !p.starts_with(&dir));
    }

    /// The lock of file `path`.
    fn file_lock(&self, path: &Path) -> Arc<Mutex<()>> {
        lock(&self.files)
            .entry(path.to_path_buf())
            .or_default()
            .clone()
    }

    /// Make `dir/name` the whole, verified file `expected` describes, fetching it from
    /// job `job_id`'s package unless it is there already. Blocking.
    pub fn fetch_file(
        &self,
        job_id: &str,
        checksum: &str,
        dir: &Path,
        name: &str,
        expected: &Expected,
    ) -> Result<(), FetchError> {
        let dest = dir.join(name);
        let file_lock = self.file_lock(&dest);
        let _held = lock(&file_lock);
        // Only verified files are ever renamed into place (a symlink is not one: the
        // fetched file replaces it).
        if std::fs::symlink_metadata(&dest).is_ok_and(|m| m.file_type().is_file()) {
            return Ok(());
        }
        let part = dir.join(format!("{name}{PART}"));
        let started = std::time::Instant::now();
        let bytes = match self.download(job_id, checksum, name, &part, expected) {
            Ok(b) => b,
            Err(e) => {
                // A failed fetch leaves nothing behind: a partial file may be all a
                // hostile coordinator sent (bytes of no file of the package), and it
                // holds disk the job no longer needs. (A symlink there, refused by the
                // open, is removed too: remove_file does not follow it.)
                let _ = std::fs::remove_file(&part);
                return Err(e);
            }
        };
        if let Err(e) = verify(&part, name, bytes, &expected.xxh3)
            .and_then(|()| std::fs::rename(&part, &dest).map_err(io_err(&dest)))
        {
            let _ = std::fs::remove_file(&part);
            return Err(e);
        }
        tracing::debug!(job = %job_id, file = %name, bytes, seconds = started.elapsed().as_secs_f64(), "package file fetched");
        Ok(())
    }

    /// Fill `part` with the whole file from the coordinator, resuming from its length
    /// after a broken stream. Returns the file's length.
    fn download(
        &self,
        job_id: &str,
        checksum: &str,
        name: &str,
        part: &Path,
        expected: &Expected,
    ) -> Result<u64, FetchError> {
        // Resumable, so not create_new; never through a symlink planted at the path.
        let mut out =
            dray_scene::private_fs::no_follow(OpenOptions::new().create(true).append(true))
                .open(part)
                .map_err(io_err(part))?;
        if !out.metadata().map_err(io_err(part))?.is_file() {
            return Err(io_err(part)(std::io::Error::other("not a regular file")));
        }
        let mut have = out.metadata().map_err(io_err(part))?.len();
        if expected.bytes.is_some_and(|b| have > b) {
            // Longer than the file can be: not a prefix of it.
            out.set_len(0).map_err(io_err(part))?;
            have = 0;
        }
        if let Some(b) = expected.bytes {
            // The size the manifest declares, before a byte of it is written.
            check_room(part, name, b - have)?;
        }
        let mut total = expected.bytes;
        let mut failures = 0u32;
        let mut last_error = String::new();
        loop {
            if total == Some(have) {
                return Ok(have);
            }
            if failures >= MAX_FAILURES {
                return Err(FetchError::Broken {
                    job: job_id.to_string(),
                    file: name.to_string(),
                    failures,
                    bytes: have,
                    message: last_error,
                });
            }
            if failures > 0 {
                std::thread::sleep(FIRST_BACKOFF * (1 << (failures - 1).min(4)));
            }
            let before = have;
            let outcome = self.one_call(
                FetchFileRequest {
                    job_id: job_id.to_string(),
                    package_checksum: checksum.to_string(),
                    path: name.to_string(),
                    offset: have,
                },
                expected,
                &mut out,
                part,
                &mut have,
                &mut total,
            );
            match outcome {
                Ok(()) => {}
                Err(CallError::Fatal(e)) => return Err(e),
                Err(CallError::Status(s)) if s.code() == Code::OutOfRange && have > 0 => {
                    // The partial file is longer than the coordinator's: start over.
                    out.set_len(0).map_err(io_err(part))?;
                    have = 0;
                    failures += 1;
                    last_error = s.message().to_string();
                    continue;
                }
                Err(CallError::Status(s)) if !retryable(s.code()) => {
                    return Err(FetchError::Refused {
                        job: job_id.to_string(),
                        file: name.to_string(),
                        code: s.code(),
                        message: s.message().to_string(),
                    });
                }
                Err(CallError::Status(s)) => {
                    last_error = format!("{:?}: {}", s.code(), s.message());
                }
                Err(CallError::EndedEarly) => {
                    last_error = format!(
                        "the stream ended at byte {have} of {}",
                        total.unwrap_or_default()
                    );
                }
            }
            if have > before {
                failures = 0;
            }
            if total != Some(have) {
                failures += 1;
                tracing::debug!(job = %job_id, file = %name, have, failures, "{last_error}; resuming");
            }
        }
    }

    /// One FetchFile call from `*have`, appending what arrives to `out`.
    #[allow(clippy::too_many_arguments)]
    fn one_call(
        &self,
        request: FetchFileRequest,
        expected: &Expected,
        out: &mut File,
        part: &Path,
        have: &mut u64,
        total: &mut Option<u64>,
    ) -> Result<(), CallError> {
        let name = request.path.clone();
        let mut client = self.client.clone();
        let mut stream = self
            .rt
            .block_on(client.fetch_file(request))
            .map_err(CallError::Status)?
            .into_inner();
        loop {
            let chunk: Option<FileChunk> = self
                .rt
                .block_on(stream.message())
                .map_err(CallError::Status)?;
            let Some(chunk) = chunk else {
                return if *total == Some(*have) {
                    Ok(())
                } else {
                    Err(CallError::EndedEarly)
                };
            };
            let announced = chunk.total_bytes;
            if chunk.xxh3 != expected.xxh3 || expected.bytes.is_some_and(|b| b != announced) {
                return Err(CallError::Fatal(FetchError::Mismatch {
                    file: name,
                    found_bytes: announced,
                    found: chunk.xxh3,
                    expected_bytes: expected
                        .bytes
                        .map_or_else(|| "any size".to_string(), |b| b.to_string()),
                    expected: expected.xxh3.clone(),
                }));
            }
            if *total != Some(announced) {
                // The first chunk: its size is checked before a byte is written.
                if expected.bytes.is_none() && announced > MAX_MANIFEST_BYTES {
                    return Err(CallError::Fatal(FetchError::TooLarge {
                        file: name,
                        bytes: announced,
                        limit: format!("the {MAX_MANIFEST_BYTES}-byte bound on a manifest"),
                    }));
                }
                check_room(part, &name, announced.saturating_sub(*have))
                    .map_err(CallError::Fatal)?;
            }
            *total = Some(announced);
            let end = chunk.offset.checked_add(chunk.data.len() as u64);
            if chunk.offset != *have || end.is_none_or(|e| e > announced) {
                return Err(CallError::Fatal(FetchError::Protocol {
                    file: name,
                    message: format!(
                        "a chunk of {} bytes at offset {} (expected offset {}, file of {announced} bytes)",
                        chunk.data.len(),
                        chunk.offset,
                        *have
                    ),
                }));
            }
            out.write_all(&chunk.data)
                .map_err(|e| CallError::Fatal(io_err(part)(e)))?;
            *have += chunk.data.len() as u64;
            if *have == announced {
                return Ok(());
            }
        }
    }
}

/// Refuse a file of `bytes` more bytes where `part` is when the file system holding it
/// has less room than that: a size a coordinator announces (or a manifest declares) is
/// checked before it is written, not discovered when the disk is full.
fn check_room(part: &Path, name: &str, bytes: u64) -> Result<(), FetchError> {
    let dir = part.parent().unwrap_or(Path::new("."));
    match free_bytes(dir) {
        Some(free) if bytes > free => Err(FetchError::TooLarge {
            file: name.to_string(),
            bytes,
            limit: format!("the {free} bytes free in {}", dir.display()),
        }),
        _ => Ok(()),
    }
}

/// Bytes an unprivileged process may still write on the file system holding `dir`
/// (statvfs), or None when that cannot be told.
fn free_bytes(dir: &Path) -> Option<u64> {
    use std::os::unix::ffi::OsStrExt;
    let c = std::ffi::CString::new(dir.as_os_str().as_bytes()).ok()?;
    // SAFETY: statvfs(3) with a NUL-terminated path and a zeroed struct it fills.
    let mut st: libc::statvfs = unsafe { std::mem::zeroed() };
    if unsafe { libc::statvfs(c.as_ptr(), &mut st) } != 0 {
        return None;
    }
    (st.f_bavail as u64).checked_mul(st.f_frsize as u64)
}

/// Make a package's folder `dir`, or use the one there if it is a real directory (a
/// cache given by the user keeps packages between runs); a symlink or anything else
/// there is refused.
fn package_dir(dir: &Path) -> Result<(), FetchError> {
    match std::fs::create_dir(dir) {
        Ok(()) => Ok(()),
        Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
            let m = std::fs::symlink_metadata(dir).map_err(io_err(dir))?;
            if m.is_dir() {
                Ok(())
            } else {
                Err(io_err(dir)(std::io::Error::other(
                    "exists and is not a directory (a symlink is not followed)",
                )))
            }
        }
        Err(e) => Err(io_err(dir)(e)),
    }
}

/// How one call ended, when not with the whole file.
enum CallError {
    /// A gRPC status (the call or the stream).
    Status(tonic::Status),
    /// The stream ended before the file's end.
    EndedEarly,
    /// Nothing to retry: a wrong file, a local disk error.
    Fatal(FetchError),
}

/// Whether a call failing with `code` may succeed when made again (a broken connection,
/// a coordinator shedding load), as opposed to a refusal.
fn retryable(code: Code) -> bool {
    matches!(
        code,
        Code::Unavailable
            | Code::Unknown
            | Code::Internal
            | Code::Cancelled
            | Code::DeadlineExceeded
            | Code::Aborted
            | Code::ResourceExhausted
    )
}

/// Check the downloaded `part` is `bytes` long and hashes to `xxh3`; remove it if not.
fn verify(part: &Path, name: &str, bytes: u64, xxh3: &str) -> Result<(), FetchError> {
    let file = dray_scene::private_fs::no_follow(OpenOptions::new().read(true))
        .open(part)
        .map_err(io_err(part))?;
    let mut r = HashingReader::new(file);
    std::io::copy(&mut r, &mut std::io::sink()).map_err(io_err(part))?;
    let found = to_hex(r.digest());
    if r.bytes_read() != bytes || found != xxh3 {
        let _ = std::fs::remove_file(part);
        return Err(FetchError::Checksum {
            file: name.to_string(),
            bytes: r.bytes_read(),
            found,
            expected: xxh3.to_string(),
        });
    }
    Ok(())
}

/// Whether `dir` holds the package whose manifest checksum is `checksum`.
fn holds_package(dir: &Path, checksum: &str) -> bool {
    let path = dir.join(MANIFEST_FILE);
    let Ok(mut f) = File::open(&path) else {
        return false;
    };
    let mut r = HashingReader::new(&mut f);
    if std::io::copy(&mut r, &mut std::io::sink()).is_err() {
        return false;
    }
    to_hex(r.digest()) == checksum
}

/// A job's package in the worker's cache: files are fetched into [`RemotePackage::dir`]
/// as they are first needed. Holds its package in the cache until dropped.
pub struct RemotePackage {
    fetcher: Arc<PackageFetcher>,
    job_id: String,
    checksum: String,
    dir: PathBuf,
}

impl std::fmt::Debug for RemotePackage {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RemotePackage")
            .field("job_id", &self.job_id)
            .field("dir", &self.dir)
            .finish()
    }
}

impl RemotePackage {
    /// The local directory (open it with `open_package` once the manifest is here).
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Fetch file `name` of the package unless it is here already. Blocking.
    pub fn fetch(&self, name: &str, expected: &Expected) -> Result<(), FetchError> {
        self.fetcher
            .fetch_file(&self.job_id, &self.checksum, &self.dir, name, expected)
    }

    /// Fetch what every domain shares: the emitters and the textures, when the package
    /// has them. Blocking.
    pub fn fetch_shared(&self, package: &Package) -> Result<(), FetchError> {
        let m = package.manifest();
        if let Some(e) = &m.emitters {
            self.fetch(&e.file, &expect(e.bytes, &e.xxh3))?;
        }
        if let Some(t) = &m.textures_file {
            self.fetch(&t.file, &expect(t.bytes, &t.xxh3))?;
        }
        Ok(())
    }

    /// Fetch domain `d`'s file unless it is here already. Blocking.
    pub fn fetch_domain(&self, package: &Package, d: u32) -> Result<(), FetchError> {
        let e = package
            .manifest()
            .domains
            .get(d as usize)
            .ok_or(FetchError::NoDomain(d))?;
        self.fetch(&e.file, &expect(e.bytes, &e.xxh3))
    }
}

fn expect(bytes: u64, xxh3: &str) -> Expected {
    Expected {
        bytes: Some(bytes),
        xxh3: xxh3.to_string(),
    }
}

impl Drop for RemotePackage {
    fn drop(&mut self) {
        self.fetcher.return_lease(&self.checksum);
    }
}

/// What a file holding exactly `data` is, as a manifest would record it.
pub fn expected_of(data: &[u8]) -> Expected {
    Expected {
        bytes: Some(data.len() as u64),
        xxh3: to_hex(dray_scene::partition::checksum::checksum(data)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_cache_directory_takes_one_worker_at_a_time() {
        let dir = std::env::temp_dir().join(format!("dray-cache-lock-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let first = lock_cache(&dir).unwrap();
        let e = lock_cache(&dir).unwrap_err();
        assert!(matches!(e, FetchError::InUse(_)), "{e}");
        assert!(e.to_string().contains("its own --package-cache"), "{e}");
        drop(first);
        let again = lock_cache(&dir).unwrap();
        drop(again);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn modes_by_name() {
        assert_eq!(FetchMode::from_name("auto"), Some(FetchMode::Auto));
        assert_eq!(FetchMode::from_name("always"), Some(FetchMode::Always));
        assert_eq!(FetchMode::from_name("never"), Some(FetchMode::Never));
        assert_eq!(FetchMode::from_name("sometimes"), None);
    }

    #[test]
    fn a_package_is_held_only_with_the_right_manifest() {
        let dir = std::env::temp_dir().join(format!("dray-holds-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        assert!(!holds_package(&dir, "0000000000000000"));
        std::fs::write(dir.join(MANIFEST_FILE), b"{}").unwrap();
        let sum = expected_of(b"{}").xxh3;
        assert!(holds_package(&dir, &sum));
        assert!(!holds_package(&dir, "0000000000000000"));
        assert!(!holds_package(Path::new("/nonexistent/dray"), &sum));
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_damaged_download_is_discarded() {
        let dir = std::env::temp_dir().join(format!("dray-verify-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let part = dir.join("f.part");
        std::fs::write(&part, b"hello").unwrap();
        let good = expected_of(b"hello");
        verify(&part, "f", 5, &good.xxh3).unwrap();
        let bad = expected_of(b"hellp");
        let e = verify(&part, "f", 5, &bad.xxh3).unwrap_err();
        assert!(e.to_string().contains("CHECKSUM MISMATCH"), "{e}");
        assert!(!part.exists(), "a damaged download is removed");
        let _ = std::fs::remove_dir_all(&dir);
    }
}

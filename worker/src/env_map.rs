//! A job's environment map on a worker (`JobSetup.env_map`, docs/lights.md
//! "Environment maps"): taken from this process's memory when the coordinator shares
//! it (`dray render --workers N`), read at the coordinator's path when that file is here
//! with the setup's checksum (the same disk, a shared volume), fetched from the
//! coordinator's PackageService otherwise, as the package's files are
//! ([`crate::package_fetch`]). A file read or fetched is decoded and turned exactly as
//! the coordinator did (`dray_core::env_map_file`), so every configuration samples the
//! same map.

use std::path::Path;
use std::sync::Arc;

use dray_core::env_map::EnvMap;
use dray_core::env_map_file::{self, EnvMapFormat};
use dray_proto::v1::{EnvMapFile, JobSetup};
use dray_scene::partition::checksum::{checksum, to_hex};
use dray_scene::partition::memory::{MemoryPackages, is_memory_package};

use crate::job_error::JobError;
use crate::package_fetch::{Expected, FetchMode, PackageFetcher};

/// The environment map `setup` asks for, or `None` when it has none. Blocking (reads,
/// may fetch, decodes).
pub fn job_env_map(
    setup: &JobSetup,
    memory: Option<&MemoryPackages>,
    fetcher: Option<&Arc<PackageFetcher>>,
) -> Result<Option<Arc<EnvMap>>, JobError> {
    let Some(file) = &setup.env_map else {
        return Ok(None);
    };
    let spec = setup
        .spec
        .as_ref()
        .and_then(|s| s.lighting.as_ref())
        .and_then(|l| l.env_map.as_ref())
        .ok_or(JobError::Missing("spec.lighting.env_map"))?;
    let invalid = |why: String| JobError::Invalid(format!("lighting.env_map: {why}"));
    if is_memory_package(&file.path) {
        return memory
            .and_then(|m| m.env_map(&file.path))
            .map(Some)
            .ok_or_else(|| {
                invalid(format!(
                    "the map {} is held in the memory of the coordinator's process, and this \
                     worker runs in another",
                    file.path
                ))
            });
    }
    let _span = tracing::info_span!("env_map", job = %setup.job_id, file = %file.name).entered();
    let bytes = match local_copy(file, fetcher) {
        Some(b) => b,
        None => {
            let f = fetcher
                .filter(|f| f.mode() != FetchMode::Never)
                .ok_or_else(|| {
                    invalid(format!(
                        "{} is not here with checksum {} and this worker fetches nothing",
                        file.path, file.xxh3
                    ))
                })?;
            fetch(f, setup, file).map_err(|e| invalid(e.to_string()))?
        }
    };
    let format = EnvMapFormat::of(Path::new(&file.name)).map_err(|e| invalid(e.to_string()))?;
    let pixels =
        env_map_file::decode(&spec.path, format, &bytes).map_err(|e| invalid(e.to_string()))?;
    let map = env_map_file::env_map_of(
        &spec.path,
        pixels,
        spec.rotation_deg
            .ok_or(JobError::Missing("spec.lighting.env_map.rotation_deg"))?,
        spec.intensity
            .ok_or(JobError::Missing("spec.lighting.env_map.intensity"))?,
    )
    .map_err(|e| invalid(e.to_string()))?;
    Ok(Some(Arc::new(map)))
}

/// The file at the coordinator's path when this worker may read it there and it has
/// the setup's size and checksum.
fn local_copy(file: &EnvMapFile, fetcher: Option<&Arc<PackageFetcher>>) -> Option<Vec<u8>> {
    if fetcher.is_some_and(|f| f.mode() == FetchMode::Always) {
        return None;
    }
    let bytes = env_map_file::read_bytes(Path::new(&file.path)).ok()?;
    (bytes.len() as u64 == file.bytes && to_hex(checksum(&bytes)) == file.xxh3).then_some(bytes)
}

/// Fetch the map into the package's folder of the worker's cache and read it.
fn fetch(
    f: &Arc<PackageFetcher>,
    setup: &JobSetup,
    file: &EnvMapFile,
) -> Result<Vec<u8>, crate::package_fetch::FetchError> {
    let remote = f.open(&setup.job_id, &setup.package_checksum)?;
    remote.fetch(
        &file.name,
        &Expected {
            bytes: Some(file.bytes),
            xxh3: file.xxh3.clone(),
        },
    )?;
    let path = remote.dir().join(&file.name);
    tracing::info!(job = %setup.job_id, file = %file.name, bytes = file.bytes, "environment map fetched from the coordinator");
    env_map_file::read_bytes(&path).map_err(|e| crate::package_fetch::FetchError::Io {
        path,
        source: std::io::Error::other(e.to_string()),
    })
}

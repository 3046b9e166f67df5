//! A scene package the coordinator made for one job, and its removal when the job ends.
//!
//! A package the coordinator wrote from a scene belongs to that job: a directory in the
//! work directory on a cluster, or an entry of the in-memory store when the workers share
//! the coordinator's process (`dray render`). A package the job was submitted as is the
//! user's and is never removed, so it has no `OwnedPackage`. A job's environment map,
//! decoded into the in-memory store for workers in the process, goes with it too.

use std::path::PathBuf;
use std::sync::Arc;

use dray_scene::partition::memory::MemoryPackages;

/// Where a job's own package lives.
#[derive(Clone, Debug)]
pub enum OwnedPackage {
    /// A directory the coordinator wrote.
    Dir(PathBuf),
    /// An entry of this process's in-memory store.
    Memory {
        /// The store.
        store: Arc<MemoryPackages>,
        /// The entry (`memory:N`).
        name: String,
    },
    /// Several of these: a job's package and its environment map in memory.
    Many(Vec<OwnedPackage>),
}

impl OwnedPackage {
    /// Delete the package. Failure only costs disk space, so it is logged, not raised.
    pub fn remove(&self) {
        match self {
            OwnedPackage::Dir(d) => {
                if let Err(e) = std::fs::remove_dir_all(d)
                    && e.kind() != std::io::ErrorKind::NotFound
                {
                    tracing::warn!(dir = %d.display(), "cannot remove the job's scene package: {e}");
                }
            }
            OwnedPackage::Memory { store, name } => store.remove(name),
            OwnedPackage::Many(all) => all.iter().for_each(OwnedPackage::remove),
        }
    }

    /// `first` (if any) and `more`, removed together.
    pub fn with(first: Option<OwnedPackage>, more: OwnedPackage) -> Option<OwnedPackage> {
        Some(match first {
            None => more,
            Some(OwnedPackage::Many(mut all)) => {
                all.push(more);
                OwnedPackage::Many(all)
            }
            Some(p) => OwnedPackage::Many(vec![p, more]),
        })
    }
}

/// Remove `package` if there is one.
pub(crate) fn remove_package(package: Option<&OwnedPackage>) {
    if let Some(p) = package {
        p.remove();
    }
}

//! The coordinator's work directory: where it writes the scene packages of jobs that run
//! on workers, one folder per job.
//!
//! Without `--work-dir` it is a private directory of this process (see
//! `dray_scene::private_fs`): a random name in the system temp directory, made with
//! `mkdir` so that a directory another local user made beforehand is never used, mode
//! 0700, and removed with its contents when the last clone of its [`WorkDir`] drops. A
//! directory the user names is trusted as the user's; either way each job's folder in it
//! is made new by the job (`mkdir`, refusing an existing path) and its files are opened
//! without following symlinks.

use std::path::{Path, PathBuf};
use std::sync::Arc;

/// The coordinator's work directory (cheap to clone: clones share the private one).
#[derive(Clone, Debug)]
pub struct WorkDir {
    path: PathBuf,
    /// The private directory's guard, when this process made it.
    private: Option<Arc<tempfile::TempDir>>,
}

impl WorkDir {
    /// A new private directory named `PREFIX…` in the system temp directory.
    pub fn private(prefix: &str) -> std::io::Result<WorkDir> {
        let dir = dray_scene::private_fs::private_temp_dir(prefix, "")?;
        Ok(WorkDir {
            path: dir.path().to_path_buf(),
            private: Some(Arc::new(dir)),
        })
    }

    /// The directory at `path`, which the user chose (and which must exist before a job
    /// is cut into it).
    pub fn given(path: PathBuf) -> WorkDir {
        WorkDir {
            path,
            private: None,
        }
    }

    /// Its path.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Whether this process made it (and removes it when done).
    pub fn is_private(&self) -> bool {
        self.private.is_some()
    }
}

impl From<PathBuf> for WorkDir {
    fn from(path: PathBuf) -> WorkDir {
        WorkDir::given(path)
    }
}

impl std::ops::Deref for WorkDir {
    type Target = Path;
    fn deref(&self) -> &Path {
        &self.path
    }
}

impl Default for WorkDir {
    /// A private directory `dray-coordinator-…`. When the temp directory takes none, a
    /// path nobody made (random, never created): jobs cut into it fail, naming it, and
    /// nothing is written anywhere another user could have prepared.
    fn default() -> WorkDir {
        match WorkDir::private("dray-coordinator-") {
            Ok(d) => d,
            Err(e) => {
                use std::hash::{BuildHasher, Hasher};
                let r = std::collections::hash_map::RandomState::new()
                    .build_hasher()
                    .finish();
                let path =
                    std::env::temp_dir().join(format!("dray-coordinator-unavailable-{r:016x}"));
                tracing::error!(
                    "cannot create a private work directory in {}: {e}; jobs cut into packages will fail (set --work-dir)",
                    std::env::temp_dir().display()
                );
                WorkDir::given(path)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::os::unix::fs::{MetadataExt, PermissionsExt};

    #[test]
    fn the_default_is_private_and_goes_with_its_last_clone() {
        let a = WorkDir::default();
        let b = WorkDir::default();
        assert!(a.is_private());
        assert_ne!(a.path(), b.path());
        let m = std::fs::symlink_metadata(a.path()).unwrap();
        assert!(m.is_dir() && !m.file_type().is_symlink());
        assert_eq!(m.permissions().mode() & 0o777, 0o700);
        // SAFETY: geteuid has no preconditions.
        assert_eq!(m.uid(), unsafe { libc::geteuid() });
        let name = a.file_name().unwrap().to_string_lossy().into_owned();
        assert!(name.starts_with("dray-coordinator-"), "{name}");
        assert!(
            !name.contains(&std::process::id().to_string()),
            "the name is random, not the pid: {name}"
        );
        let path = a.path().to_path_buf();
        let clone = a.clone();
        drop(a);
        assert!(path.is_dir(), "a clone keeps it");
        drop(clone);
        assert!(!path.exists(), "the last clone removes it");
    }
}

//! The state directory, taken only when no one else can change what is in it.
//!
//! A coordinator often runs as root or as a service user, and `--state-dir` may name a
//! path another local user could have made first (under `/tmp`, say). Whoever can write
//! the directory can plant `lock -> /etc/something` and have the coordinator truncate
//! that file, or `images -> elsewhere` and have it write films there. So:
//! - a missing directory (and `images/` in it) is made with mode 0700;
//! - the directory must belong to this process's user (or to root, which this user
//!   trusts anyway), no other user may write it, and a group may write it only when it
//!   is this process's own group (a Kubernetes volume under `fsGroup` is group-owned
//!   and group-writable: that group is the pod's); otherwise the store is refused,
//!   naming the owner and mode, before anything in it is opened;
//! - `images/` must be a real directory (not a link) with the same rules;
//! - files in it are opened without following a link in their last component
//!   (`O_NOFOLLOW`; SQLite's own `SQLITE_OPEN_NOFOLLOW` for the database) and created
//!   with mode 0600, so a link planted before the checks could be passed is an error,
//!   not a write somewhere else.
//!
//! The path given may itself be a link the user made (`/var/lib/dray -> /data/dray`):
//! it is followed, and the rules apply to the directory it leads to, as long as the link
//! belongs to this user or root (a link another user planted is refused).

use std::fs::{File, OpenOptions};
use std::os::unix::fs::{DirBuilderExt, MetadataExt, OpenOptionsExt, PermissionsExt};
use std::path::Path;

use super::StoreError;

/// Mode of the directories the store makes.
const DIR_MODE: u32 = 0o700;
/// Mode of the files the store creates.
pub const FILE_MODE: u32 = 0o600;

/// Make `dir` if it is missing, and check that no other user can change it. `what`
/// names it in errors ("state directory", "images directory").
pub fn prepare(dir: &Path, what: &str) -> Result<(), StoreError> {
    make(dir, true)?;
    let link = std::fs::symlink_metadata(dir).map_err(io_at(dir))?;
    if link.file_type().is_symlink() && !trusted_owner(link.uid()) {
        return Err(unsafe_dir(
            dir,
            what,
            format!("it is a symbolic link owned by uid {}", link.uid()),
        ));
    }
    let meta = std::fs::metadata(dir).map_err(io_at(dir))?;
    check_dir(dir, what, &meta)
}

/// Like [`prepare`] for a directory inside the state directory: it must not be a link
/// at all (nothing but this coordinator makes it).
pub fn prepare_inner(dir: &Path, what: &str) -> Result<(), StoreError> {
    make(dir, false)?;
    let meta = std::fs::symlink_metadata(dir).map_err(io_at(dir))?;
    if meta.file_type().is_symlink() {
        return Err(unsafe_dir(dir, what, "it is a symbolic link".into()));
    }
    check_dir(dir, what, &meta)
}

/// Make `dir` with mode 0700 unless something is there already; with `parents`, make
/// missing parents too (as `create_dir_all` did before; only the leaf is private).
fn make(dir: &Path, parents: bool) -> Result<(), StoreError> {
    let made = match std::fs::DirBuilder::new().mode(DIR_MODE).create(dir) {
        Err(e) if parents && e.kind() == std::io::ErrorKind::NotFound => std::fs::DirBuilder::new()
            .recursive(true)
            .mode(DIR_MODE)
            .create(dir),
        other => other,
    };
    match made {
        Err(e) if e.kind() != std::io::ErrorKind::AlreadyExists => Err(io_at(dir)(e)),
        _ => Ok(()),
    }
}

fn io_at(path: &Path) -> impl Fn(std::io::Error) -> StoreError + '_ {
    move |source| StoreError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// A directory (not a file) whose owner and mode keep other users out.
fn check_dir(dir: &Path, what: &str, meta: &std::fs::Metadata) -> Result<(), StoreError> {
    if !meta.is_dir() {
        return Err(unsafe_dir(dir, what, "it is not a directory".into()));
    }
    check_owner_and_mode(dir, what, meta)
}

/// Open (creating when missing, mode 0600) the file at `path` for reading and writing
/// without following a link in its last component.
pub fn open_file(path: &Path) -> Result<File, StoreError> {
    OpenOptions::new()
        .read(true)
        .write(true)
        .create(true)
        .truncate(false)
        .mode(FILE_MODE)
        .custom_flags(libc::O_NOFOLLOW)
        .open(path)
        .map_err(|source| link_or_io(path, source))
}

/// Create (or replace the contents of) the file at `path`, mode 0600, without following
/// a link in its last component.
pub fn create_file(path: &Path) -> Result<File, StoreError> {
    OpenOptions::new()
        .write(true)
        .create(true)
        .truncate(true)
        .mode(FILE_MODE)
        .custom_flags(libc::O_NOFOLLOW)
        .open(path)
        .map_err(|source| link_or_io(path, source))
}

/// An open that failed on a link (`ELOOP` under `O_NOFOLLOW`) says so plainly.
fn link_or_io(path: &Path, source: std::io::Error) -> StoreError {
    if source.raw_os_error() == Some(libc::ELOOP) {
        return StoreError::Unsafe {
            path: path.to_path_buf(),
            why: "it is a symbolic link, which the job store never follows".into(),
        };
    }
    StoreError::Io {
        path: path.to_path_buf(),
        source,
    }
}

fn check_owner_and_mode(
    dir: &Path,
    what: &str,
    meta: &std::fs::Metadata,
) -> Result<(), StoreError> {
    let (uid, gid, mode) = (meta.uid(), meta.gid(), meta.permissions().mode());
    if !trusted_owner(uid) {
        return Err(unsafe_dir(
            dir,
            what,
            format!(
                "it belongs to uid {uid}, not to this coordinator's user (uid {})",
                euid()
            ),
        ));
    }
    // SAFETY: getegid has no preconditions and cannot fail.
    let own_group = gid == unsafe { libc::getegid() };
    if mode & 0o002 != 0 || (mode & 0o020 != 0 && !own_group) {
        return Err(unsafe_dir(
            dir,
            what,
            format!(
                "its mode {:04o} (group {gid}) lets other users write in it (chmod go-w, or 700)",
                mode & 0o7777
            ),
        ));
    }
    Ok(())
}

fn unsafe_dir(dir: &Path, what: &str, why: String) -> StoreError {
    StoreError::Unsafe {
        path: dir.to_path_buf(),
        why: format!("the {what} is not safe to use: {why}"),
    }
}

/// This process's effective user, or root: the owners whose directories it may use.
fn trusted_owner(uid: u32) -> bool {
    uid == euid() || uid == 0
}

fn euid() -> u32 {
    // SAFETY: geteuid has no preconditions and cannot fail.
    unsafe { libc::geteuid() }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_world_writable_directory_is_refused() {
        let root = tempfile::tempdir().expect("tempdir");
        let dir = root.path().join("state");
        std::fs::create_dir(&dir).expect("mkdir");
        std::fs::set_permissions(&dir, std::fs::Permissions::from_mode(0o777)).expect("chmod");
        let e = prepare(&dir, "state directory").expect_err("0777 must be refused");
        let msg = e.to_string();
        assert!(msg.contains("0777") && msg.contains("other users"), "{msg}");
        // Writable by this process's own group (a volume under Kubernetes' fsGroup).
        std::fs::set_permissions(&dir, std::fs::Permissions::from_mode(0o2770)).expect("chmod");
        prepare(&dir, "state directory").expect("its own group may write it");
    }

    #[test]
    fn a_new_directory_is_private_and_accepted() {
        let root = tempfile::tempdir().expect("tempdir");
        let dir = root.path().join("a/b/state");
        prepare(&dir, "state directory").expect("a new directory is fine");
        let mode = std::fs::metadata(&dir).expect("stat").permissions().mode();
        assert_eq!(mode & 0o777, 0o700);
    }

    #[test]
    fn a_link_in_place_of_a_file_is_not_followed() {
        let root = tempfile::tempdir().expect("tempdir");
        let target = root.path().join("victim");
        std::fs::write(&target, b"keep me").expect("write");
        let lock = root.path().join("lock");
        std::os::unix::fs::symlink(&target, &lock).expect("symlink");
        let e = open_file(&lock).expect_err("a link must not be opened");
        assert!(e.to_string().contains("symbolic link"), "{e}");
        let e = create_file(&lock).expect_err("a link must not be written through");
        assert!(e.to_string().contains("symbolic link"), "{e}");
        assert_eq!(std::fs::read(&target).expect("read"), b"keep me");
    }

    #[test]
    fn an_images_link_is_refused() {
        let root = tempfile::tempdir().expect("tempdir");
        let elsewhere = root.path().join("elsewhere");
        std::fs::create_dir(&elsewhere).expect("mkdir");
        let images = root.path().join("images");
        std::os::unix::fs::symlink(&elsewhere, &images).expect("symlink");
        let e = prepare_inner(&images, "images directory").expect_err("a link is refused");
        assert!(e.to_string().contains("symbolic link"), "{e}");
    }
}

//! Files and directories other local users cannot plant or redirect.
//!
//! dray runs as root in some deployments, and the system temp directory is writable by
//! every local user. A directory there with a predictable name (`/tmp/dray-...-<pid>`)
//! can be made first by another user, who then owns it and can put files or symlinks in
//! it before dray writes there: a token replaced by one the attacker chose, a root-owned
//! file truncated through a `*.part` symlink. So:
//!
//! - a directory dray makes for itself is a [`private_temp_dir`]: a random name, made
//!   with `mkdir` (which fails on an existing path, so nothing made beforehand is ever
//!   used), mode 0700 (no other user may enter it), removed when its guard drops;
//! - files dray opens to write in a directory are opened with [`no_follow`]
//!   (`O_NOFOLLOW`): a symlink at the last component is refused (`ELOOP`), never
//!   followed, in a directory the user named as in a private one.

use std::fs::OpenOptions;
use std::path::Path;

/// A new directory in the system temp directory named `PREFIX` + random characters +
/// `suffix`, made atomically, owner-only (0700), and removed (with its contents) when
/// the returned guard drops.
pub fn private_temp_dir(prefix: &str, suffix: &str) -> std::io::Result<tempfile::TempDir> {
    private_dir_in(&std::env::temp_dir(), prefix, suffix)
}

/// [`private_temp_dir`] in `parent`.
pub fn private_dir_in(
    parent: &Path,
    prefix: &str,
    suffix: &str,
) -> std::io::Result<tempfile::TempDir> {
    let mut b = tempfile::Builder::new();
    b.prefix(prefix).suffix(suffix).rand_bytes(12);
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        b.permissions(std::fs::Permissions::from_mode(0o700));
    }
    b.tempdir_in(parent)
}

/// `options` set not to follow a symlink at the path's last component: opening one
/// fails (`ELOOP`) instead of writing wherever it points.
pub fn no_follow(options: &mut OpenOptions) -> &mut OpenOptions {
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        options.custom_flags(libc::O_NOFOLLOW);
    }
    options
}

/// A new file at `path` to write, mode `mode` (less the umask): refused when anything is
/// there already (a file, a symlink: `create_new` is `O_EXCL`, which never follows one).
pub fn create_new(path: &Path, mode: u32) -> std::io::Result<std::fs::File> {
    let mut o = OpenOptions::new();
    o.write(true).create_new(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        o.mode(mode);
    }
    #[cfg(not(unix))]
    let _ = mode;
    no_follow(&mut o).open(path)
}

/// `path` truncated (or made) to write, refusing a symlink there (see [`no_follow`]).
pub fn create_truncate(path: &Path) -> std::io::Result<std::fs::File> {
    no_follow(OpenOptions::new().write(true).create(true).truncate(true)).open(path)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::os::unix::fs::{MetadataExt, PermissionsExt};

    #[test]
    fn a_private_dir_is_new_owner_only_and_unpredictable() {
        let a = private_temp_dir("dray-private-test-", "").unwrap();
        let b = private_temp_dir("dray-private-test-", "").unwrap();
        assert_ne!(a.path(), b.path(), "two calls, two names");
        let m = std::fs::symlink_metadata(a.path()).unwrap();
        assert!(m.is_dir());
        assert_eq!(m.permissions().mode() & 0o777, 0o700);
        // SAFETY: geteuid has no preconditions.
        assert_eq!(m.uid(), unsafe { libc::geteuid() });
        let name = a.path().file_name().unwrap().to_string_lossy().into_owned();
        assert!(name.len() >= "dray-private-test-".len() + 12, "{name}");
        let path = a.path().to_path_buf();
        drop(a);
        assert!(!path.exists(), "removed on drop");
    }

    #[test]
    fn symlinks_are_refused_not_followed() {
        let d = private_temp_dir("dray-nofollow-test-", "").unwrap();
        let target = d.path().join("target");
        std::fs::write(&target, b"precious").unwrap();
        let link = d.path().join("link");
        std::os::unix::fs::symlink(&target, &link).unwrap();
        assert!(create_truncate(&link).is_err());
        assert!(create_new(&link, 0o600).is_err());
        let e = no_follow(OpenOptions::new().append(true).create(true))
            .open(&link)
            .unwrap_err();
        assert_eq!(e.raw_os_error(), Some(libc::ELOOP), "{e}");
        assert_eq!(std::fs::read(&target).unwrap(), b"precious");
        // A plain new file is made.
        let f = d.path().join("new");
        create_new(&f, 0o600).unwrap();
        assert!(
            create_new(&f, 0o600).is_err(),
            "an existing file is refused"
        );
        create_truncate(&f).unwrap();
    }
}

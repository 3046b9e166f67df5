//! The files a scene refers to: glTF buffers and images, OBJ material libraries and
//! textures. A scene may only read what its author shipped with it, so a reference must
//! be a relative path that resolves (symlinks and `..` included) inside the folder that
//! holds the scene file, to a regular file. Absolute paths, `file:` and other URI
//! schemes, escapes from the folder, directories, FIFOs and device files are refused
//! with a message that names the reference (shortened) and never quotes what any file
//! contains. The scene file itself must be a regular file too ([`check_scene_file`]).

use std::fs::File;
use std::io::Read;
use std::path::{Component, Path, PathBuf};

use crate::error::SceneError;

/// How many characters of a reference an error message shows (data URIs can be
/// megabytes long, and a path is the author's text, not ours).
pub const SHOWN_CHARS: usize = 60;

/// `reference` as messages show it: quoted with escapes (so it stays on one line), at
/// most [`SHOWN_CHARS`] characters, then "…".
pub fn display_reference(reference: &str) -> String {
    let escaped: String = reference.chars().flat_map(char::escape_debug).collect();
    if escaped.chars().count() <= SHOWN_CHARS {
        format!("\"{escaped}\"")
    } else {
        let head: String = escaped.chars().take(SHOWN_CHARS).collect();
        format!("\"{head}\"…")
    }
}

/// Why a reference could not be opened.
#[derive(Debug)]
pub enum RefError {
    /// No such file inside the scene's folder (OBJ treats a missing material library
    /// as a warning).
    NotFound,
    /// Refused or unreadable; the message says why, without file contents.
    Refused(String),
}

impl RefError {
    pub fn message(&self) -> String {
        match self {
            RefError::NotFound => "no such file in the scene's folder".to_string(),
            RefError::Refused(m) => m.clone(),
        }
    }
}

/// A referenced file, open, with its length when it was opened.
pub struct Opened {
    pub file: File,
    pub len: u64,
    /// The resolved (canonical) path.
    pub path: PathBuf,
}

impl Opened {
    /// Read at most `limit` bytes (never more than the file had when opened, so a file
    /// that grows while it is read cannot make the read endless).
    pub fn read_at_most(self, limit: u64) -> std::io::Result<Vec<u8>> {
        let limit = limit.min(self.len);
        let mut out = Vec::with_capacity(usize::try_from(limit).unwrap_or(0).min(1 << 26));
        self.file.take(limit).read_to_end(&mut out)?;
        Ok(out)
    }

    /// Read the whole file (as long as it was when opened).
    pub fn read_all(self) -> std::io::Result<Vec<u8>> {
        let len = self.len;
        self.read_at_most(len)
    }
}

/// The folder references of `scene` resolve against.
fn scene_folder(scene: &Path) -> &Path {
    match scene.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    }
}

/// Resolve the relative path `reference` against the folder of the scene file `scene`
/// and open it, refusing anything outside that folder or not a regular file.
pub fn open_in_scene_folder(scene: &Path, reference: &str) -> Result<Opened, RefError> {
    let refused = |m: &str| RefError::Refused(m.to_string());
    if reference.is_empty() {
        return Err(refused("the reference is empty"));
    }
    if reference.contains('\0') {
        return Err(refused("the reference contains a NUL character"));
    }
    let rel = Path::new(reference);
    let has_drive = reference.len() >= 2
        && reference.as_bytes()[1] == b':'
        && reference.as_bytes()[0].is_ascii_alphabetic();
    if rel.is_absolute()
        || rel.has_root()
        || reference.starts_with('\\')
        || has_drive
        || rel
            .components()
            .any(|c| matches!(c, Component::Prefix(_) | Component::RootDir))
    {
        return Err(refused(
            "absolute paths are not allowed (a scene may only refer to files in its own folder)",
        ));
    }
    let folder = scene_folder(scene);
    let folder_real = std::fs::canonicalize(folder).map_err(|e| {
        RefError::Refused(format!("cannot resolve the scene's folder: {}", e.kind()))
    })?;
    let real = match std::fs::canonicalize(folder.join(rel)) {
        Ok(p) => p,
        // A name that climbs out of the folder is refused as such whether or not (and
        // however) it fails to resolve; it says nothing about what exists out there.
        Err(_) if escapes_lexically(rel) => {
            return Err(refused("resolves outside the scene's folder"));
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Err(RefError::NotFound),
        Err(e) => return Err(RefError::Refused(format!("cannot resolve: {}", e.kind()))),
    };
    if !real.starts_with(&folder_real) {
        return Err(refused("resolves outside the scene's folder"));
    }
    let file = open_nonblocking(&real)
        .map_err(|e| RefError::Refused(format!("cannot open: {}", e.kind())))?;
    let meta = file
        .metadata()
        .map_err(|e| RefError::Refused(format!("cannot read: {}", e.kind())))?;
    if !meta.is_file() {
        return Err(refused(
            "is not a regular file (directories, devices and FIFOs are refused)",
        ));
    }
    Ok(Opened {
        file,
        len: meta.len(),
        path: real,
    })
}

/// Whether `rel`'s `..` components climb above its start, before any symlink is looked at.
fn escapes_lexically(rel: &Path) -> bool {
    let mut depth = 0i64;
    for c in rel.components() {
        match c {
            Component::ParentDir => {
                depth -= 1;
                if depth < 0 {
                    return true;
                }
            }
            Component::Normal(_) => depth += 1,
            _ => {}
        }
    }
    false
}

/// Open for reading without blocking: opening a FIFO for reading would otherwise wait
/// for a writer forever. (Regular files ignore the flag.)
fn open_nonblocking(path: &Path) -> std::io::Result<File> {
    let mut options = std::fs::OpenOptions::new();
    options.read(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        options.custom_flags(libc::O_NONBLOCK);
    }
    options.open(path)
}

/// The scene file itself must be a regular file: `/dev/zero` (or a symlink to it) would
/// be read until memory runs out, and a FIFO would block the loader forever.
pub fn check_scene_file(path: &Path) -> Result<(), SceneError> {
    let io = |error| SceneError::Io {
        path: path.to_path_buf(),
        error,
    };
    let meta = std::fs::metadata(path).map_err(io)?;
    if !meta.is_file() {
        return Err(SceneError::Format {
            path: path.to_path_buf(),
            message: "not a regular file (directories, devices and FIFOs are refused)".to_string(),
        });
    }
    Ok(())
}

/// Open the scene file for reading (after [`check_scene_file`]), without blocking on a
/// FIFO swapped in since, and check again on the open file.
pub fn open_scene_file(path: &Path) -> Result<Opened, SceneError> {
    check_scene_file(path)?;
    let io = |error| SceneError::Io {
        path: path.to_path_buf(),
        error,
    };
    let file = open_nonblocking(path).map_err(io)?;
    let meta = file.metadata().map_err(io)?;
    if !meta.is_file() {
        return Err(SceneError::Format {
            path: path.to_path_buf(),
            message: "not a regular file (directories, devices and FIFOs are refused)".to_string(),
        });
    }
    Ok(Opened {
        file,
        len: meta.len(),
        path: path.to_path_buf(),
    })
}

/// The whole scene file (see [`open_scene_file`]), for the importers that parse from
/// memory.
pub fn read_scene_file(path: &Path) -> Result<Vec<u8>, SceneError> {
    open_scene_file(path)?
        .read_all()
        .map_err(|error| SceneError::Io {
            path: path.to_path_buf(),
            error,
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn references_are_shown_short_and_on_one_line() {
        assert_eq!(display_reference("a.bin"), "\"a.bin\"");
        assert_eq!(display_reference("a\nb"), "\"a\\nb\"");
        let long = "x".repeat(500);
        let shown = display_reference(&long);
        assert!(
            shown.ends_with('…') && shown.chars().count() < 70,
            "{shown}"
        );
    }

    #[test]
    fn lexical_escapes() {
        assert!(escapes_lexically(Path::new("../a")));
        assert!(escapes_lexically(Path::new("a/../../b")));
        assert!(!escapes_lexically(Path::new("a/../b")));
        assert!(!escapes_lexically(Path::new("./b")));
    }
}

//! A finished job's image on disk, beside the job store: its exact fixed-point sums (so
//! GetImage encodes PNG at any exposure, or EXR, exactly as from the film in memory).
//!
//! Written atomically: the bytes go to a temporary file in the same directory, which is
//! flushed to disk, renamed over the final name and the directory flushed too. A reader
//! therefore sees either no file or a whole one, whenever the process is killed; a
//! checksum over the whole file catches what the disk itself may do.
//!
//! Layout (little-endian): `DRAYFILM`, format version (u32), width (u32), height (u32),
//! non-finite count (u64), width × height × 3 sums (i64), then XXH3-64 of all of the
//! above (u64). Format 2 (written only for a film some of whose pixels adaptive
//! sampling stopped early) has width × height sample counts (u32, 0 for a pixel that
//! did not stop: `Film::stops`) between the sums and the checksum. Format 3 (written
//! only for a film with AOVs, `Film::aovs`) has, after the header, a flags word (u32;
//! bit 0: the sample counts follow the sums) and the AOV set (u32; bit `i` for
//! `Aov::ALL[i]`), then the sums, the sample counts if flagged, width × height × 8 AOV
//! words (i64, `AovFilm::sum_fixed`), and the checksum. Formats 1 and 2 are still
//! written for films without AOVs, so older coordinators read them.

use std::io::Write;
use std::path::{Path, PathBuf};

use dray_core::aov::{AOV_WORDS, Aov, AovSet};
use dray_core::film::Film;
use dray_scene::partition::checksum::checksum;

use super::StoreError;

const MAGIC: &[u8; 8] = b"DRAYFILM";
/// The format of a film without per-pixel sample counts.
const FORMAT: u32 = 1;
/// The format of a film with them (adaptive sampling).
const FORMAT_STOPS: u32 = 2;
/// The format of a film with AOVs (and sample counts or not); the newest read.
const FORMAT_AOVS: u32 = 3;
const HEADER: usize = 8 + 4 + 4 + 4 + 8;
/// Format 3's flags and AOV set.
const AOV_HEADER: usize = 4 + 4;
/// Format 3's flag: sample counts follow the sums.
const HAS_STOPS: u32 = 1;

/// The film as the bytes of an image file.
pub fn encode(film: &Film) -> Vec<u8> {
    let pixels = film.width as usize * film.height as usize;
    let mut out = Vec::with_capacity(HEADER + pixels * 24 + 8);
    out.extend_from_slice(MAGIC);
    let format = if film.aovs.is_some() {
        FORMAT_AOVS
    } else if film.stops().is_some() {
        FORMAT_STOPS
    } else {
        FORMAT
    };
    out.extend_from_slice(&format.to_le_bytes());
    out.extend_from_slice(&film.width.to_le_bytes());
    out.extend_from_slice(&film.height.to_le_bytes());
    out.extend_from_slice(&film.nonfinite.to_le_bytes());
    if let Some(a) = &film.aovs {
        let flags = if film.stops().is_some() { HAS_STOPS } else { 0 };
        out.extend_from_slice(&flags.to_le_bytes());
        out.extend_from_slice(&set_bits(a.set).to_le_bytes());
    }
    for p in 0..pixels as u32 {
        out.extend_from_slice(&words_le(&film.sum_fixed(p)));
    }
    for n in film.stops().unwrap_or(&[]) {
        out.extend_from_slice(&n.to_le_bytes());
    }
    if let Some(a) = &film.aovs {
        for p in 0..pixels as u32 {
            out.extend_from_slice(&words_le(&a.sum_fixed(p)));
        }
    }
    let sum = checksum(&out);
    out.extend_from_slice(&sum.to_le_bytes());
    out
}

/// The film in `bytes` (read from `path`, which errors name).
pub fn decode(bytes: &[u8], path: &Path) -> Result<Film, StoreError> {
    let corrupt = |why: &str| StoreError::Corrupt {
        file: path.to_path_buf(),
        why: why.to_string(),
    };
    if bytes.len() < HEADER + 8 || &bytes[..8] != MAGIC {
        return Err(corrupt("not a dray image file"));
    }
    let (body, tail) = bytes.split_at(bytes.len() - 8);
    let want = u64::from_le_bytes(tail.try_into().map_err(|_| corrupt("truncated"))?);
    if checksum(body) != want {
        return Err(corrupt("checksum mismatch (the file is damaged)"));
    }
    let u32_at = |o: usize| u32::from_le_bytes([body[o], body[o + 1], body[o + 2], body[o + 3]]);
    let format = u32_at(8);
    if !(FORMAT..=FORMAT_AOVS).contains(&format) {
        return Err(StoreError::Newer {
            file: path.to_path_buf(),
            found: format,
            supported: FORMAT_AOVS,
        });
    }
    let (width, height) = (u32_at(12), u32_at(16));
    let mut nf = [0u8; 8];
    nf.copy_from_slice(&body[20..28]);
    let pixels = width as usize * height as usize;
    // (flags, AOV set) and where the sums start.
    let (has_stops, set, start) = match format {
        FORMAT_AOVS => {
            if body.len() < HEADER + AOV_HEADER {
                return Err(corrupt("truncated"));
            }
            let flags = u32_at(HEADER);
            let set = set_of(u32_at(HEADER + 4))
                .filter(|s| !s.is_empty() && flags & !HAS_STOPS == 0)
                .ok_or_else(|| corrupt("its AOV header names nothing this build writes"))?;
            (flags & HAS_STOPS != 0, set, HEADER + AOV_HEADER)
        }
        f => (f == FORMAT_STOPS, AovSet::NONE, HEADER),
    };
    let per_pixel =
        24 + if has_stops { 4 } else { 0 } + if set.is_empty() { 0 } else { 8 * AOV_WORDS };
    if body.len() != start + pixels * per_pixel {
        return Err(corrupt("its size does not match its width and height"));
    }
    let mut film = Film::with_aovs(width, height, set);
    film.nonfinite = u64::from_le_bytes(nf);
    let (sums, rest) = body[start..].split_at(pixels * 24);
    let (stops, aovs) = rest.split_at(if has_stops { pixels * 4 } else { 0 });
    for (p, px) in sums.chunks_exact(24).enumerate() {
        film.add_fixed(p as u32, read_words(px));
    }
    for (p, n) in stops.chunks_exact(4).enumerate() {
        film.set_stop(p as u32, u32::from_le_bytes([n[0], n[1], n[2], n[3]]));
    }
    if let Some(a) = film.aovs.as_mut() {
        for (p, px) in aovs.chunks_exact(8 * AOV_WORDS).enumerate() {
            a.set_fixed(p as u32, read_words(px));
        }
    }
    Ok(film)
}

/// `N` little-endian i64 words from `8 N` bytes (a pixel's sums, or its AOV words).
pub(crate) fn read_words<const N: usize>(px: &[u8]) -> [i64; N] {
    let mut s = [0i64; N];
    for (c, b) in s.iter_mut().zip(px.chunks_exact(8)) {
        let mut a = [0u8; 8];
        a.copy_from_slice(b);
        *c = i64::from_le_bytes(a);
    }
    s
}

/// `words` as little-endian bytes, 8 a word.
pub(crate) fn words_le<'a>(words: impl IntoIterator<Item = &'a i64>) -> Vec<u8> {
    words.into_iter().flat_map(|w| w.to_le_bytes()).collect()
}

/// An AOV set as format 3 keeps it: bit `i` for `Aov::ALL[i]`.
fn set_bits(set: AovSet) -> u32 {
    Aov::ALL
        .iter()
        .enumerate()
        .filter(|(_, a)| set.contains(**a))
        .fold(0, |b, (i, _)| b | 1 << i)
}

/// The set `bits` ([`set_bits`]) stands for; None when it has a bit this build does
/// not know.
fn set_of(bits: u32) -> Option<AovSet> {
    if bits >> Aov::ALL.len() != 0 {
        return None;
    }
    Some(
        Aov::ALL
            .iter()
            .enumerate()
            .filter(|(i, _)| bits & (1 << i) != 0)
            .fold(AovSet::NONE, |s, (_, a)| s.with(*a)),
    )
}

/// The largest image file read back: the header, 24 bytes a pixel for the largest film a
/// job may ask for (65,536 x 65,536 is beyond every limit; this is a bound on what a
/// damaged or planted file can make the coordinator allocate, not a policy).
const MAX_FILE_BYTES: u64 = (HEADER as u64) + (1u64 << 36) + 8;

/// Read the film at `path`: a regular file only (never through a link, a device or a
/// FIFO, which could read forever or block a thread for good), of a bounded size.
pub fn read(path: &Path) -> Result<Film, StoreError> {
    use std::io::Read;
    use std::os::unix::fs::OpenOptionsExt;
    let io = |source| StoreError::Io {
        path: path.to_path_buf(),
        source,
    };
    let corrupt = |why: &str| StoreError::Corrupt {
        file: path.to_path_buf(),
        why: why.to_string(),
    };
    // O_NONBLOCK: opening a FIFO must not wait for a writer; a regular file ignores it.
    let f = std::fs::OpenOptions::new()
        .read(true)
        .custom_flags(libc::O_NOFOLLOW | libc::O_NONBLOCK)
        .open(path)
        .map_err(|e| {
            if e.raw_os_error() == Some(libc::ELOOP) {
                corrupt("it is a symbolic link, which the job store never follows")
            } else {
                io(e)
            }
        })?;
    let meta = f.metadata().map_err(io)?;
    if !meta.is_file() {
        return Err(corrupt("it is not a regular file"));
    }
    if meta.len() > MAX_FILE_BYTES {
        return Err(corrupt("it is larger than any image the store writes"));
    }
    let mut bytes = Vec::with_capacity(meta.len() as usize);
    f.take(meta.len()).read_to_end(&mut bytes).map_err(io)?;
    decode(&bytes, path)
}

/// Write `bytes` to `path` atomically: a temporary file beside it, flushed, renamed over
/// `path`, then the directory flushed so the rename itself is on disk.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), StoreError> {
    let io = |p: &Path| {
        let p = p.to_path_buf();
        move |source| StoreError::Io { path: p, source }
    };
    let dir = path.parent().unwrap_or(Path::new("."));
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned());
    let tmp: PathBuf = dir.join(format!(".{}.tmp", name.unwrap_or_default()));
    let mut f = super::state_dir::create_file(&tmp)?;
    let written = f
        .write_all(bytes)
        .and_then(|()| f.sync_all())
        .map_err(io(&tmp));
    drop(f);
    if let Err(e) = written.and_then(|()| std::fs::rename(&tmp, path).map_err(io(path))) {
        // A full disk: the partial file must not keep the space (nor outlive us).
        let _ = std::fs::remove_file(&tmp);
        return Err(e);
    }
    sync_dir(dir)
}

/// Flush directory `dir`'s entries (a rename or a new file in it) to disk.
pub fn sync_dir(dir: &Path) -> Result<(), StoreError> {
    std::fs::File::open(dir)
        .and_then(|d| d.sync_all())
        .map_err(|source| StoreError::Io {
            path: dir.to_path_buf(),
            source,
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A link to `/dev/zero` read until allocation failed; a FIFO pinned the reading
    /// thread for good (issue 45, item 6). Both are errors at once now, and so is a
    /// planted link to a real image.
    #[test]
    fn links_devices_and_fifos_are_not_read() {
        let dir = tempfile::tempdir().unwrap();
        let zero = dir.path().join("zero.film");
        std::os::unix::fs::symlink("/dev/zero", &zero).unwrap();
        let e = read(&zero).unwrap_err().to_string();
        assert!(e.contains("symbolic link"), "{e}");
        let real = dir.path().join("real.film");
        write_atomic(&real, &encode(&film())).unwrap();
        let link = dir.path().join("link.film");
        std::os::unix::fs::symlink(&real, &link).unwrap();
        assert!(read(&link).is_err());
        assert_eq!(read(&real).unwrap().sum_fixed(1), film().sum_fixed(1));
        let fifo = dir.path().join("fifo.film");
        let c = std::ffi::CString::new(fifo.as_os_str().as_encoded_bytes()).unwrap();
        // SAFETY: a valid NUL-terminated path.
        assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
        let e = read(&fifo).unwrap_err().to_string();
        assert!(e.contains("not a regular file"), "{e}");
        let e = read(Path::new("/dev/zero")).unwrap_err().to_string();
        assert!(e.contains("not a regular file"), "{e}");
    }

    fn film() -> Film {
        let mut f = Film::new(3, 2);
        for p in 0..6 {
            f.add_fixed(p, [p as i64 - 2, i64::MIN + p as i64, i64::MAX - 7]);
        }
        f.nonfinite = 5;
        f
    }

    #[test]
    fn round_trips_exactly_and_atomically() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("job-1.film");
        write_atomic(&path, &encode(&film())).unwrap();
        assert_eq!(read(&path).unwrap(), film());
        let names: Vec<_> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(names, ["job-1.film"], "no temporary file is left");
    }

    /// A film some of whose pixels adaptive sampling stopped keeps their counts.
    #[test]
    fn round_trips_the_samples_of_pixels_that_stopped() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("job-2.film");
        let mut f = film();
        f.set_stop(1, 16);
        f.set_stop(4, 32);
        write_atomic(&path, &encode(&f)).unwrap();
        let back = read(&path).unwrap();
        assert_eq!(back.stops(), Some(&[0, 16, 0, 0, 32, 0][..]));
        assert_eq!(back, f);
    }

    /// A film with AOVs (format 3) keeps them, with and without sample counts; formats
    /// 1 and 2 are still what a film without AOVs is written as.
    #[test]
    fn round_trips_aovs_with_and_without_stops() {
        let set = AovSet::parse(&["albedo", "depth", "samples"]).unwrap();
        let mut f = Film::with_aovs(3, 2, set);
        for p in 0..6 {
            f.add_fixed(p, [p as i64, 1, 2]);
            f.aovs.as_mut().unwrap().add_fixed(
                p,
                &[p as i64, -1, i64::MAX, 3, 4, 5, 6, i64::MIN + p as i64],
            );
        }
        f.nonfinite = 2;
        let bytes = encode(&f);
        assert_eq!(u32::from_le_bytes(bytes[8..12].try_into().unwrap()), 3);
        let back = decode(&bytes, Path::new("a.film")).unwrap();
        assert_eq!(back, f);
        assert_eq!(back.aov_set(), set);
        f.set_stop(2, 16);
        let back = decode(&encode(&f), Path::new("a.film")).unwrap();
        assert_eq!(back.stops(), Some(&[0, 0, 16, 0, 0, 0][..]));
        assert_eq!(back, f);
        // Without AOVs: formats 1 and 2, as before.
        let format = |f: &Film| u32::from_le_bytes(encode(f)[8..12].try_into().unwrap());
        let mut plain = film();
        assert_eq!(format(&plain), 1);
        plain.set_stop(0, 8);
        assert_eq!(format(&plain), 2);
        // An AOV set with a bit this build does not know is damage, named.
        let mut bad = encode(&f);
        bad[HEADER + 4] |= 0x80;
        let n = bad.len() - 8;
        let sum = checksum(&bad[..n]);
        bad[n..].copy_from_slice(&sum.to_le_bytes());
        let e = decode(&bad, Path::new("b.film")).unwrap_err().to_string();
        assert!(e.contains("b.film") && e.contains("AOV header"), "{e}");
    }

    #[test]
    fn damage_is_an_error_naming_the_file() {
        let mut bytes = encode(&film());
        bytes[40] ^= 1;
        let err = decode(&bytes, Path::new("/x/job-1.film")).unwrap_err();
        let msg = err.to_string();
        assert!(
            msg.contains("/x/job-1.film") && msg.contains("checksum"),
            "{msg}"
        );
        let err = decode(&bytes[..20], Path::new("/x/a.film")).unwrap_err();
        assert!(matches!(err, StoreError::Corrupt { .. }), "{err}");
    }
}

//! Reading an environment map (`--env-map FILE`) from an equirectangular `.hdr`
//! (Radiance RGBE, through the `image` crate) or `.exr` (OpenEXR, through the `exr`
//! crate) into an [`EnvMap`].
//!
//! The reader works on the file's bytes, not its path, so the coordinator reads a file
//! once to checksum it (the checksum workers check what they fetch against) and decodes
//! the same bytes. The image's size is read from its header and checked against
//! [`MAX_ENV_MAP_PIXELS`] before any pixel is decoded: a hostile header cannot make the
//! reader allocate more than a map may hold. Every error names the file and what is
//! wrong with it.

use std::io::Cursor;
use std::path::Path;

use glam::Vec3;

use crate::env_map::{EnvMap, EnvMapError, MAX_ENV_MAP_PIXELS};

/// The kinds of file an environment map may be read from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum EnvMapFormat {
    /// Radiance RGBE (`.hdr`, `.pic`).
    Hdr,
    /// OpenEXR (`.exr`).
    Exr,
}

impl EnvMapFormat {
    /// The format of `path`, by its extension (case-insensitive).
    pub fn of(path: &Path) -> Result<EnvMapFormat, EnvMapFileError> {
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase)
            .unwrap_or_default();
        match ext.as_str() {
            "hdr" | "pic" => Ok(EnvMapFormat::Hdr),
            "exr" => Ok(EnvMapFormat::Exr),
            _ => Err(EnvMapFileError::Extension {
                file: path.display().to_string(),
                ext,
            }),
        }
    }

    fn name(self) -> &'static str {
        match self {
            EnvMapFormat::Hdr => "Radiance .hdr",
            EnvMapFormat::Exr => "OpenEXR",
        }
    }
}

/// Why an environment map cannot be read from a file; each names the file.
#[derive(Debug, thiserror::Error)]
pub enum EnvMapFileError {
    #[error("environment map {file}: no such file")]
    Missing { file: String },
    #[error("environment map {file}: cannot read it: {message}")]
    Io { file: String, message: String },
    #[error(
        "environment map {file}: unsupported file type {ext:?}: an environment map is an equirectangular .hdr (Radiance) or .exr (OpenEXR) image"
    )]
    Extension { file: String, ext: String },
    #[error(
        "environment map {file}: {width}x{height} pixels is more than the {MAX_ENV_MAP_PIXELS} (4096x2048) a map may have; scale it down"
    )]
    TooLarge {
        file: String,
        width: usize,
        height: usize,
    },
    #[error("environment map {file}: not a readable {format} image: {message}")]
    Decode {
        file: String,
        format: &'static str,
        message: String,
    },
    #[error("environment map {file}: pixel ({x}, {y}) is ({r}, {g}, {b}): radiance must be finite")]
    Pixel {
        file: String,
        x: usize,
        y: usize,
        r: f32,
        g: f32,
        b: f32,
    },
    #[error("environment map {file}: {source}")]
    Map { file: String, source: EnvMapError },
}

/// The pixels of an environment map file: `width` x `height` radiance values, row-major,
/// top row first, as read (no rotation, no intensity).
#[derive(Clone, Debug)]
pub struct EnvPixels {
    pub width: usize,
    pub height: usize,
    pub pixels: Vec<Vec3>,
    /// Negative components read and set to 0 (see [`decode`]).
    pub negatives_zeroed: usize,
}

/// The largest environment map file read (256 MiB): a 4096 x 2048 map of
/// uncompressed 32-bit RGBA OpenEXR is 128 MiB. Checked before the file is read, and by
/// a worker before it fetches one.
pub const MAX_ENV_MAP_FILE_BYTES: u64 = 256 << 20;

/// Read the file at `path` whole (its bytes, for [`decode`] and a checksum), if it is
/// at most [`MAX_ENV_MAP_FILE_BYTES`].
pub fn read_bytes(path: &Path) -> Result<Vec<u8>, EnvMapFileError> {
    let file = || path.display().to_string();
    let io = |e: std::io::Error| match e.kind() {
        std::io::ErrorKind::NotFound => EnvMapFileError::Missing { file: file() },
        _ => EnvMapFileError::Io {
            file: file(),
            message: e.to_string(),
        },
    };
    let f = std::fs::File::open(path).map_err(io)?;
    let len = f.metadata().map_err(io)?.len();
    if len > MAX_ENV_MAP_FILE_BYTES {
        return Err(EnvMapFileError::Io {
            file: file(),
            message: format!(
                "{len} bytes is more than the {MAX_ENV_MAP_FILE_BYTES} an environment map file may have"
            ),
        });
    }
    let mut bytes = Vec::with_capacity(len as usize);
    std::io::Read::read_to_end(
        &mut std::io::Read::take(f, MAX_ENV_MAP_FILE_BYTES),
        &mut bytes,
    )
    .map_err(io)?;
    Ok(bytes)
}

/// The map in `path`, turned by `rotation_deg` about +Y and scaled by `intensity`.
pub fn read_env_map(
    path: &Path,
    rotation_deg: f32,
    intensity: f32,
) -> Result<EnvMap, EnvMapFileError> {
    let format = EnvMapFormat::of(path)?;
    let bytes = read_bytes(path)?;
    let file = path.display().to_string();
    env_map_of(
        &file,
        decode(&file, format, &bytes)?,
        rotation_deg,
        intensity,
    )
}

/// [`EnvMap::new`] over `pixels` read from `file`, its errors naming the file.
pub fn env_map_of(
    file: &str,
    p: EnvPixels,
    rotation_deg: f32,
    intensity: f32,
) -> Result<EnvMap, EnvMapFileError> {
    let _span = tracing::info_span!("env_map_build", width = p.width, height = p.height).entered();
    EnvMap::new(p.width, p.height, p.pixels, rotation_deg, intensity).map_err(|source| {
        EnvMapFileError::Map {
            file: file.to_string(),
            source,
        }
    })
}

/// Decode `bytes`, the contents of `file` in `format`. The size is checked from the
/// header before pixels are decoded; every pixel must be finite. Negative components
/// are set to 0 and counted (`negatives_zeroed`, and a warning): public HDRIs carry
/// them (every studio-light world Blender ships, from Poly Haven, has a few hundred,
/// down to -0.004, left by colour conversion and half-float compression), a negative
/// radiance is no light, and the importance sampler needs non-negative weights.
pub fn decode(
    file: &str,
    format: EnvMapFormat,
    bytes: &[u8],
) -> Result<EnvPixels, EnvMapFileError> {
    let _span = tracing::info_span!("env_map_decode", file, bytes = bytes.len()).entered();
    let bad = |message: String| EnvMapFileError::Decode {
        file: file.to_string(),
        format: format.name(),
        message,
    };
    let check_size = |width: usize, height: usize| {
        if width == 0 || height == 0 {
            return Err(bad(format!("the image is {width}x{height}")));
        }
        if width.saturating_mul(height) > MAX_ENV_MAP_PIXELS {
            return Err(EnvMapFileError::TooLarge {
                file: file.to_string(),
                width,
                height,
            });
        }
        Ok(())
    };
    let p = match format {
        EnvMapFormat::Hdr => {
            let dec = image::codecs::hdr::HdrDecoder::new(Cursor::new(bytes))
                .map_err(|e| bad(e.to_string()))?;
            let meta = dec.metadata();
            let (width, height) = (meta.width as usize, meta.height as usize);
            check_size(width, height)?;
            let img = image::DynamicImage::from_decoder(dec)
                .map_err(|e| bad(e.to_string()))?
                .into_rgb32f();
            EnvPixels {
                width,
                height,
                pixels: img.pixels().map(|p| Vec3::from(p.0)).collect(),
                negatives_zeroed: 0,
            }
        }
        EnvMapFormat::Exr => {
            let meta = exr::meta::MetaData::read_from_buffered(Cursor::new(bytes), false)
                .map_err(|e| bad(e.to_string()))?;
            let header = meta
                .headers
                .first()
                .ok_or_else(|| bad("the file has no layer".into()))?;
            check_size(header.layer_size.0, header.layer_size.1)?;
            use exr::prelude::ReadChannels;
            use exr::prelude::ReadLayers;
            let img = exr::prelude::read()
                .no_deep_data()
                .largest_resolution_level()
                .rgb_channels(
                    |size, _| EnvPixels {
                        width: size.0,
                        height: size.1,
                        pixels: vec![Vec3::ZERO; size.0 * size.1],
                        negatives_zeroed: 0,
                    },
                    |p: &mut EnvPixels, at, (r, g, b): (f32, f32, f32)| {
                        let w = p.width;
                        p.pixels[at.1 * w + at.0] = Vec3::new(r, g, b);
                    },
                )
                .first_valid_layer()
                .all_attributes()
                .from_buffered(Cursor::new(bytes))
                .map_err(|e| bad(format!("{e} (it needs R, G and B channels)")))?;
            let p = img.layer_data.channel_data.pixels;
            check_size(p.width, p.height)?;
            p
        }
    };
    let mut p = p;
    if let Some(i) = p.pixels.iter().position(|c| !c.is_finite()) {
        let c = p.pixels[i];
        return Err(EnvMapFileError::Pixel {
            file: file.to_string(),
            x: i % p.width,
            y: i / p.width,
            r: c.x,
            g: c.y,
            b: c.z,
        });
    }
    let mut most_negative = 0.0f32;
    for c in &mut p.pixels {
        for v in c.as_mut() {
            if *v < 0.0 {
                most_negative = most_negative.min(*v);
                *v = 0.0;
                p.negatives_zeroed += 1;
            }
        }
    }
    if p.negatives_zeroed > 0 {
        tracing::warn!(
            file,
            negatives = p.negatives_zeroed,
            most_negative,
            "environment map {file}: {} negative values (the lowest {most_negative}) read as 0",
            p.negatives_zeroed
        );
    }
    Ok(p)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn temp(name: &str) -> std::path::PathBuf {
        let dir = std::env::temp_dir().join(format!("dray-envfile-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        dir.join(name)
    }

    fn write_hdr(path: &Path, w: u32, h: u32, f: impl Fn(u32, u32) -> [f32; 3]) {
        let px: Vec<image::Rgb<f32>> = (0..w * h).map(|i| image::Rgb(f(i % w, i / w))).collect();
        let out = std::io::BufWriter::new(std::fs::File::create(path).unwrap());
        image::codecs::hdr::HdrEncoder::new(out)
            .encode(&px, w as usize, h as usize)
            .unwrap();
    }

    fn write_exr(
        path: &Path,
        w: usize,
        h: usize,
        f: impl Fn(usize, usize) -> (f32, f32, f32) + Sync,
    ) {
        exr::prelude::write_rgb_file(path, w, h, f).unwrap();
    }

    #[test]
    fn hdr_and_exr_read_as_written() {
        let hdr = temp("a.hdr");
        // RGBE keeps 8 bits of mantissa: powers of two survive exactly.
        write_hdr(&hdr, 8, 4, |x, y| [x as f32, 2.0f32.powi(y as i32), 0.5]);
        let p = decode("a.hdr", EnvMapFormat::Hdr, &read_bytes(&hdr).unwrap()).unwrap();
        assert_eq!((p.width, p.height), (8, 4));
        assert_eq!(p.pixels[3 * 8 + 5], Vec3::new(5.0, 8.0, 0.5));
        let exr = temp("a.EXR");
        write_exr(&exr, 6, 3, |x, y| (x as f32 * 0.25, y as f32 + 0.125, 3.0));
        assert_eq!(EnvMapFormat::of(&exr).unwrap(), EnvMapFormat::Exr);
        let m = read_env_map(&exr, 10.0, 2.0).unwrap();
        let p = decode("a.exr", EnvMapFormat::Exr, &read_bytes(&exr).unwrap()).unwrap();
        assert_eq!((p.width, p.height), (6, 3));
        assert_eq!(p.pixels[2 * 6 + 4], Vec3::new(1.0, 2.125, 3.0));
        assert!(m.radiance(Vec3::Y).is_finite());
    }

    /// Negative components (public HDRIs have a few, near 0) read as 0, counted; the
    /// rest of the pixel stays.
    #[test]
    fn negative_values_read_as_zero_and_are_counted() {
        let exr = temp("neg.exr");
        write_exr(&exr, 4, 2, |x, y| match (x, y) {
            (1, 0) => (-0.003, 0.5, 2.0),
            (2, 1) => (-1.0, -2.0, 0.25),
            _ => (1.0, 1.0, 1.0),
        });
        let p = decode("neg.exr", EnvMapFormat::Exr, &read_bytes(&exr).unwrap()).unwrap();
        assert_eq!(p.negatives_zeroed, 3);
        assert_eq!(p.pixels[1], Vec3::new(0.0, 0.5, 2.0));
        assert_eq!(p.pixels[4 + 2], Vec3::new(0.0, 0.0, 0.25));
        assert!(p.pixels.iter().all(|c| c.min_element() >= 0.0));
        assert!(read_env_map(&exr, 0.0, 1.0).is_ok());
        let ok = decode("a.exr", EnvMapFormat::Exr, &{
            let f = temp("pos.exr");
            write_exr(&f, 2, 1, |_, _| (0.0, 1.0, 2.0));
            read_bytes(&f).unwrap()
        })
        .unwrap();
        assert_eq!(ok.negatives_zeroed, 0);
    }

    #[test]
    fn bad_files_are_named_with_what_is_wrong() {
        let missing = temp("none.hdr");
        let e = read_env_map(&missing, 0.0, 1.0).unwrap_err().to_string();
        assert!(e.contains("none.hdr") && e.contains("no such file"), "{e}");
        let png = temp("x.png");
        std::fs::write(&png, b"x").unwrap();
        let e = read_env_map(&png, 0.0, 1.0).unwrap_err().to_string();
        assert!(
            e.contains("x.png") && e.contains("unsupported file type"),
            "{e}"
        );
        let junk = temp("junk.exr");
        std::fs::write(&junk, b"not an exr at all").unwrap();
        let e = read_env_map(&junk, 0.0, 1.0).unwrap_err().to_string();
        assert!(
            e.contains("junk.exr") && e.contains("not a readable OpenEXR"),
            "{e}"
        );
        let nan = temp("nan.exr");
        write_exr(&nan, 4, 2, |x, y| {
            if (x, y) == (3, 1) {
                (f32::NAN, 0.0, 0.0)
            } else {
                (1.0, 1.0, 1.0)
            }
        });
        let e = read_env_map(&nan, 0.0, 1.0).unwrap_err().to_string();
        assert!(e.contains("nan.exr") && e.contains("pixel (3, 1)"), "{e}");
        // Too large: refused from the header, before the pixels are decoded.
        let big = temp("big.hdr");
        std::fs::write(
            &big,
            b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 4096 +X 4097\n",
        )
        .unwrap();
        let e = read_env_map(&big, 0.0, 1.0).unwrap_err();
        assert!(matches!(e, EnvMapFileError::TooLarge { .. }), "{e}");
        assert!(e.to_string().contains("4097x4096"), "{e}");
        let ok = temp("ok.hdr");
        write_hdr(&ok, 2, 1, |_, _| [1.0, 1.0, 1.0]);
        let e = read_env_map(&ok, 0.0, -1.0).unwrap_err().to_string();
        assert!(e.contains("ok.hdr") && e.contains("intensity"), "{e}");
    }
}

//! `JobSpec.lighting`: check the lights a job adds, fill in their defaults (so GetJob
//! and the workers see every value the render used) and make them ready to sample.
//!
//! An environment map is checked in two steps: its fields (and its path, resolved under
//! the scene root) with the rest of the spec ([`check_lighting`],
//! [`resolve_env_map_path`]), and its file when the scene is prepared
//! ([`load_env_map`]: reading and decoding a large map is blocking work, not for the
//! request task).

use std::path::{Path, PathBuf};
use std::sync::Arc;

use dray_core::env_map::EnvMap;
use dray_core::env_map_file::{self, EnvMapFormat};
use dray_core::lighting::Lighting;
use dray_core::sun::{SUN_DIAMETER_DEG, Sun, SunError};
use dray_proto::v1::{EnvMapFile, EnvMapSpec, LightingSpec, Rgb};
use dray_scene::partition::checksum::{checksum, to_hex};
use tonic::Status;

/// The default `lighting.sun.irradiance`.
pub const DEFAULT_SUN_IRRADIANCE: f32 = 1.0;
/// The default `lighting.env_map.rotation_deg`.
pub const DEFAULT_ENV_ROTATION_DEG: f32 = 0.0;
/// The default `lighting.env_map.intensity`.
pub const DEFAULT_ENV_INTENSITY: f32 = 1.0;

/// The longest `lighting.env_map.path` (Linux's PATH_MAX, as a scene path).
pub const MAX_ENV_MAP_PATH_BYTES: usize = 4096;

/// The default `sun_color` (with a sun): white, the same bits as a grey sun.
pub const DEFAULT_SUN_COLOR: Rgb = Rgb {
    r: 1.0,
    g: 1.0,
    b: 1.0,
};

/// Check `spec` and the sun's colour (`JobSpec.sun_color`, which needs a sun) and fill
/// in their defaults in place; errors name the field. The environment map's file is not
/// read here ([`load_env_map`]): the lighting returned has no map yet, and one sample
/// per light (`JobSpec.light_samples` is read by `crate::validate::light_samples`).
pub fn check_lighting(
    spec: &mut Option<LightingSpec>,
    sun_color: &mut Option<Rgb>,
) -> Result<Lighting, Status> {
    let has_sun = spec.as_ref().is_some_and(|l| l.sun.is_some());
    if sun_color.is_some() && !has_sun {
        return Err(Status::invalid_argument(
            "sun_color: colours a sun, and the job has none (lighting.sun)",
        ));
    }
    let Some(spec) = spec.as_mut() else {
        return Ok(Lighting::default());
    };
    if let Some(e) = spec.env_map.as_mut() {
        check_env_map(e)?;
    }
    let sun = match spec.sun.as_mut() {
        None => None,
        Some(s) => {
            let irradiance = *s.irradiance.get_or_insert(DEFAULT_SUN_IRRADIANCE);
            let diameter = *s.angular_diameter_deg.get_or_insert(SUN_DIAMETER_DEG);
            let sun =
                Sun::new(s.azimuth_deg, s.elevation_deg, irradiance, diameter).map_err(|e| {
                    let field = match e {
                        SunError::Azimuth(_) => "azimuth_deg",
                        SunError::Elevation(_) => "elevation_deg",
                        SunError::Irradiance(_) => "irradiance",
                        SunError::Diameter(_) => "angular_diameter_deg",
                        // Not made by `Sun::new`; the colour is checked below.
                        SunError::Color(_) => "color",
                    };
                    Status::invalid_argument(format!("lighting.sun.{field}: {e}"))
                })?;
            let c = *sun_color.get_or_insert(DEFAULT_SUN_COLOR);
            let sun = sun
                .with_color(glam::Vec3::new(c.r, c.g, c.b))
                .map_err(|e| Status::invalid_argument(format!("sun_color: {e}")))?;
            Some(sun)
        }
    };
    Ok(Lighting {
        sun,
        ..Lighting::default()
    })
}

/// Check `lighting.env_map`'s fields and fill in its defaults (rotation 0, intensity 1).
fn check_env_map(e: &mut EnvMapSpec) -> Result<(), Status> {
    let bad = |field: &str, why: String| {
        Status::invalid_argument(format!("lighting.env_map.{field}: {why}"))
    };
    if e.path.trim().is_empty() {
        return Err(bad("path", "empty: name an .hdr or .exr file".into()));
    }
    if e.path.len() > MAX_ENV_MAP_PATH_BYTES {
        return Err(bad(
            "path",
            format!(
                "{} bytes is longer than {MAX_ENV_MAP_PATH_BYTES}",
                e.path.len()
            ),
        ));
    }
    EnvMapFormat::of(Path::new(&e.path)).map_err(|err| bad("path", err.to_string()))?;
    let rotation = *e.rotation_deg.get_or_insert(DEFAULT_ENV_ROTATION_DEG);
    if !rotation.is_finite() {
        return Err(bad(
            "rotation_deg",
            format!("must be a finite number of degrees, got {rotation}"),
        ));
    }
    let intensity = *e.intensity.get_or_insert(DEFAULT_ENV_INTENSITY);
    if !(intensity.is_finite() && intensity >= 0.0) {
        return Err(bad(
            "intensity",
            format!("must be finite and non-negative, got {intensity}"),
        ));
    }
    Ok(())
}

/// `lighting.env_map.path` resolved against the canonical `root` as a scene path is: it
/// must name an existing regular file inside the root once symlinks and `..` are
/// resolved. Errors show the path as given, never the root.
pub fn resolve_env_map_path(given: &str, root: &Path) -> Result<PathBuf, Status> {
    let bad = |why: String| {
        Status::invalid_argument(format!(
            "lighting.env_map.path: {}: {why}",
            crate::text::bounded(given)
        ))
    };
    let canon = root.join(given).canonicalize().map_err(|e| {
        bad(match e.kind() {
            std::io::ErrorKind::NotFound => "no such file under the scene root".to_string(),
            _ => format!("cannot be opened ({e})"),
        })
    })?;
    if !canon.starts_with(root) {
        return Err(bad("outside the scene root".into()));
    }
    if !canon.is_file() {
        return Err(bad("not a file".into()));
    }
    Ok(canon)
}

/// A job's environment map, read and decoded: the map to sample, and the file as the
/// job's setup names it for workers (`JobSetup.env_map`).
#[derive(Clone, Debug)]
pub struct LoadedEnvMap {
    pub map: Arc<EnvMap>,
    pub file: EnvMapFile,
}

/// Read the environment map `spec` names from `path` (already resolved), decode it and
/// turn it as `spec` says; errors start with `field` and name the file as given in the
/// spec. `spec`'s defaults must be filled in ([`check_lighting`]). Blocking.
pub fn load_env_map(spec: &EnvMapSpec, path: &Path, field: &str) -> Result<LoadedEnvMap, Status> {
    let _span = tracing::info_span!("env_map_load", path = %spec.path).entered();
    let bad = |e: env_map_file::EnvMapFileError| {
        let canonical = path.display().to_string();
        let msg = crate::text::as_given(&e.to_string(), &canonical, &spec.path);
        Status::invalid_argument(format!("{field}: {msg}"))
    };
    let format = EnvMapFormat::of(path).map_err(bad)?;
    let bytes = env_map_file::read_bytes(path).map_err(bad)?;
    let xxh3 = to_hex(checksum(&bytes));
    let pixels = env_map_file::decode(&spec.path, format, &bytes).map_err(bad)?;
    let map = env_map_file::env_map_of(
        &spec.path,
        pixels,
        spec.rotation_deg.unwrap_or(DEFAULT_ENV_ROTATION_DEG),
        spec.intensity.unwrap_or(DEFAULT_ENV_INTENSITY),
    )
    .map_err(bad)?;
    let ext = match format {
        EnvMapFormat::Hdr => "hdr",
        EnvMapFormat::Exr => "exr",
    };
    Ok(LoadedEnvMap {
        map: Arc::new(map),
        file: EnvMapFile {
            path: path.to_string_lossy().into_owned(),
            name: env_map_file_name(&xxh3, ext),
            bytes: bytes.len() as u64,
            xxh3,
        },
    })
}

/// The name a job's environment map is fetched by from PackageService: no file of a
/// package starts with it, and the checksum keeps two maps apart in a worker's cache.
pub fn env_map_file_name(xxh3: &str, ext: &str) -> String {
    format!("{ENV_MAP_FILE_PREFIX}{xxh3}.{ext}")
}

/// The prefix of [`env_map_file_name`].
pub const ENV_MAP_FILE_PREFIX: &str = "env-map-";

#[cfg(test)]
mod tests {
    use super::*;
    use dray_proto::v1::SunSpec;

    fn spec_with_sun() -> Option<LightingSpec> {
        Some(LightingSpec {
            sun: Some(SunSpec {
                azimuth_deg: 10.0,
                elevation_deg: 30.0,
                ..SunSpec::default()
            }),
            env_map: None,
        })
    }

    #[test]
    fn defaults_are_filled_in_and_bad_values_name_their_field() {
        let mut spec = Some(LightingSpec {
            sun: Some(SunSpec {
                azimuth_deg: 10.0,
                elevation_deg: 30.0,
                ..SunSpec::default()
            }),
            env_map: None,
        });
        let l = check_lighting(&mut spec, &mut None).expect("valid");
        let sun = l.sun.expect("a sun");
        assert_eq!(sun.irradiance, DEFAULT_SUN_IRRADIANCE);
        let s = spec.and_then(|l| l.sun).expect("sun spec");
        assert_eq!(
            (s.irradiance, s.angular_diameter_deg),
            (Some(DEFAULT_SUN_IRRADIANCE), Some(SUN_DIAMETER_DEG))
        );
        let none = check_lighting(&mut None, &mut None).expect("none");
        assert!(none.sun.is_none() && none.env_map.is_none());
        // The colour: white by default (filled in), given per channel, and refused
        // without a sun or with a bad channel.
        let mut color = None;
        let white = check_lighting(&mut spec_with_sun(), &mut color).expect("white");
        assert_eq!(color, Some(DEFAULT_SUN_COLOR));
        assert_eq!(white.sun.expect("sun").radiance(), sun.radiance());
        let mut warm = Some(Rgb {
            r: 1.0,
            g: 0.5,
            b: 0.25,
        });
        let l = check_lighting(&mut spec_with_sun(), &mut warm).expect("warm");
        assert_eq!(
            l.sun.expect("sun").radiance(),
            sun.radiance() * glam::Vec3::new(1.0, 0.5, 0.25)
        );
        for (mut lighting, rgb, says) in [
            (
                None,
                Rgb {
                    r: 1.0,
                    g: 1.0,
                    b: 1.0,
                },
                "has none",
            ),
            (
                Some(LightingSpec {
                    sun: None,
                    env_map: Some(EnvMapSpec {
                        path: "sky.hdr".into(),
                        ..EnvMapSpec::default()
                    }),
                }),
                Rgb {
                    r: 1.0,
                    g: 1.0,
                    b: 1.0,
                },
                "has none",
            ),
            (
                spec_with_sun(),
                Rgb {
                    r: -1.0,
                    g: 1.0,
                    b: 1.0,
                },
                "non-negative",
            ),
            (
                spec_with_sun(),
                Rgb {
                    r: 1.0,
                    g: f32::NAN,
                    b: 1.0,
                },
                "non-negative",
            ),
        ] {
            let e = check_lighting(&mut lighting, &mut Some(rgb)).expect_err(says);
            assert_eq!(e.code(), tonic::Code::InvalidArgument);
            assert!(
                e.message().starts_with("sun_color: ") && e.message().contains(says),
                "{}",
                e.message()
            );
        }
        for (sun, field) in [
            (
                SunSpec {
                    elevation_deg: 91.0,
                    ..SunSpec::default()
                },
                "lighting.sun.elevation_deg",
            ),
            (
                SunSpec {
                    elevation_deg: f32::NAN,
                    ..SunSpec::default()
                },
                "lighting.sun.elevation_deg",
            ),
            (
                SunSpec {
                    azimuth_deg: f32::INFINITY,
                    ..SunSpec::default()
                },
                "lighting.sun.azimuth_deg",
            ),
            (
                SunSpec {
                    irradiance: Some(-1.0),
                    ..SunSpec::default()
                },
                "lighting.sun.irradiance",
            ),
            (
                SunSpec {
                    angular_diameter_deg: Some(0.0),
                    ..SunSpec::default()
                },
                "lighting.sun.angular_diameter_deg",
            ),
        ] {
            let e = check_lighting(
                &mut Some(LightingSpec {
                    sun: Some(sun),
                    env_map: None,
                }),
                &mut None,
            )
            .expect_err(field);
            assert_eq!(e.code(), tonic::Code::InvalidArgument);
            assert!(e.message().starts_with(field), "{}", e.message());
        }
    }

    #[test]
    fn env_map_fields_are_checked_and_defaulted() {
        let mut spec = Some(LightingSpec {
            sun: None,
            env_map: Some(EnvMapSpec {
                path: "sky.hdr".into(),
                ..EnvMapSpec::default()
            }),
        });
        let l = check_lighting(&mut spec, &mut None).expect("valid");
        assert!(l.env_map.is_none(), "the file is read later");
        let e = spec.and_then(|l| l.env_map).expect("env map spec");
        assert_eq!(
            (e.rotation_deg, e.intensity),
            (Some(DEFAULT_ENV_ROTATION_DEG), Some(DEFAULT_ENV_INTENSITY))
        );
        for (env, field, says) in [
            (EnvMapSpec::default(), "lighting.env_map.path", "empty"),
            (
                EnvMapSpec {
                    path: "sky.png".into(),
                    ..EnvMapSpec::default()
                },
                "lighting.env_map.path",
                "unsupported file type",
            ),
            (
                EnvMapSpec {
                    path: "sky.exr".into(),
                    rotation_deg: Some(f32::NAN),
                    ..EnvMapSpec::default()
                },
                "lighting.env_map.rotation_deg",
                "finite",
            ),
            (
                EnvMapSpec {
                    path: "sky.exr".into(),
                    intensity: Some(-2.0),
                    ..EnvMapSpec::default()
                },
                "lighting.env_map.intensity",
                "non-negative",
            ),
        ] {
            let e = check_lighting(
                &mut Some(LightingSpec {
                    sun: None,
                    env_map: Some(env),
                }),
                &mut None,
            )
            .expect_err(field);
            assert_eq!(e.code(), tonic::Code::InvalidArgument);
            assert!(
                e.message().starts_with(field) && e.message().contains(says),
                "{}",
                e.message()
            );
        }
    }

    #[test]
    fn env_map_paths_stay_under_the_scene_root() {
        let base = std::env::temp_dir().join(format!("dray-envroot-{}", std::process::id()));
        let root = base.join("root");
        std::fs::create_dir_all(root.join("dir.hdr")).unwrap();
        std::fs::write(base.join("outside.hdr"), b"x").unwrap();
        std::fs::write(root.join("in.hdr"), b"x").unwrap();
        let root = root.canonicalize().unwrap();
        assert_eq!(
            resolve_env_map_path("in.hdr", &root).unwrap(),
            root.join("in.hdr")
        );
        for (given, says) in [
            ("../outside.hdr", "outside the scene root"),
            ("missing.hdr", "no such file"),
            ("dir.hdr", "not a file"),
        ] {
            let e = resolve_env_map_path(given, &root).expect_err(given);
            let m = e.message();
            assert!(
                m.starts_with("lighting.env_map.path") && m.contains(says),
                "{m}"
            );
            assert!(!m.contains(root.to_str().unwrap()), "{m}");
        }
        let _ = std::fs::remove_dir_all(&base);
    }
}

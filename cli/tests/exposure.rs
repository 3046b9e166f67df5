//! The PNG's display transform (`--exposure`, `--tonemap`; core/src/display.rs) through
//! the real `dray render`:
//!
//! - `--exposure 0 --tonemap clamp` writes the bytes dray wrote before automatic
//!   exposure and tone curves (the PNG encoding of the film's linear values, clamped and
//!   sRGB-encoded), and a number of stops keeps its meaning, on the reference renderer
//!   and on actors;
//! - the realistic tier: every shared glTF model with photometric lights
//!   (`KHR_lights_punctual`, or emitters with `KHR_materials_emissive_strength`) renders
//!   well exposed with no flags: fewer than 2% of its lit pixels clipped and their median
//!   within a stop of mid-grey.
//!
//! Distributed jobs apply the same transform to the assembled film: the same-bits tests
//! (`workers.rs`, `submit.rs`) compare the default PNGs of 1, 2 and 4 workers with
//! `dray render`'s.

mod common;

use std::path::{Path, PathBuf};

use common::{render, tmp};
use dray_core::exposure::{MID_GREY, luminance};
use dray_core::film::{linear_to_srgb8, srgb8_to_linear};
use glam::Vec3;

/// Linear radiance of an EXR `dray render --exr` wrote: (width, height, pixels).
fn read_exr(path: &Path) -> (u32, u32, Vec<Vec3>) {
    let img = exr::prelude::read_first_rgba_layer_from_file(
        path,
        |size, _| {
            let (w, h) = (size.width(), size.height());
            (w, h, vec![Vec3::ZERO; w * h])
        },
        |(w, _, px): &mut (usize, usize, Vec<Vec3>), pos, (r, g, b, _): (f32, f32, f32, f32)| {
            px[pos.y() * *w + pos.x()] = Vec3::new(r, g, b);
        },
    )
    .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let (w, h, px) = img.layer_data.channel_data.pixels;
    (w as u32, h as u32, px)
}

/// The PNG dray wrote before automatic exposure and tone curves: each linear value
/// times 2^EV, clamped, sRGB-encoded to 8 bits (`Film::srgb8`), PNG-encoded as
/// `Film::write_png` does.
fn old_png(w: u32, h: u32, linear: &[Vec3], ev: f32) -> Vec<u8> {
    use image::ImageEncoder;
    let scale = 2f32.powf(ev);
    let buf: Vec<u8> = linear
        .iter()
        .flat_map(|p| (*p * scale).to_array().map(linear_to_srgb8))
        .collect();
    let mut out = Vec::new();
    image::codecs::png::PngEncoder::new(&mut out)
        .write_image(&buf, w, h, image::ExtendedColorType::Rgb8)
        .expect("encode PNG");
    out
}

#[test]
fn exposure_0_with_clamp_is_the_old_encoding_byte_for_byte() {
    let dir = tmp("exposure-old");
    let size = [
        "--width", "48", "--height", "36", "--spp", "4", "--seed", "3",
    ];
    for workers in ["0", "2"] {
        for ev in ["0", "-1.5"] {
            let tag = format!("w{workers}-ev{ev}");
            let exr = dir.join(format!("{tag}.exr"));
            let mut flags = size.to_vec();
            flags.extend(["--workers", workers, "--tonemap", "clamp", "--exposure", ev]);
            flags.extend(["--exr", exr.to_str().expect("utf-8 temp path")]);
            let r = render(&dir, &tag, "cornell:glass", &flags);
            assert!(r.ok, "{tag}: {}", r.stderr);
            let png = std::fs::read(r.png.expect("png")).expect("read png");
            let (w, h, linear) = read_exr(&exr);
            let want = old_png(w, h, &linear, ev.parse().expect("ev"));
            assert!(
                png == want,
                "{tag}: --exposure {ev} --tonemap clamp is not the old encoding"
            );
            let stats = r.stats.expect("stats");
            assert_eq!(stats["exposure"], ev, "{stats}");
            assert_eq!(stats["tonemap"], "clamp", "{stats}");
            // The default (automatic exposure, AgX) gives other bytes for this film, so
            // the equality above would fail if it leaked into the fixed path.
            let d = render(&dir, &format!("{tag}-default"), "cornell:glass", &size);
            assert!(d.ok, "{}", d.stderr);
            let default_png = std::fs::read(d.png.expect("png")).expect("read png");
            assert!(
                default_png != want,
                "{tag}: the default is the old encoding"
            );
            let stats = d.stats.expect("stats");
            assert_eq!(stats["exposure"], "auto", "{stats}");
            assert_eq!(stats["tonemap"], "agx", "{stats}");
            assert!(stats["exposure_stops"].as_f64().is_some(), "{stats}");
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn bad_exposure_and_tone_curve_flags_are_one_line_errors() {
    let dir = tmp("exposure-bad");
    for (flags, want) in [
        (
            ["--exposure", "bright"],
            "\"bright\" is neither \"auto\" nor a number of stops",
        ),
        (["--exposure", "65"], "65 is out of range (-64..=64 stops)"),
        (
            ["--tonemap", "filmic"],
            "expected clamp, reinhard, aces or agx",
        ),
    ] {
        let r = render(&dir, "bad", "cornell", &flags);
        assert!(!r.ok, "{flags:?} was accepted");
        assert!(r.stderr.contains(want), "{flags:?}: {}", r.stderr);
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// glTF files under `dir` that light themselves photometrically: punctual lights (lux,
/// candela) or emitters with an emissive strength. The JSON of a `.glb` is plain text
/// in its first chunk, so a byte search finds the extension names in both containers.
fn photometric_models(dir: &Path) -> Vec<PathBuf> {
    common::model_files(dir, &["gltf", "glb"])
        .into_iter()
        .filter(|p| {
            let bytes = std::fs::read(p).unwrap_or_default();
            let has = |s: &str| bytes.windows(s.len()).any(|w| w == s.as_bytes());
            has("KHR_lights_punctual") || has("KHR_materials_emissive_strength")
        })
        .collect()
}

/// The 8-bit value of display luminance `y`.
fn code(y: f32) -> u8 {
    linear_to_srgb8(y)
}

/// Over the pixels with light (linear luminance above 0 in the EXR: a black background
/// has nothing to expose): the share with a channel at 255, and the median display
/// luminance as an 8-bit value.
fn measure(png: &Path, exr: &Path) -> (f64, u8, usize) {
    let img = image::open(png).expect("decode png").to_rgb8();
    let (_, _, linear) = read_exr(exr);
    let mut lum = Vec::new();
    let mut clipped = 0usize;
    for (p, l) in img.pixels().zip(&linear) {
        if luminance(*l) <= 0.0 {
            continue;
        }
        clipped += usize::from(p.0.contains(&255));
        lum.push(code(luminance(Vec3::from_array(p.0.map(srgb8_to_linear)))));
    }
    assert!(!lum.is_empty(), "{}: no pixel has light", png.display());
    lum.sort_unstable();
    (
        clipped as f64 / lum.len() as f64,
        lum[lum.len() / 2],
        lum.len(),
    )
}

#[test]
fn photometric_gltf_models_are_well_exposed_with_no_flags() {
    let Some(scenes) = common::scenes_dir() else {
        return;
    };
    let models = photometric_models(&scenes);
    if models.is_empty() {
        common::dependency_missing(&format!(
            "realistic tier: no glTF model with KHR_lights_punctual or \
             KHR_materials_emissive_strength under {}",
            scenes.display()
        ));
        return;
    }
    let dir = tmp("exposure-photometric");
    // Mid-grey: within a stop of 0.18 on the display.
    let grey = code(MID_GREY / 2.0)..=code(MID_GREY * 2.0);
    for (i, model) in models.iter().enumerate() {
        let name = model.strip_prefix(&scenes).unwrap_or(model).display();
        let mut row = Vec::new();
        for (tag, extra) in [
            ("no flags", &[][..]),
            ("fixed", &["--exposure", "0", "--tonemap", "clamp"][..]),
        ] {
            let label = if extra.is_empty() {
                tag.to_string()
            } else {
                extra.join(" ")
            };
            let tag = tag.replace(' ', "-");
            let tag = format!("m{i}-{tag}");
            let exr = dir.join(format!("{tag}.exr"));
            let mut flags = vec!["--width", "160", "--height", "120", "--spp", "16"];
            flags.extend_from_slice(extra);
            flags.extend(["--exr", exr.to_str().expect("utf-8 temp path")]);
            let r = render(&dir, &tag, model.to_str().expect("utf-8 path"), &flags);
            assert!(r.ok, "{name}: {}", r.stderr);
            let (clipped, median, lit) = measure(&r.png.expect("png"), &exr);
            let stops = r.stats.expect("stats")["exposure_stops"].clone();
            row.push(format!(
                "{label}: {:.2}% of {lit} lit pixels clipped, median {median}/255, {stops} EV",
                clipped * 100.0
            ));
            if extra.is_empty() {
                assert!(
                    clipped < 0.02,
                    "{name} with no flags: {:.2}% of its lit pixels clipped (at most 2%)",
                    clipped * 100.0
                );
                assert!(
                    grey.contains(&median),
                    "{name} with no flags: median {median}/255, not within a stop of \
                     mid-grey ({grey:?})"
                );
            }
        }
        eprintln!("{name}: {}", row.join("; "));
    }
    let _ = std::fs::remove_dir_all(&dir);
}

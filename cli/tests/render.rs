//! End-to-end tests of `dray render` on procedural and generated scenes: determinism,
//! precision far from the origin, numerical robustness, effect gating and bad input.

mod common;

use common::{rays, render, rgb, tmp, write_box_ply};

#[test]
fn same_command_same_bytes_and_thread_count_does_not_matter() {
    let d = tmp("determinism");
    for integ in ["path", "whitted", "raycast", "primary", "ao"] {
        let args = [
            "--width",
            "96",
            "--height",
            "64",
            "--spp",
            "4",
            "--integrator",
            integ,
        ];
        let a = render(
            &d,
            &format!("{integ}-a"),
            "cornell:glass",
            &[&args[..], &["--threads", "2"]].concat(),
        );
        let b = render(
            &d,
            &format!("{integ}-b"),
            "cornell:glass",
            &[&args[..], &["--threads", "2"]].concat(),
        );
        let c = render(
            &d,
            &format!("{integ}-c"),
            "cornell:glass",
            &[&args[..], &["--threads", "1"]].concat(),
        );
        assert!(a.ok && b.ok && c.ok, "{}{}{}", a.stderr, b.stderr, c.stderr);
        let bytes = |r: &common::Run| std::fs::read(r.png.as_ref().unwrap()).unwrap();
        assert_eq!(bytes(&a), bytes(&b), "{integ}: two runs differ");
        assert_eq!(bytes(&a), bytes(&c), "{integ}: 1 and 2 threads differ");
    }
}

/// Fraction of pixels whose 8-bit value differs by more than `tol` in any channel.
fn differing(a: &image::RgbImage, b: &image::RgbImage, tol: u8) -> f64 {
    let n = a
        .pixels()
        .zip(b.pixels())
        .filter(|(p, q)| p.0.iter().zip(q.0).any(|(x, y)| x.abs_diff(y) > tol))
        .count();
    n as f64 / a.pixels().len() as f64
}

#[test]
fn far_from_the_origin_renders_like_at_the_origin() {
    let d = tmp("far");
    // At 1e6 an f32 coordinate moves in steps of 0.0625, so geometry and camera shift by a
    // fraction of a pixel and Monte Carlo noise decorrelates; self-intersection would
    // instead darken whole surfaces with speckle. Tolerances, per scene: the fraction of
    // pixels differing by more than `tol`/255 stays under `max_frac`, and the mean
    // brightness agrees within 1%.
    let cases: [(&str, &[&str], u8, f64); 2] = [
        (
            "spheres:30",
            &["--integrator", "raycast", "--spp", "4"],
            24,
            0.03,
        ),
        (
            "cornell",
            &["--integrator", "path", "--spp", "16"],
            48,
            0.02,
        ),
    ];
    for (scene, extra, tol, max_frac) in cases {
        let args = [&["--width", "128", "--height", "128"][..], extra].concat();
        let base = render(&d, "base", scene, &args);
        assert!(base.ok, "{}", base.stderr);
        let base_img = rgb(base.png.as_ref().unwrap());
        for t in ["1e5,1e5,1e5", "1e6,-1e6,1e6"] {
            let far = render(&d, "far", scene, &[&args[..], &["--translate", t]].concat());
            assert!(far.ok, "{}", far.stderr);
            assert_eq!(far.stats.as_ref().unwrap()["nonfinite_contributions"], 0);
            let img = rgb(far.png.as_ref().unwrap());
            let frac = differing(&base_img, &img, tol);
            let mean = |im: &image::RgbImage| {
                im.as_raw().iter().map(|&v| v as f64).sum::<f64>() / im.as_raw().len() as f64
            };
            let (m0, m1) = (mean(&base_img), mean(&img));
            eprintln!(
                "{scene} translated by {t}: {:.3}% of pixels differ by > {tol}, mean {m1:.2} vs {m0:.2}",
                frac * 100.0
            );
            assert!(
                frac < max_frac,
                "{scene} translated by {t}: {:.2}% of pixels differ",
                frac * 100.0
            );
            assert!(
                (m0 - m1).abs() / m0 < 0.01,
                "{scene} translated by {t}: mean {m1} vs {m0}"
            );
        }
    }
}

/// A glTF scene built to provoke numerical trouble: a sliver and a needle triangle, a
/// near-zero-area emitter, a point light lying on the floor, a spot light with equal cone
/// angles, a zero-roughness mirror, index-matched glass and a camera grazing the floor.
fn write_stress_gltf(dir: &std::path::Path) -> std::path::PathBuf {
    let mut pos: Vec<[f32; 3]> = Vec::new();
    let mut idx: Vec<u16> = Vec::new();
    let mut prims = Vec::new();
    let add =
        |tris: &[[[f32; 3]; 3]], material: usize, pos: &mut Vec<[f32; 3]>, idx: &mut Vec<u16>| {
            let first_idx = idx.len();
            for t in tris {
                for v in t {
                    idx.push(pos.len() as u16);
                    pos.push(*v);
                }
            }
            (first_idx, idx.len() - first_idx, material)
        };
    let floor = [
        [[-10.0, 0.0, -10.0], [-10.0, 0.0, 10.0], [10.0, 0.0, 10.0]],
        [[-10.0, 0.0, -10.0], [10.0, 0.0, 10.0], [10.0, 0.0, -10.0]],
    ];
    prims.push(add(&floor, 0, &mut pos, &mut idx));
    let sliver = [
        [[-2.0, 0.5, 0.0], [2.0, 0.5, 0.0], [0.0, 0.5 + 1e-6, 0.0]],
        [[0.0, 0.0, 1.0], [0.0, 3.0, 1.0], [1e-7, 1.5, 1.0]],
    ];
    prims.push(add(&sliver, 0, &mut pos, &mut idx));
    let tiny_light = [[[0.0, 2.0, 0.0], [1e-4, 2.0, 0.0], [0.0, 2.0, 1e-4]]];
    prims.push(add(&tiny_light, 1, &mut pos, &mut idx));
    let mirror = [
        [[-3.0, 0.0, -3.0], [3.0, 0.0, -3.0], [3.0, 3.0, -3.0]],
        [[-3.0, 0.0, -3.0], [3.0, 3.0, -3.0], [-3.0, 3.0, -3.0]],
    ];
    prims.push(add(&mirror, 2, &mut pos, &mut idx));
    let glass = [
        [[1.0, 0.0, 1.0], [2.0, 0.0, 1.0], [1.5, 1.0, 1.5]],
        [[1.0, 0.0, 1.0], [1.5, 1.0, 1.5], [2.0, 0.0, 1.0]],
    ];
    prims.push(add(&glass, 3, &mut pos, &mut idx));

    let mut bin: Vec<u8> = Vec::new();
    for p in &pos {
        for c in p {
            bin.extend_from_slice(&c.to_le_bytes());
        }
    }
    let pos_len = bin.len();
    for i in &idx {
        bin.extend_from_slice(&i.to_le_bytes());
    }
    while !bin.len().is_multiple_of(4) {
        bin.push(0);
    }
    std::fs::write(dir.join("stress.bin"), &bin).unwrap();
    let (mut lo, mut hi) = ([f32::MAX; 3], [f32::MIN; 3]);
    for p in &pos {
        for k in 0..3 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
    }
    let mut accessors = vec![format!(
        r#"{{"bufferView":0,"componentType":5126,"count":{},"type":"VEC3","min":[{},{},{}],"max":[{},{},{}]}}"#,
        pos.len(),
        lo[0],
        lo[1],
        lo[2],
        hi[0],
        hi[1],
        hi[2]
    )];
    let mut primitives = Vec::new();
    for (first, count, material) in prims {
        accessors.push(format!(
            r#"{{"bufferView":1,"byteOffset":{},"componentType":5123,"count":{count},"type":"SCALAR"}}"#,
            first * 2
        ));
        primitives.push(format!(
            r#"{{"attributes":{{"POSITION":0}},"indices":{},"material":{material}}}"#,
            accessors.len() - 1
        ));
    }
    let json = format!(
        r#"{{
  "asset": {{"version": "2.0"}},
  "extensionsUsed": ["KHR_lights_punctual", "KHR_materials_emissive_strength", "KHR_materials_transmission", "KHR_materials_ior"],
  "extensions": {{"KHR_lights_punctual": {{"lights": [
    {{"type": "point", "intensity": 50, "color": [1, 1, 1]}},
    {{"type": "spot", "intensity": 80, "spot": {{"innerConeAngle": 0.5, "outerConeAngle": 0.5}}}}
  ]}}}},
  "scene": 0,
  "scenes": [{{"nodes": [0, 1, 2, 3]}}],
  "nodes": [
    {{"mesh": 0}},
    {{"extensions": {{"KHR_lights_punctual": {{"light": 0}}}}, "translation": [0.5, 0.0, 0.5]}},
    {{"extensions": {{"KHR_lights_punctual": {{"light": 1}}}}, "translation": [0, 4, 0], "rotation": [-0.7071068, 0, 0, 0.7071068]}},
    {{"camera": 0, "translation": [0, 0.001, 9], "rotation": [0, 0, 0, 1]}}
  ],
  "cameras": [{{"type": "perspective", "perspective": {{"yfov": 0.8, "znear": 0.001}}}}],
  "materials": [
    {{"pbrMetallicRoughness": {{"baseColorFactor": [0.8, 0.8, 0.8, 1], "metallicFactor": 0, "roughnessFactor": 0.5}}, "doubleSided": true}},
    {{"emissiveFactor": [1, 1, 1], "extensions": {{"KHR_materials_emissive_strength": {{"emissiveStrength": 1e6}}}}, "doubleSided": true}},
    {{"pbrMetallicRoughness": {{"metallicFactor": 1, "roughnessFactor": 0}}, "doubleSided": true}},
    {{"pbrMetallicRoughness": {{"metallicFactor": 0, "roughnessFactor": 0}}, "extensions": {{"KHR_materials_transmission": {{"transmissionFactor": 1}}, "KHR_materials_ior": {{"ior": 1.0}}}}}}
  ],
  "meshes": [{{"primitives": [{}]}}],
  "buffers": [{{"uri": "stress.bin", "byteLength": {}}}],
  "bufferViews": [
    {{"buffer": 0, "byteOffset": 0, "byteLength": {pos_len}}},
    {{"buffer": 0, "byteOffset": {pos_len}, "byteLength": {}}}
  ],
  "accessors": [{}]
}}"#,
        primitives.join(","),
        bin.len(),
        idx.len() * 2,
        accessors.join(",")
    );
    let path = dir.join("stress.gltf");
    std::fs::write(&path, json).unwrap();
    path
}

#[test]
fn hard_cases_never_put_nan_or_inf_in_the_film() {
    let d = tmp("stress");
    let scene = write_stress_gltf(&d);
    let scene = scene.to_str().unwrap();
    for integ in ["path", "whitted", "raycast", "ao"] {
        let r = render(
            &d,
            integ,
            scene,
            &[
                "--width",
                "64",
                "--height",
                "48",
                "--spp",
                "8",
                "--integrator",
                integ,
                "--max-depth",
                "8",
            ],
        );
        assert!(r.ok, "{integ}: {}", r.stderr);
        let s = r.stats.unwrap();
        assert_eq!(s["nonfinite_contributions"], 0, "{integ}: {s}");
    }
    for scene in ["soup:3000", "cornell:mirror", "cornell:glass"] {
        let r = render(
            &d,
            "p",
            scene,
            &[
                "--width",
                "64",
                "--height",
                "48",
                "--spp",
                "8",
                "--max-depth",
                "12",
            ],
        );
        assert!(r.ok, "{scene}: {}", r.stderr);
        assert_eq!(r.stats.unwrap()["nonfinite_contributions"], 0, "{scene}");
    }
}

/// `primary` (Little 2011's ray caster) traces camera rays and nothing else, and lights
/// its first hits without shadows: where `raycast`'s shadow rays find the light blocked,
/// it is brighter, and with no shadow ray and no ambient term it is not the same image.
#[test]
fn primary_casts_camera_rays_only_and_lights_without_shadows() {
    let d = tmp("primary");
    let args = |integ: &'static str| {
        [
            "--width",
            "48",
            "--height",
            "48",
            "--spp",
            "2",
            "--integrator",
            integ,
        ]
    };
    let primary = render(&d, "primary", "cornell", &args("primary"));
    let raycast = render(&d, "raycast", "cornell", &args("raycast"));
    assert!(
        primary.ok && raycast.ok,
        "{}{}",
        primary.stderr,
        raycast.stderr
    );
    let s = primary.stats.expect("stats");
    assert_eq!(rays(&s, "camera"), 48 * 48 * 2, "{s}");
    for kind in [
        "shadow",
        "reflection",
        "refraction",
        "diffuse",
        "ambient_occlusion",
    ] {
        assert_eq!(rays(&s, kind), 0, "{kind}: {s}");
    }
    assert!(rays(&raycast.stats.expect("stats"), "shadow") > 0);
    let (p, r) = (
        rgb(primary.png.as_ref().expect("png")),
        rgb(raycast.png.as_ref().expect("png")),
    );
    assert!(p != r, "primary and raycast gave the same image");
    // Lit: the first hits see the ceiling light (no shadow ray can block it).
    let lit = p.pixels().filter(|q| q.0.iter().any(|&c| c > 8)).count();
    assert!(lit > p.pixels().len() / 2, "{lit} lit pixels");
}

#[test]
fn only_the_effects_the_scene_calls_for_are_traced() {
    let d = tmp("effects");
    // Diffuse only, lit by an emitter: no reflection or refraction rays.
    let r = render(
        &d,
        "cornell",
        "cornell",
        &["--width", "48", "--height", "48", "--spp", "4"],
    );
    let s = r.stats.expect("stats");
    assert_eq!(rays(&s, "reflection"), 0);
    assert_eq!(rays(&s, "refraction"), 0);
    assert!(rays(&s, "diffuse") > 0 && rays(&s, "shadow") > 0);
    assert_eq!(
        s["effects"],
        serde_json::json!(["direct_light", "emission"])
    );

    // No lights at all: the sky lights it, and no shadow ray is traced by any integrator.
    let ply = d.join("box.ply");
    write_box_ply(&ply);
    for integ in ["path", "raycast", "whitted"] {
        let r = render(
            &d,
            integ,
            ply.to_str().unwrap(),
            &[
                "--width",
                "48",
                "--height",
                "48",
                "--spp",
                "4",
                "--integrator",
                integ,
            ],
        );
        let s = r.stats.unwrap_or_else(|| panic!("{}", r.stderr));
        assert_eq!(rays(&s, "shadow"), 0, "{integ}");
        assert_eq!(rays(&s, "refraction"), 0, "{integ}");
    }

    // Glass needs refraction rays, unless forced off.
    let r = render(
        &d,
        "glass",
        "cornell:glass",
        &["--width", "48", "--height", "48", "--spp", "4"],
    );
    assert!(rays(&r.stats.unwrap(), "refraction") > 0);
    let r = render(
        &d,
        "noglass",
        "cornell:glass",
        &[
            "--width",
            "48",
            "--height",
            "48",
            "--spp",
            "4",
            "--effects",
            "-transmission",
        ],
    );
    let s = r.stats.unwrap();
    assert_eq!(rays(&s, "refraction"), 0);
    assert!(
        !s["effects"]
            .as_array()
            .unwrap()
            .iter()
            .any(|e| e == "transmission")
    );
}

#[test]
fn bad_input_gives_one_line_and_a_nonzero_exit() {
    let d = tmp("bad");
    let garbage = d.join("garbage.glb");
    std::fs::write(&garbage, b"glTF\x02\x00\x00\x00\xff\xff").unwrap();
    let unknown = d.join("scene.xyz");
    std::fs::write(&unknown, b"hello").unwrap();
    let cases: Vec<(String, Vec<&str>, &str)> = vec![
        ("does-not-exist.glb".into(), vec![], "does-not-exist.glb"),
        (garbage.to_str().unwrap().into(), vec![], "garbage.glb"),
        (
            unknown.to_str().unwrap().into(),
            vec![],
            "unrecognised scene format",
        ),
        ("cornell".into(), vec!["--width", "0"], "image size"),
        ("cornell".into(), vec!["--height", "100000"], "image size"),
        ("cornell".into(), vec!["--spp", "0"], "--spp"),
        (
            "cornell".into(),
            vec!["--integrator", "photon"],
            "unknown integrator",
        ),
        ("cornell".into(), vec!["--env", "1,2"], "--env"),
        (
            "cornell".into(),
            vec!["--camera", "nope"],
            "camera \"nope\" not found",
        ),
        (
            "cornell".into(),
            vec!["--effects", "+sparkle"],
            "unknown effect",
        ),
        ("spheres:abc".into(), vec![], "spheres:abc"),
        ("iso:nofield:32".into(), vec![], "iso:nofield:32"),
    ];
    for (scene, args, needle) in cases {
        let r = render(&d, "bad", &scene, &args);
        assert!(!r.ok, "{scene} {args:?} should fail");
        let lines: Vec<&str> = r.stderr.lines().filter(|l| !l.trim().is_empty()).collect();
        assert_eq!(
            lines.len(),
            1,
            "{scene} {args:?}: expected one line, got {:?}",
            r.stderr
        );
        assert!(lines[0].starts_with("dray: error:"), "{:?}", lines[0]);
        assert!(
            lines[0].contains(needle),
            "{scene} {args:?}: {:?} lacks {needle:?}",
            lines[0]
        );
    }
}

/// A one-triangle glTF that uses an extension dray does not know, so loading it warns.
fn write_warning_gltf(dir: &std::path::Path) -> std::path::PathBuf {
    let pos: [f32; 9] = [-1.0, -1.0, 0.0, 1.0, -1.0, 0.0, 0.0, 1.0, 0.0];
    let bin: Vec<u8> = pos.iter().flat_map(|v| v.to_le_bytes()).collect();
    std::fs::write(dir.join("warn.bin"), &bin).unwrap();
    let json = format!(
        r#"{{"asset":{{"version":"2.0"}},"extensionsUsed":["EXT_dray_test_unknown"],
"buffers":[{{"uri":"warn.bin","byteLength":{}}}],
"bufferViews":[{{"buffer":0,"byteLength":{}}}],
"accessors":[{{"bufferView":0,"componentType":5126,"count":3,"type":"VEC3","min":[-1,-1,0],"max":[1,1,0]}}],
"meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}}}}]}}],
"nodes":[{{"mesh":0}}],"scenes":[{{"nodes":[0]}}]}}"#,
        bin.len(),
        bin.len()
    );
    let path = dir.join("warn.gltf");
    std::fs::write(&path, json).unwrap();
    path
}

#[test]
fn import_warnings_are_printed_once_in_plain_text_when_stderr_is_not_a_terminal() {
    let d = tmp("warn-once");
    let scene = write_warning_gltf(&d);
    let r = render(
        &d,
        "warn",
        scene.to_str().unwrap(),
        &["--width", "8", "--height", "8", "--spp", "1"],
    );
    assert!(r.ok, "{}", r.stderr);
    // The test harness captures stderr through a pipe: not a terminal.
    assert_eq!(
        r.stderr.matches("EXT_dray_test_unknown").count(),
        1,
        "{}",
        r.stderr
    );
    assert!(!r.stderr.contains('\u{1b}'), "colour codes: {:?}", r.stderr);
}

/// A double-sided white quad facing +Z, with red `COLOR_0` on every vertex when
/// `coloured`.
fn write_quad_gltf(dir: &std::path::Path, name: &str, coloured: bool) -> std::path::PathBuf {
    let pos: [f32; 12] = [
        -1.0, -1.0, 0.0, 1.0, -1.0, 0.0, 1.0, 1.0, 0.0, -1.0, 1.0, 0.0,
    ];
    let idx: [u16; 6] = [0, 1, 2, 0, 2, 3];
    let red: [f32; 12] = [1.0, 0.0, 0.0].repeat(4).try_into().unwrap();
    let mut bin: Vec<u8> = pos.iter().flat_map(|v| v.to_le_bytes()).collect();
    bin.extend(red.iter().flat_map(|v| v.to_le_bytes()));
    bin.extend(idx.iter().flat_map(|v| v.to_le_bytes()));
    std::fs::write(dir.join(format!("{name}.bin")), &bin).unwrap();
    let colour = if coloured { r#","COLOR_0":1"# } else { "" };
    let json = format!(
        r#"{{"asset":{{"version":"2.0"}},
"buffers":[{{"uri":"{name}.bin","byteLength":{}}}],
"bufferViews":[{{"buffer":0,"byteLength":48}},{{"buffer":0,"byteOffset":48,"byteLength":48}},{{"buffer":0,"byteOffset":96,"byteLength":12}}],
"accessors":[
 {{"bufferView":0,"componentType":5126,"count":4,"type":"VEC3","min":[-1,-1,0],"max":[1,1,0]}},
 {{"bufferView":1,"componentType":5126,"count":4,"type":"VEC3"}},
 {{"bufferView":2,"componentType":5123,"count":6,"type":"SCALAR"}}],
"materials":[{{"pbrMetallicRoughness":{{"baseColorFactor":[0.8,0.8,0.8,1],"metallicFactor":0}},"doubleSided":true}}],
"meshes":[{{"primitives":[{{"attributes":{{"POSITION":0{colour}}},"indices":2,"material":0}}]}}],
"nodes":[{{"mesh":0}}],"scenes":[{{"nodes":[0]}}]}}"#,
        bin.len()
    );
    let path = dir.join(format!("{name}.gltf"));
    std::fs::write(&path, json).unwrap();
    path
}

#[test]
fn vertex_colours_tint_the_render() {
    let d = tmp("vertex-colours");
    // Linear clamp encoding: the tone curve would mix the channels it compares.
    let args = [
        "--width",
        "32",
        "--height",
        "32",
        "--spp",
        "4",
        "--exposure",
        "0",
        "--tonemap",
        "clamp",
    ];
    let centre = |coloured: bool| {
        let scene = write_quad_gltf(&d, &format!("quad-{coloured}"), coloured);
        let r = render(
            &d,
            &format!("quad-{coloured}"),
            scene.to_str().unwrap(),
            &args,
        );
        assert!(r.ok, "{}", r.stderr);
        let img = rgb(r.png.as_ref().unwrap());
        img.get_pixel(16, 16).0
    };
    let [r, g, b] = centre(true);
    // Red diffuse; the white specular reflection of the sky keeps some green and blue.
    assert!(r > 3 * g && g == b, "coloured quad is not red: {r} {g} {b}");
    let [r, g, b] = centre(false);
    assert!(
        r > 40 && r == g && g == b,
        "plain quad is not grey: {r} {g} {b}"
    );
}

/// A quad facing +Z whose material's base colour (black factor) reads TEXCOORD_0 and
/// whose emission reads TEXCOORD_`emissive_set` of a 2x1 texture, red on the left and
/// blue on the right; TEXCOORD_0 points at the red texel, TEXCOORD_1 at the blue one.
fn write_two_set_quad_gltf(
    dir: &std::path::Path,
    name: &str,
    emissive_set: u32,
) -> std::path::PathBuf {
    let pos: [f32; 12] = [
        -1.0, -1.0, 0.0, 1.0, -1.0, 0.0, 1.0, 1.0, 0.0, -1.0, 1.0, 0.0,
    ];
    let set0 = [0.25f32, 0.5].repeat(4);
    let set1 = [0.75f32, 0.5].repeat(4);
    let idx: [u16; 6] = [0, 1, 2, 0, 2, 3];
    let mut bin: Vec<u8> = pos.iter().flat_map(|v| v.to_le_bytes()).collect();
    bin.extend(set0.iter().chain(&set1).flat_map(|v| v.to_le_bytes()));
    bin.extend(idx.iter().flat_map(|v| v.to_le_bytes()));
    std::fs::write(dir.join(format!("{name}.bin")), &bin).unwrap();
    let img = image::RgbaImage::from_raw(2, 1, vec![255, 0, 0, 255, 0, 0, 255, 255]).unwrap();
    img.save(dir.join(format!("{name}.png"))).unwrap();
    let json = format!(
        r#"{{"asset":{{"version":"2.0"}},
"buffers":[{{"uri":"{name}.bin","byteLength":{}}}],
"bufferViews":[{{"buffer":0,"byteLength":48}},{{"buffer":0,"byteOffset":48,"byteLength":32}},
 {{"buffer":0,"byteOffset":80,"byteLength":32}},{{"buffer":0,"byteOffset":112,"byteLength":12}}],
"accessors":[
 {{"bufferView":0,"componentType":5126,"count":4,"type":"VEC3","min":[-1,-1,0],"max":[1,1,0]}},
 {{"bufferView":1,"componentType":5126,"count":4,"type":"VEC2"}},
 {{"bufferView":2,"componentType":5126,"count":4,"type":"VEC2"}},
 {{"bufferView":3,"componentType":5123,"count":6,"type":"SCALAR"}}],
"images":[{{"uri":"{name}.png"}}],"samplers":[{{"magFilter":9728}}],
"textures":[{{"source":0,"sampler":0}}],
"materials":[{{"pbrMetallicRoughness":{{"baseColorFactor":[0,0,0,1],"metallicFactor":0,
   "baseColorTexture":{{"index":0}}}},
  "emissiveFactor":[1,1,1],"emissiveTexture":{{"index":0,"texCoord":{emissive_set}}},
  "doubleSided":true}}],
"meshes":[{{"primitives":[{{"attributes":{{"POSITION":0,"TEXCOORD_0":1,"TEXCOORD_1":2}},
  "indices":3,"material":0}}]}}],
"nodes":[{{"mesh":0}}],"scenes":[{{"nodes":[0]}}]}}"#,
        bin.len()
    );
    let path = dir.join(format!("{name}.gltf"));
    std::fs::write(&path, json).unwrap();
    path
}

/// Each texture reads the UV set it names in the rendered image: the emission on
/// TEXCOORD_1 shows the blue texel (with one UV set per vertex it showed TEXCOORD_0's
/// red), with the same bits from the tile renderer and from 1 or 3 workers over 4
/// domains; the same file with the emission on TEXCOORD_0 shows red.
#[test]
fn each_texture_reads_its_own_uv_set_in_the_render() {
    let d = tmp("uv-sets");
    let args = [
        "--width",
        "16",
        "--height",
        "16",
        "--spp",
        "2",
        "--exposure",
        "0",
        "--tonemap",
        "clamp",
        "--domains",
        "4",
    ];
    let run = |name: &str, set: u32, workers: &str| {
        let scene = write_two_set_quad_gltf(&d, name, set);
        let tag = format!("{name}-{workers}");
        let r = render(
            &d,
            &tag,
            scene.to_str().unwrap(),
            &[&args[..], &["--workers", workers]].concat(),
        );
        assert!(r.ok, "{tag}: {}", r.stderr);
        assert!(!r.stderr.contains("TEXCOORD"), "{tag}: {}", r.stderr);
        std::fs::read(r.png.as_ref().unwrap()).unwrap()
    };
    let centre = |png: &[u8]| {
        image::load_from_memory(png)
            .unwrap()
            .to_rgb8()
            .get_pixel(8, 8)
            .0
    };
    let two = run("two", 1, "0");
    // The emission, plus the grey of the sky's specular reflection.
    let [r, g, b] = centre(&two);
    assert!(b > 200 && r == g && r + 150 < b, "not blue: {r} {g} {b}");
    for workers in ["1", "3"] {
        assert!(
            run("two", 1, workers) == two,
            "{workers} workers differ from the tile renderer"
        );
    }
    let [r, g, b] = centre(&run("one", 0, "0"));
    assert!(r > 200 && g == b && g + 150 < r, "not red: {r} {g} {b}");
}

/// The film cannot wrap (docs/numerics.md "The film"): one pixel at the most samples a
/// job accepts, each with a contribution far above the clamp, reads the clamp (white, not
/// the black of a wrapped negative sum), saturates nothing, counts the clamps, and has
/// the same linear bits on actors as on the tile renderer.
#[test]
fn the_brightest_pixel_at_the_most_samples_does_not_wrap() {
    let d = tmp("brightest");
    let args = [
        "--width",
        "1",
        "--height",
        "1",
        "--spp",
        "65536",
        "--integrator",
        "raycast",
        "--env",
        "1e8,1e8,1e8",
        "--effects",
        "+environment",
        // The PNG reads the film's largest as white only without exposure and curve.
        "--exposure",
        "0",
        "--tonemap",
        "clamp",
    ];
    let mut exrs = Vec::new();
    let mut clamps = Vec::new();
    for (tag, flags) in [("tiles", &["--workers", "0"][..]), ("actors", &[][..])] {
        let exr = d.join(format!("{tag}.exr"));
        let exr_arg = exr.to_str().unwrap();
        let r = render(
            &d,
            tag,
            "cornell",
            &[&args[..], flags, &["--exr", exr_arg]].concat(),
        );
        assert!(r.ok, "{tag}: {}", r.stderr);
        assert_eq!(
            rgb(r.png.as_ref().unwrap()).get_pixel(0, 0).0,
            [255; 3],
            "{tag}"
        );
        let s = r.stats.unwrap();
        assert_eq!(s["saturated_pixels"], 0, "{tag}: {s}");
        // Nearly every sample's ambient light is far above the clamp (those that meet
        // the lamp are not); the workers count them as the tile renderer does.
        let clamped = s["clamped_contributions"].as_u64().unwrap();
        assert!(clamped > 60_000 && clamped <= 65_536, "{tag}: {s}");
        exrs.push(std::fs::read(&exr).unwrap());
        clamps.push(clamped);
    }
    assert!(exrs[0] == exrs[1], "actors and the tile renderer differ");
    assert_eq!(
        clamps[0], clamps[1],
        "actors and the tile renderer count clamps alike"
    );
}

//! `dray render --time T [--animation NAME]`: a glTF animation sampled at a frame's time,
//! through the real binary. A generated file (a ground quad that stays, a triangle that
//! slides along +X over one second) rendered at two times must give two different
//! images, each the same bits on the reference renderer and on worker actors.

mod common;

use std::path::{Path, PathBuf};

/// Little-endian f32s, base64-encoded (a data URI keeps the test to one file).
fn base64_f32(values: &[f32]) -> String {
    const T: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
    let mut out = String::new();
    for chunk in bytes.chunks(3) {
        let b = [
            chunk[0],
            *chunk.get(1).unwrap_or(&0),
            *chunk.get(2).unwrap_or(&0),
        ];
        let n = (u32::from(b[0]) << 16) | (u32::from(b[1]) << 8) | u32::from(b[2]);
        for i in 0..4 {
            if i <= chunk.len() {
                out.push(T[(n >> (18 - 6 * i) & 63) as usize] as char);
            } else {
                out.push('=');
            }
        }
    }
    out
}

/// Buffer: ground quad (4 positions), triangle (3 positions), key times (2), key
/// translations (2), all f32, non-indexed triangles for the quad via two primitives.
fn write_animated(dir: &Path) -> PathBuf {
    let ground = [
        -2.0, 0.0, -2.0, 2.0, 0.0, -2.0, 2.0, 0.0, 2.0, -2.0, 0.0, -2.0, 2.0, 0.0, 2.0, -2.0, 0.0,
        2.0,
    ];
    let tri = [-0.5, 0.0, 0.0, 0.5, 0.0, 0.0, 0.0, 1.0, 0.0];
    let times = [0.0, 1.0];
    let keys = [-1.0, 0.0, 0.0, 1.0, 0.0, 0.0];
    let all: Vec<f32> = [&ground[..], &tri, &times, &keys].concat();
    let json = format!(
        r#"{{"asset":{{"version":"2.0"}},
"buffers":[{{"uri":"data:application/octet-stream;base64,{data}","byteLength":{len}}}],
"bufferViews":[{{"buffer":0,"byteOffset":0,"byteLength":72}},{{"buffer":0,"byteOffset":72,"byteLength":36}},
 {{"buffer":0,"byteOffset":108,"byteLength":8}},{{"buffer":0,"byteOffset":116,"byteLength":24}}],
"accessors":[
 {{"bufferView":0,"componentType":5126,"count":6,"type":"VEC3","min":[-2,0,-2],"max":[2,0,2]}},
 {{"bufferView":1,"componentType":5126,"count":3,"type":"VEC3","min":[-0.5,0,0],"max":[0.5,1,0]}},
 {{"bufferView":2,"componentType":5126,"count":2,"type":"SCALAR","min":[0],"max":[1]}},
 {{"bufferView":3,"componentType":5126,"count":2,"type":"VEC3"}}],
"materials":[{{"doubleSided":true}}],
"meshes":[{{"name":"ground","primitives":[{{"attributes":{{"POSITION":0}},"material":0}}]}},
          {{"name":"tri","primitives":[{{"attributes":{{"POSITION":1}},"material":0}}]}}],
"nodes":[{{"mesh":0}},{{"mesh":1,"translation":[-1,0,0]}}],
"scenes":[{{"nodes":[0,1]}}],
"animations":[{{"name":"slide","samplers":[{{"input":2,"output":3}}],
  "channels":[{{"sampler":0,"target":{{"node":1,"path":"translation"}}}}]}}]}}"#,
        data = base64_f32(&all),
        len = all.len() * 4
    );
    let path = dir.join("slide.gltf");
    std::fs::write(&path, json).expect("write gltf");
    path
}

#[test]
fn frames_of_an_animation_differ_and_each_is_the_same_bits_on_workers() {
    let dir = common::tmp("animation");
    let scene = write_animated(&dir);
    let scene = scene.to_str().expect("utf-8");
    let view = [
        "--width",
        "48",
        "--height",
        "36",
        "--spp",
        "2",
        "--look-from",
        "0,1.5,4",
        "--look-at",
        "0,0.4,0",
        "--sun",
        "30,60",
    ];
    let mut frames = Vec::new();
    for time in ["0", "0.75"] {
        let mut images = Vec::new();
        for workers in ["0", "2"] {
            let mut args = view.to_vec();
            args.extend(["--time", time, "--animation", "slide", "--workers", workers]);
            let r = common::render(&dir, &format!("t{time}-w{workers}"), scene, &args);
            assert!(r.ok, "--time {time} --workers {workers}: {}", r.stderr);
            images.push(std::fs::read(r.png.expect("png")).expect("read png"));
        }
        assert!(
            images[0] == images[1],
            "--time {time}: workers 0 and 2 differ"
        );
        frames.push(images.swap_remove(0));
    }
    assert!(
        frames[0] != frames[1],
        "the triangle did not move between frames"
    );
    // The rest pose is the node's own translation, which the first key repeats.
    let rest = common::render(
        &dir,
        "rest",
        scene,
        &[&view[..], &["--workers", "0"]].concat(),
    );
    assert!(rest.ok, "{}", rest.stderr);
    assert!(std::fs::read(rest.png.expect("png")).expect("png") == frames[0]);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn an_unknown_animation_is_refused_naming_the_ones_there_are() {
    let dir = common::tmp("animation-bad");
    let scene = write_animated(&dir);
    let r = common::render(
        &dir,
        "bad",
        scene.to_str().expect("utf-8"),
        &[
            "--time",
            "0.5",
            "--animation",
            "walk",
            "--width",
            "8",
            "--height",
            "8",
        ],
    );
    assert!(!r.ok);
    assert!(
        r.stderr.contains("no animation \"walk\"") && r.stderr.contains("\"slide\""),
        "{}",
        r.stderr
    );
    let _ = std::fs::remove_dir_all(&dir);
}

//! glTF 2.0 / GLB import: `dray_scene::gltf::load_gltf` (the `gltf` crate's JSON parser,
//! then dray's own buffer resolution, accessor decoding, node flattening, materials,
//! textures, lights and cameras).
//!
//! The input is the file, optionally followed by an external buffer:
//! `<scene.gltf|scene.glb>` [`\n#---bin\n` `<buf.bin>`]. Input starting with `glTF` is
//! written as `scene.glb`, anything else as `scene.gltf`; `buf.bin` and a valid 2x2
//! `tex.png` sit beside it, so the URIs `buf.bin` and `tex.png` resolve. The loaded
//! scene must keep the loader invariants (`dray_fuzz::check_scene`).

#![no_main]

use dray_fuzz::{Scratch, TEX_PNG, check_scene, split_at_marker};
use dray_scene::gltf::load_gltf;
use libfuzzer_sys::fuzz_target;

fuzz_target!(init: dray_fuzz::init("gltf"), |data: &[u8]| {
    let scratch = Scratch::fresh();
    let (file, bin) = split_at_marker(data, b"\n#---bin\n");
    if let Some(b) = bin {
        scratch.write("buf.bin", b);
    }
    scratch.write("tex.png", TEX_PNG);
    let name = if file.starts_with(b"glTF") { "scene.glb" } else { "scene.gltf" };
    let path = scratch.write(name, file);
    match load_gltf(&path) {
        Ok(scene) => check_scene(&scene),
        Err(e) => {
            let _ = e.to_string();
        }
    }
});

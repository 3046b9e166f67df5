//! OBJ import: `dray_scene::obj::load_obj` (tobj underneath, then dray's MTL mapping,
//! texture loading and validation).
//!
//! The input is up to three files separated by marker lines:
//! `<scene.obj>` [`\n#---mtl\n` `<scene.mtl>` [`\n#---png\n` `<tex.png>`]]. The OBJ
//! reaches the MTL with `mtllib scene.mtl` and the texture with `map_Kd tex.png`; when
//! the input brings no texture a valid 2x2 PNG is written as `tex.png`. The loaded
//! scene must keep the loader invariants (`dray_fuzz::check_scene`).

#![no_main]

use dray_fuzz::{Scratch, TEX_PNG, check_scene, split_at_marker};
use dray_scene::obj::load_obj;
use libfuzzer_sys::fuzz_target;

fuzz_target!(init: dray_fuzz::init("obj"), |data: &[u8]| {
    let scratch = Scratch::fresh();
    let (obj, rest) = split_at_marker(data, b"\n#---mtl\n");
    let (mtl, png) = match rest {
        Some(r) => {
            let (m, p) = split_at_marker(r, b"\n#---png\n");
            (Some(m), p)
        }
        None => (None, None),
    };
    if let Some(m) = mtl {
        scratch.write("scene.mtl", m);
    }
    scratch.write("tex.png", png.unwrap_or(TEX_PNG));
    let path = scratch.write("scene.obj", obj);
    match load_obj(&path) {
        Ok(scene) => check_scene(&scene),
        Err(e) => {
            let _ = e.to_string();
        }
    }
});

//! Hostile scene files, one class per test (see docs/security.md, "Hostile scene
//! files"): every case must come back as an `Err` whose one-line message names the scene
//! file and says what is wrong, without quoting any file's contents, and without a panic
//! anywhere (not even one the loader contains).

use std::cell::Cell;
use std::path::{Path, PathBuf};
use std::sync::Once;

use dray_scene::SceneError;
use dray_scene::gltf::load_gltf;
use dray_scene::obj::load_obj;
use dray_scene::ply::load_ply;

// ---- helpers ------------------------------------------------------------------------

thread_local! {
    static PANICS: Cell<usize> = const { Cell::new(0) };
}

/// Count panics per thread (the loaders contain third-party panics with `catch_unwind`,
/// which would pass unnoticed; a contained panic still counts as a failure here).
fn watch_panics() {
    static HOOK: Once = Once::new();
    HOOK.call_once(|| {
        let default = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            PANICS.with(|p| p.set(p.get() + 1));
            default(info);
        }));
    });
}

fn panics() -> usize {
    PANICS.with(Cell::get)
}

/// A fresh folder `<tmp>/dray-hostile-<pid>-<name>` with `scene/` (where scene files go)
/// and `outside/secret.bin` (a file scenes must not reach), returned as (root, scene dir).
fn dirs(name: &str) -> (PathBuf, PathBuf) {
    watch_panics();
    let root = std::env::temp_dir().join(format!("dray-hostile-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&root);
    let scene = root.join("scene");
    std::fs::create_dir_all(&scene).unwrap();
    std::fs::create_dir_all(root.join("outside")).unwrap();
    std::fs::write(root.join("outside/secret.bin"), SECRET).unwrap();
    (root, scene)
}

/// 36 bytes: as long as the triangle buffer, so only the path check can refuse it.
const SECRET: &[u8; 36] = b"TOP-SECRET-CONTENTS-DO-NOT-PRINT-ME!";

/// Three float3 positions: one triangle.
fn triangle_bin() -> Vec<u8> {
    [0f32, 0., 0., 1., 0., 0., 0., 1., 0.]
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .collect()
}

/// A one-triangle glTF whose buffer is `uri` with `byteLength` `len`, plus `extra`
/// top-level members (e.g. images).
fn gltf_json(uri: &str, len: u64, extra: &str) -> String {
    let uri = serde_json::to_string(uri).unwrap();
    format!(
        r#"{{"asset":{{"version":"2.0"}},
  "buffers":[{{"uri":{uri},"byteLength":{len}}}],
  "bufferViews":[{{"buffer":0,"byteLength":36}}],
  "accessors":[{{"bufferView":0,"componentType":5126,"count":3,"type":"VEC3",
                 "min":[0,0,0],"max":[1,1,0]}}],
  "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}}}}]}}],
  "nodes":[{{"mesh":0}}],"scenes":[{{"nodes":[0]}}],"scene":0{extra}}}"#
    )
}

fn write_gltf(dir: &Path, name: &str, uri: &str, len: u64, extra: &str) -> PathBuf {
    let path = dir.join(name);
    std::fs::write(&path, gltf_json(uri, len, extra)).unwrap();
    path
}

/// The error's message, checked for what every hostile-file error must be: one line,
/// naming the scene file, containing every word of `expect`, quoting no secret, and
/// no panic on this thread.
fn check_err(result: dray_scene::Result<dray_core::scene::Scene>, scene: &Path, expect: &[&str]) {
    let before = panics();
    let err: SceneError = match result {
        Ok(_) => panic!("{}: loaded, but should have been refused", scene.display()),
        Err(e) => e,
    };
    let msg = err.to_string();
    println!("{msg}");
    assert_eq!(panics(), before, "a panic happened: {msg}");
    assert!(!msg.contains('\n'), "not one line: {msg}");
    let name = scene.file_name().unwrap().to_string_lossy();
    assert!(msg.contains(&*name), "does not name the scene file: {msg}");
    for word in expect {
        assert!(msg.contains(word), "expected {word:?} in: {msg}");
    }
    assert!(!msg.contains("SECRET"), "quotes file contents: {msg}");
    assert!(msg.chars().count() < 400, "too long: {msg}");
}

fn mkfifo(path: &Path) {
    use std::os::unix::ffi::OsStrExt;
    let c = std::ffi::CString::new(path.as_os_str().as_bytes()).unwrap();
    // SAFETY: a valid NUL-terminated path.
    let rc = unsafe { libc::mkfifo(c.as_ptr(), 0o644) };
    assert_eq!(rc, 0, "mkfifo {}", path.display());
}

// ---- glTF buffers and images ----------------------------------------------------------

#[test]
fn gltf_buffer_with_an_absolute_path_is_refused() {
    let (root, dir) = dirs("abs");
    let secret = root.join("outside/secret.bin");
    let p = write_gltf(&dir, "abs.gltf", secret.to_str().unwrap(), 36, "");
    check_err(load_gltf(&p), &p, &["buffer 0", "secret.bin", "absolute"]);
    let p = write_gltf(&dir, "etc.gltf", "/etc/passwd", 36, "");
    check_err(load_gltf(&p), &p, &["/etc/passwd", "absolute"]);
}

#[test]
fn gltf_buffer_escaping_with_dotdot_is_refused() {
    let (_root, dir) = dirs("dotdot");
    for uri in [
        "../outside/secret.bin",
        "%2e%2e/outside/secret.bin",
        "sub/../../outside/secret.bin",
        "../../../../../../../../etc/passwd",
    ] {
        std::fs::create_dir_all(dir.join("sub")).unwrap();
        let p = write_gltf(&dir, "dotdot.gltf", uri, 36, "");
        check_err(
            load_gltf(&p),
            &p,
            &["buffer 0", "outside the scene's folder"],
        );
    }
    // `..` that stays inside is fine.
    std::fs::write(dir.join("tri.bin"), triangle_bin()).unwrap();
    let p = write_gltf(&dir, "inside.gltf", "sub/../tri.bin", 36, "");
    assert_eq!(load_gltf(&p).unwrap().mesh.indices.len(), 1);
}

#[test]
fn gltf_buffer_symlink_out_of_the_folder_is_refused() {
    let (root, dir) = dirs("symlink");
    std::os::unix::fs::symlink(root.join("outside/secret.bin"), dir.join("link.bin")).unwrap();
    let p = write_gltf(&dir, "link.gltf", "link.bin", 36, "");
    check_err(
        load_gltf(&p),
        &p,
        &["link.bin", "outside the scene's folder"],
    );
    // A symlinked folder out of the scene's folder too.
    std::os::unix::fs::symlink(root.join("outside"), dir.join("out")).unwrap();
    let p = write_gltf(&dir, "linkdir.gltf", "out/secret.bin", 36, "");
    check_err(load_gltf(&p), &p, &["outside the scene's folder"]);
}

#[test]
fn gltf_file_uris_are_refused() {
    let (root, dir) = dirs("fileuri");
    std::fs::write(dir.join("tri.bin"), triangle_bin()).unwrap();
    let secret = root.join("outside/secret.bin");
    for uri in [
        format!("file://{}", secret.display()),
        format!("file:{}", secret.display()),
        format!("FILE://{}", dir.join("tri.bin").display()),
        "file:tri.bin".to_string(),
    ] {
        let p = write_gltf(&dir, "fileuri.gltf", &uri, 36, "");
        check_err(
            load_gltf(&p),
            &p,
            &["buffer 0", "file: URIs are not allowed"],
        );
    }
    let p = write_gltf(&dir, "http.gltf", "http://example.com/tri.bin", 36, "");
    check_err(load_gltf(&p), &p, &["not supported"]);
}

#[test]
fn gltf_device_files_fifos_and_folders_are_refused() {
    let (_root, dir) = dirs("devices");
    // /dev/zero by absolute path, by escaping and through a symlink in the folder: all
    // outside the folder, refused before anything is read (it would never end).
    let p = write_gltf(&dir, "zero.gltf", "/dev/zero", 36, "");
    check_err(load_gltf(&p), &p, &["absolute"]);
    std::os::unix::fs::symlink("/dev/zero", dir.join("zero.bin")).unwrap();
    let p = write_gltf(&dir, "zerolink.gltf", "zero.bin", 36, "");
    check_err(
        load_gltf(&p),
        &p,
        &["zero.bin", "outside the scene's folder"],
    );
    // Inside the folder but not regular files: a FIFO (opening it must not block) and
    // a folder.
    mkfifo(&dir.join("fifo.bin"));
    let p = write_gltf(&dir, "fifo.gltf", "fifo.bin", 36, "");
    check_err(load_gltf(&p), &p, &["fifo.bin", "not a regular file"]);
    std::fs::create_dir_all(dir.join("folder.bin")).unwrap();
    let p = write_gltf(&dir, "folder.gltf", "folder.bin", 36, "");
    check_err(load_gltf(&p), &p, &["folder.bin", "not a regular file"]);
}

#[test]
fn gltf_byte_length_is_enforced() {
    let (_root, dir) = dirs("bytelength");
    std::fs::write(dir.join("tri.bin"), triangle_bin()).unwrap();
    // Shorter than declared: refused, and a huge declaration does not allocate it.
    let p = write_gltf(&dir, "short.gltf", "tri.bin", 48, "");
    check_err(
        load_gltf(&p),
        &p,
        &["tri.bin", "byteLength is 48", "36 bytes"],
    );
    let p = write_gltf(&dir, "huge.gltf", "tri.bin", 1 << 50, "");
    check_err(load_gltf(&p), &p, &["tri.bin", "byteLength"]);
    // Longer than declared: only byteLength is read, so a view past it is out of range.
    let mut long = triangle_bin();
    long.extend_from_slice(&[0u8; 64]);
    std::fs::write(dir.join("long.bin"), long).unwrap();
    let p = write_gltf(&dir, "long.gltf", "long.bin", 36, "");
    assert_eq!(load_gltf(&p).unwrap().mesh.indices.len(), 1);
    let json = gltf_json("long.bin", 36, "").replace(
        r#""bufferViews":[{"buffer":0,"byteLength":36}]"#,
        r#""bufferViews":[{"buffer":0,"byteOffset":36,"byteLength":36}]"#,
    );
    let p = dir.join("past.gltf");
    std::fs::write(&p, json).unwrap();
    check_err(load_gltf(&p), &p, &["buffer view 0", "36 bytes"]);
}

#[test]
fn gltf_image_uris_are_held_to_the_same_rules() {
    let (root, dir) = dirs("images");
    std::fs::write(dir.join("tri.bin"), triangle_bin()).unwrap();
    let image = |uri: &str| {
        format!(
            r#","images":[{{"uri":{}}}],"textures":[{{"source":0}}]"#,
            serde_json::to_string(uri).unwrap()
        )
    };
    let secret = root.join("outside/secret.bin");
    for (uri, words) in [
        ("../outside/secret.bin", &["image 0", "outside"][..]),
        (secret.to_str().unwrap(), &["image 0", "absolute"][..]),
        ("file:///etc/passwd", &["image 0", "file: URIs"][..]),
        ("/dev/zero", &["image 0", "absolute"][..]),
    ] {
        let p = write_gltf(&dir, "img.gltf", "tri.bin", 36, &image(uri));
        check_err(load_gltf(&p), &p, words);
    }
}

#[test]
fn long_uris_are_shortened_in_messages() {
    let (_root, dir) = dirs("longuri");
    let uri = format!("../{}/x.bin", "a".repeat(5000));
    let p = write_gltf(&dir, "long.gltf", &uri, 36, "");
    check_err(load_gltf(&p), &p, &["…", "outside"]);
    let uri = format!("missing-{}\n.bin", "b".repeat(5000));
    let p = write_gltf(&dir, "long2.gltf", &uri, 36, "");
    check_err(load_gltf(&p), &p, &["…"]);
}

// ---- OBJ material libraries and textures ----------------------------------------------

const OBJ_TRI: &str = "v 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl m\nf 1 2 3\n";

#[test]
fn obj_mtllib_outside_the_folder_is_refused() {
    let (root, dir) = dirs("mtllib");
    std::fs::write(root.join("outside/evil.mtl"), "newmtl m\nKd 1 0 0\n").unwrap();
    let evil = root.join("outside/evil.mtl");
    std::os::unix::fs::symlink(&evil, dir.join("link.mtl")).unwrap();
    mkfifo(&dir.join("fifo.mtl"));
    for (lib, words) in [
        ("../outside/evil.mtl", &["material library", "outside"][..]),
        (
            evil.to_str().unwrap(),
            &["material library", "absolute"][..],
        ),
        ("link.mtl", &["material library", "outside"][..]),
        ("/dev/zero", &["material library", "absolute"][..]),
        ("fifo.mtl", &["material library", "not a regular file"][..]),
    ] {
        let p = dir.join("scene.obj");
        std::fs::write(&p, format!("mtllib {lib}\n{OBJ_TRI}")).unwrap();
        check_err(load_obj(&p), &p, words);
    }
    // A library missing inside the folder stays a warning.
    let p = dir.join("scene.obj");
    std::fs::write(&p, format!("mtllib nothere.mtl\n{OBJ_TRI}")).unwrap();
    let scene = load_obj(&p).unwrap();
    assert!(
        scene
            .stats
            .warnings
            .iter()
            .any(|w| w.contains("nothere.mtl"))
    );
}

#[test]
fn obj_textures_outside_the_folder_are_refused() {
    let (root, dir) = dirs("objtex");
    std::fs::write(root.join("outside/evil.png"), SECRET).unwrap();
    std::os::unix::fs::symlink("/dev/zero", dir.join("zero.png")).unwrap();
    for (map, words) in [
        ("../outside/evil.png", &["texture", "outside"][..]),
        ("/etc/passwd", &["texture", "absolute"][..]),
        ("..\\outside\\evil.png", &["texture", "outside"][..]),
        ("zero.png", &["texture", "outside"][..]),
    ] {
        std::fs::write(dir.join("m.mtl"), format!("newmtl m\nmap_Kd {map}\n")).unwrap();
        let p = dir.join("tex.obj");
        std::fs::write(&p, format!("mtllib m.mtl\n{OBJ_TRI}")).unwrap();
        check_err(load_obj(&p), &p, words);
    }
}

#[test]
fn obj_inputs_that_panicked_inside_tobj_are_errors() {
    let (_root, dir) = dirs("tobj");
    for (name, obj, words) in [
        (
            "vn.obj",
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 1\nf 1//9223372036854775807 2//1 3//1\n",
            &["normal index", "out of range"][..],
        ),
        (
            "vt.obj",
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 1\nf 1/-5 2/1 3/1\n",
            &["texture coordinate index -5", "out of range"][..],
        ),
        (
            "zero.obj",
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/0 2/1 3/1\n",
            &["index 0"][..],
        ),
    ] {
        let p = dir.join(name);
        std::fs::write(&p, obj).unwrap();
        check_err(load_obj(&p), &p, words);
    }
    std::fs::write(dir.join("short.mtl"), "newmtl a\nKd 4\n").unwrap();
    let p = dir.join("short.obj");
    std::fs::write(
        &p,
        "mtllib short.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl a\nf 1 2 3\n",
    )
    .unwrap();
    check_err(load_obj(&p), &p, &["short.mtl", "Kd needs three numbers"]);
}

// ---- the scene file itself ------------------------------------------------------------

#[test]
fn scene_files_that_are_not_regular_files_are_refused() {
    let (_root, dir) = dirs("scenefile");
    for name in ["zero.gltf", "zero.glb", "zero.obj", "zero.ply"] {
        std::os::unix::fs::symlink("/dev/zero", dir.join(name)).unwrap();
    }
    check_err(
        load_gltf(&dir.join("zero.gltf")),
        &dir.join("zero.gltf"),
        &["not a regular file"],
    );
    check_err(
        load_gltf(&dir.join("zero.glb")),
        &dir.join("zero.glb"),
        &["not a regular file"],
    );
    check_err(
        load_obj(&dir.join("zero.obj")),
        &dir.join("zero.obj"),
        &["not a regular file"],
    );
    check_err(
        load_ply(&dir.join("zero.ply")),
        &dir.join("zero.ply"),
        &["not a regular file"],
    );
    mkfifo(&dir.join("fifo.ply"));
    check_err(
        load_ply(&dir.join("fifo.ply")),
        &dir.join("fifo.ply"),
        &["not a regular file"],
    );
    std::fs::create_dir_all(dir.join("folder.obj")).unwrap();
    check_err(
        load_obj(&dir.join("folder.obj")),
        &dir.join("folder.obj"),
        &["not a regular file"],
    );
    // Through the one entry point, too.
    let p = dir.join("zero.gltf");
    check_err(
        dray_scene::load(p.to_str().unwrap()),
        &p,
        &["not a regular file"],
    );
}

#[test]
fn glb_header_behind_a_byte_order_mark_is_checked() {
    let (_root, dir) = dirs("bomglb");
    let p = dir.join("bom.glb");
    std::fs::write(&p, b"\xef\xbb\xbfglTF\x02\0\0\0\x04\0\0\0").unwrap();
    check_err(load_gltf(&p), &p, &["GLB header declares 4 bytes"]);
}

// ---- geometry -------------------------------------------------------------------------

fn ply_ascii(vertices: &[[&str; 3]], faces: &[[u32; 3]]) -> String {
    let mut s = format!(
        "ply\nformat ascii 1.0\nelement vertex {}\nproperty float x\nproperty float y\n\
         property float z\nelement face {}\nproperty list uchar int vertex_indices\nend_header\n",
        vertices.len(),
        faces.len()
    );
    for v in vertices {
        s += &format!("{} {} {}\n", v[0], v[1], v[2]);
    }
    for f in faces {
        s += &format!("3 {} {} {}\n", f[0], f[1], f[2]);
    }
    s
}

#[test]
fn coordinates_near_the_float_range_are_refused_at_import() {
    let (_root, dir) = dirs("floatrange");
    let p = dir.join("huge.ply");
    let v = [["-3e38", "0", "0"], ["3e38", "0", "0"], ["0", "3e38", "0"]];
    std::fs::write(&p, ply_ascii(&v, &[[0, 1, 2]])).unwrap();
    check_err(load_ply(&p), &p, &["vertex 0", "beyond ±1e18"]);
    // A value past f32 is infinite once read.
    let p = dir.join("inf.obj");
    std::fs::write(&p, "v 0 0 0\nv 1e39 0 0\nv 0 1 0\nf 1 2 3\n").unwrap();
    check_err(load_obj(&p), &p, &["vertex 1", "non-finite"]);
    // In range in the file, out of range once a node's scale is applied.
    std::fs::write(dir.join("tri.bin"), triangle_bin()).unwrap();
    let json = gltf_json("tri.bin", 36, "").replace(
        r#""nodes":[{"mesh":0}]"#,
        r#""nodes":[{"mesh":0,"scale":[1e30,1e30,1e30]}]"#,
    );
    let p = dir.join("scaled.gltf");
    std::fs::write(&p, json).unwrap();
    check_err(load_gltf(&p), &p, &["beyond ±1e18"]);
}

#[test]
fn many_coincident_triangles_load_and_build() {
    let (_root, dir) = dirs("coincident");
    // 100k copies of one triangle, binary: a small file whose BVH used to be a chain
    // 100k deep (quadratic to build, then a stack overflow converting it).
    let n = 100_000u32;
    let mut bytes = format!(
        "ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\n\
         property float y\nproperty float z\nelement face {n}\n\
         property list uchar int vertex_indices\nend_header\n"
    )
    .into_bytes();
    for v in [0f32, 0., 0., 1., 0., 0., 0., 1., 0.] {
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    // Each face: a count of 3, then vertex indices 0, 1, 2 as little-endian i32.
    let face = [3u8, 0, 0, 0, 0, 1, 0, 0, 0, 2, 0, 0, 0];
    for _ in 0..n {
        bytes.extend_from_slice(&face);
    }
    let p = dir.join("coincident.ply");
    std::fs::write(&p, bytes).unwrap();
    let scene = load_ply(&p).unwrap();
    assert_eq!(scene.mesh.indices.len(), n as usize);
    let accel = dray_core::bvh::Accel::build(&scene.mesh);
    assert_eq!(accel.triangle_count(), n as usize);
    let ray = dray_core::bvh::QueryRay {
        origin: glam::Vec3::new(0.25, 0.25, 1.0),
        dir: glam::Vec3::NEG_Z,
        tmin: 0.0,
        tmax: f32::INFINITY,
    };
    let hit = accel.closest(&ray, |_, _| true).expect("hits the triangle");
    assert_eq!(hit.tri, 0, "ties go to the lowest index");
}

// ---- scene packages -------------------------------------------------------------------

#[test]
fn package_domains_with_non_finite_positions_are_refused() {
    use dray_scene::partition::checksum::{checksum, to_hex};
    use dray_scene::partition::package::WriteOptions;
    use dray_scene::partition::{LayoutSpec, SceneParts, open_package, write_package};
    let (_root, dir) = dirs("package");
    let scene = dray_scene::load("cornell").unwrap();
    let pkg = dir.join("pkg");
    let options = WriteOptions::default();
    write_package(
        &pkg,
        SceneParts::of(&scene),
        &scene,
        &LayoutSpec::Kd(2),
        &options,
    )
    .unwrap();
    open_package(&pkg).unwrap().verify().unwrap();
    // Vertex 0 of domain 0 (right after the 32-byte header) becomes NaN, and the
    // checksums are recomputed, as a hostile writer would: only the position check is
    // left to refuse it.
    let f = pkg.join("domain-00000.bin");
    let mut bytes = std::fs::read(&f).unwrap();
    bytes[32..36].copy_from_slice(&f32::NAN.to_le_bytes());
    std::fs::write(&f, &bytes).unwrap();
    let m = pkg.join("manifest.json");
    let mut v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&m).unwrap()).unwrap();
    v["body"]["domains"][0]["xxh3"] = to_hex(checksum(&bytes)).into();
    let body = serde_json::to_string(&v["body"]).unwrap();
    v["body_xxh3"] = to_hex(checksum(body.as_bytes())).into();
    std::fs::write(&m, serde_json::to_string(&v).unwrap()).unwrap();
    let before = panics();
    let pkg = open_package(&pkg).unwrap();
    let msg = match pkg.load_domain(0) {
        Ok(_) => panic!("a NaN position was loaded"),
        Err(e) => e.to_string(),
    };
    println!("{msg}");
    assert!(
        msg.contains("domain-00000.bin") && msg.contains("vertex 0 has a non-finite position"),
        "{msg}"
    );
    assert!(pkg.verify().is_err());
    pkg.load_domain(1).unwrap();
    assert_eq!(panics(), before);
}

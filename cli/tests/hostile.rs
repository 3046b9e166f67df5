//! Hostile input to the real `dray render` process (see docs/security.md, "Hostile scene
//! files"): each case must end with one `dray: error: ...` line on stderr and a non-zero
//! exit, write no image, and never panic or overflow a stack; output path problems are
//! reported before any work is done.

use std::path::{Path, PathBuf};
use std::process::Command;

/// A fresh folder `<tmp>/dray-cli-hostile-<pid>-<name>` with `scene/` and
/// `outside/secret.bin` (36 bytes a scene must never reach or print).
fn dirs(name: &str) -> (PathBuf, PathBuf) {
    let root = std::env::temp_dir().join(format!("dray-cli-hostile-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&root);
    let scene = root.join("scene");
    std::fs::create_dir_all(&scene).unwrap();
    std::fs::create_dir_all(root.join("outside")).unwrap();
    std::fs::write(root.join("outside/secret.bin"), SECRET).unwrap();
    (root, scene)
}

const SECRET: &[u8; 36] = b"TOP-SECRET-CONTENTS-DO-NOT-PRINT-ME!";

struct Out {
    ok: bool,
    stderr: String,
}

fn dray(args: &[&str]) -> Out {
    let out = Command::new(env!("CARGO_BIN_EXE_dray"))
        .args(args)
        .output()
        .expect("run dray");
    Out {
        ok: out.status.success(),
        stderr: String::from_utf8_lossy(&out.stderr).into_owned(),
    }
}

/// `dray render SCENE --output PNG -q` plus `args`, small and quick.
fn render(scene: &Path, png: &Path, args: &[&str]) -> Out {
    let (scene, png) = (scene.to_str().unwrap(), png.to_str().unwrap());
    let mut all = vec!["render", scene, "--output", png, "-q"];
    all.extend_from_slice(&["--width", "32", "--height", "24", "--spp", "1"]);
    all.extend_from_slice(args);
    dray(&all)
}

/// The run failed the way hostile input must: non-zero exit, exactly one line on
/// stderr, `dray: error: ` with every word of `expect`, no panic, no stack overflow, no
/// file contents, and no image at `png`.
fn refused(out: &Out, png: Option<&Path>, expect: &[&str]) {
    let e = &out.stderr;
    println!("{e}");
    assert!(!out.ok, "succeeded: {e}");
    assert_eq!(e.lines().count(), 1, "not one line: {e}");
    assert!(e.starts_with("dray: error: "), "{e}");
    for word in expect {
        assert!(e.contains(word), "expected {word:?} in: {e}");
    }
    for bad in [
        "panicked",
        "stack overflow",
        "overflowed",
        "SECRET",
        "RUST_BACKTRACE",
    ] {
        assert!(!e.contains(bad), "{bad:?} in: {e}");
    }
    if let Some(png) = png {
        assert!(!png.exists(), "an image was written: {}", png.display());
    }
}

fn triangle_bin() -> Vec<u8> {
    [0f32, 0., 0., 1., 0., 0., 0., 1., 0.]
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .collect()
}

fn write_gltf(dir: &Path, name: &str, uri: &str, len: u64) -> PathBuf {
    let uri = serde_json::to_string(uri).unwrap();
    let json = format!(
        r#"{{"asset":{{"version":"2.0"}},
  "buffers":[{{"uri":{uri},"byteLength":{len}}}],
  "bufferViews":[{{"buffer":0,"byteLength":36}}],
  "accessors":[{{"bufferView":0,"componentType":5126,"count":3,"type":"VEC3",
                 "min":[0,0,0],"max":[1,1,0]}}],
  "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}}}}]}}],
  "nodes":[{{"mesh":0}}],"scenes":[{{"nodes":[0]}}],"scene":0}}"#
    );
    let path = dir.join(name);
    std::fs::write(&path, json).unwrap();
    path
}

fn mkfifo(path: &Path) {
    let status = Command::new("mkfifo").arg(path).status().expect("mkfifo");
    assert!(status.success(), "mkfifo {}", path.display());
}

#[test]
fn gltf_references_out_of_the_scene_folder_are_one_line_errors() {
    let (root, dir) = dirs("gltf");
    std::os::unix::fs::symlink("/dev/zero", dir.join("zero.bin")).unwrap();
    std::os::unix::fs::symlink(root.join("outside/secret.bin"), dir.join("link.bin")).unwrap();
    mkfifo(&dir.join("fifo.bin"));
    std::fs::write(dir.join("tri.bin"), triangle_bin()).unwrap();
    let secret = root.join("outside/secret.bin");
    let file_uri = format!("file://{}", secret.display());
    let cases: Vec<(&str, u64, &[&str])> = vec![
        (
            "../outside/secret.bin",
            36,
            &["buffer 0", "outside the scene's folder"],
        ),
        (secret.to_str().unwrap(), 36, &["buffer 0", "absolute"]),
        (&file_uri, 36, &["buffer 0", "file: URIs are not allowed"]),
        ("/dev/zero", 36, &["absolute"]),
        ("zero.bin", 36, &["zero.bin", "outside the scene's folder"]),
        ("link.bin", 36, &["link.bin", "outside the scene's folder"]),
        ("fifo.bin", 36, &["fifo.bin", "not a regular file"]),
        ("tri.bin", 4096, &["tri.bin", "byteLength is 4096"]),
    ];
    for (i, (uri, len, words)) in cases.into_iter().enumerate() {
        let scene = write_gltf(&dir, &format!("case{i}.gltf"), uri, len);
        let png = root.join(format!("case{i}.png"));
        let out = render(&scene, &png, &[]);
        refused(&out, Some(&png), words);
        assert!(
            out.stderr.contains(&format!("case{i}.gltf")),
            "{}",
            out.stderr
        );
    }
    // The same scene with its buffer in place renders.
    let scene = write_gltf(&dir, "good.gltf", "tri.bin", 36);
    let png = root.join("good.png");
    let out = render(&scene, &png, &[]);
    assert!(out.ok && png.exists(), "{}", out.stderr);
}

#[test]
fn obj_references_and_scene_files_that_are_not_files() {
    let (root, dir) = dirs("obj");
    let tri = "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n";
    let obj = dir.join("escape.obj");
    std::fs::write(&obj, format!("mtllib ../outside/secret.bin\n{tri}")).unwrap();
    let png = root.join("escape.png");
    refused(
        &render(&obj, &png, &[]),
        Some(&png),
        &["escape.obj", "material library", "outside"],
    );
    std::fs::write(dir.join("m.mtl"), "newmtl m\nmap_Kd /etc/passwd\n").unwrap();
    let obj = dir.join("tex.obj");
    std::fs::write(&obj, format!("mtllib m.mtl\nusemtl m\n{tri}")).unwrap();
    refused(
        &render(&obj, &png, &[]),
        Some(&png),
        &["tex.obj", "texture", "absolute"],
    );
    // The scene itself: a symlink to /dev/zero and a FIFO (neither may hang or eat memory).
    std::os::unix::fs::symlink("/dev/zero", dir.join("zero.glb")).unwrap();
    refused(
        &render(&dir.join("zero.glb"), &png, &[]),
        Some(&png),
        &["zero.glb", "not a regular file"],
    );
    mkfifo(&dir.join("fifo.ply"));
    refused(
        &render(&dir.join("fifo.ply"), &png, &[]),
        Some(&png),
        &["fifo.ply", "not a regular file"],
    );
}

#[test]
fn coordinates_near_the_float_range_are_an_error_not_a_panic() {
    let (root, dir) = dirs("floatrange");
    let ply = dir.join("huge.ply");
    std::fs::write(
        &ply,
        "ply\nformat ascii 1.0\nelement vertex 6\nproperty float x\nproperty float y\n\
         property float z\nelement face 2\nproperty list uchar int vertex_indices\n\
         end_header\n0 0 0\n1 0 0\n0 1 0\n3e38 0 0\n3e38 1e38 0\n3e38 0 1e38\n\
         3 0 1 2\n3 3 4 5\n",
    )
    .unwrap();
    let png = root.join("huge.png");
    for workers in ["0", "1"] {
        refused(
            &render(&ply, &png, &["--workers", workers]),
            Some(&png),
            &["huge.ply", "vertex 3", "beyond"],
        );
    }
    // Moved there after import (--translate): held to the same bound.
    let ok = dir.join("ok.ply");
    std::fs::write(
        &ok,
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n\
         property float z\nelement face 1\nproperty list uchar int vertex_indices\n\
         end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n",
    )
    .unwrap();
    let out = render(&ok, &png, &["--translate", "3e38,0,0", "--workers", "0"]);
    refused(&out, Some(&png), &["--translate", "vertex 0", "beyond"]);
}

/// `dray render` with `args`, stderr into a file, waited for at most `secs` (killed and
/// failed beyond: the case under test used to hang).
fn render_within(root: &Path, name: &str, args: &[&str], secs: u64) -> Out {
    let png = root.join(format!("{name}.png"));
    let log = root.join(format!("{name}.stderr"));
    let mut all = vec!["render", "--output", png.to_str().unwrap(), "-q"];
    all.extend_from_slice(&["--width", "32", "--height", "24", "--spp", "1"]);
    all.extend_from_slice(args);
    let mut child = Command::new(env!("CARGO_BIN_EXE_dray"))
        .args(&all)
        .stdout(std::process::Stdio::null())
        .stderr(std::fs::File::create(&log).unwrap())
        .spawn()
        .expect("run dray");
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(secs);
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if std::time::Instant::now() > deadline {
            let _ = child.kill();
            let _ = child.wait();
            panic!(
                "dray {all:?} still running after {secs} s: {}",
                std::fs::read_to_string(&log).unwrap_or_default()
            );
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    };
    assert!(!png.exists(), "an image was written for {args:?}");
    Out {
        ok: status.success(),
        stderr: std::fs::read_to_string(&log).unwrap(),
    }
}

/// docs/security.md "Hardening, second round", item 3: `--translate 1e25,0,0` (or 1e22, or
/// 3e38) panicked in the BVH
/// conversion: exit 101 with `--workers 0`, and a hang with worker actors (the tracing
/// thread that loaded the domain died and the job waited for it). Now it is refused like
/// a file with such coordinates, in both modes, before anything is built.
#[test]
fn translating_beyond_the_coordinate_bound_is_an_error_in_both_modes() {
    let (root, _) = dirs("translate");
    for (i, t) in ["1e25,0,0", "0,1e22,0", "0,0,-3e38"].iter().enumerate() {
        for workers in ["0", "1", "2"] {
            let name = format!("t{i}-{workers}");
            let out = render_within(
                &root,
                &name,
                &["cornell", "--translate", t, "--workers", workers],
                300,
            );
            refused(&out, None, &["--translate", t, "beyond", "1e18"]);
        }
    }
}

#[test]
fn many_coincident_triangles_render_without_overflowing_the_stack() {
    let (root, dir) = dirs("coincident");
    let n = 100_000u32;
    let mut bytes = format!(
        "ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\n\
         property float y\nproperty float z\nelement face {n}\n\
         property list uchar int vertex_indices\nend_header\n"
    )
    .into_bytes();
    bytes.extend(triangle_bin());
    // Each face: a count of 3, then vertex indices 0, 1, 2 as little-endian i32.
    let face = [3u8, 0, 0, 0, 0, 1, 0, 0, 0, 2, 0, 0, 0];
    for _ in 0..n {
        bytes.extend_from_slice(&face);
    }
    let ply = dir.join("coincident.ply");
    std::fs::write(&ply, bytes).unwrap();
    // Default flags (one in-process worker actor, path tracing), except a small image:
    // every ray that meets the triangle tests all 100k copies.
    let png = root.join("coincident.png");
    let out = render(&ply, &png, &[]);
    assert!(out.ok, "{}", out.stderr);
    assert!(png.exists());
    for bad in ["panicked", "overflow"] {
        assert!(!out.stderr.contains(bad), "{}", out.stderr);
    }
    let img = image::open(&png).unwrap();
    assert_eq!((img.width(), img.height()), (32, 24));
}

#[test]
fn thread_counts_have_an_upper_bound() {
    let (root, _dir) = dirs("threads");
    let png = root.join("t.png");
    for n in ["4097", "100000000", "18446744073709551615"] {
        let out = dray(&[
            "render",
            "cornell",
            "--threads",
            n,
            "--output",
            png.to_str().unwrap(),
        ]);
        refused(&out, Some(&png), &["--threads", "4096"]);
    }
    let out = dray(&["render", "cornell", "--threads=-1"]);
    refused(&out, None, &["--threads"]);
    // The bound itself is accepted: the run gets as far as the (missing) scene. (Not
    // rendered: 4096 threads are more than a shared test machine should be asked for.)
    let out = dray(&[
        "render",
        "no-such-scene.ply",
        "--threads",
        "4096",
        "--output",
        png.to_str().unwrap(),
    ]);
    refused(&out, Some(&png), &["no-such-scene.ply"]);
    let out = dray(&[
        "render",
        "cornell",
        "--threads",
        "3",
        "--width",
        "8",
        "--height",
        "8",
        "--spp",
        "1",
        "-q",
        "--output",
        png.to_str().unwrap(),
    ]);
    assert!(out.ok && png.exists(), "{}", out.stderr);
}

#[test]
fn output_paths_are_checked_before_rendering() {
    let (root, _dir) = dirs("output");
    std::fs::create_dir_all(root.join("a-folder.png")).unwrap();
    std::fs::write(root.join("file"), b"x").unwrap();
    let missing = root.join("no/such/folder/out.png");
    let folder = root.join("a-folder.png");
    let txt = root.join("out.txt");
    let under_file = root.join("file/out.png");
    let cases: Vec<(&Path, &[&str])> = vec![
        (&missing, &["--output", "does not exist"]),
        (&folder, &["--output", "is a folder"]),
        (&txt, &["--output", "unsupported file type", ".png"]),
        (&under_file, &["--output", "is not a folder"]),
        (
            Path::new("/proc/dray-hostile-test.png"),
            &["--output", "cannot be written"],
        ),
    ];
    // A scene that does not exist: if the output were checked after loading (let alone
    // rendering), the error would be about the scene.
    for (png, words) in cases {
        let out = dray(&[
            "render",
            "no-such-scene.ply",
            "--output",
            png.to_str().unwrap(),
        ]);
        refused(&out, None, words);
        assert!(!out.stderr.contains("no-such-scene"), "{}", out.stderr);
    }
    assert!(folder.is_dir(), "the folder is left alone");
    // --exr and --stats get the same checks; a good --output is not created by them.
    let png = root.join("fine.png");
    let side_cases: [(&str, PathBuf, &[&str]); 3] = [
        (
            "--exr",
            root.join("missing/x.exr"),
            &["--exr", "does not exist"],
        ),
        ("--exr", root.join("x.png"), &["--exr", ".exr"]),
        ("--stats", folder.clone(), &["--stats", "is a folder"]),
    ];
    for (flag, path, words) in side_cases {
        let out = dray(&[
            "render",
            "cornell",
            "--output",
            png.to_str().unwrap(),
            flag,
            path.to_str().unwrap(),
        ]);
        refused(&out, Some(&png), words);
    }
    // An existing output file is left as it was by the check (and then replaced).
    std::fs::write(&png, b"old").unwrap();
    let out = dray(&[
        "render",
        "cornell",
        "--width",
        "8",
        "--height",
        "8",
        "--spp",
        "1",
        "-q",
        "--output",
        png.to_str().unwrap(),
    ]);
    assert!(out.ok, "{}", out.stderr);
    assert!(image::open(&png).is_ok());
}

/// A coordinator cannot be told to admit more jobs than a worker holds
/// (`dray_cache::bounds::MAX_COORDINATOR_JOBS`, half of a worker's bound): `--max-jobs`
/// beyond it is refused by name. (The worker's other bounds and the coordinator's limits
/// are one definition, `dray_cache::bounds`, so they cannot drift apart.)
#[test]
fn max_jobs_beyond_what_a_worker_holds_is_refused() {
    use dray_cache::bounds::MAX_COORDINATOR_JOBS;
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_dray"))
        .args(["coordinator", "--listen", "127.0.0.1:0", "--max-jobs"])
        .arg((MAX_COORDINATOR_JOBS + 1).to_string())
        .output()
        .expect("run dray coordinator");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{err}");
    assert!(
        err.contains("--max-jobs") && err.contains("1..=128"),
        "{err}"
    );
}

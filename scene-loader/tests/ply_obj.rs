//! PLY and OBJ import: encodings, skipping of unknown data, error reporting on malformed
//! files (never a panic), MTL mapping, and the shared real-world scans.

use std::fs;
use std::path::{Path, PathBuf};

use dray_core::material::AlphaMode;
use dray_core::scene::Scene;
use dray_scene::SceneError;
use dray_scene::obj::load_obj;
use dray_scene::ply::load_ply;
use glam::{Vec2, Vec3, Vec4};

/// A fresh, empty directory unique to this process and test.
fn tmpdir(test: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("dray-ply-obj-{}-{test}", std::process::id()));
    let _ = fs::remove_dir_all(&d);
    fs::create_dir_all(&d).unwrap();
    d
}

fn write(dir: &Path, name: &str, bytes: impl AsRef<[u8]>) -> PathBuf {
    let p = dir.join(name);
    fs::write(&p, bytes).unwrap();
    p
}

// The test mesh: a unit quad (0..3) and a triangle (1, 4, 2) beside it.
const POS: [[f32; 3]; 5] = [
    [0.0, 0.0, 0.0],
    [1.0, 0.0, 0.0],
    [1.0, 1.0, 0.0],
    [0.0, 1.0, 0.0],
    [2.0, 0.0, 0.0],
];
const UV: [[f32; 2]; 5] = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0], [0.5, 0.25]];
const FACES: [&[u32]; 2] = [&[0, 1, 2, 3], &[1, 4, 2]];
const TRIS: [[u32; 3]; 3] = [[0, 1, 2], [0, 2, 3], [1, 4, 2]];

fn ascii_ply() -> String {
    let mut s = String::from(
        "ply\r\nformat ascii 1.0\ncomment made by the dray tests\nobj_info nothing\n\
         element vertex 5\nproperty float x\nproperty float32 y\nproperty double z\n\
         property float confidence\nproperty float nx\nproperty float ny\nproperty float nz\n\
         property float s\nproperty float t\nproperty uchar intensity\n\
         element face 2\nproperty list uchar int vertex_indices\nend_header\n",
    );
    for (p, t) in POS.iter().zip(UV) {
        s += &format!(
            "{} {} {} 0.5 0 0 1 {} {} 200\n",
            p[0], p[1], p[2], t[0], t[1]
        );
    }
    for f in FACES {
        s += &format!("{}", f.len());
        for i in f {
            s += &format!(" {i}");
        }
        s += "\n";
    }
    s
}

/// Binary writer in either byte order.
struct Bin {
    be: bool,
    out: Vec<u8>,
}

impl Bin {
    fn put<const N: usize>(&mut self, le: [u8; N], be: [u8; N]) {
        self.out.extend_from_slice(if self.be { &be } else { &le });
    }
    fn f32(&mut self, v: f32) {
        self.put(v.to_le_bytes(), v.to_be_bytes());
    }
    fn f64(&mut self, v: f64) {
        self.put(v.to_le_bytes(), v.to_be_bytes());
    }
    fn u8(&mut self, v: u8) {
        self.out.push(v);
    }
    fn i16(&mut self, v: i16) {
        self.put(v.to_le_bytes(), v.to_be_bytes());
    }
    fn i32(&mut self, v: i32) {
        self.put(v.to_le_bytes(), v.to_be_bytes());
    }
    fn u32(&mut self, v: u32) {
        self.put(v.to_le_bytes(), v.to_be_bytes());
    }
}

/// A binary PLY with every kind of thing to skip: extra scalar and list properties in
/// the vertex and face elements and two unknown elements (one with a list, one fixed
/// size) between vertex and face.
fn binary_ply(be: bool) -> Vec<u8> {
    let fmt = if be {
        "binary_big_endian"
    } else {
        "binary_little_endian"
    };
    let header = format!(
        "ply\nformat {fmt} 1.0\ncomment binary test\n\
         element vertex 5\nproperty float x\nproperty float y\nproperty float z\n\
         property double confidence\nproperty list uint8 float extra\nproperty uchar intensity\n\
         property float nx\nproperty float ny\nproperty float nz\n\
         property float32 texture_u\nproperty float32 texture_v\n\
         element edge 2\nproperty int vertex1\nproperty list uchar int path\nproperty uchar red\n\
         element material 3\nproperty double k\nproperty short id\n\
         element face 2\nproperty uchar flags\nproperty list uchar uint vertex_indices\n\
         property int16 tag\nend_header\n"
    );
    let mut b = Bin {
        be,
        out: header.into_bytes(),
    };
    for (p, t) in POS.iter().zip(UV) {
        b.f32(p[0]);
        b.f32(p[1]);
        b.f32(p[2]);
        b.f64(0.75);
        b.u8(2);
        b.f32(9.0);
        b.f32(-9.0);
        b.u8(17);
        b.f32(0.0);
        b.f32(0.0);
        b.f32(1.0);
        b.f32(t[0]);
        b.f32(t[1]);
    }
    for e in 0..2 {
        b.i32(e);
        b.u8(3);
        for k in 0..3 {
            b.i32(k);
        }
        b.u8(255);
    }
    for m in 0..3 {
        b.f64(m as f64);
        b.i16(-1);
    }
    for f in FACES {
        b.u8(7);
        b.u8(f.len() as u8);
        for &i in f {
            b.u32(i);
        }
        b.i16(42);
    }
    b.out
}

fn check_test_mesh(scene: &Scene, what: &str) {
    let m = &scene.mesh;
    assert_eq!(m.indices, TRIS.to_vec(), "{what}: indices");
    let pos: Vec<Vec3> = POS.iter().map(|p| Vec3::from_array(*p)).collect();
    assert_eq!(m.positions, pos, "{what}: positions");
    assert!(m.normals.iter().all(|&n| n == Vec3::Z), "{what}: normals");
    // v is flipped: dray textures put row 0 at v = 0.
    let uv: Vec<Vec2> = UV.iter().map(|t| Vec2::new(t[0], 1.0 - t[1])).collect();
    assert_eq!(m.uvs, uv, "{what}: uvs");
    assert_eq!(m.material, vec![0; 3], "{what}: material");
    assert_eq!(scene.materials.len(), 1);
    assert_eq!(scene.materials[0].name, "ply");
    assert_eq!(scene.materials[0].base_color, Vec4::new(0.8, 0.8, 0.8, 1.0));
    assert_eq!(scene.stats.degenerate_triangles, 0);
}

#[test]
fn ascii_ply_with_quads_and_extra_properties() {
    let dir = tmpdir("ascii");
    let p = write(&dir, "quad.ply", ascii_ply());
    let scene = load_ply(&p).unwrap();
    check_test_mesh(&scene, "ascii");
    assert_eq!(scene.name, "quad");
}

#[test]
fn binary_ply_both_endians_skip_unknown_elements() {
    let dir = tmpdir("binary");
    for be in [false, true] {
        let p = write(&dir, &format!("quad_{be}.ply"), binary_ply(be));
        let scene = load_ply(&p).unwrap_or_else(|e| panic!("be={be}: {e}"));
        check_test_mesh(&scene, if be { "big endian" } else { "little endian" });
        assert!(
            scene.stats.warnings.iter().any(|w| w.contains("edge")),
            "{:?}",
            scene.stats.warnings
        );
    }
}

fn err_of(dir: &Path, name: &str, bytes: impl AsRef<[u8]>) -> String {
    let p = write(dir, name, bytes);
    match load_ply(&p) {
        Ok(s) => panic!(
            "{name}: expected an error, got {} triangles",
            s.mesh.indices.len()
        ),
        Err(e) => {
            let msg = e.to_string();
            println!("{msg}");
            assert!(msg.contains(name), "error does not name the file: {msg}");
            msg
        }
    }
}

#[test]
fn truncated_binary_is_an_error() {
    let dir = tmpdir("truncated");
    let full = binary_ply(false);
    let cut = &full[..full.len() - 3];
    let msg = err_of(&dir, "cut.ply", cut);
    assert!(msg.contains("face 1"), "{msg}");
    assert!(msg.contains("truncated"), "{msg}");
    // Cut inside the vertex data.
    let header_len = full.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
    let msg = err_of(&dir, "cut2.ply", &full[..header_len + 30]);
    assert!(msg.contains("vertex 0"), "{msg}");
}

#[test]
fn list_count_overflow_is_an_error() {
    let dir = tmpdir("overflow");
    let header = "ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\n\
                  property float y\nproperty float z\nelement face 1\n\
                  property list uint int vertex_indices\nend_header\n";
    let mut b = Bin {
        be: false,
        out: header.as_bytes().to_vec(),
    };
    for p in &POS[..3] {
        p.iter().for_each(|&c| b.f32(c));
    }
    b.u32(u32::MAX);
    b.i32(0);
    b.i32(1);
    b.i32(2);
    let msg = err_of(&dir, "overflow.ply", &b.out);
    assert!(
        msg.contains("face 0") && msg.contains("list count"),
        "{msg}"
    );

    // A huge element count with little data behind it.
    let mut huge = header.replace("element vertex 3", "element vertex 4000000000");
    huge.push_str("xyz");
    let msg = err_of(&dir, "huge.ply", huge);
    assert!(msg.contains("vertex 0"), "{msg}");
}

#[test]
fn bad_index_names_the_face() {
    let dir = tmpdir("badindex");
    let text = ascii_ply().replace("3 1 4 2", "3 1 9 2");
    let msg = err_of(&dir, "badindex.ply", text);
    assert!(msg.contains("face 1") && msg.contains("9"), "{msg}");
    let text = ascii_ply().replace("3 1 4 2", "3 1 -1 2");
    let msg = err_of(&dir, "negindex.ply", text);
    assert!(msg.contains("face 1") && msg.contains("-1"), "{msg}");
}

#[test]
fn nan_vertex_is_an_error() {
    let dir = tmpdir("nan");
    let text = ascii_ply().replacen("\n1 1 0 0.5", "\n1 nan 0 0.5", 1);
    let msg = err_of(&dir, "nan.ply", text);
    assert!(
        msg.contains("vertex 2") && msg.contains("non-finite"),
        "{msg}"
    );

    let mut bin = binary_ply(false);
    let header_len = bin.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
    bin[header_len..header_len + 4].copy_from_slice(&f32::NAN.to_le_bytes());
    let msg = err_of(&dir, "nan_bin.ply", bin);
    assert!(
        msg.contains("vertex 0") && msg.contains("non-finite"),
        "{msg}"
    );
}

#[test]
fn malformed_ascii_and_headers_are_errors() {
    let dir = tmpdir("malformed");
    let text = ascii_ply().replacen("\n1 1 0 0.5", "\n1 abc 0 0.5", 1);
    let msg = err_of(&dir, "token.ply", text);
    assert!(msg.contains("vertex 2") && msg.contains("abc"), "{msg}");

    let text = ascii_ply().replace("end_header\n", "");
    let msg = err_of(&dir, "noend.ply", text);
    assert!(msg.contains("header line 18"), "{msg}");
    let text = ascii_ply().split("end_header").next().unwrap().to_string();
    let msg = err_of(&dir, "noend2.ply", text);
    assert!(msg.contains("end_header"), "{msg}");

    let text = ascii_ply().replace("format ascii", "format utf8");
    let msg = err_of(&dir, "format.ply", text);
    assert!(msg.contains("format"), "{msg}");

    let text = ascii_ply().replace("property float x", "property quad x");
    let msg = err_of(&dir, "type.ply", text);
    assert!(msg.contains("quad"), "{msg}");

    let text = ascii_ply().replace("vertex_indices", "corners");
    let msg = err_of(&dir, "nolist.ply", text);
    assert!(msg.contains("vertex_indices"), "{msg}");

    let text = ascii_ply().replace("3 1 4 2\n", "3 1 4");
    let msg = err_of(&dir, "shortascii.ply", text);
    assert!(msg.contains("face 1"), "{msg}");

    // Point cloud: no triangles.
    let text = ascii_ply()
        .replace("element face 2", "element face 0")
        .replace("4 0 1 2 3\n3 1 4 2\n", "");
    let p = write(&dir, "points.ply", text);
    assert!(matches!(load_ply(&p), Err(SceneError::Empty { .. })));

    let missing = dir.join("missing.ply");
    assert!(matches!(load_ply(&missing), Err(SceneError::Io { .. })));
}

/// Every truncation of a valid binary file, and byte flips throughout it, must give Ok
/// or Err, never a panic or a runaway allocation.
#[test]
fn fuzz_truncation_and_byte_flips() {
    let dir = tmpdir("fuzz");
    let p = dir.join("fuzz.ply");
    let full = binary_ply(false);
    for len in 0..full.len() {
        fs::write(&p, &full[..len]).unwrap();
        assert!(load_ply(&p).is_err(), "truncated to {len} bytes loaded");
    }
    let header_len = full.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
    let mut loaded = 0;
    for i in 0..full.len() {
        // Every header byte; a sample of data bytes.
        if i >= header_len && i % 3 != 0 {
            continue;
        }
        for x in [0x01u8, 0x10, 0x20, 0x80, 0xff] {
            let mut bytes = full.clone();
            bytes[i] ^= x;
            fs::write(&p, &bytes).unwrap();
            loaded += load_ply(&p).is_ok() as usize;
        }
    }
    println!("byte flips that still loaded: {loaded}");
}

#[test]
fn obj_with_mtl_and_texture() {
    let dir = tmpdir("obj_mtl");
    write(
        &dir,
        "mats.mtl",
        "newmtl red\nKd 0.2 0.4 0.6\nKs 0.5 0.25 0.5\nNs 98\nd 0.5\nNi 1.45\nKe 1 0 0\n\
         illum 2\n\nnewmtl glass\nKd 0 0 0\nillum 7\nNi 1.5\nTf 0.9 0.9 1.0\n\n\
         newmtl textured\nKd 0.8 0.8 0.8\nmap_Kd -s 1 1 1 tex/checker.png\n\n\
         newmtl unused\nmap_Kd nowhere.png\n",
    );
    fs::create_dir_all(dir.join("tex")).unwrap();
    let img = image::RgbaImage::from_raw(2, 1, vec![255, 0, 0, 255, 0, 0, 255, 128]).unwrap();
    img.save(dir.join("tex/checker.png")).unwrap();
    let obj = "mtllib mats.mtl\n\
               v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\n\
               vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nvn 0 0 1\n\
               o panel\nusemtl red\nf 1/1/1 2/2/1 3/3/1 4/4/1\n\
               o pane\nusemtl glass\nf 1 2 3\n\
               o picture\nusemtl textured\nf 1/1 2/2 3/3\n";
    let p = write(&dir, "scene.obj", obj);
    let scene = load_obj(&p).unwrap();
    assert_eq!(scene.name, "scene");
    assert_eq!(scene.mesh.indices.len(), 4);
    assert_eq!(
        scene.materials.len(),
        3,
        "unused materials are not converted"
    );

    let red = &scene.materials[0];
    assert_eq!(red.name, "red");
    assert_eq!(red.base_color, Vec4::new(0.2, 0.4, 0.6, 0.5));
    assert_eq!(red.alpha_mode, AlphaMode::Blend);
    assert_eq!(red.metallic, 0.0);
    assert_eq!(red.specular, 0.5);
    assert_eq!(red.specular_color, Vec3::new(1.0, 0.5, 1.0));
    assert!((red.roughness - (2.0f32 / 100.0).sqrt()).abs() < 1e-6);
    assert_eq!(red.emissive, Vec3::X);
    assert!((red.ior - 1.45).abs() < 1e-6);

    let glass = &scene.materials[1];
    assert_eq!(glass.transmission, 1.0);
    assert_eq!(glass.base_color, Vec4::new(0.9, 0.9, 1.0, 1.0));
    assert_eq!(glass.ior, 1.5);

    let textured = &scene.materials[2];
    let tex = textured.base_color_tex.expect("map_Kd becomes a texture");
    let t = &scene.textures[tex.texture as usize];
    assert_eq!((t.width, t.height), (2, 1));
    assert_eq!(*t.texels, [[255, 0, 0, 255], [0, 0, 255, 128]]);
    assert_eq!(textured.base_color, Vec4::ONE);

    // Quad triangulated as a fan, uvs flipped in v, normals kept.
    assert_eq!(scene.mesh.material, vec![0, 0, 1, 2]);
    let [a, b, c] = scene.mesh.indices[0];
    assert_eq!(scene.mesh.uvs[b as usize], Vec2::new(1.0, 1.0));
    assert_eq!(scene.mesh.uvs[a as usize], Vec2::new(0.0, 1.0));
    assert_eq!(scene.mesh.normals[c as usize], Vec3::Z);
    // "pane" has no normals: zero ("absent").
    let [a, ..] = scene.mesh.indices[2];
    assert_eq!(scene.mesh.normals[a as usize], Vec3::ZERO);
}

#[test]
fn obj_missing_texture_is_an_error() {
    let dir = tmpdir("obj_notex");
    write(&dir, "m.mtl", "newmtl t\nmap_Kd gone.png\n");
    let p = write(
        &dir,
        "notex.obj",
        "mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl t\nf 1 2 3\n",
    );
    let msg = load_obj(&p).unwrap_err().to_string();
    assert!(
        msg.contains("gone.png") && msg.contains("notex.obj"),
        "{msg}"
    );
}

#[test]
fn obj_without_mtl() {
    let dir = tmpdir("obj_nomtl");
    // A library that does not exist: warning, default material.
    let p = write(
        &dir,
        "lost.obj",
        "mtllib lost.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nusemtl x\nf 1 2 3\nf 2 4 3\n",
    );
    let scene = load_obj(&p).unwrap();
    assert_eq!(scene.mesh.indices.len(), 2);
    assert_eq!(scene.materials.len(), 1);
    assert_eq!(scene.materials[0].base_color, Vec4::new(0.8, 0.8, 0.8, 1.0));
    assert!(
        scene.stats.warnings.iter().any(|w| w.contains("lost.mtl")),
        "{:?}",
        scene.stats.warnings
    );

    // No library at all: no warning.
    let p = write(&dir, "plain.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n");
    let scene = load_obj(&p).unwrap();
    assert_eq!(scene.mesh.indices.len(), 1);
    assert_eq!(scene.materials.len(), 1);
    assert!(
        scene.stats.warnings.is_empty(),
        "{:?}",
        scene.stats.warnings
    );

    // Bad face index and empty file are errors.
    let p = write(&dir, "bad.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 7\n");
    assert!(load_obj(&p).is_err());
    let p = write(&dir, "empty.obj", "v 0 0 0\n");
    assert!(matches!(load_obj(&p), Err(SceneError::Empty { .. })));
}

fn shared_scenes() -> Option<PathBuf> {
    let dir = std::env::var_os("DRAY_SCENES")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/scenes"));
    if dir.is_dir() {
        Some(dir)
    } else {
        let why = format!(
            "shared scenes not found at {} (set DRAY_SCENES)",
            dir.display()
        );
        // Under CI a missing folder is a missing install step, not a pass.
        assert!(
            std::env::var("CI").map_or(true, |v| v != "true"),
            "CI=true: {why}"
        );
        println!("SKIPPED (not under CI): {why}");
        None
    }
}

/// `vertices` is checked when given: the OBJ path keeps only referenced vertices.
fn check_count(what: &str, scene: &Scene, expected: usize, vertices: Option<usize>) {
    let got = scene.mesh.indices.len();
    let dropped = scene.stats.degenerate_triangles as usize;
    println!(
        "{what}: {got} triangles ({dropped} degenerate dropped, {expected} in file), \
         {} vertices",
        scene.mesh.positions.len()
    );
    assert!(
        got.abs_diff(expected) * 1000 <= expected,
        "{what}: {got} triangles, expected {expected} within 0.1%"
    );
    assert_eq!(got + dropped, expected, "{what}: faces lost");
    if let Some(v) = vertices {
        assert_eq!(scene.mesh.positions.len(), v, "{what}: vertices");
    }
}

#[test]
fn shared_bunny_and_lucy() {
    let Some(dir) = shared_scenes() else {
        return;
    };
    let bunny_ply = load_ply(&dir.join("stanford_bunny/bun_zipper.ply")).unwrap();
    check_count("bun_zipper.ply", &bunny_ply, 69451, Some(35947));
    let bunny_obj = load_obj(&dir.join("stanford_bunny/stanford-bunny.obj")).unwrap();
    check_count("stanford-bunny.obj", &bunny_obj, 69451, None);
    let lucy = load_ply(&dir.join("lucy_100k/lucy.ply")).unwrap();
    check_count("lucy.ply", &lucy, 99970, Some(49987));
    let (lo, hi) = lucy.bounds();
    println!("lucy bounds {lo} .. {hi}");
    assert!(lo.is_finite() && hi.is_finite() && (hi - lo).min_element() > 0.0);
}

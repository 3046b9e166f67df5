//! Integration tests for the glTF importer: small files written to a temporary folder,
//! plus every glTF in the shared scenes folder when it is present.

use std::path::{Path, PathBuf};

use dray_core::camera::Projection;
use dray_core::light::Light;
use dray_core::material::AlphaMode;
use dray_core::scene::Scene;
use dray_core::texture::{Filter, Wrap};
use dray_scene::SceneError;
use dray_scene::gltf::load_gltf;
use glam::{Vec3, Vec4};

mod support;
use support::{Builder, TRI_MESH, TRI_POS, approx, test_dir, triangle_builder};

#[test]
fn matrix_and_trs_transforms_with_instancing_and_mirroring() {
    let dir = test_dir("transforms");
    let s = std::f32::consts::FRAC_1_SQRT_2;
    let rest = format!(
        r#"{TRI_MESH},
        "nodes":[
          {{"matrix":[2,0,0,0, 0,2,0,0, 0,0,2,0, 10,0,0,1],"children":[1]}},
          {{"translation":[0,1,0],"rotation":[0,0,{s},{s}],"mesh":0}},
          {{"scale":[-1,1,1],"mesh":0}}
        ],
        "scenes":[{{"nodes":[0,2]}}],"scene":0"#
    );
    let path = triangle_builder().write(&dir, "transforms", &rest);
    let scene = load_gltf(&path).unwrap();
    assert_eq!(scene.name, "transforms");
    assert_eq!(scene.mesh.triangle_count(), 2);
    // Primitives without a material share one appended default material.
    assert_eq!(scene.materials.len(), 1);
    assert_eq!(scene.materials[0].name, "default");
    assert!(scene.mesh.material.iter().all(|&m| m == 0));

    // First instance: parent scale 2 and translation 10, child rotation 90° about Z and
    // translation +1 Y.
    let [a, b, c] = scene.mesh.corners(0);
    assert!(approx(a, Vec3::new(10.0, 2.0, 0.0)), "{a}");
    assert!(approx(b, Vec3::new(10.0, 4.0, 0.0)), "{b}");
    assert!(approx(c, Vec3::new(8.0, 2.0, 0.0)), "{c}");
    let t = scene.mesh.tangents[scene.mesh.indices[0][0] as usize];
    assert!((t - Vec4::new(0.0, 1.0, 0.0, 1.0)).length() < 1e-5, "{t}");

    // Second instance is mirrored: winding is flipped so the geometric normal still
    // agrees with the shading normal, and the bitangent sign flips.
    for tri in 0..2 {
        let [a, b, c] = scene.mesh.corners(tri);
        let geometric = (b - a).cross(c - a).normalize();
        let n = scene.mesh.normals[scene.mesh.indices[tri][0] as usize];
        assert!(
            geometric.dot(n) > 0.99,
            "triangle {tri}: {geometric} vs {n}"
        );
    }
    let t = scene.mesh.tangents[scene.mesh.indices[1][0] as usize];
    assert!((t - Vec4::new(-1.0, 0.0, 0.0, -1.0)).length() < 1e-5, "{t}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn strips_fans_non_indexed_and_skipped_points() {
    let dir = test_dir("modes");
    let mut b = Builder::default();
    // A unit square as a strip (0), a pentagon fan (1), two non-indexed triangles (2).
    b.floats(&[0., 0., 0., 1., 0., 0., 0., 1., 0., 1., 1., 0.], "VEC3");
    b.floats(
        &[0., 0., 0., 1., 0., 0., 1., 1., 0., 0., 1., 0., -1., 0.5, 0.],
        "VEC3",
    );
    b.floats(
        &[
            0., 0., 1., 1., 0., 1., 0., 1., 1., 0., 0., 2., 1., 0., 2., 0., 1., 2.,
        ],
        "VEC3",
    );
    let rest = r#""meshes":[{"name":"Modes","primitives":[
        {"attributes":{"POSITION":0},"mode":5},
        {"attributes":{"POSITION":1},"mode":6},
        {"attributes":{"POSITION":2}},
        {"attributes":{"POSITION":2},"mode":0}
      ]}],
      "nodes":[{"mesh":0}],"scenes":[{"nodes":[0]}]"#;
    let path = b.write(&dir, "modes", rest);
    let scene = load_gltf(&path).unwrap();
    assert_eq!(scene.mesh.triangle_count(), 2 + 3 + 2);
    assert_eq!(scene.stats.degenerate_triangles, 0);
    assert!(
        scene
            .stats
            .warnings
            .iter()
            .any(|w| w.contains("primitive 3") && w.contains("Points")),
        "{:?}",
        scene.stats.warnings
    );
    // Strip winding stays consistent: both square triangles face +Z.
    for tri in 0..2 {
        let [a, b, c] = scene.mesh.corners(tri);
        assert!((b - a).cross(c - a).z > 0.0);
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn missing_bin_names_the_uri() {
    let dir = test_dir("missing");
    let b = triangle_builder();
    let path = dir.join("missing.gltf");
    let rest = format!(r#"{TRI_MESH},"nodes":[{{"mesh":0}}]"#);
    std::fs::write(&path, b.json(Some("no_such_file.bin"), &rest)).unwrap();
    let err = load_gltf(&path).unwrap_err();
    let msg = err.to_string();
    println!("{msg}");
    assert!(msg.contains("no_such_file.bin"), "{msg}");
    assert!(msg.contains("missing.gltf"), "{msg}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn index_out_of_range_names_mesh_and_primitive() {
    let dir = test_dir("badindex");
    let mut b = triangle_builder();
    b.indices(&[0, 1, 7]);
    let rest = r#""meshes":[{"name":"BadMesh","primitives":[
        {"attributes":{"POSITION":0},"indices":3},
        {"attributes":{"POSITION":0},"indices":4}]}],
      "nodes":[{"mesh":0}]"#;
    let path = b.write(&dir, "badindex", rest);
    let err = load_gltf(&path).unwrap_err();
    assert!(
        matches!(err, SceneError::Primitive { primitive: 1, .. }),
        "{err}"
    );
    let msg = err.to_string();
    println!("{msg}");
    assert!(
        msg.contains("BadMesh") && msg.contains("primitive 1"),
        "{msg}"
    );
    assert!(msg.contains("vertex 7"), "{msg}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn nan_position_is_an_error() {
    let dir = test_dir("nan");
    let mut b = Builder::default();
    b.floats(&[0.0, 0.0, 0.0, f32::NAN, 0.0, 0.0, 0.0, 1.0, 0.0], "VEC3");
    let rest = r#""meshes":[{"primitives":[{"attributes":{"POSITION":0}}]}],"nodes":[{"mesh":0}]"#;
    let path = b.write(&dir, "nan", rest);
    let msg = load_gltf(&path).unwrap_err().to_string();
    println!("{msg}");
    assert!(
        msg.contains("non-finite") && msg.contains("mesh #0"),
        "{msg}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn truncated_buffers_are_errors_not_panics() {
    let dir = test_dir("truncated");
    let rest = format!(r#"{TRI_MESH},"nodes":[{{"mesh":0}}]"#);

    // The .bin file is shorter than the buffer's byteLength.
    let b = triangle_builder();
    let path = b.write(&dir, "short_file", &rest);
    std::fs::write(dir.join("short_file.bin"), &b.bin[..20]).unwrap();
    let msg = load_gltf(&path).unwrap_err().to_string();
    println!("{msg}");
    assert!(
        msg.contains("short_file.bin") && msg.contains("byteLength"),
        "{msg}"
    );

    // byteLength (and the file) too short for the buffer views.
    let mut b = triangle_builder();
    b.bin.truncate(30);
    let path = b.write(&dir, "short_length", &rest);
    let msg = load_gltf(&path).unwrap_err().to_string();
    println!("{msg}");
    assert!(msg.contains("Tri") && msg.contains("primitive 0"), "{msg}");

    // An accessor whose count runs past the end of its buffer view.
    let mut b = triangle_builder();
    b.accessors[0] = b.accessors[0].replace(r#""count":3"#, r#""count":3000"#);
    let path = b.write(&dir, "long_accessor", &rest);
    let msg = load_gltf(&path).unwrap_err().to_string();
    println!("{msg}");
    assert!(msg.contains("Tri") && msg.contains("POSITION"), "{msg}");

    // A stride smaller than the element.
    let mut b = triangle_builder();
    b.views[0] = b.views[0].replace(r#""buffer":0"#, r#""buffer":0,"byteStride":4"#);
    let path = b.write(&dir, "bad_stride", &rest);
    assert!(load_gltf(&path).is_err());

    // A GLB whose header lies about its length.
    let path = dir.join("bad.glb");
    std::fs::write(&path, b"glTF\x02\0\0\0\x04\0\0\0").unwrap();
    assert!(matches!(
        load_gltf(&path).unwrap_err(),
        SceneError::Format { .. }
    ));

    // Not JSON at all.
    let path = dir.join("garbage.gltf");
    std::fs::write(&path, b"{ not json").unwrap();
    assert!(matches!(
        load_gltf(&path).unwrap_err(),
        SceneError::Format { .. }
    ));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn extensions_required_and_used() {
    let dir = test_dir("extensions");
    let b = triangle_builder();
    let rest = format!(
        r#"{TRI_MESH},"nodes":[{{"mesh":0}}],
        "extensionsUsed":["KHR_draco_mesh_compression"],
        "extensionsRequired":["KHR_draco_mesh_compression"]"#
    );
    let path = b.write(&dir, "required", &rest);
    let err = load_gltf(&path).unwrap_err();
    assert!(
        matches!(&err, SceneError::UnsupportedExtension { extension, .. } if extension == "KHR_draco_mesh_compression"),
        "{err}"
    );

    // Used but not required: loads, with one warning.
    let rest = format!(
        r#"{TRI_MESH},"nodes":[{{"mesh":0}}],
        "extensionsUsed":["KHR_materials_diffuse_transmission"]"#
    );
    let path = b.write(&dir, "used", &rest);
    let scene = load_gltf(&path).unwrap();
    assert_eq!(
        scene
            .stats
            .warnings
            .iter()
            .filter(|w| w.contains("KHR_materials_diffuse_transmission"))
            .count(),
        1
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn materials_and_extensions_are_converted() {
    let dir = test_dir("materials");
    let b = triangle_builder();
    let rest = r#""meshes":[{"primitives":[
        {"attributes":{"POSITION":0},"material":0},
        {"attributes":{"POSITION":0},"material":1}]}],
      "nodes":[{"mesh":0}],
      "extensionsUsed":["KHR_materials_specular","KHR_materials_emissive_strength",
        "KHR_materials_transmission","KHR_materials_ior"],
      "extensionsRequired":["KHR_materials_specular"],
      "materials":[
        {"name":"Glass","pbrMetallicRoughness":{"baseColorFactor":[0.5,0.6,0.7,0.8],
           "metallicFactor":0.25,"roughnessFactor":0.75},
         "emissiveFactor":[1,0.5,0.25],
         "alphaMode":"MASK","doubleSided":true,
         "extensions":{
           "KHR_materials_emissive_strength":{"emissiveStrength":4},
           "KHR_materials_transmission":{"transmissionFactor":0.9},
           "KHR_materials_ior":{"ior":1.33},
           "KHR_materials_specular":{"specularFactor":0.5,"specularColorFactor":[1,0.5,0.25]}}},
        {"name":"Blend","alphaMode":"BLEND"}
      ]"#;
    let path = b.write(&dir, "materials", rest);
    let scene = load_gltf(&path).unwrap();
    assert_eq!(scene.materials.len(), 2);
    let m = &scene.materials[0];
    assert_eq!(m.name, "Glass");
    assert_eq!(m.base_color, Vec4::new(0.5, 0.6, 0.7, 0.8));
    assert_eq!((m.metallic, m.roughness), (0.25, 0.75));
    assert_eq!(m.emissive, Vec3::new(4.0, 2.0, 1.0));
    assert_eq!(m.alpha_mode, AlphaMode::Mask { cutoff: 0.5 });
    assert!(m.double_sided);
    assert_eq!(m.transmission, 0.9);
    assert_eq!(m.ior, 1.33);
    assert_eq!(m.specular, 0.5);
    assert_eq!(m.specular_color, Vec3::new(1.0, 0.5, 0.25));
    assert_eq!(scene.materials[1].alpha_mode, AlphaMode::Blend);
    assert_eq!(scene.mesh.material, vec![0, 1]);
    assert!(
        scene.stats.warnings.is_empty(),
        "{:?}",
        scene.stats.warnings
    );
    let _ = std::fs::remove_dir_all(&dir);
}

fn base64(data: &[u8]) -> String {
    const T: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut out = String::new();
    for chunk in data.chunks(3) {
        let n = chunk.len();
        let v = (u32::from(chunk[0]) << 16)
            | (u32::from(*chunk.get(1).unwrap_or(&0)) << 8)
            | u32::from(*chunk.get(2).unwrap_or(&0));
        for i in 0..4 {
            if i <= n {
                out.push(T[((v >> (18 - 6 * i)) & 63) as usize] as char);
            } else {
                out.push('=');
            }
        }
    }
    out
}

fn png_2x1() -> Vec<u8> {
    let img = image::RgbaImage::from_raw(2, 1, vec![255, 0, 0, 255, 0, 0, 255, 128]).unwrap();
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png).unwrap();
    out.into_inner()
}

/// Wrap JSON and a binary chunk into a GLB container.
fn glb(json: &str, bin: &[u8]) -> Vec<u8> {
    let mut json = json.as_bytes().to_vec();
    while !json.len().is_multiple_of(4) {
        json.push(b' ');
    }
    let mut bin = bin.to_vec();
    while !bin.len().is_multiple_of(4) {
        bin.push(0);
    }
    let total = 12 + 8 + json.len() + 8 + bin.len();
    let mut out = Vec::new();
    out.extend_from_slice(b"glTF");
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&(total as u32).to_le_bytes());
    out.extend_from_slice(&(json.len() as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(&json);
    out.extend_from_slice(&(bin.len() as u32).to_le_bytes());
    out.extend_from_slice(b"BIN\0");
    out.extend_from_slice(&bin);
    out
}

const TEXTURED_REST: &str = r#""meshes":[{"primitives":[{"attributes":{"POSITION":0},"material":0}]}],
  "nodes":[{"mesh":0}],
  "materials":[{"pbrMetallicRoughness":{"baseColorTexture":{"index":0},
     "metallicRoughnessTexture":{"index":1,"texCoord":1}},
     "normalTexture":{"index":1,"scale":0.5}}],
  "samplers":[{"magFilter":9728,"wrapS":33071,"wrapT":33648}],
  "textures":[{"source":0,"sampler":0},{"source":0}],"#;

#[test]
fn glb_with_image_in_buffer_view() {
    let dir = test_dir("glb");
    let mut b = Builder::default();
    b.floats(&TRI_POS, "VEC3");
    let png = png_2x1();
    let view = b.view(&png);
    let rest =
        format!(r#"{TEXTURED_REST}"images":[{{"bufferView":{view},"mimeType":"image/png"}}]"#);
    let path = dir.join("textured.glb");
    std::fs::write(&path, glb(&b.json(None, &rest), &b.bin)).unwrap();
    let scene = load_gltf(&path).unwrap();
    check_textured(&scene);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn data_uris_for_buffer_and_image() {
    let dir = test_dir("datauri");
    let mut b = Builder::default();
    b.floats(&TRI_POS, "VEC3");
    let rest = format!(
        r#"{TEXTURED_REST}"images":[{{"uri":"data:image/png;base64,{}"}}]"#,
        base64(&png_2x1())
    );
    let uri = format!("data:application/octet-stream;base64,{}", base64(&b.bin));
    let path = dir.join("embedded.gltf");
    std::fs::write(&path, b.json(Some(&uri), &rest)).unwrap();
    let scene = load_gltf(&path).unwrap();
    check_textured(&scene);

    // A broken image is an error naming the image URI.
    let rest = format!(r#"{TEXTURED_REST}"images":[{{"uri":"broken.png"}}]"#);
    std::fs::write(dir.join("broken.png"), b"not a png").unwrap();
    std::fs::write(&path, b.json(Some(&uri), &rest)).unwrap();
    let msg = load_gltf(&path).unwrap_err().to_string();
    println!("{msg}");
    assert!(
        msg.contains("broken.png") && msg.contains("embedded.gltf"),
        "{msg}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

fn check_textured(scene: &Scene) {
    assert_eq!(scene.textures.len(), 2);
    let t = &scene.textures[0];
    assert_eq!((t.width, t.height), (2, 1));
    assert_eq!(*t.texels, [[255, 0, 0, 255], [0, 0, 255, 128]]);
    assert_eq!(t.sampler.filter, Filter::Nearest);
    assert_eq!(t.sampler.wrap_s, Wrap::ClampToEdge);
    assert_eq!(t.sampler.wrap_t, Wrap::MirroredRepeat);
    assert_eq!(scene.textures[1].sampler.filter, Filter::Linear);
    assert_eq!(scene.textures[1].sampler.wrap_s, Wrap::Repeat);
    let m = &scene.materials[0];
    assert_eq!(m.base_color_tex.map(|t| t.texture), Some(0));
    // The metallic-roughness texture reads TEXCOORD_1, the others TEXCOORD_0: two sets,
    // no warning (the primitive has neither, so both read zero).
    assert_eq!(
        m.metallic_roughness_tex
            .map(|t| (t.texture, t.tex_coord, t.second_uv)),
        Some((1, 1, true))
    );
    assert_eq!(m.base_color_tex.map(|t| t.second_uv), Some(false));
    assert_eq!(m.normal_tex.map(|t| t.texture), Some(1));
    assert_eq!(m.normal_scale, 0.5);
    assert!(
        scene.stats.warnings.iter().all(|w| !w.contains("UV set")),
        "{:?}",
        scene.stats.warnings
    );
    assert!(scene.mesh.uvs2.is_empty());
}

#[test]
fn spot_light_and_cameras() {
    let dir = test_dir("lights");
    let b = triangle_builder();
    let s = std::f32::consts::FRAC_1_SQRT_2;
    // Rotating -Z by -90° about X gives -Y: the spot points down.
    let rest = format!(
        r#"{TRI_MESH},
        "extensionsUsed":["KHR_lights_punctual"],
        "extensions":{{"KHR_lights_punctual":{{"lights":[
            {{"type":"spot","color":[1,0.5,0.25],"intensity":8,"spot":{{"outerConeAngle":0.6}}}},
            {{"type":"point","intensity":2}}]}}}},
        "cameras":[
            {{"name":"Persp","type":"perspective","perspective":{{"yfov":0.7,"znear":0.05}}}},
            {{"type":"orthographic","orthographic":{{"xmag":2,"ymag":1,"znear":0.1,"zfar":10}}}}],
        "nodes":[
            {{"mesh":0,"children":[1,2,3,4]}},
            {{"translation":[1,5,2],"rotation":[{ns},0,0,{s}],
              "extensions":{{"KHR_lights_punctual":{{"light":0}}}}}},
            {{"translation":[0,1,0],"extensions":{{"KHR_lights_punctual":{{"light":1}}}}}},
            {{"translation":[0,0,3],"camera":0}},
            {{"camera":1}}],
        "scenes":[{{"nodes":[0]}}]"#,
        ns = -s
    );
    let path = b.write(&dir, "lights", &rest);
    let scene = load_gltf(&path).unwrap();
    assert_eq!(scene.lights.len(), 2);
    match &scene.lights[0] {
        Light::Spot {
            position,
            direction,
            intensity,
            inner_cone,
            outer_cone,
        } => {
            assert!(approx(*position, Vec3::new(1.0, 5.0, 2.0)), "{position}");
            assert!(approx(*direction, Vec3::NEG_Y), "{direction}");
            assert!(approx(*intensity, Vec3::new(8.0, 4.0, 2.0)));
            assert_eq!(*inner_cone, 0.0);
            assert_eq!(*outer_cone, 0.6);
        }
        other => panic!("expected a spot light, got {other:?}"),
    }
    assert_eq!(
        scene.lights[1],
        Light::Point {
            position: Vec3::Y,
            intensity: Vec3::splat(2.0)
        }
    );
    assert_eq!(scene.cameras.len(), 2);
    let c = &scene.cameras[0];
    assert_eq!(c.name, "Persp");
    assert_eq!(
        c.projection,
        Projection::Perspective {
            yfov: 0.7,
            aspect: None
        }
    );
    assert_eq!(c.znear, 0.05);
    assert!(approx(
        c.transform.w_axis.truncate(),
        Vec3::new(0.0, 0.0, 3.0)
    ));
    let c = &scene.cameras[1];
    assert_eq!(c.name, "camera #1");
    assert_eq!(
        c.projection,
        Projection::Orthographic {
            xmag: 2.0,
            ymag: 1.0
        }
    );
    assert!(c.is_valid());
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn scene_without_triangles_is_empty() {
    let dir = test_dir("empty");
    let b = triangle_builder();
    let rest = format!(r#"{TRI_MESH},"nodes":[{{"name":"nothing"}}],"scenes":[{{"nodes":[0]}}]"#);
    let path = b.write(&dir, "empty", &rest);
    assert!(matches!(
        load_gltf(&path).unwrap_err(),
        SceneError::Empty { .. }
    ));

    // A node that is its own child must not hang the loader.
    let rest =
        format!(r#"{TRI_MESH},"nodes":[{{"mesh":0,"children":[0]}}],"scenes":[{{"nodes":[0]}}]"#);
    let path = b.write(&dir, "cycle", &rest);
    let msg = load_gltf(&path).unwrap_err().to_string();
    println!("{msg}");
    assert!(msg.contains("cycle"), "{msg}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// The shared scenes folder: `DRAY_SCENES`, else `/work/shared/scenes` relative to this
/// crate.
fn scenes_dir() -> PathBuf {
    std::env::var_os("DRAY_SCENES")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/scenes"))
}

fn within(actual: usize, expected: usize, tolerance: f64) -> bool {
    (actual as f64 - expected as f64).abs() <= expected as f64 * tolerance
}

#[test]
fn shared_scenes_load_with_manifest_counts() {
    let dir = scenes_dir();
    if !dir.is_dir() {
        let why = format!(
            "shared scenes folder {} not found (set DRAY_SCENES)",
            dir.display()
        );
        // Under CI a missing folder is a missing install step, not a pass.
        assert!(
            std::env::var("CI").map_or(true, |v| v != "true"),
            "CI=true: {why}"
        );
        println!("SKIPPED (not under CI): {why}");
        return;
    }
    let mut files = Vec::new();
    for entry in std::fs::read_dir(&dir).unwrap() {
        let sub = entry.unwrap().path();
        if !sub.is_dir() {
            continue;
        }
        for f in std::fs::read_dir(&sub).unwrap() {
            let f = f.unwrap().path();
            let ext = f.extension().and_then(|e| e.to_str()).unwrap_or("");
            if ext.eq_ignore_ascii_case("gltf") || ext.eq_ignore_ascii_case("glb") {
                files.push(f);
            }
        }
    }
    files.sort();
    assert!(!files.is_empty(), "no glTF files under {}", dir.display());
    for f in &files {
        let scene = load_gltf(f).unwrap_or_else(|e| panic!("{e}"));
        let tris = scene.mesh.triangle_count();
        let folder = f
            .parent()
            .and_then(|p| p.file_name())
            .and_then(|n| n.to_str())
            .unwrap_or("");
        println!(
            "{}: {tris} triangles, {} materials, {} textures, {} lights, {} cameras, {} degenerate, warnings {:?}",
            f.display(),
            scene.materials.len(),
            scene.textures.len(),
            scene.lights.len(),
            scene.cameras.len(),
            scene.stats.degenerate_triangles,
            scene.stats.warnings
        );
        assert!(
            scene.mesh.positions.iter().all(|p| p.is_finite()),
            "{}",
            f.display()
        );
        match folder {
            "box" => {
                assert_eq!(tris, 12, "{}", f.display());
                let (lo, hi) = scene.bounds();
                assert!(approx(lo, Vec3::splat(-0.5)) && approx(hi, Vec3::splat(0.5)));
            }
            "water_bottle" => assert!(within(tris, 4510, 0.01), "{tris}"),
            "clearcoat_test" => assert!(within(tris, 37116, 0.01), "{tris}"),
            "flight_helmet" => assert!(within(tris, 94722, 0.01), "{tris}"),
            "palm_tree" => assert!(within(tris, 10124, 0.01), "{tris}"),
            "volumetric_fog_room" => {
                assert_eq!(tris, 360);
                assert_eq!(scene.lights.len(), 1);
                match scene.lights[0] {
                    Light::Directional {
                        direction,
                        irradiance,
                    } => {
                        assert!((direction.length() - 1.0).abs() < 1e-5);
                        assert!((irradiance.x - 68300.0).abs() < 1.0, "{irradiance}");
                    }
                    ref other => panic!("expected a directional light, got {other:?}"),
                }
            }
            "cornell_box" => {
                assert_eq!(tris, 36);
                let (lo, hi) = scene.bounds();
                assert!(
                    (lo - Vec3::new(-556.0, 0.0, -559.2)).abs().max_element() < 1.0,
                    "{lo}"
                );
                assert!(
                    hi.abs().max_element() < 549.0 && (hi.y - 548.8).abs() < 1.0,
                    "{hi}"
                );
                assert!(
                    scene
                        .materials
                        .iter()
                        .any(|m| (m.emissive - Vec3::splat(100.0)).abs().max_element() < 1e-3),
                    "{:?}",
                    scene
                        .materials
                        .iter()
                        .map(|m| m.emissive)
                        .collect::<Vec<_>>()
                );
            }
            "cameras" => {
                assert_eq!(tris, 2);
                assert_eq!(scene.cameras.len(), 2);
                assert!(scene.cameras.iter().any(|c| matches!(
                    c.projection,
                    Projection::Perspective { yfov, .. } if (yfov - 0.7).abs() < 1e-6
                )));
                assert!(
                    scene
                        .cameras
                        .iter()
                        .any(|c| matches!(c.projection, Projection::Orthographic { .. }))
                );
            }
            other => println!("no expectations for {other}"),
        }
        // Every texture reference resolves.
        for m in &scene.materials {
            for t in m.texture_refs() {
                assert!((t.texture as usize) < scene.textures.len());
            }
        }
    }
}

/// Corrupt a small GLB byte by byte (deterministically) and check that every outcome is
/// a clean load or an ordinary error, never a panic caught by the loader's safety net.
#[test]
fn corrupted_glb_never_panics() {
    let dir = test_dir("fuzz");
    let mut b = triangle_builder();
    b.floats(&[0.0, 0.0, 1.0, 1.0, 0.5, 0.5], "VEC2");
    let png = png_2x1();
    let view = b.view(&png);
    let rest = format!(
        r#""meshes":[{{"name":"Tri","primitives":[{{"attributes":{{"POSITION":0,"NORMAL":1,"TANGENT":2,"TEXCOORD_0":4}},"indices":3,"material":0}}]}}],
        "nodes":[{{"mesh":0,"children":[1]}},{{"mesh":0,"scale":[1,-1,1]}}],
        "materials":[{{"pbrMetallicRoughness":{{"baseColorTexture":{{"index":0}}}}}}],
        "textures":[{{"source":0}}],
        "images":[{{"bufferView":{view},"mimeType":"image/png"}}]"#
    );
    let original = glb(&b.json(None, &rest), &b.bin);
    let path = dir.join("fuzz.glb");
    let mut state: u64 = 0x9E37_79B9_7F4A_7C15;
    let mut next = || {
        state = state
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        (state >> 33) as usize
    };
    // DRAY_FUZZ_ITERS raises the count for a longer manual run.
    let iters: usize = std::env::var("DRAY_FUZZ_ITERS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(1500);
    let mut loaded = 0;
    for _ in 0..iters {
        let mut bytes = original.clone();
        for _ in 0..1 + next() % 4 {
            let at = next() % bytes.len();
            bytes[at] = match next() % 4 {
                0 => 0,
                1 => 0xFF,
                2 => bytes[at] ^ (1 << (next() % 8)),
                _ => b"0123456789-.e,[]{}\""[next() % 19],
            };
        }
        if next() % 8 == 0 {
            bytes.truncate(next() % bytes.len());
        }
        std::fs::write(&path, &bytes).unwrap();
        match load_gltf(&path) {
            Ok(_) => loaded += 1,
            Err(e) => assert!(!e.to_string().contains("internal error"), "{e}"),
        }
    }
    println!("{loaded} of {iters} corrupted files still loaded");
    let _ = std::fs::remove_dir_all(&dir);
}

/// A quad (two triangles) in the XY plane facing +Z with NORMAL and TEXCOORD_0, U along
/// +X and V along -Y (glTF's V runs down the image): POSITION 0, NORMAL 1, TEXCOORD_0 2,
/// indices 3.
fn normal_mapped_quad() -> Builder {
    let mut b = Builder::default();
    b.floats(
        &[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 1.0, 0.0],
        "VEC3",
    );
    b.floats(&[0.0, 0.0, 1.0].repeat(4), "VEC3");
    b.floats(&[0.0, 1.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0], "VEC2");
    b.indices(&[0, 1, 2, 0, 2, 3]);
    b
}

/// The rest of a file with one quad mesh whose material has a normal map.
fn normal_mapped_rest(attributes: &str) -> String {
    format!(
        r#""meshes":[{{"name":"Quad","primitives":[{{"attributes":{{{attributes}}},"indices":3,"material":0}}]}}],
"nodes":[{{"mesh":0}}],"scenes":[{{"nodes":[0]}}],
"materials":[{{"normalTexture":{{"index":0}}}}],
"textures":[{{"source":0}}],
"images":[{{"uri":"data:image/png;base64,{}"}}]"#,
        base64(&png_2x1())
    )
}

#[test]
fn normal_mapped_primitive_without_tangents_gets_mikktspace_tangents() {
    let dir = test_dir("mikktspace");
    let b = normal_mapped_quad();
    let path = b.write(
        &dir,
        "quad",
        &normal_mapped_rest(r#""POSITION":0,"NORMAL":1,"TEXCOORD_0":2"#),
    );
    let scene = load_gltf(&path).unwrap();
    let m = &scene.mesh;
    assert_eq!(m.tangents.len(), m.positions.len());
    for t in &m.tangents {
        // U grows along +X and "up the image" (-V) along +Y = N x T: sign +1, as
        // Blender would have written the TANGENT for this quad.
        assert!(approx(t.truncate(), Vec3::X), "{t}");
        assert_eq!(t.w, 1.0, "{t}");
    }
    assert!(
        scene.stats.warnings.is_empty(),
        "{:?}",
        scene.stats.warnings
    );

    // Without NORMAL there is nothing to build a frame on: a warning says the normal
    // map is ignored, and no tangent is made up.
    let path = b.write(
        &dir,
        "no-normals",
        &normal_mapped_rest(r#""POSITION":0,"TEXCOORD_0":2"#),
    );
    let scene = load_gltf(&path).unwrap();
    assert!(scene.mesh.tangents.iter().all(|t| *t == Vec4::ZERO));
    assert!(
        scene
            .stats
            .warnings
            .iter()
            .any(|w| w.contains("normal map is ignored")),
        "{:?}",
        scene.stats.warnings
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn morph_targets_are_applied_at_mesh_and_node_weights() {
    let dir = test_dir("morph");
    let mut b = triangle_builder();
    // Target 0 lifts every vertex by 1 in z; target 1 moves them 2 along x.
    let lift = b.floats(&[0.0, 0.0, 1.0].repeat(3), "VEC3");
    let shift = b.floats(&[2.0, 0.0, 0.0].repeat(3), "VEC3");
    let rest = format!(
        r#""meshes":[{{"name":"Tri","weights":[0.5,0.25],"primitives":[{{"attributes":{{"POSITION":0,"NORMAL":1,"TANGENT":2}},"indices":3,"targets":[{{"POSITION":{lift}}},{{"POSITION":{shift}}}]}}]}}],
"nodes":[{{"mesh":0}},{{"mesh":0,"weights":[1.0,0.0],"translation":[10,0,0]}},{{"mesh":0}}],
"scenes":[{{"nodes":[0,1,2]}}]"#
    );
    let path = b.write(&dir, "morph", &rest);
    let scene = load_gltf(&path).unwrap();
    let p = &scene.mesh.positions;
    assert_eq!(p.len(), 9);
    // Node 0 and 2: the mesh's weights (0.5 lift, 0.25 x 2 shift).
    let mesh_weighted = [
        Vec3::new(0.5, 0.0, 0.5),
        Vec3::new(1.5, 0.0, 0.5),
        Vec3::new(0.5, 1.0, 0.5),
    ];
    // Node 1: its own weights (full lift, no shift), then its translation.
    let node_weighted = [
        Vec3::new(10.0, 0.0, 1.0),
        Vec3::new(11.0, 0.0, 1.0),
        Vec3::new(10.0, 1.0, 1.0),
    ];
    let found = |want: &[Vec3; 3]| {
        p.chunks(3)
            .filter(|c| c.iter().zip(want).all(|(a, b)| approx(*a, *b)))
            .count()
    };
    assert_eq!(found(&mesh_weighted), 2, "{p:?}");
    assert_eq!(found(&node_weighted), 1, "{p:?}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn each_warning_is_recorded_once() {
    let dir = test_dir("warn-once");
    let b = triangle_builder();
    // A line primitive in a mesh instanced with different node weights, so the mesh is
    // decoded twice: its skip is reported once.
    let rest = r#""meshes":[
  {"name":"Tri","primitives":[{"attributes":{"POSITION":0},"indices":3},{"attributes":{"POSITION":0},"mode":1}]}
],
"nodes":[{"mesh":0},{"mesh":0,"weights":[]},{"mesh":0}],
"scenes":[{"nodes":[0,1,2]}]"#;
    let path = b.write(&dir, "lines", rest);
    let scene = load_gltf(&path).unwrap();
    let skipped: Vec<_> = scene
        .stats
        .warnings
        .iter()
        .filter(|w| w.contains("not triangles"))
        .collect();
    assert_eq!(skipped.len(), 1, "{:?}", scene.stats.warnings);
    let _ = std::fs::remove_dir_all(&dir);
}

/// Tangents made by dray agree with the ones the exporter wrote: the shared WaterBottle
/// (exported with TANGENT) is loaded as is and with its TANGENT attributes removed, and
/// the generated frames must have the exporter's handedness at every corner and nearly
/// its direction. This pins the UV convention (V up, as the baking tools have it): with
/// glTF's V down every sign would be inverted.
#[test]
fn generated_tangents_match_the_exporters_on_a_shared_model() {
    let src = scenes_dir().join("water_bottle");
    if !src.join("WaterBottle.gltf").is_file() {
        let why = format!("{} not found (set DRAY_SCENES)", src.display());
        assert!(
            std::env::var("CI").map_or(true, |v| v != "true"),
            "CI=true: {why}"
        );
        println!("SKIPPED (not under CI): {why}");
        return;
    }
    let dir = test_dir("exporter-tangents");
    for entry in std::fs::read_dir(&src).unwrap() {
        let path = entry.unwrap().path();
        if path.is_file() {
            std::fs::copy(&path, dir.join(path.file_name().unwrap())).unwrap();
        }
    }
    let mut json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("WaterBottle.gltf")).unwrap()).unwrap();
    for mesh in json["meshes"].as_array_mut().unwrap() {
        for prim in mesh["primitives"].as_array_mut().unwrap() {
            prim["attributes"]
                .as_object_mut()
                .unwrap()
                .remove("TANGENT");
        }
    }
    let stripped = dir.join("stripped.gltf");
    std::fs::write(&stripped, serde_json::to_vec(&json).unwrap()).unwrap();

    let file = load_gltf(&dir.join("WaterBottle.gltf")).unwrap();
    let made = load_gltf(&stripped).unwrap();
    assert_eq!(file.mesh.indices.len(), made.mesh.indices.len());
    let (mut corners, mut missing, mut same_sign, mut close) = (0usize, 0, 0, 0);
    for (a, b) in file.mesh.indices.iter().zip(&made.mesh.indices) {
        for k in 0..3 {
            let x = file.mesh.tangents[a[k] as usize];
            let y = made.mesh.tangents[b[k] as usize];
            if y == Vec4::ZERO {
                // MikkTSpace gives nothing for a triangle with degenerate UVs and no
                // neighbour to borrow from.
                missing += 1;
                continue;
            }
            corners += 1;
            same_sign += usize::from(x.w.signum() == y.w.signum());
            let cos = x.truncate().normalize().dot(y.truncate().normalize());
            close += usize::from(cos > 0.9);
        }
    }
    println!(
        "{corners} corners with tangents, {missing} without, {same_sign} same sign, {close} close"
    );
    assert!(
        missing * 1000 <= corners,
        "{missing} corners without a tangent"
    );
    assert_eq!(same_sign, corners, "handedness differs at some corners");
    assert!(
        close * 100 >= corners * 99,
        "{close} of {corners} within 25 degrees"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn vertex_colours_are_read_as_rgba_and_cost_nothing_when_absent() {
    let dir = test_dir("colours");
    let mut b = triangle_builder();
    // COLOR_0 as float VEC3 (alpha 1) on primitive 0, as normalized u8 VEC4 on
    // primitive 1, none on primitive 2.
    let rgb = b.floats(&[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0], "VEC3");
    let view = b.view(&[255, 0, 0, 255, 0, 255, 0, 128, 0, 0, 255, 0]);
    b.accessors.push(format!(
        r#"{{"bufferView":{view},"componentType":5121,"normalized":true,"count":3,"type":"VEC4"}}"#
    ));
    let rgba = b.accessors.len() - 1;
    let rest = format!(
        r#""meshes":[{{"primitives":[
  {{"attributes":{{"POSITION":0,"COLOR_0":{rgb}}},"indices":3}},
  {{"attributes":{{"POSITION":0,"COLOR_0":{rgba}}},"indices":3}},
  {{"attributes":{{"POSITION":0}},"indices":3}}]}}],
"nodes":[{{"mesh":0}}],"scenes":[{{"nodes":[0]}}]"#
    );
    let scene = load_gltf(&b.write(&dir, "colours", &rest)).unwrap();
    let c = &scene.mesh.colors;
    assert_eq!(c.len(), 9);
    assert_eq!(
        c[0..3],
        [
            Vec4::new(1.0, 0.0, 0.0, 1.0),
            Vec4::new(0.0, 1.0, 0.0, 1.0),
            Vec4::new(0.0, 0.0, 1.0, 1.0)
        ]
    );
    let half = 128.0 / 255.0;
    assert_eq!(
        c[3..6],
        [
            Vec4::new(1.0, 0.0, 0.0, 1.0),
            Vec4::new(0.0, 1.0, 0.0, half),
            Vec4::new(0.0, 0.0, 1.0, 0.0)
        ]
    );
    assert_eq!(c[6..9], [Vec4::ONE; 3]);
    assert!(
        scene.stats.warnings.is_empty(),
        "{:?}",
        scene.stats.warnings
    );

    // Integer colours must be normalized (glTF 2.0, "Meshes"): otherwise the file is
    // wrong and the error says where.
    let bad = rest.replace(r#""normalized":true,"#, "");
    let mut b2 = b;
    if let Some(a) = b2.accessors.last_mut() {
        *a = a.replace(r#""normalized":true,"#, "");
    }
    let msg = load_gltf(&b2.write(&dir, "bad", &bad))
        .unwrap_err()
        .to_string();
    assert!(
        msg.contains("COLOR_0") && msg.contains("normalized"),
        "{msg}"
    );

    // A file without COLOR_0 keeps no colour array at all.
    let scene = load_gltf(&triangle_builder().write(
        &dir,
        "plain",
        &format!(r#"{TRI_MESH},"nodes":[{{"mesh":0}}],"scenes":[{{"nodes":[0]}}]"#),
    ))
    .unwrap();
    assert!(scene.mesh.colors.is_empty());
    let _ = std::fs::remove_dir_all(&dir);
}

/// A 2x1 PNG as a data-URI image, and one texture on it.
fn one_texture() -> String {
    format!(
        r#""images":[{{"uri":"data:image/png;base64,{}"}}],"textures":[{{"source":0}}]"#,
        base64(&png_2x1())
    )
}

/// A triangle with TEXCOORD_0 (accessor 4) and TEXCOORD_1 (accessor 5) that differ.
fn two_uv_sets() -> Builder {
    let mut b = triangle_builder();
    b.floats(&[0.0; 6], "VEC2");
    b.floats(&[0.25, 0.5, 0.75, 0.5, 0.25, 1.0], "VEC2");
    b
}

#[test]
fn each_material_reads_its_own_uv_set() {
    let dir = test_dir("texcoord");
    let b = two_uv_sets();
    let rest = format!(
        r#""meshes":[{{"primitives":[
  {{"attributes":{{"POSITION":0,"TEXCOORD_0":4,"TEXCOORD_1":5}},"indices":3,"material":0}},
  {{"attributes":{{"POSITION":0,"TEXCOORD_0":4,"TEXCOORD_1":5}},"indices":3,"material":1}},
  {{"attributes":{{"POSITION":0,"TEXCOORD_0":4,"TEXCOORD_1":5}},"indices":3,"material":2}}]}}],
"nodes":[{{"mesh":0}}],"extensionsUsed":["KHR_texture_transform"],
"materials":[
  {{"pbrMetallicRoughness":{{"baseColorTexture":{{"index":0,"texCoord":1}}}},
    "emissiveTexture":{{"index":0,"texCoord":1}}}},
  {{"pbrMetallicRoughness":{{"baseColorTexture":{{"index":0}}}}}},
  {{"pbrMetallicRoughness":{{"baseColorTexture":{{"index":0,
    "extensions":{{"KHR_texture_transform":{{"texCoord":1}}}}}}}}}}],
{}"#,
        one_texture()
    );
    let scene = load_gltf(&b.write(&dir, "sets", &rest)).unwrap();
    let set1 = [
        glam::Vec2::new(0.25, 0.5),
        glam::Vec2::new(0.75, 0.5),
        glam::Vec2::new(0.25, 1.0),
    ];
    assert_eq!(scene.mesh.uvs[0..3], set1, "texCoord 1");
    assert_eq!(scene.mesh.uvs[3..6], [glam::Vec2::ZERO; 3], "texCoord 0");
    assert_eq!(scene.mesh.uvs[6..9], set1, "texCoord 1 from the transform");
    // Each material reads one set, so no second set is stored.
    assert!(scene.mesh.uvs2.is_empty());
    assert_eq!(
        scene.materials[2].base_color_tex.map(|t| t.tex_coord),
        Some(1)
    );
    // An identity transform keeps the lookup untouched (same bits).
    assert_eq!(
        scene.materials[2].base_color_tex.and_then(|t| t.transform),
        None
    );
    assert!(
        scene.stats.warnings.is_empty(),
        "{:?}",
        scene.stats.warnings
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// A triangle whose TEXCOORD_0 (accessor 4) reads the left (red) texel of
/// [`png_2x1`] and whose TEXCOORD_1 (accessor 5) reads the right (blue) one, at every
/// vertex; TEXCOORD_2 (accessor 6) reads the left one again.
fn red_and_blue_uv_sets() -> Builder {
    let mut b = triangle_builder();
    b.floats(&[0.25, 0.5].repeat(3), "VEC2");
    b.floats(&[0.75, 0.5].repeat(3), "VEC2");
    b.floats(&[0.25, 0.5].repeat(3), "VEC2");
    b
}

/// The rest of a file with one triangle of material 0 (`material`, JSON) over
/// [`red_and_blue_uv_sets`], with the 2x1 texture and nearest filtering.
fn red_and_blue_rest(material: &str) -> String {
    format!(
        r#""meshes":[{{"primitives":[{{"attributes":{{"POSITION":0,"NORMAL":1,
  "TEXCOORD_0":4,"TEXCOORD_1":5,"TEXCOORD_2":6}},"indices":3,"material":0}}]}}],
"nodes":[{{"mesh":0}}],"extensionsUsed":["KHR_texture_transform"],
"materials":[{material}],
"samplers":[{{"magFilter":9728}}],
"images":[{{"uri":"data:image/png;base64,{}"}}],"textures":[{{"source":0,"sampler":0}}]"#,
        base64(&png_2x1())
    )
}

/// Every texture slot reads the UV set it names, as the glTF spec and the Sample Viewer
/// do: base colour on TEXCOORD_0 (red texel), emission on TEXCOORD_1 (blue texel), in the
/// shading values a render reads. With one UV set per vertex, the emission read red.
#[test]
fn each_texture_slot_reads_the_uv_set_it_names() {
    let dir = test_dir("slot-sets");
    let b = red_and_blue_uv_sets();
    let file = |name: &str, emissive_set: u32| {
        let material = format!(
            r#"{{"name":"TwoSets","pbrMetallicRoughness":{{"baseColorTexture":{{"index":0}}}},
  "emissiveFactor":[1,1,1],"emissiveTexture":{{"index":0,"texCoord":{emissive_set}}}}}"#
        );
        load_gltf(&b.write(&dir, name, &red_and_blue_rest(&material))).unwrap()
    };
    let scene = file("two", 1);
    assert!(
        scene.stats.warnings.is_empty(),
        "{:?}",
        scene.stats.warnings
    );
    let m = &scene.materials[0];
    assert_eq!(
        (
            m.base_color_tex.unwrap().second_uv,
            m.emissive_tex.unwrap().second_uv
        ),
        (false, true)
    );
    assert_eq!(scene.mesh.uvs, [glam::Vec2::new(0.25, 0.5); 3]);
    assert_eq!(scene.mesh.uvs2, [glam::Vec2::new(0.75, 0.5); 3]);
    let fx = dray_scene::effects::analyze(&scene, Vec3::ONE);
    let (_, sv) = shade_first_triangle(&scene, fx);
    assert!(approx(sv.base_color, Vec3::new(1.0, 0.0, 0.0)), "{sv:?}");
    assert!(approx(sv.emission, Vec3::new(0.0, 0.0, 1.0)), "{sv:?}");
    // Light sampling sees the same emission as a camera ray.
    let uv = dray_core::surface::interpolate_uv(&scene, 0, [0.2, 0.3, 0.5]);
    assert!(approx(
        dray_core::light_sampler::emitted(&scene, m, uv),
        Vec3::new(0.0, 0.0, 1.0)
    ));

    // Both slots on TEXCOORD_0: one set stored (no memory for a second), red emission.
    let one = file("one", 0);
    assert!(one.mesh.uvs2.is_empty());
    let (_, sv) = shade_first_triangle(&one, fx);
    assert!(approx(sv.emission, Vec3::new(1.0, 0.0, 0.0)), "{sv:?}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// `KHR_texture_transform`'s `texCoord` overrides the slot's, and the slot then reads
/// that set beside the others.
#[test]
fn a_texture_transform_tex_coord_picks_the_set() {
    let dir = test_dir("transform-set");
    let b = red_and_blue_uv_sets();
    let material = r#"{"pbrMetallicRoughness":{"baseColorTexture":{"index":0,"texCoord":0}},
  "emissiveFactor":[1,1,1],"emissiveTexture":{"index":0,"texCoord":0,
    "extensions":{"KHR_texture_transform":{"texCoord":1}}}}"#;
    let scene = load_gltf(&b.write(&dir, "override", &red_and_blue_rest(material))).unwrap();
    assert!(
        scene.stats.warnings.is_empty(),
        "{:?}",
        scene.stats.warnings
    );
    let e = scene.materials[0].emissive_tex.unwrap();
    assert_eq!((e.tex_coord, e.second_uv, e.transform), (1, true, None));
    let fx = dray_scene::effects::analyze(&scene, Vec3::ONE);
    let (_, sv) = shade_first_triangle(&scene, fx);
    assert!(approx(sv.base_color, Vec3::new(1.0, 0.0, 0.0)), "{sv:?}");
    assert!(approx(sv.emission, Vec3::new(0.0, 0.0, 1.0)), "{sv:?}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// A material whose slots name three sets keeps two (the first is the base colour's, the
/// second the first other one in slot order): a slot naming a third reads the first set,
/// with a warning naming the material, the slot and the sets (never a panic).
#[test]
fn a_third_uv_set_falls_back_to_the_first_with_a_warning() {
    let dir = test_dir("three-sets");
    let b = red_and_blue_uv_sets();
    let material = r#"{"name":"ThreeSets","pbrMetallicRoughness":{"baseColorTexture":{"index":0},
    "metallicRoughnessTexture":{"index":0,"texCoord":1}},
  "normalTexture":{"index":0,"texCoord":2},
  "emissiveFactor":[1,1,1],"emissiveTexture":{"index":0,"texCoord":1}}"#;
    let scene = load_gltf(&b.write(&dir, "three", &red_and_blue_rest(material))).unwrap();
    let w = &scene.stats.warnings;
    assert_eq!(w.len(), 1, "{w:?}");
    for word in [
        "ThreeSets",
        "normalTexture",
        "TEXCOORD_2",
        "TEXCOORD_0",
        "TEXCOORD_1",
        "third",
    ] {
        assert!(w[0].contains(word), "{word:?} not in {w:?}");
    }
    let m = &scene.materials[0];
    let normal = m.normal_tex.unwrap();
    assert_eq!((normal.tex_coord, normal.second_uv), (0, false));
    assert!(m.metallic_roughness_tex.unwrap().second_uv);
    assert!(m.emissive_tex.unwrap().second_uv);
    assert_eq!(scene.mesh.uvs2, [glam::Vec2::new(0.75, 0.5); 3]);
    let fx = dray_scene::effects::analyze(&scene, Vec3::ONE);
    let (_, sv) = shade_first_triangle(&scene, fx);
    assert!(approx(sv.emission, Vec3::new(0.0, 0.0, 1.0)), "{sv:?}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// Occlusion maps are not read (a path tracer computes occlusion), so an
/// `occlusionTexture` on another set asks for no second set and warns of nothing.
#[test]
fn an_occlusion_map_on_another_set_stores_no_second_set() {
    let dir = test_dir("occlusion-set");
    let b = red_and_blue_uv_sets();
    let material = r#"{"pbrMetallicRoughness":{"baseColorTexture":{"index":0}},
  "occlusionTexture":{"index":0,"texCoord":1}}"#;
    let scene = load_gltf(&b.write(&dir, "occlusion", &red_and_blue_rest(material))).unwrap();
    assert!(scene.mesh.uvs2.is_empty());
    assert!(
        scene.stats.warnings.is_empty(),
        "{:?}",
        scene.stats.warnings
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// A normal map on TEXCOORD_1 gets its tangents from TEXCOORD_1 when the file has none:
/// there U runs along +Y, where TEXCOORD_0's runs along +X.
#[test]
fn generated_tangents_follow_the_normal_maps_own_set() {
    let dir = test_dir("tangent-set");
    let mut b = triangle_builder();
    b.floats(&[0.0, 0.0, 1.0, 0.0, 0.0, 1.0], "VEC2");
    b.floats(&[0.0, 0.0, 0.0, 1.0, 1.0, 0.0], "VEC2");
    let file = |name: &str, normal_set: u32| {
        let rest = format!(
            r#""meshes":[{{"primitives":[{{"attributes":{{"POSITION":0,"NORMAL":1,
  "TEXCOORD_0":4,"TEXCOORD_1":5}},"indices":3,"material":0}}]}}],
"nodes":[{{"mesh":0}}],
"materials":[{{"pbrMetallicRoughness":{{"baseColorTexture":{{"index":0}}}},
  "normalTexture":{{"index":0,"texCoord":{normal_set}}}}}],
"images":[{{"uri":"data:image/png;base64,{}"}}],"textures":[{{"source":0}}]"#,
            base64(&png_2x1())
        );
        load_gltf(&b.write(&dir, name, &rest)).unwrap()
    };
    for (set, along) in [(0, Vec3::X), (1, Vec3::Y)] {
        let scene = file(&format!("set{set}"), set);
        assert!(
            scene.stats.warnings.is_empty(),
            "{:?}",
            scene.stats.warnings
        );
        assert!(!scene.mesh.tangents.is_empty());
        for t in &scene.mesh.tangents {
            assert!(approx(t.truncate(), along), "set {set}: {t}");
        }
        assert_eq!(scene.mesh.uvs2.is_empty(), set == 0);
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn texture_transforms_map_uvs_on_every_slot() {
    let dir = test_dir("transform");
    let b = two_uv_sets();
    let rest = format!(
        r#""meshes":[{{"primitives":[
  {{"attributes":{{"POSITION":0,"NORMAL":1,"TANGENT":2,"TEXCOORD_0":4}},"indices":3,"material":0}}]}}],
"nodes":[{{"mesh":0}}],
"extensionsUsed":["KHR_texture_transform","KHR_materials_clearcoat"],
"extensionsRequired":["KHR_texture_transform"],
"materials":[{{
  "pbrMetallicRoughness":{{"baseColorTexture":{{"index":0,"extensions":{{"KHR_texture_transform":
    {{"offset":[0,1],"rotation":1.5707963,"scale":[0.5,0.5]}}}}}}}},
  "normalTexture":{{"index":0,"extensions":{{"KHR_texture_transform":{{"scale":[2,3]}}}}}},
  "extensions":{{"KHR_materials_clearcoat":{{"clearcoatFactor":1,
    "clearcoatTexture":{{"index":0,"extensions":{{"KHR_texture_transform":{{"offset":[0.5,0]}}}}}}}}}}}}],
{}"#,
        one_texture()
    );
    let scene = load_gltf(&b.write(&dir, "transform", &rest)).unwrap();
    let m = &scene.materials[0];
    let base = m.base_color_tex.unwrap();
    // The extension's own example: the lower-left quadrant, turned clockwise.
    let at = |t: dray_core::material::TexRef, u: f32, v: f32| {
        t.uv(dray_core::material::TexCoords::first(glam::Vec2::new(u, v)))
    };
    assert!((at(base, 1.0, 0.0) - glam::Vec2::new(0.0, 0.5)).length() < 1e-6);
    assert!((at(base, 0.0, 1.0) - glam::Vec2::new(0.5, 1.0)).length() < 1e-6);
    assert_eq!(
        at(m.normal_tex.unwrap(), 1.0, 1.0),
        glam::Vec2::new(2.0, 3.0)
    );
    let coat = m.clearcoat.unwrap().tex.unwrap();
    assert_eq!(at(coat, 0.25, 0.25), glam::Vec2::new(0.75, 0.25));
    let _ = std::fs::remove_dir_all(&dir);
}

/// The surface and shading values of triangle 0 at one inner point, seen from +z.
fn shade_first_triangle(
    scene: &Scene,
    fx: dray_core::effects::Effects,
) -> (
    dray_core::surface::Surface,
    dray_core::surface::ShadingValues,
) {
    let hit = dray_core::bvh::Hit {
        t: 1.0,
        tri: 0,
        b0: 0.2,
        b1: 0.3,
        b2: 0.5,
    };
    let surf = dray_core::surface::Surface::new(scene, &hit, -Vec3::Z, fx);
    let sv = surf.shading(scene, fx);
    (surf, sv)
}

#[test]
fn unlit_materials_show_their_base_colour_and_light_nothing() {
    use dray_core::effects::Effect;
    let dir = test_dir("unlit");
    let b = triangle_builder();
    let rest = format!(
        r#"{TRI_MESH},"nodes":[{{"mesh":0}}],
"extensionsUsed":["KHR_materials_unlit"],"extensionsRequired":["KHR_materials_unlit"],
"materials":[{{"pbrMetallicRoughness":{{"baseColorFactor":[0.5,0.25,1,1],"metallicFactor":1}},
  "emissiveFactor":[1,1,1],"extensions":{{"KHR_materials_unlit":{{}}}}}}]"#
    )
    .replace(r#""indices":3}"#, r#""indices":3,"material":0}"#);
    let scene = load_gltf(&b.write(&dir, "unlit", &rest)).unwrap();
    let m = &scene.materials[0];
    assert!(m.unlit && !m.has_emission());
    let fx = dray_scene::effects::analyze(&scene, Vec3::ONE);
    assert!(fx.contains(Effect::Unlit));
    assert!(!fx.contains(Effect::Specular) && !fx.contains(Effect::Emission));
    let (_, sv) = shade_first_triangle(&scene, fx);
    assert_eq!(sv.emission, Vec3::new(0.5, 0.25, 1.0));
    assert_eq!(sv.base_color, Vec3::ZERO);
    assert_eq!((sv.metallic, sv.specular), (0.0, 0.0));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn quantized_attributes_are_read() {
    let dir = test_dir("quantized");
    let mut b = Builder::default();
    // POSITION as unsigned 16-bit integers (a node scale brings them back), NORMAL as
    // normalized signed bytes, TEXCOORD_0 as normalized unsigned shorts.
    let pos: Vec<u8> = [0u16, 0, 0, 1000, 0, 0, 0, 1000, 0, 0]
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    let v = b.view(&pos[..18]);
    b.accessors.push(format!(
        r#"{{"bufferView":{v},"componentType":5123,"count":3,"type":"VEC3","min":[0,0,0],"max":[1000,1000,0]}}"#
    ));
    let v = b.view(&[0, 0, 127, 0, 0, 0, 127, 0, 0, 0, 127, 0]);
    b.accessors.push(format!(
        r#"{{"bufferView":{v},"componentType":5120,"normalized":true,"count":3,"type":"VEC3"}}"#
    ));
    b.views[v] = b.views[v].replace('}', r#","byteStride":4}"#);
    let uv: Vec<u8> = [0u16, 0, 65535, 0, 0, 65535]
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    let v = b.view(&uv);
    b.accessors.push(format!(
        r#"{{"bufferView":{v},"componentType":5123,"normalized":true,"count":3,"type":"VEC2"}}"#
    ));
    let rest = r#""meshes":[{"primitives":[{"attributes":{"POSITION":0,"NORMAL":1,"TEXCOORD_0":2}}]}],
"nodes":[{"mesh":0,"scale":[0.001,0.001,0.001]}],
"extensionsUsed":["KHR_mesh_quantization"],"extensionsRequired":["KHR_mesh_quantization"]"#;
    let scene = load_gltf(&b.write(&dir, "quantized", rest)).unwrap();
    let m = &scene.mesh;
    assert!(approx(m.positions[1], Vec3::X) && approx(m.positions[2], Vec3::Y));
    assert!(
        m.normals.iter().all(|n| approx(*n, Vec3::Z)),
        "{:?}",
        m.normals
    );
    assert_eq!(m.uvs[1], glam::Vec2::new(1.0, 0.0));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn meshopt_compressed_buffer_views_are_decoded() {
    let dir = test_dir("meshopt");
    let positions: Vec<[f32; 3]> = vec![
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        [1.0, 1.0, 0.0],
    ];
    let indices: Vec<u32> = vec![0, 1, 2, 2, 1, 3];
    let vbuf = meshopt::encode_vertex_buffer(&positions).unwrap();
    let ibuf = meshopt::encode_index_buffer(&indices, positions.len()).unwrap();
    let mut bin = vbuf.clone();
    while !bin.len().is_multiple_of(4) {
        bin.push(0);
    }
    let ioff = bin.len();
    bin.extend_from_slice(&ibuf);
    std::fs::write(dir.join("c.bin"), &bin).unwrap();
    let json = format!(
        r#"{{"asset":{{"version":"2.0"}},
"extensionsUsed":["EXT_meshopt_compression"],"extensionsRequired":["EXT_meshopt_compression"],
"buffers":[{{"uri":"c.bin","byteLength":{}}},
  {{"byteLength":60,"extensions":{{"EXT_meshopt_compression":{{"fallback":true}}}}}}],
"bufferViews":[
  {{"buffer":1,"byteLength":48,"byteStride":12,"extensions":{{"EXT_meshopt_compression":
    {{"buffer":0,"byteLength":{},"byteStride":12,"count":4,"mode":"ATTRIBUTES"}}}}}},
  {{"buffer":1,"byteOffset":48,"byteLength":12,"extensions":{{"EXT_meshopt_compression":
    {{"buffer":0,"byteOffset":{ioff},"byteLength":{},"byteStride":2,"count":6,"mode":"TRIANGLES"}}}}}}],
"accessors":[
  {{"bufferView":0,"componentType":5126,"count":4,"type":"VEC3","min":[0,0,0],"max":[1,1,0]}},
  {{"bufferView":1,"componentType":5123,"count":6,"type":"SCALAR"}}],
"meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}},"indices":1}}]}}],
"nodes":[{{"mesh":0}}]}}"#,
        bin.len(),
        vbuf.len(),
        ibuf.len()
    );
    let path = dir.join("c.gltf");
    std::fs::write(&path, &json).unwrap();
    let scene = load_gltf(&path).unwrap();
    assert_eq!(scene.mesh.triangle_count(), 2);
    let got: Vec<[f32; 3]> = scene.mesh.positions.iter().map(|p| p.to_array()).collect();
    assert_eq!(got, positions);
    assert_eq!(scene.mesh.indices, vec![[0, 1, 2], [2, 1, 3]]);

    // A corrupted stream is an error naming the buffer view, not a crash.
    let mut bad = bin.clone();
    for b in bad.iter_mut().take(vbuf.len()).skip(1) {
        *b = 0xff;
    }
    std::fs::write(dir.join("c.bin"), &bad).unwrap();
    let msg = load_gltf(&path).unwrap_err().to_string();
    assert!(msg.contains("buffer view 0"), "{msg}");
    // A stride the decoder does not take is refused before it is called.
    std::fs::write(dir.join("c.bin"), &bin).unwrap();
    std::fs::write(
        &path,
        json.replace(r#""byteStride":12,"count""#, r#""byteStride":10,"count""#),
    )
    .unwrap();
    let msg = load_gltf(&path).unwrap_err().to_string();
    assert!(msg.contains("byteStride 10"), "{msg}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// A decompression bomb (issue 45): one small compressed stream named by many views,
/// each declaring the whole expansion. Each view alone is within the per-view cap, so
/// before the file's shared allowance the loader allocated once per view (an 8 MiB file
/// with 12 views took 6 GiB and aborted). Now a view past the allowance is an error
/// naming it, and admission sees the declared total without decoding anything.
#[test]
fn a_meshopt_decompression_bomb_is_an_error_not_an_allocation() {
    let dir = test_dir("meshopt_bomb");
    let count = 1usize << 18;
    let zeros = vec![[0f32; 4]; count];
    let stream = meshopt::encode_vertex_buffer(&zeros).unwrap();
    // Enough views for the declared total to pass the file's allowance whatever ratio
    // this encoder reaches on zeros.
    let allowance = dray_scene::meshopt::MAX_EXPANSION * stream.len();
    let views = allowance / (count * 16) + 2;
    let view = |i: usize| {
        format!(
            r#"{{"buffer":1,"byteOffset":{},"byteLength":{},"byteStride":16,"extensions":{{"EXT_meshopt_compression":
    {{"buffer":0,"byteLength":{},"byteStride":16,"count":{count},"mode":"ATTRIBUTES"}}}}}}"#,
            i * count * 16,
            count * 16,
            stream.len()
        )
    };
    let json = format!(
        r#"{{"asset":{{"version":"2.0"}},
"extensionsUsed":["EXT_meshopt_compression"],"extensionsRequired":["EXT_meshopt_compression"],
"buffers":[{{"uri":"bomb.bin","byteLength":{}}},
  {{"byteLength":{},"extensions":{{"EXT_meshopt_compression":{{"fallback":true}}}}}}],
"bufferViews":[{}],
"accessors":[{{"bufferView":0,"componentType":5126,"count":3,"type":"VEC3","min":[0,0,0],"max":[0,0,0]}}],
"meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}}}}]}}],
"nodes":[{{"mesh":0}}]}}"#,
        stream.len(),
        views * count * 16,
        (0..views).map(view).collect::<Vec<_>>().join(",")
    );
    std::fs::write(dir.join("bomb.bin"), &stream).unwrap();
    let path = dir.join("bomb.gltf");
    std::fs::write(&path, &json).unwrap();
    let declared = dray_scene::gltf::declared_expansion(&path);
    assert_eq!(declared, (views * count * 16) as u64);
    assert!(declared > allowance as u64, "{declared} vs {allowance}");
    let msg = load_gltf(&path).unwrap_err().to_string();
    assert!(
        msg.contains("allowance") && msg.contains("buffer view"),
        "{msg}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn clearcoat_sheen_and_volume_are_read_and_counted() {
    use dray_core::effects::Effect;
    let dir = test_dir("coat");
    let b = triangle_builder();
    let rest = format!(
        r#""meshes":[{{"primitives":[
  {{"attributes":{{"POSITION":0}},"indices":3,"material":0}},
  {{"attributes":{{"POSITION":0}},"indices":3,"material":1}}]}}],
"nodes":[{{"mesh":0}}],
"extensionsUsed":["KHR_materials_clearcoat","KHR_materials_volume","KHR_materials_transmission",
  "KHR_materials_sheen"],
"extensionsRequired":["KHR_materials_clearcoat","KHR_materials_volume","KHR_materials_sheen"],
"materials":[
  {{"extensions":{{"KHR_materials_clearcoat":{{"clearcoatFactor":0.75,
    "clearcoatRoughnessFactor":0.25,"clearcoatRoughnessTexture":{{"index":0,"texCoord":0}}}},
    "KHR_materials_sheen":{{"sheenColorFactor":[1,0.5,0.25],"sheenRoughnessFactor":0.5,
      "sheenColorTexture":{{"index":0}}}}}}}},
  {{"extensions":{{"KHR_materials_transmission":{{"transmissionFactor":1}},
    "KHR_materials_volume":{{"attenuationColor":[0.5,0.25,1],"attenuationDistance":2}}}}}}],
{}"#,
        one_texture()
    );
    let scene = load_gltf(&b.write(&dir, "coat", &rest)).unwrap();
    let c = scene.materials[0].clearcoat.unwrap();
    assert_eq!((c.factor, c.roughness), (0.75, 0.25));
    assert_eq!(c.roughness_tex.map(|t| t.texture), Some(0));
    let sh = scene.materials[0].sheen.unwrap();
    assert_eq!((sh.color, sh.roughness), (Vec3::new(1.0, 0.5, 0.25), 0.5));
    assert_eq!(sh.color_tex.map(|t| t.texture), Some(0));
    let v = scene.materials[1].volume.unwrap();
    assert_eq!(v.attenuation_color, Vec3::new(0.5, 0.25, 1.0));
    // Beer-Lambert: after attenuationDistance white light has the attenuation colour.
    let t = v.transmittance(2.0);
    assert!(
        (t - Vec3::new(0.5, 0.25, 1.0)).abs().max_element() < 1e-6,
        "{t}"
    );
    let fx = dray_scene::effects::analyze(&scene, Vec3::ZERO);
    assert!(fx.contains(Effect::Clearcoat) && fx.contains(Effect::Volume));
    assert!(fx.contains(Effect::Sheen));
    // A scene without them asks for neither.
    let plain = load_gltf(&triangle_builder().write(
        &dir,
        "plain",
        &format!(r#"{TRI_MESH},"nodes":[{{"mesh":0}}]"#),
    ))
    .unwrap();
    let fx = dray_scene::effects::analyze(&plain, Vec3::ZERO);
    for e in [
        Effect::Clearcoat,
        Effect::Sheen,
        Effect::Volume,
        Effect::Unlit,
    ] {
        assert!(!fx.contains(e), "{e:?}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn anisotropy_is_read_and_gets_tangents() {
    use dray_core::effects::Effect;
    let dir = test_dir("anisotropy");
    // NORMAL (1) and TEXCOORD_1 (5) but no TANGENT: tangents are made for the lobe.
    let b = two_uv_sets();
    let rest = r#""meshes":[{"primitives":[
  {"attributes":{"POSITION":0,"NORMAL":1,"TEXCOORD_0":5},"indices":3,"material":0}]}],
"nodes":[{"mesh":0}],
"extensionsUsed":["KHR_materials_anisotropy"],"extensionsRequired":["KHR_materials_anisotropy"],
"materials":[{"pbrMetallicRoughness":{"roughnessFactor":0.3},
  "extensions":{"KHR_materials_anisotropy":{"anisotropyStrength":0.6,"anisotropyRotation":0.5}}}]"#;
    let scene = load_gltf(&b.write(&dir, "aniso", rest)).unwrap();
    let a = scene.materials[0].anisotropy.unwrap();
    assert_eq!((a.strength, a.rotation, a.tex), (0.6, 0.5, None));
    assert!(
        scene
            .mesh
            .tangents
            .iter()
            .all(|t| t.truncate().length() > 0.5),
        "{:?}",
        scene.mesh.tangents
    );
    let fx = dray_scene::effects::analyze(&scene, Vec3::ONE);
    assert!(fx.contains(Effect::Anisotropy));
    // The direction reaches shading: the tangent turned by the rotation.
    let (surf, sv) = shade_first_triangle(&scene, fx);
    assert_eq!(sv.anisotropy, 0.6);
    let want = surf.tangent * 0.5f32.cos() + surf.bitangent * 0.5f32.sin();
    assert!((sv.anisotropy_direction - want).length() < 1e-6);
    assert!(surf.tangent.length() > 0.99);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn iridescence_is_read_counted_and_shaded() {
    use dray_core::effects::Effect;
    let dir = test_dir("iridescence");
    let b = two_uv_sets();
    let rest = format!(
        r#""meshes":[{{"primitives":[
  {{"attributes":{{"POSITION":0,"NORMAL":1,"TEXCOORD_0":5}},"indices":3,"material":0}},
  {{"attributes":{{"POSITION":0,"NORMAL":1,"TEXCOORD_0":5}},"indices":3,"material":1}}]}}],
"nodes":[{{"mesh":0}}],
"extensionsUsed":["KHR_materials_iridescence"],"extensionsRequired":["KHR_materials_iridescence"],
"materials":[
  {{"extensions":{{"KHR_materials_iridescence":{{"iridescenceFactor":0.75,
    "iridescenceTexture":{{"index":0}},"iridescenceIor":1.42,
    "iridescenceThicknessMinimum":120,"iridescenceThicknessMaximum":620,
    "iridescenceThicknessTexture":{{"index":0}}}}}}}},
  {{"extensions":{{"KHR_materials_iridescence":{{"iridescenceFactor":1}}}}}}],
{}"#,
        one_texture()
    );
    // A file that requires the extension loads, without a warning.
    let scene = load_gltf(&b.write(&dir, "film", &rest)).unwrap();
    assert!(
        scene.stats.warnings.is_empty(),
        "{:?}",
        scene.stats.warnings
    );
    let ir = scene.materials[0].iridescence.unwrap();
    assert_eq!(
        (ir.factor, ir.ior, ir.thickness_min, ir.thickness_max),
        (0.75, 1.42, 120.0, 620.0)
    );
    assert_eq!(ir.tex.map(|t| t.texture), Some(0));
    assert_eq!(ir.thickness_tex.map(|t| t.texture), Some(0));
    // The extension's defaults.
    let d = scene.materials[1].iridescence.unwrap();
    assert_eq!(
        (d.factor, d.ior, d.thickness_min, d.thickness_max, d.tex),
        (1.0, 1.3, 100.0, 400.0, None)
    );
    let fx = dray_scene::effects::analyze(&scene, Vec3::ONE);
    assert!(fx.contains(Effect::Iridescence));

    // Shading: factor x texture R; thickness mix(min, max, texture G).
    let (surf, sv) = shade_first_triangle(&scene, fx);
    let texel = scene.textures[0].sample(surf.uv.first, false);
    assert!((sv.iridescence - 0.75 * texel.x).abs() < 1e-6, "{sv:?}");
    let want = 120.0 + 500.0 * texel.y;
    assert!((sv.iridescence_thickness - want).abs() < 1e-3, "{sv:?}");
    assert_eq!(sv.iridescence_ior, 1.42);
    // `--effects -iridescence` turns the film off.
    let mut off = fx;
    off.set(Effect::Iridescence, false);
    assert_eq!(shade_first_triangle(&scene, off).1.iridescence, 0.0);

    // A scene without the extension does not ask for it.
    let plain = load_gltf(&triangle_builder().write(
        &dir,
        "plain",
        &format!(r#"{TRI_MESH},"nodes":[{{"mesh":0}}]"#),
    ))
    .unwrap();
    assert!(!dray_scene::effects::analyze(&plain, Vec3::ONE).contains(Effect::Iridescence));
    let _ = std::fs::remove_dir_all(&dir);
}

/// A 1x1 PNG of one RGBA texel.
fn png_1x1(texel: [u8; 4]) -> Vec<u8> {
    let img = image::RgbaImage::from_raw(1, 1, texel.to_vec()).unwrap();
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png).unwrap();
    out.into_inner()
}

#[test]
fn clearcoat_normal_texture_tilts_the_coat_only() {
    use dray_core::effects::Effect;
    let dir = test_dir("coat-normal");
    // NORMAL and TEXCOORD_0 but no TANGENT: the coat's normal map asks for tangents.
    let b = normal_mapped_quad();
    let file = |name: &str, coat_normal: &str| {
        let rest = format!(
            r#""meshes":[{{"primitives":[{{"attributes":{{"POSITION":0,"NORMAL":1,"TEXCOORD_0":2}},
  "indices":3,"material":0}}]}}],
"nodes":[{{"mesh":0}}],
"extensionsUsed":["KHR_materials_clearcoat"],"extensionsRequired":["KHR_materials_clearcoat"],
"materials":[{{"extensions":{{"KHR_materials_clearcoat":{{"clearcoatFactor":1{coat_normal}}}}}}}],
"textures":[{{"source":0}}],
"images":[{{"uri":"data:image/png;base64,{}"}}]"#,
            base64(&png_1x1([255, 128, 180, 255]))
        );
        load_gltf(&b.write(&dir, name, &rest)).unwrap()
    };
    let scene = file(
        "mapped",
        r#","clearcoatNormalTexture":{"index":0,"scale":0.5}"#,
    );
    assert!(
        scene.stats.warnings.is_empty(),
        "{:?}",
        scene.stats.warnings
    );
    let c = scene.materials[0].clearcoat.unwrap();
    assert_eq!(
        (c.normal_tex.map(|t| t.texture), c.normal_scale),
        (Some(0), 0.5)
    );
    assert!(
        scene
            .mesh
            .tangents
            .iter()
            .all(|t| t.truncate().length() > 0.5)
    );
    let fx = dray_scene::effects::analyze(&scene, Vec3::ONE);
    let (surf, _) = shade_first_triangle(&scene, fx);
    // The texel (255, 128, 180) leans toward +U = +X, by 0.5 x 1 against its z 0.41.
    let s = scene.textures[0].sample(surf.uv.first, false);
    let k = Vec3::new(
        (s.x * 2.0 - 1.0) * 0.5,
        (s.y * 2.0 - 1.0) * 0.5,
        s.z * 2.0 - 1.0,
    );
    assert!(
        (surf.coat_n - k.normalize()).length() < 1e-5,
        "{} vs {k}",
        surf.coat_n
    );
    assert!(surf.coat_n.x > 0.5);
    // The base keeps the vertex normal.
    assert_eq!(surf.n, Vec3::Z);
    // Without textures, or without the coat, there is no coat normal.
    let mut off = fx;
    off.set(Effect::Clearcoat, false);
    assert_eq!(shade_first_triangle(&scene, off).0.coat_n, Vec3::ZERO);
    let mut off = fx;
    off.set(Effect::Textures, false);
    assert_eq!(shade_first_triangle(&scene, off).0.coat_n, Vec3::ZERO);
    // Without the map: the same surface, bit for bit, and no coat normal.
    let plain = file("plain", "");
    let fx = dray_scene::effects::analyze(&plain, Vec3::ONE);
    let (p, _) = shade_first_triangle(&plain, fx);
    assert_eq!(p.coat_n, Vec3::ZERO);
    assert_eq!((p.n, p.p), (surf.n, surf.p));
    // A material with no texture reads no texture coordinates, so none are interpolated.
    assert_eq!(p.uv, dray_core::material::TexCoords::default());
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn dispersion_is_read_and_counted_on_transmissive_materials() {
    use dray_core::effects::Effect;
    let dir = test_dir("dispersion");
    let b = triangle_builder();
    let rest = r#""meshes":[{"primitives":[
  {"attributes":{"POSITION":0},"indices":3,"material":0},
  {"attributes":{"POSITION":0},"indices":3,"material":1}]}],
"nodes":[{"mesh":0}],
"extensionsUsed":["KHR_materials_dispersion","KHR_materials_transmission",
  "KHR_materials_volume"],
"extensionsRequired":["KHR_materials_dispersion"],
"materials":[
  {"extensions":{"KHR_materials_transmission":{"transmissionFactor":1},
    "KHR_materials_volume":{"thicknessFactor":1},
    "KHR_materials_dispersion":{"dispersion":0.36}}},
  {"extensions":{"KHR_materials_dispersion":{"dispersion":2}}}]"#;
    let scene = load_gltf(&b.write(&dir, "prism", rest)).unwrap();
    assert!(
        scene.stats.warnings.is_empty(),
        "{:?}",
        scene.stats.warnings
    );
    assert_eq!(scene.materials[0].dispersion, 0.36);
    assert!(scene.materials[0].has_dispersion());
    // An opaque material shows no dispersion.
    assert_eq!(scene.materials[1].dispersion, 2.0);
    assert!(!scene.materials[1].has_dispersion());
    let fx = dray_scene::effects::analyze(&scene, Vec3::ONE);
    assert!(fx.contains(Effect::Dispersion));
    let (_, sv) = shade_first_triangle(&scene, fx);
    assert_eq!(sv.dispersion, 0.36);
    let mut off = fx;
    off.set(Effect::Dispersion, false);
    assert_eq!(shade_first_triangle(&scene, off).1.dispersion, 0.0);
    let plain = load_gltf(&triangle_builder().write(
        &dir,
        "plain",
        &format!(r#"{TRI_MESH},"nodes":[{{"mesh":0}}]"#),
    ))
    .unwrap();
    assert!(!dray_scene::effects::analyze(&plain, Vec3::ONE).contains(Effect::Dispersion));
    let _ = std::fs::remove_dir_all(&dir);
}

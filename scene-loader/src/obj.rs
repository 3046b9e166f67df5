//! Wavefront OBJ import (with MTL materials), built on the `tobj` crate.
//!
//! `tobj` parses and triangulates (fans) and gives one index per vertex; this module
//! maps the classic Phong-style MTL parameters onto dray's glTF-style materials and
//! pushes every model through [`validate::add_primitive`].
//!
//! MTL mapping, and why:
//! - `Kd` is the base colour (metallic 0). A material without `Kd` gets grey 0.8, the
//!   usual exporter default, rather than the MTL spec's black, which is rarely meant.
//! - `Ks` turns on a dielectric specular lobe: `specular = max(Ks)`, tinted by
//!   `Ks / max(Ks)`, with `roughness = sqrt(2 / (Ns + 2))` (the usual Phong-exponent to
//!   microfacet-roughness match). Without `Ks` (or with `illum` 0 or 1, which have no
//!   highlight) the material is pure Lambert, as those models are.
//! - `Ke` is emission; `d` (or `1 - Tr`) below 1 is alpha blending.
//! - `Ni` sets the IOR only when it is above 1: in the Phong model `Ni` is used only for
//!   refraction, and exporters often write `Ni 1`, which as a glTF IOR would erase every
//!   `Ks` highlight.
//! - `illum` 6 or 7 (refraction) makes a clear dielectric (transmission 1), tinted by
//!   `Tf` when given. `Tf` alone does not: some exporters write `Tf 1 1 1` on every
//!   opaque material.
//! - `map_Kd` is the base colour texture, loaded relative to the OBJ file (and, like
//!   `mtllib`, refused unless it resolves inside the OBJ's folder). It replaces
//!   `Kd` rather than multiplying it, because exporters write a placeholder `Kd` next
//!   to the map. Other maps are ignored with a warning.
//!
//! OBJ texture coordinates put v = 0 at the bottom of the image; dray's textures put
//! the first row at v = 0 (glTF), so v is flipped.

use std::cell::RefCell;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

use dray_core::material::{AlphaMode, Material, TexRef};
use dray_core::scene::Scene;
use dray_core::texture::{Sampler, Texture};
use glam::{Vec2, Vec3};

use crate::error::{Result, SceneError};
use crate::reference::{RefError, display_reference, open_in_scene_folder as open_reference};
use crate::validate::{self, Origin, Primitive};

/// Load an OBJ file and the MTL libraries it names.
///
/// A missing MTL library is a warning (the affected models get a grey Lambert
/// material); a malformed one, or a missing or undecodable texture, is an error naming
/// the file.
pub fn load_obj(path: &Path) -> Result<Scene> {
    let bytes = crate::reference::read_scene_file(path)?;
    let parsed = parse(path, &bytes)?;
    let stem = path
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "obj".to_string());
    let mut scene = Scene {
        name: stem.clone(),
        ..Scene::default()
    };
    for mtl in parsed.missing_mtl {
        scene.stats.warnings.push(format!(
            "material library {} not found; using a default material",
            display_reference(&mtl)
        ));
    }

    let mut builder = MaterialBuilder {
        path,
        obj_materials: &parsed.materials,
        converted: HashMap::new(),
        textures: HashMap::new(),
        default: None,
    };
    let mut primitive_of_name: HashMap<String, usize> = HashMap::new();
    for model in &parsed.models {
        let name = if model.name.is_empty() {
            stem.as_str()
        } else {
            model.name.as_str()
        };
        let primitive = primitive_of_name.entry(name.to_string()).or_insert(0);
        let origin = Origin {
            path,
            mesh: name,
            primitive: *primitive,
        };
        *primitive += 1;
        if model.mesh.indices.is_empty() {
            continue;
        }
        add_mesh(&model.mesh, origin, &mut builder, &mut scene)?;
    }
    if scene.mesh.indices.is_empty() {
        return Err(SceneError::Empty {
            path: path.to_path_buf(),
        });
    }
    Ok(scene)
}

/// What `tobj` made of an OBJ file and its MTL libraries.
struct Parsed {
    models: Vec<tobj::Model>,
    materials: Vec<tobj::Material>,
    /// MTL libraries named but not found (a warning each).
    missing_mtl: Vec<String>,
}

/// Parse the OBJ file at `path` (its `bytes`) and the MTL libraries it names, with
/// `tobj`; a refused or malformed library is an error naming it.
fn parse(path: &Path, bytes: &[u8]) -> Result<Parsed> {
    let format_err = |message: String| SceneError::Format {
        path: path.to_path_buf(),
        message,
    };
    // tobj reports MTL trouble only as a bare error code; record which library failed
    // and how, so the warning or error can name it. A library must be a regular file
    // inside the OBJ's folder: one that is missing there is a warning, one that is
    // refused (absolute, escaping, a device or FIFO) an error.
    let missing_mtl: RefCell<Vec<String>> = RefCell::new(Vec::new());
    let bad_mtl: RefCell<Vec<(String, String)>> = RefCell::new(Vec::new());
    let options = tobj::LoadOptions {
        triangulate: true,
        single_index: true,
        // Points and lines have no surface; tobj would otherwise turn them into
        // zero-area triangles.
        ignore_points: true,
        ignore_lines: true,
    };
    let loader = |mtl: &Path| {
        let name = mtl.to_string_lossy().into_owned();
        match open_reference(path, &name) {
            Ok(opened) => checked_mtl(opened.read_all())
                .and_then(|text| {
                    tobj::load_mtl_buf(&mut std::io::Cursor::new(text)).map_err(|e| e.to_string())
                })
                .map_err(|m| {
                    bad_mtl.borrow_mut().push((name, m));
                    tobj::LoadError::MaterialParseError
                }),
            Err(RefError::NotFound) => {
                missing_mtl.borrow_mut().push(name);
                Err(tobj::LoadError::OpenFileFailed)
            }
            Err(e) => {
                bad_mtl.borrow_mut().push((name, e.message()));
                Err(tobj::LoadError::OpenFileFailed)
            }
        }
    };
    // tobj does index arithmetic on face indices without overflow checks (a huge or
    // zero index wraps and then indexes out of bounds): refuse such faces first.
    precheck_faces(bytes).map_err(format_err)?;
    // tobj is fuzzed but third-party; a panic on hostile input must still surface as a
    // load error rather than take down the renderer.
    let parsed = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        tobj::load_obj_buf(&mut std::io::Cursor::new(bytes), &options, loader)
    }))
    .map_err(|_| format_err("the OBJ parser failed on this file".to_string()))?;
    let (models, materials) = parsed.map_err(|e| format_err(format!("cannot parse OBJ: {e}")))?;
    if let Some((mtl, e)) = bad_mtl.into_inner().into_iter().next() {
        return Err(format_err(format!(
            "material library {}: {e}",
            display_reference(&mtl)
        )));
    }
    Ok(Parsed {
        models,
        materials: materials.unwrap_or_default(),
        missing_mtl: missing_mtl.into_inner(),
    })
}

/// An MTL library's contents as read, checked first for what `tobj`'s MTL parser
/// would panic on ([`precheck_mtl`]), or why they cannot be used.
fn checked_mtl(read: std::io::Result<Vec<u8>>) -> std::result::Result<Vec<u8>, String> {
    let text = read.map_err(|e| format!("cannot read: {}", e.kind()))?;
    precheck_mtl(&text)?;
    Ok(text)
}

/// One model's mesh into `scene`, with its material (converted on first use).
fn add_mesh(
    mesh: &tobj::Mesh,
    origin: Origin,
    builder: &mut MaterialBuilder,
    scene: &mut Scene,
) -> Result<()> {
    if !mesh.positions.len().is_multiple_of(3) {
        return Err(origin.error("position array is not a multiple of 3"));
    }
    let positions: Vec<Vec3> = mesh
        .positions
        .chunks_exact(3)
        .map(|p| Vec3::new(p[0], p[1], p[2]))
        .collect();
    let n = positions.len();
    let name = origin.mesh;
    let warnings = &mut scene.stats.warnings;
    let normals = per_vertex::<3, _>(
        &mesh.normals,
        n,
        |v| Vec3::new(v[0], v[1], v[2]),
        || format!("{name}: only some vertices have normals; normals ignored"),
        warnings,
    );
    let uvs = per_vertex::<2, _>(
        &mesh.texcoords,
        n,
        |t| Vec2::new(t[0], 1.0 - t[1]),
        || format!("{name}: only some vertices have texture coordinates; they are ignored"),
        warnings,
    );
    let material = builder.material(mesh.material_id, scene)?;
    validate::add_primitive(
        &mut scene.mesh,
        &mut scene.stats,
        origin,
        Primitive {
            positions: &positions,
            normals: normals.as_deref(),
            tangents: None,
            uvs: uvs.as_deref(),
            uvs2: None,
            uv_sets: [0, 1],
            colors: None,
            indices: &mesh.indices,
            material,
        },
    )
}

/// A per-vertex attribute of `W` floats a vertex (`values`), made by `make`, for `n`
/// vertices. With one index per vertex, tobj fills normals and UVs only for vertices
/// that had them; a partial set cannot be matched to vertices, so it is dropped: `None`,
/// with the `partial` warning (none when no vertex had the attribute).
fn per_vertex<const W: usize, T>(
    values: &[f32],
    n: usize,
    make: impl Fn(&[f32]) -> T,
    partial: impl FnOnce() -> String,
    warnings: &mut Vec<String>,
) -> Option<Vec<T>> {
    if values.len() == n * W {
        return Some(values.chunks_exact(W).map(make).collect());
    }
    if !values.is_empty() {
        warnings.push(partial());
    }
    None
}

/// Converts MTL materials on first use, so unused materials (and their textures) cost
/// nothing and cannot fail the load.
struct MaterialBuilder<'a> {
    path: &'a Path,
    obj_materials: &'a [tobj::Material],
    /// tobj material id -> index in `Scene::materials`.
    converted: HashMap<usize, u32>,
    /// Resolved texture path -> index in `Scene::textures`, so a shared map loads once.
    textures: HashMap<PathBuf, u32>,
    default: Option<u32>,
}

impl MaterialBuilder<'_> {
    fn error(&self, message: String) -> SceneError {
        SceneError::Format {
            path: self.path.to_path_buf(),
            message,
        }
    }

    fn material(&mut self, id: Option<usize>, scene: &mut Scene) -> Result<u32> {
        let Some((id, mtl)) = id.and_then(|i| self.obj_materials.get(i).map(|m| (i, m))) else {
            if let Some(d) = self.default {
                return Ok(d);
            }
            let d = scene.materials.len() as u32;
            scene
                .materials
                .push(Material::lambert("obj", Vec3::splat(0.8)));
            self.default = Some(d);
            return Ok(d);
        };
        if let Some(&m) = self.converted.get(&id) {
            return Ok(m);
        }
        let material = self.convert(mtl, scene)?;
        let m = scene.materials.len() as u32;
        scene.materials.push(material);
        self.converted.insert(id, m);
        Ok(m)
    }

    fn convert(&mut self, mtl: &tobj::Material, scene: &mut Scene) -> Result<Material> {
        let name = &mtl.name;
        let color = |c: [f32; 3]| {
            let v = Vec3::from_array(c);
            if v.is_finite() {
                v.max(Vec3::ZERO)
            } else {
                Vec3::ZERO
            }
        };
        let param = |key: &str| mtl.unknown_param.get(key).map(String::as_str);
        let roughness = |ns: Option<f32>| {
            let ns = ns.filter(|n| n.is_finite()).unwrap_or(0.0).max(0.0);
            (2.0 / (ns + 2.0)).sqrt()
        };

        let kd = mtl.diffuse.map(color).unwrap_or(Vec3::splat(0.8));
        let mut m = Material::lambert(name, kd);

        let phong_highlight = !matches!(mtl.illumination_model, Some(0 | 1));
        if let (Some(ks), true) = (mtl.specular.map(color), phong_highlight) {
            let s = ks.max_element();
            if s > 0.0 {
                m.specular = s.min(1.0);
                m.specular_color = ks / s;
                m.roughness = roughness(mtl.shininess);
            }
        }

        let ke = mtl
            .emissive
            .or_else(|| param("Ke").and_then(parse_vec3).map(|v| v.to_array()))
            .map(color);
        if let Some(ke) = ke {
            m.emissive = ke;
        }

        let alpha = mtl
            .dissolve
            .or_else(|| {
                param("Tr")
                    .and_then(|t| t.trim().parse::<f32>().ok())
                    .map(|t| 1.0 - t)
            })
            .filter(|a| a.is_finite());
        if let Some(a) = alpha
            && a < 1.0
        {
            let a = a.max(0.0);
            m.base_color.w = a;
            m.alpha_mode = AlphaMode::Blend;
            if a == 0.0 {
                scene
                    .stats
                    .warnings
                    .push(format!("material {name:?} is fully transparent (d = 0)"));
            }
        }

        if let Some(ni) = mtl.optical_density
            && ni.is_finite()
            && ni > 1.0
        {
            m.ior = ni;
        }

        if matches!(mtl.illumination_model, Some(6 | 7)) {
            let tint = param("Tf").and_then(parse_vec3).unwrap_or(Vec3::ONE);
            m.transmission = 1.0;
            m.metallic = 0.0;
            m.specular = 1.0;
            m.specular_color = Vec3::ONE;
            m.roughness = if mtl.shininess.is_some() {
                roughness(mtl.shininess)
            } else {
                0.0
            };
            let tint = if tint.is_finite() {
                tint.clamp(Vec3::ZERO, Vec3::ONE)
            } else {
                Vec3::ONE
            };
            m.base_color = tint.extend(m.base_color.w);
        }

        if let Some(tex) = &mtl.diffuse_texture {
            let texture = self.texture(name, tex, scene)?;
            m.base_color_tex = Some(TexRef::new(texture));
            m.base_color = Vec3::ONE.extend(m.base_color.w);
        }
        for (slot, map) in [
            ("map_Ka", &mtl.ambient_texture),
            ("map_Ks", &mtl.specular_texture),
            ("map_Bump", &mtl.normal_texture),
            ("map_Ns", &mtl.shininess_texture),
            ("map_d", &mtl.dissolve_texture),
        ] {
            if map.is_some() {
                scene.stats.warnings.push(format!(
                    "material {name:?}: {slot} is not supported and was ignored"
                ));
            }
        }
        Ok(m)
    }

    /// Load (once) the texture a `map_*` statement names.
    fn texture(&mut self, material: &str, statement: &str, scene: &mut Scene) -> Result<u32> {
        let file = texture_file_name(statement);
        if file.is_empty() {
            return Err(self.error(format!(
                "material {material:?}: map_Kd {statement:?} names no file"
            )));
        }
        let shown = display_reference(file);
        let refused = |e: RefError| {
            self.error(format!(
                "material {material:?}: texture {shown}: {}",
                e.message()
            ))
        };
        // OBJ files written on Windows often use backslashes.
        let opened = match open_reference(self.path, file) {
            Err(RefError::NotFound) if file.contains('\\') => {
                open_reference(self.path, &file.replace('\\', "/"))
            }
            other => other,
        }
        .map_err(|e| match e {
            RefError::NotFound => self.error(format!(
                "material {material:?}: texture file {shown} not found in the OBJ's folder"
            )),
            e => refused(e),
        })?;
        if let Some(&t) = self.textures.get(&opened.path) {
            return Ok(t);
        }
        let full = opened.path.clone();
        let bytes = opened
            .read_all()
            .map_err(|e| refused(RefError::Refused(format!("cannot read: {}", e.kind()))))?;
        let image = image::ImageReader::new(std::io::Cursor::new(bytes))
            .with_guessed_format()
            .map_err(|e| e.to_string())
            .and_then(|r| r.decode().map_err(|e| e.to_string()))
            .map_err(|e| self.error(format!("material {material:?}: texture {shown}: {e}")))?
            .to_rgba8();
        let (width, height) = image.dimensions();
        let texels = image.pixels().map(|p| p.0).collect();
        let index = scene.textures.len() as u32;
        scene.textures.push(Texture {
            name: Path::new(file)
                .file_name()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_else(|| file.to_string()),
            width,
            height,
            texels,
            sampler: Sampler::default(),
        });
        self.textures.insert(full, index);
        Ok(index)
    }
}

/// The file name in a `map_*` statement, after any options (`-s 1 1 1`, `-clamp on`,
/// `-bm 0.5`, ...). Option arguments are numbers, `on`/`off`, or (for `-imfchan`) one
/// channel letter; the rest is the file name, which may contain spaces.
fn texture_file_name(statement: &str) -> &str {
    let mut rest = statement.trim();
    while rest.starts_with('-') {
        let (option, after) = split_word(rest);
        rest = after;
        if option == "-imfchan" {
            rest = split_word(rest).1;
            continue;
        }
        loop {
            let (word, after) = split_word(rest);
            let is_arg =
                !word.is_empty() && (word.parse::<f32>().is_ok() || word == "on" || word == "off");
            if !is_arg {
                break;
            }
            rest = after;
        }
    }
    rest
}

/// Lines as tobj reads them (`BufRead::lines`), with 1-based numbers; lines that are not
/// UTF-8 are skipped (tobj refuses them itself).
fn text_lines(bytes: &[u8]) -> impl Iterator<Item = (usize, &str)> {
    bytes
        .split(|&b| b == b'\n')
        .enumerate()
        .filter_map(|(i, l)| Some((i + 1, std::str::from_utf8(l).ok()?)))
}

/// Check every face (`f`) and line (`l`) statement's indices the way tobj will use
/// them: positive ones within the file's `v`/`vt`/`vn` counts, negative (relative) ones
/// within the counts so far, none zero. tobj subtracts, multiplies and then indexes
/// without overflow checks, so such an index would panic inside it.
fn precheck_faces(bytes: &[u8]) -> std::result::Result<(), String> {
    let mut total = [0i64; 3];
    for (_, line) in text_lines(bytes) {
        match line.split_whitespace().next() {
            Some("v") => total[0] += 1,
            Some("vt") => total[1] += 1,
            Some("vn") => total[2] += 1,
            _ => {}
        }
    }
    let mut so_far = [0i64; 3];
    const KIND: [&str; 3] = ["vertex", "texture coordinate", "normal"];
    for (n, line) in text_lines(bytes) {
        let mut words = line.split_whitespace();
        match words.next() {
            Some("v") => so_far[0] += 1,
            Some("vt") => so_far[1] += 1,
            Some("vn") => so_far[2] += 1,
            Some("f" | "l") => {
                for vertex in words {
                    for (k, part) in vertex.split('/').take(3).enumerate() {
                        // Unparsable parts are tobj's to refuse.
                        let Ok(x) = part.parse::<i64>() else { continue };
                        let ok = match x {
                            0 => false,
                            x if x > 0 => x <= total[k],
                            x => x.checked_neg().is_some_and(|m| m <= so_far[k]),
                        };
                        if !ok {
                            return Err(format!(
                                "line {n}: {} index {x} is out of range ({} {}s {})",
                                KIND[k],
                                if x < 0 { so_far[k] } else { total[k] },
                                KIND[k],
                                if x < 0 { "before it" } else { "in the file" }
                            ));
                        }
                    }
                }
            }
            _ => {}
        }
    }
    Ok(())
}

/// Check what tobj's MTL parser would panic on: a colour statement (`Ka`, `Kd`, `Ks`,
/// `Ke`) with fewer than three values.
fn precheck_mtl(bytes: &[u8]) -> std::result::Result<(), String> {
    for (n, line) in text_lines(bytes) {
        let mut words = line.split_whitespace();
        if let Some(key @ ("Ka" | "Kd" | "Ks" | "Ke")) = words.next()
            && words.count() < 3
        {
            return Err(format!("line {n}: {key} needs three numbers"));
        }
    }
    Ok(())
}

/// Split off the first whitespace-separated word; returns (word, trimmed rest).
fn split_word(s: &str) -> (&str, &str) {
    let s = s.trim_start();
    match s.find(char::is_whitespace) {
        Some(i) => (
            s.get(..i).unwrap_or(s),
            s.get(i..).unwrap_or("").trim_start(),
        ),
        None => (s, ""),
    }
}

/// Parse an MTL colour: three numbers, or one number meaning grey (`Tf 0.9`).
fn parse_vec3(s: &str) -> Option<Vec3> {
    let v: Vec<f32> = s
        .split_whitespace()
        .map(str::parse::<f32>)
        .collect::<std::result::Result<_, _>>()
        .ok()?;
    match v.as_slice() {
        [g] => Some(Vec3::splat(*g)),
        [r, g, b] => Some(Vec3::new(*r, *g, *b)),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn texture_options_are_stripped() {
        assert_eq!(texture_file_name("wood.png"), "wood.png");
        assert_eq!(texture_file_name("my wood.png"), "my wood.png");
        assert_eq!(
            texture_file_name("-s 1 1 1 -clamp on -imfchan r tex/a b.png"),
            "tex/a b.png"
        );
        assert_eq!(texture_file_name("-bm 0.5 n.png"), "n.png");
    }

    #[test]
    fn colours() {
        assert_eq!(parse_vec3("0.5"), Some(Vec3::splat(0.5)));
        assert_eq!(parse_vec3("1 2 3"), Some(Vec3::new(1.0, 2.0, 3.0)));
        assert_eq!(parse_vec3("1 2"), None);
        assert_eq!(parse_vec3("a"), None);
    }
}

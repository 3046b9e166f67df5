//! Partitioning and scene packages: layouts tile the bounds, every triangle is in every
//! domain it touches, kd domains are balanced, a package round trip is exact, and a
//! damaged package is a clear error naming the file.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use dray_core::material::{Material, TexRef};
use dray_core::scene::{Mesh, Scene};
use dray_core::texture::{Filter, Sampler, Texture, Wrap};
use dray_scene::partition::overlap::triangle_overlaps_box;
use dray_scene::partition::package::WriteOptions;
use dray_scene::partition::{
    Aabb, DomainLayout, DomainMesh, LayoutSpec, SceneParts, TriangleSource, open_package,
    partition_in_memory, write_package, write_scene_package,
};
use glam::{Vec2, Vec3, Vec4};

fn load(spec: &str) -> Scene {
    dray_scene::load(spec).unwrap_or_else(|e| panic!("{spec}: {e}"))
}

/// A fresh directory for one test (removed on success).
struct TmpDir(PathBuf);

impl TmpDir {
    fn new(name: &str) -> TmpDir {
        let d = std::env::temp_dir().join(format!("dray-partition-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        TmpDir(d)
    }
}

impl Drop for TmpDir {
    fn drop(&mut self) {
        if !std::thread::panicking() {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }
}

/// Deterministic points for probing.
struct Rng(u64);
impl Rng {
    fn f(&mut self) -> f32 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (self.0 >> 40) as f32 / (1u64 << 24) as f32
    }
}

fn layout_for(scene: &Scene, spec: LayoutSpec) -> DomainLayout {
    DomainLayout::for_source(scene, &spec).unwrap()
}

fn bounds_of(scene: &Scene) -> Aabb {
    let (lo, hi) = scene.bounds();
    Aabb::new(lo, hi)
}

#[test]
fn layouts_tile_the_bounds_and_locate_agrees() {
    let mut rng = Rng(1);
    for spec_name in ["soup:2000", "cornell"] {
        let scene = load(spec_name);
        let b = bounds_of(&scene);
        for spec in [
            LayoutSpec::Grid([3, 2, 4]),
            LayoutSpec::GridCount(6),
            LayoutSpec::Kd(1),
            LayoutSpec::Kd(7),
            LayoutSpec::Kd(8),
        ] {
            let l = layout_for(&scene, spec);
            let what = format!("{spec_name} {spec:?}");
            assert_eq!(l.domain_count() as u64, spec.domain_count(), "{what}");
            assert_eq!(l.scene_bounds(), b, "{what}");
            // Boxes lie in the bounds, their volumes add up, and interiors are disjoint.
            let mut volume = 0.0;
            for (i, bi) in l.boxes().iter().enumerate() {
                assert!(
                    !bi.is_empty() && b.contains(bi.min) && b.contains(bi.max),
                    "{what}"
                );
                volume += bi.volume();
                for bj in &l.boxes()[i + 1..] {
                    let lo = bi.min.max(bj.min);
                    let hi = bi.max.min(bj.max);
                    let e = (hi - lo).max(Vec3::ZERO);
                    assert!(
                        e.x * e.y * e.z == 0.0,
                        "{what}: boxes {bi:?} and {bj:?} overlap"
                    );
                }
            }
            assert!(
                (volume - b.volume()).abs() <= 1e-5 * b.volume(),
                "{what}: domains cover {volume} of {}",
                b.volume()
            );
            // The core's ray walker sees the same domains.
            let tree = l.to_domain_tree();
            let tree_boxes: Vec<Aabb> = tree
                .domain_bounds()
                .into_iter()
                .map(|(lo, hi)| Aabb::new(lo, hi))
                .collect();
            assert_eq!(tree_boxes, l.boxes(), "{what}");
            if let LayoutSpec::Grid(dims) = spec {
                let core = dray_core::domain::DomainTree::grid(b.min, b.max, dims);
                assert_eq!(core, tree, "{what}");
            }
            // Random points, box corners and wall points all locate to a box holding them.
            let mut probes: Vec<Vec3> = (0..5000)
                .map(|_| b.min + b.extent() * Vec3::new(rng.f(), rng.f(), rng.f()))
                .collect();
            for bx in l.boxes() {
                probes.push(bx.min);
                probes.push(bx.max);
                probes.push((bx.min + bx.max) * 0.5);
                probes.push(Vec3::new(bx.min.x, (bx.min.y + bx.max.y) * 0.5, bx.max.z));
            }
            for p in probes {
                let d = l
                    .locate(p)
                    .unwrap_or_else(|| panic!("{what}: {p} in the bounds has no domain"));
                assert_eq!(tree.locate(p), Some(d), "{what}: {p}");
                assert!(l.bounds(d).contains(p), "{what}: {p} located in {d}");
                // Strictly inside a box: located there.
                for (k, bx) in l.boxes().iter().enumerate() {
                    if p.cmpgt(bx.min).all() && p.cmplt(bx.max).all() {
                        assert_eq!(d, k as u32, "{what}: {p}");
                    }
                }
            }
            for p in [
                b.min - Vec3::splat(1.0),
                b.max + Vec3::new(0.0, 1.0, 0.0),
                Vec3::NAN,
            ] {
                assert_eq!(l.locate(p), None, "{what}: {p}");
            }
        }
    }
}

/// The domains of each global triangle id.
fn domains_by_triangle(parts: &[DomainMesh], n: usize) -> Vec<BTreeSet<u32>> {
    let mut by = vec![BTreeSet::new(); n];
    for dm in parts {
        for &g in &dm.global_ids {
            assert!(
                by[g as usize].insert(dm.domain),
                "triangle {g} twice in one domain"
            );
        }
    }
    by
}

fn check_assignment(scene: &Scene, layout: &DomainLayout, what: &str) {
    let parts = partition_in_memory(scene, layout).unwrap();
    assert_eq!(parts.len() as u32, layout.domain_count());
    let n = scene.mesh.triangle_count();
    // Stored triangles are the source's, bit for bit.
    for dm in &parts {
        assert_eq!(dm.global_ids.len(), dm.mesh.indices.len());
        for (t, &g) in dm.global_ids.iter().enumerate() {
            let local = dm.mesh.corners(t);
            let global = scene.mesh.corners(g as usize);
            assert_eq!(
                local.map(|p| p.to_array().map(f32::to_bits)),
                global.map(|p| p.to_array().map(f32::to_bits))
            );
            assert_eq!(dm.mesh.material[t], scene.mesh.material[g as usize]);
        }
    }
    let by = domains_by_triangle(&parts, n);
    let eps = layout.epsilon();
    let mut rng = Rng(9);
    for (g, set) in by.iter().enumerate() {
        assert!(!set.is_empty(), "{what}: triangle {g} is in no domain");
        let tri = scene.mesh.corners(g);
        let tb = Aabb::of_triangle(&tri);
        for d in 0..layout.domain_count() {
            let grown = layout.bounds(d).expanded(eps);
            // Exactly the domains the (brute-force) overlap test picks…
            assert_eq!(
                set.contains(&d),
                triangle_overlaps_box(&tri, &grown),
                "{what}: triangle {g} vs domain {d}"
            );
            // …which are among those its bounds touch…
            if set.contains(&d) {
                assert!(
                    grown.overlaps(&tb),
                    "{what}: triangle {g} in far domain {d}"
                );
            }
        }
        // …and include every domain that holds any point of the triangle (independent of
        // the separating-axis code).
        for _ in 0..8 {
            let (mut u, mut v) = (rng.f(), rng.f());
            if u + v > 1.0 {
                (u, v) = (1.0 - u, 1.0 - v);
            }
            let p = tri[0] + (tri[1] - tri[0]) * u + (tri[2] - tri[0]) * v;
            for d in 0..layout.domain_count() {
                if layout.bounds(d).expanded(eps * 0.5).contains(p) {
                    assert!(set.contains(&d), "{what}: triangle {g} has a point in {d}");
                }
            }
        }
    }
}

#[test]
fn every_triangle_is_in_every_domain_it_overlaps() {
    let scene = load("soup:3000");
    for spec in [LayoutSpec::Grid([3, 3, 3]), LayoutSpec::Kd(9)] {
        let l = layout_for(&scene, spec);
        check_assignment(&scene, &l, &format!("soup {spec:?}"));
    }
    // Far from the origin rounding grows with the coordinates; so does the epsilon.
    let mut far = load("spheres:4");
    far.translate(Vec3::new(1.0e5, -2.0e4, 3.0e3));
    let l = layout_for(&far, LayoutSpec::Kd(6));
    assert!(l.epsilon() >= 1.0e5 * dray_scene::partition::layout::EPSILON_FRACTION);
    check_assignment(&far, &l, "far spheres kd 6");
}

fn tri_scene(tris: &[[Vec3; 3]]) -> Scene {
    let mut mesh = Mesh::default();
    for t in tris {
        let b = mesh.push_vertices(t);
        mesh.indices.push([b, b + 1, b + 2]);
        mesh.material.push(0);
    }
    Scene {
        name: "tris".into(),
        mesh,
        materials: vec![Material::default()],
        ..Scene::default()
    }
}

#[test]
fn triangles_on_or_near_a_wall_are_in_both_neighbours() {
    let big = [
        [
            Vec3::ZERO,
            Vec3::new(2.0, 0.0, 0.0),
            Vec3::new(0.0, 2.0, 2.0),
        ],
        [
            Vec3::new(2.0, 2.0, 2.0),
            Vec3::new(0.0, 2.0, 2.0),
            Vec3::new(2.0, 0.0, 0.0),
        ],
    ];
    let wall = |x: f32| {
        [
            Vec3::new(x, 0.5, 0.5),
            Vec3::new(x, 0.6, 0.5),
            Vec3::new(x, 0.5, 0.6),
        ]
    };
    let above = f32::from_bits(1.0f32.to_bits() + 1);
    let below = f32::from_bits(1.0f32.to_bits() - 1);
    let scene = tri_scene(&[
        big[0],
        big[1],
        wall(1.0),
        wall(above),
        wall(below),
        wall(1.01),
        wall(0.99),
    ]);
    let layout = layout_for(&scene, LayoutSpec::Grid([2, 1, 1]));
    let by = domains_by_triangle(&partition_in_memory(&scene, &layout).unwrap(), 7);
    let both: BTreeSet<u32> = [0, 1].into();
    assert_eq!(by[2], both, "on the wall");
    assert_eq!(by[3], both, "one ulp above");
    assert_eq!(by[4], both, "one ulp below");
    assert_eq!(by[5], [1].into(), "clearly above");
    assert_eq!(by[6], [0].into(), "clearly below");
    // A diagonal triangle whose bounds touch a domain it does not cross stays out of it.
    let diag = [
        Vec3::ZERO,
        Vec3::new(1.8, 0.0, 0.0),
        Vec3::new(0.0, 1.8, 0.0),
    ];
    let corner = [
        Vec3::new(2.0, 2.0, 0.0),
        Vec3::new(1.9, 2.0, 0.0),
        Vec3::new(2.0, 1.9, 0.0),
    ];
    let scene = tri_scene(&[
        diag,
        corner,
        [Vec3::ZERO, Vec3::splat(2.0), Vec3::new(0.0, 2.0, 2.0)],
    ]);
    let layout = layout_for(&scene, LayoutSpec::Grid([2, 2, 1]));
    let by = domains_by_triangle(&partition_in_memory(&scene, &layout).unwrap(), 3);
    assert_eq!(by[0], [0, 1, 2].into(), "the diagonal skips the far cell");
}

#[test]
fn kd_domains_are_balanced() {
    let scene = load("soup:20000");
    let layout = layout_for(&scene, LayoutSpec::Kd(8));
    let parts = partition_in_memory(&scene, &layout).unwrap();
    let counts: Vec<usize> = parts.iter().map(|p| p.triangle_count()).collect();
    let mean = counts.iter().sum::<usize>() as f64 / counts.len() as f64;
    let (min, max) = (*counts.iter().min().unwrap(), *counts.iter().max().unwrap());
    eprintln!("kd 8 on soup:20000: {counts:?}");
    // Centroids split exactly 2500 per domain; triangles straddling planes add copies.
    assert!(
        min as f64 >= 0.85 * mean && max as f64 <= 1.15 * mean,
        "{counts:?}"
    );
    assert!(min >= 2500, "{counts:?}");
    // Odd counts split proportionally too.
    let layout = layout_for(&scene, LayoutSpec::Kd(5));
    let parts = partition_in_memory(&scene, &layout).unwrap();
    let counts: Vec<usize> = parts.iter().map(|p| p.triangle_count()).collect();
    let mean = counts.iter().sum::<usize>() as f64 / 5.0;
    assert!(
        counts
            .iter()
            .all(|&c| (c as f64 - mean).abs() <= 0.15 * mean),
        "{counts:?}"
    );
}

/// A small scene with everything a manifest stores: a texture, textured and masked
/// materials, attributes, lights, cameras and an environment.
fn rich_scene() -> Scene {
    let mut scene = load("cornell:glass");
    let n = scene.mesh.positions.len();
    for i in 0..n {
        scene.mesh.normals[i] = Vec3::new(0.0, 1.0, 0.0);
        scene.mesh.uvs[i] = Vec2::new(i as f32 * 0.1, 0.3);
        scene.mesh.tangents[i] = Vec4::new(1.0, 0.0, 0.0, -1.0);
    }
    scene.textures.push(Texture {
        name: "checker".into(),
        width: 2,
        height: 3,
        texels: (0..6).map(|i| [i * 40, 255 - i * 40, 7, 255]).collect(),
        sampler: Sampler {
            wrap_s: Wrap::MirroredRepeat,
            wrap_t: Wrap::ClampToEdge,
            filter: Filter::Nearest,
        },
    });
    scene.materials.push(Material {
        base_color_tex: Some(TexRef::new(0)),
        alpha_mode: dray_core::material::AlphaMode::Mask { cutoff: 0.3 },
        roughness: 0.1,
        ..Material::default()
    });
    let m = scene.materials.len() as u32 - 1;
    scene.mesh.material[0] = m;
    scene.environment = Some(Vec3::new(0.1, 0.2, 0.3));
    scene.stats.warnings.push("a warning".into());
    scene
}

/// Every vertex attribute of `m` as raw bits (so -0.0 and NaN payloads count), with the
/// vertex count first.
fn bits(m: &Mesh) -> Vec<u32> {
    let mut out = vec![m.positions.len() as u32];
    out.extend(
        m.positions
            .iter()
            .flat_map(|v| v.to_array())
            .map(f32::to_bits),
    );
    out.extend(
        m.normals
            .iter()
            .flat_map(|v| v.to_array())
            .map(f32::to_bits),
    );
    out.extend(
        m.tangents
            .iter()
            .flat_map(|v| v.to_array())
            .map(f32::to_bits),
    );
    out.extend(m.uvs.iter().flat_map(|v| v.to_array()).map(f32::to_bits));
    out.push(m.uvs2.len() as u32);
    out.extend(m.uvs2.iter().flat_map(|v| v.to_array()).map(f32::to_bits));
    out.push(m.colors.len() as u32);
    out.extend(m.colors.iter().flat_map(|v| v.to_array()).map(f32::to_bits));
    out
}

/// [`rich_scene`] with vertex colours on every other vertex (white on the rest).
fn coloured_scene() -> Scene {
    let mut scene = rich_scene();
    let n = scene.mesh.positions.len();
    scene.mesh.colors = (0..n)
        .map(|i| {
            if i % 2 == 0 {
                Vec4::new(0.1 * (i % 10) as f32, 0.5, 1.0, 0.75)
            } else {
                Vec4::ONE
            }
        })
        .collect();
    scene
}

/// [`coloured_scene`] with a second UV set on a third of the vertices (zero on the rest)
/// and a material whose emissive texture reads it.
fn two_set_scene() -> Scene {
    let mut scene = coloured_scene();
    let n = scene.mesh.positions.len();
    scene.mesh.uvs2 = (0..n)
        .map(|i| {
            if i % 3 == 0 {
                Vec2::new(0.5, 0.05 * (i % 20) as f32)
            } else {
                Vec2::ZERO
            }
        })
        .collect();
    scene.materials.push(Material {
        base_color_tex: Some(TexRef::new(0)),
        emissive: Vec3::ONE,
        emissive_tex: Some(TexRef {
            tex_coord: 1,
            second_uv: true,
            ..TexRef::new(0)
        }),
        ..Material::default()
    });
    let m = scene.materials.len() as u32 - 1;
    scene.mesh.material[1] = m;
    scene
}

fn write(dir: &Path, scene: &Scene, spec: LayoutSpec) {
    // A tiny spill buffer forces many flushes per domain.
    let options = WriteOptions {
        buffer_bytes: 1,
        ..WriteOptions::default()
    };
    write_package(dir, SceneParts::of(scene), scene, &spec, &options).unwrap();
}

#[test]
fn package_round_trip_is_exact() {
    for (name, scene, spec) in [
        ("rich-kd", rich_scene(), LayoutSpec::Kd(5)),
        ("rich-grid", rich_scene(), LayoutSpec::Grid([2, 2, 1])),
        ("soup-kd", load("soup:5000"), LayoutSpec::Kd(6)),
        ("coloured-kd", coloured_scene(), LayoutSpec::Kd(5)),
        ("two-sets-kd", two_set_scene(), LayoutSpec::Kd(5)),
        (
            "two-sets-grid",
            two_set_scene(),
            LayoutSpec::Grid([2, 2, 1]),
        ),
    ] {
        let tmp = TmpDir::new(name);
        write(&tmp.0, &scene, spec);
        let pkg = open_package(&tmp.0).unwrap();
        pkg.verify().unwrap();
        let layout = layout_for(&scene, spec);
        assert_eq!(pkg.layout(), &layout, "{name}");
        assert_eq!(pkg.name(), scene.name);
        assert_eq!(pkg.materials(), scene.materials.as_slice());
        assert_eq!(pkg.lights(), scene.lights.as_slice());
        assert_eq!(pkg.cameras(), scene.cameras.as_slice());
        assert_eq!(pkg.environment(), scene.environment);
        assert_eq!(pkg.load_textures().unwrap(), scene.textures);
        let m = pkg.manifest();
        assert_eq!(m.source_triangles, scene.mesh.triangle_count() as u64);
        assert_eq!(m.stats.warnings, scene.stats.warnings);
        assert_eq!(m.material_triangles.iter().sum::<u64>(), m.source_triangles);
        let memory = partition_in_memory(&scene, &layout).unwrap();
        let mut assigned = 0;
        for (d, mem) in memory.iter().enumerate() {
            let disk = pkg.load_domain(d as u32).unwrap();
            assert_eq!(bits(&disk.mesh), bits(&mem.mesh), "{name} domain {d}");
            assert_eq!(disk.mesh.indices, mem.mesh.indices);
            assert_eq!(disk.mesh.material, mem.mesh.material);
            assert_eq!(disk.global_ids, mem.global_ids);
            assert_eq!(disk.bounds, mem.bounds);
            assigned += disk.triangle_count() as u64;
        }
        assert_eq!(assigned, m.assigned_triangles);
        // Vertex colours travel only where the scene has them: colourless scenes keep
        // no colour array in any domain (no memory, no bytes on disk).
        let coloured = (0..pkg.domain_count())
            .filter(|&d| !pkg.load_domain(d).unwrap().mesh.colors.is_empty())
            .count();
        assert_eq!(coloured > 0, !scene.mesh.colors.is_empty(), "{name}");
        // So does a second UV set, and only a package with one is format version 3
        // (earlier dray refuses it rather than render its textures on the wrong set).
        let two_sets = (0..pkg.domain_count())
            .filter(|&d| !pkg.load_domain(d).unwrap().mesh.uvs2.is_empty())
            .count();
        assert_eq!(two_sets > 0, !scene.mesh.uvs2.is_empty(), "{name}");
        assert_eq!(
            m.domains.iter().filter(|e| e.uvs2).count(),
            two_sets,
            "{name}"
        );
        let text = std::fs::read_to_string(tmp.0.join("manifest.json")).unwrap();
        let version = if scene.mesh.uvs2.is_empty() { 2 } else { 3 };
        assert!(
            text.contains(&format!("\"version\": {version},")),
            "{name}: {}",
            &text[..120]
        );
        assert_eq!(
            text.contains("uvs2") || text.contains("second_uv"),
            version == 3,
            "{name}"
        );
        assert!(pkg.load_domain(pkg.domain_count()).is_err());
    }
}

/// Domains whose tangents (or uvs) are all zero leave the section out, 16 (8) bytes a
/// vertex, and read back bit for bit; a single non-zero bit (-0.0 too) keeps it.
#[test]
fn all_zero_tangents_and_uvs_are_left_out_and_read_back() {
    let iso = load("iso:gyroid:12");
    assert!(iso.mesh.tangents.iter().all(|t| *t == Vec4::ZERO));
    assert!(iso.mesh.uvs.iter().all(|u| *u == Vec2::ZERO));
    let mut signed = iso.clone();
    signed.mesh.tangents[0].w = -0.0;
    let mut uv = iso.clone();
    uv.mesh.uvs[0].x = 0.5;
    for (name, scene, tangents, uvs) in [
        ("iso", &iso, false, false),
        ("signed", &signed, true, false),
        ("uv", &uv, false, true),
    ] {
        let tmp = TmpDir::new(&format!("sections-{name}"));
        let spec = LayoutSpec::Kd(1);
        write(&tmp.0, scene, spec);
        let pkg = open_package(&tmp.0).unwrap();
        pkg.verify().unwrap();
        let e = &pkg.manifest().domains[0];
        assert_eq!((e.no_tangents, e.no_uvs), (!tangents, !uvs), "{name}");
        let v = e.vertices;
        let full = 32 + 48 * v + 20 * e.triangles;
        let left_out = if tangents { 0 } else { 16 * v } + if uvs { 0 } else { 8 * v };
        assert_eq!(e.bytes, full - left_out, "{name}");
        let disk = pkg.load_domain(0).unwrap();
        let mem = partition_in_memory(scene, &layout_for(scene, spec)).unwrap();
        assert_eq!(bits(&disk.mesh), bits(&mem[0].mesh), "{name}");
        assert_eq!(disk.mesh.indices, mem[0].mesh.indices, "{name}");
    }
    // The flags are part of the size check: a manifest that says the tangents are there
    // when the file left them out is refused on opening.
    let tmp = TmpDir::new("sections-lie");
    write(&tmp.0, &iso, LayoutSpec::Kd(1));
    let mut m = open_package(&tmp.0).unwrap().manifest().clone();
    m.domains[0].no_tangents = false;
    let lie = dray_scene::partition::manifest::encode(&m).unwrap();
    std::fs::write(tmp.0.join("manifest.json"), lie).unwrap();
    let e = open_package(&tmp.0).err().unwrap().to_string();
    assert!(e.contains("cannot hold"), "{e}");
}

#[test]
fn rewriting_replaces_a_package_but_never_clobbers_other_files() {
    let tmp = TmpDir::new("rewrite");
    let scene = load("soup:500");
    write_scene_package(&tmp.0, &scene, &LayoutSpec::Kd(4)).unwrap();
    let s = write_scene_package(&tmp.0, &scene, &LayoutSpec::Grid([2, 1, 1])).unwrap();
    assert_eq!(s.domains, 2);
    assert!(
        !tmp.0.join("domain-00003.bin").exists(),
        "stale domain file left"
    );
    let pkg = open_package(&tmp.0).unwrap();
    pkg.verify().unwrap();
    std::fs::write(tmp.0.join("notes.txt"), "mine").unwrap();
    let e = write_scene_package(&tmp.0, &scene, &LayoutSpec::Kd(2))
        .unwrap_err()
        .to_string();
    assert!(e.contains("notes.txt") && e.contains("refusing"), "{e}");
    assert!(tmp.0.join("notes.txt").exists());
}

/// A written package to damage.
fn damaged(name: &str) -> (TmpDir, Scene) {
    let tmp = TmpDir::new(name);
    let scene = rich_scene();
    write(&tmp.0, &scene, LayoutSpec::Kd(4));
    (tmp, scene)
}

fn load_err(dir: &Path, d: u32) -> String {
    let pkg = open_package(dir).unwrap();
    pkg.load_domain(d).unwrap_err().to_string()
}

#[test]
fn a_flipped_byte_in_a_domain_is_a_checksum_error_naming_the_file() {
    let (tmp, _) = damaged("flip");
    let f = tmp.0.join("domain-00001.bin");
    let mut bytes = std::fs::read(&f).unwrap();
    let mid = bytes.len() / 2;
    bytes[mid] ^= 0x10;
    std::fs::write(&f, bytes).unwrap();
    let e = load_err(&tmp.0, 1);
    assert!(
        e.contains("domain-00001.bin") && e.contains("checksum mismatch"),
        "{e}"
    );
    assert!(open_package(&tmp.0).unwrap().verify().is_err());
    // Other domains still load.
    open_package(&tmp.0).unwrap().load_domain(0).unwrap();
}

#[test]
fn a_truncated_domain_is_an_error_naming_the_file() {
    let (tmp, _) = damaged("truncate");
    let f = tmp.0.join("domain-00002.bin");
    let bytes = std::fs::read(&f).unwrap();
    std::fs::write(&f, &bytes[..bytes.len() - 7]).unwrap();
    let e = load_err(&tmp.0, 2);
    assert!(
        e.contains("domain-00002.bin") && e.contains("truncated"),
        "{e}"
    );
    std::fs::write(&f, &bytes[..10]).unwrap();
    let e = load_err(&tmp.0, 2);
    assert!(
        e.contains("domain-00002.bin") && e.contains("truncated"),
        "{e}"
    );
}

#[test]
fn a_bogus_header_count_is_refused_without_allocating() {
    let (tmp, _) = damaged("header");
    let f = tmp.0.join("domain-00000.bin");
    let mut bytes = std::fs::read(&f).unwrap();
    bytes[24..32].copy_from_slice(&u64::MAX.to_le_bytes());
    std::fs::write(&f, &bytes).unwrap();
    let e = load_err(&tmp.0, 0);
    assert!(
        e.contains("domain-00000.bin") && e.contains("corrupt"),
        "{e}"
    );
    bytes[..8].copy_from_slice(b"NOTDRAY!");
    std::fs::write(&f, &bytes).unwrap();
    let e = load_err(&tmp.0, 0);
    assert!(e.contains("domain-00000.bin") && e.contains("magic"), "{e}");
}

#[test]
fn a_missing_domain_file_is_an_error_naming_it() {
    let (tmp, _) = damaged("missing");
    std::fs::remove_file(tmp.0.join("domain-00003.bin")).unwrap();
    let e = load_err(&tmp.0, 3);
    assert!(e.contains("domain-00003.bin"), "{e}");
    let e = open_package(&tmp.0)
        .unwrap()
        .verify()
        .unwrap_err()
        .to_string();
    assert!(e.contains("domain-00003.bin"), "{e}");
}

fn edit_manifest(dir: &Path, f: impl FnOnce(&mut serde_json::Value)) {
    let p = dir.join("manifest.json");
    let mut v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap();
    f(&mut v);
    std::fs::write(&p, serde_json::to_string_pretty(&v).unwrap()).unwrap();
}

#[test]
fn a_wrong_version_is_a_version_error() {
    let (tmp, _) = damaged("version");
    edit_manifest(&tmp.0, |v| v["version"] = 99.into());
    let e = open_package(&tmp.0).unwrap_err().to_string();
    assert!(
        e.contains("manifest.json") && e.contains("version 99 is not supported"),
        "{e}"
    );
    edit_manifest(&tmp.0, |v| v["format"] = "something-else".into());
    let e = open_package(&tmp.0).unwrap_err().to_string();
    assert!(e.contains("not a dray scene package"), "{e}");
    // A domain file of another version.
    let (tmp, _) = damaged("version-domain");
    let f = tmp.0.join("domain-00000.bin");
    let mut bytes = std::fs::read(&f).unwrap();
    bytes[8..12].copy_from_slice(&7u32.to_le_bytes());
    std::fs::write(&f, &bytes).unwrap();
    let e = load_err(&tmp.0, 0);
    assert!(
        e.contains("domain-00000.bin") && e.contains("version 7"),
        "{e}"
    );
}

/// A package with a second UV set is format version 3, which this dray reads along with
/// version 2; one relabelled as version 2 (what earlier dray reads, and would misread)
/// is refused, and so is a domain file whose header disagrees with its manifest entry.
#[test]
fn a_second_uv_set_is_format_version_3() {
    let tmp = TmpDir::new("uvs2-version");
    write(&tmp.0, &two_set_scene(), LayoutSpec::Kd(1));
    open_package(&tmp.0).unwrap().verify().unwrap();
    let p = tmp.0.join("manifest.json");
    let text = std::fs::read_to_string(&p).unwrap();
    assert!(text.contains("\"version\": 3,"), "{text}");
    let f = tmp.0.join("domain-00000.bin");
    let bytes = std::fs::read(&f).unwrap();
    assert_eq!(bytes[8..12], 3u32.to_le_bytes());

    std::fs::write(&p, text.replacen("\"version\": 3,", "\"version\": 2,", 1)).unwrap();
    let e = open_package(&tmp.0).unwrap_err().to_string();
    assert!(
        e.contains("manifest.json") && e.contains("second UV set") && e.contains("version 3"),
        "{e}"
    );
    std::fs::write(&p, text.replacen("\"version\": 3,", "\"version\": 1,", 1)).unwrap();
    let e = open_package(&tmp.0).unwrap_err().to_string();
    assert!(e.contains("version 1 is not supported"), "{e}");

    std::fs::write(&p, &text).unwrap();
    let mut damaged = bytes.clone();
    damaged[8..12].copy_from_slice(&2u32.to_le_bytes());
    std::fs::write(&f, &damaged).unwrap();
    let e = load_err(&tmp.0, 0);
    assert!(
        e.contains("domain-00000.bin") && e.contains("version 2"),
        "{e}"
    );
}

#[test]
fn a_damaged_manifest_is_refused() {
    let (tmp, _) = damaged("manifest");
    let p = tmp.0.join("manifest.json");
    let text = std::fs::read_to_string(&p).unwrap();
    // Change one digit of the first material's roughness in the body.
    let key = "\"roughness\":";
    let at = text.find(key).unwrap() + key.len();
    let at = at + text[at..].find(|c: char| c.is_ascii_digit()).unwrap();
    let mut bytes = text.into_bytes();
    bytes[at] = if bytes[at] == b'0' { b'1' } else { b'0' };
    std::fs::write(&p, &bytes).unwrap();
    let e = open_package(&tmp.0).unwrap_err().to_string();
    assert!(
        e.contains("manifest.json") && e.contains("checksum mismatch"),
        "{e}"
    );
    std::fs::write(&p, "{ not json").unwrap();
    let e = open_package(&tmp.0).unwrap_err().to_string();
    assert!(
        e.contains("manifest.json") && e.contains("invalid JSON"),
        "{e}"
    );
    std::fs::remove_file(&p).unwrap();
    let e = open_package(&tmp.0).unwrap_err().to_string();
    assert!(e.contains("manifest.json"), "{e}");
}

/// Edit the manifest body and re-sign it, as a buggy or hostile writer would.
fn resign(dir: &Path, f: impl FnOnce(&mut serde_json::Value)) {
    use dray_scene::partition::checksum::{checksum, to_hex};
    let p = dir.join("manifest.json");
    let mut v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap();
    f(&mut v["body"]);
    let body = serde_json::to_string_pretty(&v["body"]).unwrap();
    let text = format!(
        "{{\"format\": {}, \"version\": {}, \"body_xxh3\": \"{}\", \"body\": {body}}}",
        v["format"],
        v["version"],
        to_hex(checksum(body.as_bytes()))
    );
    std::fs::write(&p, text).unwrap();
}

#[test]
fn a_signed_but_inconsistent_manifest_is_refused() {
    // Counts no file could hold: refused when opening, before any allocation.
    let (tmp, _) = damaged("lying-counts");
    resign(&tmp.0, |b| {
        b["domains"][0]["triangles"] = (1u64 << 40).into()
    });
    let e = open_package(&tmp.0).unwrap_err().to_string();
    assert!(e.contains("manifest.json") && e.contains("domain 0"), "{e}");
    // A path instead of a domain file name.
    let (tmp, _) = damaged("traversal");
    resign(&tmp.0, |b| {
        b["domains"][1]["file"] = "../../etc/passwd".into()
    });
    let e = open_package(&tmp.0).unwrap_err().to_string();
    assert!(e.contains("domain 1"), "{e}");
    // A material pointing at a texture that does not exist.
    let (tmp, _) = damaged("texref");
    resign(&tmp.0, |b| {
        let last = b["materials"].as_array().unwrap().len() - 1;
        b["materials"][last]["base_color_tex"]["texture"] = 9.into();
    });
    let e = open_package(&tmp.0).unwrap_err().to_string();
    assert!(e.contains("texture 9"), "{e}");
    // A layout whose tree is not a tree.
    let (tmp, _) = damaged("tree");
    resign(&tmp.0, |b| {
        b["layout"]["nodes"][0]["split"]["left"] = 0.into()
    });
    let e = open_package(&tmp.0).unwrap_err().to_string();
    assert!(e.contains("layout"), "{e}");
    // The signed manifest itself still opens when nothing was changed.
    let (tmp, _) = damaged("resigned");
    resign(&tmp.0, |_| {});
    open_package(&tmp.0).unwrap().verify().unwrap();
}

#[test]
fn corrupt_textures_are_refused() {
    let (tmp, _) = damaged("textures");
    let f = tmp.0.join("textures.bin");
    let mut bytes = std::fs::read(&f).unwrap();
    let last = bytes.len() - 1;
    bytes[last] ^= 1;
    std::fs::write(&f, &bytes).unwrap();
    let e = open_package(&tmp.0)
        .unwrap()
        .load_textures()
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("textures.bin") && e.contains("checksum mismatch"),
        "{e}"
    );
}

#[test]
fn layout_json_is_compact_enough_for_every_worker() {
    let scene = load("soup:2000");
    let l = layout_for(&scene, LayoutSpec::Kd(64));
    let json = serde_json::to_string(&l).unwrap();
    assert!(json.len() < 64 * 400, "{} bytes", json.len());
    let back: DomainLayout = serde_json::from_str(&json).unwrap();
    assert_eq!(back, l);
}

/// A grid streamed copy by copy (as `dray partition` does, so only the base model is in
/// memory) gives the very package the grid made in memory gives: same manifest, which
/// records every domain file's checksum.
#[test]
fn a_streamed_grid_writes_the_same_package_as_the_grid_in_memory() {
    for spec in ["grid:cornell:3x2x2", "grid:spheres:5:2x1x3"] {
        let source = dray_scene::procedural::stream(spec, &dray_scene::load)
            .unwrap()
            .expect("grid specs stream");
        let scene = dray_scene::load(spec).unwrap();
        assert!(scene.mesh.triangle_count() > 0);
        assert_streams_like_memory(
            &source,
            source.tables(),
            &scene,
            &LayoutSpec::Kd(7),
            &format!("grid-{}", spec.len()),
        );
    }
}

/// A source that hides its [`TriangleSource::lookup`], so the package writer must spill
/// whole triangles.
struct StreamOnly<'a>(&'a dyn TriangleSource);

impl TriangleSource for StreamOnly<'_> {
    fn for_each_triangle(
        &self,
        f: &mut dyn FnMut(&dray_scene::partition::SourceTriangle) -> dray_scene::Result<()>,
    ) -> dray_scene::Result<()> {
        self.0.for_each_triangle(f)
    }

    fn has_colors(&self) -> bool {
        self.0.has_colors()
    }

    fn has_uvs2(&self) -> bool {
        self.0.has_uvs2()
    }
}

/// Spilling global ids and making the triangles again from the source's lookup writes
/// the very package that spilling whole triangles writes: every attribute (tangents, uvs,
/// colours), for scenes in memory and streamed grids, with many flushes per domain.
#[test]
fn spilling_ids_writes_the_same_package_as_spilling_triangles() {
    let grid = dray_scene::procedural::stream("grid:cornell:glass:3x2x2", &dray_scene::load)
        .unwrap()
        .expect("grid specs stream");
    let (rich, coloured, two_sets) = (rich_scene(), coloured_scene(), two_set_scene());
    let cases: [(&str, &dyn TriangleSource, &Scene); 4] = [
        ("rich", &rich, &rich),
        ("coloured", &coloured, &coloured),
        ("two-sets", &two_sets, &two_sets),
        ("grid", &grid, grid.tables()),
    ];
    for (name, source, tables) in cases {
        assert!(source.lookup().is_some(), "{name} has a lookup");
        let (ids, records) = (
            TmpDir::new(&format!("ids-{name}")),
            TmpDir::new(&format!("records-{name}")),
        );
        let options = WriteOptions {
            buffer_bytes: 1,
            ..WriteOptions::default()
        };
        let spec = LayoutSpec::Kd(5);
        let parts = SceneParts::of(tables);
        let a = write_package(&ids.0, parts, source, &spec, &options).unwrap();
        let b = write_package(&records.0, parts, &StreamOnly(source), &spec, &options).unwrap();
        assert_eq!(a.bytes, b.bytes, "{name}");
        assert!(
            a.assigned_triangles > a.source_triangles,
            "{name}: walls cut triangles"
        );
        assert_same_package(&ids.0, &records.0, name);
        open_package(&ids.0).unwrap().verify().unwrap();
    }
}

/// Write a package from the streaming `source` (whose tables are `tables`) and one from
/// `scene` in memory, both cut by `layout`, into fresh directories tagged `tag`, and
/// check every file has the same bytes.
fn assert_streams_like_memory(
    source: &dyn TriangleSource,
    tables: &Scene,
    scene: &Scene,
    layout: &LayoutSpec,
    tag: &str,
) {
    let (a, b) = (
        TmpDir::new(&format!("stream-{tag}")),
        TmpDir::new(&format!("memory-{tag}")),
    );
    write_package(
        &a.0,
        SceneParts::of(tables),
        source,
        layout,
        &WriteOptions::default(),
    )
    .unwrap();
    write_scene_package(&b.0, scene, layout).unwrap();
    assert_same_package(&a.0, &b.0, &format!("{tag} {layout:?}"));
}

/// Every file of package `a` has the same bytes in package `b`, and no file is extra.
fn assert_same_package(a: &Path, b: &Path, what: &str) {
    let files = |d: &Path| -> BTreeSet<std::ffi::OsString> {
        std::fs::read_dir(d)
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect()
    };
    let names = files(a);
    assert_eq!(names, files(b), "{what}: file lists differ");
    assert!(names.len() > 2, "{what}: {names:?}");
    for name in names {
        let (fa, fb) = (a.join(&name), b.join(&name));
        assert!(
            std::fs::read(&fa).unwrap() == std::fs::read(&fb).unwrap(),
            "{what}: {name:?} differs"
        );
    }
}

/// soup, city and iso stream primitive by primitive (as `dray partition` does, so none
/// of them is ever whole in memory) and give the very package their scene made in memory
/// gives, for both layouts: same manifest (which records every domain file's checksum),
/// same domain files.
#[test]
fn streamed_generators_write_the_same_package_as_their_scenes_in_memory() {
    for spec in ["soup:3000", "city:6", "iso:gyroid:16"] {
        let source = dray_scene::procedural::stream(spec, &dray_scene::load)
            .unwrap()
            .unwrap_or_else(|| panic!("{spec} streams"));
        let scene = load(spec);
        assert!(scene.mesh.triangle_count() > 1000, "{spec}");
        for layout in [LayoutSpec::Kd(7), LayoutSpec::GridCount(8)] {
            let name = spec.replace(':', "-");
            assert_streams_like_memory(&source, source.tables(), &scene, &layout, &name);
        }
    }
}

/// A small bumpy sheet as PLY: `n` x `n` vertices, quads, a pentagon, a repeated-index
/// and a zero-area triangle (dropped as degenerate), a two-vertex face (a warning) and
/// an extra element (a warning). ASCII gets texture coordinates, binary little-endian
/// gets normals and an ignored per-vertex property, so both attribute paths are covered.
fn sheet_ply(n: u32, binary: bool) -> Vec<u8> {
    let vertex = |i: u32, j: u32| {
        let (x, y) = (i as f32 / (n - 1) as f32, j as f32 / (n - 1) as f32);
        let z = 0.1 * (7.0 * x).sin() * (5.0 * y).cos();
        Vec3::new(x, y, z)
    };
    let id = |i: u32, j: u32| j * n + i;
    let mut faces: Vec<Vec<u32>> = Vec::new();
    for j in 0..n - 1 {
        for i in 0..n - 1 {
            faces.push(vec![id(i, j), id(i + 1, j), id(i + 1, j + 1), id(i, j + 1)]);
        }
    }
    faces.push(vec![0, 1, 1]); // repeated index
    faces.push(vec![id(0, 0), id(0, 1), id(0, 2)]); // collinear (x = z = 0): zero area
    faces.push(vec![0, 1]); // too short
    faces.push(vec![id(0, 1), id(1, 1), id(2, 2), id(1, 3), id(0, 2)]); // pentagon
    let vertex_props = if binary {
        "property float x\nproperty float y\nproperty float z\nproperty uchar quality\n\
         property float nx\nproperty float ny\nproperty float nz\n"
    } else {
        "property float x\nproperty float y\nproperty float z\nproperty float s\n\
         property float t\n"
    };
    let mut out = format!(
        "ply\nformat {} 1.0\ncomment dray streaming test\nelement vertex {}\n{vertex_props}\
         element face {}\nproperty list uchar int vertex_indices\nelement edge 1\n\
         property int vertex1\nproperty int vertex2\nend_header\n",
        if binary {
            "binary_little_endian"
        } else {
            "ascii"
        },
        n * n,
        faces.len()
    )
    .into_bytes();
    for j in 0..n {
        for i in 0..n {
            let p = vertex(i, j);
            if binary {
                let nrm = Vec3::new(-p.z, 0.3, 1.0); // deliberately not unit length
                for c in [p.x, p.y, p.z] {
                    out.extend_from_slice(&c.to_le_bytes());
                }
                out.push(7);
                for c in [nrm.x, nrm.y, nrm.z] {
                    out.extend_from_slice(&c.to_le_bytes());
                }
            } else {
                let (s, t) = (i as f32 / n as f32, j as f32 / n as f32);
                out.extend_from_slice(format!("{} {} {} {s} {t}\n", p.x, p.y, p.z).as_bytes());
            }
        }
    }
    for f in &faces {
        if binary {
            out.push(f.len() as u8);
            for &i in f {
                out.extend_from_slice(&(i as i32).to_le_bytes());
            }
        } else {
            let idx: Vec<String> = f.iter().map(u32::to_string).collect();
            out.extend_from_slice(format!("{} {}\n", f.len(), idx.join(" ")).as_bytes());
        }
    }
    if binary {
        out.extend_from_slice(&[0, 0, 0, 0, 1, 0, 0, 0]);
    } else {
        out.extend_from_slice(b"0 1\n");
    }
    out
}

/// A PLY file streamed face by face (as `dray partition` does) gives the very package
/// the loaded scene gives, for ASCII and binary files and both layouts, with the same
/// tables (warnings, degenerate count); and it fails, as the loader does, on a bad index.
#[test]
fn streamed_ply_writes_the_same_package_as_the_loaded_scene() {
    let dir = TmpDir::new("ply-stream");
    std::fs::create_dir_all(&dir.0).unwrap();
    for binary in [false, true] {
        let path = dir.0.join(if binary {
            "sheet-bin.ply"
        } else {
            "sheet-ascii.ply"
        });
        std::fs::write(&path, sheet_ply(24, binary)).unwrap();
        let scene = load(path.to_str().unwrap());
        let source = dray_scene::ply_stream::PlySource::open(&path).unwrap();
        let tables = source.tables();
        assert_eq!(tables.name, scene.name);
        assert_eq!(tables.materials, scene.materials);
        assert_eq!(tables.cameras, scene.cameras);
        assert_eq!(tables.lights, scene.lights);
        assert_eq!(tables.environment, scene.environment);
        assert_eq!(tables.stats, scene.stats, "binary={binary}");
        assert_eq!(scene.stats.degenerate_triangles, 2);
        assert_eq!(scene.stats.warnings.len(), 2, "{:?}", scene.stats.warnings);
        assert_eq!(scene.mesh.triangle_count(), 23 * 23 * 2 + 3);
        // Same triangles, in the same order, with the same ids.
        let mut streamed = Vec::new();
        source
            .for_each_triangle(&mut |t| {
                streamed.push(*t);
                Ok(())
            })
            .unwrap();
        let mut loaded = Vec::new();
        scene
            .for_each_triangle(&mut |t| {
                loaded.push(*t);
                Ok(())
            })
            .unwrap();
        assert!(streamed == loaded, "binary={binary}: triangles differ");
        for layout in [LayoutSpec::Kd(7), LayoutSpec::GridCount(8)] {
            let tag = format!("ply-binary-{binary}");
            assert_streams_like_memory(&source, source.tables(), &scene, &layout, &tag);
        }
    }

    // Errors are the loader's.
    let text = String::from_utf8(sheet_ply(4, false)).unwrap();
    for (name, edited) in [
        (
            "badindex.ply",
            text.replacen("\n3 0 1 1\n", "\n3 0 1 99\n", 1),
        ),
        (
            "nan.ply",
            text.replacen("\n0 0 0 0 0\n", "\n0 nan 0 0 0\n", 1),
        ),
        (
            "empty.ply",
            text.replace("element face 13", "element face 0"),
        ),
    ] {
        let path = dir.0.join(name);
        std::fs::write(&path, &edited).unwrap();
        let loaded = dray_scene::load(path.to_str().unwrap()).unwrap_err();
        let streamed = dray_scene::ply_stream::PlySource::open(&path)
            .err()
            .unwrap_or_else(|| panic!("{name} streams"));
        assert_ne!(edited, text, "{name}: the edit did not apply");
        assert_eq!(streamed.to_string(), loaded.to_string());
        assert!(loaded.to_string().contains(name), "{loaded}");
    }
}

/// A file whose face element precedes its vertex element (legal PLY) cannot be resolved
/// face by face; the source loads it whole instead and still gives the loader's triangles.
#[test]
fn ply_with_faces_first_streams_as_the_loaded_scene() {
    let dir = TmpDir::new("ply-faces-first");
    std::fs::create_dir_all(&dir.0).unwrap();
    let path = dir.0.join("faces-first.ply");
    std::fs::write(
        &path,
        "ply\nformat ascii 1.0\nelement face 2\nproperty list uchar int vertex_indices\n\
         element vertex 4\nproperty float x\nproperty float y\nproperty float z\nend_header\n\
         3 0 1 2\n3 0 2 3\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n",
    )
    .unwrap();
    let scene = load(path.to_str().unwrap());
    let source = dray_scene::ply_stream::PlySource::open(&path).unwrap();
    assert_eq!(source.tables().stats, scene.stats);
    let mut n = 0;
    source
        .for_each_triangle(&mut |t| {
            assert_eq!(t.positions, scene.mesh.corners(t.id as usize));
            n += 1;
            Ok(())
        })
        .unwrap();
    assert_eq!(n, 2);
}

#[test]
fn a_cancelled_cut_stops_and_leaves_no_package() {
    let tmp = TmpDir::new("cancelled-cut");
    let scene = load("soup:500");
    let flag = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(true));
    let e = dray_scene::cancel::with_cancel(&flag, || {
        write_scene_package(&tmp.0, &scene, &LayoutSpec::Kd(4))
    })
    .unwrap_err();
    assert!(matches!(e, dray_scene::SceneError::Cancelled), "{e}");
    assert!(
        open_package(&tmp.0).is_err(),
        "a cancelled cut left a package"
    );
    // Outside the call the same cut goes through.
    write_scene_package(&tmp.0, &scene, &LayoutSpec::Kd(4)).unwrap();
    open_package(&tmp.0).unwrap().verify().unwrap();
}

//! Procedural scenes: every generator builds a valid, deterministic scene; isosurfaces of
//! closed fields are watertight; malformed specs fail with a message, never a panic.

use std::collections::HashMap;

use dray_core::scene::Scene;
use dray_scene::partition::TriangleSource;
use dray_scene::procedural::{MAX_TRIANGLES, generate, stream};
use dray_scene::{Result, SceneError};

/// Loads procedural specs only (enough for `grid` over procedural scenes).
fn load(spec: &str) -> Result<Scene> {
    generate(spec, &load)?.ok_or_else(|| SceneError::UnknownFormat { path: spec.into() })
}

fn check_valid(spec: &str, scene: &Scene) {
    let mesh = &scene.mesh;
    assert!(mesh.triangle_count() > 0, "{spec}: no triangles");
    let n = mesh.positions.len();
    assert_eq!(mesh.normals.len(), n, "{spec}");
    assert_eq!(mesh.tangents.len(), n, "{spec}");
    assert_eq!(mesh.uvs.len(), n, "{spec}");
    assert_eq!(mesh.material.len(), mesh.indices.len(), "{spec}");
    assert!(mesh.positions.iter().all(|p| p.is_finite()), "{spec}");
    assert!(mesh.normals.iter().all(|p| p.is_finite()), "{spec}");
    assert!(
        mesh.indices.iter().flatten().all(|&i| (i as usize) < n),
        "{spec}: index out of range"
    );
    assert!(
        mesh.material
            .iter()
            .all(|&m| (m as usize) < scene.materials.len()),
        "{spec}: material out of range"
    );
    assert!(!scene.cameras.is_empty(), "{spec}: no camera");
    assert!(scene.cameras.iter().all(|c| c.is_valid()), "{spec}");
    let has_emitter = scene.materials.iter().any(|m| m.has_emission());
    assert!(has_emitter || !scene.lights.is_empty(), "{spec}: unlit");
    assert_eq!(scene.name, spec);
}

/// Every edge (as a sorted vertex-index pair) used by exactly two triangles.
fn assert_closed(spec: &str, scene: &Scene) {
    let mut uses: HashMap<(u32, u32), u32> = HashMap::new();
    for &[a, b, c] in &scene.mesh.indices {
        for (p, q) in [(a, b), (b, c), (c, a)] {
            *uses.entry((p.min(q), p.max(q))).or_default() += 1;
        }
    }
    let bad = uses.values().filter(|&&u| u != 2).count();
    assert_eq!(
        bad,
        0,
        "{spec}: {bad} of {} edges not shared by two triangles",
        uses.len()
    );
    assert_eq!(scene.stats.degenerate_triangles, 0, "{spec}");
}

const SPECS: [&str; 19] = [
    "cornell",
    "cornell:mirror",
    "cornell:glass",
    "spheres",
    "spheres:10",
    "spheres:12:mirror",
    "grid:spheres:3:mirror:2x1x2",
    "soup",
    "soup:1000",
    "city",
    "city:3",
    "iso",
    "iso:sphere:32",
    "iso:torus:24",
    "iso:gyroid:24",
    "iso:metaballs:24",
    "iso:heart:24",
    "grid:cornell:2x1x3",
    "grid:iso:sphere:8:3x3x3",
];

#[test]
fn every_generator_builds_a_valid_deterministic_scene() {
    for spec in SPECS {
        let a = load(spec).unwrap_or_else(|e| panic!("{spec}: {e}"));
        check_valid(spec, &a);
        let b = load(spec).unwrap();
        assert!(a == b, "{spec}: two calls differ");
    }
}

#[test]
fn closed_isosurfaces_are_watertight() {
    for spec in [
        "iso:sphere:32",
        "iso:sphere:7",
        "iso:torus:40",
        "iso:metaballs:33",
        "iso:metaballs:64",
        "iso:heart:30",
    ] {
        assert_closed(spec, &load(spec).unwrap());
    }
}

#[test]
fn isosphere_is_round_and_outward() {
    let s = load("iso:sphere:32").unwrap();
    for p in &s.mesh.positions {
        assert!((p.length() - 0.8).abs() < 2.0 / 32.0, "{p}");
    }
    for t in 0..s.mesh.triangle_count() {
        let [a, b, c] = s.mesh.corners(t);
        assert!(
            (b - a).cross(c - a).dot(a + b + c) > 0.0,
            "triangle {t} faces inward"
        );
    }
    // Smooth normals from the gradient agree with the radial direction.
    for (p, n) in s.mesh.positions.iter().zip(&s.mesh.normals) {
        assert!(n.dot(p.normalize()) > 0.999);
    }
}

#[test]
fn triangle_counts_scale() {
    let count = |spec: &str| load(spec).unwrap().mesh.triangle_count();
    assert_eq!(count("cornell"), 32);
    assert_eq!(count("spheres:1"), 320 + 2);
    assert_eq!(count("spheres:50"), 50 * 320 + 2);
    assert_eq!(count("spheres:50:mirror"), 50 * 320 + 2);
    let mirrors = load("spheres:6:mirror").unwrap();
    assert!(
        mirrors.materials.iter().any(|m| m.has_specular()),
        "spheres:N:mirror has mirrors"
    );
    assert!(
        load("spheres:6:chrome").is_err(),
        "an unknown variant is an error"
    );
    let soup = load("soup:1000").unwrap();
    let kept = soup.mesh.triangle_count() as u64;
    assert_eq!(kept + soup.stats.degenerate_triangles, 1000);
    assert!(kept >= 990, "{kept}");
    assert_eq!(count("grid:cornell:2x3x4"), 24 * 32);
    assert!(count("city:4") > count("city:2") * 3);
    // Isosurface triangle counts grow with the square of the resolution.
    let (lo, hi) = (count("iso:sphere:16"), count("iso:sphere:32"));
    assert!(hi > lo * 3 && hi < lo * 5, "{lo} {hi}");
}

#[test]
fn grid_keeps_materials_and_lights_once() {
    let base = load("spheres:3").unwrap();
    let grid = load("grid:spheres:3:2x2x2").unwrap();
    assert_eq!(grid.materials, base.materials);
    assert_eq!(grid.lights, base.lights);
    assert_eq!(grid.mesh.triangle_count(), 8 * base.mesh.triangle_count());
    // The Cornell box has only an emitter, so the grid adds a directional light.
    let cornell = load("grid:cornell:2x2x2").unwrap();
    assert_eq!(cornell.lights.len(), 1);
    // Copies do not overlap: the grid is wider than twice the box.
    let (lo, hi) = base.bounds();
    let (glo, ghi) = grid.bounds();
    assert!((ghi - glo).x > 2.0 * (hi - lo).x);
}

#[test]
fn cornell_variants() {
    let plain = load("cornell").unwrap();
    assert!(plain.lights.is_empty());
    assert!(plain.materials.iter().any(|m| m.has_emission()));
    assert!(
        plain
            .materials
            .iter()
            .all(|m| !m.has_specular() || m.has_emission())
    );
    let mirror = load("cornell:mirror").unwrap();
    assert!(
        mirror
            .materials
            .iter()
            .any(|m| m.metallic == 1.0 && m.roughness == 0.0)
    );
    let glass = load("cornell:glass").unwrap();
    assert!(glass.materials.iter().any(|m| m.has_transmission()));
    assert!(glass.mesh.triangle_count() > 5000);
}

#[test]
fn malformed_specs_are_errors_not_panics() {
    for spec in [
        "spheres:",
        "spheres:-1",
        "spheres:0",
        "spheres:abc",
        "spheres:1e3",
        "spheres:10:5",
        "spheres:99999999999999999999999",
        "spheres:1000000",
        "soup:",
        "soup:0",
        "soup:300000000",
        "cornell:",
        "cornell:wood",
        "grid",
        "grid:",
        "grid:cornell",
        "grid:cornell:",
        "grid::2x2x2",
        "grid:cornell:0x1x1",
        "grid:cornell:2x2",
        "grid:cornell:2x2x2x2",
        "grid:cornell:axbxc",
        "grid:cornell:1000x1000x1000",
        "grid:soup:1000:1000x1000x1",
        "iso:",
        "iso:nofield:32",
        "iso:sphere:",
        "iso:sphere:1",
        "iso:sphere:0",
        "iso:sphere:4096",
        "iso:sphere:32:7",
        "city:",
        "city:0",
        "city:1000000",
    ] {
        match load(spec) {
            Err(SceneError::Procedural { spec: s, message }) => {
                assert_eq!(s, spec, "{message}");
                assert!(!message.is_empty());
                let shown = SceneError::Procedural { spec: s, message }.to_string();
                assert!(shown.contains(spec), "{shown}");
            }
            Err(other) => panic!("{spec}: unexpected error kind {other}"),
            Ok(_) => panic!("{spec}: accepted"),
        }
    }
    // Nesting is bounded, so a hostile spec cannot recurse until the stack overflows.
    let deep = format!(
        "{}cornell{}",
        "grid:".repeat(100_000),
        ":1x1x1".repeat(100_000)
    );
    assert!(matches!(load(&deep), Err(SceneError::Procedural { .. })));
    assert!(load("grid:grid:cornell:2x1x1:1x1x2").is_ok());
    // An inner scene that cannot be loaded surfaces the loader's error.
    assert!(load("grid:nosuchfile.ply:2x2x2").is_err());
}

/// A grid's lookup gives every triangle bit for bit as its stream does, and nothing past
/// the end.
#[test]
fn a_grids_lookup_is_its_stream() {
    let source = stream("grid:spheres:3:mirror:2x3x2", &load)
        .unwrap()
        .unwrap();
    let lookup = source.lookup().expect("grids have a lookup");
    let mut n = 0u32;
    source
        .for_each_triangle(&mut |t| {
            assert_eq!(t.id, n);
            assert_eq!(lookup.triangle(t.id).as_ref(), Some(t));
            n += 1;
            Ok(())
        })
        .unwrap();
    assert_eq!(
        n as usize,
        load("spheres:3:mirror").unwrap().mesh.triangle_count() * 12
    );
    assert!(lookup.triangle(n).is_none());
    assert!(lookup.triangle(u32::MAX).is_none());
}

/// A streamed grid holds only its base model in memory, so it may pass the in-memory cap
/// (the grid to partition for a billion triangles does) up to the 32-bit global ids, and
/// its lookup reaches the last of them without overflowing.
#[test]
fn streamed_grids_pass_the_memory_cap_up_to_32_bit_ids() {
    let per_copy = load("spheres:13").unwrap().mesh.triangle_count() as u64;
    let total = per_copy * 1_000_000;
    assert!(total > MAX_TRIANGLES && total <= u32::MAX as u64, "{total}");
    let spec = "grid:spheres:13:100x100x100";
    assert!(matches!(load(spec), Err(SceneError::Procedural { .. })));
    let source = stream(spec, &load).unwrap().unwrap();
    let lookup = source.lookup().unwrap();
    let last = u32::try_from(total - 1).unwrap();
    assert_eq!(lookup.triangle(last).map(|t| t.id), Some(last));
    assert!(lookup.triangle(last + 1).is_none());
    // Copy 999,999 is the far corner, (99, 99, 99) steps from copy 0.
    let corner = |id: u64| lookup.triangle(id as u32).unwrap().positions[0];
    let step = corner(per_copy) - corner(0);
    let far = corner(total - per_copy) - corner(0);
    assert!(step.x > 0.0 && step.y == 0.0 && step.z == 0.0, "{step}");
    assert!((far.x / step.x - 99.0).abs() < 1e-3, "{far} {step}");
    assert!(far.min_element() > 0.0, "{far}");
    // Past the ids, streaming refuses too.
    let over = "grid:spheres:14:100x100x100";
    assert!(load("spheres:14").unwrap().mesh.triangle_count() as u64 * 1_000_000 > u32::MAX as u64);
    match stream(over, &load) {
        Err(SceneError::Procedural { message, .. }) => {
            assert!(message.contains(&u32::MAX.to_string()), "{message}")
        }
        Err(other) => panic!("{over}: unexpected error kind {other}"),
        Ok(_) => panic!("{over}: accepted"),
    }
}

#[test]
fn non_procedural_specs_are_left_to_the_caller() {
    let nothing = |_: &str| -> Result<Scene> { panic!("load must not be called") };
    for spec in [
        "",
        "foo.gltf",
        "cornell.gltf",
        "scenes/city.obj",
        "/abs/path/bunny.ply",
        "C:\\scenes\\x.glb",
        "Cornell",
        "spheres.ply",
    ] {
        assert!(generate(spec, &nothing).unwrap().is_none(), "{spec}");
    }
}

#[test]
fn arbitrary_spec_strings_never_panic() {
    let heads = ["cornell", "spheres", "soup", "city", "iso", "grid", "x"];
    let pieces = [
        "",
        ":",
        "::",
        "0",
        "1",
        "2",
        "-1",
        "+3",
        "1e9",
        "x",
        "1x1x1",
        "2x1x1",
        "0x0x0",
        "sphere",
        "torus",
        "heart",
        "mirror",
        "glass",
        "cornell",
        "iso",
        "grid",
        " ",
        "\u{1F600}",
        "99999999999999999999",
        "18446744073709551615",
    ];
    let mut state = 0x1234_5678_u64;
    let mut pick = |n: usize| {
        state = state
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        (state >> 33) as usize % n
    };
    for _ in 0..3000 {
        let mut spec = heads[pick(heads.len())].to_string();
        for _ in 0..pick(5) {
            spec.push(':');
            spec.push_str(pieces[pick(pieces.len())]);
        }
        // Ok or Err are both fine; a panic fails the test.
        let _ = load(&spec);
    }
}

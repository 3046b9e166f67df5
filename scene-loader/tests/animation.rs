//! glTF animations sampled at a time (`dray_scene::gltf::load_gltf_at`): a generated file
//! whose keyframes have known values, loaded at times between and beyond them, must
//! place its triangles where the keys say (translation, rotation, scale and morph
//! weights; linear, step and cubic-spline keys), choose an animation by name or index,
//! and refuse what it cannot sample with a message naming the animation and channel.

use dray_scene::animation::AnimationTime;
use dray_scene::gltf::{load_gltf, load_gltf_at};
use glam::Vec3;

mod support;
use support::{approx, test_dir, triangle_builder};

fn at(seconds: f64) -> AnimationTime {
    AnimationTime {
        seconds,
        animation: None,
    }
}

fn named(seconds: f64, name: &str) -> AnimationTime {
    AnimationTime {
        seconds,
        animation: Some(name.into()),
    }
}

/// Node 0 holds the triangle; animation "move" slides it from x = 0 at t = 1 s to x = 4
/// at t = 3 s (linear) and turns it 90 degrees about +Z over the same time; animation
/// "grow" scales it by 2 from t = 0 on (step keys); morph target 0 lifts every vertex by
/// 1 in z and "lift" drives its weight along a cubic spline from 0 to 1 over 1 s with
/// zero tangents (smoothstep).
fn animated_file(dir: &std::path::Path) -> std::path::PathBuf {
    let mut b = triangle_builder();
    let lift = b.floats(&[0.0, 0.0, 1.0].repeat(3), "VEC3");
    let times = b.floats(&[1.0, 3.0], "SCALAR");
    let slide = b.floats(&[0.0, 0.0, 0.0, 4.0, 0.0, 0.0], "VEC3");
    let h = std::f32::consts::FRAC_1_SQRT_2;
    let turn = b.floats(&[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, h, h], "VEC4");
    let grow_times = b.floats(&[0.0, 2.0], "SCALAR");
    let grow = b.floats(&[2.0, 2.0, 2.0, 1.0, 1.0, 1.0], "VEC3");
    let lift_times = b.floats(&[0.0, 1.0], "SCALAR");
    // Per key: in-tangent, value, out-tangent (one weight each).
    let lift_keys = b.floats(&[0.0, 0.0, 0.0, 0.0, 1.0, 0.0], "SCALAR");
    let rest = format!(
        r#""meshes":[{{"name":"Tri","primitives":[{{"attributes":{{"POSITION":0,"NORMAL":1,"TANGENT":2}},"indices":3,"targets":[{{"POSITION":{lift}}}]}}],"weights":[0.0]}}],
"nodes":[{{"mesh":0}}],
"scenes":[{{"nodes":[0]}}],
"animations":[
 {{"name":"move","samplers":[{{"input":{times},"output":{slide}}},{{"input":{times},"output":{turn}}}],
   "channels":[{{"sampler":0,"target":{{"node":0,"path":"translation"}}}},{{"sampler":1,"target":{{"node":0,"path":"rotation"}}}}]}},
 {{"name":"grow","samplers":[{{"input":{grow_times},"output":{grow},"interpolation":"STEP"}}],
   "channels":[{{"sampler":0,"target":{{"node":0,"path":"scale"}}}}]}},
 {{"name":"lift","samplers":[{{"input":{lift_times},"output":{lift_keys},"interpolation":"CUBICSPLINE"}}],
   "channels":[{{"sampler":0,"target":{{"node":0,"path":"weights"}}}}]}}
]"#
    );
    b.write(dir, "animated", &rest)
}

fn triangle(p: &[Vec3]) -> [Vec3; 3] {
    assert_eq!(p.len(), 3, "{p:?}");
    [p[0], p[1], p[2]]
}

fn same(got: [Vec3; 3], want: [Vec3; 3]) {
    assert!(
        got.iter().zip(&want).all(|(a, b)| approx(*a, *b)),
        "got {got:?}, want {want:?}"
    );
}

#[test]
fn translation_and_rotation_follow_linear_keys() {
    let dir = test_dir("anim-move");
    let path = animated_file(&dir);
    // The rest pose: the triangle as written.
    let rest = load_gltf(&path).unwrap();
    same(
        triangle(&rest.mesh.positions),
        [Vec3::ZERO, Vec3::X, Vec3::Y],
    );
    // Halfway (t = 2 s): x = 2, turned 45 degrees about +Z.
    let mid = load_gltf_at(&path, Some(&at(2.0))).unwrap();
    let (c, s) = (45f32.to_radians().cos(), 45f32.to_radians().sin());
    same(
        triangle(&mid.mesh.positions),
        [
            Vec3::new(2.0, 0.0, 0.0),
            Vec3::new(2.0 + c, s, 0.0),
            Vec3::new(2.0 - s, c, 0.0),
        ],
    );
    // Before the first key: the first key's values (x = 0, no turn); after the last, the
    // last's (x = 4, a quarter turn).
    same(
        triangle(&load_gltf_at(&path, Some(&at(0.0))).unwrap().mesh.positions),
        [Vec3::ZERO, Vec3::X, Vec3::Y],
    );
    same(
        triangle(&load_gltf_at(&path, Some(&at(9.0))).unwrap().mesh.positions),
        [
            Vec3::new(4.0, 0.0, 0.0),
            Vec3::new(4.0, 1.0, 0.0),
            Vec3::new(3.0, 0.0, 0.0),
        ],
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn an_animation_is_chosen_by_name_or_index() {
    let dir = test_dir("anim-choose");
    let path = animated_file(&dir);
    // "grow" (step keys): scale 2 until t = 2 s, then 1.
    let early = load_gltf_at(&path, Some(&named(1.9, "grow"))).unwrap();
    same(
        triangle(&early.mesh.positions),
        [
            Vec3::ZERO,
            Vec3::new(2.0, 0.0, 0.0),
            Vec3::new(0.0, 2.0, 0.0),
        ],
    );
    let late = load_gltf_at(&path, Some(&named(2.0, "1"))).unwrap();
    same(
        triangle(&late.mesh.positions),
        [Vec3::ZERO, Vec3::X, Vec3::Y],
    );
    let err = load_gltf_at(&path, Some(&named(0.0, "walk")))
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("no animation \"walk\"") && err.contains("\"move\", \"grow\", \"lift\""),
        "{err}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn the_json_alone_names_the_animations_and_chooses_as_the_loader_does() {
    let dir = test_dir("anim-names");
    let path = animated_file(&dir);
    let names = dray_scene::gltf::animation_names(&path).expect("a glTF file");
    assert_eq!(
        names,
        [
            Some("move".into()),
            Some("grow".into()),
            Some("lift".into())
        ]
    );
    use dray_scene::animation::choose;
    assert_eq!(choose(&names, "grow"), Ok(1));
    assert_eq!(choose(&names, "2"), Ok(2));
    let err = choose(&names, "walk").unwrap_err();
    let loaded = load_gltf_at(&path, Some(&named(0.0, "walk")))
        .unwrap_err()
        .to_string();
    assert!(loaded.ends_with(&err), "{loaded} vs {err}");
    assert_eq!(
        choose(&[None, None], "3").unwrap_err(),
        "no animation \"3\" (the file has #0, #1)"
    );
    assert_eq!(
        choose(&[], "walk").unwrap_err(),
        "has no animations to choose from"
    );
    // Not a glTF file: left to the load.
    assert_eq!(
        dray_scene::gltf::animation_names(&dir.join("missing.gltf")),
        None
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_grid_of_a_file_replicates_the_file_posed_at_the_time() {
    let dir = test_dir("anim-grid");
    let path = animated_file(&dir);
    let spec = format!("grid:{}:2x1x1", path.display());
    // Halfway through "move" (t = 2 s) the triangle is turned 45 degrees: each copy of
    // the grid has the posed triangle's shape, not the rest pose's.
    let posed = load_gltf_at(&path, Some(&at(2.0))).unwrap();
    let grid = dray_scene::load_at(&spec, Some(&at(2.0))).unwrap();
    let rest = dray_scene::load_at(&spec, None).unwrap();
    let p = triangle(&posed.mesh.positions);
    let shape = |t: [Vec3; 3]| [Vec3::ZERO, t[1] - t[0], t[2] - t[0]];
    assert_eq!(grid.mesh.positions.len(), 6, "two copies of one triangle");
    for copy in grid.mesh.positions.chunks(3) {
        same(shape(triangle(copy)), shape(p));
    }
    same(
        shape(triangle(&rest.mesh.positions[..3])),
        [Vec3::ZERO, Vec3::X, Vec3::Y],
    );
    assert!(
        grid.mesh.positions != rest.mesh.positions,
        "the time changed nothing in the grid"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn morph_weights_follow_a_cubic_spline() {
    let dir = test_dir("anim-lift");
    let path = animated_file(&dir);
    // Zero tangents: smoothstep, 3s^2 - 2s^3; at s = 1/4, 0.15625 of the lift.
    let scene = load_gltf_at(&path, Some(&named(0.25, "lift"))).unwrap();
    let z = 0.15625;
    same(
        triangle(&scene.mesh.positions),
        [
            Vec3::new(0.0, 0.0, z),
            Vec3::new(1.0, 0.0, z),
            Vec3::new(0.0, 1.0, z),
        ],
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn unsampleable_keys_and_times_are_refused_with_their_names() {
    let dir = test_dir("anim-bad");
    let mut b = triangle_builder();
    // Times that go backwards.
    let times = b.floats(&[1.0, 0.5], "SCALAR");
    let slide = b.floats(&[0.0, 0.0, 0.0, 4.0, 0.0, 0.0], "VEC3");
    let rest = format!(
        r#""meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}},"indices":3}}]}}],"nodes":[{{"mesh":0}}],"scenes":[{{"nodes":[0]}}],
"animations":[{{"name":"back","samplers":[{{"input":{times},"output":{slide}}}],"channels":[{{"sampler":0,"target":{{"node":0,"path":"translation"}}}}]}}]"#
    );
    let path = b.write(&dir, "backwards", &rest);
    let err = load_gltf_at(&path, Some(&at(0.7))).unwrap_err().to_string();
    assert!(
        err.contains("backwards.gltf")
            && err.contains("animation \"back\" channel 0")
            && err.contains("ascending"),
        "{err}"
    );
    // The rest pose does not read the animation at all.
    assert!(load_gltf(&path).is_ok());
    let err = load_gltf_at(&path, Some(&at(f64::NAN)))
        .unwrap_err()
        .to_string();
    assert!(err.contains("not a finite number"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_file_without_animations_warns_and_shows_its_rest_pose() {
    let dir = test_dir("anim-none");
    let b = triangle_builder();
    let rest = format!(
        r#"{},"nodes":[{{"mesh":0}}],"scenes":[{{"nodes":[0]}}]"#,
        support::TRI_MESH
    );
    let path = b.write(&dir, "still", &rest);
    let scene = load_gltf_at(&path, Some(&at(1.0))).unwrap();
    same(
        triangle(&scene.mesh.positions),
        [Vec3::ZERO, Vec3::X, Vec3::Y],
    );
    assert!(
        scene
            .stats
            .warnings
            .iter()
            .any(|w| w.contains("has no animations")),
        "{:?}",
        scene.stats.warnings
    );
    let err = load_gltf_at(&path, Some(&named(1.0, "walk")))
        .unwrap_err()
        .to_string();
    assert!(err.contains("has no animations"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// A skinned triangle: joint "root" (node 1) at the origin, joint "tip" (node 2, its
/// child) sliding from the origin to y = 2 over one second; vertex 0 follows the root,
/// vertex 1 the tip, vertex 2 both half and half. The mesh's node (0) is moved far away,
/// which a skin ignores.
fn skinned_file(dir: &std::path::Path) -> std::path::PathBuf {
    let mut b = triangle_builder();
    let joints: Vec<u8> = [0u16, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0]
        .iter()
        .flat_map(|j| j.to_le_bytes())
        .collect();
    let view = b.view(&joints);
    b.accessors.push(format!(
        r#"{{"bufferView":{view},"componentType":5123,"count":3,"type":"VEC4"}}"#
    ));
    let joints = b.accessors.len() - 1;
    let weights = b.floats(
        &[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.5, 0.5, 0.0, 0.0],
        "VEC4",
    );
    let times = b.floats(&[0.0, 1.0], "SCALAR");
    let slide = b.floats(&[0.0, 0.0, 0.0, 0.0, 2.0, 0.0], "VEC3");
    let rest = format!(
        r#""meshes":[{{"name":"Skinned","primitives":[{{"attributes":{{"POSITION":0,"NORMAL":1,"TANGENT":2,"JOINTS_0":{joints},"WEIGHTS_0":{weights}}},"indices":3}}]}}],
"skins":[{{"joints":[1,2]}}],
"nodes":[{{"mesh":0,"skin":0,"translation":[100,0,0]}},{{"name":"root","children":[2]}},{{"name":"tip"}}],
"scenes":[{{"nodes":[0,1]}}],
"animations":[{{"name":"raise","samplers":[{{"input":{times},"output":{slide}}}],
  "channels":[{{"sampler":0,"target":{{"node":2,"path":"translation"}}}}]}}]"#
    );
    b.write(dir, "skinned", &rest)
}

#[test]
fn a_skin_follows_its_joints_and_ignores_its_node() {
    let dir = test_dir("anim-skin");
    let path = skinned_file(&dir);
    // The joints where the file puts them: the triangle as written, not at x = 100.
    let rest = load_gltf(&path).unwrap();
    same(
        triangle(&rest.mesh.positions),
        [Vec3::ZERO, Vec3::X, Vec3::Y],
    );
    // Halfway: the tip joint is at y = 1; vertex 1 follows it, vertex 2 half of it.
    let mid = load_gltf_at(&path, Some(&at(0.5))).unwrap();
    same(
        triangle(&mid.mesh.positions),
        [
            Vec3::ZERO,
            Vec3::new(1.0, 1.0, 0.0),
            Vec3::new(0.0, 1.5, 0.0),
        ],
    );
    let _ = std::fs::remove_dir_all(&dir);
}

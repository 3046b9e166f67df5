//! End-to-end tests of the camera flags (docs/cameras.md): placement, orthographic
//! projection and the thin lens against answers known without rendering, and the same
//! bits from the tile renderer and from workers.

mod common;

use std::path::{Path, PathBuf};

use common::{render, rgb, tmp};

/// An ASCII PLY of axis-aligned cubes, each (centre, half-size): no lights, so the
/// scene is lit by the white sky and every cube is darker than the sky around it.
fn write_cubes(dir: &Path, cubes: &[([f32; 3], f32)]) -> PathBuf {
    let (mut v, mut f) = (Vec::new(), Vec::new());
    for ([x, y, z], h) in cubes {
        let base = v.len();
        for sx in [-1.0, 1.0] {
            for sy in [-1.0, 1.0] {
                for sz in [-1.0, 1.0] {
                    v.push(format!("{} {} {}", x + sx * h, y + sy * h, z + sz * h));
                }
            }
        }
        // Corner i is (x, y, z) = bits (4, 2, 1) of i.
        for q in [
            [0, 1, 3, 2],
            [4, 6, 7, 5],
            [0, 4, 5, 1],
            [2, 3, 7, 6],
            [0, 2, 6, 4],
            [1, 5, 7, 3],
        ] {
            f.push(format!(
                "4 {} {} {} {}",
                base + q[0],
                base + q[1],
                base + q[2],
                base + q[3]
            ));
        }
    }
    let path = dir.join("cubes.ply");
    let s = format!(
        "ply\nformat ascii 1.0\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nelement face {}\nproperty list uchar int vertex_indices\nend_header\n{}\n{}\n",
        v.len(),
        f.len(),
        v.join("\n"),
        f.join("\n")
    );
    std::fs::write(&path, s).expect("write ply");
    path
}

/// Linear-light-free reading: sky is white (255) with `--exposure 0 --tonemap clamp`.
const PLAIN: [&str; 4] = ["--exposure", "0", "--tonemap", "clamp"];

fn run(dir: &Path, tag: &str, scene: &Path, args: &[&str]) -> image::RgbImage {
    let r = render(
        dir,
        tag,
        scene.to_str().unwrap(),
        &[&PLAIN[..], args].concat(),
    );
    assert!(r.ok, "{tag}: {}", r.stderr);
    rgb(r.png.as_ref().unwrap())
}

fn grey(im: &image::RgbImage, x: u32, y: u32) -> u8 {
    im.get_pixel(x, y).0[1]
}

/// Pixels of column range `xs` darker than the sky: a cube's projected area.
fn cube_pixels(im: &image::RgbImage, xs: std::ops::Range<u32>) -> usize {
    xs.flat_map(|x| (0..im.height()).map(move |y| (x, y)))
        .filter(|&(x, y)| grey(im, x, y) < 250)
        .count()
}

/// A camera looking at a point puts it at the image's centre: a small cube there fills
/// the centre pixel while the corners see the sky, from two sides; an orbit sees it too.
#[test]
fn a_camera_looking_at_a_point_puts_it_at_the_centre() {
    let d = tmp("cam-centre");
    let scene = write_cubes(&d, &[([3.0, 1.0, -2.0], 0.1), ([-4.0, 0.0, 4.0], 0.1)]);
    for (tag, from) in [("front", "3,1.5,3"), ("side", "-2,-1,-1.5")] {
        let im = run(
            &d,
            tag,
            &scene,
            &[
                "--width",
                "33",
                "--height",
                "33",
                "--spp",
                "4",
                "--look-from",
                from,
                "--look-at",
                "3,1,-2",
                "--fov",
                "10",
            ],
        );
        assert!(
            grey(&im, 16, 16) < 250,
            "{tag}: centre {}",
            grey(&im, 16, 16)
        );
        for (x, y) in [(0, 0), (32, 0), (0, 32), (32, 32)] {
            assert_eq!(grey(&im, x, y), 255, "{tag}: corner {x},{y}");
        }
    }
}

/// Orthographic rays are parallel: two equal cubes at depths 10 and 40 project to the
/// same area, where a perspective camera shows the far one 16 times smaller.
#[test]
fn orthographic_keeps_sizes_at_every_depth() {
    let d = tmp("cam-ortho");
    let scene = write_cubes(&d, &[([-1.5, 0.0, 0.0], 0.5), ([1.5, 0.0, -30.0], 0.5)]);
    let args = [
        "--width",
        "64",
        "--height",
        "32",
        "--spp",
        "16",
        "--look-from",
        "0,0,10",
        "--look-at",
        "0,0,0",
        "--fov",
        "20",
    ];
    let ortho = run(
        &d,
        "ortho",
        &scene,
        &[&args[..], &["--orthographic"]].concat(),
    );
    let (near, far) = (cube_pixels(&ortho, 0..32), cube_pixels(&ortho, 32..64));
    assert!(near > 20, "{near}");
    assert!(
        near.abs_diff(far) * 10 <= near,
        "orthographic: {near} vs {far} pixels"
    );
    let persp = run(&d, "persp", &scene, &args);
    let (near, far) = (cube_pixels(&persp, 0..32), cube_pixels(&persp, 32..64));
    assert!(far * 4 < near, "perspective: {near} vs {far} pixels");
}

/// The new flags give the same bits with `--workers 0` (the tile renderer) and with two
/// workers over four domains: the camera is resolved once and built from the same
/// numbers everywhere, and lens samples come from the counter-based random numbers.
#[test]
fn camera_flags_give_the_same_bits_on_every_configuration() {
    let d = tmp("cam-bits");
    let scene = write_cubes(&d, &[([-1.5, 0.0, 0.0], 0.5), ([1.5, 0.3, -6.0], 0.8)]);
    let base = [
        "--width",
        "40",
        "--height",
        "24",
        "--spp",
        "4",
        "--domains",
        "4",
    ];
    let views: [&[&str]; 3] = [
        &["--orbit", "35,25", "--aperture", "0.2"],
        &[
            "--look-from",
            "1,2,9",
            "--look-at",
            "0,0,-2",
            "--up",
            "0.1,1,0",
            "--fov",
            "30",
            "--orthographic",
            "--aperture",
            "0.1",
            "--focus-on",
            "-1.5,0,0.5",
        ],
        &[
            "--orbit",
            "-120,-10",
            "--fov",
            "55",
            "--aperture",
            "f/0.5",
            "--focus-distance",
            "7",
        ],
    ];
    for (i, view) in views.iter().enumerate() {
        let exr = |w: &str| d.join(format!("v{i}-{w}.exr"));
        let mut bytes = Vec::new();
        for w in ["0", "2"] {
            let out = exr(w);
            run(
                &d,
                &format!("v{i}-{w}"),
                &scene,
                &[
                    &base[..],
                    view,
                    &["--workers", w, "--exr", out.to_str().unwrap()],
                ]
                .concat(),
            );
            bytes.push(std::fs::read(&out).expect("exr"));
        }
        assert!(bytes[0] == bytes[1], "view {i}: --workers 0 and 2 differ");
    }
}

/// A thin lens keeps the plane in focus as sharp as a pinhole and blurs what is far
/// from it: around a cube at the focus distance the lens render matches the pinhole's
/// within noise, around a cube four times further it does not.
#[test]
fn thin_lens_is_sharp_at_the_focus_distance_and_blurs_elsewhere() {
    let d = tmp("cam-lens");
    // Front faces at distance 10 (in focus) and 40 (blurred over about 3 pixels).
    let scene = write_cubes(&d, &[([-1.5, 0.0, -0.5], 0.5), ([6.0, 0.0, -32.0], 2.0)]);
    let args = [
        "--width",
        "64",
        "--height",
        "32",
        "--spp",
        "64",
        "--look-from",
        "0,0,10",
        "--look-at",
        "0,0,0",
        "--fov",
        "20",
    ];
    let pin = run(&d, "pinhole", &scene, &args);
    let lens = run(
        &d,
        "lens",
        &scene,
        &[&args[..], &["--aperture", "0.4", "--focus-distance", "10"]].concat(),
    );
    let diff = |xs: std::ops::Range<u32>| {
        let mut sum = 0u64;
        for x in xs {
            for y in 0..32 {
                sum += u64::from(grey(&pin, x, y).abs_diff(grey(&lens, x, y)));
            }
        }
        sum
    };
    let (near, far) = (diff(0..32), diff(32..64));
    eprintln!("in focus {near}, far {far}");
    assert!(far > 500, "the far cube is not blurred: {far}");
    assert!(near * 8 < far, "the cube in focus changed: {near} vs {far}");
}

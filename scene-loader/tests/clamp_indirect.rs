//! `--clamp-indirect` on the Cornell box with a glass sphere, whose caustics make
//! fireflies: with the clamp, no pixel's indirect light exceeds what the clamp allows
//! a sample, so the fireflies are gone; no pixel gains energy; and direct light is left
//! exactly as it was.

use dray_core::bvh::Accel;
use dray_core::integrator::{Integrator, IntegratorKind, RenderSettings};
use dray_core::lighting::Lighting;
use dray_core::render::{RenderOutput, render};
use glam::Vec3;

const SIZE: u32 = 48;
const SPP: u32 = 8;
const MAX_DEPTH: u32 = 5;
/// The clamp: a hundred and seventieth of the light's radiance (17, 12, 4), twice the
/// median pixel's indirect light.
const CLAMP: f32 = 0.1;

fn cornell(max_depth: u32, clamp_indirect: Option<f32>) -> RenderOutput {
    let scene = dray_scene::load("cornell:glass").expect("cornell:glass");
    let environment = dray_scene::effects::default_environment(&scene);
    let settings = RenderSettings {
        width: SIZE,
        height: SIZE,
        spp: SPP,
        integrator: IntegratorKind::Path,
        max_depth,
        seed: 7,
        environment,
        effects: dray_scene::effects::analyze(&scene, environment),
        ao_samples: 1,
        ao_distance: f32::INFINITY,
        lighting: Lighting::default(),
        clamp_indirect,
        aovs: Default::default(),
    };
    let camera = scene
        .choose_camera(None, scene.bounds(), 1.0)
        .expect("camera");
    let bvh = Accel::build(&scene.mesh);
    let integrator = Integrator::new(&scene, camera, settings);
    render(&integrator, &bvh, 2, &|_, _| {}).expect("render")
}

/// The most contributions of indirect light one path sample makes: at each of the
/// hits at depth 1..MAX_DEPTH a light sample (its shadow ray), and at each hit at depth
/// 2..=MAX_DEPTH the emitter it finds (the sky is black: the box has a light).
const INDIRECT_PER_SAMPLE: f32 = 2.0 * (MAX_DEPTH - 1) as f32;

#[test]
fn the_clamp_removes_fireflies_and_never_adds_light() {
    let free = cornell(MAX_DEPTH, None);
    let clamped = cornell(MAX_DEPTH, Some(CLAMP));
    // Direct light alone: with one surface interaction the paths end where indirect
    // light would begin, with the same random numbers as the deeper renders.
    let direct = cornell(1, Some(CLAMP));
    assert_eq!(free.film.clamped_indirect, 0);
    assert_eq!(
        direct.film.clamped_indirect, 0,
        "direct light is never clamped"
    );
    assert!(clamped.film.clamped_indirect > 0, "nothing was clamped");

    let (f, c, d) = (
        free.film.linear(SPP),
        clamped.film.linear(SPP),
        direct.film.linear(SPP),
    );
    // What a clamped sample may add to direct light, averaged over the pixel's samples
    // (each at most CLAMP per component per contribution), with room for rounding.
    let bound = INDIRECT_PER_SAMPLE * CLAMP * 1.0001;
    let mut fireflies = 0;
    for p in 0..(SIZE * SIZE) as usize {
        // Integer sums: the clamp only ever scales a contribution down.
        let (sf, sc) = (
            free.film.sum_fixed(p as u32),
            clamped.film.sum_fixed(p as u32),
        );
        for k in 0..3 {
            assert!(
                sc[k] <= sf[k],
                "pixel {p}: clamped {sc:?} > unclamped {sf:?}"
            );
        }
        // Direct light is the same contributions with or without the clamp, so the
        // clamped render holds it exactly and adds only non-negative indirect light.
        let sd = direct.film.sum_fixed(p as u32);
        for k in 0..3 {
            assert!(sd[k] <= sc[k], "pixel {p}: direct {sd:?} > clamped {sc:?}");
        }
        let indirect = c[p] - d[p];
        assert!(
            indirect.max_element() <= bound,
            "pixel {p}: indirect light {indirect} above {bound} with the clamp"
        );
        if (f[p] - d[p]).max_element() > bound {
            fireflies += 1;
        }
    }
    let top = |img: &[Vec3]| {
        let mut v: Vec<f32> = img
            .iter()
            .zip(&d)
            .map(|(x, d)| (*x - *d).max_element())
            .collect();
        v.sort_by(f32::total_cmp);
        [v[v.len() / 2], v[v.len() * 99 / 100], v[v.len() - 1]]
    };
    let (tf, tc) = (top(&f), top(&c));
    eprintln!("indirect light, median, 99th percentile, max: free {tf:?}, clamped {tc:?}");
    assert!(
        tc[2] < tf[2] / 4.0,
        "the brightest pixel: {tc:?} clamped, {tf:?} not"
    );
    // The clamp had fireflies to remove.
    assert!(fireflies > 0, "no pixel's indirect light was above {bound}");
    // And it keeps most of the light: the image is darker, not dark.
    let mean = |v: &[Vec3]| v.iter().map(|p| p.element_sum()).sum::<f32>() / v.len() as f32;
    let (mf, mc) = (mean(&f), mean(&c));
    assert!(mc < mf && mc > 0.5 * mf, "mean {mc} clamped, {mf} not");
    eprintln!(
        "fireflies {fireflies}, clamped {} contributions, mean {mc} of {mf}",
        clamped.film.clamped_indirect
    );
}

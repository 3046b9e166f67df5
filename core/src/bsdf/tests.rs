//! The BSDF's analytic tests: white furnaces, sampling against evaluation, reciprocity,
//! Snell's law, the Lambert fast path's bits, and hostile parameters.

use std::f32::consts::{PI, TAU};

use super::clearcoat::coat_fresnel;
use super::*;

/// splitmix64: a tiny deterministic generator for the Monte Carlo tests.
struct Rng(u64);

impl Rng {
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    fn f32(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 * (1.0 / (1u64 << 24) as f32)
    }

    fn vec2(&mut self) -> Vec2 {
        Vec2::new(self.f32(), self.f32())
    }

    fn sphere(&mut self) -> Vec3 {
        uniform_sphere(self.vec2())
    }

    /// The `i`-th of `side^2` jittered-stratified uniform sphere directions.
    fn sphere_strat(&mut self, i: usize, side: usize) -> Vec3 {
        let (a, b) = ((i % side) as f32, (i / side) as f32);
        let u = Vec2::new(
            (a + self.f32()) / side as f32,
            (b + self.f32()) / side as f32,
        );
        uniform_sphere(u.min(Vec2::splat(ONE_MINUS_EPS)))
    }
}

/// Bits of an `eval_pdf` answer, for exact comparisons.
fn bits(fp: (Vec3, f32)) -> [u32; 4] {
    [fp.0.x, fp.0.y, fp.0.z, fp.1].map(f32::to_bits)
}

#[test]
fn sat_is_nan_to_zero_then_clamp() {
    for x in [
        f32::NAN,
        -f32::NAN,
        f32::INFINITY,
        f32::NEG_INFINITY,
        -0.0,
        0.0,
        1.0,
        1.5,
        -2.0,
        0.25,
        f32::MIN_POSITIVE,
        1.0 - f32::EPSILON,
        -f32::MIN_POSITIVE,
    ] {
        let old = if x.is_nan() { 0.0 } else { x.clamp(0.0, 1.0) };
        assert_eq!(sat(x).to_bits(), old.to_bits(), "{x}");
    }
}

/// Bits of a sample, for exact comparisons.
fn sample_bits(s: Option<BsdfSample>) -> Option<([u32; 3], [u32; 4], Lobe, bool)> {
    s.map(|s| {
        (
            s.wi.to_array().map(f32::to_bits),
            bits((s.f, s.pdf)),
            s.lobe,
            s.delta,
        )
    })
}

/// Bits of a Whitted direction and weight (`mirror`, `refraction`).
fn pair_bits(r: Option<(Vec3, Vec3)>) -> Option<([u32; 3], [u32; 3])> {
    r.map(|(a, b)| {
        (
            a.to_array().map(f32::to_bits),
            b.to_array().map(f32::to_bits),
        )
    })
}

/// Diffuse-only materials, including the edges of the sanitising: NaN, `-0.0`,
/// negative and out-of-range factors, a transmission whose tint is black (black base)
/// or underflows to zero, and parameters the diffuse lobe ignores (roughness, index,
/// film, anisotropy, the coat's roughness and normal) set to what would change the
/// other lobes.
fn lambert_params() -> Vec<BsdfParams> {
    let bases = [
        Vec3::new(0.8, 0.8, 0.8),
        Vec3::new(0.9, 0.2, 0.05),
        Vec3::ZERO,
        Vec3::new(-0.0, 0.0, -0.0),
        Vec3::new(1e-30, 0.0, 0.0),
        Vec3::new(f32::NAN, 0.5, 2.0),
    ];
    let mut all = Vec::new();
    for (k, &base) in bases.iter().enumerate() {
        all.push(BsdfParams {
            base_color: base,
            metallic: [0.0, -0.0, f32::NAN, -1.0][k % 4],
            specular: [0.0, f32::NAN, -0.0, -3.0][k % 4],
            roughness: [0.3, 0.0, 1.0][k % 3],
            ior: [1.5, f32::NAN, 0.0, f32::INFINITY][k % 4],
            // Ignored without a reflective layer, but they must not change the bits.
            iridescence: 1.0,
            iridescence_thickness: 400.0,
            anisotropy: if k % 2 == 0 { 0.7 } else { 0.0 },
            anisotropy_direction: Vec3::X,
            clearcoat: [0.0, -0.0, f32::NAN, -0.5][k % 4],
            clearcoat_roughness: 0.1,
            clearcoat_normal: Vec3::Y,
            sheen_color: [Vec3::ZERO, Vec3::new(-0.0, f32::NAN, -1.0)][k % 2],
            sheen_roughness: 0.5,
            ..BsdfParams::default()
        });
    }
    // Transmission without a tint: a black base, or a product below the smallest f32.
    for (base, transmission) in [(Vec3::ZERO, 1.0), (Vec3::splat(1e-30), 1e-20)] {
        all.push(BsdfParams {
            base_color: base,
            transmission,
            ..p(0.0, 0.0, 0.5, 0.0, 0.0)
        });
    }
    all
}

#[test]
fn lambert_fast_path_gives_the_general_bits() {
    let mut rng = Rng(41);
    let mut checked = 0;
    for params in lambert_params() {
        for _ in 0..1000 {
            let n = rng.sphere();
            let ng = (n + rng.sphere() * 0.3).normalize_or(n);
            let fast = Bsdf::new(&params, n, ng);
            assert!(fast.lambert, "{params:?}");
            // The general path: every lobe built and sanitised, no fast branch.
            let general = Bsdf::new_general(&params, n, ng);
            assert!(!general.lambert);
            assert_eq!(
                (
                    fast.has_diffuse(),
                    fast.has_specular_lobe(),
                    fast.has_transmission(),
                    fast.is_delta_only()
                ),
                (
                    general.has_diffuse(),
                    general.has_specular_lobe(),
                    general.has_transmission(),
                    general.is_delta_only()
                )
            );
            assert_eq!(
                fast.diffuse_albedo().to_array().map(f32::to_bits),
                general.diffuse_albedo().to_array().map(f32::to_bits)
            );
            let wo = rng.sphere();
            assert_eq!(pair_bits(fast.mirror(wo)), pair_bits(general.mirror(wo)));
            assert_eq!(
                pair_bits(fast.refraction(wo)),
                pair_bits(general.refraction(wo))
            );
            let (Some(a), Some(b)) = (fast.at(wo), general.at(wo)) else {
                assert!(fast.at(wo).is_none() && general.at(wo).is_none());
                continue;
            };
            for _ in 0..4 {
                let wi = rng.sphere();
                let e = bits(a.eval_pdf(wi));
                assert_eq!(e, bits(b.eval_pdf(wi)), "{params:?} wo {wo} wi {wi}");
                assert_eq!(e, bits(general.eval_pdf(wo, wi)));
                assert_eq!(e, bits(fast.eval_pdf(wo, wi)));
                assert_eq!(e, bits((a.eval(wi), general.pdf(wo, wi))));
                assert_eq!(e, bits((fast.eval(wo, wi), fast.pdf(wo, wi))));
                // The fast path never reads the lobe number: any one, even out of range
                // or NaN, must pick what the general selection picks.
                let u = rng.vec2();
                for ul in [rng.f32(), 0.0, 1.0, 2.0, -1.0, f32::NAN] {
                    let s = sample_bits(a.sample(ul, u));
                    assert_eq!(s, sample_bits(b.sample(ul, u)), "{params:?}");
                    assert_eq!(s, sample_bits(fast.sample(wo, ul, u)));
                    assert_eq!(s, sample_bits(general.sample(wo, ul, u)));
                }
                checked += 1;
            }
        }
    }
    assert!(checked > 20_000, "only {checked} directions compared");
    // Any reflective, transmissive, coated or sheened layer takes the general path.
    for params in [
        p(0.8, 0.0, 1.0, 1.0, 0.0),
        p(0.8, 0.1, 1.0, 0.0, 0.0),
        p(0.8, 0.0, 1.0, 0.0, 0.5),
        BsdfParams {
            clearcoat: 0.5,
            ..p(0.8, 0.0, 1.0, 0.0, 0.0)
        },
        BsdfParams {
            sheen_color: Vec3::splat(0.5),
            ..p(0.8, 0.0, 1.0, 0.0, 0.0)
        },
    ] {
        assert!(!Bsdf::new(&params, Vec3::Z, Vec3::Z).lambert, "{params:?}");
    }
    assert!(Bsdf::new(&p(0.8, 0.0, 1.0, 0.0, 0.0), Vec3::Z, Vec3::Z).lambert);
}

/// `Bsdf::new` decides "diffuse-only" on the raw coat and sheen parameters; the
/// decision must be the lobes' own test on what the general construction sanitises.
#[test]
fn lambert_flag_is_the_general_lobes_test() {
    let edges = [
        0.0,
        -0.0,
        f32::NAN,
        -f32::NAN,
        -1.0,
        f32::NEG_INFINITY,
        f32::INFINITY,
        f32::from_bits(1),
        1e-20,
        0.5,
        2.0,
    ];
    let mut lambert = 0;
    for (i, &a) in edges.iter().enumerate() {
        for (j, &b) in edges.iter().enumerate() {
            for &c in &edges {
                let params = BsdfParams {
                    base_color: Vec3::new(c, 1e-30, 0.5),
                    metallic: [a, 0.0][j % 2],
                    specular: [b, 0.0][i % 2],
                    transmission: [c, 0.0][(i + j) % 2],
                    clearcoat: [a, b][(i + j) % 2],
                    sheen_color: Vec3::new(b, c, a),
                    ..BsdfParams::default()
                };
                let g = Bsdf::new_general(&params, Vec3::Z, Vec3::Z);
                let lobes = !g.reflection.on
                    && g.transmission.tint.max_element() <= 0.0
                    && g.coat.strength <= 0.0
                    && g.sheen.max <= 0.0;
                assert_eq!(
                    Bsdf::new(&params, Vec3::Z, Vec3::Z).lambert,
                    lobes,
                    "{params:?}"
                );
                lambert += usize::from(lobes);
            }
        }
    }
    assert!(lambert > 20, "only {lambert} diffuse-only materials");
}

const STRAT_SIDE: usize = 700;

fn uniform_sphere(u: Vec2) -> Vec3 {
    let z = 1.0 - 2.0 * u.x;
    let r = (1.0 - z * z).max(0.0).sqrt();
    let phi = TAU * u.y;
    Vec3::new(r * phi.cos(), r * phi.sin(), z)
}

/// Direction at polar angle `deg` from +z, in the xz plane.
fn dir(deg: f32) -> Vec3 {
    let t = deg.to_radians();
    Vec3::new(t.sin(), 0.0, t.cos())
}

fn p(base: f32, metallic: f32, roughness: f32, specular: f32, transmission: f32) -> BsdfParams {
    BsdfParams {
        base_color: Vec3::splat(base),
        metallic,
        roughness,
        specular,
        specular_color: Vec3::ONE,
        transmission,
        ior: 1.5,
        clearcoat: 0.0,
        clearcoat_roughness: 0.0,
        clearcoat_normal: Vec3::ZERO,
        sheen_color: Vec3::ZERO,
        sheen_roughness: 0.0,
        anisotropy: 0.0,
        anisotropy_direction: Vec3::ZERO,
        iridescence: 0.0,
        iridescence_ior: 1.3,
        iridescence_thickness: 0.0,
    }
}

fn flat(params: &BsdfParams) -> Bsdf {
    Bsdf::new(params, Vec3::Z, Vec3::Z)
}

/// Albedo estimate `E[f |cos| / pdf]` through `sample()` (None counts as 0).
fn albedo(b: &Bsdf, wo: Vec3, n: usize, rng: &mut Rng) -> Vec3 {
    let mut sum = Vec3::ZERO;
    for _ in 0..n {
        if let Some(s) = b.sample(wo, rng.f32(), rng.vec2()) {
            sum += s.f * s.wi.z.abs() / s.pdf;
        }
    }
    sum / n as f32
}

/// `integral of f |cos|` over the sphere by uniform sphere sampling of `eval`.
fn albedo_uniform(b: &Bsdf, wo: Vec3, rng: &mut Rng) -> Vec3 {
    let n = STRAT_SIDE * STRAT_SIDE;
    let mut sum = Vec3::ZERO;
    for i in 0..n {
        let wi = rng.sphere_strat(i, STRAT_SIDE);
        sum += b.eval(wo, wi) * wi.z.abs();
    }
    sum * (4.0 * PI / n as f32)
}

fn rel_eq(a: f32, b: f32, tol: f32) -> bool {
    (a - b).abs() <= tol * a.abs().max(b.abs()).max(1e-6)
}

#[test]
fn white_furnace_lambert() {
    let b = flat(&p(1.0, 0.0, 1.0, 0.0, 0.0));
    let mut rng = Rng(1);
    for deg in [0.0, 30.0, 60.0, 85.0] {
        let wo = dir(deg);
        let a = albedo(&b, wo, 50_000, &mut rng);
        assert!((a - Vec3::ONE).abs().max_element() < 0.01, "{deg}: {a}");
        // Uniform hemisphere sampling of eval.
        let n = 400_000;
        let mut sum = Vec3::ZERO;
        for _ in 0..n {
            let mut wi = rng.sphere();
            wi.z = wi.z.abs();
            sum += b.eval(wo, wi) * wi.z;
        }
        let a = sum * (2.0 * PI / n as f32);
        assert!((a - Vec3::ONE).abs().max_element() < 0.01, "{deg}: {a}");
    }
}

#[test]
fn energy_bounded() {
    let mut rng = Rng(2);
    for roughness in [0.0, 0.05, 0.2, 0.5, 1.0] {
        for metallic in [0.0, 0.5, 1.0] {
            for specular in [1.0, 0.5] {
                for (transmission, ior) in [(0.0, 1.5), (0.5, 1.5), (1.0, 1.5), (1.0, 1.0)] {
                    let b = flat(&BsdfParams {
                        ior,
                        ..p(1.0, metallic, roughness, specular, transmission)
                    });
                    for wo in [dir(0.0), dir(45.0), dir(80.0), -dir(30.0), -dir(60.0)] {
                        let a = albedo(&b, wo, 20_000, &mut rng);
                        assert!(
                            a.max_element() <= 1.01 && a.min_element() > 0.0,
                            "r {roughness} m {metallic} s {specular} t {transmission} \
                             ior {ior} wo {wo}: {a}"
                        );
                    }
                }
            }
        }
    }
}

#[test]
fn smooth_glass_conserves_energy() {
    let b = flat(&p(1.0, 0.0, 0.0, 1.0, 1.0));
    let mut rng = Rng(3);
    for wo in [dir(0.0), dir(50.0), dir(85.0), -dir(20.0), -dir(60.0)] {
        let a = albedo(&b, wo, 20_000, &mut rng);
        assert!((a - Vec3::ONE).abs().max_element() < 0.01, "{wo}: {a}");
    }
}

/// Sampling and evaluation agree for each material and `wo`: E_sample[f cos / pdf]
/// over the non-delta samples equals the uniform-sphere estimate of the integral of
/// f |cos|, and the pdf integrates to the fraction of accepted samples.
fn assert_sampling_matches_eval(mats: &[BsdfParams], wos: &[Vec3], rng: &mut Rng) {
    for (k, m) in mats.iter().enumerate() {
        let b = flat(m);
        for &wo in wos {
            // Non-delta samples only: eval/pdf cover the non-delta lobes.
            let n = 400_000;
            let mut a_s = Vec3::ZERO;
            let mut ok = 0usize;
            for _ in 0..n {
                if let Some(s) = b.sample(wo, rng.f32(), rng.vec2()).filter(|s| !s.delta) {
                    a_s += s.f * s.wi.z.abs() / s.pdf;
                    ok += 1;
                }
            }
            let a_s = a_s / n as f32;
            let a_u = albedo_uniform(&b, wo, rng);
            assert!(
                (a_s - a_u).abs().max_element() < 0.015,
                "mat {k} wo {wo}: sampled {a_s} uniform {a_u}"
            );
            let mut pdf_sum = 0.0f64;
            let ns = STRAT_SIDE * STRAT_SIDE;
            for i in 0..ns {
                pdf_sum += b.pdf(wo, rng.sphere_strat(i, STRAT_SIDE)) as f64;
            }
            let integral = (pdf_sum * 4.0 * std::f64::consts::PI / ns as f64) as f32;
            let frac = ok as f32 / n as f32;
            assert!(integral <= 1.02, "mat {k} wo {wo}: pdf integral {integral}");
            assert!(
                (integral - frac).abs() < 0.01,
                "mat {k} wo {wo}: pdf integral {integral} vs accepted {frac}"
            );
        }
    }
}

/// Sampling and evaluation agree: E_sample[f cos / pdf] equals the uniform-sphere
/// estimate of the integral of f |cos|, and the pdf integrates to the fraction of
/// successful samples.
#[test]
fn sampling_matches_eval() {
    let mats = [
        p(0.8, 0.0, 0.5, 1.0, 0.0),
        p(0.9, 1.0, 0.4, 1.0, 0.0),
        p(0.7, 0.3, 0.7, 0.6, 0.0),
        p(1.0, 0.0, 0.5, 1.0, 1.0),
        p(0.9, 0.0, 0.6, 1.0, 0.5),
        // Index-matched: rough reflection, delta pass-through transmission.
        BsdfParams {
            ior: 1.0,
            ..p(0.9, 0.0, 0.4, 1.0, 0.5)
        },
        // Tinted specular colour over a coloured base.
        BsdfParams {
            base_color: Vec3::new(0.9, 0.4, 0.1),
            specular_color: Vec3::new(2.0, 1.0, 0.2),
            ior: 1.8,
            ..p(1.0, 0.2, 0.45, 0.8, 0.0)
        },
    ];
    assert_sampling_matches_eval(&mats, &[dir(10.0), dir(60.0), -dir(40.0)], &mut Rng(4));
}

fn coated(base: BsdfParams, coat: f32, roughness: f32) -> BsdfParams {
    BsdfParams {
        clearcoat: coat,
        clearcoat_roughness: roughness,
        ..base
    }
}

/// White furnace for the clear coat: a smooth coat over a white Lambert base
/// reflects `c F(cos_o)` and passes `(1 - c F(cos_o))` down and `(1 - c F(cos_i))`
/// back up, so its albedo is `c F_o + (1 - c F_o)(1 - c F_hemi)` with
/// `F_hemi = 2 integral F(mu) mu dmu`: the sampled albedo must match within 1%. Rough
/// coats, over every base, never gain energy.
#[test]
fn clearcoat_white_furnace() {
    let mut rng = Rng(12);
    let n = 100_000;
    let f_hemi: f64 = (0..n)
        .map(|i| {
            let mu = (i as f64 + 0.5) / n as f64;
            2.0 * coat_fresnel(mu as f32) as f64 * mu / n as f64
        })
        .sum();
    let white = p(1.0, 0.0, 1.0, 0.0, 0.0);
    for coat in [0.5f32, 1.0] {
        let b = flat(&coated(white, coat, 0.0));
        assert!(!b.is_delta_only() && b.has_specular_lobe());
        for deg in [0.0f32, 40.0, 75.0, 88.0] {
            let wo = dir(deg);
            let a = albedo(&b, wo, 100_000, &mut rng);
            let fo = coat * coat_fresnel(wo.z);
            let want = fo + (1.0 - fo) * (1.0 - coat * f_hemi as f32);
            assert!(
                (a - Vec3::splat(want)).abs().max_element() < 0.01 && a.is_finite(),
                "coat {coat} at {deg}: {a} vs {want}"
            );
        }
    }
    let bases = [
        white,
        p(1.0, 1.0, 0.2, 1.0, 0.0),
        p(1.0, 0.0, 0.4, 1.0, 0.0),
        p(1.0, 0.0, 0.0, 1.0, 1.0),
        p(1.0, 0.0, 0.5, 1.0, 1.0),
    ];
    assert_no_gain(
        "coat",
        &bases,
        &[0.0, 0.05, 0.3, 0.7, 1.0],
        &mut rng,
        |b, r| coated(b, 1.0, r),
    );
}

/// `layer` (a base and a roughness to a layered material) over each of `bases` at
/// each of `roughnesses` reflects no more than it receives (albedo at most 1.01),
/// something, and nothing non-finite, from above and below.
fn assert_no_gain(
    name: &str,
    bases: &[BsdfParams],
    roughnesses: &[f32],
    rng: &mut Rng,
    layer: impl Fn(BsdfParams, f32) -> BsdfParams,
) {
    for &roughness in roughnesses {
        for &base in bases {
            let b = flat(&layer(base, roughness));
            for wo in [dir(0.0), dir(50.0), dir(85.0), -dir(30.0)] {
                let a = albedo(&b, wo, 20_000, rng);
                assert!(
                    a.max_element() <= 1.01 && a.min_element() > 0.0 && a.is_finite(),
                    "{name} roughness {roughness} base {base:?} wo {wo}: {a}"
                );
            }
        }
    }
}

/// The coat's pdf is the density its sampler draws from, so MIS weights are right:
/// sampled and uniformly integrated albedos agree, and the pdf integrates to the
/// fraction of accepted samples.
#[test]
fn clearcoat_sampling_matches_eval() {
    let mats = [
        coated(p(0.8, 0.0, 0.6, 1.0, 0.0), 1.0, 0.3),
        coated(p(0.9, 1.0, 0.5, 1.0, 0.0), 0.6, 0.15),
        coated(p(0.5, 0.0, 1.0, 0.0, 0.0), 1.0, 0.8),
        coated(p(1.0, 0.0, 0.5, 1.0, 1.0), 1.0, 0.4),
    ];
    assert_sampling_matches_eval(&mats, &[dir(10.0), dir(70.0), -dir(40.0)], &mut Rng(13));
}

fn coat_normal(base: BsdfParams, n: Vec3) -> BsdfParams {
    BsdfParams {
        clearcoat_normal: n,
        ..base
    }
}

fn reflect(wo: Vec3, n: Vec3) -> Vec3 {
    n * (2.0 * wo.dot(n)) - wo
}

/// `clearcoatNormalTexture`: the coat reflects about its own normal and the base
/// about its own; nothing gains energy, sampling and evaluation agree, and a coat
/// normal equal to the shading normal changes nothing.
#[test]
fn clearcoat_normal_moves_the_coat_not_the_base() {
    let mut rng = Rng(18);
    let tilt = Vec3::new(0.3, 0.1, 1.0).normalize();
    let bases = [
        p(1.0, 0.0, 1.0, 0.0, 0.0),
        p(1.0, 1.0, 0.3, 1.0, 0.0),
        p(1.0, 0.0, 0.4, 1.0, 0.0),
        p(1.0, 0.0, 0.5, 1.0, 1.0),
    ];
    assert_no_gain("coat normal", &bases, &[0.0, 0.1, 0.4], &mut rng, |b, r| {
        coat_normal(coated(b, 1.0, r), tilt)
    });
    let mats = [
        coat_normal(coated(p(0.8, 0.0, 0.6, 1.0, 0.0), 1.0, 0.3), tilt),
        coat_normal(
            coated(p(0.9, 1.0, 0.5, 1.0, 0.0), 0.6, 0.15),
            Vec3::new(-0.4, 0.2, 1.0),
        ),
        coat_normal(coated(p(1.0, 0.0, 0.5, 1.0, 1.0), 1.0, 0.4), tilt),
    ];
    assert_sampling_matches_eval(&mats, &[dir(10.0), dir(60.0), -dir(40.0)], &mut rng);

    let wo = dir(30.0);
    let (m_n, m_c) = (reflect(wo, Vec3::Z), reflect(wo, tilt));
    // A rough coat over a black base: its highlight follows the coat's normal.
    let black = p(0.0, 0.0, 1.0, 0.0, 0.0);
    let b = flat(&coat_normal(coated(black, 1.0, 0.15), tilt));
    let (at_c, at_n) = (b.eval(wo, m_c).x, b.eval(wo, m_n).x);
    assert!(
        at_c > 5.0 * at_n,
        "coat mirror {at_c} vs base mirror {at_n}"
    );
    let plain = flat(&coated(black, 1.0, 0.15));
    assert!(plain.eval(wo, m_n).x > 5.0 * plain.eval(wo, m_c).x);
    // A smooth coat's mirror sample is about its own normal; the rough metal under
    // it still reflects about the shading normal, only attenuated a little
    // differently.
    let metal = p(0.9, 1.0, 0.3, 1.0, 0.0);
    let b = flat(&coat_normal(coated(metal, 1.0, 0.0), tilt));
    let untilted = flat(&coated(metal, 1.0, 0.0));
    let mut coat_samples = 0;
    for _ in 0..2_000 {
        if let Some(s) = b.sample(wo, rng.f32(), rng.vec2())
            && s.lobe == Lobe::CoatReflection
        {
            assert!((s.wi - m_c).length() < 1e-5, "{s:?}");
            coat_samples += 1;
        }
    }
    assert!(coat_samples > 20, "{coat_samples}");
    let (f_t, f_u) = (b.eval(wo, m_n), untilted.eval(wo, m_n));
    assert!(
        (f_t - f_u).abs().max_element() < 0.05 * f_u.max_element(),
        "{f_t} vs {f_u}"
    );
    // A coat normal equal to the shading normal is no change.
    for m in [
        coated(metal, 1.0, 0.3),
        coated(p(0.5, 0.0, 0.4, 1.0, 1.0), 0.7, 0.2),
    ] {
        let same = flat(&coat_normal(m, Vec3::Z));
        let plain = flat(&m);
        for _ in 0..1_000 {
            let (wo, wi) = (rng.sphere(), rng.sphere());
            let (a, c) = (same.eval(wo, wi), plain.eval(wo, wi));
            for k in 0..3 {
                assert!(rel_eq(a[k], c[k], 1e-4), "{a} vs {c}");
            }
            assert!(rel_eq(same.pdf(wo, wi), plain.pdf(wo, wi), 1e-4));
        }
    }
}

fn sheened(base: BsdfParams, color: f32, roughness: f32) -> BsdfParams {
    BsdfParams {
        sheen_color: Vec3::splat(color),
        sheen_roughness: roughness,
        ..base
    }
}

/// White furnace for the sheen: a white sheen over a black base reflects exactly its
/// directional albedo `E(cos_o)` (so sampling, pdf and the albedo table agree); over
/// any base, under a coat or not, the sum never gains energy.
#[test]
fn sheen_white_furnace() {
    let mut rng = Rng(14);
    let black = p(0.0, 0.0, 1.0, 0.0, 0.0);
    for roughness in [0.1f32, 0.4, 1.0] {
        let b = flat(&sheened(black, 1.0, roughness));
        assert!(!b.is_delta_only());
        for deg in [0.0f32, 45.0, 80.0] {
            let wo = dir(deg);
            let a = albedo(&b, wo, 200_000, &mut rng);
            let e = crate::sheen::albedo(wo.z, roughness);
            assert!(
                (a - Vec3::splat(e)).abs().max_element() < 0.01 && a.is_finite(),
                "roughness {roughness} at {deg}: {a} vs E {e}"
            );
        }
    }
    let bases = [
        p(1.0, 0.0, 1.0, 0.0, 0.0),
        p(1.0, 0.0, 0.3, 1.0, 0.0),
        p(1.0, 1.0, 0.0, 1.0, 0.0),
        coated(p(1.0, 0.0, 0.5, 1.0, 0.0), 1.0, 0.2),
        p(1.0, 0.0, 0.5, 1.0, 1.0),
    ];
    assert_no_gain("sheen", &bases, &[0.0, 0.3, 1.0], &mut rng, |b, r| {
        sheened(b, 1.0, r)
    });
}

/// Sampled and uniformly integrated albedos agree with a sheen, and the pdf
/// integrates to the accepted fraction: the sheen's pdf is the density its sampler
/// draws from.
#[test]
fn sheen_sampling_matches_eval() {
    let mats = [
        sheened(p(0.8, 0.0, 0.6, 1.0, 0.0), 0.9, 0.5),
        sheened(p(0.3, 0.0, 1.0, 0.0, 0.0), 1.0, 0.2),
        sheened(coated(p(0.9, 1.0, 0.4, 1.0, 0.0), 0.5, 0.3), 0.6, 0.8),
    ];
    assert_sampling_matches_eval(&mats, &[dir(10.0), dir(75.0)], &mut Rng(15));
}

fn anisotropic(base: BsdfParams, strength: f32, direction: Vec3) -> BsdfParams {
    BsdfParams {
        anisotropy: strength,
        anisotropy_direction: direction,
        ..base
    }
}

/// Anisotropy stretches the lobe along its direction and nothing else: a white
/// anisotropic metal never gains energy, sampling and evaluation agree, strength 0
/// is the isotropic lobe to the bit, and the lobe is wider along its direction.
#[test]
fn anisotropic_ggx_furnace_and_sampling() {
    let mut rng = Rng(16);
    for roughness in [0.0, 0.3, 0.7] {
        for strength in [0.5, 1.0] {
            for base in [
                p(1.0, 1.0, roughness, 1.0, 0.0),
                p(1.0, 0.0, roughness, 1.0, 1.0),
            ] {
                let b = flat(&anisotropic(base, strength, Vec3::new(1.0, 1.0, 0.3)));
                for wo in [dir(0.0), dir(50.0), dir(85.0), -dir(30.0)] {
                    let a = albedo(&b, wo, 20_000, &mut rng);
                    assert!(
                        a.max_element() <= 1.01 && a.min_element() > 0.0 && a.is_finite(),
                        "r {roughness} s {strength} {base:?} wo {wo}: {a}"
                    );
                }
            }
        }
    }
    let mats = [
        anisotropic(p(0.9, 1.0, 0.3, 1.0, 0.0), 0.8, Vec3::X),
        anisotropic(p(0.8, 0.0, 0.2, 1.0, 0.0), 1.0, Vec3::new(1.0, 2.0, 0.0)),
        anisotropic(p(1.0, 0.0, 0.4, 1.0, 1.0), 0.6, Vec3::Y),
    ];
    assert_sampling_matches_eval(&mats, &[dir(10.0), dir(60.0), -dir(40.0)], &mut rng);

    let iso = p(0.9, 1.0, 0.4, 1.0, 0.0);
    let none = flat(&anisotropic(iso, 0.0, Vec3::X));
    let plain = flat(&iso);
    let stretched = flat(&anisotropic(iso, 1.0, Vec3::X));
    for _ in 0..1_000 {
        let (wo, wi) = (rng.sphere(), rng.sphere());
        assert_eq!(none.eval(wo, wi), plain.eval(wo, wi));
        assert_eq!(none.pdf(wo, wi), plain.pdf(wo, wi));
    }
    // Off-specular by 40 degrees along the direction (x) the stretched lobe still
    // reflects much more than across it (y).
    let wo = Vec3::Z;
    let along = Vec3::new(40f32.to_radians().sin(), 0.0, 40f32.to_radians().cos());
    let across = Vec3::new(0.0, along.x, along.z);
    let (fa, fc) = (stretched.eval(wo, along).x, stretched.eval(wo, across).x);
    assert!(fa > 2.0 * fc, "along {fa} across {fc}");
    assert!((plain.eval(wo, along).x - plain.eval(wo, across).x).abs() < 1e-4);
}

fn iridescent(base: BsdfParams, factor: f32, thickness: f32) -> BsdfParams {
    BsdfParams {
        iridescence: factor,
        iridescence_ior: 1.3,
        iridescence_thickness: thickness,
        ..base
    }
}

/// The thin film changes only the Fresnel term, and keeps it a fraction: over white
/// bases (dielectric, metal, glass, coated) nothing gains energy; sampling and
/// evaluation agree; factor 0 (or thickness 0) is the material without the film, to
/// the bit; and the film's thickness changes the hue of the reflection.
#[test]
fn iridescence_furnace_bits_and_colour() {
    let mut rng = Rng(17);
    let bases = [
        p(1.0, 0.0, 1.0, 1.0, 0.0),
        p(1.0, 0.0, 0.3, 1.0, 0.0),
        p(1.0, 1.0, 0.0, 1.0, 0.0),
        p(1.0, 1.0, 0.4, 1.0, 0.0),
        p(1.0, 0.5, 0.2, 1.0, 0.0),
        p(1.0, 0.0, 0.0, 1.0, 1.0),
        p(1.0, 0.0, 0.5, 1.0, 1.0),
        coated(p(1.0, 0.0, 0.4, 1.0, 0.0), 1.0, 0.2),
    ];
    // The "roughness" argument is the film's thickness here.
    assert_no_gain(
        "iridescence",
        &bases,
        &[150.0, 400.0, 900.0],
        &mut rng,
        |b, t| iridescent(b, 1.0, t),
    );
    let mats = [
        iridescent(p(0.8, 0.0, 0.5, 1.0, 0.0), 1.0, 300.0),
        iridescent(p(0.9, 1.0, 0.4, 1.0, 0.0), 0.7, 500.0),
        iridescent(p(1.0, 0.0, 0.5, 1.0, 1.0), 1.0, 250.0),
    ];
    assert_sampling_matches_eval(&mats, &[dir(10.0), dir(60.0), -dir(40.0)], &mut rng);

    for base in [p(0.7, 0.3, 0.4, 1.0, 0.0), p(1.0, 0.0, 0.3, 1.0, 1.0)] {
        let plain = flat(&base);
        for off in [iridescent(base, 0.0, 400.0), iridescent(base, 1.0, 0.0)] {
            let off = flat(&off);
            for _ in 0..1_000 {
                let (wo, wi) = (rng.sphere(), rng.sphere());
                assert_eq!(off.eval(wo, wi), plain.eval(wo, wi));
                assert_eq!(off.pdf(wo, wi), plain.pdf(wo, wi));
                let (ul, u) = (rng.f32(), rng.vec2());
                assert_eq!(off.sample(wo, ul, u), plain.sample(wo, ul, u));
            }
        }
    }

    // A smooth black dielectric reflects only its Fresnel term: grey without the film,
    // coloured with it, and differently coloured for another thickness.
    let chroma = |b: &Bsdf| {
        let w = b.mirror(dir(0.0)).unwrap().1;
        w / w.element_sum()
    };
    let black = p(0.0, 0.0, 0.0, 1.0, 0.0);
    let grey = chroma(&flat(&black));
    assert!((grey - Vec3::splat(1.0 / 3.0)).abs().max_element() < 1e-6);
    let thin = chroma(&flat(&iridescent(black, 1.0, 250.0)));
    let thick = chroma(&flat(&iridescent(black, 1.0, 400.0)));
    assert!((thin - grey).abs().max_element() > 0.05, "{thin}");
    assert!(
        (thin - thick).abs().max_element() > 0.05,
        "{thin} vs {thick}"
    );
}

#[test]
fn pdf_integral_lambert_is_one() {
    let b = flat(&p(0.5, 0.0, 1.0, 0.0, 0.0));
    let mut rng = Rng(5);
    let n = 400_000;
    let mut sum = 0.0f64;
    for _ in 0..n {
        sum += b.pdf(dir(35.0), rng.sphere()) as f64;
    }
    let integral = sum * 4.0 * std::f64::consts::PI / n as f64;
    assert!((integral - 1.0).abs() < 0.01, "{integral}");
}

#[test]
fn sample_consistent_with_eval_and_pdf() {
    let mut rng = Rng(6);
    let mut checked = 0;
    for _ in 0..20_000 {
        let m = BsdfParams {
            base_color: Vec3::new(rng.f32(), rng.f32(), rng.f32()),
            metallic: rng.f32(),
            roughness: 0.05 + rng.f32() * 0.95,
            specular: rng.f32(),
            specular_color: Vec3::new(rng.f32(), rng.f32(), rng.f32()) * 2.0,
            transmission: if rng.f32() < 0.5 { 0.0 } else { rng.f32() },
            ior: 1.1 + rng.f32(),
            clearcoat: if rng.f32() < 0.5 { 0.0 } else { rng.f32() },
            clearcoat_roughness: 0.05 + rng.f32() * 0.95,
            clearcoat_normal: if rng.f32() < 0.5 {
                Vec3::ZERO
            } else {
                Vec3::Z + rng.sphere() * 0.5
            },
            sheen_color: if rng.f32() < 0.5 {
                Vec3::ZERO
            } else {
                Vec3::new(rng.f32(), rng.f32(), rng.f32())
            },
            sheen_roughness: rng.f32(),
            anisotropy: if rng.f32() < 0.5 { 0.0 } else { rng.f32() },
            anisotropy_direction: rng.sphere(),
            iridescence: if rng.f32() < 0.5 { 0.0 } else { rng.f32() },
            iridescence_ior: 1.0 + rng.f32(),
            iridescence_thickness: rng.f32() * 1000.0,
        };
        let b = flat(&m);
        let wo = rng.sphere();
        if let Some(s) = b.sample(wo, rng.f32(), rng.vec2()) {
            if s.delta {
                continue;
            }
            let f = b.eval(wo, s.wi);
            let pdf = b.pdf(wo, s.wi);
            assert!(rel_eq(s.pdf, pdf, 1e-3), "{m:?} {wo}: {} vs {pdf}", s.pdf);
            for c in 0..3 {
                assert!(rel_eq(s.f[c], f[c], 1e-3), "{m:?} {wo}: {} vs {f}", s.f);
            }
            checked += 1;
        }
    }
    assert!(checked > 10_000, "{checked}");
}

#[test]
fn reciprocity() {
    let mut rng = Rng(7);
    let mats = [
        p(0.8, 0.0, 0.3, 1.0, 0.0),
        p(0.8, 1.0, 0.1, 1.0, 0.0),
        BsdfParams {
            base_color: Vec3::new(0.9, 0.5, 0.2),
            metallic: 0.4,
            roughness: 0.6,
            specular: 0.7,
            specular_color: Vec3::new(1.0, 0.5, 2.0),
            transmission: 0.0,
            ior: 1.8,
            clearcoat: 0.7,
            clearcoat_roughness: 0.3,
            clearcoat_normal: Vec3::ZERO,
            sheen_color: Vec3::new(0.5, 0.8, 0.2),
            sheen_roughness: 0.5,
            anisotropy: 0.0,
            anisotropy_direction: Vec3::ZERO,
            iridescence: 0.8,
            iridescence_ior: 1.6,
            iridescence_thickness: 300.0,
        },
    ];
    for m in &mats {
        let b = flat(m);
        for _ in 0..2_000 {
            let mut wo = rng.sphere();
            let mut wi = rng.sphere();
            wo.z = wo.z.abs();
            wi.z = wi.z.abs();
            let a = b.eval(wo, wi);
            let c = b.eval(wi, wo);
            for k in 0..3 {
                assert!(rel_eq(a[k], c[k], 1e-3), "{m:?}: {a} vs {c}");
            }
        }
    }
}

#[test]
fn pure_lambert_never_leaves_diffuse() {
    let b = flat(&p(0.6, 0.0, 0.0, 0.0, 0.0));
    assert!(!b.has_specular_lobe() && b.has_diffuse() && !b.is_delta_only());
    let mut rng = Rng(8);
    for _ in 0..10_000 {
        let mut wo = rng.sphere();
        wo.z = wo.z.abs().max(1e-3);
        if let Some(s) = b.sample(wo, rng.f32(), rng.vec2()) {
            assert_eq!(s.lobe, Lobe::Diffuse);
            assert!(!s.delta);
        }
    }
    assert!(b.mirror(dir(10.0)).is_none() && b.refraction(dir(10.0)).is_none());
}

#[test]
fn smooth_glass_is_delta_and_obeys_snell() {
    let ior = 1.5;
    let b = Bsdf::new(
        &BsdfParams {
            ior,
            ..p(1.0, 0.0, 0.0, 1.0, 1.0)
        },
        Vec3::Z,
        Vec3::Z,
    );
    assert!(b.is_delta_only() && b.has_transmission() && !b.has_diffuse());
    let mut rng = Rng(9);
    for _ in 0..10_000 {
        let wo = rng.sphere();
        if let Some(s) = b.sample(wo, rng.f32(), rng.vec2()) {
            assert!(s.delta);
            assert!(matches!(
                s.lobe,
                Lobe::SpecularReflection | Lobe::SpecularTransmission
            ));
        }
        assert_eq!(b.eval(wo, rng.sphere()), Vec3::ZERO);
        assert_eq!(b.pdf(wo, rng.sphere()), 0.0);
    }
    // Entering: sin_i = ior sin_t.
    for deg in [0.0f32, 20.0, 45.0, 70.0, 89.0] {
        let wo = dir(deg);
        let (wi, w) = b.refraction(wo).unwrap();
        let sin_t = (1.0 - wi.z * wi.z).sqrt();
        assert!(wi.z < 0.0 && wi.x <= 1e-6);
        assert!((deg.to_radians().sin() - ior * sin_t).abs() < 1e-4, "{deg}");
        assert!(w.max_element() <= 1.0 && w.min_element() > 0.0);
    }
    // Leaving: ior sin_i = sin_t below the critical angle, TIR above it.
    let critical = (1.0 / ior).asin().to_degrees();
    for deg in [0.0f32, 20.0, 40.0, critical - 0.5] {
        let wo = -dir(deg);
        let (wi, _) = b.refraction(wo).unwrap();
        let sin_t = (1.0 - wi.z * wi.z).sqrt();
        assert!(wi.z > 0.0);
        assert!((ior * deg.to_radians().sin() - sin_t).abs() < 1e-3, "{deg}");
    }
    for deg in [critical + 0.5, 60.0, 85.0] {
        let wo = -dir(deg);
        assert!(b.refraction(wo).is_none(), "{deg}");
        let (wi, w) = b.mirror(wo).unwrap();
        assert!((w - Vec3::ONE).abs().max_element() < 1e-6 && wi.z < 0.0);
        for _ in 0..1_000 {
            let s = b.sample(wo, rng.f32(), rng.vec2()).unwrap();
            assert_eq!(s.lobe, Lobe::SpecularReflection);
            assert!(rel_eq(s.f.x * s.wi.z.abs() / s.pdf, 1.0, 1e-5));
        }
    }
}

#[test]
fn reflection_below_geometric_surface_is_zero() {
    // Shading normal tilted 30 degrees from the geometric normal.
    let n = dir(30.0);
    let mut rng = Rng(10);
    for m in [p(0.8, 0.0, 0.5, 1.0, 0.0), p(0.8, 1.0, 0.3, 1.0, 0.0)] {
        let b = Bsdf::new(&m, n, Vec3::Z);
        let wo = dir(40.0);
        // Above the shading hemisphere, below the geometric one.
        let wi = dir(100.0);
        assert!(wi.dot(n) > 0.0 && wi.z < 0.0);
        assert_eq!(b.eval(wo, wi), Vec3::ZERO);
        assert_eq!(b.pdf(wo, wi), 0.0);
        for _ in 0..5_000 {
            if let Some(s) = b.sample(wo, rng.f32(), rng.vec2()) {
                assert!(s.wi.z > 0.0, "{s:?}");
            }
        }
    }
}

#[test]
fn mirror_and_orientation() {
    let b = Bsdf::new(&p(0.9, 1.0, 0.0, 1.0, 0.0), -Vec3::Z, Vec3::Z);
    assert!(b.is_delta_only() && b.has_specular_lobe());
    let (wi, w) = b.mirror(dir(30.0)).unwrap();
    assert!((wi - Vec3::new(-0.5, 0.0, 3f32.sqrt() / 2.0)).length() < 1e-5);
    assert!(w.min_element() >= 0.9 - 1e-6 && w.max_element() <= 1.0);
    // Same from the back side.
    let (wi, _) = b.mirror(-dir(30.0)).unwrap();
    assert!((wi - Vec3::new(0.5, 0.0, -(3f32.sqrt()) / 2.0)).length() < 1e-5);
    // Rough metal: no Whitted mirror.
    assert!(
        flat(&p(0.9, 1.0, 0.5, 1.0, 0.0))
            .mirror(dir(30.0))
            .is_none()
    );
    assert!(!flat(&p(0.9, 1.0, 0.5, 1.0, 0.0)).is_delta_only());
}

#[test]
fn stress_no_nan() {
    let mut rng = Rng(11);
    let specials = [0.0, 1e-7, 1e-4, 0.03, 0.5, 1.0];
    let iors = [1.0, 1.0005, 1.5, 0.0, f32::INFINITY, 2.4, 1.0 + 1e-6];
    for i in 0..100_000 {
        let pick = |rng: &mut Rng, xs: &[f32]| xs[(rng.next_u64() % xs.len() as u64) as usize];
        let m = BsdfParams {
            base_color: Vec3::new(rng.f32(), rng.f32(), rng.f32()),
            metallic: pick(&mut rng, &[0.0, 1.0, 0.5, 0.999]),
            roughness: if i % 2 == 0 {
                pick(&mut rng, &specials)
            } else {
                rng.f32()
            },
            specular: pick(&mut rng, &[0.0, 1.0, 0.3]),
            specular_color: Vec3::new(rng.f32(), rng.f32(), rng.f32()) * 3.0,
            transmission: pick(&mut rng, &[0.0, 1.0, 0.5]),
            ior: pick(&mut rng, &iors),
            clearcoat: pick(&mut rng, &[0.0, 1.0, 0.5]),
            clearcoat_roughness: if i % 3 == 0 {
                pick(&mut rng, &specials)
            } else {
                rng.f32()
            },
            clearcoat_normal: match i % 5 {
                0 => Vec3::ZERO,
                1 => Vec3::NAN,
                _ => rng.sphere(),
            },
            sheen_color: if i % 4 == 1 {
                Vec3::new(rng.f32(), rng.f32(), rng.f32())
            } else {
                Vec3::ZERO
            },
            sheen_roughness: pick(&mut rng, &[0.0, 0.5, 1.0]),
            anisotropy: pick(&mut rng, &[0.0, 1.0, 0.5]),
            anisotropy_direction: match i % 6 {
                0 => Vec3::ZERO,
                1 => Vec3::NAN,
                _ => rng.sphere(),
            },
            iridescence: pick(&mut rng, &[0.0, 1.0, 0.5]),
            iridescence_ior: pick(&mut rng, &[1.0, 1.3, 0.0, f32::INFINITY, f32::NAN]),
            iridescence_thickness: pick(&mut rng, &[0.0, 1e-6, 0.01, 400.0, 1e9, f32::NAN]),
        };
        let ng = rng.sphere();
        let n = match i % 4 {
            0 => ng,
            1 => -ng,
            2 => (ng + rng.sphere() * 0.5).normalize_or(ng),
            _ => rng.sphere(),
        };
        let b = Bsdf::new(&m, n, ng);
        let wo = match i % 5 {
            0 => {
                // Grazing / tangent to the geometric surface.
                let t = ng.any_orthonormal_pair().0;
                let eps = pick(&mut rng, &[0.0, 1e-8, 1e-6, 1e-4, -1e-6]);
                (t + ng * eps).normalize()
            }
            1 => {
                // Grazing to the shading normal.
                let t = n.any_orthonormal_pair().0;
                (t + n * pick(&mut rng, &[0.0, 1e-7, -1e-7])).normalize()
            }
            _ => rng.sphere(),
        };
        let u = match i % 7 {
            0 => Vec2::new(0.0, 0.0),
            1 => Vec2::new(ONE_MINUS_EPS, ONE_MINUS_EPS),
            _ => rng.vec2(),
        };
        let ul = if i % 11 == 0 { 1.0 } else { rng.f32() };
        if let Some(s) = b.sample(wo, ul, u) {
            assert!(
                s.f.is_finite() && s.pdf.is_finite() && s.pdf > 0.0,
                "{m:?} {s:?}"
            );
            assert!(s.wi.is_finite() && (s.wi.length() - 1.0).abs() < 1e-3);
            assert!(s.f.min_element() >= 0.0);
            let e = b.eval(wo, s.wi);
            assert!(e.is_finite() && b.pdf(wo, s.wi).is_finite());
        }
        let wi = if i % 3 == 0 { -wo } else { rng.sphere() };
        let e = b.eval(wo, wi);
        let pd = b.pdf(wo, wi);
        assert!(
            e.is_finite() && pd.is_finite() && pd >= 0.0,
            "{m:?} {wo} {wi}"
        );
        assert!(e.min_element() >= 0.0);
        if let Some((d, w)) = b.mirror(wo) {
            assert!(d.is_finite() && w.is_finite());
        }
        if let Some((d, w)) = b.refraction(wo) {
            assert!(d.is_finite() && w.is_finite());
        }
        assert!(b.diffuse_albedo().is_finite());
    }
    // Degenerate inputs.
    let b = Bsdf::new(&BsdfParams::default(), Vec3::ZERO, Vec3::ZERO);
    assert!(b.sample(Vec3::Z, 0.5, Vec2::splat(0.5)).is_none());
    let b = flat(&BsdfParams {
        base_color: Vec3::NAN,
        metallic: f32::NAN,
        roughness: f32::NAN,
        specular: f32::INFINITY,
        specular_color: Vec3::INFINITY,
        transmission: f32::NAN,
        ior: f32::NAN,
        clearcoat: f32::NAN,
        clearcoat_roughness: f32::NAN,
        clearcoat_normal: Vec3::NAN,
        sheen_color: Vec3::NAN,
        sheen_roughness: f32::NAN,
        anisotropy: 0.0,
        anisotropy_direction: Vec3::ZERO,
        iridescence: f32::NAN,
        iridescence_ior: f32::NAN,
        iridescence_thickness: f32::INFINITY,
    });
    for wo in [Vec3::Z, Vec3::X, Vec3::NAN, Vec3::ZERO, dir(89.999)] {
        let _ = b
            .sample(wo, f32::NAN, Vec2::NAN)
            .map(|s| assert!(s.f.is_finite()));
        assert!(b.eval(wo, Vec3::Z).is_finite() && b.pdf(wo, Vec3::NAN).is_finite());
    }
}

#!/usr/bin/env python3
"""dray's thin-lens camera and its sun against Mitsuba 3's `thinlens` sensor and `directional`
emitter, with NVIDIA FLIP, side by side with time (issue 39).

Scene (tabletop scale, metres, so an f-number gives visible depth of field): three Lambert
spheres of radius 5 cm at three depths (near and off to the left, middle, far and off to the
right) on a checkered ground quad (1.2 m square, 27 x 27 cells), seen from 0.75 m at 384x256
(landscape, so the vertical field of view and the f-number's film back are put to the test).
The meshes are benches/gltf_vs_mitsuba.py's (its 96 x 48 UV sphere, moved and scaled, and its
ground, scaled), written as a glTF for dray and given to Mitsuba as the same triangles through
`mi.Mesh`; the materials are pure Lambert in both (glTF `KHR_materials_specular` 0 against
`diffuse`).

Cases:
- pinhole: `--look-from/--look-at/--fov` against Mitsuba's `perspective` (fov_axis "y": dray's
  --fov is vertical). Lit by the glTF's directional light (a delta, as Mitsuba's
  `directional`) and a constant environment. Control: Mitsuba's default fov_axis "x".
- lens_radius: `--aperture R --focus-distance D` against `thinlens` with aperture_radius R and
  focus_distance D, focused on the near sphere. Both put the plane in focus D along the view
  axis (dray `Frustum::generate_through_lens`: the pinhole ray's point at depth D; Mitsuba
  `ThinLensCamera::sample_ray`: near_p * (focus_distance / near_p.z)), and both sample the
  lens uniformly by Shirley and Chiu's concentric map. As a control that the comparison can
  tell conventions apart, Mitsuba also renders the focus at the near sphere's Euclidean
  distance (what a "focus distance along the ray" convention would give): dray must be
  further from that than from the axial one.
- lens_fstop: `--aperture f/N --focus-on X,Y,Z` (the far sphere's centre) against `thinlens`
  with aperture_radius = focal length / (2 N), the focal length a 36 mm film back along the
  image's wider side gives dray's vertical field of view, scene units as metres
  (docs/cameras.md; core/src/view.rs `Aperture::radius`), and focus_distance the point's
  depth along the view axis. Controls: the radius an f-number read against a 36 mm film
  height would give (1.5 times dray's here), the diameter taken for the radius (2 times), and
  the focus at the far sphere's Euclidean distance.
- sun: `--sun AZ,EL,IRRADIANCE` (a disk 0.53 degrees wide) on the same scene without the
  glTF's light, against Mitsuba's `directional` with the same irradiance and the direction
  -(sin AZ cos EL, sin EL, cos AZ cos EL) (dray's is the direction toward the sun; Mitsuba's
  the direction light travels). A delta light against a 0.53-degree disk: shadow edges differ
  by the penumbra (here at most 1.6 mm, about a pixel), so FLIP is reported over the whole
  image, shadows included.
  Control: Mitsuba with the azimuth mirrored (-AZ), which a wrong sign would give.

Each row: FLIP (LDR: clamp to [0,1], sRGB) dray against Mitsuba, over the whole image and over
each sphere's pixels (those whose pinhole centre ray hits it first), beside Mitsuba against
Mitsuba with another seed (the noise floor) and dray against dray with another seed; for the
lenses, dray's lens render against dray's pinhole render per sphere (the sphere in focus must
be as close to the pinhole as the noise allows; the others blur). The image's mean linear
radiance, dray / Mitsuba, shows a bias FLIP could hide.

Timed: dray's whole `dray render` process (wall) and its render_time_s (--stats); Mitsuba's
`mi.render` of the second seed (warm: the first compiles its kernels) and its load_dict +
render. Both pinned to the same cores (taskset) with the same thread count; --runs N repeats
dray and the warm Mitsuba render and reports medians. On a shared machine the wall times
follow the other processes' load, so CPU seconds are reported too: the whole dray process's
(user + system, all threads), and Mitsuba's process CPU time over `mi.render`.

Depth: dray --max-depth D, Mitsuba max_depth D + 1 and rr_depth 4 (benches/vs_mitsuba.py
explains why).

Usage (from the repository root; creates benches/.venv on first use):
    benches/lens_sun_vs_mitsuba.sh                      # builds dray, then runs this
    python3 benches/lens_sun_vs_mitsuba.py [--cases pinhole,sun] [--spp 256] [--runs 3]
Outputs go to benches/out/lens_sun_vs_mitsuba/ (per case: PNGs of both renderers and of the
controls, the FLIP map; the two glTF scenes; results.json). At the defaults with --runs 3,
about 9 minutes on 2 shared cores.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _bench_env as env  # noqa: E402
import gltf_vs_mitsuba as gvm  # noqa: E402  (meshes, glTF writer, mi.Mesh, variant pick)
import vs_mitsuba as vsm  # noqa: E402  (tonemap, read_exr, save_png, vector helpers)

WIDTH, HEIGHT = 384, 256
FOV_DEG = 30.0  # vertical
EYE = (0.0, 0.16, 0.75)
TARGET = (0.0, 0.04, 0.0)
UP = (0.0, 1.0, 0.0)
SCALE = 0.1  # gltf_vs_mitsuba's ground (12 units) becomes 1.2 m
RADIUS = 0.05
SPHERES = {"near": (-0.12, RADIUS, 0.25), "mid": (0.0, RADIUS, 0.0), "far": (0.18, RADIUS, -0.35)}
ALBEDO = (0.8, 0.45, 0.25)
ENV_RADIANCE = gvm.ENV_RADIANCE
LENS_RADIUS = 0.04
F_NUMBER = 2.0
FILM_BACK_MM = 36.0  # core/src/view.rs FILM_BACK_MM
SUN = (300.0, 35.0, 3.0)  # azimuth, elevation (degrees), irradiance
NEAR_CLIP = 1e-4


def frame():
    """(forward, right, up) of dray's `Camera::look_at` for EYE, TARGET, UP."""
    fwd = vsm.normalize(tuple(t - e for t, e in zip(TARGET, EYE)))
    right = vsm.normalize(vsm.cross(fwd, UP))
    return fwd, right, vsm.cross(right, fwd)


def axial_depth(p) -> float:
    """Distance of `p` along the view axis: where dray's and Mitsuba's plane in focus is."""
    return sum((a - e) * f for a, e, f in zip(p, EYE, frame()[0]))


def euclidean(p) -> float:
    return math.dist(p, EYE)


def fstop_radius(n: float) -> float:
    """dray's f-number as a lens radius (core/src/view.rs `Aperture::radius`)."""
    film_h = FILM_BACK_MM / max(WIDTH / HEIGHT, 1.0)
    focal_mm = film_h * 0.5 / math.tan(math.radians(FOV_DEG) * 0.5)
    return focal_mm / (2.0 * n) / 1000.0


def sun_direction(az: float, el: float):
    """dray's direction toward the sun (core/src/sun.rs `Sun::new`)."""
    a, e = math.radians(az), math.radians(el)
    return (math.sin(a) * math.cos(e), math.sin(e), math.cos(a) * math.cos(e))


def build_cases() -> dict:
    """Each case: dray's extra flags, the Mitsuba sensor and light, and the controls (other
    Mitsuba renders that a wrong convention would match)."""
    near, far = SPHERES["near"], SPHERES["far"]
    fstop_r = fstop_radius(F_NUMBER)
    persp = {"type": "perspective"}
    mitsuba_sun = {"type": "directional", "direction": [-c for c in sun_direction(SUN[0], SUN[1])],
                   "irradiance": SUN[2]}
    mirrored = dict(mitsuba_sun, direction=[-c for c in sun_direction(-SUN[0], SUN[1])])
    gltf_sun = {"type": "directional", "direction": list(gvm.SUN_DIRECTION), "irradiance": gvm.SUN_IRRADIANCE}
    return {
        "pinhole": {"what": "pinhole, --fov 30 (vertical)", "dray": [], "sensor": persp, "light": gltf_sun,
                    "mapping": "perspective, fov 30, fov_axis y",
                    "controls": [{"what": "fov_axis x (Mitsuba's default: a horizontal field of view)",
                                  "sensor": dict(persp, fov_axis="x")}]},
        "lens_radius": {
            "what": f"--aperture {LENS_RADIUS} --focus-distance {axial_depth(near):.4f} (near sphere)",
            "dray": ["--aperture", LENS_RADIUS, "--focus-distance", f"{axial_depth(near):.6f}"],
            "sensor": {"type": "thinlens", "aperture_radius": LENS_RADIUS, "focus_distance": axial_depth(near)},
            "light": gltf_sun, "lens": True,
            "mapping": f"thinlens, aperture_radius {LENS_RADIUS}, focus_distance {axial_depth(near):.4f}",
            "controls": [{"what": f"focus_distance {euclidean(near):.4f}, the near sphere's Euclidean distance",
                          "sensor": {"type": "thinlens", "aperture_radius": LENS_RADIUS,
                                     "focus_distance": euclidean(near)}}]},
        "lens_fstop": {
            "what": f"--aperture f/{F_NUMBER:g} --focus-on {','.join(map(str, far))} (far sphere)",
            "dray": ["--aperture", f"f/{F_NUMBER:g}", "--focus-on", ",".join(map(str, far))],
            "sensor": {"type": "thinlens", "aperture_radius": fstop_r, "focus_distance": axial_depth(far)},
            "light": gltf_sun, "lens": True,
            "mapping": f"thinlens, aperture_radius {fstop_r:.5f} (f/{F_NUMBER:g}), focus_distance "
                       f"{axial_depth(far):.4f}",
            "controls": [{"what": f"aperture_radius {fstop_r * 1.5:.5f}, the f-number read against a 36 mm film "
                                  "height", "sensor": {"type": "thinlens", "aperture_radius": fstop_r * 1.5,
                                                        "focus_distance": axial_depth(far)}},
                         {"what": f"aperture_radius {fstop_r * 2:.5f}, focal length / N (the diameter) as the "
                                  "radius", "sensor": {"type": "thinlens", "aperture_radius": fstop_r * 2,
                                                        "focus_distance": axial_depth(far)}},
                         {"what": f"focus_distance {euclidean(far):.4f}, the far sphere's Euclidean distance",
                          "sensor": {"type": "thinlens", "aperture_radius": fstop_r,
                                     "focus_distance": euclidean(far)}}]},
        "sun": {"what": f"--sun {SUN[0]:g},{SUN[1]:g},{SUN[2]:g} (0.53-degree disk), no glTF light",
                "dray": ["--sun", f"{SUN[0]:g},{SUN[1]:g},{SUN[2]:g}"], "sensor": persp, "light": mitsuba_sun,
                "no_gltf_light": True,
                "mapping": "directional (a delta), direction "
                           + ", ".join(f"{c:.4f}" for c in mitsuba_sun["direction"]) + f", irradiance {SUN[2]:g}",
                "controls": [{"what": f"the sun at azimuth {-SUN[0]:g} (a mirrored convention)", "light": mirrored}]},
    }


# ---------------------------------------------------------------------------------------
# Scene
# ---------------------------------------------------------------------------------------

def meshes():
    """The three spheres as one mesh, and the ground, from gltf_vs_mitsuba's geometry."""
    import numpy as np

    unit = gvm.sphere_mesh(False)
    c0 = np.array(gvm.SPHERE_CENTER, np.float32)
    parts = []
    for i, c in enumerate(SPHERES.values()):
        pos = ((unit["pos"] - c0) / gvm.SPHERE_RADIUS * RADIUS + np.array(c, np.float32)).astype("<f4")
        parts.append(dict(unit, pos=pos, idx=unit["idx"] + i * len(pos)))
    spheres = {k: np.concatenate([p[k] for p in parts]) for k in unit}
    ground = gvm.ground_mesh()
    ground["pos"] = (ground["pos"] * SCALE).astype("<f4")
    return spheres, ground


def write_scene(out: Path, spheres, ground, with_light: bool) -> Path:
    """The glTF for dray (gltf_vs_mitsuba's writer; its camera is replaced by --look-from),
    with or without its directional light."""
    out.mkdir(parents=True, exist_ok=True)
    gvm.write_checker(out / "checker.png")
    material = gvm.mat("lambert", ALBEDO, 0.0, 1.0, dict(gvm.NO_SPEC))
    path = gvm.write_gltf(out, material, spheres, ground)
    if not with_light:
        doc = json.loads(path.read_text())
        doc["scenes"][0]["nodes"] = [0, 1, 2]
        doc["nodes"][3].pop("extensions")
        del doc["extensions"]
        doc["extensionsUsed"].remove("KHR_lights_punctual")
        path.write_text(json.dumps(doc, indent=1) + "\n")
    return path


def labels():
    """Per pixel: 1, 2, 3 where the pinhole centre ray first hits the near, mid, far sphere;
    0 elsewhere."""
    import numpy as np

    fwd, right, up = (np.array(v) for v in frame())
    t = math.tan(math.radians(FOV_DEG) / 2)
    x = (2 * (np.arange(WIDTH) + 0.5) / WIDTH - 1) * t * WIDTH / HEIGHT
    y = (1 - 2 * (np.arange(HEIGHT) + 0.5) / HEIGHT) * t
    d = fwd + x[None, :, None] * right + y[:, None, None] * up
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    best = np.full((HEIGHT, WIDTH), np.inf)
    lab = np.zeros((HEIGHT, WIDTH), np.int32)
    for i, c in enumerate(SPHERES.values(), 1):
        oc = np.array(EYE) - np.array(c)
        b = d @ oc
        disc = b * b - (oc @ oc - RADIUS ** 2)
        tt = np.where(disc > 0, -b - np.sqrt(np.maximum(disc, 0.0)), np.inf)
        closer = tt < best
        lab[closer], best[closer] = i, tt[closer]
    return lab


def flip_regions(ref, test, lab, path: Path | None = None) -> dict:
    """Mean FLIP over the image and over each sphere's pixels; the error map goes to `path`."""
    import flip_evaluator as flip
    import numpy as np

    raw, mean, _ = flip.evaluate(ref, test, "LDR", applyMagma=False)
    raw = np.asarray(raw)
    raw = raw[..., 0] if raw.ndim == 3 else raw
    if path is not None:
        vsm.save_png(np.asarray(flip.evaluate(ref, test, "LDR")[0]), path)
    out = {"image": float(mean)}
    for i, name in enumerate(SPHERES, 1):
        out[name] = float(raw[lab == i].mean())
    return out


# ---------------------------------------------------------------------------------------
# Mitsuba worker (own process, pinned): python lens_sun_vs_mitsuba.py --mitsuba-worker cfg.json
# ---------------------------------------------------------------------------------------

def mitsuba_worker(cfg_path: Path) -> None:
    import drjit as dr
    import mitsuba as mi
    import numpy as np

    cfg = json.loads(cfg_path.read_text())
    mi.set_variant(cfg["variant"])
    dr.set_thread_count(cfg["threads"])
    spheres = {k: np.load(v) for k, v in cfg["sphere"].items()}
    ground = {k: np.load(v) for k, v in cfg["ground"].items()}
    checker = {"type": "diffuse", "reflectance": {"type": "bitmap", "filename": cfg["checker"],
                                                  "filter_type": "bilinear", "wrap_mode": "repeat"}}
    film = {"type": "hdrfilm", "width": WIDTH, "height": HEIGHT, "pixel_format": "rgb", "rfilter": {"type": "box"}}
    runs = []
    for run in cfg["runs"]:
        t0 = time.perf_counter()
        sensor = dict({"fov_axis": "y"}, **run["sensor"], fov=FOV_DEG, near_clip=NEAR_CLIP, far_clip=1e4, film=film,
                      to_world=mi.ScalarTransform4f().look_at(origin=EYE, target=TARGET, up=UP),
                      sampler={"type": "independent", "sample_count": cfg["spp"]})
        light = dict(run["light"], irradiance=gvm.rgb(run["light"]["irradiance"]))
        scene = mi.load_dict({
            "type": "scene",
            "integrator": {"type": "path", "max_depth": cfg["max_depth"], "rr_depth": gvm.MITSUBA_RR_DEPTH},
            "sensor": sensor,
            "spheres": gvm.mi_mesh(mi, "spheres", spheres, {"type": "diffuse", "reflectance": gvm.rgb(ALBEDO)}),
            "ground": gvm.mi_mesh(mi, "ground", ground, checker),
            "light": light,
            "env": {"type": "constant", "radiance": gvm.rgb(ENV_RADIANCE)},
        })
        t1, c1 = time.perf_counter(), time.process_time()
        img = np.array(mi.render(scene, spp=cfg["spp"], seed=run["seed"]), dtype=np.float32)[..., :3]
        t2, c2 = time.perf_counter(), time.process_time()
        if run.get("save"):
            np.save(run["save"], img)
        runs.append({"seed": run["seed"], "load_s": t1 - t0, "render_s": t2 - t1, "total_s": t2 - t0,
                     "render_cpu_s": c2 - c1})
        print(f"run: {runs[-1]}", file=sys.stderr, flush=True)
    print(json.dumps({"variant": cfg["variant"], "thread_count": dr.thread_count(), "runs": runs}))


# ---------------------------------------------------------------------------------------
# Driver
# ---------------------------------------------------------------------------------------

def parse_args():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", help="comma-separated case names (default: all): " + ", ".join(build_cases()))
    ap.add_argument("--spp", type=int, default=256, help="samples per pixel of every render (default 256)")
    ap.add_argument("--max-depth", type=int, default=4, help="dray's --max-depth; Mitsuba's is one more")
    gvm.add_comparison_args(ap, env.OUT / "lens_sun_vs_mitsuba")
    args = ap.parse_args()
    if args.mitsuba_worker:
        return args
    names = list(build_cases())
    args.case_names = names if not args.cases else [c.strip() for c in args.cases.split(",") if c.strip()]
    bad = [c for c in args.case_names if c not in names]
    if bad:
        ap.error(f"--cases: unknown case(s) {bad}; known: {names}")
    if min(args.spp, args.max_depth, args.runs, args.threads) < 1:
        ap.error("--spp, --max-depth, --runs and --threads must be positive")
    if args.threads > len(env.parse_cores(args.cores)):
        ap.error("--threads is more than the number of --cores")
    return args


def run_dray(args, dray, gltf: Path, out: Path, tag: str, seed: int, extra: list) -> dict:
    exr, stats = out / f"dray_{tag}.exr", out / f"dray_{tag}.stats.json"
    view = ["--look-from", ",".join(map(str, EYE)), "--look-at", ",".join(map(str, TARGET)), "--fov", FOV_DEG]
    cmd = env.pin(args.cores, [dray, "render", gltf, "--width", WIDTH, "--height", HEIGHT, "--spp", args.spp,
                               "--integrator", "path", "--max-depth", args.max_depth, "--seed", seed, *view,
                               *extra, "--env", ",".join([str(ENV_RADIANCE)] * 3), "--threads", args.threads,
                               "--output", out / f"dray_{tag}.png", "--exr", exr, "--stats", stats, "-q"])
    r = env.run_timed(cmd)
    return {"cmd": r["cmd"], "wall_s": r["wall_s"], "cpu_s": r["cpu_s"],
            "render_s": json.loads(stats.read_text())["render_time_s"], "exr": str(exr)}


def run_mitsuba(args, cfg: dict, tag: str, extra_env: dict) -> dict:
    """Mitsuba's renders of one case in their own pinned process (this file's worker)."""
    path = args.out / f"mitsuba_{tag}.json"
    path.write_text(json.dumps(cfg))
    e = dict(os.environ, **extra_env, HOME=str(args.out / "drjit_home"))  # Dr.Jit's kernel cache: with the outputs
    r = env.run_timed(env.pin(args.cores, [sys.executable, Path(__file__).resolve(), "--mitsuba-worker", path]), env=e)
    return dict(env.last_json_line(r["stdout"]), cmd=r["cmd"])


def run_case(args, dray, name: str, case: dict, scenes: dict, base_cfg: dict, lab, pinhole_ldr) -> dict:
    import numpy as np

    out = args.out / name
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    gltf = scenes["sun" if case.get("no_gltf_light") else "lit"]
    res = {"name": name, "what": case["what"], "mapping": case["mapping"]}

    druns = [run_dray(args, dray, gltf, out, f"run{r}", args.seed, case["dray"]) for r in range(args.runs)]
    d2 = run_dray(args, dray, gltf, out, "seed2", args.seed + 1000, case["dray"])
    res["dray"] = {"render_s": statistics.median(x["render_s"] for x in druns),
                   "wall_s": statistics.median(x["wall_s"] for x in druns),
                   "cpu_s": statistics.median(x["cpu_s"] for x in druns), "cmd": druns[0]["cmd"]}
    img_d = vsm.read_exr(druns[0]["exr"])
    ldr_d = vsm.tonemap(img_d)
    vsm.save_png(ldr_d, out / "dray.png")

    runs = [{"seed": args.seed, "save": str(out / "mitsuba_a.npy")},
            {"seed": args.seed + 1000, "save": str(out / "mitsuba_b.npy")}]
    runs += [{"seed": args.seed + 2000 + r} for r in range(args.runs - 1)]
    runs = [dict(r, sensor=case["sensor"], light=case["light"]) for r in runs]
    controls = case.get("controls", [])
    runs += [{"seed": args.seed, "save": str(out / f"mitsuba_control{i}.npy"), "sensor": c.get("sensor", case["sensor"]),
              "light": c.get("light", case["light"])} for i, c in enumerate(controls)]
    m = run_mitsuba(args, dict(base_cfg, runs=runs), name, scenes["llvm_env"])
    warm = m["runs"][1:args.runs + 1]
    res["mitsuba"] = {"render_s": statistics.median(x["render_s"] for x in warm),
                      "total_s": statistics.median(x["total_s"] for x in warm),
                      "render_cpu_s": statistics.median(x["render_cpu_s"] for x in warm),
                      "cold_total_s": m["runs"][0]["total_s"], "cmd": m["cmd"]}
    img_a, img_b = np.load(out / "mitsuba_a.npy"), np.load(out / "mitsuba_b.npy")
    ldr_a = vsm.tonemap(img_a)
    vsm.save_png(ldr_a, out / "mitsuba.png")
    res["flip_dray_vs_mitsuba"] = flip_regions(ldr_a, ldr_d, lab, out / "flip_dray_vs_mitsuba.png")
    res["flip_mitsuba_vs_mitsuba"] = flip_regions(ldr_a, vsm.tonemap(img_b), lab)
    res["flip_dray_vs_dray"] = flip_regions(vsm.tonemap(vsm.read_exr(d2["exr"])), ldr_d, lab)
    res["mean_ratio_dray_over_mitsuba"] = float(img_d.mean() / max(img_a.mean(), 1e-9))
    res["mean_ratio_mitsuba_seeds"] = float(img_b.mean() / max(img_a.mean(), 1e-9))
    res["controls"] = []
    for i, c in enumerate(controls):
        ldr_c = vsm.tonemap(np.load(out / f"mitsuba_control{i}.npy"))
        vsm.save_png(ldr_c, out / f"mitsuba_control{i}.png")
        res["controls"].append({"what": c["what"], "flip_dray_vs_control": flip_regions(ldr_c, ldr_d, lab)})
    if case.get("lens") and pinhole_ldr is not None:
        res["flip_lens_vs_pinhole_dray"] = flip_regions(pinhole_ldr, ldr_d, lab)
    for f in out.glob("mitsuba_*.npy"):
        f.unlink()
    env.log(f"  FLIP dray vs mitsuba {res['flip_dray_vs_mitsuba']} (mitsuba vs mitsuba "
            f"{res['flip_mitsuba_vs_mitsuba']}); dray {res['dray']['render_s']:.2f} s, mitsuba "
            f"{res['mitsuba']['render_s']:.2f} s")
    return res, ldr_d


def main(args) -> None:
    import numpy as np

    args.out.mkdir(parents=True, exist_ok=True)
    dray = env.dray_binary()
    spheres, ground = meshes()
    arrays = args.out / "arrays"
    arrays.mkdir(exist_ok=True)
    files: dict = {"sphere": {}, "ground": {}}
    for key, m in (("sphere", spheres), ("ground", ground)):
        for k, a in m.items():
            np.save(arrays / f"{key}_{k}.npy", a)
            files[key][k] = str(arrays / f"{key}_{k}.npy")
    scenes = {"lit": write_scene(args.out / "scene_lit", spheres, ground, True),
              "sun": write_scene(args.out / "scene_sun", spheres, ground, False)}
    fwd, right, up = frame()
    base_cfg = {"camera": [list(EYE), list(right), list(up), list(fwd)], "width": WIDTH, "height": HEIGHT,
                "max_depth": args.max_depth + 1, "rr_depth": gvm.MITSUBA_RR_DEPTH, "threads": args.threads,
                "spp": args.spp, "checker": str(args.out / "scene_lit" / "checker.png"), **files}
    info = env.machine_info()
    info["busy_cores_before_start"] = round(env.idle_check(), 2)
    load = env.OtherLoad()
    info["packages"] = env.package_versions(["mitsuba", "drjit", "flip-evaluator", "numpy"])
    info["dray_binary"] = env.binary_info(dray)
    info["variant"], scenes["llvm_env"] = gvm.pick_variant(args, base_cfg)
    base_cfg["variant"] = info["variant"]
    env.log(f"mitsuba variant {info['variant']} {scenes['llvm_env'] or ''}")
    lab = labels()
    results, pinhole = [], None
    cases = build_cases()
    # The pinhole first: the lens rows compare against its dray render.
    for name in sorted(args.case_names, key=lambda n: n != "pinhole"):
        env.log(f"case {name}: {cases[name]['what']}")
        r, ldr = run_case(args, dray, name, cases[name], scenes, base_cfg, lab, pinhole)
        pinhole = ldr if name == "pinhole" else pinhole
        results.append(r)
    shutil.rmtree(args.out / "drjit_home", ignore_errors=True)
    env.save_results(args.out / "results.json", info, args, results, load)
    report(info, args, results)


def regions(f: dict) -> str:
    return f"{f['image']:.4f} ({f['near']:.4f} / {f['mid']:.4f} / {f['far']:.4f})"


def report(info: dict, args, results: list) -> None:
    print(f"# Thin lens and sun, dray against Mitsuba {info['packages']['mitsuba']} ({info['variant']}), "
          f"{WIDTH}x{HEIGHT}, {args.spp} spp, dray --max-depth {args.max_depth} (Mitsuba max_depth "
          f"{args.max_depth + 1}), {args.threads} threads on cores {args.cores}, runs {args.runs} (median times)")
    print(f"# {info['cpu_model']}, {info['date']}, dray {info['dray_git']}; busy cores before the start "
          f"{info['busy_cores_before_start']:.2f}, other processes used {info['other_processes_cores_during_run']:.2f}"
          " cores on average during the run")
    print("# FLIP: mean over the image (over the near / mid / far sphere's pixels)")
    print("\n| case (dray) | Mitsuba | FLIP dray vs Mitsuba | FLIP Mitsuba vs Mitsuba (seed) | FLIP dray vs dray "
          "(seed) | mean dray/Mitsuba | dray wall (s) | dray render (s) | dray CPU (s) | Mitsuba render, warm (s) "
          "| Mitsuba render CPU (s) |")
    print("|---|---|---|---|---|---:|---:|---:|---:|---:|---:|")
    for r in results:
        print(f"| {r['what']} | {r['mapping']} | {regions(r['flip_dray_vs_mitsuba'])} | "
              f"{regions(r['flip_mitsuba_vs_mitsuba'])} | {regions(r['flip_dray_vs_dray'])} | "
              f"{r['mean_ratio_dray_over_mitsuba']:.4f} | {r['dray']['wall_s']:.2f} | {r['dray']['render_s']:.2f} | "
              f"{r['dray']['cpu_s']:.2f} | {r['mitsuba']['render_s']:.2f} | {r['mitsuba']['render_cpu_s']:.2f} |")
    print()
    for r in results:
        for c in r["controls"]:
            print(f"- {r['name']}: control, dray against Mitsuba with {c['what']}: FLIP "
                  f"{regions(c['flip_dray_vs_control'])}")
        if "flip_lens_vs_pinhole_dray" in r:
            print(f"- {r['name']}: dray's lens render against dray's pinhole render: FLIP "
                  f"{regions(r['flip_lens_vs_pinhole_dray'])}")
    print(f"\noutputs: {args.out}")


if __name__ == "__main__":
    env.ensure_venv()
    cli = parse_args()
    if cli.mitsuba_worker:
        mitsuba_worker(cli.mitsuba_worker)
    else:
        main(cli)

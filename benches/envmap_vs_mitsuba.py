#!/usr/bin/env python3
"""dray's environment map (`--env-map`, `--env-rotation`) against Mitsuba 3's `envmap` emitter
on a public HDRI, with NVIDIA FLIP, side by side with time (issue 39).

The HDRI: one of the studio-light worlds Blender ships (datafiles/studiolights/world/*.exr,
1024 x 512 OpenEXR, by Greg Zaal for HDRI Haven, now Poly Haven; CC0 by the license.txt beside
them), taken from Debian's `blender-data` package (3.4.1+dfsg-2): `apt-get download
blender-data` and `dpkg -x` into target/hdri-cache/ (not into the repository), once. Default
`courtyard.exr` (a sunny courtyard: a sharp bright sky and coloured walls, peak 56), turned by
--rotation degrees.

Scene: a Lambert sphere (albedo 0.8) and a glossy metal sphere (grey 0.9, roughness 0.2), radius
1, side by side on a checkered Lambert ground quad (12 x 12), lit only by the map (no other
light, no constant environment), seen at 384 x 256 by a pinhole camera (vertical fov 35) that
also sees the map behind them. The meshes are benches/gltf_vs_mitsuba.py's (its 96 x 48 UV
sphere and ground), written as a glTF for dray and given to Mitsuba as the same triangles
through `mi.Mesh`; the metal is glTF metallic-roughness against `principled` metallic 1
(gltf_vs_mitsuba's "metal" row: the same lobe but for Smith masking).

Conventions (checked here, each by a control Mitsuba render that a wrong one would match):
- Orientation: both map +Y up and azimuth phi = atan2(x, -z) to u, increasing toward +X, but
  Mitsuba's u = phi / 2 pi (the image's left edge looks along -Z, its centre along +Z) and
  dray's u = 0.5 + phi / 2 pi (its centre along -Z). So dray's map turned by R is Mitsuba's
  with `to_world` = rotate(+Y, R + 180). Controls: rotate(+Y, R) (no half-turn) and
  rotate(+Y, 180 - R) (the rotation's sense reversed, which dray had before this benchmark).
- Radiance scale: both read the EXR's linear RGB as radiance, scale 1 (Mitsuba's rgb variant
  does no colour conversion). The mean linear radiance dray / Mitsuba, per region, at the
  references' spp shows a bias FLIP could hide.
- Filtering: both interpolate bilinearly (dray since 2026-11-30; before, it looked pixels up
  without filtering, and the background, the map magnified about 3.5 times here, differed at
  pixel edges). Texels are centred in u in both; in v Mitsuba puts the first and last rows at
  the poles, dray at the rows' centres (half a row apart toward the poles, none at the
  horizon). Reflected by the spheres and integrated by the ground such differences hardly
  show, so FLIP is reported per region: the image, the background (pixels whose centre ray
  leaves the scene), the ground, the diffuse and the glossy sphere.

Renders: dray and Mitsuba at --spp (the comparison at equal spp), each again with another seed,
and each at --ref-spp (its own reference). Reported per region: FLIP dray against Mitsuba at
equal spp; each against its own reference (its noise at --spp: "within its noise" means the
first is not much above these); dray's reference against Mitsuba's (what is left at high spp:
the model differences); and the controls.

Timed: dray's render_time_s (--stats) and the whole process's wall and CPU time; Mitsuba's warm
`mi.render` (the first render compiles its kernels) and its CPU time; both pinned to the same
cores with the same thread count; --runs N repeats and reports medians.

Depth: dray --max-depth D, Mitsuba max_depth D + 1 and rr_depth 4 (benches/vs_mitsuba.py says
why).

Usage (from the repository root; creates benches/.venv on first use):
    benches/envmap_vs_mitsuba.sh                        # builds dray, then runs this
    python3 benches/envmap_vs_mitsuba.py [--map sunset] [--rotation 60] [--spp 64] [--ref-spp 1024]
    python3 benches/envmap_vs_mitsuba.py --hdri FILE.exr  # any equirectangular map instead
Outputs go to benches/out/envmap_vs_mitsuba/ (PNGs of every render, the FLIP map, the glTF,
results.json).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _bench_env as env  # noqa: E402
import gltf_vs_mitsuba as gvm  # noqa: E402  (meshes, glTF buffer, mi.Mesh, variant pick)
import vs_mitsuba as vsm  # noqa: E402  (tonemap, read_exr, save_png, vector helpers)

WIDTH, HEIGHT = 384, 256
FOV_DEG = 35.0  # vertical
EYE = (0.0, 1.7, 6.2)
TARGET = (0.0, 1.0, 0.0)
UP = (0.0, 1.0, 0.0)
NEAR_CLIP = 1e-3
SPHERES = {"diffuse": (-1.15, 1.0, 0.0), "glossy": (1.15, 1.0, 0.0)}
RADIUS = 1.0
DIFFUSE_ALBEDO = (0.8, 0.8, 0.8)
GLOSSY_BASE = (0.9, 0.9, 0.9)
GLOSSY_ROUGHNESS = 0.2
BLENDER_DATA = "blender-data"
STUDIOLIGHTS = "usr/share/blender/datafiles/studiolights/world"
MAPS = ("courtyard", "city", "forest", "interior", "night", "studio", "sunrise", "sunset")
REGIONS = ("image", "background", "ground", "diffuse", "glossy")


# ---------------------------------------------------------------------------------------
# The HDRI
# ---------------------------------------------------------------------------------------

def fetch_hdri(name: str) -> tuple[Path, str]:
    """Blender's studio-light world `name`.exr from Debian's blender-data, unpacked once into
    target/hdri-cache/. Returns the file and the licence text shipped beside it."""
    cache = env.ROOT / "target" / "hdri-cache"
    world = cache / STUDIOLIGHTS
    if not (world / f"{name}.exr").exists():
        if not shutil.which("apt-get") or not shutil.which("dpkg-deb"):
            sys.exit("apt-get and dpkg-deb are needed to fetch Debian's blender-data (or pass --hdri FILE)")
        cache.mkdir(parents=True, exist_ok=True)
        env.log(f"apt-get download {BLENDER_DATA} into {cache}")
        p = subprocess.run(["apt-get", "download", BLENDER_DATA], cwd=cache, capture_output=True, text=True)
        debs = sorted(cache.glob(f"{BLENDER_DATA}_*.deb"))
        if p.returncode != 0 or not debs:
            sys.exit(f"`apt-get download {BLENDER_DATA}` failed (exit {p.returncode}; run `apt-get update` "
                     f"first?): {p.stderr.strip()[-300:]}")
        subprocess.run(["dpkg-deb", "-x", str(debs[-1]), str(cache)], check=True)
        (cache / "package.txt").write_text(debs[-1].name + "\n")
        debs[-1].unlink()
    path = world / f"{name}.exr"
    if not path.exists():
        sys.exit(f"{path} is not in {BLENDER_DATA}; the worlds there: {sorted(p.stem for p in world.glob('*.exr'))}")
    licence = (world / "license.txt").read_text().strip() if (world / "license.txt").exists() else "(no license.txt)"
    return path, licence


# ---------------------------------------------------------------------------------------
# Scene
# ---------------------------------------------------------------------------------------

def frame():
    fwd = vsm.normalize(tuple(t - e for t, e in zip(TARGET, EYE)))
    right = vsm.normalize(vsm.cross(fwd, UP))
    return fwd, right, vsm.cross(right, fwd)


def meshes():
    """Each sphere (gltf_vs_mitsuba's, moved) and the ground."""
    import numpy as np

    unit = gvm.sphere_mesh(False)
    c0 = np.array(gvm.SPHERE_CENTER, np.float32)
    out = {}
    for name, c in SPHERES.items():
        pos = ((unit["pos"] - c0) / gvm.SPHERE_RADIUS * RADIUS + np.array(c, np.float32)).astype("<f4")
        out[name] = dict(unit, pos=pos)
    out["ground"] = gvm.ground_mesh()
    return out


def materials() -> dict:
    """glTF materials for dray and the Mitsuba BSDFs, per mesh."""
    return {
        "diffuse": (gvm.mat("diffuse", DIFFUSE_ALBEDO, 0.0, 1.0, dict(gvm.NO_SPEC)),
                    {"type": "diffuse", "reflectance": gvm.rgb(DIFFUSE_ALBEDO)}),
        "glossy": (gvm.mat("glossy", GLOSSY_BASE, 1.0, GLOSSY_ROUGHNESS),
                   {"type": "principled", "base_color": gvm.rgb(GLOSSY_BASE), "metallic": 1.0,
                    "roughness": GLOSSY_ROUGHNESS}),
    }


def write_scene(out: Path, ms: dict) -> Path:
    """The glTF for dray: two spheres and the checkered ground, no camera (--look-from) and no
    light (the map is the only one)."""
    out.mkdir(parents=True, exist_ok=True)
    gvm.write_checker(out / "checker.png")
    buf = gvm.Buffer()

    def prim(m, material):
        attrs = {"POSITION": buf.add(m["pos"], "VEC3", 34962, True), "NORMAL": buf.add(m["nrm"], "VEC3", 34962),
                 "TEXCOORD_0": buf.add(m["uv"], "VEC2", 34962)}
        if "tan" in m:
            attrs["TANGENT"] = buf.add(m["tan"], "VEC4", 34962)
        return {"attributes": attrs, "indices": buf.add(m["idx"].reshape(-1), "SCALAR", 34963),
                "material": material, "mode": 4}

    mats = materials()
    ground_material = {"name": "checker", "doubleSided": True,
                       "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}, "metallicFactor": 0.0,
                                                "roughnessFactor": 1.0},
                       "extensions": dict(gvm.NO_SPEC)}
    names = ["diffuse", "glossy", "ground"]
    doc = {
        "asset": {"version": "2.0", "generator": "dray benches/envmap_vs_mitsuba.py"},
        "extensionsUsed": ["KHR_materials_specular"],
        "scene": 0,
        "scenes": [{"nodes": [0, 1, 2]}],
        "nodes": [{"name": n, "mesh": i} for i, n in enumerate(names)],
        "materials": [mats["diffuse"][0], mats["glossy"][0], ground_material],
        "meshes": [{"name": n, "primitives": [prim(ms[n], i)]} for i, n in enumerate(names)],
        "images": [{"uri": "checker.png"}],
        "samplers": [{"magFilter": 9729, "minFilter": 9729, "wrapS": 10497, "wrapT": 10497}],
        "textures": [{"source": 0, "sampler": 0}],
        "buffers": [{"uri": "scene.bin", "byteLength": len(buf.data)}],
        "bufferViews": buf.views,
        "accessors": buf.accessors,
    }
    (out / "scene.bin").write_bytes(bytes(buf.data))
    path = out / "scene.gltf"
    path.write_text(json.dumps(doc, indent=1) + "\n")
    return path


def labels():
    """Per pixel, what the pinhole centre ray hits first: 1 diffuse sphere, 2 glossy sphere,
    3 ground, 0 nothing (the map)."""
    import numpy as np

    fwd, right, up = (np.array(v) for v in frame())
    t = math.tan(math.radians(FOV_DEG) / 2)
    x = (2 * (np.arange(WIDTH) + 0.5) / WIDTH - 1) * t * WIDTH / HEIGHT
    y = (1 - 2 * (np.arange(HEIGHT) + 0.5) / HEIGHT) * t
    d = fwd + x[None, :, None] * right + y[:, None, None] * up
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    eye = np.array(EYE)
    best = np.full((HEIGHT, WIDTH), np.inf)
    lab = np.zeros((HEIGHT, WIDTH), np.int32)
    for i, c in enumerate(SPHERES.values(), 1):
        oc = eye - np.array(c)
        b = d @ oc
        disc = b * b - (oc @ oc - RADIUS ** 2)
        tt = np.where(disc > 0, -b - np.sqrt(np.maximum(disc, 0.0)), np.inf)
        closer = tt < best
        lab[closer], best[closer] = i, tt[closer]
    with np.errstate(divide="ignore", invalid="ignore"):
        tg = np.where(d[..., 1] < 0, -eye[1] / d[..., 1], np.inf)
    px, pz = eye[0] + tg * d[..., 0], eye[2] + tg * d[..., 2]
    on = (np.abs(px) <= gvm.GROUND_HALF) & (np.abs(pz) <= gvm.GROUND_HALF) & (tg < best)
    lab[on] = 3
    return lab


def flip_regions(ref, test, lab, path: Path | None = None) -> dict:
    """Mean FLIP over the image and over each region's pixels; the error map goes to `path`."""
    import flip_evaluator as flip
    import numpy as np

    raw, mean, _ = flip.evaluate(ref, test, "LDR", applyMagma=False)
    raw = np.asarray(raw)
    raw = raw[..., 0] if raw.ndim == 3 else raw
    if path is not None:
        vsm.save_png(np.asarray(flip.evaluate(ref, test, "LDR")[0]), path)
    out = {"image": float(mean)}
    for i, name in ((0, "background"), (3, "ground"), (1, "diffuse"), (2, "glossy")):
        out[name] = float(raw[lab == i].mean())
    return out


def mean_ratio(a, b, lab) -> dict:
    """Mean linear radiance a / b over the image and each region (all channels)."""
    out = {"image": float(a.mean() / max(b.mean(), 1e-9))}
    for i, name in ((0, "background"), (3, "ground"), (1, "diffuse"), (2, "glossy")):
        m = lab == i
        out[name] = float(a[m].mean() / max(b[m].mean(), 1e-9))
    return out


# ---------------------------------------------------------------------------------------
# Mitsuba worker (own process, pinned): python envmap_vs_mitsuba.py --mitsuba-worker cfg.json
# ---------------------------------------------------------------------------------------

def mitsuba_worker(cfg_path: Path) -> None:
    import drjit as dr
    import mitsuba as mi
    import numpy as np

    cfg = json.loads(cfg_path.read_text())
    mi.set_variant(cfg["variant"])
    dr.set_thread_count(cfg["threads"])
    ms = {n: {k: np.load(v) for k, v in files.items()} for n, files in cfg["meshes"].items()}
    checker = {"type": "diffuse", "reflectance": {"type": "bitmap", "filename": cfg["checker"],
                                                  "filter_type": "bilinear", "wrap_mode": "repeat"}}
    bsdfs = {n: b for n, (_, b) in materials().items()}
    film = {"type": "hdrfilm", "width": WIDTH, "height": HEIGHT, "pixel_format": "rgb", "rfilter": {"type": "box"}}
    runs = []
    for run in cfg["runs"]:
        t0 = time.perf_counter()
        scene = mi.load_dict({
            "type": "scene",
            "integrator": {"type": "path", "max_depth": cfg["max_depth"], "rr_depth": gvm.MITSUBA_RR_DEPTH},
            "sensor": {"type": "perspective", "fov_axis": "y", "fov": FOV_DEG, "near_clip": NEAR_CLIP,
                       "far_clip": 1e4, "film": film,
                       "to_world": mi.ScalarTransform4f().look_at(origin=EYE, target=TARGET, up=UP),
                       "sampler": {"type": "independent", "sample_count": run["spp"]}},
            "diffuse": gvm.mi_mesh(mi, "diffuse", ms["diffuse"], bsdfs["diffuse"]),
            "glossy": gvm.mi_mesh(mi, "glossy", ms["glossy"], bsdfs["glossy"]),
            "ground": gvm.mi_mesh(mi, "ground", ms["ground"], checker),
            "env": {"type": "envmap", "filename": cfg["hdri"],
                    "to_world": mi.ScalarTransform4f().rotate(axis=[0, 1, 0], angle=run["rotate_y"])},
        })
        t1, c1 = time.perf_counter(), time.process_time()
        img = np.array(mi.render(scene, spp=run["spp"], seed=run["seed"]), dtype=np.float32)[..., :3]
        t2, c2 = time.perf_counter(), time.process_time()
        if run.get("save"):
            np.save(run["save"], img)
        runs.append({"tag": run["tag"], "seed": run["seed"], "spp": run["spp"], "load_s": t1 - t0,
                     "render_s": t2 - t1, "render_cpu_s": c2 - c1})
        print(f"run: {runs[-1]}", file=sys.stderr, flush=True)
    print(json.dumps({"variant": cfg["variant"], "thread_count": dr.thread_count(), "runs": runs}))


# ---------------------------------------------------------------------------------------
# Driver
# ---------------------------------------------------------------------------------------

def parse_args():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--map", default="courtyard", choices=MAPS,
                    help="Blender's studio-light world from Debian's blender-data (default courtyard)")
    ap.add_argument("--hdri", type=Path, help="an equirectangular .exr to use instead of --map")
    ap.add_argument("--rotation", type=float, default=60.0, help="dray's --env-rotation (default 60)")
    ap.add_argument("--spp", type=int, default=64, help="spp of the equal-spp comparison (default 64)")
    ap.add_argument("--ref-spp", type=int, default=1024, help="spp of each renderer's reference (default 1024)")
    ap.add_argument("--max-depth", type=int, default=8, help="dray's --max-depth; Mitsuba's is one more")
    gvm.add_comparison_args(ap, env.OUT / "envmap_vs_mitsuba")
    args = ap.parse_args()
    if args.mitsuba_worker:
        return args
    if min(args.spp, args.ref_spp, args.max_depth, args.runs, args.threads) < 1:
        ap.error("--spp, --ref-spp, --max-depth, --runs and --threads must be positive")
    if args.ref_spp <= args.spp:
        ap.error("--ref-spp must be more than --spp")
    if not math.isfinite(args.rotation):
        ap.error("--rotation must be a finite number of degrees")
    if args.hdri is not None and not args.hdri.is_file():
        ap.error(f"--hdri {args.hdri}: no such file")
    if args.threads > len(env.parse_cores(args.cores)):
        ap.error("--threads is more than the number of --cores")
    return args


def run_dray(args, dray, gltf: Path, hdri: Path, tag: str, spp: int, seed: int) -> dict:
    out = args.out
    exr, stats = out / f"dray_{tag}.exr", out / f"dray_{tag}.stats.json"
    cmd = env.pin(args.cores, [dray, "render", gltf, "--width", WIDTH, "--height", HEIGHT, "--spp", spp,
                               "--integrator", "path", "--max-depth", args.max_depth, "--seed", seed,
                               "--look-from", ",".join(map(str, EYE)), "--look-at", ",".join(map(str, TARGET)),
                               "--fov", FOV_DEG, "--env-map", hdri, "--env-rotation", args.rotation,
                               "--threads", args.threads, "--output", out / f"dray_{tag}.png", "--exr", exr,
                               "--stats", stats, "-q"])
    r = env.run_timed(cmd)
    return {"cmd": r["cmd"], "wall_s": r["wall_s"], "cpu_s": r["cpu_s"],
            "render_s": json.loads(stats.read_text())["render_time_s"], "exr": str(exr)}


def run_mitsuba(args, cfg: dict, extra_env: dict) -> dict:
    path = args.out / "mitsuba_cfg.json"
    path.write_text(json.dumps(cfg))
    e = dict(os.environ, **extra_env, HOME=str(args.out / "drjit_home"))  # Dr.Jit's kernel cache: with the outputs
    r = env.run_timed(env.pin(args.cores, [sys.executable, Path(__file__).resolve(), "--mitsuba-worker", path]), env=e)
    return dict(env.last_json_line(r["stdout"]), cmd=r["cmd"])


def main(args) -> None:
    import numpy as np

    out = args.out
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    dray = env.dray_binary()
    if args.hdri is not None:
        hdri, licence, source = args.hdri.resolve(), "(given with --hdri)", str(args.hdri)
    else:
        hdri, licence = fetch_hdri(args.map)
        pkg = (env.ROOT / "target" / "hdri-cache" / "package.txt")
        source = f"Debian {pkg.read_text().strip() if pkg.exists() else BLENDER_DATA}: {STUDIOLIGHTS}/{hdri.name}"
    env.log(f"map {hdri} ({source}); licence: {licence}")
    ms = meshes()
    arrays = out / "arrays"
    arrays.mkdir()
    files: dict = {}
    for name, m in ms.items():
        files[name] = {}
        for k, a in m.items():
            np.save(arrays / f"{name}_{k}.npy", a)
            files[name][k] = str(arrays / f"{name}_{k}.npy")
    gltf = write_scene(out / "scene", ms)
    fwd, right, up = frame()
    base_cfg = {"camera": [list(EYE), list(right), list(up), list(fwd)], "width": WIDTH, "height": HEIGHT,
                "max_depth": args.max_depth + 1, "rr_depth": gvm.MITSUBA_RR_DEPTH, "threads": args.threads,
                "spp": args.spp, "checker": str(out / "scene" / "checker.png"), "sphere": files["diffuse"],
                "ground": files["ground"], "meshes": files}
    info = env.machine_info()
    info["busy_cores_before_start"] = round(env.idle_check(), 2)
    load = env.OtherLoad()
    info["packages"] = env.package_versions(["mitsuba", "drjit", "flip-evaluator", "numpy"])
    info["dray_binary"] = env.binary_info(dray)
    info["hdri"] = {"path": str(hdri), "source": source, "licence": licence}
    info["variant"], llvm_env = gvm.pick_variant(args, base_cfg)
    env.log(f"mitsuba variant {info['variant']} {llvm_env or ''}")
    lab = labels()

    env.log(f"dray: {args.runs} x {args.spp} spp, another seed, {args.ref_spp} spp reference")
    druns = [run_dray(args, dray, gltf, hdri, f"run{r}", args.spp, args.seed) for r in range(args.runs)]
    d_b = run_dray(args, dray, gltf, hdri, "seed2", args.spp, args.seed + 1000)
    d_ref = run_dray(args, dray, gltf, hdri, "ref", args.ref_spp, args.seed + 2000)

    rot = args.rotation + 180.0
    runs = [{"tag": "a", "seed": args.seed, "spp": args.spp, "rotate_y": rot, "save": str(out / "mi_a.npy")},
            {"tag": "b", "seed": args.seed + 1000, "spp": args.spp, "rotate_y": rot, "save": str(out / "mi_b.npy")}]
    runs += [{"tag": f"warm{r}", "seed": args.seed + 3000 + r, "spp": args.spp, "rotate_y": rot}
             for r in range(args.runs - 1)]
    runs += [{"tag": "ref", "seed": args.seed + 2000, "spp": args.ref_spp, "rotate_y": rot,
              "save": str(out / "mi_ref.npy")}]
    controls = [{"what": f"rotate(+Y, {args.rotation:g}): no half-turn (the image's centre along +Z, as "
                         "Mitsuba's own)", "rotate_y": args.rotation},
                {"what": f"rotate(+Y, {180 - args.rotation:g}): the rotation's sense reversed (dray's before "
                         "this benchmark)", "rotate_y": 180.0 - args.rotation}]
    runs += [{"tag": f"control{i}", "seed": args.seed, "spp": args.spp, "rotate_y": c["rotate_y"],
              "save": str(out / f"mi_control{i}.npy")} for i, c in enumerate(controls)]
    env.log(f"mitsuba: {len(runs)} renders (to_world rotate(+Y, {rot:g}))")
    m = run_mitsuba(args, dict(base_cfg, variant=info["variant"], hdri=str(hdri), runs=runs), llvm_env)
    by_tag = {r["tag"]: r for r in m["runs"]}
    warm = [by_tag["b"]] + [by_tag[f"warm{r}"] for r in range(args.runs - 1)]

    img = {"dray": vsm.read_exr(druns[0]["exr"]), "dray_b": vsm.read_exr(d_b["exr"]),
           "dray_ref": vsm.read_exr(d_ref["exr"]), "mi": np.load(out / "mi_a.npy"), "mi_b": np.load(out / "mi_b.npy"),
           "mi_ref": np.load(out / "mi_ref.npy")}
    ldr = {k: vsm.tonemap(v) for k, v in img.items()}
    for k, v in ldr.items():
        vsm.save_png(v, out / f"{k}.png")
    res = {
        "flip_dray_vs_mitsuba": flip_regions(ldr["mi"], ldr["dray"], lab, out / "flip_dray_vs_mitsuba.png"),
        "flip_dray_vs_dray_ref": flip_regions(ldr["dray_ref"], ldr["dray"], lab),
        "flip_mitsuba_vs_mitsuba_ref": flip_regions(ldr["mi_ref"], ldr["mi"], lab),
        "flip_dray_vs_mitsuba_ref": flip_regions(ldr["mi_ref"], ldr["dray"], lab),
        "flip_dray_ref_vs_mitsuba_ref": flip_regions(ldr["mi_ref"], ldr["dray_ref"], lab,
                                                     out / "flip_refs.png"),
        "flip_mitsuba_vs_mitsuba_seed": flip_regions(ldr["mi"], ldr["mi_b"], lab),
        "flip_dray_vs_dray_seed": flip_regions(ldr["dray"], ldr["dray_b"], lab),
        "mean_ratio_dray_ref_over_mitsuba_ref": mean_ratio(img["dray_ref"], img["mi_ref"], lab),
        "pixels": {name: int((lab == i).sum()) for i, name in ((0, "background"), (3, "ground"), (1, "diffuse"),
                                                                (2, "glossy"))},
        "dray": {"render_s": statistics.median(x["render_s"] for x in druns),
                 "wall_s": statistics.median(x["wall_s"] for x in druns),
                 "cpu_s": statistics.median(x["cpu_s"] for x in druns), "cmd": druns[0]["cmd"],
                 "ref_render_s": d_ref["render_s"], "ref_cmd": d_ref["cmd"]},
        "mitsuba": {"render_s": statistics.median(x["render_s"] for x in warm),
                    "render_cpu_s": statistics.median(x["render_cpu_s"] for x in warm),
                    "cold_render_s": by_tag["a"]["render_s"], "ref_render_s": by_tag["ref"]["render_s"],
                    "cmd": m["cmd"], "to_world": f"rotate(+Y, {rot:g})"},
        "controls": [],
    }
    for i, c in enumerate(controls):
        lc = vsm.tonemap(np.load(out / f"mi_control{i}.npy"))
        vsm.save_png(lc, out / f"mi_control{i}.png")
        res["controls"].append({"what": c["what"], "flip_dray_vs_control": flip_regions(lc, ldr["dray"], lab)})
    for f in out.glob("mi_*.npy"):
        f.unlink()
    shutil.rmtree(out / "drjit_home", ignore_errors=True)
    env.save_results(out / "results.json", info, args, [res], load)
    report(info, args, res)


def regions(f: dict) -> str:
    return " / ".join(f"{f[r]:.4f}" for r in REGIONS)


def report(info: dict, args, r: dict) -> None:
    print(f"# Environment map, dray --env-map --env-rotation {args.rotation:g} against Mitsuba "
          f"{info['packages']['mitsuba']} ({info['variant']}) envmap, {r['mitsuba']['to_world']}; "
          f"{WIDTH}x{HEIGHT}, {args.spp} spp (references {args.ref_spp} spp), dray --max-depth {args.max_depth} "
          f"(Mitsuba max_depth {args.max_depth + 1}), {args.threads} threads on cores {args.cores}, runs {args.runs}")
    print(f"# map: {info['hdri']['source']} ({info['hdri']['licence']})")
    print(f"# {info['cpu_model']}, {info['date']}, dray {info['dray_git']}; busy cores before the start "
          f"{info['busy_cores_before_start']:.2f}, other processes used {info['other_processes_cores_during_run']:.2f}"
          " cores on average during the run")
    print(f"# FLIP (LDR) over: {' / '.join(REGIONS)} (pixels: {r['pixels']})")
    print("\n| comparison | FLIP |\n|---|---|")
    rows = [("dray vs Mitsuba, equal spp", "flip_dray_vs_mitsuba"),
            ("dray vs its own reference", "flip_dray_vs_dray_ref"),
            ("Mitsuba vs its own reference", "flip_mitsuba_vs_mitsuba_ref"),
            ("dray vs Mitsuba's reference", "flip_dray_vs_mitsuba_ref"),
            ("dray's reference vs Mitsuba's reference", "flip_dray_ref_vs_mitsuba_ref"),
            ("Mitsuba vs Mitsuba, another seed", "flip_mitsuba_vs_mitsuba_seed"),
            ("dray vs dray, another seed", "flip_dray_vs_dray_seed")]
    for what, key in rows:
        print(f"| {what} | {regions(r[key])} |")
    for c in r["controls"]:
        print(f"| control: dray vs Mitsuba with {c['what']} | {regions(c['flip_dray_vs_control'])} |")
    mr = r["mean_ratio_dray_ref_over_mitsuba_ref"]
    print(f"\nmean linear radiance, dray reference / Mitsuba reference: {regions(mr)}")
    d, m = r["dray"], r["mitsuba"]
    print(f"time at {args.spp} spp: dray render {d['render_s']:.2f} s (process wall {d['wall_s']:.2f} s, CPU "
          f"{d['cpu_s']:.2f} s); Mitsuba render, warm {m['render_s']:.2f} s (CPU {m['render_cpu_s']:.2f} s; cold, "
          f"with kernel compilation, {m['cold_render_s']:.2f} s); references: dray {d['ref_render_s']:.2f} s, "
          f"Mitsuba {m['ref_render_s']:.2f} s")
    print(f"\noutputs: {args.out}")


if __name__ == "__main__":
    env.ensure_venv()
    cli = parse_args()
    if cli.mitsuba_worker:
        mitsuba_worker(cli.mitsuba_worker)
    else:
        main(cli)

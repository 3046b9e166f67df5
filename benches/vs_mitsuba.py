#!/usr/bin/env python3
"""End-to-end path tracing: dray vs Mitsuba 3 on the same scene, cores and sample counts.

Scene: one mesh (the Stanford bunny PLY from $DRAY_SCENES, else a procedural mesh), pure
Lambert (albedo 0.8, two-sided, flat normals), one directional light plus a constant
environment, a perspective camera, 512x512, 16 spp, Mitsuba max_depth 3 (= dray
--max-depth 2: direct light + one indirect bounce, next-event estimation at each hit).

The mesh is taken from dray itself (`dray bench-rays --dump-mesh`), welded, and written
both as a .gltf (+ .bin) for dray and as a binary PLY for Mitsuba, so both trace exactly
the same triangles. Both renderers run pinned to the same cores (`taskset -c 0,1`) with
the same number of threads (2).

Timed:
- dray: wall time of the whole `dray render` process (load, BVH build, render, PNG+EXR
  write) and the render_time_s it reports; first run ("cold") and median of the rest.
- Mitsuba: each variant in its own process: `mi.load_dict` (PLY load + BVH build) +
  `mi.render` + conversion to numpy; run 1 is "cold" (for llvm_ad_rgb it includes JIT
  compilation, with an empty Dr.Jit kernel cache), runs 2-3 "warm". Interpreter start and
  `import mitsuba` are reported separately and not included.
Variants are tried in the order llvm_ad_rgb, scalar_rgb; scalar_rgb is always timed
because the target is "dray faster than Mitsuba scalar_rgb".

Quality: both render the scene at 256 spp; the LDR images (clamp to [0,1], sRGB) are
compared with NVIDIA FLIP (PyPI flip-evaluator), target mean <= 0.05. When the llvm
variant runs, a second Mitsuba render with another seed gives the noise floor.

Outputs go to benches/out/vs_mitsuba/ (PNGs, FLIP error map, results JSON).

Usage (from the repository root; creates benches/.venv on first use):
    benches/vs_mitsuba.sh                 # builds dray, then runs this
    python3 benches/vs_mitsuba.py [--spp 16] [--ref-spp 256] [--cores 0,1]
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

WIDTH = HEIGHT = 512
ALBEDO = 0.8
SUN_IRRADIANCE = 2.0  # W/m^2 (glTF intensity, used radiometrically by dray)
SUN_DIRECTION = (-0.45, -1.0, -0.35)  # direction of propagation (glTF: the light node's -Z)
ENV_RADIANCE = 0.25
YFOV_DEG = 30.0
ZNEAR = 1e-3
MITSUBA_MAX_DEPTH = 3
DRAY_MAX_DEPTH = MITSUBA_MAX_DEPTH - 1
FALLBACK_MESH = "iso:metaballs:64"
LLVM_DEB = "libllvm19"


def parse_args() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mesh", help="mesh spec for dray (default: the Stanford bunny, else " + FALLBACK_MESH + ")")
    ap.add_argument("--spp", type=int, default=16, help="samples per pixel of the timed renders (default 16)")
    ap.add_argument("--ref-spp", type=int, default=256, help="samples per pixel of the FLIP renders (default 256)")
    ap.add_argument("--runs", type=int, default=5, help="interleaved timing rounds (default 5)")
    ap.add_argument("--cores", default="0,1", help="cores for both renderers (taskset -c)")
    ap.add_argument("--threads", type=int, default=2, help="threads for both renderers")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--no-llvm-fetch", action="store_true",
                    help=f"do not fetch {LLVM_DEB} from Debian (apt-get download, unpacked into benches/.venv) "
                         "when the system LLVM cannot run the llvm variant")
    ap.add_argument("--out", type=Path, default=env.OUT / "vs_mitsuba")
    ap.add_argument("--mitsuba-worker", type=Path, help=argparse.SUPPRESS)  # internal
    return ap.parse_args()


# ---------------------------------------------------------------------------------------
# Geometry: camera, light frame, mesh files
# ---------------------------------------------------------------------------------------

def normalize(v):
    n = math.sqrt(sum(c * c for c in v))
    return tuple(c / n for c in v)


def cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def camera_frame(lo, hi):
    """Eye, right, up, forward for a camera framing the bounds' sphere at YFOV_DEG."""
    center = tuple((a + b) / 2 for a, b in zip(lo, hi))
    radius = 0.5 * math.dist(lo, hi)
    dist = radius / math.sin(math.radians(YFOV_DEG) / 2) * 0.82
    view = normalize((0.35, 0.25, 1.0))  # from the front (+Z), a little right and above
    eye = tuple(c + dist * v for c, v in zip(center, view))
    fwd = normalize(tuple(c - e for c, e in zip(center, eye)))
    right = normalize(cross(fwd, (0.0, 1.0, 0.0)))
    up = cross(right, fwd)
    return eye, right, up, fwd


def gltf_matrix(x, y, z, t):
    """Column-major 4x4 with basis columns x, y, z and translation t."""
    return [*x, 0.0, *y, 0.0, *z, 0.0, *t, 1.0]


def light_basis(direction):
    """Right-handed frame whose -Z is `direction` (glTF light convention)."""
    z = normalize(tuple(-c for c in direction))
    helper = (0.0, 1.0, 0.0) if abs(z[1]) < 0.9 else (1.0, 0.0, 0.0)
    x = normalize(cross(helper, z))
    y = cross(z, x)
    return x, y, z


def write_meshes(tris, out: Path):
    """Weld the triangle soup; write mesh.bin + scene.gltf-ready data and mesh.ply. Returns info."""
    import numpy as np

    verts, inverse = np.unique(tris.reshape(-1, 3), axis=0, return_inverse=True)
    idx = inverse.reshape(-1).astype(np.uint32)
    verts = verts.astype("<f4")
    # PLY for Mitsuba.
    ply = out / "mesh.ply"
    faces = np.empty(len(tris), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    faces["n"] = 3
    faces["i"] = idx.reshape(-1, 3).astype("<i4")
    header = (f"ply\nformat binary_little_endian 1.0\ncomment dray benches/vs_mitsuba.py\n"
              f"element vertex {len(verts)}\nproperty float x\nproperty float y\nproperty float z\n"
              f"element face {len(tris)}\nproperty list uchar int vertex_indices\nend_header\n")
    with open(ply, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(verts.tobytes())
        f.write(faces.tobytes())
    # Buffer for glTF.
    pos_bytes = verts.tobytes()
    idx_bytes = idx.astype("<u4").tobytes()
    (out / "mesh.bin").write_bytes(pos_bytes + idx_bytes)
    return {"vertices": len(verts), "triangles": len(tris), "pos_bytes": len(pos_bytes),
            "idx_bytes": len(idx_bytes), "min": verts.min(0).tolist(), "max": verts.max(0).tolist(), "ply": ply}


def write_gltf(mesh, cam, out: Path) -> Path:
    eye, right, up, fwd = cam
    back = tuple(-c for c in fwd)
    lx, ly, lz = light_basis(SUN_DIRECTION)
    doc = {
        "asset": {"version": "2.0", "generator": "dray benches/vs_mitsuba.py"},
        "extensionsUsed": ["KHR_lights_punctual", "KHR_materials_specular"],
        "extensions": {"KHR_lights_punctual": {"lights": [
            {"name": "sun", "type": "directional", "color": [1.0, 1.0, 1.0], "intensity": SUN_IRRADIANCE}]}},
        "scene": 0,
        "scenes": [{"nodes": [0, 1, 2]}],
        "nodes": [
            {"name": "mesh", "mesh": 0},
            {"name": "camera", "camera": 0, "matrix": gltf_matrix(right, up, back, eye)},
            {"name": "sun", "matrix": gltf_matrix(lx, ly, lz, (0.0, 0.0, 0.0)),
             "extensions": {"KHR_lights_punctual": {"light": 0}}},
        ],
        "cameras": [{"name": "camera", "type": "perspective",
                     "perspective": {"yfov": math.radians(YFOV_DEG), "aspectRatio": WIDTH / HEIGHT, "znear": ZNEAR}}],
        "materials": [{
            "name": "lambert",
            "doubleSided": True,
            "pbrMetallicRoughness": {"baseColorFactor": [ALBEDO, ALBEDO, ALBEDO, 1.0],
                                     "metallicFactor": 0.0, "roughnessFactor": 1.0},
            "extensions": {"KHR_materials_specular": {"specularFactor": 0.0}},
        }],
        "meshes": [{"name": "mesh", "primitives": [
            {"attributes": {"POSITION": 0}, "indices": 1, "material": 0, "mode": 4}]}],
        "buffers": [{"uri": "mesh.bin", "byteLength": mesh["pos_bytes"] + mesh["idx_bytes"]}],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": mesh["pos_bytes"], "target": 34962},
            {"buffer": 0, "byteOffset": mesh["pos_bytes"], "byteLength": mesh["idx_bytes"], "target": 34963},
        ],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": mesh["vertices"], "type": "VEC3",
             "min": mesh["min"], "max": mesh["max"]},
            {"bufferView": 1, "componentType": 5125, "count": 3 * mesh["triangles"], "type": "SCALAR"},
        ],
    }
    path = out / "scene.gltf"
    path.write_text(json.dumps(doc, indent=1) + "\n")
    return path


def mitsuba_scene_dict(mi, cfg: dict, spp: int) -> dict:
    eye, right, up, fwd = (tuple(v) for v in cfg["camera"])
    left = tuple(-c for c in right)
    # Mitsuba's camera looks down local +Z and its local +X points to the image's left;
    # this is exactly ScalarTransform4f.look_at(eye, eye + fwd, up).
    to_world = mi.ScalarTransform4f([[left[0], up[0], fwd[0], eye[0]],
                                     [left[1], up[1], fwd[1], eye[1]],
                                     [left[2], up[2], fwd[2], eye[2]],
                                     [0.0, 0.0, 0.0, 1.0]])
    rgb = lambda v: {"type": "rgb", "value": [v, v, v]}  # noqa: E731
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": MITSUBA_MAX_DEPTH},
        "sensor": {
            "type": "perspective", "fov_axis": "y", "fov": YFOV_DEG, "near_clip": ZNEAR, "far_clip": 1e4,
            "to_world": to_world,
            "film": {"type": "hdrfilm", "width": WIDTH, "height": HEIGHT, "pixel_format": "rgb",
                     "rfilter": {"type": "box"}},
            "sampler": {"type": "independent", "sample_count": spp},
        },
        "mesh": {"type": "ply", "filename": cfg["ply"], "face_normals": True,
                 "bsdf": {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": rgb(ALBEDO)}}},
        "sun": {"type": "directional", "direction": list(SUN_DIRECTION), "irradiance": rgb(SUN_IRRADIANCE)},
        "env": {"type": "constant", "radiance": rgb(ENV_RADIANCE)},
    }


# ---------------------------------------------------------------------------------------
# Mitsuba worker (own process, pinned): python vs_mitsuba.py --mitsuba-worker cfg.json
# ---------------------------------------------------------------------------------------

def mitsuba_worker(cfg_path: Path) -> None:
    import numpy as np

    cfg = json.loads(cfg_path.read_text())
    t0 = time.perf_counter()
    import drjit as dr
    import mitsuba as mi

    mi.set_variant(cfg["variant"])
    dr.set_thread_count(cfg["threads"])
    import_s = time.perf_counter() - t0
    runs = []
    for i, run in enumerate(cfg["runs"]):
        c0 = time.process_time()
        t0 = time.perf_counter()
        scene = mi.load_dict(mitsuba_scene_dict(mi, cfg, run["spp"]))
        t1 = time.perf_counter()
        img = np.array(mi.render(scene, spp=run["spp"], seed=run["seed"]))
        t2 = time.perf_counter()
        cpu = time.process_time() - c0
        if run.get("save"):
            np.save(run["save"], img.astype(np.float32))
        runs.append({"spp": run["spp"], "seed": run["seed"], "load_s": t1 - t0, "render_s": t2 - t1,
                     "total_s": t2 - t0, "cpu_s": cpu, "mean": float(img.mean()), "shape": list(img.shape)})
        print(f"run {i}: {runs[-1]}", file=sys.stderr, flush=True)
    print(json.dumps({"variant": cfg["variant"], "import_s": import_s, "thread_count": dr.thread_count(),
                      "drjit": dr.__version__, "mitsuba": mi.__version__, "runs": runs,
                      "affinity": sorted(os.sched_getaffinity(0)),
                      "libllvm": os.environ.get("DRJIT_LIBLLVM_PATH", "(system default)")}))


# ---------------------------------------------------------------------------------------
# Driver
# ---------------------------------------------------------------------------------------

def fetch_llvm(dest: Path) -> tuple[Path | None, str]:
    """Unpack Debian's libllvm19 into `dest` (no system install). Returns (library, log)."""
    lib = next(dest.glob("usr/lib/*/libLLVM.so.19*"), None) if dest.exists() else None
    if lib:
        return lib, f"reused {lib}"
    if not shutil.which("apt-get") or not shutil.which("dpkg-deb"):
        return None, "apt-get/dpkg-deb not available"
    dest.mkdir(parents=True, exist_ok=True)
    p = subprocess.run(["apt-get", "download", LLVM_DEB], cwd=dest, capture_output=True, text=True)
    debs = list(dest.glob(f"{LLVM_DEB}_*.deb"))
    if p.returncode != 0 or not debs:
        return None, (f"`apt-get download {LLVM_DEB}` failed (exit {p.returncode}; run `apt-get update` first?): "
                      f"{p.stderr.strip()[-300:]}")
    subprocess.run(["dpkg-deb", "-x", str(debs[0]), str(dest)], check=True)
    debs[0].unlink()
    lib = next(dest.glob("usr/lib/*/libLLVM.so.19*"), None)
    return lib, f"apt-get download {LLVM_DEB} + dpkg-deb -x into {dest}"


def run_mitsuba(args, base_cfg: dict, variant: str, runs: list, tag: str, extra_env: dict) -> dict:
    cfg = dict(base_cfg, variant=variant, runs=runs, threads=args.threads)
    cfg_path = args.out / f"mitsuba_{tag}.json"
    cfg_path.write_text(json.dumps(cfg))
    home = args.out / f"drjit_home_{tag}"  # fresh HOME -> empty ~/.drjit kernel cache -> cold JIT
    shutil.rmtree(home, ignore_errors=True)
    home.mkdir(parents=True)
    e = dict(os.environ, HOME=str(home), **extra_env)
    cmd = env.pin(args.cores, [sys.executable, Path(__file__).resolve(), "--mitsuba-worker", cfg_path])
    r = env.run_timed(cmd, env=e, check=False)
    if r["rc"] != 0:
        err = [ln for ln in r["stderr"].splitlines() if ln.strip()]
        key = next((ln for ln in err if "ERROR" in ln or "Error" in ln), err[-1] if err else "")
        return {"ok": False, "variant": variant, "rc": r["rc"], "error": key.strip()[:400],
                "cmd": r["cmd"], "env": extra_env}
    d = env.last_json_line(r["stdout"])
    d.update(ok=True, cmd=r["cmd"], process_wall_s=r["wall_s"], process_cpu_s=r["cpu_s"], env=extra_env)
    return d


def run_dray(args, dray, gltf: Path, spp: int, tag: str, seed: int) -> dict:
    png, exr, stats = args.out / f"dray_{tag}.png", args.out / f"dray_{tag}.exr", args.out / f"dray_{tag}.stats.json"
    cmd = env.pin(args.cores, [dray, "render", gltf, "--width", WIDTH, "--height", HEIGHT, "--spp", spp,
                              "--integrator", "path", "--max-depth", DRAY_MAX_DEPTH, "--seed", seed,
                              "--env", f"{ENV_RADIANCE},{ENV_RADIANCE},{ENV_RADIANCE}", "--threads", args.threads,
                              "--output", png, "--exr", exr, "--stats", stats, "-q"])
    r = env.run_timed(cmd)
    s = json.loads(stats.read_text())
    return {"cmd": r["cmd"], "wall_s": r["wall_s"], "cpu_s": r["cpu_s"], "stats": s, "exr": str(exr)}


def tonemap(img):
    import numpy as np

    x = np.clip(np.nan_to_num(img[..., :3], nan=0.0, posinf=1.0), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055).astype(np.float32)


def save_png(ldr, path: Path):
    import numpy as np
    from PIL import Image

    Image.fromarray((np.clip(ldr, 0, 1) * 255.0 + 0.5).astype(np.uint8)).save(path)


def read_exr(path: str):
    import mitsuba as mi
    import numpy as np

    if mi.variant() is None:
        mi.set_variant("scalar_rgb")
    return np.array(mi.Bitmap(path), dtype=np.float32)[..., :3]


def main() -> None:
    args = parse_args()
    if args.mitsuba_worker:
        mitsuba_worker(args.mitsuba_worker)
        return
    import numpy as np

    args.out.mkdir(parents=True, exist_ok=True)
    for pattern in ("dray_*", "mitsuba_*", "flip_*", "results.json", "mesh.*", "scene.gltf"):
        for f in args.out.glob(pattern):  # outputs of an earlier run
            if f.is_file():
                f.unlink()
    dray = env.dray_binary()
    scenes = env.scenes_dir()
    bunny = scenes / "stanford_bunny" / "bun_zipper.ply"
    spec = args.mesh or (str(bunny) if bunny.exists() else FALLBACK_MESH)
    if not args.mesh and not bunny.exists():
        env.log(f"{bunny} not found: using the procedural mesh {FALLBACK_MESH}")

    # 1. The mesh as dray sees it -> glTF for dray, PLY for Mitsuba.
    soup = args.out / "mesh.tris.f32"
    env.run_timed([dray, "bench-rays", spec, "--kind", "primary", "--res", 1, "--repeat", 1, "--dump-mesh", soup])
    tris = np.fromfile(soup, dtype="<f4").reshape(-1, 3, 3)
    soup.unlink()
    mesh = write_meshes(tris, args.out)
    lo, hi = mesh["min"], mesh["max"]
    cam = camera_frame(lo, hi)
    gltf = write_gltf(mesh, cam, args.out)
    env.log(f"scene: {spec}: {mesh['triangles']} triangles, {mesh['vertices']} vertices -> {gltf}, {mesh['ply']}")
    base_cfg = {"ply": str(mesh["ply"]), "camera": [list(v) for v in cam]}

    info = env.machine_info()
    info["busy_cores_before_start"] = round(env.idle_check(), 2)
    load = env.OtherLoad()
    info["packages"] = env.package_versions(["mitsuba", "drjit", "flip-evaluator", "numpy"])
    info["dray_binary"] = env.binary_info(dray)
    res = {"machine": info, "scene": {"mesh": spec, "triangles": mesh["triangles"], "width": WIDTH,
                                      "height": HEIGHT, "spp": args.spp, "ref_spp": args.ref_spp,
                                      "mitsuba_max_depth": MITSUBA_MAX_DEPTH, "dray_max_depth": DRAY_MAX_DEPTH,
                                      "albedo": ALBEDO, "sun_irradiance": SUN_IRRADIANCE,
                                      "sun_direction": SUN_DIRECTION, "env_radiance": ENV_RADIANCE,
                                      "yfov_deg": YFOV_DEG},
           "cores": args.cores, "threads": args.threads}

    # 2. Timed renders, interleaved round by round (dray, Mitsuba llvm_ad_rgb, Mitsuba scalar_rgb)
    # so that any other load on the machine hits all of them alike. Each Mitsuba round is a
    # fresh process (fresh HOME, so an empty Dr.Jit kernel cache) doing two load+render
    # passes: the first is "cold" (includes JIT compilation for llvm), the second "warm".
    llvm_env: dict = {}
    if os.environ.get("DRJIT_LIBLLVM_PATH"):
        llvm_env["DRJIT_LIBLLVM_PATH"] = os.environ["DRJIT_LIBLLVM_PATH"]
    attempts: list = []
    pair = [{"spp": args.spp, "seed": args.seed}, {"spp": args.spp, "seed": args.seed}]
    dray_runs: list = []
    mruns: dict = {"llvm_ad_rgb": [], "scalar_rgb": []}
    failed: dict = {}
    for rnd in range(args.runs):
        env.log(f"round {rnd + 1}/{args.runs}: dray, {args.spp} spp")
        o = env.OtherLoad(env.parse_cores(args.cores))
        x = run_dray(args, dray, gltf, args.spp, f"{args.spp}spp_round{rnd}", args.seed)
        x["other_cores"] = o.cores()
        dray_runs.append(x)
        env.log(f"  dray: wall {x['wall_s']:.2f} s, render {x['stats']['render_time_s']:.2f} s, "
                f"cpu/wall {x['cpu_s'] / x['wall_s']:.2f}, others {x['other_cores']:.2f} cores")
        for v in ("llvm_ad_rgb", "scalar_rgb"):
            if v in failed:
                continue
            venv_extra = llvm_env if v == "llvm_ad_rgb" else {}
            env.log(f"round {rnd + 1}/{args.runs}: mitsuba {v}" + (f" {venv_extra}" if venv_extra else ""))
            o = env.OtherLoad(env.parse_cores(args.cores))
            m = run_mitsuba(args, base_cfg, v, pair, v, venv_extra)
            if not m["ok"] and v == "llvm_ad_rgb" and not llvm_env and not args.no_llvm_fetch:
                attempts.append({k: m[k] for k in ("variant", "rc", "error", "env")})
                env.log(f"  failed with the system LLVM: {m['error']}")
                lib, how = fetch_llvm(env.VENV / "llvm")
                attempts.append({"fetch": how})
                env.log(f"  {how}")
                if lib:
                    llvm_env = {"DRJIT_LIBLLVM_PATH": str(lib)}
                    o = env.OtherLoad(env.parse_cores(args.cores))
                    m = run_mitsuba(args, base_cfg, v, pair, v, llvm_env)
            if not m["ok"]:
                attempts.append({k: m[k] for k in ("variant", "rc", "error", "env")})
                env.log(f"  {v} failed: {m['error']}")
                failed[v] = m
                continue
            m["other_cores"] = o.cores()
            mruns[v].append(m)
            env.log(f"  {v}: cold {m['runs'][0]['total_s']:.2f} s, warm {m['runs'][1]['total_s']:.2f} s, "
                    f"cpu/wall {m['runs'][1]['cpu_s'] / m['runs'][1]['total_s']:.2f}, others {m['other_cores']:.2f} cores")

    warm_dray = dray_runs[1:] or dray_runs
    res["dray"] = {"runs": dray_runs, "cold_wall_s": dray_runs[0]["wall_s"],
                   "warm_wall_s": statistics.median(r["wall_s"] for r in warm_dray),
                   "warm_render_s": statistics.median(r["stats"]["render_time_s"] for r in warm_dray),
                   "cpu_per_wall": statistics.median(r["cpu_s"] / r["wall_s"] for r in dray_runs),
                   "max_other_cores": max(r["other_cores"] for r in dray_runs)}
    res["mitsuba"] = {"llvm_attempts": attempts}
    for v, ms in mruns.items():
        if not ms:
            res["mitsuba"][v] = failed.get(v, {"ok": False, "error": "not run"})
            continue
        res["mitsuba"][v] = {
            "ok": True, "rounds": ms, "import_s": statistics.median(m["import_s"] for m in ms),
            "cold_total_s": statistics.median(m["runs"][0]["total_s"] for m in ms),
            "warm_total_s": statistics.median(m["runs"][1]["total_s"] for m in ms),
            "warm_render_s": statistics.median(m["runs"][1]["render_s"] for m in ms),
            "cpu_per_wall": statistics.median(m["runs"][1]["cpu_s"] / m["runs"][1]["total_s"] for m in ms),
            "max_other_cores": max(m["other_cores"] for m in ms),
            "libllvm": ms[0]["libllvm"], "thread_count": ms[0]["thread_count"]}
    ran = [v for v in ("llvm_ad_rgb", "scalar_rgb") if res["mitsuba"][v].get("ok")]
    res["mitsuba"]["ran"] = ran

    # 4. Quality at ref spp: FLIP between the LDR images.
    if ran:
        ref_variant = ran[0]
        env.log(f"quality: dray and mitsuba {ref_variant} at {args.ref_spp} spp")
        dref = run_dray(args, dray, gltf, args.ref_spp, f"{args.ref_spp}spp", args.seed)
        ref_runs = [{"spp": args.ref_spp, "seed": args.seed, "save": str(args.out / "mitsuba_ref.npy")}]
        if ref_variant == "llvm_ad_rgb":  # cheap: a second seed gives Mitsuba's own noise floor
            ref_runs.append({"spp": args.ref_spp, "seed": args.seed + 1000, "save": str(args.out / "mitsuba_ref2.npy")})
        mref = run_mitsuba(args, base_cfg, ref_variant, ref_runs, "ref",
                           llvm_env if ref_variant == "llvm_ad_rgb" else {})
        if not mref["ok"]:
            raise RuntimeError(f"mitsuba reference render failed: {mref['error']}")
        import flip_evaluator as flip

        img_d = read_exr(dref["exr"])
        img_m = np.load(args.out / "mitsuba_ref.npy")
        ldr_d, ldr_m = tonemap(img_d), tonemap(img_m)
        save_png(ldr_d, args.out / f"dray_{args.ref_spp}spp_tonemapped.png")
        save_png(ldr_m, args.out / f"mitsuba_{ref_variant}_{args.ref_spp}spp.png")
        errmap, mean_err, _ = flip.evaluate(ldr_m, ldr_d, "LDR")
        save_png(np.asarray(errmap), args.out / "flip_dray_vs_mitsuba.png")
        q = {"ref_variant": ref_variant, "ref_spp": args.ref_spp, "flip_mean": float(mean_err),
             "dray": {k: dref[k] for k in ("cmd", "wall_s", "cpu_s")} | {"render_time_s": dref["stats"]["render_time_s"]},
             "mitsuba": {"total_s": [r["total_s"] for r in mref["runs"]], "cmd": mref["cmd"]},
             "mean_linear_dray": img_d.mean(0).mean(0).tolist(), "mean_linear_mitsuba": img_m.mean(0).mean(0).tolist(),
             "mean_ratio_dray_over_mitsuba": float(img_d.mean() / img_m.mean()),
             "clipped_pct_dray": float((img_d > 1).any(-1).mean() * 100),
             "clipped_pct_mitsuba": float((img_m > 1).any(-1).mean() * 100)}
        if len(mref["runs"]) > 1:
            img_m2 = np.load(args.out / "mitsuba_ref2.npy")
            _, floor, _ = flip.evaluate(ldr_m, tonemap(img_m2), "LDR")
            q["flip_mitsuba_seed_vs_seed"] = float(floor)
        res["quality"] = q
        env.log(f"  FLIP mean dray vs mitsuba: {mean_err:.4f}" +
                (f" (mitsuba vs itself, other seed: {q['flip_mitsuba_seed_vs_seed']:.4f})"
                 if "flip_mitsuba_seed_vs_seed" in q else ""))
        for f in args.out.glob("mitsuba_ref*.npy"):
            f.unlink()
    for h in args.out.glob("drjit_home_*"):
        shutil.rmtree(h, ignore_errors=True)

    info["other_processes_cores_during_run"] = round(load.cores(), 2)
    (args.out / "results.json").write_text(json.dumps(res, indent=2, default=str) + "\n")
    report(res, args)


def report(res: dict, args) -> None:
    m = res["machine"]
    print(f"# dray vs Mitsuba 3, {res['scene']['mesh']} ({res['scene']['triangles']:,} triangles), "
          f"{WIDTH}x{HEIGHT}, {args.spp} spp, Mitsuba max_depth {MITSUBA_MAX_DEPTH} = dray --max-depth {DRAY_MAX_DEPTH}")
    print(f"# {m['cpu_model']}, nproc {m['nproc']}, {m['date']}, cores {args.cores}, {args.threads} threads each, "
          f"dray {m['dray_git']}, mitsuba {m['packages']['mitsuba']}, drjit {m['packages']['drjit']}")
    print(f"# other processes used {m['other_processes_cores_during_run']:.2f} cores on average during the run "
          f"({m['busy_cores_before_start']:.2f} busy just before it)")
    d = res["dray"]
    print(f"# {args.runs} interleaved rounds; cold = first, warm = median of the rest (dray) or of each round's "
          "second pass (Mitsuba)")
    print("| renderer | cold (s) | warm (s) | warm render only (s) | CPU/wall | max other load (cores) | what is timed |")
    print("|---|---:|---:|---:|---:|---:|---|")
    print(f"| dray | {d['cold_wall_s']:.2f} | {d['warm_wall_s']:.2f} | {d['warm_render_s']:.2f} | {d['cpu_per_wall']:.2f} | "
          f"{d['max_other_cores']:.2f} | whole `dray render` process; render only = stats render_time_s |")
    for v in ("llvm_ad_rgb", "scalar_rgb"):
        x = res["mitsuba"].get(v)
        if x and x.get("ok"):
            print(f"| Mitsuba {v} | {x['cold_total_s']:.2f} | {x['warm_total_s']:.2f} | {x['warm_render_s']:.2f} | "
                  f"{x['cpu_per_wall']:.2f} | {x['max_other_cores']:.2f} | load_dict + render + to numpy; "
                  f"not counted: interpreter start + import ({x['import_s']:.2f} s) |")
        elif x:
            print(f"| Mitsuba {v} | failed | | | | | {x.get('error')} |")
    for a in res["mitsuba"]["llvm_attempts"]:
        print(f"# llvm attempt: {a}")
    sc = res["mitsuba"].get("scalar_rgb", {})
    if sc.get("ok"):
        ratio = sc["warm_total_s"] / d["warm_wall_s"]
        print(f"\ntarget 'dray faster than Mitsuba scalar_rgb': {'MET' if ratio > 1 else 'MISSED'} "
              f"(scalar_rgb warm {sc['warm_total_s']:.2f} s / dray warm {d['warm_wall_s']:.2f} s = {ratio:.2f}x; "
              f"render only {sc['warm_render_s'] / d['warm_render_s']:.2f}x)")
    q = res.get("quality")
    if q:
        print(f"target 'FLIP mean <= 0.05' at {q['ref_spp']} spp vs {q['ref_variant']}: "
              f"{'MET' if q['flip_mean'] <= 0.05 else 'MISSED'} (FLIP mean {q['flip_mean']:.4f}"
              + (f"; Mitsuba seed-vs-seed {q['flip_mitsuba_seed_vs_seed']:.4f}" if "flip_mitsuba_seed_vs_seed" in q else "")
              + f"; mean linear radiance dray/Mitsuba {q['mean_ratio_dray_over_mitsuba']:.4f})")
    print(f"\noutputs: {args.out}")


if __name__ == "__main__":
    env.ensure_venv()
    main()

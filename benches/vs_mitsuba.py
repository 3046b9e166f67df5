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

Depth and Russian roulette, matched: dray's `--max-depth D` shades (next-event estimation
plus one BSDF bounce) the first D surface vertices of a path; Mitsuba's `path` does the
same at vertex d when d + 1 < max_depth, so Mitsuba's max_depth = D + 1. dray's roulette
starts on the bounce out of the 4th vertex (vertex depth >= 3, q = min(max(weight), 0.95));
Mitsuba's applies once its incremented depth >= rr_depth with the same q (eta = 1 here),
so Mitsuba gets rr_depth = 4 (its default, 5, would start one bounce later). At the
default depth (2) neither renderer ever reaches roulette, and Mitsuba draws its roulette
sample either way, so rr_depth does not change that image.

Options beyond the defaults: --width/--height, --max-depth (dray's; Mitsuba's is one
more), --threads as a list (e.g. 1,2: every round runs every count; N threads run on the
first N of --cores), --up z for Z-up models (rotated to Y-up in both renderers' files).

--case ground is issue 41's kind of scene: the Stanford bunny (69,451 triangles) standing on
a ground plane 40 bounding-sphere radii wide (two triangles), otherwise as deep (256x256, 64
spp, --max-depth 64, the sun and the constant environment, threads 1 and 2); most shading
points are on the ground and send a shadow ray past the model. Outputs go to
benches/out/vs_mitsuba_ground/.

--case deep is the scanned-model case: Lucy ($DRAY_SCENES/lucy_100k/lucy.ply,
99,970 triangles; the bunny if Lucy is missing), 256x256, 64 spp, --max-depth 64 (Mitsuba
max_depth 65, rr_depth 4), the same sun and constant environment, scalar_rgb and
llvm_ad_rgb, threads 1 and 2; it reports dray/Mitsuba time ratios per thread count and
each renderer's 1->2 thread speedup. Outputs go to benches/out/vs_mitsuba_deep/. Any
option given explicitly overrides the preset's value.

Usage (from the repository root; creates benches/.venv on first use):
    benches/vs_mitsuba.sh                 # builds dray, then runs this
    python3 benches/vs_mitsuba.py [--spp 16] [--ref-spp 256] [--cores 0,1]
    benches/vs_mitsuba.sh --case deep     # Lucy, 256x256, 64 spp, depth 64, 1 and 2 threads
    benches/vs_mitsuba.sh --case ground   # the bunny on a ground plane, as deep otherwise
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

ALBEDO = 0.8
SUN_IRRADIANCE = 2.0  # W/m^2 (glTF intensity, used radiometrically by dray)
SUN_DIRECTION = (-0.45, -1.0, -0.35)  # direction of propagation (glTF: the light node's -Z)
ENV_RADIANCE = 0.25
YFOV_DEG = 30.0
ZNEAR = 1e-3
DRAY_RR_START = 3  # dray's path integrator: roulette on the bounce out of vertex depth >= 3
MITSUBA_RR_DEPTH = DRAY_RR_START + 1  # Mitsuba: roulette once (vertex depth + 1) >= rr_depth
FALLBACK_MESH = "iso:metaballs:64"
LLVM_DEB = "libllvm19"

# Defaults (the original benchmark) and the deep scanned-model case (docs/benchmarks.md,
# "Path tracing against Mitsuba 3"). Values given on the command line win over the case's.
CASES = {
    "default": {"width": 512, "height": 512, "spp": 16, "ref_spp": 256, "max_depth": 2, "threads": "2",
                "up": "y", "mesh": None, "ground": False, "out": "vs_mitsuba"},
    "deep": {"width": 256, "height": 256, "spp": 64, "ref_spp": 256, "max_depth": 64, "threads": "1,2",
             "up": None, "mesh": "lucy", "ground": False, "out": "vs_mitsuba_deep"},
    # Issue 41's kind of scene: a scanned model standing on a large ground plane, lit by the sun
    # and the constant environment, path traced deep: most shading points are on the ground,
    # most of them send a shadow ray past the model, and many paths bounce between the two.
    "ground": {"width": 256, "height": 256, "spp": 64, "ref_spp": 256, "max_depth": 64, "threads": "1,2",
               "up": "y", "mesh": "bunny", "ground": True, "out": "vs_mitsuba_ground"},
}

# The ground plane of --case ground: a square this many bounding-sphere radii wide, at the
# model's lowest point, two triangles.
GROUND_RADII = 40.0


def mitsuba_max_depth(dray_max_depth: int) -> int:
    return dray_max_depth + 1


def parse_args() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--case", choices=sorted(CASES), default="default",
                    help="preset: default (bunny, 512x512, 16 spp, --max-depth 2, 2 threads), deep (Lucy, "
                         "256x256, 64 spp, --max-depth 64, threads 1 and 2) or ground (the bunny on a ground "
                         "plane, otherwise as deep)")
    ap.add_argument("--mesh", help="mesh spec for dray (default: the Stanford bunny, else " + FALLBACK_MESH +
                    "; --case deep: Lucy, else the bunny)")
    ap.add_argument("--width", type=int, help="image width (default 512; deep 256)")
    ap.add_argument("--height", type=int, help="image height (default 512; deep 256)")
    ap.add_argument("--max-depth", type=int, help="dray's --max-depth; Mitsuba's max_depth is one more "
                    "(default 2; deep 64)")
    ap.add_argument("--up", choices=("y", "z"), help="the model's up axis; z: the files both renderers read hold "
                    "the model rotated by (x, y, z) -> (-x, z, y), so it stands up and its +Y side faces the camera "
                    "(default y; deep: z for Lucy)")
    ap.add_argument("--spp", type=int, help="samples per pixel of the timed renders (default 16; deep 64)")
    ap.add_argument("--ref-spp", type=int, help="samples per pixel of the FLIP renders (default 256)")
    ap.add_argument("--runs", type=int, default=5, help="interleaved timing rounds (default 5)")
    ap.add_argument("--cores", default="0,1", help="cores for both renderers (taskset -c); N threads run on "
                    "the first N of them")
    ap.add_argument("--threads", help="thread counts for both renderers, comma-separated, each timed in every "
                    "round (default 2; deep 1,2)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--no-llvm-fetch", action="store_true",
                    help=f"do not fetch {LLVM_DEB} from Debian (apt-get download, unpacked into benches/.venv) "
                         "when the system LLVM cannot run the llvm variant")
    ap.add_argument("--out", type=Path, help="output folder (default benches/out/vs_mitsuba; deep: "
                    "benches/out/vs_mitsuba_deep)")
    ap.add_argument("--mitsuba-worker", type=Path, help=argparse.SUPPRESS)  # internal
    args = ap.parse_args()
    if args.mitsuba_worker:
        return args
    case = CASES[args.case]
    for k in ("width", "height", "spp", "ref_spp", "max_depth", "threads", "up"):
        if getattr(args, k) is None:
            setattr(args, k, case[k])
    if args.out is None:
        args.out = env.OUT / case["out"]
    args.thread_counts = sorted({int(t) for t in str(args.threads).split(",") if t.strip()})
    cores = env.parse_cores(args.cores)
    if not args.thread_counts or min(args.thread_counts) < 1 or max(args.thread_counts) > len(cores):
        ap.error(f"--threads {args.threads}: each count must be between 1 and the number of --cores ({len(cores)})")
    if args.width < 1 or args.height < 1 or args.max_depth < 1 or args.spp < 1 or args.ref_spp < 1:
        ap.error("--width, --height, --max-depth, --spp and --ref-spp must be positive")
    args.mitsuba_max_depth = mitsuba_max_depth(args.max_depth)
    return args


def cores_for(args, threads: int) -> str:
    """The first `threads` cores of --cores, as a taskset list."""
    return ",".join(str(c) for c in env.parse_cores(args.cores)[:threads])


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


def write_gltf(mesh, cam, out: Path, width: int, height: int) -> Path:
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
                     "perspective": {"yfov": math.radians(YFOV_DEG), "aspectRatio": width / height, "znear": ZNEAR}}],
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
        "integrator": {"type": "path", "max_depth": cfg["max_depth"], "rr_depth": cfg["rr_depth"]},
        "sensor": {
            "type": "perspective", "fov_axis": "y", "fov": YFOV_DEG, "near_clip": ZNEAR, "far_clip": 1e4,
            "to_world": to_world,
            "film": {"type": "hdrfilm", "width": cfg["width"], "height": cfg["height"], "pixel_format": "rgb",
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


def run_mitsuba(args, base_cfg: dict, variant: str, runs: list, tag: str, extra_env: dict, threads: int) -> dict:
    cfg = dict(base_cfg, variant=variant, runs=runs, threads=threads)
    cfg_path = args.out / f"mitsuba_{tag}.json"
    cfg_path.write_text(json.dumps(cfg))
    home = args.out / f"drjit_home_{tag}"  # fresh HOME -> empty ~/.drjit kernel cache -> cold JIT
    shutil.rmtree(home, ignore_errors=True)
    home.mkdir(parents=True)
    e = dict(os.environ, HOME=str(home), **extra_env)
    cmd = env.pin(cores_for(args, threads), [sys.executable, Path(__file__).resolve(), "--mitsuba-worker", cfg_path])
    r = env.run_timed(cmd, env=e, check=False)
    if r["rc"] != 0:
        err = [ln for ln in r["stderr"].splitlines() if ln.strip()]
        key = next((ln for ln in err if "ERROR" in ln or "Error" in ln), err[-1] if err else "")
        return {"ok": False, "variant": variant, "rc": r["rc"], "error": key.strip()[:400],
                "cmd": r["cmd"], "env": extra_env}
    d = env.last_json_line(r["stdout"])
    d.update(ok=True, cmd=r["cmd"], process_wall_s=r["wall_s"], process_cpu_s=r["cpu_s"], env=extra_env)
    return d


def run_dray(args, dray, gltf: Path, spp: int, tag: str, seed: int, threads: int) -> dict:
    png, exr, stats = args.out / f"dray_{tag}.png", args.out / f"dray_{tag}.exr", args.out / f"dray_{tag}.stats.json"
    cmd = env.pin(cores_for(args, threads),
                  [dray, "render", gltf, "--width", args.width, "--height", args.height, "--spp", spp,
                   "--integrator", "path", "--max-depth", args.max_depth, "--seed", seed,
                   "--env", f"{ENV_RADIANCE},{ENV_RADIANCE},{ENV_RADIANCE}", "--threads", threads,
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


def ground_plane(lo, hi):
    """Two triangles of a square ground under the model's bounds (y = the lowest point), facing
    +Y, GROUND_RADII bounding-sphere radii wide, centred under the model."""
    import numpy as np

    cx, cz = (lo[0] + hi[0]) / 2, (lo[2] + hi[2]) / 2
    h = GROUND_RADII * 0.5 * math.dist(lo, hi) / 2
    y = lo[1]
    a, b, c, d = (cx - h, y, cz - h), (cx + h, y, cz - h), (cx + h, y, cz + h), (cx - h, y, cz + h)
    # Counter-clockwise seen from +Y: a, d, c and a, c, b.
    return np.array([[a, d, c], [a, c, b]], dtype="<f4")


def pick_mesh(args, scenes: Path) -> str:
    """The mesh spec (and, when not given, the model's up axis into args.up)."""
    bunny = scenes / "stanford_bunny" / "bun_zipper.ply"
    lucy = scenes / "lucy_100k" / "lucy.ply"
    if args.mesh:
        spec = args.mesh
    elif CASES[args.case]["mesh"] == "bunny":
        if not bunny.exists():
            sys.exit(f"--case {args.case} renders the Stanford bunny, and {bunny} does not exist: set DRAY_SCENES "
                     "to the shared scenes folder (default ../shared/scenes beside the repository) or pass --mesh")
        spec = str(bunny)
    elif CASES[args.case]["mesh"] == "lucy":
        if lucy.exists():
            spec = str(lucy)
        elif bunny.exists():
            env.log(f"{lucy} not found (set DRAY_SCENES to the shared scenes folder): using the Stanford bunny "
                    f"{bunny} instead (69,451 triangles, also a scanned model)")
            spec = str(bunny)
        else:
            sys.exit(f"--case deep renders a scanned model, and neither {lucy} nor {bunny} exists: set DRAY_SCENES "
                     "to the shared scenes folder (default ../shared/scenes beside the repository) or pass --mesh")
    else:
        spec = str(bunny) if bunny.exists() else FALLBACK_MESH
        if not bunny.exists():
            env.log(f"{bunny} not found: using the procedural mesh {FALLBACK_MESH}")
    if args.up is None:  # Lucy's scan stands along +Z; the bunny and the procedural meshes along +Y
        is_lucy = lucy.exists() and Path(spec).exists() and Path(spec).resolve() == lucy.resolve()
        args.up = "z" if is_lucy else "y"
    return spec


def summarize(dray_runs: list, mruns: dict, failed: dict) -> tuple[dict, dict]:
    """Medians of one thread count's rounds: (dray, {variant: Mitsuba})."""
    warm_dray = dray_runs[1:] or dray_runs
    d = {"runs": dray_runs, "cold_wall_s": dray_runs[0]["wall_s"],
         "warm_wall_s": statistics.median(r["wall_s"] for r in warm_dray),
         "warm_render_s": statistics.median(r["stats"]["render_time_s"] for r in warm_dray),
         "cpu_per_wall": statistics.median(r["cpu_s"] / r["wall_s"] for r in dray_runs),
         "max_other_cores": max(r["other_cores"] for r in dray_runs)}
    m: dict = {}
    for v, ms in mruns.items():
        if not ms:
            m[v] = failed.get(v, {"ok": False, "error": "not run"})
            continue
        m[v] = {
            "ok": True, "rounds": ms, "import_s": statistics.median(x["import_s"] for x in ms),
            "cold_total_s": statistics.median(x["runs"][0]["total_s"] for x in ms),
            "warm_total_s": statistics.median(x["runs"][1]["total_s"] for x in ms),
            "warm_render_s": statistics.median(x["runs"][1]["render_s"] for x in ms),
            "cpu_per_wall": statistics.median(x["runs"][1]["cpu_s"] / x["runs"][1]["total_s"] for x in ms),
            "max_other_cores": max(x["other_cores"] for x in ms),
            "libllvm": ms[0]["libllvm"], "thread_count": ms[0]["thread_count"]}
    return d, m


def main() -> None:
    args = parse_args()
    if args.mitsuba_worker:
        mitsuba_worker(args.mitsuba_worker)
        return
    import numpy as np

    dray = env.dray_binary()
    scenes = env.scenes_dir()
    spec = pick_mesh(args, scenes)
    args.out.mkdir(parents=True, exist_ok=True)
    for pattern in ("dray_*", "mitsuba_*", "flip_*", "results.json", "mesh.*", "scene.gltf"):
        for f in args.out.glob(pattern):  # outputs of an earlier run
            if f.is_file():
                f.unlink()
    threads_list = args.thread_counts
    top = max(threads_list)  # the thread count of the targets and the quality renders
    multi = len(threads_list) > 1

    # 1. The mesh as dray sees it -> glTF for dray, PLY for Mitsuba.
    soup = args.out / "mesh.tris.f32"
    env.run_timed([dray, "bench-rays", spec, "--kind", "primary", "--res", 1, "--repeat", 1, "--dump-mesh", soup])
    tris = np.fromfile(soup, dtype="<f4").reshape(-1, 3, 3)
    soup.unlink()
    if args.up == "z":  # +Z up -> +Y up: (x, y, z) -> (-x, z, y), a rotation (det +1, winding kept); the
        # camera (on +Z after it) then looks at the model's +Y side: Lucy's front
        tris = np.ascontiguousarray(np.stack([-tris[..., 0], tris[..., 2], tris[..., 1]], axis=-1), dtype="<f4")
    lo, hi = tris.reshape(-1, 3).min(0).tolist(), tris.reshape(-1, 3).max(0).tolist()
    if CASES[args.case]["ground"]:
        tris = np.concatenate([tris, ground_plane(lo, hi)])
    mesh = write_meshes(tris, args.out)
    cam = camera_frame(lo, hi)  # frames the model; the ground runs out of the picture
    gltf = write_gltf(mesh, cam, args.out, args.width, args.height)
    env.log(f"scene: {spec}: {mesh['triangles']} triangles, {mesh['vertices']} vertices"
            + (" (Z up, rotated to Y up)" if args.up == "z" else "") + f" -> {gltf}, {mesh['ply']}")
    base_cfg = {"ply": str(mesh["ply"]), "camera": [list(v) for v in cam], "width": args.width,
                "height": args.height, "max_depth": args.mitsuba_max_depth, "rr_depth": MITSUBA_RR_DEPTH}

    info = env.machine_info()
    info["busy_cores_before_start"] = round(env.idle_check(), 2)
    load = env.OtherLoad()
    info["packages"] = env.package_versions(["mitsuba", "drjit", "flip-evaluator", "numpy"])
    info["dray_binary"] = env.binary_info(dray)
    res = {"machine": info, "case": args.case,
           "scene": {"mesh": spec, "ground_plane": CASES[args.case]["ground"], "triangles": mesh["triangles"],
                     "up": args.up, "width": args.width,
                     "height": args.height, "spp": args.spp, "ref_spp": args.ref_spp,
                     "mitsuba_max_depth": args.mitsuba_max_depth, "dray_max_depth": args.max_depth,
                     "mitsuba_rr_depth": MITSUBA_RR_DEPTH, "dray_rr_from_vertex_depth": DRAY_RR_START,
                     "albedo": ALBEDO, "sun_irradiance": SUN_IRRADIANCE,
                     "sun_direction": SUN_DIRECTION, "env_radiance": ENV_RADIANCE,
                     "yfov_deg": YFOV_DEG},
           "cores": args.cores, "threads": top if not multi else threads_list}

    # 2. Timed renders, interleaved round by round (per thread count: dray, Mitsuba llvm_ad_rgb,
    # Mitsuba scalar_rgb) so that any other load on the machine hits all of them alike. Each
    # Mitsuba round is a fresh process (fresh HOME, so an empty Dr.Jit kernel cache) doing two
    # load+render passes: the first is "cold" (includes JIT compilation for llvm), the second "warm".
    llvm_env: dict = {}
    if os.environ.get("DRJIT_LIBLLVM_PATH"):
        llvm_env["DRJIT_LIBLLVM_PATH"] = os.environ["DRJIT_LIBLLVM_PATH"]
    attempts: list = []
    pair = [{"spp": args.spp, "seed": args.seed}, {"spp": args.spp, "seed": args.seed}]
    dray_runs: dict = {t: [] for t in threads_list}
    mruns: dict = {t: {"llvm_ad_rgb": [], "scalar_rgb": []} for t in threads_list}
    failed: dict = {}
    for rnd in range(args.runs):
        for t in threads_list:
            tsuf = f"_t{t}" if multi else ""  # file tags of a single thread count are the original ones
            tlog = f", {t} thread{'s' if t > 1 else ''} (cores {cores_for(args, t)})" if multi else ""
            tcores = env.parse_cores(cores_for(args, t))
            env.log(f"round {rnd + 1}/{args.runs}: dray, {args.spp} spp{tlog}")
            o = env.OtherLoad(tcores)
            x = run_dray(args, dray, gltf, args.spp, f"{args.spp}spp{tsuf}_round{rnd}", args.seed, t)
            x["other_cores"] = o.cores()
            dray_runs[t].append(x)
            env.log(f"  dray: wall {x['wall_s']:.2f} s, render {x['stats']['render_time_s']:.2f} s, "
                    f"cpu/wall {x['cpu_s'] / x['wall_s']:.2f}, others {x['other_cores']:.2f} cores")
            for v in ("llvm_ad_rgb", "scalar_rgb"):
                if v in failed:
                    continue
                venv_extra = llvm_env if v == "llvm_ad_rgb" else {}
                env.log(f"round {rnd + 1}/{args.runs}: mitsuba {v}{tlog}" + (f" {venv_extra}" if venv_extra else ""))
                o = env.OtherLoad(tcores)
                m = run_mitsuba(args, base_cfg, v, pair, v + tsuf, venv_extra, t)
                if not m["ok"] and v == "llvm_ad_rgb" and not llvm_env and not args.no_llvm_fetch:
                    attempts.append({k: m[k] for k in ("variant", "rc", "error", "env")})
                    env.log(f"  failed with the system LLVM: {m['error']}")
                    lib, how = fetch_llvm(env.VENV / "llvm")
                    attempts.append({"fetch": how})
                    env.log(f"  {how}")
                    if lib:
                        llvm_env = {"DRJIT_LIBLLVM_PATH": str(lib)}
                        o = env.OtherLoad(tcores)
                        m = run_mitsuba(args, base_cfg, v, pair, v + tsuf, llvm_env, t)
                if not m["ok"]:
                    attempts.append({k: m[k] for k in ("variant", "rc", "error", "env")})
                    env.log(f"  {v} failed: {m['error']}")
                    failed[v] = m
                    continue
                m["other_cores"] = o.cores()
                mruns[t][v].append(m)
                env.log(f"  {v}: cold {m['runs'][0]['total_s']:.2f} s, warm {m['runs'][1]['total_s']:.2f} s, "
                        f"cpu/wall {m['runs'][1]['cpu_s'] / m['runs'][1]['total_s']:.2f}, "
                        f"others {m['other_cores']:.2f} cores")

    by_threads: dict = {}
    for t in threads_list:
        d, m = summarize(dray_runs[t], mruns[t], failed)
        by_threads[t] = {"threads": t, "cores": cores_for(args, t), "dray": d, "mitsuba": m}
    # The top thread count's numbers where they always were (the targets refer to them).
    res["dray"] = by_threads[top]["dray"]
    res["mitsuba"] = {"llvm_attempts": attempts, **by_threads[top]["mitsuba"]}
    ran = [v for v in ("llvm_ad_rgb", "scalar_rgb") if res["mitsuba"][v].get("ok")]
    res["mitsuba"]["ran"] = ran
    if multi:
        res["by_threads"] = {str(t): b for t, b in by_threads.items()}
        res["scaling"] = scaling(by_threads, threads_list)

    # 4. Quality at ref spp: FLIP between the LDR images (at the top thread count).
    if ran:
        ref_variant = ran[0]
        env.log(f"quality: dray and mitsuba {ref_variant} at {args.ref_spp} spp")
        dref = run_dray(args, dray, gltf, args.ref_spp, f"{args.ref_spp}spp", args.seed, top)
        ref_runs = [{"spp": args.ref_spp, "seed": args.seed, "save": str(args.out / "mitsuba_ref.npy")}]
        if ref_variant == "llvm_ad_rgb":  # cheap: a second seed gives Mitsuba's own noise floor
            ref_runs.append({"spp": args.ref_spp, "seed": args.seed + 1000, "save": str(args.out / "mitsuba_ref2.npy")})
        mref = run_mitsuba(args, base_cfg, ref_variant, ref_runs, "ref",
                           llvm_env if ref_variant == "llvm_ad_rgb" else {}, top)
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
        q = {"ref_variant": ref_variant, "ref_spp": args.ref_spp, "threads": top, "flip_mean": float(mean_err),
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


RENDERERS = (("dray", None), ("Mitsuba llvm_ad_rgb", "llvm_ad_rgb"), ("Mitsuba scalar_rgb", "scalar_rgb"))


def _times(b: dict, variant: str | None) -> tuple[float, float] | None:
    """(warm whole, warm render only) of one renderer at one thread count, or None."""
    if variant is None:
        return b["dray"]["warm_wall_s"], b["dray"]["warm_render_s"]
    x = b["mitsuba"].get(variant)
    return (x["warm_total_s"], x["warm_render_s"]) if x and x.get("ok") else None


def scaling(by_threads: dict, threads_list: list) -> dict:
    """dray/Mitsuba time ratios per thread count, and each renderer's speedup from the fewest
    to the most threads (warm medians)."""
    ratios = {}
    for t in threads_list:
        b = by_threads[t]
        dw, dr_ = _times(b, None)
        ratios[str(t)] = {}
        for v in ("llvm_ad_rgb", "scalar_rgb"):
            mt = _times(b, v)
            if mt:
                ratios[str(t)][v] = {"dray_over_mitsuba_warm": dw / mt[0], "dray_over_mitsuba_render": dr_ / mt[1]}
    lo, hi = min(threads_list), max(threads_list)
    speedup = {}
    for name, v in RENDERERS:
        a, b = _times(by_threads[lo], v), _times(by_threads[hi], v)
        if a and b:
            speedup[name] = {"from_threads": lo, "to_threads": hi, "warm": a[0] / b[0], "render": a[1] / b[1],
                             "warm_s": {str(lo): a[0], str(hi): b[0]}, "render_s": {str(lo): a[1], str(hi): b[1]}}
    return {"time_ratios": ratios, "speedup": speedup}


def report(res: dict, args) -> None:
    m = res["machine"]
    sc_ = res["scene"]
    multi = "by_threads" in res
    rr = (f", rr_depth {sc_['mitsuba_rr_depth']} (dray's roulette from vertex depth {sc_['dray_rr_from_vertex_depth']})"
          if args.max_depth > DRAY_RR_START else "")
    print(f"# dray vs Mitsuba 3, {sc_['mesh']} ({sc_['triangles']:,} triangles"
          + (", Z up rotated to Y up" if sc_["up"] == "z" else "") + f"), "
          f"{args.width}x{args.height}, {args.spp} spp, Mitsuba max_depth {args.mitsuba_max_depth} = dray --max-depth "
          f"{args.max_depth}{rr}")
    threads_txt = (f"{args.threads} threads each" if not multi else
                   f"threads {','.join(map(str, args.thread_counts))} each (N threads on the first N cores)")
    print(f"# {m['cpu_model']}, nproc {m['nproc']}, {m['date']}, cores {args.cores}, {threads_txt}, "
          f"dray {m['dray_git']}, mitsuba {m['packages']['mitsuba']}, drjit {m['packages']['drjit']}")
    print(f"# other processes used {m['other_processes_cores_during_run']:.2f} cores on average during the run "
          f"({m['busy_cores_before_start']:.2f} busy just before it)")
    print(f"# {args.runs} interleaved rounds; cold = first, warm = median of the rest (dray) or of each round's "
          "second pass (Mitsuba)")
    blocks = ([(t, res["by_threads"][str(t)]) for t in args.thread_counts] if multi
              else [(None, {"dray": res["dray"], "mitsuba": res["mitsuba"]})])
    for t, b in blocks:
        if t is not None:
            print(f"\n## {t} thread{'s' if t > 1 else ''} each, cores {b['cores']}\n")
        d = b["dray"]
        print("| renderer | cold (s) | warm (s) | warm render only (s) | CPU/wall | max other load (cores) | what is timed |")
        print("|---|---:|---:|---:|---:|---:|---|")
        print(f"| dray | {d['cold_wall_s']:.2f} | {d['warm_wall_s']:.2f} | {d['warm_render_s']:.2f} | "
              f"{d['cpu_per_wall']:.2f} | {d['max_other_cores']:.2f} | whole `dray render` process; "
              "render only = stats render_time_s |")
        for v in ("llvm_ad_rgb", "scalar_rgb"):
            x = b["mitsuba"].get(v)
            if x and x.get("ok"):
                print(f"| Mitsuba {v} | {x['cold_total_s']:.2f} | {x['warm_total_s']:.2f} | {x['warm_render_s']:.2f} | "
                      f"{x['cpu_per_wall']:.2f} | {x['max_other_cores']:.2f} | load_dict + render + to numpy; "
                      f"not counted: interpreter start + import ({x['import_s']:.2f} s) |")
            elif x:
                print(f"| Mitsuba {v} | failed | | | | | {x.get('error')} |")
    for a in res["mitsuba"]["llvm_attempts"]:
        print(f"# llvm attempt: {a}")
    if multi:
        s = res["scaling"]
        print("\n## dray / Mitsuba time (warm medians; above 1 = dray slower)\n")
        print("| threads | cores | dray warm (s) | dray / llvm_ad_rgb | dray / scalar_rgb | render only: dray / llvm_ad_rgb "
              "| render only: dray / scalar_rgb |")
        print("|---:|---|---:|---:|---:|---:|---:|")
        for t in args.thread_counts:
            r = s["time_ratios"][str(t)]
            cell = lambda v, k: f"{r[v][k]:.2f}" if v in r else "n/a"  # noqa: E731
            print(f"| {t} | {res['by_threads'][str(t)]['cores']} | {res['by_threads'][str(t)]['dray']['warm_wall_s']:.2f} "
                  f"| {cell('llvm_ad_rgb', 'dray_over_mitsuba_warm')} | {cell('scalar_rgb', 'dray_over_mitsuba_warm')} "
                  f"| {cell('llvm_ad_rgb', 'dray_over_mitsuba_render')} | {cell('scalar_rgb', 'dray_over_mitsuba_render')} |")
        lo, hi = min(args.thread_counts), max(args.thread_counts)
        print(f"\n## Speedup from {lo} to {hi} threads (warm time at {lo} / warm time at {hi})\n")
        print(f"| renderer | warm, {lo} thr. (s) | warm, {hi} thr. (s) | **speedup** | render only: {lo} thr. (s) "
              f"| render only: {hi} thr. (s) | render-only speedup |")
        print("|---|---:|---:|---:|---:|---:|---:|")
        for name, _ in RENDERERS:
            x = s["speedup"].get(name)
            if x:
                print(f"| {name} | {x['warm_s'][str(lo)]:.2f} | {x['warm_s'][str(hi)]:.2f} | **{x['warm']:.2f}x** | "
                      f"{x['render_s'][str(lo)]:.2f} | {x['render_s'][str(hi)]:.2f} | {x['render']:.2f}x |")
    d = res["dray"]
    sc = res["mitsuba"].get("scalar_rgb", {})
    at = f" at {max(args.thread_counts)} threads" if multi else ""
    if sc.get("ok"):
        ratio = sc["warm_total_s"] / d["warm_wall_s"]
        print(f"\ntarget 'dray faster than Mitsuba scalar_rgb'{at}: {'MET' if ratio > 1 else 'MISSED'} "
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

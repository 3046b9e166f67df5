#!/usr/bin/env python3
"""Closest-hit ray throughput: dray vs Embree (PyPI `embreex`), one core, the same rays.

For each mesh, `dray bench-rays` builds its BVH, traces primary (camera) and incoherent
(random origin, random direction) rays, and dumps the exact triangles and rays it used
(`--dump-mesh`, `--dump-rays`). The same triangles and rays are then loaded into Embree
through embreex and traced with closest-hit queries (tmin 0, tmax "infinite" = 1e37).
Both processes are pinned to one core with `taskset -c CORE` (Embree would otherwise
start one TBB thread per core for its build) and dray runs with `--threads 1`.

dray runs twice on each ray set: one ray at a time (`Accel::closest`, what the renderer
calls today) and `--batch` (`Accel::closest_batch`, 16 rays in flight with their memory
loads overlapped; the script checks that it finds the same hits and distance sum).
Embree is traced one ray at a time by embreex's loop (rtcIntersect1).

Reported per mesh and ray kind: Mrays/s of each (median of --repeat passes), the ratio
dray/Embree, hit counts and their agreement, the sum of hit distances, and the fixed cost
of calling Embree from Python (a 1-ray batch, and a batch of rays that miss the scene's
bounding box, which measures the per-ray cost of embreex's Cython loop plus Embree's
cheapest possible query).

Usage (from the repository root; creates benches/.venv on first use):
    benches/ray_throughput.sh                       # builds dray, then runs this
    python3 benches/ray_throughput.py [--mesh SPEC ...] [--res 1024] [--rays 1000000]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _bench_env as env  # noqa: E402

# About 1.3M triangles each (dray prints the exact count; see docs/benchmarks.md, "Ray
# throughput and BVH build against Embree").
DEFAULT_PROCEDURAL = "iso:gyroid:259"  # 1,300,420 triangles
LUCY_GRID = "grid:{scenes}/lucy_100k/lucy.ply:1x13x1"  # 13 x 99,970 = 1,299,610 triangles


def parse_args() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mesh", action="append", help="mesh spec (repeatable); default: "
                    f"{DEFAULT_PROCEDURAL} and the 13-copy Lucy grid if $DRAY_SCENES has it")
    ap.add_argument("--res", type=int, default=1024, help="primary rays: res x res (default 1024)")
    ap.add_argument("--rays", type=int, default=1_000_000, help="incoherent rays (default 1M)")
    ap.add_argument("--repeat", type=int, default=5, help="timed passes per side; the median is reported")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--core", default="0", help="CPU core both sides are pinned to (taskset -c)")
    ap.add_argument("--keep-dumps", action="store_true", help="keep the dumped mesh/ray files")
    ap.add_argument("--json", type=Path, default=env.OUT / "ray_throughput.json", help="results file")
    # Internal: the Embree side, run in its own pinned process.
    ap.add_argument("--embree-worker", nargs=2, metavar=("MESH_F32", "RAYS_F32"), help=argparse.SUPPRESS)
    return ap.parse_args()


# ---------------------------------------------------------------------------------------
# Embree side (runs inside `taskset -c CORE python ray_throughput.py --embree-worker ...`)
# ---------------------------------------------------------------------------------------

def embree_worker(mesh_path: str, rays_path: str, repeat: int) -> None:
    import numpy as np

    tris = np.fromfile(mesh_path, dtype="<f4").reshape(-1, 3, 3)
    rays = np.fromfile(rays_path, dtype="<f4").reshape(-1, 6)
    origins = np.ascontiguousarray(rays[:, :3])
    dirs = np.ascontiguousarray(rays[:, 3:])
    n = len(rays)

    # Build: scene + mesh + commit (embreex commits lazily on the first run()). build_s is
    # the whole of it, as before; commit_s is the BVH build alone and copy_s embreex's
    # Python-speed copy of the vertices (see _bench_env.embree_build and bvh_build.py).
    scene, bt = env.embree_build(tris)
    build_s = bt["device_s"] + bt["copy_s"] + bt["first_query_s"]

    MISS = np.float32(1e37)  # embreex's default tfar; unchanged on a miss
    times = []
    dist = None
    scene.run(origins[: min(n, 65536)], dirs[: min(n, 65536)], query="DISTANCE")  # warm caches
    for _ in range(repeat):
        t = time.perf_counter()
        dist = scene.run(origins, dirs, query="DISTANCE")
        times.append(time.perf_counter() - t)
    hit = dist < MISS
    median_s = statistics.median(times)

    # Fixed costs of the Python binding.
    one_o, one_d = origins[:1].copy(), dirs[:1].copy()
    call = []
    for _ in range(2000):
        t = time.perf_counter()
        scene.run(one_o, one_d, query="DISTANCE")
        call.append(time.perf_counter() - t)
    # Rays that start outside the bounds and point away from them: every one misses the
    # root box, so this is the per-ray floor (Cython loop + ray setup + rtcIntersect1 entry).
    lo, hi = tris.reshape(-1, 3).min(0), tris.reshape(-1, 3).max(0)
    away_o = np.tile(hi + (hi - lo) + 1.0, (n, 1)).astype(np.float32)
    away_d = np.tile(np.array([[1.0, 1.0, 1.0]], np.float32) / np.sqrt(3.0), (n, 1)).astype(np.float32)
    floor = []
    for _ in range(3):
        t = time.perf_counter()
        d_away = scene.run(away_o, away_d, query="DISTANCE")
        floor.append(time.perf_counter() - t)
    assert not (d_away < MISS).any(), "rays pointing away from the bounds hit something"

    print(json.dumps({
        "triangles": int(len(tris)),
        "rays": int(n),
        "build_s": build_s,
        "commit_s": bt["commit_s"],
        "copy_s": bt["copy_s"],
        "times_s": times,
        "median_s": median_s,
        "mrays_per_s": n / median_s / 1e6,
        "hits": int(hit.sum()),
        "t_sum": float(dist[hit].astype(np.float64).sum()),
        "call_overhead_us": statistics.median(call) * 1e6,
        "miss_floor_ns_per_ray": statistics.median(floor) / n * 1e9,
        "affinity": sorted(os.sched_getaffinity(0)),
    }))


# ---------------------------------------------------------------------------------------
# Driver
# ---------------------------------------------------------------------------------------

def slug(spec: str) -> str:
    return re.sub(r"[^A-Za-z0-9]+", "_", Path(spec).name if "/" in spec and ":" not in spec else spec).strip("_")[-60:]


def main() -> None:
    args = parse_args()
    if args.embree_worker:
        embree_worker(*args.embree_worker, repeat=args.repeat)
        return

    dray = env.dray_binary()
    scenes = env.scenes_dir()
    meshes = args.mesh or [DEFAULT_PROCEDURAL]
    if not args.mesh:
        if (scenes / "lucy_100k" / "lucy.ply").exists():
            meshes.append(LUCY_GRID.format(scenes=scenes))
        else:
            env.log(f"no {scenes}/lucy_100k/lucy.ply: benchmarking the procedural mesh only")
    work = env.OUT / "ray_throughput"
    work.mkdir(parents=True, exist_ok=True)

    info = env.machine_info()
    info["busy_cores_before_start"] = round(env.idle_check(), 2)
    load = env.OtherLoad()
    info["packages"] = env.package_versions(["embreex", "numpy"])
    info["dray_binary"] = env.binary_info(dray)
    results = []
    for spec in meshes:
        tag = slug(spec)
        mesh_f = work / f"{tag}.tris.f32"
        for kind in ("primary", "incoherent"):
            rays_f = work / f"{tag}.{kind}.rays.f32"
            cmd = [dray, "bench-rays", spec, "--kind", kind, "--threads", 1, "--seed", args.seed,
                   "--repeat", args.repeat, "--res", args.res, "--rays", args.rays, "--dump-rays", rays_f]
            if kind == "primary" or not mesh_f.exists():
                cmd += ["--dump-mesh", mesh_f]
            env.log(f"dray bench-rays {spec} --kind {kind}")
            o = env.OtherLoad(env.parse_cores(args.core))
            r = env.run_timed(env.pin(args.core, cmd))
            dray_others = o.cores()
            d = env.last_json_line(r["stdout"])
            d["cmd"] = r["cmd"]
            env.log(f"  dray: {d['triangles']} triangles, {d['rays']} rays, {d['mrays_per_s']:.3f} Mrays/s, "
                    f"{d['hits']} hits, build {d['build_s']:.2f} s")
            # The same rays through closest_batch (16 rays in flight): same answers.
            bcmd = [dray, "bench-rays", spec, "--kind", kind, "--threads", 1, "--seed", args.seed,
                    "--repeat", args.repeat, "--res", args.res, "--rays", args.rays, "--batch"]
            o = env.OtherLoad(env.parse_cores(args.core))
            br = env.run_timed(env.pin(args.core, bcmd))
            batch_others = o.cores()
            b = env.last_json_line(br["stdout"])
            b["cmd"] = br["cmd"]
            if (b["hits"], b["t_sum"]) != (d["hits"], d["t_sum"]):
                raise RuntimeError(f"closest_batch answers differ: {b['hits']} hits, t_sum {b['t_sum']} "
                                   f"against {d['hits']}, {d['t_sum']}")
            env.log(f"  dray --batch: {b['mrays_per_s']:.3f} Mrays/s")

            env.log("  embree (embreex) on the same triangles and rays")
            ecmd = [sys.executable, Path(__file__).resolve(), "--embree-worker", mesh_f, rays_f,
                    "--repeat", args.repeat]
            o = env.OtherLoad(env.parse_cores(args.core))
            er = env.run_timed(env.pin(args.core, ecmd))
            embree_others = o.cores()
            e = env.last_json_line(er["stdout"])
            e["cmd"] = er["cmd"]
            env.log(f"  embree: {e['mrays_per_s']:.3f} Mrays/s, {e['hits']} hits, build {e['build_s']:.2f} s, "
                    f"call overhead {e['call_overhead_us']:.1f} us, miss floor {e['miss_floor_ns_per_ray']:.1f} ns/ray")
            if e["triangles"] != d["triangles"] or e["rays"] != d["rays"]:
                raise RuntimeError(f"dump mismatch: dray {d['triangles']} tris/{d['rays']} rays, "
                                   f"embree read {e['triangles']}/{e['rays']}")
            hd, he = d["hits"], e["hits"]
            agree = 100.0 * (1.0 - abs(hd - he) / d["rays"])
            tsum_rel = abs(d["t_sum"] - e["t_sum"]) / max(abs(e["t_sum"]), 1e-30)
            per_ray_ns = e["median_s"] / e["rays"] * 1e9
            results.append({
                "mesh": spec, "kind": kind, "triangles": d["triangles"], "rays": d["rays"],
                "dray": d, "dray_batch": b, "embree": e,
                "ratio_dray_over_embree": d["mrays_per_s"] / e["mrays_per_s"],
                "ratio_dray_batch_over_embree": b["mrays_per_s"] / e["mrays_per_s"],
                "hit_count_agreement_pct": agree,
                "t_sum_rel_diff": tsum_rel,
                "embree_miss_floor_share_pct": 100.0 * e["miss_floor_ns_per_ray"] / per_ray_ns,
                "other_load_on_core": {"dray": dray_others, "dray_batch": batch_others,
                                       "embree": embree_others},
            })
            if not args.keep_dumps:
                rays_f.unlink(missing_ok=True)
        if not args.keep_dumps:
            mesh_f.unlink(missing_ok=True)

    env.save_results(args.json, info, args, results, load)

    print(f"# ray throughput, 1 core (taskset -c {args.core}), median of {args.repeat}")
    print(f"# {info['cpu_model']}, nproc {info['nproc']}, {info['date']}, dray {info['dray_git']}, "
          f"embreex {info['packages']['embreex']}")
    print(f"# other processes used {info['other_processes_cores_during_run']:.2f} cores on average during the run "
          f"({info['busy_cores_before_start']:.2f} busy just before it)")
    print("| mesh | triangles | rays | kind | dray Mrays/s | dray batch Mrays/s | Embree Mrays/s | dray/Embree "
          "| batch/Embree | hits dray | hits Embree "
          "| hit agreement | t_sum rel. diff | build dray s | build Embree s | of which Embree commit s "
          "| other load on core |")
    print("|---|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in results:
        print(f"| `{r['mesh']}` | {r['triangles']:,} | {r['rays']:,} | {r['kind']} | {r['dray']['mrays_per_s']:.3f} | "
              f"{r['dray_batch']['mrays_per_s']:.3f} | "
              f"{r['embree']['mrays_per_s']:.3f} | {r['ratio_dray_over_embree']:.2f} | "
              f"{r['ratio_dray_batch_over_embree']:.2f} | {r['dray']['hits']:,} | "
              f"{r['embree']['hits']:,} | {r['hit_count_agreement_pct']:.4f}% | {r['t_sum_rel_diff']:.2e} | "
              f"{r['dray']['build_s']:.2f} | {r['embree']['build_s']:.2f} | {r['embree']['commit_s']:.2f} | "
              f"{max(r['other_load_on_core'].values()):.2f} |")
    print("\n(build Embree = device + embreex's vertex copy (a Python-speed loop) + rtcCommitScene; the commit alone "
          "is Embree's BVH build. benches/bvh_build.py compares build rates over interleaved rounds.)")
    print()
    print("| mesh | kind | Embree ns/ray | embreex 1-ray call (us) | embreex miss floor (ns/ray) | floor share of Embree time |")
    print("|---|---|---:|---:|---:|---:|")
    for r in results:
        e = r["embree"]
        print(f"| `{r['mesh']}` | {r['kind']} | {e['median_s'] / e['rays'] * 1e9:.1f} | {e['call_overhead_us']:.2f} | "
              f"{e['miss_floor_ns_per_ray']:.1f} | {r['embree_miss_floor_share_pct']:.1f}% |")
    print(f"\nresults: {args.json}")


if __name__ == "__main__":
    env.ensure_venv()
    main()

#!/usr/bin/env python3
"""BVH build rate: dray vs Embree (PyPI `embreex`), one core, one thread, the same triangles.

For each mesh, `dray bench-rays MESH --dump-mesh` first writes the exact triangles dray
builds over (unwelded f32 records, as benches/ray_throughput.py uses them). Then, in
--rounds interleaved rounds (per round, per mesh: dray, then Embree, each a fresh
process pinned with `taskset -c CORE`):

- dray: `dray bench-rays MESH --kind primary --res 1 --repeat 1 --threads 1`. Its JSON line
  has `build_s`: the wall time of `Accel::build` over the loaded mesh (binned-SAH BVH2,
  the CWBVH conversion, dray's node and triangle re-layout). Loading or generating the
  mesh is not in it; tracing one ray follows it and is not in it either. The build is
  single-threaded code; the pin makes sure of it.
- Embree: `python bvh_build.py --embree-worker T.f32` loads the same triangles and builds
  with `_bench_env.embree_build`: `EmbreeDevice()` + `EmbreeScene()`, then
  `TriangleMesh(scene, tris)` (embreex's copy of the vertices into Embree's buffers, in
  a Python-speed loop: reported, not counted), then the first one-ray `run()`, inside
  which embreex calls rtcCommitScene (the BVH build: checked by `is_committed` going
  from 0 to 1 across it). The commit time is that first call minus the median of later
  one-ray calls. embreex cannot pass `threads=1` to rtcNewDevice (it calls
  `rtcNewDevice(NULL)`, and its Embree reads no ~/.embree4), so one thread comes from
  the pin: TBB starts one worker per core in the affinity mask. The worker reports the
  threads in its process and the CPU time of the commit to show it. Embree's defaults:
  RTC_BUILD_QUALITY_MEDIUM (binned SAH, no spatial splits), BVH8 on AVX2 CPUs.

Reported per mesh: the median over rounds of each build time, million triangles per
second of build (triangles / median time) for each, and dray's rate over Embree's.

Usage (from the repository root; creates benches/.venv on first use):
    benches/bvh_build.sh                        # builds dray, then runs this
    python3 benches/bvh_build.py [--mesh SPEC ...] [--rounds 5] [--core 0]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _bench_env as env  # noqa: E402

# The meshes of benches/ray_throughput.py (about 1.3M triangles each), and the two scanned
# models themselves.
PROCEDURAL = "iso:gyroid:259"  # 1,300,420 triangles
BUNNY = "{scenes}/stanford_bunny/bun_zipper.ply"  # 69,451 triangles
LUCY = "{scenes}/lucy_100k/lucy.ply"  # 99,970 triangles
LUCY_GRID = "grid:{scenes}/lucy_100k/lucy.ply:1x13x1"  # 13 x 99,970 = 1,299,610 triangles


def parse_args() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mesh", action="append", help="mesh spec (repeatable); default: the Stanford bunny, Lucy, "
                    f"{PROCEDURAL} and the 13-copy Lucy grid (the scanned ones if $DRAY_SCENES has them)")
    ap.add_argument("--rounds", type=int, default=5, help="interleaved rounds; medians are reported (default 5)")
    ap.add_argument("--core", default="0", help="the one CPU core both sides are pinned to (taskset -c)")
    ap.add_argument("--keep-dumps", action="store_true", help="keep the dumped triangle files")
    ap.add_argument("--json", type=Path, default=env.OUT / "bvh_build.json", help="results file")
    ap.add_argument("--embree-worker", metavar="MESH_F32", help=argparse.SUPPRESS)  # internal
    return ap.parse_args()


def embree_worker(mesh_path: str) -> None:
    import numpy as np

    tris = np.fromfile(mesh_path, dtype="<f4").reshape(-1, 3, 3)
    _, t = env.embree_build(tris)
    print(json.dumps({"triangles": int(len(tris)), **t, "affinity": sorted(os.sched_getaffinity(0))}))


def slug(spec: str) -> str:
    return re.sub(r"[^A-Za-z0-9]+", "_", spec).strip("_")[-60:]


def short(spec: str, scenes: Path) -> str:
    return spec.replace(str(scenes), "$DRAY_SCENES")


def main() -> None:
    args = parse_args()
    if args.embree_worker:
        embree_worker(args.embree_worker)
        return
    if len(env.parse_cores(args.core)) != 1:
        sys.exit("--core takes one core: both builds are single-threaded")

    dray = env.dray_binary()
    scenes = env.scenes_dir()
    if args.mesh:
        meshes = list(args.mesh)
    else:
        meshes = []
        missing = []
        for tmpl in (BUNNY, LUCY):
            p = Path(tmpl.format(scenes=scenes))
            (meshes if p.exists() else missing).append(str(p))
        meshes.append(PROCEDURAL)
        if Path(LUCY.format(scenes=scenes)).exists():
            meshes.append(LUCY_GRID.format(scenes=scenes))
        if missing:
            env.log(f"not found (set DRAY_SCENES to the shared scenes folder): {', '.join(missing)}; "
                    f"benchmarking {', '.join(meshes)} only")
    work = env.OUT / "bvh_build"
    work.mkdir(parents=True, exist_ok=True)

    # The exact triangles dray builds over, for Embree (one untimed dray run per mesh).
    dumps = {}
    for spec in meshes:
        f = work / f"{slug(spec)}.tris.f32"
        env.log(f"dump {spec} -> {f.name}")
        env.run_timed([dray, "bench-rays", spec, "--kind", "primary", "--res", 1, "--repeat", 1,
                       "--threads", 1, "--dump-mesh", f])
        dumps[spec] = f

    info = env.machine_info()
    info["busy_cores_before_start"] = round(env.idle_check(), 2)
    load = env.OtherLoad()
    info["packages"] = env.package_versions(["embreex", "numpy"])
    info["dray_binary"] = env.binary_info(dray)
    core = env.parse_cores(args.core)
    runs: dict = {spec: {"dray": [], "embree": []} for spec in meshes}
    for rnd in range(args.rounds):
        for spec in meshes:
            o = env.OtherLoad(core)
            r = env.run_timed(env.pin(args.core, [dray, "bench-rays", spec, "--kind", "primary", "--res", 1,
                                                  "--repeat", 1, "--threads", 1]))
            d = env.last_json_line(r["stdout"])
            d.update(cmd=r["cmd"], process_wall_s=r["wall_s"], other_cores=o.cores())
            runs[spec]["dray"].append(d)
            o = env.OtherLoad(core)
            er = env.run_timed(env.pin(args.core, [sys.executable, Path(__file__).resolve(),
                                                   "--embree-worker", dumps[spec]]))
            e = env.last_json_line(er["stdout"])
            e.update(cmd=er["cmd"], process_wall_s=er["wall_s"], other_cores=o.cores())
            runs[spec]["embree"].append(e)
            if e["triangles"] != d["triangles"]:
                raise RuntimeError(f"{spec}: dray built {d['triangles']} triangles, Embree read {e['triangles']}")
            env.log(f"round {rnd + 1}/{args.rounds} {spec}: {d['triangles']:,} triangles; dray build "
                    f"{d['build_s']:.3f} s; Embree commit {e['commit_s']:.3f} s (+ embreex copy {e['copy_s']:.3f} s), "
                    f"{e['threads_in_process']} thread(s), commit CPU/wall "
                    f"{e['commit_cpu_s'] / max(e['first_query_s'], 1e-9):.2f}; others {max(o.cores(), d['other_cores']):.2f} cores")

    results = []
    for spec in meshes:
        ds, es = runs[spec]["dray"], runs[spec]["embree"]
        n = ds[0]["triangles"]
        dray_s = statistics.median(x["build_s"] for x in ds)
        commit_s = statistics.median(x["commit_s"] for x in es)
        copy_s = statistics.median(x["copy_s"] for x in es)
        results.append({
            "mesh": spec, "triangles": n,
            "dray_build_s": dray_s, "dray_build_s_all": [x["build_s"] for x in ds],
            "dray_mtris_per_s": n / dray_s / 1e6,
            "embree_commit_s": commit_s, "embree_commit_s_all": [x["commit_s"] for x in es],
            "embree_mtris_per_s": n / commit_s / 1e6,
            "embree_copy_s": copy_s,
            "embree_copy_plus_commit_mtris_per_s": n / (copy_s + commit_s) / 1e6,
            "embree_device_s": statistics.median(x["device_s"] for x in es),
            "embree_query_s": statistics.median(x["query_s"] for x in es),
            "embree_threads_in_process": max(x["threads_in_process"] for x in es),
            "embree_commit_cpu_per_wall": statistics.median(x["commit_cpu_s"] / max(x["first_query_s"], 1e-9)
                                                            for x in es),
            "ratio_dray_rate_over_embree": commit_s / dray_s,
            "max_other_cores": max(x["other_cores"] for x in ds + es),
            "rounds": {"dray": ds, "embree": es},
        })
    if not args.keep_dumps:
        for f in dumps.values():
            f.unlink(missing_ok=True)

    env.save_results(args.json, info, args, results, load)

    print(f"# BVH build, 1 core (taskset -c {args.core}), 1 thread each, median of {args.rounds} interleaved rounds")
    print(f"# {info['cpu_model']}, nproc {info['nproc']}, {info['date']}, dray {info['dray_git']}, "
          f"embreex {info['packages']['embreex']} (Embree {results[0]['rounds']['embree'][0]['embree_version'] if results else '?'})")
    print(f"# other processes used {info['other_processes_cores_during_run']:.2f} cores on average during the run "
          f"({info['busy_cores_before_start']:.2f} busy just before it)")
    print("# dray: bench-rays build_s (Accel::build over the loaded mesh). Embree: rtcCommitScene (first 1-ray run() "
          "minus a 1-ray query); embreex's vertex copy is listed apart, not counted")
    print("| mesh | triangles | dray build (s) | dray Mtris/s | Embree build (s) | Embree Mtris/s | **dray / Embree** "
          "| embreex copy (s, not counted) | Embree threads | Embree CPU/wall | max other load on core |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in results:
        print(f"| `{short(r['mesh'], scenes)}` | {r['triangles']:,} | {r['dray_build_s']:.3f} | {r['dray_mtris_per_s']:.2f} | "
              f"{r['embree_commit_s']:.3f} | {r['embree_mtris_per_s']:.2f} | **{r['ratio_dray_rate_over_embree']:.2f}** | "
              f"{r['embree_copy_s']:.2f} | {r['embree_threads_in_process']} | {r['embree_commit_cpu_per_wall']:.2f} | "
              f"{r['max_other_cores']:.2f} |")
    print("\n(dray / Embree = dray's build rate over Embree's, i.e. Embree's time over dray's: above 1, dray builds faster.)")
    print(f"\nresults: {args.json}")


if __name__ == "__main__":
    env.ensure_venv()
    main()

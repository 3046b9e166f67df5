#!/usr/bin/env python3
"""A job group of frames (issue 42): 24 frames of a generated animated glTF (a ground
quad and a triangle sliding along +X over one second, as cli/tests/frames.rs builds it),
replicated 4x1x4 with `grid:` so every copy slides, rendered

  - in one process: `dray render --frames 0..23 --fps 24 --workers 0`, and
  - as a job group on a 2-worker `dray cluster`: `dray submit --frames 0..23 --fps 24`,

printing each wall time (the cluster's from `dray submit` to its last frame, the cluster
already up) and whether every frame's PNG is byte-identical between the two.

With --warm, instead: 12 frames of a 160x160-quad still ground (51,200 triangles)
under a small triangle sliding in one corner, `dray render --frames --workers 1
--domains 8` in one process, printing the domain loads and warm domains summed over
the frames, the workers' load (read and BVH build) seconds and the wall time: the
static domains stay warm from frame to frame (issue 42), only the moving triangle's
are built again. Run it with an older DRAY_BIN to compare.

Usage: DRAY_BIN=target/release/dray python3 benches/frames.py [--port 17400] [--warm]
"""

import argparse
import base64
import json
import os
import shutil
import struct
import subprocess
import sys
import tempfile
import time

FLAGS = (
    "--width 256 --height 192 --spp 16 --integrator path --max-depth 4 "
    "--look-from 0,6,14 --look-at 0,0,0 --sun 30,60 --animation slide"
).split()
FRAMES = ["--frames", "0..23", "--fps", "24"]
N = 24


def write_sliding(path):
    """slide.gltf: the scene of cli/tests/frames.rs `write_sliding`."""
    chunks, views, accessors = bytearray(), [], []

    def add(values, fmt, ty, count, target_minmax=False):
        while len(chunks) % 4:
            chunks.append(0)
        data = struct.pack("<" + fmt * len(values), *values)
        views.append({"buffer": 0, "byteOffset": len(chunks), "byteLength": len(data)})
        chunks.extend(data)
        acc = {
            "bufferView": len(views) - 1,
            "componentType": 5126 if fmt == "f" else 5125,
            "count": count,
            "type": ty,
        }
        if target_minmax:
            acc["min"] = [min(values[i::3]) for i in range(3)]
            acc["max"] = [max(values[i::3]) for i in range(3)]
        accessors.append(acc)
        return len(accessors) - 1

    ground = add([-2, 0, -2, 2, 0, -2, 2, 0, 2, -2, 0, 2], "f", "VEC3", 4, True)
    indices = add([0, 2, 1, 0, 3, 2], "I", "SCALAR", 6)
    tri = add([-0.5, 0, 0, 0.5, 0, 0, 0, 1, 0], "f", "VEC3", 3, True)
    times = add([0.0, 1.0], "f", "SCALAR", 2)
    keys = add([-1.0, 0, 0, 1.0, 0, 0], "f", "VEC3", 2)
    doc = {
        "asset": {"version": "2.0"},
        "buffers": [
            {
                "byteLength": len(chunks),
                "uri": "data:application/octet-stream;base64,"
                + base64.b64encode(bytes(chunks)).decode(),
            }
        ],
        "bufferViews": views,
        "accessors": accessors,
        "materials": [{"doubleSided": True}],
        "meshes": [
            {"name": "ground", "primitives": [{"attributes": {"POSITION": ground}, "indices": indices, "material": 0}]},
            {"name": "tri", "primitives": [{"attributes": {"POSITION": tri}, "material": 0}]},
        ],
        "nodes": [{"mesh": 0}, {"mesh": 1, "translation": [-1, 0, 0]}],
        "scenes": [{"nodes": [0, 1]}],
        "animations": [
            {
                "name": "slide",
                "samplers": [{"input": times, "output": keys}],
                "channels": [{"sampler": 0, "target": {"node": 1, "path": "translation"}}],
            }
        ],
    }
    with open(path, "w") as f:
        json.dump(doc, f)


def write_still_ground(path, n=160):
    """still.gltf: an n x n quad ground over [-2, 2]^2 and a small triangle sliding
    from x = 1.3 to 1.5 over one second (cli/tests/frames.rs `write_still_and_moving`,
    with a finer ground)."""
    chunks, views, accessors = bytearray(), [], []

    def add(values, fmt, ty, count):
        while len(chunks) % 4:
            chunks.append(0)
        data = struct.pack("<" + fmt * len(values), *values)
        views.append({"buffer": 0, "byteOffset": len(chunks), "byteLength": len(data)})
        chunks.extend(data)
        acc = {"bufferView": len(views) - 1, "componentType": 5126 if fmt == "f" else 5125,
               "count": count, "type": ty}
        if ty == "VEC3" and fmt == "f":
            acc["min"] = [min(values[i::3]) for i in range(3)]
            acc["max"] = [max(values[i::3]) for i in range(3)]
        accessors.append(acc)
        return len(accessors) - 1

    pos, idx = [], []
    for j in range(n + 1):
        for i in range(n + 1):
            pos += [-2 + 4 * i / n, 0.0, -2 + 4 * j / n]
    for j in range(n):
        for i in range(n):
            a = j * (n + 1) + i
            idx += [a, a + n + 1, a + 1, a + 1, a + n + 1, a + n + 2]
    ground = add(pos, "f", "VEC3", len(pos) // 3)
    indices = add(idx, "I", "SCALAR", len(idx))
    tri = add([-0.1, 0, 0, 0.1, 0, 0, 0, 1, 0], "f", "VEC3", 3)
    times = add([0.0, 1.0], "f", "SCALAR", 2)
    keys = add([1.3, 0, 0, 1.5, 0, 0], "f", "VEC3", 2)
    doc = {
        "asset": {"version": "2.0"},
        "buffers": [{"byteLength": len(chunks), "uri": "data:application/octet-stream;base64,"
                     + base64.b64encode(bytes(chunks)).decode()}],
        "bufferViews": views,
        "accessors": accessors,
        "materials": [{"doubleSided": True}],
        "meshes": [
            {"name": "ground", "primitives": [{"attributes": {"POSITION": ground}, "indices": indices, "material": 0}]},
            {"name": "tri", "primitives": [{"attributes": {"POSITION": tri}, "material": 0}]},
        ],
        "nodes": [{"mesh": 0}, {"mesh": 1, "translation": [1.3, 0, 0]}],
        "scenes": [{"nodes": [0, 1]}],
        "animations": [{"name": "slide", "samplers": [{"input": times, "output": keys}],
                        "channels": [{"sampler": 0, "target": {"node": 1, "path": "translation"}}]}],
    }
    with open(path, "w") as f:
        json.dump(doc, f)


def warm(dray):
    """--warm: the static domains of 12 frames in one process."""
    out = tempfile.mkdtemp(prefix="dray-frames-warm-")
    write_still_ground(os.path.join(out, "still.gltf"))
    wall = timed(
        [dray, "render", f"{out}/still.gltf", "--width", "128", "--height", "96", "--spp", "4",
         "--look-from", "0,1.5,4", "--look-at", "0,0.4,0", "--sun", "30,60", "--animation",
         "slide", "--frames", "0..11", "--fps", "12", "--workers", "1", "--domains", "8",
         "-q", "--stats", f"{out}/s.json", "--output", f"{out}/f.png"]
    )
    stats = [json.load(open(f"{out}/s.{f:04}.json")) for f in range(12)]
    loads = sum(s["domain_loads"] for s in stats)
    warm_domains = sum(s["domains_warm"] for s in stats)
    seconds = sum(s["domain_load_seconds"] for s in stats)
    print(f"12 frames, 51,202 triangles, 8 kd domains, one process: {loads} domain loads, "
          f"{warm_domains} warm; load seconds {seconds:.2f}; wall {wall:.2f} s")
    shutil.rmtree(out)


def timed(cmd, **kw):
    t0 = time.monotonic()
    subprocess.run(cmd, check=True, **kw)
    return time.monotonic() - t0


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", type=int, default=17400)
    ap.add_argument("--warm", action="store_true", help="the static domains of 12 frames")
    a = ap.parse_args()
    dray = os.environ.get("DRAY_BIN", "target/release/dray")
    if a.warm:
        return warm(dray)
    out = tempfile.mkdtemp(prefix="dray-frames-")
    write_sliding(os.path.join(out, "slide.gltf"))
    scene = "grid:slide.gltf:4x1x4"

    one = timed(
        [dray, "render", f"grid:{out}/slide.gltf:4x1x4", *FLAGS, *FRAMES, "--workers", "0", "-q",
         "--output", f"{out}/one.##.png"]
    )
    # Registrations are logged at info: the group is submitted once both workers are in
    # (else the coordinator would render it itself).
    log_path = os.path.join(out, "cluster.log")
    log = open(log_path, "w")
    cluster = subprocess.Popen(
        [dray, "cluster", "--workers", "2", "--base-port", str(a.port), "--scene-root", out],
        stdout=subprocess.DEVNULL, stderr=log, text=True,
        env={**os.environ, "DRAY_LOG": "warn,dray_coordinator::membership=info", "NO_COLOR": "1"},
    )
    try:
        deadline = time.monotonic() + 120
        while open(log_path).read().count("worker registered") < 2:
            if time.monotonic() > deadline or cluster.poll() is not None:
                sys.exit("the cluster's workers did not register: " + open(log_path).read())
            time.sleep(0.1)
        group = timed(
            [dray, "submit", scene, "--coordinator", f"127.0.0.1:{a.port}", *FLAGS, *FRAMES,
             "--output", f"{out}/group.##.png"],
            stderr=subprocess.DEVNULL,
        )
    finally:
        cluster.terminate()
        cluster.wait(timeout=30)
    same = all(
        open(f"{out}/one.{f:02}.png", "rb").read() == open(f"{out}/group.{f:02}.png", "rb").read()
        for f in range(N)
    )
    print(f"{N} frames, {scene}: one process {one:.2f} s, 2-worker cluster {group:.2f} s "
          f"(ratio {group / one:.2f}); same bits: {same}")
    if not same:
        sys.exit(f"the frames differ; both sets are kept in {out}")
    shutil.rmtree(out)


if __name__ == "__main__":
    main()

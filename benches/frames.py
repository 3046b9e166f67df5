#!/usr/bin/env python3
"""A job group of frames (issue 42): 24 frames of a generated animated glTF (a ground
quad and a triangle sliding along +X over one second, as cli/tests/frames.rs builds it),
replicated 4x1x4 with `grid:` so every copy slides, rendered

  - in one process: `dray render --frames 0..23 --fps 24 --workers 0`, and
  - as a job group on a 2-worker `dray cluster`: `dray submit --frames 0..23 --fps 24`,

printing each wall time (the cluster's from `dray submit` to its last frame, the cluster
already up) and whether every frame's PNG is byte-identical between the two.

Usage: DRAY_BIN=target/release/dray python3 benches/frames.py [--port 17400]
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


def timed(cmd, **kw):
    t0 = time.monotonic()
    subprocess.run(cmd, check=True, **kw)
    return time.monotonic() - t0


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", type=int, default=17400)
    a = ap.parse_args()
    dray = os.environ.get("DRAY_BIN", "target/release/dray")
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

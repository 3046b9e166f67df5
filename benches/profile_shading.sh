#!/usr/bin/env bash
# Where the instructions of a path-traced render go, by what the code does: BVH closest hit
# and any-hit (shadow rays), light sampling, BSDF, per-hit data (Surface: mesh positions,
# normals, uvs), camera rays, film, sampler, the worker's queues. Counted by valgrind's callgrind,
# so machine load does not move the numbers (wall time on a shared machine would).
#
# Scene: issue 41's kind, `benches/vs_mitsuba.py --case ground` (the Stanford bunny on a
# ground plane 40 bounding-sphere radii wide, a sun, a constant environment, Lambert 0.8,
# path tracing to depth 64), written the way that script writes it (same triangles, camera,
# light and material: its camera_frame and write_gltf), small enough for callgrind.
#
# Usage: benches/profile_shading.sh
#   env: DRAY_BIN (default: build and use target/release/dray), DRAY_SCENES (default
#        ../shared/scenes), RES (image RES x RES, default 64), SPP and SPP_LO (the two
#        sample counts profiled, default 8 and 2), DEPTH (default 64), OUT (default
#        benches/out/profile_shading), TAG (name of this run's files in OUT, default
#        "dray": profile two binaries with two TAGs), REUSE (1: reuse the callgrind
#        outputs in OUT).
# Prints a markdown table: instructions per category of the samples between SPP_LO and SPP
# (the difference of the two runs, so set-up cancels out), share, and per ray traced.
# `callgrind_annotate` tables of each run are kept beside it (.self.txt: self cost by
# source file and function, inlined code under the file it came from; .incl.txt:
# inclusive cost by function). Notes: docs/history/2026-11-30-shading-path.md.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
BUNNY="${DRAY_SCENES:-../shared/scenes}/stanford_bunny/bun_zipper.ply"
[ -f "$BUNNY" ] || { echo "no $BUNNY: set DRAY_SCENES to the shared scenes folder" >&2; exit 1; }
RES="${RES:-64}" SPP="${SPP:-8}" SPP_LO="${SPP_LO:-2}" DEPTH="${DEPTH:-64}"
OUT="${OUT:-benches/out/profile_shading}" TAG="${TAG:-dray}"
mkdir -p "$OUT"
if [ -z "${DRAY_BIN:-}" ]; then
    cargo build --release -p dray
    DRAY_BIN=target/release/dray
fi

# 1. The scene, as benches/vs_mitsuba.py --case ground writes it (without numpy).
if [ ! -s "$OUT/scene.gltf" ]; then
    "$DRAY_BIN" bench-rays "$BUNNY" --kind primary --res 1 --repeat 1 --dump-mesh "$OUT/mesh.tris.f32" >/dev/null
    python3 - "$OUT" "$RES" <<'EOF'
import math, struct, sys
from pathlib import Path
sys.path.insert(0, "benches")
import vs_mitsuba as vm

out, res = Path(sys.argv[1]), int(sys.argv[2])
raw = (out / "mesh.tris.f32").read_bytes()
f = struct.unpack(f"<{len(raw) // 4}f", raw)
tris = [tuple(tuple(f[i + 3 * k:i + 3 * k + 3]) for k in range(3)) for i in range(0, len(f), 9)]
pts = [p for t in tris for p in t]
lo = [min(p[a] for p in pts) for a in range(3)]
hi = [max(p[a] for p in pts) for a in range(3)]
# vs_mitsuba.ground_plane, in float32 as its numpy array holds it.
f32 = lambda x: struct.unpack("<f", struct.pack("<f", x))[0]  # noqa: E731
cx, cz = (lo[0] + hi[0]) / 2, (lo[2] + hi[2]) / 2
h = vm.GROUND_RADII * 0.5 * math.dist(lo, hi) / 2
y = lo[1]
a, b, c, d = [tuple(map(f32, v)) for v in ((cx - h, y, cz - h), (cx + h, y, cz - h), (cx + h, y, cz + h),
                                            (cx - h, y, cz + h))]
tris += [(a, d, c), (a, c, b)]
# vs_mitsuba.write_meshes' weld: unique vertices in sorted order, triangles in order.
verts = sorted(set(p for t in tris for p in t))
index = {v: i for i, v in enumerate(verts)}
idx = [index[p] for t in tris for p in t]
pos = b"".join(struct.pack("<3f", *v) for v in verts)
ind = struct.pack(f"<{len(idx)}I", *idx)
(out / "mesh.bin").write_bytes(pos + ind)
mesh = {"vertices": len(verts), "triangles": len(tris), "pos_bytes": len(pos), "idx_bytes": len(ind),
        "min": [min(v[a] for v in verts) for a in range(3)], "max": [max(v[a] for v in verts) for a in range(3)]}
vm.write_gltf(mesh, vm.camera_frame(lo, hi), out, res, res)
print(f"scene: {len(tris)} triangles, {len(verts)} vertices -> {out / 'scene.gltf'}", file=sys.stderr)
EOF
    rm -f "$OUT/mesh.tris.f32"
fi

# 2. The render under callgrind, one thread, at two sample counts: everything but the
# samples (scene load, BVH build, partition, actors' start-up, image output) is the same in
# both, so the difference is what SPP - SPP_LO samples per pixel cost, by function.
for spp in "$SPP_LO" "$SPP"; do
    cg="$OUT/callgrind.$TAG.spp$spp"
    if [ -z "${REUSE:-}" ] || [ ! -s "$cg" ]; then
        valgrind --tool=callgrind --callgrind-out-file="$cg" "$DRAY_BIN" render "$OUT/scene.gltf" \
            --width "$RES" --height "$RES" --spp "$spp" --integrator path --max-depth "$DEPTH" --seed 1 \
            --env 0.25,0.25,0.25 --threads 1 --output "$OUT/$TAG.spp$spp.png" \
            --stats "$OUT/$TAG.spp$spp.stats.json" -q 2>"$cg.log"
    fi
    callgrind_annotate --threshold=100 --auto=no "$cg" >"$cg.self.txt"
    callgrind_annotate --threshold=100 --auto=no --inclusive=yes "$cg" >"$cg.incl.txt"
done

# 3. The table.
python3 - "$OUT/callgrind.$TAG.spp$SPP_LO" "$OUT/callgrind.$TAG.spp$SPP" "$OUT/$TAG" <<'EOF'
import json, re, sys
from collections import defaultdict

lo_cg, hi_cg, tag = sys.argv[1], sys.argv[2], sys.argv[3]
line_re = re.compile(r"^\s*([\d,]+)\s+\([ \d.]+%\)\s+(\S.*)$")


def stats(cg):
    s = json.load(open(tag + "." + cg.rsplit(".", 1)[1] + ".stats.json"))
    return s["rays"], s["rays_total"]


def table(path):
    """(program total, {(source file, function): instructions})."""
    total, rows, started = None, defaultdict(int), False
    for line in open(path):
        if "PROGRAM TOTALS" in line:
            total = int(line.split()[0].replace(",", ""))
        elif "file:function" in line:
            started = True
        elif started and (m := line_re.match(line)):
            src, _, func = m.group(2).partition(":")
            rows[(src, func.split(" [")[0])] += int(m.group(1).replace(",", ""))
    return total, rows


def inclusive(rows, func_rx):
    """The largest inclusive cost of a function matching func_rx (its outermost call)."""
    return max((ir for (_, fn), ir in rows.items() if re.search(func_rx, fn)), default=0)


(lo_total, lo_self), (hi_total, hi_self) = table(lo_cg + ".self.txt"), table(hi_cg + ".self.txt")
(_, lo_incl), (_, hi_incl) = table(lo_cg + ".incl.txt"), table(hi_cg + ".incl.txt")
(lo_rays, lo_n), (hi_rays, hi_n) = stats(lo_cg), stats(hi_cg)
n = hi_n - lo_n
# The two queries are never inlined (`#[inline(never)]` on Accel::closest and occluded):
# their inclusive cost is the traversal's (accept callback included).
QUERIES = [("BVH closest hit (Accel::closest: camera and bounce rays)", r"dray_core::bvh::Accel::closest$"),
           ("BVH any-hit (Accel::occluded: shadow rays)", r"dray_core::bvh::Accel::occluded$")]
# Functions inside those two: their self cost is already counted in them.
IN_QUERIES = r"dray_core::bvh::(Accel::(closest|occluded)|walk_avx|traverse::|leaf4::|node_test::)|" \
             r"Integrator::(intersect|occluded)::\{\{closure|FnMut<A> for &F>::call_mut"
# (category, regex on the source file of the costed line, regex on the function it was
# inlined into); first match wins; the file wins over the function unless it is library
# code (glam, std), which counts for the function it was inlined into.
CATEGORIES = [
    ("light sampling (light_sampler.rs, light.rs, sun.rs, direct_light)", r"core/src/(light[^/]*|sun|env_map)\.rs",
     r"dray_core::(light|sun|env_map)|Integrator::(direct_light|distant_sample|light_out|shadow_ray)"),
    ("BSDF set-up, evaluation and sampling (bsdf/)", r"core/src/bsdf/", r"dray_core::bsdf::"),
    ("per-hit data: Surface (positions, normals, uvs), material values", r"core/src/(surface|material|texture)\.rs",
     r"dray_core::(surface|material|texture)::"),
    ("sampler (sampling.rs: hashes, warps)", r"core/src/sampling\.rs", r"dray_core::sampling::"),
    ("camera rays (camera.rs, camera_ray*)", r"core/src/camera\.rs", r"dray_core::camera::|Integrator::camera_ray"),
    ("film (fixed-point sums, clamp)", r"core/src/(film|clamp)\.rs", r"dray_core::(film|clamp)::"),
    ("integrator: shade_hit, path_step, spawn, ray offsets", r"core/src/(integrator|intersect|trace)\.rs",
     r"dray_core::(integrator|intersect|trace)::"),
    ("worker tracer: ray queues, batches, outbox (worker/src/tracer)", r"worker/src/", r"dray_worker::"),
    ("actors' messages: protobuf, gRPC, tokio", r"prost|tonic|h2-|hyper|tokio|bytes-|net/src|proto/",
     r"prost|tonic|h2::|hyper|tokio|bytes::|dray_net|dray_proto|dray_coordinator"),
    ("allocation, memcpy (libc)", r"malloc|memmove|memcpy|memset|libc\.so", r"malloc|free|memcpy|memmove|memset|alloc::"),
]
LIBRARY = r"glam-[^/]+/|/rustc/|library/(core|std|alloc)|stdarch|\?\?\?"
sums = defaultdict(int)
for key in set(lo_self) | set(hi_self):
    ir = hi_self.get(key, 0) - lo_self.get(key, 0)
    src, func = key
    if re.search(IN_QUERIES, func):
        continue
    lib = re.search(LIBRARY, src)
    cat = next((c for c, file_rx, _ in CATEGORIES if not lib and re.search(file_rx, src)), None)
    if cat is None:
        cat = next((c for c, _, func_rx in CATEGORIES if re.search(func_rx, func)), None)
    sums[cat or "other"] += ir
rows = [(name, inclusive(hi_incl, rx) - inclusive(lo_incl, rx)) for name, rx in QUERIES]
rows += sorted(sums.items(), key=lambda kv: -kv[1])
render = hi_total - lo_total
print(f"{hi_cg} minus {lo_cg}: the samples in between")
print(f"rays traced: {n:,} ({', '.join(f'{k} {hi_rays[k] - lo_rays.get(k, 0):,}' for k in hi_rays if hi_rays[k])})")
print()
print("| category | instructions | share | per ray traced |")
print("|---|---:|---:|---:|")
for name, ir in rows:
    print(f"| {name} | {ir:,} | {100 * ir / render:.1f}% | {ir / max(n, 1):,.0f} |")
print(f"| **the samples' whole cost** | {render:,} | 100% | {render / max(n, 1):,.0f} |")
print(f"| (the whole process at the lower count, set-up included) | {lo_total:,} | | |")
EOF

#!/usr/bin/env python3
"""Write the seed corpora of dray's fuzz targets into fuzz/corpus/<target>/.

Every seed is made here from scratch (a unit cube, a quad, a few rays), so nothing from
shared/scenes is copied into the repository. The scene-package seeds are packages that
`dray partition` writes from those tiny scenes,
framed the way fuzz/src/lib.rs's `Sections` reads them. Run from anywhere:

    python3 fuzz/seeds.py [--dray target/release/dray]

It replaces the files it writes (names are fixed) and leaves other files alone. The
output is deterministic except for the package seeds, which depend on `dray partition`.
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
import zlib

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
CORPUS = os.path.join(HERE, "corpus")

# A unit cube: 8 corners, 12 triangles (outward winding).
CUBE_V = [
    (0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0),
    (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1),
]
CUBE_QUADS = [
    (0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4),
    (2, 3, 7, 6), (1, 2, 6, 5), (0, 4, 7, 3),
]
CUBE_T = [t for q in CUBE_QUADS for t in ((q[0], q[1], q[2]), (q[0], q[2], q[3]))]


def put(target, name, data):
    d = os.path.join(CORPUS, target)
    os.makedirs(d, exist_ok=True)
    if isinstance(data, str):
        data = data.encode()
    with open(os.path.join(d, name), "wb") as f:
        f.write(data)


def png_2x2():
    def chunk(t, d):
        return struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d) & 0xFFFFFFFF)
    raw = b"\x00" + bytes([255, 0, 0, 255, 0, 255, 0, 255]) + b"\x00" + bytes([0, 0, 255, 255, 255, 255, 255, 128])
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 2, 2, 8, 6, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))


# ---------------------------------------------------------------- PLY

def ply_seeds():
    v = CUBE_V
    # ASCII, positions only, quads (fan-triangulated by the loader).
    s = "ply\nformat ascii 1.0\ncomment unit cube\nelement vertex 8\nproperty float x\nproperty float y\nproperty float z\n"
    s += "element face 6\nproperty list uchar int vertex_indices\nend_header\n"
    s += "".join(f"{x} {y} {z}\n" for x, y, z in v)
    s += "".join(f"4 {a} {b} {c} {d}\n" for a, b, c, d in CUBE_QUADS)
    put("ply", "cube-ascii.ply", s)

    # ASCII with normals, uvs, an extra property and an extra element, triangles.
    s = ("ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
         "property float nx\nproperty float ny\nproperty float nz\nproperty float s\nproperty float t\n"
         "property uchar red\nelement face 2\nproperty list uchar uint vertex_index\n"
         "element edge 1\nproperty int vertex1\nproperty int vertex2\nend_header\n"
         "0 0 0 0 0 1 0 0 255\n1 0 0 0 0 1 1 0 0\n1 1 0 0 0 1 1 1 10\n0 1 0 0 0 1 0 1 20\n"
         "3 0 1 2\n3 0 2 3\n0 1\n")
    put("ply", "quad-attrs-ascii.ply", s)

    # Binary little endian: float xyz, double normals, texture_u/v, uchar/int list.
    hdr = ("ply\nformat binary_little_endian 1.0\nelement vertex 8\nproperty float x\nproperty float y\n"
           "property float z\nproperty double nx\nproperty double ny\nproperty double nz\n"
           "property float texture_u\nproperty float texture_v\n"
           "element face 12\nproperty list uchar int vertex_indices\nend_header\n").encode()
    body = b""
    for x, y, z in v:
        n = (x - 0.5, y - 0.5, z - 0.5)
        body += struct.pack("<3f3d2f", x, y, z, *n, x, y)
    for t in CUBE_T:
        body += struct.pack("<B3i", 3, *t)
    put("ply", "cube-binary-le.ply", hdr + body)

    # Binary big endian, short/ushort positions, faces before vertices.
    hdr = ("ply\nformat binary_big_endian 1.0\nelement face 2\nproperty list uchar ushort vertex_indices\n"
           "element vertex 4\nproperty short x\nproperty short y\nproperty short z\nend_header\n").encode()
    body = struct.pack(">B3H", 3, 0, 1, 2) + struct.pack(">B3H", 3, 0, 2, 3)
    for p in [(0, 0, 0), (2, 0, 0), (2, 2, 0), (0, 2, 0)]:
        body += struct.pack(">3h", *p)
    put("ply", "quad-faces-first-be.ply", hdr + body)


# ---------------------------------------------------------------- OBJ

def cube_obj(mtl=True, texture=True):
    s = "# unit cube\n"
    if mtl:
        s += "mtllib scene.mtl\n"
    s += "o cube\n"
    s += "".join(f"v {x} {y} {z}\n" for x, y, z in CUBE_V)
    s += "vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\n"
    s += "vn 0 0 -1\nvn 0 0 1\nvn 0 -1 0\nvn 0 1 0\nvn 1 0 0\nvn -1 0 0\n"
    for i, (a, b, c, d) in enumerate(CUBE_QUADS):
        if i == 0 and mtl:
            s += "usemtl red\n"
        if i == 2 and mtl:
            s += "g lid\nusemtl glass\n"
        if i == 4 and mtl:
            s += "usemtl lamp\n"
        s += f"f {a+1}/1/{i+1} {b+1}/2/{i+1} {c+1}/3/{i+1} {d+1}/4/{i+1}\n"
    return s


MTL = ("newmtl red\nKd 0.8 0.1 0.1\nKs 0.5 0.5 0.5\nNs 50\nillum 2\n" + "map_Kd tex.png\n"
       "newmtl glass\nKd 1 1 1\nNi 1.5\nillum 7\nTf 0.9 1 0.9\nd 0.5\n"
       "newmtl lamp\nKe 4 4 4\nKd 0 0 0\nTr 0.25\nmap_Bump bump.png\n")


def obj_seeds():
    put("obj", "cube-plain.obj", cube_obj(mtl=False))
    put("obj", "cube-mtl.obj", cube_obj() + "\n#---mtl\n" + MTL)
    put("obj", "cube-mtl-png.obj", cube_obj().encode() + b"\n#---mtl\n" + MTL.encode() + b"\n#---png\n" + png_2x2())
    s = ("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv -1 0.5 0\nvt 0 0\nvt 1 1\n"
         "f 1 2 3 4 5\nf -1 -2 -3\nl 1 2\np 3\ns 1\nf 1/1 2/2 3/1\n")
    put("obj", "polygon-relative.obj", s)


# ---------------------------------------------------------------- glTF

def pad4(b, fill=b"\x00"):
    return b + fill * (-len(b) % 4)


def cube_buffer():
    pos = b"".join(struct.pack("<3f", *p) for p in CUBE_V)
    nrm = b"".join(struct.pack("<3f", x - 0.5, y - 0.5, z - 0.5) for x, y, z in CUBE_V)
    uv = b"".join(struct.pack("<2f", x, y) for x, y, z in CUBE_V)
    idx = pad4(b"".join(struct.pack("<3H", *t) for t in CUBE_T))
    return pos, nrm, uv, idx


def cube_gltf(uri, bin_len, extra=True):
    pos, nrm, uv, idx = cube_buffer()
    o_n, o_uv, o_i = len(pos), len(pos) + len(nrm), len(pos) + len(nrm) + len(uv)
    doc = {
        "asset": {"version": "2.0", "generator": "dray fuzz/seeds.py"},
        "scene": 0,
        "scenes": [{"nodes": [0, 2]}],
        "nodes": [
            {"mesh": 0, "translation": [0, 0, -3], "rotation": [0, 0.3826834, 0, 0.9238795],
             "scale": [1, 2, 1], "children": [1]},
            {"mesh": 0, "matrix": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 2, 0, 0, 1]},
            {"camera": 0, "translation": [0, 0, 4]},
        ],
        "meshes": [{"name": "cube", "primitives": [{
            "attributes": {"POSITION": 0, "NORMAL": 1, "TEXCOORD_0": 2},
            "indices": 3, "material": 0, "mode": 4}]}],
        "materials": [{"name": "m", "pbrMetallicRoughness": {
            "baseColorFactor": [1, 0.5, 0.5, 1], "baseColorTexture": {"index": 0},
            "metallicFactor": 0.1, "roughnessFactor": 0.7},
            "emissiveFactor": [0, 0, 0], "alphaMode": "MASK", "alphaCutoff": 0.4,
            "doubleSided": True}],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 8, "type": "VEC3",
             "min": [0, 0, 0], "max": [1, 1, 1]},
            {"bufferView": 1, "componentType": 5126, "count": 8, "type": "VEC3"},
            {"bufferView": 2, "componentType": 5126, "count": 8, "type": "VEC2"},
            {"bufferView": 3, "componentType": 5123, "count": 36, "type": "SCALAR"},
        ],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": len(pos)},
            {"buffer": 0, "byteOffset": o_n, "byteLength": len(nrm)},
            {"buffer": 0, "byteOffset": o_uv, "byteLength": len(uv)},
            {"buffer": 0, "byteOffset": o_i, "byteLength": 72},
        ],
        "buffers": [{"byteLength": bin_len}],
        "cameras": [{"type": "perspective", "perspective": {"yfov": 0.8, "znear": 0.1, "aspectRatio": 1.5}}],
        "textures": [{"source": 0, "sampler": 0}],
        "samplers": [{"magFilter": 9728, "wrapS": 33648, "wrapT": 33071}],
        "images": [{"uri": "tex.png"}],
    }
    if uri is not None:
        doc["buffers"][0]["uri"] = uri
    if extra:
        doc["extensionsUsed"] = ["KHR_lights_punctual", "KHR_materials_emissive_strength"]
        doc["extensions"] = {"KHR_lights_punctual": {"lights": [
            {"type": "point", "color": [1, 1, 1], "intensity": 5},
            {"type": "spot", "intensity": 2, "spot": {"innerConeAngle": 0.2, "outerConeAngle": 0.6}},
        ]}}
        doc["nodes"].append({"extensions": {"KHR_lights_punctual": {"light": 0}}, "translation": [0, 3, 0]})
        doc["scenes"][0]["nodes"].append(3)
    return doc, pos + nrm + uv + idx


def gltf_seeds():
    doc, blob = cube_gltf(None, 0)
    data_uri = "data:application/octet-stream;base64," + base64.b64encode(blob).decode()
    doc["buffers"][0] = {"byteLength": len(blob), "uri": data_uri}
    put("gltf", "cube-data-uri.gltf", json.dumps(doc, separators=(",", ":")))

    doc, blob = cube_gltf("buf.bin", 0, extra=False)
    doc["buffers"][0]["byteLength"] = len(blob)
    put("gltf", "cube-external.gltf", json.dumps(doc, separators=(",", ":")).encode() + b"\n#---bin\n" + blob)

    # GLB: header, JSON chunk (space padded), BIN chunk (zero padded); the image comes
    # from the binary chunk through a buffer view.
    doc, blob = cube_gltf(None, 0, extra=False)
    png = png_2x2()
    img_off = len(blob)
    blob = pad4(blob + png)
    doc["buffers"][0]["byteLength"] = len(blob)
    doc["bufferViews"].append({"buffer": 0, "byteOffset": img_off, "byteLength": len(png)})
    doc["images"] = [{"bufferView": 4, "mimeType": "image/png"}]
    js = pad4(json.dumps(doc, separators=(",", ":")).encode(), b" ")
    glb = struct.pack("<I", len(js)) + b"JSON" + js + struct.pack("<I", len(blob)) + b"BIN\x00" + blob
    glb = b"glTF" + struct.pack("<II", 2, 12 + len(glb)) + glb
    put("gltf", "cube.glb", glb)

    # A triangle strip with a sparse accessor, u8 indices and no material.
    pos = struct.pack("<12f", 0, 0, 0, 1, 0, 0, 0, 1, 0, 1, 1, 0)
    idx = bytes([0, 1, 2, 3])
    sparse_idx = bytes([3, 0, 0, 0])
    sparse_val = struct.pack("<3f", 1, 1, 0.5)
    blob = pos + idx + sparse_idx + sparse_val
    doc = {
        "asset": {"version": "2.0"},
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1, "mode": 5}]}],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3",
             "min": [0, 0, 0], "max": [1, 1, 0.5],
             "sparse": {"count": 1, "indices": {"bufferView": 2, "componentType": 5121},
                        "values": {"bufferView": 3}}},
            {"bufferView": 1, "componentType": 5121, "count": 4, "type": "SCALAR"},
        ],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": 48},
            {"buffer": 0, "byteOffset": 48, "byteLength": 4},
            {"buffer": 0, "byteOffset": 52, "byteLength": 4},
            {"buffer": 0, "byteOffset": 56, "byteLength": 12},
        ],
        "buffers": [{"byteLength": len(blob),
                     "uri": "data:application/octet-stream;base64," + base64.b64encode(blob).decode()}],
    }
    put("gltf", "strip-sparse.gltf", json.dumps(doc, separators=(",", ":")))


# ---------------------------------------------------------------- ray batches

RECORD = struct.Struct("<Q3f3ff3ffIIHBB")


def record(credit, o, d, tmax, w, pdf, pixel, sample, depth, kind, flags):
    return RECORD.pack(credit, *o, *d, tmax, *w, pdf, pixel, sample, depth, kind, flags)


def varint(n):
    out = b""
    while True:
        b = n & 0x7F
        n >>= 7
        if n:
            out += bytes([b | 0x80])
        else:
            return out + bytes([b])


def field_varint(no, v):
    return varint(no << 3) + varint(v)


def field_bytes(no, b):
    return varint(no << 3 | 2) + varint(len(b)) + b


def rays():
    inf = float("inf")
    return [
        record(1 << 40, (0, 1, 2), (0, 0, -1), inf, (1, 1, 1), 0, 640 * 12 + 3, 0, 0, 0, 0),
        record(12345, (0.5, -0.25, 3), (0.6, 0.8, 0), 17.5, (0.2, 0.3, 0.4), 0.75, 99, 3, 2, 4, 1),
        record(7, (1e-3, 1e3, -2), (-1, 0, 0), 1.0, (-0.0, 0, 5), 1.5, 0, 1, 1, 1, 2 | 1),
        record(0, (3, 3, 3), (0, -1, 0), -inf, (float("nan"), 0, 0), float("nan"), 2**32 - 1, 7, 65535, 5, 4),
    ]


def ray_seeds():
    r = rays()
    put("ray_batch", "records-one.bin", b"\x00" + r[0])
    put("ray_batch", "records-four.bin", b"\x00" + b"".join(r))
    put("ray_batch", "records-truncated.bin", b"\x00" + r[1][:40])
    # RayStreamRequest { batch: RayBatch { ... } }: records 1 and 2 are TICKETED.
    recs = b"".join(r[:3])
    tickets = [(1, (3 << 32) | 17), (2, (1 << 32) | 5), (2, (4 << 32) | 9)]
    batch = (field_bytes(1, b"job-7") + field_varint(2, 3) + field_varint(3, 2) + field_varint(4, 1)
             + field_varint(5, 3) + field_bytes(6, recs)
             + b"".join(field_bytes(7, field_varint(1, i) + field_varint(2, t)) for i, t in tickets)
             + field_varint(8, 0) + field_varint(9, 1))
    put("ray_batch", "stream-batch.bin", b"\x01" + field_bytes(2, batch))
    batch1 = field_bytes(1, b"j") + field_varint(4, 2) + field_varint(5, 1) + field_bytes(6, r[0])
    put("ray_batch", "stream-batch-plain.bin", b"\x01" + field_bytes(2, batch1))
    open_msg = field_varint(1, 4) + field_varint(2, 1)
    put("ray_batch", "stream-open.bin", b"\x01" + field_bytes(1, open_msg))
    # CacheRequest { lookups: CacheLookups { ... } } with packed walls and options.
    recs = r[0] + r[1]
    lookups = (field_bytes(1, b"job-7") + field_varint(2, 1) + field_varint(3, 9) + field_varint(4, 2)
               + field_bytes(5, recs) + field_bytes(6, varint(0) + varint(3))
               + field_bytes(7, varint(1) + varint(7)))
    put("ray_batch", "cache-lookups.bin", b"\x02" + field_bytes(1, lookups))


# ---------------------------------------------------------------- scene packages

def section(i, b):
    return bytes([i]) + struct.pack("<I", len(b)) + b


def frame_package(pkg, body_mode):
    with open(os.path.join(pkg, "manifest.json"), "rb") as f:
        text = f.read()
    files = []
    for name in sorted(os.listdir(pkg)):
        with open(os.path.join(pkg, name), "rb") as f:
            b = f.read()
        if name == "textures.bin":
            files.append((2, b))
        elif name == "emitters.bin":
            files.append((3, b))
        elif name.startswith("domain-") and name.endswith(".bin"):
            files.append((4 + int(name[7:12]), b))
    if body_mode:
        # The body exactly as written: the text between `"body": ` and the envelope's
        # closing brace.
        start = text.index(b'"body": ') + len(b'"body": ')
        end = text.rstrip().rindex(b"}")
        out = b"\x01" + section(1, text[start:end].strip())
    else:
        out = b"\x00" + section(0, text)
    for i, b in files:
        out += section(i, b)
    return out


def package_seeds(dray):
    tmp = tempfile.mkdtemp(prefix="dray-seeds-")
    try:
        scenes = os.path.join(tmp, "scenes")
        os.makedirs(scenes)
        with open(os.path.join(scenes, "cube.ply"), "wb") as f:
            f.write(open(os.path.join(CORPUS, "ply", "cube-ascii.ply"), "rb").read())
        with open(os.path.join(scenes, "cube.obj"), "w") as f:
            f.write(cube_obj())
        with open(os.path.join(scenes, "scene.mtl"), "w") as f:
            f.write(MTL.replace("map_Bump bump.png\n", ""))
        with open(os.path.join(scenes, "tex.png"), "wb") as f:
            f.write(png_2x2())
        # (name, scene, layout, also a raw-manifest seed): the textured package (with
        # textures.bin and emitters.bin) only as a body seed, to keep the corpus small.
        jobs = [
            ("cube-kd2", os.path.join(scenes, "cube.ply"), ["--domains", "2"], True),
            ("cube-textured-grid2", os.path.join(scenes, "cube.obj"), ["--grid", "2x1x1"], False),
        ]
        for name, scene, layout, raw in jobs:
            out = os.path.join(tmp, name)
            subprocess.run([dray, "partition", scene, *layout, "--out", out],
                           check=True, stdout=subprocess.DEVNULL)
            if raw:
                put("scene_package", f"{name}.bin", frame_package(out, body_mode=False))
            put("scene_package", f"{name}-body.bin", frame_package(out, body_mode=True))
    finally:
        shutil.rmtree(tmp)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dray", default=os.path.join(ROOT, "target", "release", "dray"),
                    help="the dray binary for the scene-package seeds (default: %(default)s)")
    args = ap.parse_args()
    ply_seeds()
    obj_seeds()
    gltf_seeds()
    ray_seeds()
    if os.access(args.dray, os.X_OK):
        package_seeds(args.dray)
    else:
        print(f"seeds.py: {args.dray} not found; scene_package seeds not written", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

#!/usr/bin/env python3
"""A procedural "studio" environment map, written as a Radiance .hdr with no dependency:
a sky gradient above the horizon, a dim floor below, a warm key soft-box and a cool rim
light. It lights the README's picture (depth of field and an environment map) and is a
map anyone can make without downloading an HDRI.

Equirectangular, +Y up, the image's centre looking along -Z (dray's convention,
docs/lights.md). Usage: python3 benches/studio_env.py OUT.hdr [--width 1024]
"""

from __future__ import annotations

import argparse
import math


def radiance(az: float, el: float) -> tuple[float, float, float]:
    """Linear RGB radiance in the direction at azimuth `az` and elevation `el` (radians)."""

    def inside(c_az: float, c_el: float, w: float, h: float) -> bool:
        d = math.atan2(math.sin(az - math.radians(c_az)), math.cos(az - math.radians(c_az)))
        return abs(d) < math.radians(w) / 2 and abs(el - math.radians(c_el)) < math.radians(h) / 2

    if inside(-50, 35, 40, 25):
        return (30.0, 26.0, 20.0)  # warm key
    if inside(140, 20, 20, 40):
        return (6.0, 9.0, 14.0)  # cool rim
    up = math.sin(el)
    if up > 0:
        return (0.15 + 0.35 * up, 0.15 + 0.5 * up, 0.15 + 0.8 * up)
    return (0.08, 0.07, 0.06)


def rgbe(r: float, g: float, b: float) -> bytes:
    m = max(r, g, b)
    if m < 1e-32:
        return b"\0\0\0\0"
    mant, exp = math.frexp(m)
    scale = mant * 256.0 / m
    return bytes((int(r * scale), int(g * scale), int(b * scale), exp + 128))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out")
    ap.add_argument("--width", type=int, default=1024)
    a = ap.parse_args()
    w, h = a.width, a.width // 2
    with open(a.out, "wb") as f:
        f.write(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n")
        f.write(f"-Y {h} +X {w}\n".encode())
        for row in range(h):
            el = math.pi / 2 - (row + 0.5) / h * math.pi
            line = bytearray()
            for col in range(w):
                az = ((col + 0.5) / w - 0.5) * 2 * math.pi
                line += rgbe(*radiance(az, el))
            f.write(line)


if __name__ == "__main__":
    main()

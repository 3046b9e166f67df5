"""What `--clamp-indirect` costs and buys on the Cornell box with a glass sphere
(docs/noise.md, docs/benchmarks.md "Noise").

Renders a high-spp reference without the clamp, then at each of a few low sample counts
the image without a clamp and with each clamp X, and reports render time and NVIDIA FLIP
(PyPI flip-evaluator, LDR, on the PNGs, all with one fixed exposure and AgX) against the
reference. The clamp costs no time, so equal spp is equal time: the table says whether
the clamp's bias is worth its lower variance at that budget.

Run it with a Python that has flip-evaluator, numpy and pillow (benches/requirements.txt
pins them), e.g. `python3 -m venv /tmp/v && /tmp/v/bin/pip install flip-evaluator==1.7
numpy==2.4.6 pillow==13.0.0 && /tmp/v/bin/python benches/clamp_indirect.py`.
Options: --size, --ref-spp, --spp (comma list), --clamps (comma list), --threads.
Writes benches/out/clamp_indirect/results.json.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "benches" / "out" / "clamp_indirect"


def dray() -> str:
    return os.environ.get("DRAY_BIN", str(ROOT / "target" / "release" / "dray"))


def render(tag: str, size: int, spp: int, threads: int, extra: list[str]) -> dict:
    png, stats = OUT / f"{tag}.png", OUT / f"{tag}.json"
    cmd = [dray(), "render", "cornell:glass", "--width", str(size), "--height", str(size),
           "--spp", str(spp), "--workers", "0", "--threads", str(threads),
           "--exposure", "0", "--tonemap", "agx", "--output", str(png), "--stats", str(stats), "-q",
           *extra]
    t0 = time.monotonic()
    subprocess.run(cmd, check=True)
    wall = time.monotonic() - t0
    s = json.loads(stats.read_text())
    return {"png": png, "wall_s": wall, "render_s": s["render_time_s"],
            "clamped_indirect": s.get("clamped_indirect", 0)}


def main() -> None:
    import flip_evaluator as flip
    import numpy as np
    from PIL import Image

    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--ref-spp", type=int, default=2048)
    ap.add_argument("--spp", default="16,64")
    ap.add_argument("--clamps", default="0.25,1,4")
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)

    def ldr(png: Path):
        return np.asarray(Image.open(png).convert("RGB"), dtype=np.float32) / 255.0

    ref = render("ref", a.size, a.ref_spp, a.threads, [])
    ref_img = ldr(ref["png"])
    rows = []
    for spp in [int(s) for s in a.spp.split(",")]:
        for clamp in [None, *[float(c) for c in a.clamps.split(",")]]:
            tag = f"spp{spp}-" + ("free" if clamp is None else f"clamp{clamp:g}")
            extra = [] if clamp is None else ["--clamp-indirect", f"{clamp:g}"]
            r = render(tag, a.size, spp, a.threads, extra)
            _, mean, _ = flip.evaluate(ref_img, ldr(r["png"]), "LDR")
            row = {"spp": spp, "clamp": clamp, "render_s": r["render_s"],
                   "clamped_indirect": r["clamped_indirect"], "flip_mean": float(mean)}
            rows.append(row)
            print(json.dumps(row), file=sys.stderr, flush=True)
    result = {"command": " ".join(sys.argv), "size": a.size, "ref_spp": a.ref_spp,
              "ref_render_s": ref["render_s"], "threads": a.threads, "rows": rows}
    (OUT / "results.json").write_text(json.dumps(result, indent=2) + "\n")
    print("| spp | clamp | render s | clamped contributions | FLIP vs reference |")
    print("|---|---|---|---|---|")
    for r in rows:
        c = "none" if r["clamp"] is None else f"{r['clamp']:g}"
        print(f"| {r['spp']} | {c} | {r['render_s']:.2f} | {r['clamped_indirect']} | {r['flip_mean']:.4f} |")


if __name__ == "__main__":
    main()

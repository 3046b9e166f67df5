"""What `--noise-threshold` (adaptive sampling) costs and buys (docs/noise.md,
docs/benchmarks.md "Noise").

Renders a high-spp reference, then at each sample budget and threshold the adaptive image
and a uniform image of the same mean samples per pixel (equal samples, about equal
time), and reports render time, the samples saved and NVIDIA FLIP (PyPI flip-evaluator,
LDR, on the PNGs, all at one fixed exposure with AgX) against the reference. The
uniform image at the full budget is the baseline adaptive sampling is meant to approach
at lower cost.

Run it with a Python that has flip-evaluator, numpy and pillow (benches/requirements.txt
pins them), e.g. `python3 -m venv /tmp/v && /tmp/v/bin/pip install flip-evaluator==1.7
numpy==2.4.6 pillow==13.0.0 && /tmp/v/bin/python benches/adaptive.py`.
Options: --scene, --size, --ref-spp, --spp (comma list), --thresholds (comma list),
--threads, --extra (more `dray render` flags, one string). Writes
benches/out/adaptive/results.json.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "benches" / "out" / "adaptive"


def dray() -> str:
    return os.environ.get("DRAY_BIN", str(ROOT / "target" / "release" / "dray"))


def render(a, tag: str, spp: int, extra: list[str]) -> dict:
    png, stats = OUT / f"{tag}.png", OUT / f"{tag}.json"
    cmd = [dray(), "render", a.scene, "--width", str(a.size), "--height", str(a.size),
           "--spp", str(spp), "--workers", "0", "--threads", str(a.threads),
           "--exposure", "0", "--tonemap", "agx", "--output", str(png), "--stats", str(stats),
           "-q", *shlex.split(a.extra), *extra]
    t0 = time.monotonic()
    subprocess.run(cmd, check=True)
    wall = time.monotonic() - t0
    s = json.loads(stats.read_text())
    return {"png": png, "wall_s": wall, "render_s": s["render_time_s"],
            "tiles_stopped": s.get("tiles_stopped", 0),
            "samples_saved": s.get("samples_saved", 0)}


def main() -> None:
    import flip_evaluator as flip
    import numpy as np
    from PIL import Image

    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", default="cornell:glass")
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--ref-spp", type=int, default=1024)
    ap.add_argument("--spp", default="64,256")
    ap.add_argument("--thresholds", default="0.01,0.02,0.05")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--extra", default="")
    a = ap.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)

    def ldr(png: Path):
        return np.asarray(Image.open(png).convert("RGB"), dtype=np.float32) / 255.0

    ref = render(a, "ref", a.ref_spp, [])
    ref_img = ldr(ref["png"])

    def row_of(kind: str, spp: int, threshold, r: dict) -> dict:
        _, mean, _ = flip.evaluate(ref_img, ldr(r["png"]), "LDR")
        mean_spp = spp - r["samples_saved"] / (a.size * a.size)
        row = {"kind": kind, "spp": spp, "threshold": threshold, "mean_spp": mean_spp,
               "render_s": r["render_s"], "tiles_stopped": r["tiles_stopped"],
               "flip_mean": float(mean)}
        print(json.dumps(row), file=sys.stderr, flush=True)
        return row

    rows = []
    for spp in [int(s) for s in a.spp.split(",")]:
        rows.append(row_of("uniform", spp, None, render(a, f"u{spp}", spp, [])))
        for th in [float(t) for t in a.thresholds.split(",")]:
            ad = row_of("adaptive", spp, th, render(
                a, f"a{spp}-{th:g}", spp, ["--noise-threshold", f"{th:g}"]))
            rows.append(ad)
            # The uniform image of the same mean samples per pixel: about equal time.
            eq = max(1, round(ad["mean_spp"]))
            rows.append(row_of("uniform, equal samples", eq, th,
                               render(a, f"u{eq}-for-{spp}-{th:g}", eq, [])))
    result = {"command": " ".join(sys.argv), "scene": a.scene, "size": a.size,
              "ref_spp": a.ref_spp, "ref_render_s": ref["render_s"], "threads": a.threads,
              "extra": a.extra, "rows": rows}
    (OUT / "results.json").write_text(json.dumps(result, indent=2) + "\n")
    print("| kind | spp | threshold | mean spp | tiles stopped | render s | FLIP vs reference |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        t = "" if r["threshold"] is None else f"{r['threshold']:g}"
        print(f"| {r['kind']} | {r['spp']} | {t} | {r['mean_spp']:.1f} | {r['tiles_stopped']} "
              f"| {r['render_s']:.2f} | {r['flip_mean']:.4f} |")


if __name__ == "__main__":
    main()

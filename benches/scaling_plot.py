#!/usr/bin/env python3
"""Plot benches/scaling.sh's output as an SVG (no plotting library needed): speed-up
over one worker against workers, per case, beside the ideal line, and each case's
one-process time as a dashed level (speed-up = one worker's time / one process's).

    benches/scaling.sh | tee scaling.txt
    python3 benches/scaling_plot.py scaling.txt docs/scaling-curve.svg
"""

import sys

W, H, PAD = 420, 300, 48
COLOURS = {"fit": "#1f77b4", "big": "#d62728"}
NAMES = {"fit": "fits (replicated)", "big": "does not fit (dynamic)"}


def read(path):
    cases = {}
    for line in open(path):
        f = line.split()
        if len(f) < 3 or f[0] not in COLOURS:
            continue
        c = cases.setdefault(f[0], {"one": None, "n": {}})
        if f[1] == "one-process":
            c["one"] = float(f[2])
        else:
            c["n"][int(f[1])] = float(f[2])
    return cases


def main(src, dst):
    cases = read(src)
    nmax = max(max(c["n"]) for c in cases.values())
    ymax = max(
        max(max(c["n"][1] / t for t in c["n"].values()), c["n"][1] / c["one"])
        for c in cases.values()
    )
    ymax = max(ymax, nmax) * 1.1

    def x(n):
        return PAD + (n - 1) / max(nmax - 1, 1) * (W - 2 * PAD)

    def y(s):
        return H - PAD - s / ymax * (H - 2 * PAD)

    out = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{W}" height="{H}" font-family="sans-serif" font-size="11">',
        f'<rect width="{W}" height="{H}" fill="white"/>',
        f'<line x1="{PAD}" y1="{H - PAD}" x2="{W - PAD}" y2="{H - PAD}" stroke="black"/>',
        f'<line x1="{PAD}" y1="{PAD}" x2="{PAD}" y2="{H - PAD}" stroke="black"/>',
        f'<text x="{W / 2}" y="{H - 12}" text-anchor="middle">workers (--threads 1)</text>',
        f'<text x="14" y="{H / 2}" transform="rotate(-90 14 {H / 2})" text-anchor="middle">speed-up over one worker</text>',
        f'<line x1="{x(1)}" y1="{y(1)}" x2="{x(nmax)}" y2="{y(nmax)}" stroke="#999" stroke-dasharray="2,3"/>',
        f'<text x="{x(nmax) - 4}" y="{y(nmax) - 4}" text-anchor="end" fill="#999">ideal</text>',
    ]
    for n in range(1, nmax + 1):
        out.append(f'<text x="{x(n)}" y="{H - PAD + 14}" text-anchor="middle">{n}</text>')
    for k in range(0, int(ymax) + 1):
        out.append(f'<text x="{PAD - 6}" y="{y(k) + 4}" text-anchor="end">{k}</text>')
    for i, (name, c) in enumerate(sorted(cases.items(), key=lambda kv: kv[0] != "fit")):
        col = COLOURS[name]
        pts = " ".join(f"{x(n)},{y(c['n'][1] / t)}" for n, t in sorted(c["n"].items()))
        out.append(f'<polyline points="{pts}" fill="none" stroke="{col}" stroke-width="2"/>')
        one = c["n"][1] / c["one"]
        out.append(
            f'<line x1="{x(1)}" y1="{y(one)}" x2="{x(nmax)}" y2="{y(one)}" stroke="{col}" stroke-dasharray="6,4"/>'
        )
        ly = PAD + 14 * i
        out.append(f'<text x="{PAD + 8}" y="{ly}" fill="{col}">{NAMES[name]}; dashed: one process</text>')
    out.append("</svg>")
    open(dst, "w").write("\n".join(out) + "\n")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])

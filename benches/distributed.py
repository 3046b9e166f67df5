#!/usr/bin/env python3
"""The distributed runtime on one machine (docs/benchmarks.md, "Distributed runtime").

Sections (--sections, default all, in this order):
- overhead:  the same scene and settings with `dray render` (embedded: coordinator and one
             worker actor in one process; same --domains, and --domains 1), with the
             reference renderer (`dray render --workers 0`, no actors, same --domains) and
             with `dray submit` to a `dray cluster --workers 4`;
             wall time of each process, the ratio of medians, the job's ray_bytes_sent /
             rays traced (read with GetJob over gRPC reflection), and whether the PNGs are
             the same bytes.
- stream:    `cargo bench -p dray-worker --bench ray_stream` (one ray stream on loopback,
             encode to decode); its time and throughput lines are parsed.
- big:       `dray partition BIG --domains 64 --out WORK/big64`, then that package is
             submitted to a fresh 4-worker cluster whose --scene-root is WORK. Peak memory
             (VmHWM) of the coordinator and each worker is read from /proc while the cluster
             lives; each worker's resident triangles come from its "job loaded" log line.
             The image must not be blank; with --big-embedded, `dray render BIG` at the same
             settings gives the reference and the PNGs are compared byte for byte.
- partition: `dray partition PART --domains 64 --out WORK/part100` (about 100M triangles);
             wall time and peak memory (wait4 rusage of the child), package size on disk;
             the package is deleted afterwards unless --keep-package.

Every command is recorded in WORK/results.json with its wall time and the "other load"
(cores used by other processes while it ran, see _bench_env.OtherLoad).

Standard library only. GetJob needs grpcio: the venv .ci/run builds into target/py-venv
from cli/tests/python/requirements.txt (created here the same way if it is missing).

Usage (from the repository root):
    benches/distributed.sh                               # builds dray, then runs this
    python3 benches/distributed.py --sections overhead --runs 3
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import shutil
import signal
import statistics
import struct
import subprocess
import sys
import threading
import time
import zlib
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _bench_env as env  # noqa: E402

PY_VENV = env.ROOT / "target" / "py-venv"
PY_REQS = env.ROOT / "cli" / "tests" / "python" / "requirements.txt"
SECTIONS = ["overhead", "stream", "big", "partition"]

GETJOB = r"""
import json, sys
sys.path.insert(0, sys.argv[1])
import grpc
from google.protobuf import descriptor_pool
from reflection_client import Service, as_json, reflection_database
ch = grpc.insecure_channel(sys.argv[2])
grpc.channel_ready_future(ch).result(timeout=30)
db, _, _ = reflection_database(ch)
svc = Service(ch, descriptor_pool.DescriptorPool(db), "dray.v1.RenderService")
print(json.dumps(as_json(svc.call("GetJob", {"jobId": sys.argv[3]}, timeout=30))))
"""


def parse_args() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sections", default=",".join(SECTIONS), help="comma-separated subset of " + ",".join(SECTIONS))
    ap.add_argument("--workers", type=int, default=4)
    ap.add_argument("--base-port", type=int, default=47400, help="cluster ports P..P+workers")
    ap.add_argument("--runs", type=int, default=3, help="interleaved rounds of the overhead section")
    ap.add_argument("--scene", default="stanford_bunny/bun_zipper.ply",
                    help="overhead: a file under $DRAY_SCENES (the cluster's scene root), replicated by --grid")
    ap.add_argument("--grid", default="2x2x2", help="overhead: grid:<scene>:XxYxZ replication ('' for none)")
    ap.add_argument("--width", type=int, default=512)
    ap.add_argument("--height", type=int, default=512)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--integrator", default="path")
    ap.add_argument("--domains", type=int, default=16)
    ap.add_argument("--layout", default="kd")
    ap.add_argument("--schedule", default="dynamic",
                    help="overhead: the schedule of the embedded and cluster runs (default dynamic, the "
                         "ray-exchange path this benchmark measures; auto, dray's default, replicates a "
                         "scene that fits and exchanges no rays)")
    ap.add_argument("--big", default="grid:iso:gyroid:200:3x3x3", help="big: the 10M+-triangle scene")
    ap.add_argument("--big-domains", type=int, default=64)
    ap.add_argument("--big-res", type=int, default=256, help="big: square image size")
    ap.add_argument("--big-spp", type=int, default=4)
    ap.add_argument("--big-embedded", action="store_true", help="big: also render it embedded and compare")
    ap.add_argument("--part", default="grid:iso:gyroid:259:4x4x5", help="partition: the ~100M-triangle scene")
    ap.add_argument("--part-domains", type=int, default=64)
    ap.add_argument("--keep-package", action="store_true")
    ap.add_argument("--work", type=Path, default=env.OUT / "distributed")
    return ap.parse_args()


# ---------------------------------------------------------------- helpers

def proc_mem(pid: int) -> dict:
    """VmHWM / VmRSS of a live process in MiB ({} once it is gone)."""
    out = {}
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            k, _, v = line.partition(":")
            if k in ("VmHWM", "VmRSS"):
                out[k] = int(v.split()[0]) / 1024
    except OSError:
        pass
    return out


def proc_cpu(pid: int) -> float:
    """user+sys CPU seconds of a live process (0 once it is gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return 0.0


def run_peak(cmd: list, log_to: Path | None = None) -> dict:
    """Run `cmd`; wall time, CPU time and peak RSS (wait4 rusage, exact) and other load."""
    load = env.OtherLoad()
    t0 = time.perf_counter()
    out = open(log_to, "w") if log_to else subprocess.DEVNULL
    p = subprocess.Popen([str(c) for c in cmd], stdout=subprocess.PIPE, stderr=out, text=True)
    stdout = p.stdout.read()
    _, status, ru = os.wait4(p.pid, 0)
    p.returncode = os.waitstatus_to_exitcode(status)
    wall = time.perf_counter() - t0
    if log_to:
        out.close()
    res = {"cmd": " ".join(map(str, cmd)), "wall_s": wall, "cpu_s": ru.ru_utime + ru.ru_stime,
           "peak_rss_mib": ru.ru_maxrss / 1024, "rc": p.returncode, "stdout": stdout,
           "other_load_cores": load.cores()}
    if p.returncode != 0:
        raise RuntimeError(f"command failed (exit {p.returncode}): {res['cmd']}")
    return res


def timed(cmd: list, **kw) -> dict:
    load = env.OtherLoad()
    r = env.run_timed(cmd, **kw)
    r["other_load_cores"] = load.cores()
    return r


def png_stats(path: Path) -> dict:
    """Decode an 8-bit, non-interlaced RGB/RGBA/grey PNG (what dray writes): mean value and the
    fraction of pixels that are not black, to tell a blank image."""
    data = path.read_bytes()
    pos, idat, w = 8, b"", 0
    while pos < len(data):
        n, kind = struct.unpack(">I4s", data[pos:pos + 8])
        body = data[pos + 8:pos + 8 + n]
        if kind == b"IHDR":
            w, h, depth, ctype, _, _, interlace = struct.unpack(">IIBBBBB", body)
            if depth != 8 or interlace:
                return {"error": f"unsupported PNG depth {depth} interlace {interlace}"}
            ch = {0: 1, 2: 3, 4: 2, 6: 4}[ctype]
        elif kind == b"IDAT":
            idat += body
        pos += 12 + n
    raw, stride = zlib.decompress(idat), w * ch
    prev, rows = bytearray(stride), []
    for y in range(h):
        f, line = raw[y * (stride + 1)], bytearray(raw[y * (stride + 1) + 1:(y + 1) * (stride + 1)])
        for i in range(stride):
            a = line[i - ch] if i >= ch else 0
            b, c = prev[i], (prev[i - ch] if i >= ch else 0)
            if f == 1:
                line[i] = (line[i] + a) & 255
            elif f == 2:
                line[i] = (line[i] + b) & 255
            elif f == 3:
                line[i] = (line[i] + (a + b) // 2) & 255
            elif f == 4:
                pa, pb, pc = abs(b - c), abs(a - c), abs(a + b - 2 * c)
                line[i] = (line[i] + (a if pa <= pb and pa <= pc else b if pb <= pc else c)) & 255
        rows.append(bytes(line))
        prev = line
    colour = min(ch, 3)
    lit = total = 0
    sums = 0
    for row in rows:
        for x in range(w):
            px = row[x * ch:x * ch + colour]
            s = sum(px)
            sums += s
            lit += s > 0
            total += 1
    return {"width": w, "height": h, "mean_8bit": sums / (total * colour), "lit_fraction": lit / total}


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()[:16]


def py_venv() -> Path:
    py = PY_VENV / "bin" / "python"
    if not py.exists():
        env.log(f"creating {PY_VENV} from {PY_REQS.relative_to(env.ROOT)}")
        subprocess.run([sys.executable, "-m", "venv", str(PY_VENV)], check=True)
        subprocess.run([str(py), "-m", "pip", "install", "--disable-pip-version-check", "-q", "-r", str(PY_REQS)],
                       check=True)
    return py


def get_job(addr: str, job_id: str) -> dict:
    p = subprocess.run([str(py_venv()), "-c", GETJOB, str(PY_REQS.parent), addr, job_id],
                       capture_output=True, text=True, check=True)
    return json.loads(p.stdout)["job"]


class Cluster:
    """`dray cluster` as a child process; members and their pids parsed from its stdout."""

    def __init__(self, dray: Path, workers: int, base_port: int, root: Path, log: Path) -> None:
        self.addr = f"127.0.0.1:{base_port}"
        self.log = log
        self.cmd = [str(dray), "cluster", "--workers", str(workers), "--base-port", str(base_port),
                    "--scene-root", str(root)]
        self.logf = open(log, "w")
        self.p = subprocess.Popen(self.cmd, stdout=subprocess.PIPE, stderr=self.logf, text=True,
                                  env=dict(os.environ, DRAY_LOG=os.environ.get("DRAY_LOG", "info")))
        self.pids: dict[str, int] = {}
        for line in self.p.stdout:
            m = re.match(r"(coordinator|worker \d+)\s+\S+\s+pid (\d+)", line)
            if m:
                self.pids[m.group(1)] = int(m.group(2))
            if line.startswith("dray cluster ready"):
                break
        else:
            self.stop()
            raise RuntimeError(f"dray cluster did not start; see {log}")
        env.log(f"cluster up: {self.pids}")

    def cpu(self) -> dict:
        """CPU seconds (user+sys) used so far by each member and by `dray cluster` itself."""
        return {name: proc_cpu(pid) for name, pid in {**self.pids, "cluster": self.p.pid}.items()}

    def mem(self) -> dict:
        return {name: proc_mem(pid) for name, pid in self.pids.items()}

    def stop(self) -> None:
        if self.p.poll() is None:
            self.p.send_signal(signal.SIGTERM)
            try:
                self.p.wait(30)
            except subprocess.TimeoutExpired:
                self.p.kill()
                self.p.wait()
        self.logf.close()


def submit(dray: Path, cl: Cluster, scene: str, flags: list, out: Path) -> dict:
    """`dray submit` to the cluster; the other load excludes the cluster's own CPU time (its
    members are grandchildren, which rusage of children does not see)."""
    addr = cl.addr
    cpu0 = cl.cpu()
    load = env.OtherLoad()
    r = env.run_timed([dray, "submit", "--coordinator", addr, scene, *flags, "--output", out])
    cpu1 = cl.cpu()
    r["cluster_cpu_s"] = {k: round(cpu1[k] - cpu0.get(k, 0.0), 2) for k in cpu1}
    r["other_load_cores"] = max(0.0, load.cores() - sum(r["cluster_cpu_s"].values()) / r["wall_s"])
    m = re.search(r"job (\S+) accepted", r["stderr"])
    r["job_id"] = m.group(1) if m else None
    r["stderr"] = "\n".join(r["stderr"].strip().splitlines()[-2:])
    if r["job_id"]:
        job = get_job(addr, r["job_id"])
        stats = job.get("stats", {})
        rays = int(job["progress"].get("raysTraced", "0"))
        sent = int(stats.get("rayBytesSent", "0"))
        r["job"] = job
        r["rays_traced"] = rays
        r["ray_bytes_sent"] = sent
        r["bytes_per_ray"] = sent / rays if rays else None
        el = job["progress"].get("elapsed", "0s").rstrip("s")
        r["job_elapsed_s"] = float(el)
    return r


# ---------------------------------------------------------------- sections

def overhead(a, dray: Path, work: Path) -> dict:
    scenes = env.scenes_dir()
    rel = f"grid:{a.scene}:{a.grid}" if a.grid else a.scene
    absolute = f"grid:{scenes / a.scene}:{a.grid}" if a.grid else str(scenes / a.scene)
    flags = ["--width", a.width, "--height", a.height, "--spp", a.spp, "--integrator", a.integrator,
             "--schedule", a.schedule]
    cl = Cluster(dray, a.workers, a.base_port, scenes, work / "overhead_cluster.log")
    rounds = []
    try:
        for i in range(a.runs):
            r = {}
            env.log(f"overhead round {i + 1}/{a.runs}: embedded --domains {a.domains}")
            r["embedded"] = timed([dray, "render", absolute, *flags, "--domains", a.domains, "--layout", a.layout,
                                   "--stats", work / f"emb{i}.json", "--output", work / f"emb{i}.png", "-q"])
            r["embedded"]["stats"] = json.loads((work / f"emb{i}.json").read_text())
            env.log(f"overhead round {i + 1}/{a.runs}: reference renderer (--workers 0) --domains {a.domains}")
            r["reference"] = timed([dray, "render", absolute, *flags, "--domains", a.domains, "--layout", a.layout,
                                    "--workers", "0", "--output", work / f"ref{i}.png", "-q"])
            env.log(f"overhead round {i + 1}/{a.runs}: embedded --domains 1")
            r["embedded_1"] = timed([dray, "render", absolute, *flags, "--stats", work / f"emb1_{i}.json",
                                     "--output", work / f"emb1_{i}.png", "-q"])
            r["embedded_1"]["stats"] = json.loads((work / f"emb1_{i}.json").read_text())
            env.log(f"overhead round {i + 1}/{a.runs}: cluster ({a.workers} workers) --domains {a.domains}")
            r["cluster"] = submit(dray, cl, rel, [*flags, "--domains", a.domains, "--layout", a.layout],
                                  work / f"sub{i}.png")
            r["same_png"] = sha(work / f"emb{i}.png") == sha(work / f"sub{i}.png") == sha(work / f"ref{i}.png")
            r["same_png_as_1_domain"] = sha(work / f"emb1_{i}.png") == sha(work / f"sub{i}.png")
            env.log(f"  embedded {r['embedded']['wall_s']:.2f} s, 1 domain {r['embedded_1']['wall_s']:.2f} s, "
                    f"cluster {r['cluster']['wall_s']:.2f} s, {r['cluster'].get('bytes_per_ray', 0):.2f} B/ray, "
                    f"same PNG {r['same_png']}")
            rounds.append(r)
        mem = cl.mem()
    finally:
        cl.stop()
    med = lambda k: statistics.median(r[k]["wall_s"] for r in rounds)  # noqa: E731
    summary = {
        "scene_embedded": absolute, "scene_cluster": rel, "cluster_cmd": " ".join(cl.cmd),
        "embedded_median_s": med("embedded"), "embedded_1_domain_median_s": med("embedded_1"),
        "reference_median_s": med("reference"),
        "ratio_vs_reference": med("cluster") / med("reference"),
        "cluster_median_s": med("cluster"),
        "ratio_vs_same_domains": med("cluster") / med("embedded"),
        "ratio_vs_1_domain": med("cluster") / med("embedded_1"),
        "bytes_per_ray": [r["cluster"].get("bytes_per_ray") for r in rounds],
        "rays_traced": [r["cluster"].get("rays_traced") for r in rounds],
        "embedded_rays": [r["embedded"]["stats"]["rays_total"] for r in rounds],
        "same_png": [r["same_png"] for r in rounds],
        "cluster_cpu_s": [round(sum(r["cluster"]["cluster_cpu_s"].values()), 1) for r in rounds],
        "embedded_cpu_s": [round(r["embedded"]["cpu_s"], 1) for r in rounds],
        "other_load": {k: [round(r[k]["other_load_cores"], 2) for r in rounds]
                       for k in ("embedded", "embedded_1", "reference", "cluster")},
        "cluster_mem_mib_at_end": mem,
    }
    return {"rounds": rounds, "summary": summary}


def stream(a, dray: Path, work: Path) -> dict:
    cmd = ["cargo", "bench", "-p", "dray-worker", "--bench", "ray_stream"]
    env.log(" ".join(cmd))
    r = timed(cmd)
    text = r["stdout"] + r["stderr"]
    out = {"cmd": r["cmd"], "other_load_cores": r["other_load_cores"], "wall_s": r["wall_s"]}
    m = re.search(r"time:\s+\[([^\]]+)\]", text)
    if m:
        out["time"] = m.group(1)
    m = re.search(r"thrpt:\s+\[([^\]]+)\]", text)
    if m:
        out["thrpt"] = m.group(1)
    m = re.search(r"ray_stream: .*", text)
    if m:
        out["wire"] = m.group(0)
    (work / "ray_stream.txt").write_text(text)
    env.log(f"ray_stream: time [{out.get('time')}], thrpt [{out.get('thrpt')}]")
    return out


def big(a, dray: Path, work: Path) -> dict:
    pkg = work / "big64"
    env.log(f"big: dray partition {a.big} --domains {a.big_domains}")
    part = run_peak([dray, "partition", a.big, "--domains", a.big_domains, "--out", pkg], work / "big_partition.log")
    manifest = json.loads((pkg / "manifest.json").read_text()) if (pkg / "manifest.json").exists() else None
    flags = ["--width", a.big_res, "--height", a.big_res, "--spp", a.big_spp, "--integrator", a.integrator]
    cl = Cluster(dray, a.workers, a.base_port + 10, work, work / "big_cluster.log")
    samples: dict[str, dict] = {}
    stop = threading.Event()

    def poll() -> None:
        while not stop.is_set():
            for name, m in cl.mem().items():
                s = samples.setdefault(name, {"VmHWM": 0.0, "VmRSS_max": 0.0})
                s["VmHWM"] = max(s["VmHWM"], m.get("VmHWM", 0.0))
                s["VmRSS_max"] = max(s["VmRSS_max"], m.get("VmRSS", 0.0))
            stop.wait(0.25)

    idle = cl.mem()
    t = threading.Thread(target=poll, daemon=True)
    t.start()
    try:
        env.log(f"big: submit {pkg.name} to {a.workers} workers")
        sub = submit(dray, cl, pkg.name, flags, work / "big_cluster.png")
        time.sleep(0.5)
    finally:
        stop.set()
        t.join()
        cl.stop()
    loaded = [int(x) for x in re.findall(r"job loaded\S*\s+\S*triangles\S*=\S*?(\d+)",
                                         re.sub(r"\x1b\[[0-9;]*m", "", cl.log.read_text()))]
    res = {"partition": part, "manifest_head": _manifest_summary(manifest), "cluster_cmd": " ".join(cl.cmd),
           "submit": sub, "mem_mib_idle": idle, "mem_mib_peak": samples, "worker_triangles_loaded": loaded,
           "png": png_stats(work / "big_cluster.png")}
    if a.big_embedded:
        env.log(f"big: embedded dray render {a.big}")
        emb = run_peak([dray, "render", a.big, *flags, "--domains", a.big_domains, "--output",
                        work / "big_embedded.png", "-q"])
        res["embedded"] = emb
        res["same_png"] = sha(work / "big_embedded.png") == sha(work / "big_cluster.png")
    return res


def _manifest_summary(m: dict | None) -> dict | None:
    """Totals of a package manifest, and which domains each worker owns under the
    coordinator's static round robin (domain d -> worker d % n, in registration order)."""
    if not m:
        return None
    b = m.get("body", m)
    doms = b.get("domains", [])
    return {"format": m.get("format"), "version": m.get("version"), "source_triangles": b.get("source_triangles"),
            "assigned_triangles": b.get("assigned_triangles"), "domains": len(doms),
            "domain_triangles": [d.get("triangles") for d in doms],
            "domain_bytes": [d.get("bytes") for d in doms]}


def partition(a, dray: Path, work: Path) -> dict:
    pkg = work / "part100"
    env.log(f"partition: dray partition {a.part} --domains {a.part_domains}")
    r = run_peak(["/usr/bin/time", "-v", dray, "partition", a.part, "--domains", a.part_domains, "--out", pkg],
                 work / "part100.log")
    log = (work / "part100.log").read_text()
    m = re.search(r"Maximum resident set size \(kbytes\): (\d+)", log)
    r["time_v_max_rss_mib"] = int(m.group(1)) / 1024 if m else None
    r["package_bytes"] = sum(f.stat().st_size for f in pkg.rglob("*") if f.is_file())
    r["log_tail"] = "\n".join(log.strip().splitlines()[-30:])
    if not a.keep_package:
        shutil.rmtree(pkg)
    return r


def main() -> int:
    a = parse_args()
    os.chdir(env.ROOT)
    dray = env.dray_binary().resolve()
    work = a.work.resolve()
    work.mkdir(parents=True, exist_ok=True)
    wanted = [s.strip() for s in a.sections.split(",") if s.strip()]
    results_path = work / "results.json"
    results = json.loads(results_path.read_text()) if results_path.exists() else {}
    results["machine"] = env.machine_info()
    results["binary"] = env.binary_info(dray)
    results["idle_before_cores"] = env.idle_check()
    for s in wanted:
        t0 = time.time()
        results[s] = {**globals()[s](a, dray, work),
                      "started": time.strftime("%H:%M:%S", time.gmtime(t0)) + " UTC"}
        results_path.write_text(json.dumps(results, indent=1, default=str))
        summary = results[s].get("summary") or {k: v for k, v in results[s].items()
                                                if k not in ("rounds", "stdout", "log_tail")}
        print(json.dumps({s: summary}, default=str)[:4000])
    env.log(f"results in {results_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

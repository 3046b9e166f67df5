"""Shared plumbing for the comparison benchmarks in benches/.

- `ensure_venv()` re-executes the calling script inside benches/.venv, creating the venv
  and installing benches/requirements.txt first (nothing is installed by hand).
- `dray_binary()` finds target/release/dray (or $DRAY_BIN).
- `machine_info()` describes the machine for the report.
- `run_timed()` runs a child process and measures its wall and CPU time.

Only the standard library is imported at module level, so this works before the venv exists.
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

BENCH_DIR = Path(__file__).resolve().parent
ROOT = BENCH_DIR.parent
VENV = BENCH_DIR / ".venv"
REQUIREMENTS = BENCH_DIR / "requirements.txt"
OUT = BENCH_DIR / "out"


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def _in_venv() -> bool:
    try:
        return Path(sys.prefix).resolve() == VENV.resolve()
    except OSError:
        return False


def ensure_venv() -> None:
    """Make sure we run inside benches/.venv with requirements.txt installed; re-exec if not."""
    if _in_venv():
        return
    py = VENV / "bin" / "python"
    if not py.exists():
        log(f"creating venv {VENV}")
        subprocess.run([sys.executable, "-m", "venv", str(VENV)], check=True)
    stamp = VENV / ".requirements.installed"
    wanted = REQUIREMENTS.read_text()
    if not stamp.exists() or stamp.read_text() != wanted:
        log(f"pip install -r {REQUIREMENTS.relative_to(ROOT)} into {VENV.relative_to(ROOT)}")
        subprocess.run(
            [str(py), "-m", "pip", "install", "--disable-pip-version-check", "-q", "-r", str(REQUIREMENTS)],
            check=True,
        )
        stamp.write_text(wanted)
    os.execv(str(py), [str(py), *sys.argv])


def dray_binary() -> Path:
    p = Path(os.environ.get("DRAY_BIN", ROOT / "target" / "release" / "dray"))
    if not p.exists():
        sys.exit(f"dray binary {p} not found: build it with `cargo build --release -p dray` (or set DRAY_BIN)")
    return p


def scenes_dir() -> Path:
    return Path(os.environ.get("DRAY_SCENES", ROOT.parent / "shared" / "scenes")).resolve()


def have_taskset() -> bool:
    return shutil.which("taskset") is not None


def pin(cores: str, cmd: list) -> list:
    """Prefix `cmd` with `taskset -c cores`."""
    if not have_taskset():
        sys.exit("taskset not found (util-linux); it is needed to pin both sides to the same cores")
    return ["taskset", "-c", cores, *map(str, cmd)]


def run_timed(cmd: list, env: dict | None = None, check: bool = True) -> dict:
    """Run `cmd`; return wall time, child CPU time (user+sys), stdout, stderr and return code."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    p = subprocess.run([str(c) for c in cmd], capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    res = {"cmd": " ".join(map(str, cmd)), "wall_s": wall, "cpu_s": cpu, "rc": p.returncode,
           "stdout": p.stdout, "stderr": p.stderr}
    if check and p.returncode != 0:
        tail = "\n".join(p.stderr.strip().splitlines()[-15:])
        raise RuntimeError(f"command failed (exit {p.returncode}): {res['cmd']}\n{tail}")
    return res


def last_json_line(text: str) -> dict:
    for line in reversed(text.strip().splitlines()):
        line = line.strip()
        if line.startswith("{"):
            return json.loads(line)
    raise ValueError(f"no JSON line in output:\n{text}")


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def cpu_flags() -> list[str]:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("flags"):
                flags = set(line.split(":", 1)[1].split())
                return [f for f in ("sse4_2", "avx", "avx2", "fma", "avx512f") if f in flags]
    except OSError:
        pass
    return []


def git_rev() -> str:
    try:
        p = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
        rev = p.stdout.strip() or "unknown"
        d = subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain"], capture_output=True, text=True)
        return rev + ("+dirty" if d.stdout.strip() else "")
    except OSError:
        return "unknown"


def package_versions(names: list[str]) -> dict:
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for n in names:
        try:
            out[n] = version(n)
        except PackageNotFoundError:
            out[n] = None
    return out


def machine_info() -> dict:
    mem_gib = None
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal"):
                mem_gib = round(int(line.split()[1]) / 2**20, 1)
    except OSError:
        pass
    return {
        "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "nproc": os.cpu_count(),
        "affinity": sorted(os.sched_getaffinity(0)),
        "cpu_model": cpu_model(),
        "cpu_flags": cpu_flags(),
        "mem_gib": mem_gib,
        "kernel": platform.release(),
        "python": platform.python_version(),
        "loadavg_at_start": [round(x, 2) for x in os.getloadavg()],
        "dray_git": git_rev(),
    }


def _cpu_jiffies(cores: list[int] | None = None) -> tuple[int, int]:
    """(busy, total) jiffies from /proc/stat, over all cores or just `cores`."""
    busy = total = 0
    with open("/proc/stat") as f:
        for line in f:
            if not line.startswith("cpu"):
                break
            name, *rest = line.split()
            if (cores is None and name != "cpu") or (cores is not None and name[3:] not in {str(c) for c in cores}):
                continue
            vals = [int(x) for x in rest]
            idle = vals[3] + (vals[4] if len(vals) > 4 else 0)
            busy += sum(vals[:8]) - idle
            total += sum(vals[:8])
    return busy, total


def parse_cores(spec: str) -> list[int]:
    """'0,1' or '0-1' (taskset -c syntax, simple forms) -> [0, 1]."""
    out: list[int] = []
    for part in spec.split(","):
        a, _, b = part.partition("-")
        out.extend(range(int(a), int(b or a) + 1))
    return out


class OtherLoad:
    """How busy the machine (or the given cores) was with processes other than ours.

    Reported as the average number of cores used by others while the benchmark ran:
    (CPU time spent on those cores by anyone - CPU time of this process and its children)
    / wall time. With `cores`, our own work must be pinned to those cores. Anything well
    above 0 means the timings were disturbed by other work on the machine.
    """

    def __init__(self, cores: list[int] | None = None) -> None:
        self.cores_sel = cores
        self.t0 = time.perf_counter()
        self.busy0, _ = _cpu_jiffies(cores)
        self.ours0 = self._ours()

    @staticmethod
    def _ours() -> float:
        s, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
        return s.ru_utime + s.ru_stime + c.ru_utime + c.ru_stime

    def cores(self) -> float:
        wall = time.perf_counter() - self.t0
        busy = (_cpu_jiffies(self.cores_sel)[0] - self.busy0) / os.sysconf("SC_CLK_TCK")
        return max(0.0, (busy - (self._ours() - self.ours0)) / max(wall, 1e-9))


def embree_build(tris) -> tuple:
    """Build an Embree BVH over `tris` ((n, 3, 3) float32, unwelded) through embreex, timing
    each stage. Returns (scene, timings). Needs the venv (numpy, embreex).

    embreex gives no way to call rtcCommitScene or to pass rtcNewDevice a config (its
    `EmbreeDevice()` calls `rtcNewDevice(NULL)`, and this Embree build reads no
    ~/.embree4 file), so:
    - `device_s`: `EmbreeDevice()` + `EmbreeScene(device)` (rtcNewDevice, TBB start-up,
      rtcNewScene);
    - `copy_s`: `TriangleMesh(scene, tris)`: embreex copies every vertex into Embree's
      buffers in an untyped Cython loop (Python-speed indexing; slow, and not Embree's
      cost), then rtcCommitGeometry + rtcAttachGeometry;
    - `commit_s`: the BVH build. embreex commits the scene lazily in the first `run()`;
      `first_query_s` times that first run() of one ray (checked: `is_committed` goes
      from 0 to 1 inside it), `query_s` is the median of later 1-ray run() calls on the
      built scene, and `commit_s = first_query_s - query_s`.
    One thread: Embree builds with one TBB worker per core of the process's affinity
    mask, so the caller pins the process to one core (taskset -c CORE);
    `threads_in_process` and `commit_cpu_s` (process CPU time over the first run) show it.
    The one-ray query aims at the centroid of triangle 0 from outside the bounds, so it
    must hit: a scene that built nothing would fail the check.
    """
    import numpy as np
    from embreex import mesh_construction, rtcore, rtcore_scene

    tris = np.ascontiguousarray(tris, dtype=np.float32)
    lo, hi = tris.reshape(-1, 3).min(0), tris.reshape(-1, 3).max(0)
    target = tris[0].mean(0)
    origin = (hi + (hi - lo) + 1.0).astype(np.float32)
    d = (target - origin).astype(np.float64)
    o1 = origin.reshape(1, 3).astype(np.float32)
    d1 = (d / np.linalg.norm(d)).reshape(1, 3).astype(np.float32)

    t0 = time.perf_counter()
    device = rtcore.EmbreeDevice()
    scene = rtcore_scene.EmbreeScene(device)
    t1 = time.perf_counter()
    mesh = mesh_construction.TriangleMesh(scene, tris)
    t2 = time.perf_counter()
    committed_before = int(scene.is_committed)
    c0 = time.process_time()
    t3 = time.perf_counter()
    dist = scene.run(o1, d1, query="DISTANCE")
    t4 = time.perf_counter()
    commit_cpu = time.process_time() - c0
    committed_after = int(scene.is_committed)
    if committed_before != 0 or committed_after != 1:
        raise RuntimeError(f"embreex did not commit inside the first run() (is_committed {committed_before} -> "
                           f"{committed_after}): the build was not timed")
    if not float(dist[0]) < 1e37:
        raise RuntimeError("the check ray towards triangle 0 missed: the Embree scene is empty or broken")
    q = []
    for _ in range(200):
        t = time.perf_counter()
        scene.run(o1, d1, query="DISTANCE")
        q.append(time.perf_counter() - t)
    query_s = sorted(q)[len(q) // 2]
    first = t4 - t3
    timings = {
        "device_s": t1 - t0,
        "copy_s": t2 - t1,
        "first_query_s": first,
        "query_s": query_s,
        "commit_s": max(first - query_s, 0.0),
        "commit_cpu_s": commit_cpu,
        "threads_in_process": len(os.listdir("/proc/self/task")),
        "embree_version": repr(device).split(":", 1)[-1].strip(),
        "check_ray_t": float(dist[0]),
    }
    del mesh  # the scene holds the attached geometry (and the device)
    return scene, timings


def binary_info(path: Path) -> dict:
    import hashlib

    st = path.stat()
    return {"path": str(path), "size": st.st_size,
            "mtime": datetime.datetime.fromtimestamp(st.st_mtime, datetime.timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC"),
            "sha256": hashlib.sha256(path.read_bytes()).hexdigest()[:16]}


def idle_check(seconds: float = 2.0) -> float:
    """Cores busy (all processes) over `seconds` before we start; warns when the machine is not idle."""
    b0, t0 = _cpu_jiffies()
    time.sleep(seconds)
    b1, t1 = _cpu_jiffies()
    busy_cores = (b1 - b0) / max(t1 - t0, 1) * (os.cpu_count() or 1)
    if busy_cores > 0.15:
        log(f"WARNING: the machine is not idle ({busy_cores:.2f} cores busy before the start); "
            "timings will be disturbed")
    return busy_cores


def bunny() -> Path:
    """The Stanford bunny of the shared scenes; exits with a clear message when absent."""
    path = scenes_dir() / "stanford_bunny" / "bun_zipper.ply"
    if not path.exists():
        sys.exit(f"the Stanford bunny is not at {path}: set DRAY_SCENES to the shared scenes")
    return path


def bunny_grid_package(dray: Path, work: Path) -> Path:
    """The 3x3x3 bunny grid cut into 27 grid domains (Little 2011's Table 5.1 scene) as a
    scene package under `work`, partitioned once and shared by the cache benchmarks."""
    package = work / "bunny-grid-27"
    if not (package / "manifest.json").exists():
        work.mkdir(parents=True, exist_ok=True)
        subprocess.run([str(dray), "partition", f"grid:{bunny()}:3x3x3", "--grid", "3x3x3",
                        "--layout", "grid", "--out", str(package)], check=True)
    return package


class Cluster:
    """`dray cluster --workers N` as a child process (extra flags in `extra`), up until
    `stop`; `addr` is its coordinator's host:port."""

    def __init__(self, dray: Path, workers: int, port: int, root: Path, log: Path,
                 extra: list[str] | None = None) -> None:
        self.addr = f"127.0.0.1:{port}"
        cmd = [str(dray), "cluster", "--workers", str(workers), "--base-port", str(port),
               "--scene-root", str(root), *(extra or [])]
        self.logf = open(log, "w")
        self.p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=self.logf, text=True)
        for line in self.p.stdout:
            if line.startswith("dray cluster ready"):
                break
        else:
            self.stop()
            raise RuntimeError(f"dray cluster did not start: {' '.join(cmd)}; see {log}")

    def stop(self) -> None:
        import signal
        if self.p.poll() is None:
            self.p.send_signal(signal.SIGTERM)
            try:
                self.p.wait(60)
            except subprocess.TimeoutExpired:
                self.p.kill()
                self.p.wait()
        self.logf.close()


def save_results(path, info: dict, args, results: list, load) -> None:
    """Write results.json: the machine facts (with the other processes' average load
    during the run, from `load`), the arguments and the results."""
    import json
    from pathlib import Path as _Path

    info["other_processes_cores_during_run"] = round(load.cores(), 2)
    out = {"machine": info, "args": {k: (str(v) if isinstance(v, _Path) else v) for k, v in vars(args).items()},
           "results": results}
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=2) + "\n")

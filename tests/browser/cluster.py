"""A real `dray cluster` for the browser test: started on ports the system chooses (the
dashboard's picked free here), its coordinator's gRPC address read from its ready line,
stopped with SIGTERM (then SIGKILL) however the test ends."""

from __future__ import annotations

import json
import re
import socket
import subprocess
import threading
import time
from pathlib import Path


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Cluster:
    def __init__(self, dray: str, log: Path, workers: int = 2, token_file: Path | None = None):
        self.http_port = free_port()
        self.token_file = token_file
        args = [dray, "cluster", "--workers", str(workers), "--base-port", "0",
                "--threads", "1", "--http-listen", f"127.0.0.1:{self.http_port}"]
        if token_file:
            args += ["--auth-token-file", str(token_file)]
        self.log = log
        self._stderr = open(log, "w")
        self.proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=self._stderr,
                                     stdin=subprocess.DEVNULL, text=True)
        self.grpc = None
        self.lines: list[str] = []
        ready = threading.Event()

        def read() -> None:
            for line in self.proc.stdout:
                self.lines.append(line.rstrip())
                m = re.search(r"dray cluster ready: .* coordinator at (\S+);", line)
                if m:
                    self.grpc = m.group(1)
                    ready.set()
            ready.set()

        threading.Thread(target=read, daemon=True).start()
        # Generous: a cluster on a loaded 2-core machine can take a while to start.
        if not ready.wait(300) or self.grpc is None:
            self.stop()
            raise RuntimeError(f"dray cluster did not become ready; stdout {self.lines}; "
                               f"stderr in {log}")

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.http_port}"

    def grpcurl(self, grpcurl: str, method: str, body: dict, token: bool = True) -> dict:
        """One RenderService call through grpcurl (reflection, plaintext)."""
        args = [grpcurl, "-plaintext", "-d", json.dumps(body)]
        if token and self.token_file:
            args[1:1] = ["-H", f"authorization: Bearer {self.token_file.read_text().strip()}"]
        args += [self.grpc, f"dray.v1.RenderService/{method}"]
        r = subprocess.run(args, capture_output=True, text=True, timeout=120)
        if r.returncode != 0:
            raise RuntimeError(f"grpcurl {method}: {r.stderr.strip()}")
        return json.loads(r.stdout)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(60)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._stderr.close()


def wait_for(what: str, check, timeout: float = 300.0, every: float = 0.2):
    """Poll `check` until it returns something truthy (returned); no assertion on how
    long it took, only a generous bound so a broken build does not hang CI."""
    end = time.monotonic() + timeout
    last_error = None
    while time.monotonic() < end:
        try:
            v = check()
            if v:
                return v
        except Exception as e:  # noqa: BLE001 - a page mid-render may throw; try again
            last_error = e
        time.sleep(every)
    raise AssertionError(f"gave up waiting for {what}" + (f" (last error: {last_error})"
                                                          if last_error else ""))

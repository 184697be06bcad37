"""A real bodyfit server in a subprocess (``bodyfit serve`` on 127.0.0.1), for benchmarks and end-to-end
tests: started with its own settings, waited on until ready, measured (resident memory) and stopped."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypeVar

import httpx

ROOT = Path(__file__).resolve().parents[1]
T = TypeVar("T")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass
class ServerProcess:
    """A started server: ``url`` (REST), ``target`` (gRPC host:port), the process, its start-up time and
    the last lines of its log (:meth:`log`)."""

    proc: subprocess.Popen[bytes]
    url: str
    target: str
    startup_s: float
    lines: deque[str] = field(default_factory=lambda: deque(maxlen=2000))

    def log(self) -> str:
        """The server's log so far (its last 2,000 lines)."""
        return "".join(self.lines)

    def rss_mb(self) -> float:
        """The server's resident memory now (MiB)."""
        return _status_kb(self.proc.pid, "VmRSS") / 1024

    def peak_growth(self, work: Callable[[], T]) -> tuple[T, float]:
        """Run ``work`` (e.g. one request) and return its result and how far the server's peak resident
        memory rose above its resident memory before it (MiB; Linux: the peak is reset with clear_refs 5)."""
        before = self.rss_mb()
        Path(f"/proc/{self.proc.pid}/clear_refs").write_text("5")
        result = work()
        return result, _status_kb(self.proc.pid, "VmHWM") / 1024 - before

    def ready(self) -> bool:
        try:
            return httpx.get(f"{self.url}/readyz", timeout=5).status_code == 200
        except httpx.HTTPError:
            return False

    def stop(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(10)


def start_server(env: dict[str, str] | None = None, timeout_s: float = 180.0) -> ServerProcess:
    """Start ``bodyfit serve`` with REST and gRPC on free 127.0.0.1 ports and ``env`` added to the
    environment (``BODYFIT_*`` settings); return once /readyz answers 200.

    Raises:
        RuntimeError: the server exited or was not ready within ``timeout_s`` (with the end of its log).
    """
    rest, grpc = free_port(), free_port()
    cmd = [
        sys.executable,
        "-m",
        "bodyfit.cli",
        "serve",
        "--port",
        str(rest),
        "--grpc-port",
        str(grpc),
    ]
    began = time.monotonic()
    proc = subprocess.Popen(
        cmd, cwd=ROOT, env={**os.environ, **(env or {})}, stdout=subprocess.PIPE, stderr=subprocess.STDOUT
    )
    server = ServerProcess(proc, f"http://127.0.0.1:{rest}", f"127.0.0.1:{grpc}", 0.0)
    _keep_log(server)
    while time.monotonic() - began < timeout_s:
        if proc.poll() is not None:
            time.sleep(0.2)  # the log's last lines
            raise RuntimeError(f"the server exited: {server.log()[-3000:]}")
        if server.ready():
            server.startup_s = time.monotonic() - began
            return server
        time.sleep(0.1)
    server.stop()
    raise RuntimeError(f"the server was not ready within {timeout_s:g} s")


def _keep_log(server: ServerProcess) -> None:
    """Read the server's output in the background into ``server.lines`` (so that it never fills the pipe)."""

    def run() -> None:
        assert server.proc.stdout is not None
        for line in server.proc.stdout:
            server.lines.append(line.decode(errors="replace"))

    threading.Thread(target=run, daemon=True).start()


def _status_kb(pid: int, key: str) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return float(line.split()[1])
    raise RuntimeError(f"no {key} in /proc/{pid}/status")

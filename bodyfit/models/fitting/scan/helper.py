"""A second process for the scan fit (:class:`~bodyfit.models.fitting.scan.fitter.ScanFitter` with
``processes=2``).

The scan fit is bound by Python's per-call overhead under the interpreter lock: its two branches, run at
once on two threads, take little less than one after the other, and the phases before the branches run on
one core. A helper process, with its own copy of the fitter, runs the second branch and half of the
hypotheses of the phases before the branches on the other core.

The helper starts in the background, as ``python -m bodyfit.models.fitting.scan.helper`` (a fresh
interpreter: it does not import the caller's script, so no ``__main__`` guard is needed there); it builds its
fitter from the parent's model and registered fitter (its memory and speed-up: docs/service.md).
Work it is asked for while it is starting, busy with another fit's work, or after it failed is run by the
caller itself (:meth:`ScanHelper.submit` returns None): the fit is the same either way, only slower.
"""

from __future__ import annotations

import contextlib
import logging
import os
import pickle
import socket
import subprocess
import sys
import time
import weakref
from collections.abc import Callable
from multiprocessing.connection import Connection
from threading import Lock, Thread
from typing import Any

import torch

log = logging.getLogger(__name__)

STOP_SECONDS = 5.0  # how long a stopping helper may take to exit before it is killed
ANSWER_SECONDS = 300.0  # a task takes seconds; a helper silent this long is stuck and is killed
RESTART_SECONDS = 60.0  # after a helper failed, work waits this long before it starts a new one
MAX_RESTARTS = 5  # then the fits stay in the calling process


def _send(conn: Connection, message: Any) -> None:
    """Send ``message`` pickled by value (a tensor's data in the message, not in shared memory that the
    other process would fetch through multiprocessing's own authenticated channel)."""
    conn.send_bytes(pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL))


def _receive(conn: Connection) -> Any:
    return pickle.loads(conn.recv_bytes())


def _serve(conn: Connection) -> None:
    """The helper's loop: receive ``(make, args)`` and build ``make(*args)``, say so, then run each
    ``(method name, arguments)`` received on it and send back ``("ok", result)`` or ``("error", message)``,
    until None or the parent's end closes."""
    torch.set_num_threads(1)  # one core's worth; the parent's process has the other
    try:
        first = _receive(conn)
    except (EOFError, OSError):
        return
    if first is None:  # stopped before it was given its work
        return
    make, args = first
    worker = make(*args)
    _send(conn, ("ready", None))
    while True:
        try:
            message = _receive(conn)
        except (EOFError, OSError):
            return
        if message is None:
            return
        name, task = message
        try:
            reply: tuple[str, Any] = ("ok", getattr(worker, name)(*task))
        except Exception as error:  # the parent runs the task itself and meets the error there
            reply = ("error", f"{type(error).__name__}: {error}")
        try:
            _send(conn, reply)
        except OSError:  # the parent is gone
            return


def _stop(process: subprocess.Popen[bytes], conn: Connection, starting: list[bool]) -> None:
    """Ask the helper to exit, then end it; one not yet known to have started (``starting[0]``: its imports
    take a second and it would read the request only after them) is killed at once: it holds no work."""
    if starting[0]:
        process.kill()
    with contextlib.suppress(OSError, ValueError):
        _send(conn, None)
    try:
        process.wait(STOP_SECONDS)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait(STOP_SECONDS)
    conn.close()


class ScanHelper:
    """A helper process holding ``make(*args)`` (a fitter), which runs its methods on request, one request
    at a time. A helper that failed is started again by the first work asked for ``restart_after`` seconds
    later (a long-lived service keeps its speed), up to :data:`MAX_RESTARTS` times. Stopped by
    :meth:`close`, when the helper object is collected, or when the parent exits."""

    def __init__(self, make: Callable[..., Any], *args: Any, restart_after: float = RESTART_SECONDS) -> None:
        self._make, self._args = make, args
        self.restart_after = restart_after  # seconds after a failure before the next work restarts it
        self.restarts = 0
        self.completed = 0  # tasks it ran to the end
        self._lock = Lock()
        self._closed = False
        self._start()

    def _start(self) -> None:
        """Start a helper process (the caller holds the lock, or is the constructor)."""
        mine, theirs = socket.socketpair()
        fd = theirs.fileno()
        # the caller's import path, as multiprocessing's spawn passes it (bodyfit may be on it by hand)
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}
        self._process = subprocess.Popen(
            [sys.executable, "-m", __name__, str(fd)], pass_fds=(fd,), stdin=subprocess.DEVNULL, env=env
        )
        theirs.close()
        self._conn = Connection(mine.detach())
        # the parent's model travels while both go on (the helper reads it once its imports are done)
        Thread(target=self._send_quietly, args=((self._make, self._args),), daemon=True).start()
        self._ready = False
        self._starting = [True]  # shared with the finalizer: False once its "ready" has been read here
        self._failed = False
        self._failed_at = 0.0
        self._stop = weakref.finalize(self, _stop, self._process, self._conn, self._starting)

    def _send_quietly(self, message: Any) -> None:
        with contextlib.suppress(OSError, ValueError):  # a helper gone: noticed when it is waited for
            _send(self._conn, message)

    @property
    def pid(self) -> int:
        """The helper's process id."""
        return self._process.pid

    @property
    def alive(self) -> bool:
        """The helper's process runs."""
        return self._process.poll() is None

    @property
    def ready(self) -> bool:
        """The helper has started and has not failed (its start is noticed here, without waiting)."""
        with self._lock:
            return self._poll_ready(0.0)

    def wait_ready(self, timeout: float) -> bool:
        """Wait up to ``timeout`` seconds for the helper to start; whether it is ready."""
        with self._lock:
            return self._poll_ready(timeout)

    def _poll_ready(self, timeout: float) -> bool:
        if self._ready or self._failed:
            return self._ready
        try:
            if self._conn.poll(timeout):
                self._ready = _receive(self._conn)[0] == "ready"
                self._failed = not self._ready
                self._starting[0] = False
        except (EOFError, OSError):
            self._fail("it exited while starting")
        return self._ready

    def submit(self, name: str, *task: Any) -> Callable[[], Any] | None:
        """Start ``fitter.name(*task)`` in the helper when it is ready and free: returns a function that
        waits for its result (None when the helper failed meanwhile); None when the helper cannot take it
        now. The caller then runs the task itself."""
        if not self._lock.acquire(blocking=False):
            return None  # another fit's work is running there
        try:
            if self._failed and not self._closed:
                self._restart()
            if not self._poll_ready(0.0):
                self._lock.release()
                return None
            _send(self._conn, (name, task))
        except (OSError, ValueError) as error:
            self._fail(f"sending work failed ({error})")
            self._lock.release()
            return None

        def result() -> Any:
            try:
                if not self._conn.poll(ANSWER_SECONDS):
                    self._process.kill()  # stuck: its answer would come out of turn later
                    raise TimeoutError(f"no answer in {ANSWER_SECONDS:.0f} s")
                status, value = _receive(self._conn)
            except (EOFError, OSError) as error:
                self._fail(f"it gave no answer to {name} ({type(error).__name__}: {error})")
                return None
            finally:
                self._lock.release()
            if status != "ok":
                log.warning("scan helper: %s failed there (%s); running it here", name, value)
                return None
            self.completed += 1
            return value

        return result

    def _fail(self, why: str) -> None:
        if not self._failed:
            log.warning("scan helper: %s; the fits go on in one process for now", why)
            self._failed_at = time.monotonic()
        self._failed, self._ready = True, False

    def _restart(self) -> None:
        """Start a new helper once ``restart_after`` seconds have passed since the last one failed (the
        caller holds the lock); the old one is stopped."""
        if self.restarts >= MAX_RESTARTS or time.monotonic() - self._failed_at < self.restart_after:
            return
        self._stop()
        self.restarts += 1
        log.warning("scan helper: starting it again (restart %d)", self.restarts)
        self._start()

    def close(self) -> None:
        """Stop the helper for good (idempotent); later work runs in the caller."""
        with self._lock:
            self._closed = True
            self._failed, self._ready = True, False
        self._stop()


if __name__ == "__main__":
    _serve(Connection(int(sys.argv[1])))
    os._exit(0)  # nothing to flush; the interpreter's teardown of torch would keep the parent waiting

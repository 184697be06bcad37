"""Control of one long-running request: cancellation, a deadline, a progress sink and a sink for partial
results.

The core calls :meth:`Job.report` between steps of a long computation; that is where a cancelled or late
job stops (by raising). Work that has final results before it ends (a sequence fit's first frames) hands
them to :meth:`Job.emit`, so a client reads them while the rest is computed. Transports create the job,
wire ``cancel()`` to the client going away, and forward the reported and emitted events to the client.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from bodyfit.service.errors import DeadlineExceededError, JobCancelledError


@dataclass(frozen=True)
class Progress:
    """A progress event: ``stage`` name, ``done`` of ``total`` units, and a human-readable message."""

    stage: str
    done: int
    total: int
    message: str = ""

    def to_dict(self) -> dict[str, Any]:
        return {"stage": self.stage, "done": self.done, "total": self.total, "message": self.message}


@dataclass
class Job:
    """Args:
    timeout_s: wall-clock limit from creation (None: no limit).
    on_progress: called with each :class:`Progress` (from the worker thread).
    on_event: called with each partial result the work emits (from the worker thread), in order; what an
        event is is the transport's business (a wire document, a protobuf message).
    """

    timeout_s: float | None = None
    on_progress: Callable[[Progress], None] | None = None
    on_event: Callable[[Any], None] | None = None
    started: float = field(default_factory=time.monotonic)
    _cancelled: threading.Event = field(default_factory=threading.Event)

    def cancel(self) -> None:
        """Ask the work to stop at its next check (thread-safe)."""
        self._cancelled.set()

    @property
    def cancelled(self) -> bool:
        return self._cancelled.is_set()

    @property
    def elapsed_s(self) -> float:
        return time.monotonic() - self.started

    def check(self) -> None:
        """Raise :class:`JobCancelledError` or :class:`DeadlineExceededError` when the work must stop."""
        if self._cancelled.is_set():
            raise JobCancelledError("the request was cancelled by the client")
        if self.timeout_s is not None and self.elapsed_s > self.timeout_s:
            raise DeadlineExceededError(
                f"the work took longer than the server's limit of {self.timeout_s:g} s; send a smaller "
                "input (fewer points or frames) or ask the operator to raise BODYFIT_MAX_SECONDS"
            )

    def report(self, stage: str, done: int, total: int, message: str = "") -> None:
        """Check for cancellation and deadline, then forward a progress event."""
        self.check()
        if self.on_progress is not None:
            self.on_progress(Progress(stage, done, total, message))

    def emit(self, event: Any) -> None:
        """Check for cancellation and deadline, then hand a partial result to the transport.

        Raises:
            RuntimeError: the job has no ``on_event`` sink, so the event would be lost.
        """
        self.check()
        if self.on_event is None:
            raise RuntimeError("this job has no on_event sink; the transport must collect emitted events")
        self.on_event(event)

"""Micro-batching of synthesis: concurrent requests share one ONNX Runtime call.

One worker thread takes the first waiting request, adds every request already queued behind it (up to
``max_bodies`` bodies, without waiting for more), runs the model once on the stacked inputs and hands each
caller its rows. Under load this trades B small calls for one larger one, which costs less per body; an
idle server answers a lone request at once.
"""

from __future__ import annotations

import queue
import threading
from concurrent.futures import Future
from dataclasses import dataclass, field

import numpy as np
import onnxruntime as ort

Outputs = tuple[np.ndarray, np.ndarray]
"""vertices (B, V, 3) and joints (B, J, 3), float32."""


@dataclass
class _Item:
    shape: np.ndarray
    coordinates: np.ndarray
    root: np.ndarray
    future: Future[Outputs] = field(default_factory=Future)


class SynthBatcher:
    """Args:
    session: the body model's ONNX Runtime session (inputs shape, coordinates, root).
    max_bodies: most bodies run in one call.
    """

    def __init__(self, session: ort.InferenceSession, max_bodies: int = 64) -> None:
        self.session = session
        self.max_bodies = max_bodies
        self._queue: queue.SimpleQueue[_Item | None] = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._serve, name="bodyfit-synth", daemon=True)
        self._thread.start()

    def submit(self, shape: np.ndarray, coordinates: np.ndarray, root: np.ndarray) -> Future[Outputs]:
        """Queue validated float32 inputs (B, n_shape), (B, n_dof), (B, 3); the future gives the outputs."""
        item = _Item(shape, coordinates, root)
        self._queue.put(item)
        return item.future

    def run(self, shape: np.ndarray, coordinates: np.ndarray, root: np.ndarray) -> Outputs:
        """One call, bypassing the queue (for batches that are already large)."""
        vertices, joints = self.session.run(None, {"shape": shape, "coordinates": coordinates, "root": root})
        return vertices, joints

    def close(self) -> None:
        """Stop the worker once the queued requests are served."""
        self._queue.put(None)

    def _serve(self) -> None:
        while True:
            first = self._queue.get()
            if first is None:
                return
            items = [first]
            bodies = len(first.shape)
            while bodies < self.max_bodies:
                try:
                    nxt = self._queue.get_nowait()
                except queue.Empty:
                    break
                if nxt is None:
                    self._queue.put(None)  # stop after this batch
                    break
                items.append(nxt)
                bodies += len(nxt.shape)
            self._run_batch(items)

    def _run_batch(self, items: list[_Item]) -> None:
        live = [it for it in items if it.future.set_running_or_notify_cancel()]
        if not live:
            return
        try:
            if len(live) == 1:
                it = live[0]
                out = self.run(it.shape, it.coordinates, it.root)
                it.future.set_result(out)
                return
            vertices, joints = self.run(
                np.concatenate([it.shape for it in live]),
                np.concatenate([it.coordinates for it in live]),
                np.concatenate([it.root for it in live]),
            )
        except Exception as exc:  # handed to every caller of the batch
            for it in live:
                if not it.future.done():
                    it.future.set_exception(exc)
            return
        start = 0
        for it in live:
            stop = start + len(it.shape)
            it.future.set_result((vertices[start:stop], joints[start:stop]))
            start = stop

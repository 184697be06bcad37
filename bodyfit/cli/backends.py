"""Where a batch upgrade runs: the SDK against a server, the service in this process (``local``: needs the
``server`` extra) or a pool of Ray actors each holding one loaded model (``ray``: needs the ``ray`` extra).

Each back-end is an :class:`~bodyfit.clients.batch.Upgrader` (a sequence file in, its output files out),
which :func:`bodyfit.clients.batch.batch_upgrade` runs ``concurrency`` at a time. The in-process back-ends
live beside the command line rather than in the SDK because they import the service and the models.
"""

from __future__ import annotations

import os
import queue
from pathlib import Path
from typing import Any

from bodyfit.clients.batch import Files, Upgrader, server_upgrader


class LocalUpgrader:
    """Upgrades in this process: the body model and fitters are loaded once (``server`` extra). Path (a)
    with the SMPL-family model file ``smpl_model`` (default $BODYFIT_SMPL_MODEL; a path that does not exist
    is an error), else path (b) from the joint rotations (each result's notes say which ran)."""

    def __init__(self, smpl_model: str | os.PathLike[str] | None = None) -> None:
        from bodyfit.models.upgrade.smpl_model import ENV_VAR, model_path
        from bodyfit.service.core import BodyService
        from bodyfit.service.limits import Limits

        given = smpl_model or os.environ.get(ENV_VAR)
        limits = Limits(max_concurrent=os.cpu_count() or 1, max_frames=10**7, max_upload_bytes=2**40)
        self.service = BodyService.load(limits=limits, smpl_model=model_path(given) if given else None)

    def __call__(self, path: Path) -> Files:
        from bodyfit.io.smpl import read_smpl_sequence

        result = self.service.upgrade(read_smpl_sequence(path))
        return self.service.upgrade_files(result, path.stem)


class RayWorker:
    """One Ray actor's state: a :class:`LocalUpgrader`. A failure comes back as its message, so that one bad
    sequence never takes the actor down."""

    def __init__(self, smpl_model: str | None) -> None:
        self.upgrade = LocalUpgrader(smpl_model)

    def run(self, path: str) -> Files | str:
        try:
            return self.upgrade(Path(path))
        except Exception as exc:  # reported per file
            return f"{type(exc).__name__}: {exc}"


class RayUpgrader:
    """Upgrades on ``concurrency`` Ray actors (a local Ray when ``address`` is None, else the cluster at
    ``ray://host:port``); each call takes an idle actor, waits for its result and gives the actor back, so
    ``concurrency`` calls at once keep every actor busy."""

    def __init__(
        self, address: str | None, concurrency: int, smpl_model: str | os.PathLike[str] | None = None
    ) -> None:
        import ray

        from bodyfit.models.upgrade.smpl_model import ENV_VAR, model_path

        if not ray.is_initialized():
            ray.init(address=address, ignore_reinit_error=True, log_to_driver=False)
        given = smpl_model or os.environ.get(ENV_VAR)
        model_file = str(model_path(given)) if given else None
        actor: Any = ray.remote(RayWorker)
        self._idle: queue.Queue[Any] = queue.Queue()
        for _ in range(concurrency):
            self._idle.put(actor.remote(model_file))

    def __call__(self, path: Path) -> Files:
        import ray

        actor = self._idle.get()
        try:
            outcome = ray.get(actor.run.remote(str(path)))
        finally:
            self._idle.put(actor)
        if isinstance(outcome, str):
            raise RuntimeError(outcome)
        return outcome


def upgrader(
    backend: str, concurrency: int = 1, smpl_model: str | os.PathLike[str] | None = None
) -> Upgrader:
    """The back-end named ``backend``: ``local``, ``ray``, ``ray://host:port`` or a server URL
    (``http://host:8000``; the server uses its own model file, so ``smpl_model`` is for the others).

    Raises:
        ValueError: any other name.
    """
    if backend == "local":
        return LocalUpgrader(smpl_model)
    if backend == "ray" or backend.startswith("ray://"):
        return RayUpgrader(None if backend == "ray" else backend, concurrency, smpl_model)
    if backend.startswith(("http://", "https://")):
        return server_upgrader(backend)
    raise ValueError(
        f"unknown backend {backend!r}: give local, ray, ray://host:port or a server URL (http://host:8000)"
    )

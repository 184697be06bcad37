"""Where a batch upgrade or batch fit runs: the SDK against a server, the service in this process
(``local``: needs the ``server`` extra) or a pool of Ray actors each holding one loaded model (``ray``: needs
the ``ray`` extra).

Each back-end is a :class:`~bodyfit.clients.batch.Worker` (a sequence or scan file in, its output files
out), which :func:`bodyfit.clients.batch.batch_upgrade` and :func:`bodyfit.clients.batch_fit.batch_fit` run
``concurrency`` at a time. The in-process back-ends live beside the command line rather than in the SDK
because they import the service and the models.
"""

from __future__ import annotations

import functools
import os
import queue
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from bodyfit.clients.batch import Files, Upgrader, Worker, server_upgrader
from bodyfit.clients.batch_fit import fit_files, server_fitter

if TYPE_CHECKING:
    from bodyfit.service.hints import ScanHints


class LocalUpgrader:
    """Upgrades in this process: the body model and fitters are loaded once (``server`` extra). Path (a)
    with the SMPL-family model file ``smpl_model`` (default $BODYFIT_SMPL_MODEL; a path that does not exist
    is an error), else path (b) from the joint rotations (each result's notes say which ran); with
    ``subject`` (a subject file's bytes), every sequence as that person's body.

    Raises:
        InvalidInputError: a subject file that cannot be used with this model.
    """

    def __init__(
        self, smpl_model: str | os.PathLike[str] | None = None, subject: bytes | None = None
    ) -> None:
        from bodyfit.models.upgrade.smpl_model import ENV_VAR, model_path
        from bodyfit.service.core import BodyService
        from bodyfit.service.limits import Limits

        given = smpl_model or os.environ.get(ENV_VAR)
        limits = Limits(max_concurrent=os.cpu_count() or 1, max_frames=10**7, max_upload_bytes=2**40)
        self.service = BodyService.load(limits=limits, smpl_model=model_path(given) if given else None)
        self.body = None if subject is None else self.service.subject_body(subject)

    def __call__(self, path: Path) -> Files:
        from bodyfit.io.smpl import read_smpl_sequence

        result = self.service.upgrade(read_smpl_sequence(path), body=self.body)
        return self.service.upgrade_files(result, path.stem)


class LocalFitter:
    """Fits scans in this process: the body model is loaded once (``server`` extra); every scan is read in
    ``units`` (auto, m or mm; NaN and infinite points dropped) and fitted with the same ``hints``."""

    def __init__(self, units: str = "auto", hints: ScanHints | None = None) -> None:
        from bodyfit.service.core import BodyService

        self.service = BodyService.load(fitters=False)
        self.units, self.hints = units, hints

    def __call__(self, path: Path) -> Files:
        from bodyfit.io.scans import load_scan
        from bodyfit.service.jobs import Job

        fit = self.service.fit_mesh(load_scan(path, units=self.units, drop_nonfinite=True), Job(), self.hints)
        model = self.service.model
        report = fit.report.to_dict()
        return fit_files(
            path.name, fit.fitted_as, fit.arrays(), model.dof_names, model.joint_names, report, model.faces
        )


class RayWorker:
    """One Ray actor's state: the worker ``make()`` builds (a :class:`LocalUpgrader` or :class:`LocalFitter`,
    loaded once). A failure comes back as its message, so that one bad input never takes the actor down."""

    def __init__(self, make: Callable[[], Worker]) -> None:
        self.work = make()

    def run(self, path: str) -> Files | str:
        try:
            return self.work(Path(path))
        except Exception as exc:  # reported per file
            return f"{type(exc).__name__}: {exc}"


class RayPool:
    """Runs a worker on ``concurrency`` Ray actors (a local Ray when ``address`` is None, else the cluster
    at ``ray://host:port``), each built by ``make``; each call takes an idle actor, waits for its result and
    gives the actor back, so ``concurrency`` calls at once keep every actor busy."""

    def __init__(self, address: str | None, concurrency: int, make: Callable[[], Worker]) -> None:
        import ray

        if not ray.is_initialized():
            ray.init(address=address, ignore_reinit_error=True, log_to_driver=False)
        actor: Any = ray.remote(RayWorker)
        self._idle: queue.Queue[Any] = queue.Queue()
        for _ in range(concurrency):
            self._idle.put(actor.remote(make))

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


def _ray_address(backend: str) -> str | None:
    return None if backend == "ray" else backend


def _is_ray(backend: str) -> bool:
    return backend == "ray" or backend.startswith("ray://")


def upgrader(
    backend: str,
    concurrency: int = 1,
    smpl_model: str | os.PathLike[str] | None = None,
    subject: bytes | None = None,
) -> Upgrader:
    """The back-end named ``backend``: ``local``, ``ray``, ``ray://host:port`` or a server URL
    (``http://host:8000``; the server uses its own model file, so ``smpl_model`` is for the others);
    ``subject``: the subject file's bytes of the person every sequence shows, or None.

    Raises:
        ValueError: any other name.
    """
    if backend == "local":
        return LocalUpgrader(smpl_model, subject)
    if _is_ray(backend):
        from bodyfit.models.upgrade.smpl_model import ENV_VAR, model_path

        given = smpl_model or os.environ.get(ENV_VAR)
        model_file = str(model_path(given)) if given else None
        make = functools.partial(LocalUpgrader, model_file, subject)
        return RayPool(_ray_address(backend), concurrency, make)
    if backend.startswith(("http://", "https://")):
        return server_upgrader(backend, subject=subject)
    raise ValueError(
        f"unknown backend {backend!r}: give local, ray, ray://host:port or a server URL (http://host:8000)"
    )


def fitter(backend: str, concurrency: int = 1, units: str = "auto", hints: ScanHints | None = None) -> Worker:
    """The scan-fitting back-end named ``backend``: ``local``, ``ray``, ``ray://host:port`` or a server URL
    (``http://host:8000``), every scan read in ``units`` and fitted with ``hints``.

    Raises:
        ValueError: any other name.
    """
    if backend == "local":
        return LocalFitter(units, hints)
    if _is_ray(backend):
        return RayPool(_ray_address(backend), concurrency, functools.partial(LocalFitter, units, hints))
    if backend.startswith(("http://", "https://")):
        given = {} if hints is None else {k: v for k, v in hints.values().items() if v is not None}
        return server_fitter(backend, units=units, **given)
    raise ValueError(
        f"unknown backend {backend!r}: give local, ray, ray://host:port or a server URL (http://host:8000)"
    )

"""Batch upgrades of AMASS-style dataset trees: resumable, concurrent, one failure never stops the rest.

``batch_upgrade(dataset_dir, out_dir, concurrency=N, backend=...)`` walks ``dataset_dir`` for ``*.npz``
sequences (AMASS's per-subject ``shape.npz`` files are not sequences and are skipped), upgrades each one
and writes ``<out_dir>/<same relative path>.{npz,json,osim,mot}``. A sequence whose ``.json`` exists is
finished (the JSON is written last, after the other files are in place) and is skipped, so an interrupted
run resumes where it stopped. Back-ends:

* a server URL (``"http://host:8000"``): the REST SDK, ``concurrency`` requests at once;
* ``"local"``: in this process (needs the ``server`` extra); path (a) with an SMPL-family model file
  (``smpl_model`` or $BODYFIT_SMPL_MODEL), else path (b) from the joint rotations, as ``bodyfit upgrade``
  and the server choose;
* ``"ray"`` / ``"ray://host:10001"``: a pool of ``concurrency`` Ray actors, each holding one loaded
  model (needs the ``ray`` extra; ``ray`` alone starts a local Ray).
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from tqdm import tqdm

from bodyfit.clients.errors import BodyfitClientError

Files = dict[str, bytes]
SKIPPED_NAMES = ("shape.npz",)
ORDER = ("npz", "osim", "mot", "json")  # the JSON last: its presence marks a finished sequence


class Upgrader(Protocol):
    """Upgrades one sequence file to its output files (npz, json, osim, mot as bytes)."""

    def __call__(self, path: Path) -> Files: ...


@dataclass
class BatchReport:
    """done / skipped: sequences (relative paths) upgraded now / found finished; failed: path -> why."""

    done: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    failed: dict[str, str] = field(default_factory=dict)
    seconds: float = 0.0

    def summary(self) -> str:
        return (
            f"{len(self.done)} upgraded, {len(self.skipped)} already done, {len(self.failed)} failed "
            f"in {self.seconds:.1f} s"
        )


def find_sequences(dataset_dir: Path) -> list[Path]:
    """Every ``*.npz`` under ``dataset_dir`` except AMASS's ``shape.npz``, sorted."""
    return sorted(p for p in dataset_dir.rglob("*.npz") if p.name not in SKIPPED_NAMES)


def output_base(dataset_dir: Path, out_dir: Path, path: Path) -> Path:
    return out_dir / path.relative_to(dataset_dir).with_suffix("")


def write_outputs(base: Path, files: Files) -> None:
    """Write each file atomically (temporary name, then rename), the JSON last."""
    base.parent.mkdir(parents=True, exist_ok=True)
    for ext in sorted(files, key=lambda e: ORDER.index(e) if e in ORDER else -1):
        target = base.with_suffix(f".{ext}")
        tmp = target.with_suffix(f".{ext}.part")
        tmp.write_bytes(files[ext])
        os.replace(tmp, target)


def server_upgrader(url: str, timeout: float = 600.0) -> Upgrader:
    """Upgrades through a bodyfit server's REST API."""
    import httpx

    from bodyfit.clients.rest_client import Client

    client = Client(url, timeout=httpx.Timeout(30.0, read=timeout))

    def upgrade(path: Path) -> Files:
        return client.upgrade(path).files

    return upgrade


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


def _ray_upgrades(
    paths: list[Path], address: str | None, concurrency: int, smpl_model: str | os.PathLike[str] | None
) -> Iterator[tuple[Path, Files | BaseException]]:
    import ray
    from ray.util import ActorPool

    from bodyfit.models.upgrade.smpl_model import ENV_VAR, model_path

    if not ray.is_initialized():
        ray.init(address=address, ignore_reinit_error=True, log_to_driver=False)
    given = smpl_model or os.environ.get(ENV_VAR)
    model_file = str(model_path(given)) if given else None

    @ray.remote
    class Worker:
        def __init__(self) -> None:
            self.upgrade = LocalUpgrader(model_file)

        def run(self, path: str) -> tuple[str, Files | str]:
            try:
                return path, self.upgrade(Path(path))
            except Exception as exc:  # reported per file
                return path, f"{type(exc).__name__}: {exc}"

    pool = ActorPool([Worker.remote() for _ in range(concurrency)])  # type: ignore[attr-defined]
    for path, outcome in pool.map_unordered(lambda actor, p: actor.run.remote(str(p)), paths):
        yield Path(path), (RuntimeError(outcome) if isinstance(outcome, str) else outcome)


def _thread_upgrades(
    paths: list[Path], upgrader: Upgrader, concurrency: int
) -> Iterator[tuple[Path, Files | BaseException]]:
    with ThreadPoolExecutor(max(1, concurrency)) as pool:
        futures = {pool.submit(upgrader, p): p for p in paths}
        for future in as_completed(futures):
            try:
                yield futures[future], future.result()
            except Exception as exc:  # reported per file, the batch goes on
                yield futures[future], exc


def batch_upgrade(
    dataset_dir: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    concurrency: int = 1,
    backend: str | Upgrader = "local",
    smpl_model: str | os.PathLike[str] | None = None,
    progress: bool = True,
) -> BatchReport:
    """Upgrade every sequence under ``dataset_dir`` into ``out_dir`` (see the module docstring).

    Args:
        concurrency: sequences in flight at once (requests, threads or Ray actors).
        backend: a server URL, "local", "ray" / "ray://host:port", or any :class:`Upgrader` callable.
        smpl_model: the SMPL-family model file for "local" and "ray" (default $BODYFIT_SMPL_MODEL); a server
            uses its own.
        progress: show a tqdm bar.
    """
    began = time.perf_counter()
    root, out = Path(dataset_dir), Path(out_dir)
    if not root.is_dir():
        raise FileNotFoundError(f"{root} is not a folder of .npz sequences")
    report = BatchReport()
    todo = []
    for path in find_sequences(root):
        rel = str(path.relative_to(root))
        if output_base(root, out, path).with_suffix(".json").exists():
            report.skipped.append(rel)
        else:
            todo.append(path)
    results: Iterable[tuple[Path, Files | BaseException]]
    if isinstance(backend, str) and backend.startswith("ray"):
        address = None if backend == "ray" else backend
        results = _ray_upgrades(todo, address, concurrency, smpl_model)
    elif isinstance(backend, str):
        upgrader = LocalUpgrader(smpl_model) if backend == "local" else server_upgrader(backend)
        results = _thread_upgrades(todo, upgrader, concurrency)
    else:
        results = _thread_upgrades(todo, backend, concurrency)
    bar: Any = tqdm(total=len(todo), unit="seq", disable=not progress)
    for path, outcome in results:
        rel = str(path.relative_to(root))
        if isinstance(outcome, BaseException):
            report.failed[rel] = _message(outcome)
        else:
            write_outputs(output_base(root, out, path), outcome)
            report.done.append(rel)
        bar.update(1)
        bar.set_postfix(failed=len(report.failed))
    bar.close()
    report.seconds = time.perf_counter() - began
    return report


def _message(exc: BaseException) -> str:
    if isinstance(exc, BodyfitClientError):
        return str(exc)
    return f"{type(exc).__name__}: {exc}"

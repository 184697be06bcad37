"""Batch upgrades of AMASS-style dataset trees: resumable, concurrent, one failure never stops the rest.

``batch_upgrade(dataset_dir, out_dir, concurrency=N, backend=...)`` walks ``dataset_dir`` for ``*.npz``
sequences (AMASS's per-subject ``shape.npz`` files are not sequences and are skipped), upgrades each one
and writes ``<out_dir>/<same relative path>.{npz,json,osim,mot}``. A sequence whose ``.json`` exists is
finished (the JSON is written last, after the other files are in place) and is skipped, so an interrupted
run resumes where it stopped. The back-end is a server URL (``"http://host:8000"``: the REST SDK,
``concurrency`` requests at once) or any :class:`Upgrader`.

Upgrading in this process or on Ray needs the service and the models, which the SDK does not import:
those back-ends are :func:`bodyfit.cli.backends.upgrader` (``"local"``, ``"ray"``, ``"ray://host:10001"``),
as ``bodyfit batch-upgrade --backend`` runs them. Deprecated: ``backend="local"`` / ``"ray"`` here, and
``LocalUpgrader`` from this module, still reach them; they will be removed in the next release.
"""

from __future__ import annotations

import os
import time
import warnings
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from tqdm import tqdm

from bodyfit.clients.errors import BodyfitClientError
from bodyfit.clients.uploads import SubjectInput, subject_upload

Files = dict[str, bytes]
SKIPPED_NAMES = ("shape.npz",)
ORDER = ("npz", "osim", "mot", "json")  # the JSON last: its presence marks a finished sequence


class Worker(Protocol):
    """Processes one input file into its output files (extension -> bytes; a ``json`` among them is written
    last and marks the input finished)."""

    def __call__(self, path: Path) -> Files: ...


Upgrader = Worker
"""Upgrades one sequence file to its output files (npz, json, osim, mot as bytes)."""


@dataclass
class BatchReport:
    """done / skipped: inputs (relative paths) processed now / found finished; failed: path -> why;
    ``verb`` names what was done to each (upgraded, fitted) in :meth:`summary`."""

    done: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    failed: dict[str, str] = field(default_factory=dict)
    seconds: float = 0.0
    verb: str = "upgraded"

    def summary(self) -> str:
        return (
            f"{len(self.done)} {self.verb}, {len(self.skipped)} already done, {len(self.failed)} failed "
            f"in {self.seconds:.1f} s"
        )


def find_sequences(dataset_dir: Path) -> list[Path]:
    """Every ``*.npz`` under ``dataset_dir`` except AMASS's ``shape.npz``, sorted."""
    return sorted(p for p in dataset_dir.rglob("*.npz") if p.name not in SKIPPED_NAMES)


def output_base(dataset_dir: Path, out_dir: Path, path: Path) -> Path:
    """``out_dir`` / the input's relative path without its extension."""
    return out_dir / path.relative_to(dataset_dir).with_suffix("")


def output_file(base: Path, ext: str) -> Path:
    """``base`` with ``.ext`` appended (not :meth:`Path.with_suffix`, which would cut a stem that holds a
    dot: walk.01 -> walk.json)."""
    return base.with_name(f"{base.name}.{ext}")


def write_outputs(base: Path, files: Files) -> None:
    """Write each file atomically (temporary name, then rename), the JSON last."""
    base.parent.mkdir(parents=True, exist_ok=True)
    for ext in sorted(files, key=lambda e: ORDER.index(e) if e in ORDER else -1):
        target = output_file(base, ext)
        tmp = output_file(base, f"{ext}.part")
        tmp.write_bytes(files[ext])
        os.replace(tmp, target)


def server_upgrader(
    url: str, timeout: float = 600.0, up: str | None = None, subject: SubjectInput | None = None
) -> Upgrader:
    """Upgrades through a bodyfit server's REST API; ``up``: every sequence's up axis (None: detected per
    sequence, see :func:`bodyfit.clients.core.operations.upgrade`); ``subject``: the subject file of the
    person every sequence shows (None: each sequence's own body)."""
    import httpx

    from bodyfit.clients.rest_client import Client

    client = Client(url, timeout=httpx.Timeout(30.0, read=timeout))
    person = subject_upload(subject)

    def upgrade(path: Path) -> Files:
        return client.upgrade(path, up=up, subject=person).files

    return upgrade


def _threads(
    paths: list[Path], worker: Worker, concurrency: int
) -> Iterator[tuple[Path, Files | BaseException]]:
    with ThreadPoolExecutor(max(1, concurrency)) as pool:
        futures = {pool.submit(worker, p): p for p in paths}
        for future in as_completed(futures):
            try:
                yield futures[future], future.result()
            except Exception as exc:  # reported per file, the batch goes on
                yield futures[future], exc


def batch_upgrade(
    dataset_dir: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    concurrency: int = 1,
    backend: str | Upgrader = "http://127.0.0.1:8000",
    smpl_model: str | os.PathLike[str] | None = None,
    progress: bool = True,
    up: str | None = None,
    subject: SubjectInput | None = None,
) -> BatchReport:
    """Upgrade every sequence under ``dataset_dir`` into ``out_dir`` (see the module docstring).

    Args:
        concurrency: sequences in flight at once (requests or threads).
        backend: a server URL (default: a server on this machine, as ``bodyfit serve`` starts it, the
            same default as ``batch_fit``) or any :class:`Upgrader` callable (``"local"`` and ``"ray"``:
            deprecated, see the module docstring).
        smpl_model: the SMPL-family model file of the deprecated in-process back-ends (default
            $BODYFIT_SMPL_MODEL); a server uses its own.
        progress: show a tqdm bar.
        up: the sequences' up axis (+x, -x, +y, -y, +z or -z) for a server URL back-end; None: each
            sequence's is detected from its motion (AMASS's Z-up needs nothing).
        subject: for a server URL back-end, the subject file of the one person every sequence shows (a
            path, bytes, a ``Subject`` or ``build_subject``'s result; see ``upgrade(subject=)``).

    Raises:
        ValueError: ``up`` or ``subject`` with a back-end that cannot take it (give the server URL, or an
            :class:`Upgrader` that applies it).
    """
    root = Path(dataset_dir)
    if not root.is_dir():
        raise FileNotFoundError(f"{root} is not a folder of .npz sequences")
    served = isinstance(backend, str) and backend.startswith(("http://", "https://"))
    if (up is not None or subject is not None) and not served:
        raise ValueError(
            "batch_upgrade(up=..., subject=...) needs a server URL back-end; an Upgrader applies its own"
        )
    if isinstance(backend, str):
        upgrader = _resolve(backend, concurrency, smpl_model, up, subject)
    else:
        upgrader = backend
    return run_batch(root, Path(out_dir), find_sequences(root), upgrader, concurrency, progress, "seq")


def run_batch(
    root: Path,
    out: Path,
    inputs: list[Path],
    worker: Worker,
    concurrency: int = 1,
    progress: bool = True,
    unit: str = "seq",
    verb: str = "upgraded",
) -> BatchReport:
    """Run ``worker`` on each of ``inputs`` (files under ``root``), ``concurrency`` at a time on threads,
    and write each one's files to ``out/<relative path>.<ext>`` (:func:`write_outputs`). An input whose
    ``.json`` exists is finished and skipped (resume); a failure is recorded with its message and the batch
    goes on. ``progress``: a tqdm bar counting ``unit``."""
    began = time.perf_counter()
    report = BatchReport(verb=verb)
    todo = []
    for path in inputs:
        if output_file(output_base(root, out, path), "json").exists():
            report.skipped.append(str(path.relative_to(root)))
        else:
            todo.append(path)
    bar: Any = tqdm(total=len(todo), unit=unit, disable=not progress)
    for path, outcome in _threads(todo, worker, concurrency):
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


def _resolve(
    backend: str,
    concurrency: int,
    smpl_model: str | os.PathLike[str] | None,
    up: str | None = None,
    subject: SubjectInput | None = None,
) -> Upgrader:
    """A server URL's :func:`server_upgrader`; the deprecated in-process names through
    :func:`bodyfit.cli.backends.upgrader`, with a :class:`DeprecationWarning`."""
    if backend.startswith(("http://", "https://")):
        return server_upgrader(backend, up=up, subject=subject)
    warnings.warn(
        f"batch_upgrade(backend={backend!r}) from bodyfit.clients.batch is deprecated and will be removed in "
        "the next release: pass backend=bodyfit.cli.backends.upgrader(name, concurrency, smpl_model)",
        DeprecationWarning,
        stacklevel=3,
    )
    from bodyfit.cli.backends import upgrader  # deprecated bridge, removed in the next release

    return upgrader(backend, concurrency, smpl_model)


def __getattr__(name: str) -> Any:
    """``LocalUpgrader`` moved to :mod:`bodyfit.cli.backends` (deprecated here; removed in the next
    release)."""
    if name == "LocalUpgrader":
        from bodyfit.cli.backends import LocalUpgrader  # deprecated bridge, removed in the next release

        return LocalUpgrader
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _message(exc: BaseException) -> str:
    if isinstance(exc, BodyfitClientError):
        return str(exc)
    return f"{type(exc).__name__}: {exc}"

"""``bodyfit grow-space``: grow the body model's shape space from a folder of raw scans (BLiSS) and write it
as a complete asset folder (:mod:`bodyfit.models.spaces`).

The scans are fitted once through the batch engine (``bodyfit batch-fit``: in this process, on a server or on
Ray; resumable, failures listed), into ``--fits`` (default ``<out>.fits`` beside the output). Every round then
runs in this process: it keeps each scan's fitted pose, re-projects the shape into the current space, refines
the registration non-rigidly and accepts the closest ones, as BLiSS does.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from bodyfit.cli.common import fail, note, reported

if TYPE_CHECKING:
    from bodyfit.clients.batch import Worker
    from bodyfit.models.body.model import BodyModel
    from bodyfit.models.spaces.population import Population
    from bodyfit.models.spaces.register import PosedScan

BACKEND_HELP = "Where the scans are fitted: local, a server URL (http://host:8000), ray, or ray://host:10001."


def fit_folder(
    folder: Path, fits: Path, worker: Worker, concurrency: int, units: str, kind: str
) -> list[PosedScan]:
    """Fit every scan under ``folder`` into ``fits`` through the batch engine and read them back with their
    fits (failures listed on standard error and left out).

    Raises:
        ValueError: no scan could be fitted.
    """
    from bodyfit.clients.batch_fit import batch_fit, find_scans
    from bodyfit.models.spaces.register import read_fit

    report = batch_fit(folder, fits, concurrency, worker, progress=True)
    for failed, why in sorted(report.failed.items()):
        note(f"FAILED {failed}: {why}")
    scans = []
    for path in find_scans(folder):
        fit = fits / path.relative_to(folder).with_suffix(".npz")
        if fit.is_file() and (fit.with_suffix(".json")).is_file():
            scans.append(read_fit(path, fit, units))
    if not scans:
        raise ValueError(f"no {kind} under {folder} could be fitted")
    note(f"{kind}: {len(scans)} fitted ({report.summary()})")
    return scans


def grow_space(
    scans: Annotated[
        Path,
        typer.Argument(
            exists=True, file_okay=False, help="Folder of raw scans (ply, obj, stl, pcd, npz; recursive)."
        ),
    ],
    out: Annotated[Path, typer.Option("--out", help="New asset folder for the grown space.")],
    seed_registrations: Annotated[
        Path | None,
        typer.Option(
            exists=True,
            file_okay=False,
            help="Folder of meshes already registered in the body model's topology, added as they are.",
        ),
    ] = None,
    backend: Annotated[str, typer.Option(help=BACKEND_HELP)] = "local",
    rounds: Annotated[int, typer.Option(min=1, help="The most rounds.")] = 5,
    concurrency: Annotated[int, typer.Option(min=1, help="Scans fitted at once.")] = 1,
    units: Annotated[str, typer.Option(help="Unit of every scan's coordinates: auto, m or mm.")] = "auto",
    population: Annotated[
        int, typer.Option(min=0, help="Bodies sampled from the current space, which it keeps explaining.")
    ] = 200,
    max_chamfer_mm: Annotated[
        float, typer.Option(min=0.0, help="Registrations further from their scan are never accepted.")
    ] = 12.0,
    fits: Annotated[
        Path | None, typer.Option(help="Folder of the first fits (default: <out>.fits); reruns resume.")
    ] = None,
) -> None:
    """Grow the shape space from SCANS and write it to --out: body.npz, body.onnx, the unchanged assets and a
    hash-checked manifest (load it with `bodyfit serve --assets OUT`), plus grow_report.json (per round:
    accepted scans, Chamfer distances)."""
    from bodyfit.cli.backends import fitter
    from bodyfit.models.assets import assets_dir
    from bodyfit.models.body.model import BodyModel
    from bodyfit.models.spaces.grow import GrowConfig
    from bodyfit.models.spaces.grow import grow_space as grow
    from bodyfit.models.spaces.writer import REPORT, check_destination, write_space

    source = assets_dir()
    fits = fits or out.with_name(out.name + ".fits")
    with reported():
        check_destination(source, out)
        model = BodyModel.load(source)
        worker = fitter(backend, concurrency, units)
        raw = fit_folder(scans, fits / "scans", worker, concurrency, units, "scans")
        seeds = _seeds(model, seed_registrations, fits, worker, concurrency, units)
        config = GrowConfig(rounds=rounds, n_population=population, max_chamfer_mm=max_chamfer_mm)
        result = grow(model, raw, config, seeds, log=note)
        report = result.report()
        write_space(source, out, model, result.data, report)
    if not result.accepted:
        fail(f"no registration was accepted (all over {max_chamfer_mm} mm from their scans); nothing grew")
    typer.echo(json.dumps({"out": str(out), "report": str(out / REPORT), **_totals(report)}))


def _seeds(
    model: BodyModel, folder: Path | None, fits: Path, worker: Worker, concurrency: int, units: str
) -> Population | None:
    """The seed registrations under ``folder`` as a population (None without a folder)."""
    from bodyfit.models.spaces.population import Population
    from bodyfit.models.spaces.register import seed_registrations

    if folder is None:
        return None
    meshes = fit_folder(folder, fits / "seeds", worker, concurrency, units, "seed registrations")
    return Population(*seed_registrations(model, meshes))


def _totals(report: dict[str, object]) -> dict[str, object]:
    return {k: report[k] for k in ("n_rounds", "n_accepted")}

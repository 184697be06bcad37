"""``bodyfit measure``: the anthropometric measurements of bodies in a parameters file, or a body built
from measurements (docs/anthropometry.md), computed in this process."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any

import typer

from bodyfit.cli.common import ASSETS_HELP, fail, reported


def measure(
    params: Annotated[
        Path | None,
        typer.Argument(
            help="Parameters .npz holding `shape`: (B, n_shape) or (n_shape,) coefficients in population "
            "standard deviations (a fit's fit.npz, a synth .npz); measured in the measuring posture."
        ),
    ] = None,
    set_: Annotated[
        list[str] | None,
        typer.Option(
            "--set",
            "-s",
            help="NAME=VALUE: build a body from measurements instead, in metres (kilograms for mass), e.g. "
            "-s stature=1.8 -s mass=80 -s waist=0.9; repeat for more.",
        ),
    ] = None,
    sex: Annotated[
        str | None,
        typer.Option(help="male or female: the plausible ranges and the prior of a body built with --set."),
    ] = None,
    out: Annotated[
        Path | None,
        typer.Option(help="With --set: write the built body's `shape` (standard deviations) to this .npz."),
    ] = None,
    as_json: Annotated[
        bool,
        typer.Option(
            "--json", help="Print one JSON object (metres, kilograms) instead of a table in mm and kg."
        ),
    ] = False,
    assets: Annotated[Path | None, typer.Option(help=ASSETS_HELP)] = None,
) -> None:
    """Measure bodies (stature, mass, circumferences, lengths: ANSUR II names), or build one from
    measurements and print what it achieved."""
    if (params is None) == (not set_):
        fail("give a parameters .npz to measure, or --set NAME=VALUE to build a body (not both)")
    with reported():
        from bodyfit.models.body.model import BodyModel

        model = BodyModel.load(assets)
        if params is not None:
            values = _measure_file(model, params)
            _print(values, None, as_json)
            return
        result = _build(model, set_ or [], sex)
        if out is not None:
            import numpy as np

            out.parent.mkdir(parents=True, exist_ok=True)
            np.savez_compressed(out, allow_pickle=False, shape=result.shape[None])
        _print({k: [v] for k, v in result.achieved.items()}, result, as_json)


def _measure_file(model: Any, path: Path) -> dict[str, list[float]]:
    import numpy as np

    from bodyfit.io.npz import FLOAT, ArraySpec, Dim, read_npz
    from bodyfit.models.anthropometry.measure import measure

    K = model.n_shape
    spec = ArraySpec(((Dim("B"), K), (K,)), FLOAT, hint=f"{K} shape coefficients per body")
    shape = np.asarray(read_npz(path, {"shape": spec})["shape"], np.float64)
    return {k: v.tolist() for k, v in measure(model, shape.reshape(-1, K)).items()}


def _build(model: Any, items: list[str], sex: str | None) -> Any:
    from bodyfit.models.anthropometry.inverse import shape_from_measurements

    try:
        wanted = {k.strip(): float(v) for k, v in (item.split("=", 1) for item in items)}
    except ValueError as exc:
        fail(f"{exc}; write measurements as NAME=VALUE, e.g. stature=1.8")
    return shape_from_measurements(model, wanted, sex=sex)


def _print(values: dict[str, list[float]], built: Any, as_json: bool) -> None:
    """The measurements as JSON (SI units) or as a table in millimetres and kilograms."""
    from bodyfit.models.anthropometry.definitions import MEASUREMENTS

    if as_json:
        doc: dict[str, Any] = {"measurements": values}
        if built is not None:
            doc.update(shape=built.shape.tolist(), residuals=built.residuals, unmet=built.unmet)
        typer.echo(json.dumps(doc))
        return
    for name, row in values.items():
        kg = MEASUREMENTS[name].unit == "kg"
        cells = "  ".join(f"{v:9.2f}" if kg else f"{v * 1000:9.1f}" for v in row)
        residual = ""
        if built is not None and name in built.residuals:
            r = built.residuals[name]
            residual = f"   (asked {row[0] - r:.2f} kg)" if kg else f"   (asked {(row[0] - r) * 1000:.1f} mm)"
        typer.echo(f"{name:>32} {'kg' if kg else 'mm'} {cells}{residual}")
    if built is not None and built.flagged:
        typer.echo(f"not all met within tolerance: {', '.join(built.unmet)}", err=True)

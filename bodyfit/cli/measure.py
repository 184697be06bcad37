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
    server: Annotated[
        str | None,
        typer.Option(help="Ask this bodyfit server (URL: POST /v1/measure) instead of computing locally."),
    ] = None,
) -> None:
    """Measure bodies (stature, mass, circumferences, lengths: ANSUR II names), or build one from
    measurements and print what it achieved."""
    if (params is None) == (not set_):
        fail("give a parameters .npz to measure, or --set NAME=VALUE to build a body (not both)")
    wanted = None if params is not None else _wanted(set_ or [])
    if server is not None:
        answer = _from_server(server, params, wanted, sex)
    else:
        with reported():
            answer = _computed(assets, params, wanted, sex)
    if out is not None and answer.shape is not None:
        import numpy as np

        out.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(out, allow_pickle=False, shape=np.asarray(answer.shape, np.float64))
    _print(answer, as_json)


def _wanted(items: list[str]) -> dict[str, float]:
    try:
        return {k.strip(): float(v) for k, v in (item.split("=", 1) for item in items)}
    except ValueError as exc:
        fail(f"{exc}; write measurements as NAME=VALUE, e.g. stature=1.8")


def _computed(
    assets: Path | None, params: Path | None, wanted: dict[str, float] | None, sex: str | None
) -> Any:
    """The :class:`~bodyfit.wire.measure.Measurements` computed in this process."""
    from bodyfit.models.anthropometry.definitions import MEASUREMENTS
    from bodyfit.models.anthropometry.inverse import shape_from_measurements
    from bodyfit.models.body.model import BodyModel
    from bodyfit.wire.measure import MeasurementInfo, Measurements

    model = BodyModel.load(assets)
    built = None
    if params is not None:
        values = _measure_file(model, params)
    else:
        built = shape_from_measurements(model, wanted or {}, sex=sex)
        values = {k: [v] for k, v in built.achieved.items()}
    infos = [MeasurementInfo(name=k, kind=MEASUREMENTS[k].kind, unit=MEASUREMENTS[k].unit) for k in values]
    if built is None:
        return Measurements(measurements=infos, values=values)
    return Measurements(
        measurements=infos,
        values=values,
        shape=[built.shape.tolist()],
        residuals=built.residuals,
        unmet=built.unmet,
        flagged=built.flagged,
    )


def _from_server(url: str, params: Path | None, wanted: dict[str, float] | None, sex: str | None) -> Any:
    """The :class:`~bodyfit.wire.measure.Measurements` of a server's REST API, through the SDK."""
    import numpy as np

    from bodyfit.clients.errors import BodyfitClientError
    from bodyfit.clients.rest_client import Client

    try:
        shape = None
        if params is not None:
            with np.load(params, allow_pickle=False) as archive:
                if "shape" not in archive:
                    fail(f"{params} holds no `shape` array; save the shape coefficients as `shape`")
                shape = np.asarray(archive["shape"], np.float64)
        with Client(url) as client:
            return client.measure(shape=shape, measurements=wanted, sex=sex)
    except (BodyfitClientError, OSError, ValueError) as exc:
        fail(exc)


def _measure_file(model: Any, path: Path) -> dict[str, list[float]]:
    import numpy as np

    from bodyfit.io.npz import FLOAT, ArraySpec, Dim, read_npz
    from bodyfit.models.anthropometry.measure import measure

    K = model.n_shape
    spec = ArraySpec(((Dim("B"), K), (K,)), FLOAT, hint=f"{K} shape coefficients per body")
    shape = np.asarray(read_npz(path, {"shape": spec})["shape"], np.float64)
    return {k: v.tolist() for k, v in measure(model, shape.reshape(-1, K)).items()}


def _print(answer: Any, as_json: bool) -> None:
    """The measurements (a :class:`~bodyfit.wire.measure.Measurements`) as JSON (SI units) or as a table in
    millimetres and kilograms."""
    built = answer.shape is not None
    if as_json:
        doc: dict[str, Any] = {"measurements": answer.values}
        if built:
            doc.update(shape=answer.shape[0], residuals=answer.residuals, unmet=answer.unmet)
        typer.echo(json.dumps(doc))
        return
    units = {m.name: m.unit for m in answer.measurements}
    residuals = answer.residuals or {}
    for name, row in answer.values.items():
        kg = units[name] == "kg"
        cells = "  ".join(f"{v:9.2f}" if kg else f"{v * 1000:9.1f}" for v in row)
        residual = ""
        if name in residuals:
            r = residuals[name]
            residual = f"   (asked {row[0] - r:.2f} kg)" if kg else f"   (asked {(row[0] - r) * 1000:.1f} mm)"
        typer.echo(f"{name:>32} {'kg' if kg else 'mm'} {cells}{residual}")
    if answer.flagged:
        typer.echo(f"not all met within tolerance: {', '.join(answer.unmet)}", err=True)

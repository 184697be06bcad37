"""``bodyfit synth``: one posed body, given by its shape coefficients or built from measurements
(docs/anthropometry.md), computed in this process or asked of a server through the SDK."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from bodyfit.cli.common import fail, reported

if TYPE_CHECKING:
    import numpy as np


def synth(
    out: Annotated[
        Path, typer.Argument(help="Output file: .npz, .ply, .obj, .glb or .json (positions in metres).")
    ],
    coordinate: Annotated[
        list[str] | None,
        typer.Option(
            "--coordinate",
            "-c",
            help="NAME=RADIANS: a joint coordinate in RADIANS (OpenSim's names; missing ones are 0), e.g. "
            "knee_angle_r=1.0; repeat for more.",
        ),
    ] = None,
    shape: Annotated[
        str | None,
        typer.Option(
            help="Comma-separated shape coefficients (bone, then identity) in population standard deviations "
            "(0: the population mean)."
        ),
    ] = None,
    measure: Annotated[
        list[str] | None,
        typer.Option(
            "--measure",
            "-m",
            help="NAME=VALUE: build the body from measurements instead of --shape, in metres (kilograms "
            "for mass), ANSUR II names or aliases, e.g. -m stature=1.80 -m mass=80 -m waist=0.85; repeat "
            "for more.",
        ),
    ] = None,
    sex: Annotated[
        str | None, typer.Option(help="male or female: the plausible ranges and prior of a --measure body.")
    ] = None,
    root: Annotated[str | None, typer.Option(help="Pelvis translation x,y,z in metres.")] = None,
    skeleton: Annotated[bool, typer.Option(help="Also write the posed bone mesh.")] = False,
    server: Annotated[
        str | None, typer.Option(help="Ask this bodyfit server (URL) instead of computing locally.")
    ] = None,
    subject: Annotated[
        Path | None,
        typer.Option(
            exists=True,
            dir_okay=False,
            help="A subject file (the subject.npz of `bodyfit rig`): the body is that person's, instead of "
            "--shape or --measure.",
        ),
    ] = None,
) -> None:
    """Synthesize one posed body and write it (format from the file suffix); a body built from --measure
    prints what it achieved beside what was asked."""
    import numpy as np

    fmt = out.suffix.lstrip(".").lower()
    if shape is not None and measure:
        fail("give --shape or --measure, not both: the body built from measurements has its own shape")
    if subject is not None and (shape is not None or measure):
        fail("give --subject or --shape / --measure, not both: the subject's body has its own shape")
    try:
        values = {k: float(v) for k, v in (item.split("=", 1) for item in coordinate or [])}
        wanted = {k.strip(): float(v) for k, v in (item.split("=", 1) for item in measure or [])} or None
        c = None if shape is None else np.array([[float(x) for x in shape.split(",")]])
        r = None if root is None else np.array([[float(x) for x in root.split(",")]])
    except ValueError as exc:
        fail(
            f"{exc}; write coordinates as -c NAME=RADIANS, measurements as -m NAME=VALUE (metres, kilograms) "
            "and arrays as comma-separated numbers"
        )
    built = None
    if server is not None:
        data, built = _from_server(server, fmt, c, values, r, skeleton, wanted, sex, subject)
    else:
        with reported():
            from bodyfit.service.core import BodyService, SynthRequest
            from bodyfit.service.formats import encode_bodies

            service = BodyService.load(fitters=False)
            person = None if subject is None else subject.read_bytes()
            asked = SynthRequest(c, values, r, skeleton, None, wanted, sex, person)
            request, built = service.with_built_shape(asked)
            data = encode_bodies(service.synthesize(request), fmt, faces=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_bytes(data)
    typer.echo(f"wrote {out} ({len(data):,} bytes)")
    if built is not None:
        _print_built(built)


def _print_built(built: Any) -> None:
    """Each requested measurement beside what the body achieved (mm, kg), and the unmet ones."""
    achieved = {k: v[0] for k, v in built.values.items()}
    for name, asked in (built.requested or {}).items():
        scale, unit = (1.0, "kg") if name == "weightkg" else (1000.0, "mm")
        typer.echo(
            f"{name:>32}: asked {asked * scale:8.1f} {unit}, built {achieved[name] * scale:8.1f} {unit}"
        )
    if built.flagged:
        typer.echo(f"not all met within tolerance: {', '.join(built.unmet)}", err=True)


def _from_server(
    url: str,
    fmt: str,
    shape: np.ndarray | None,
    coordinates: dict[str, float],
    root: np.ndarray | None,
    skeleton: bool,
    measurements: dict[str, float] | None,
    sex: str | None,
    subject: Path | None = None,
) -> tuple[bytes, Any]:
    """The body's file from a server's REST API, through the SDK, and for measurements what the build
    achieved (the SDK's synthesis arrays carry it; the file is then asked for with the built shape)."""
    import numpy as np

    from bodyfit.clients.errors import BodyfitClientError
    from bodyfit.clients.rest_client import Client

    try:
        with Client(url) as client:
            built = None
            if measurements is not None or sex is not None:
                built = client.synthesize(measurements=measurements, sex=sex).built
                shape = None if built is None else np.asarray(built.shape, np.float64)
            data = client.synthesize_file(
                fmt, shape=shape, coordinates=coordinates, root=root, skeleton=skeleton, subject=subject
            )
            return data, built
    except BodyfitClientError as exc:
        fail(exc)

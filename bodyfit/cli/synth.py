"""``bodyfit synth``: one posed body, computed in this process or asked of a server through the SDK."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

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
    root: Annotated[str | None, typer.Option(help="Pelvis translation x,y,z in metres.")] = None,
    skeleton: Annotated[bool, typer.Option(help="Also write the posed bone mesh.")] = False,
    server: Annotated[
        str | None, typer.Option(help="Ask this bodyfit server (URL) instead of computing locally.")
    ] = None,
) -> None:
    """Synthesize one posed body and write it (format from the file suffix)."""
    import numpy as np

    fmt = out.suffix.lstrip(".").lower()
    try:
        values = {k: float(v) for k, v in (item.split("=", 1) for item in coordinate or [])}
        c = None if shape is None else np.array([[float(x) for x in shape.split(",")]])
        r = None if root is None else np.array([[float(x) for x in root.split(",")]])
    except ValueError as exc:
        fail(f"{exc}; write coordinates as NAME=RADIANS and arrays as comma-separated numbers")
    if server is not None:
        data = _from_server(server, fmt, c, values, r, skeleton)
    else:
        with reported():
            from bodyfit.service.core import BodyService, SynthRequest
            from bodyfit.service.formats import encode_bodies

            service = BodyService.load(fitters=False)
            data = encode_bodies(service.synthesize(SynthRequest(c, values, r, skeleton)), fmt, faces=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_bytes(data)
    typer.echo(f"wrote {out} ({len(data):,} bytes)")


def _from_server(
    url: str,
    fmt: str,
    shape: np.ndarray | None,
    coordinates: dict[str, float],
    root: np.ndarray | None,
    skeleton: bool,
) -> bytes:
    """The body's file from a server's REST API, through the SDK."""
    from bodyfit.clients.errors import BodyfitClientError
    from bodyfit.clients.rest_client import Client

    try:
        with Client(url) as client:
            return client.synthesize_file(
                fmt, shape=shape, coordinates=coordinates, root=root, skeleton=skeleton
            )
    except BodyfitClientError as exc:
        fail(exc)

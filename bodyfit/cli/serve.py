"""``bodyfit serve``: the REST and gRPC service (:func:`bodyfit.api.server.run_server`)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

from bodyfit.cli.common import SMPL_MODEL_HELP, fail


def serve(
    host: Annotated[
        str | None,
        typer.Option(help="Interface (default $BODYFIT_HOST, else 127.0.0.1; 0.0.0.0 in a container)."),
    ] = None,
    port: Annotated[
        int | None, typer.Option(help="REST port (default $BODYFIT_REST_PORT, else 8000).")
    ] = None,
    grpc_port: Annotated[
        int | None, typer.Option(help="gRPC port (0: no gRPC; default $BODYFIT_GRPC_PORT, else 50051).")
    ] = None,
    assets: Annotated[Path | None, typer.Option(help="Asset folder (default: the built-in assets).")] = None,
    smpl_model: Annotated[Path | None, typer.Option(help=f"For upgrades: {SMPL_MODEL_HELP}")] = None,
    threads: Annotated[
        int | None, typer.Option(min=1, help="ONNX Runtime / torch threads (default $BODYFIT_THREADS).")
    ] = None,
) -> None:
    """Serve REST and gRPC over the built-in model (limits from BODYFIT_* variables, see the README).

    REST: /v1/model, /v1/synthesize, /v1/fit/scan, /v1/fit/sequence, /v1/upgrade, /healthz, /readyz,
    /metrics and the OpenAPI document at /docs. gRPC: service bodyfit.v1.Bodyfit with health and reflection.
    """
    from bodyfit.api import server
    from bodyfit.api.settings import ServiceSettings
    from bodyfit.models.errors import BodyfitError

    given: dict[str, Any] = {
        "host": host,
        "rest_port": port,
        "grpc_port": grpc_port,
        "assets": assets,
        "threads": threads,
        "smpl_model": smpl_model,
    }
    # options given on the command line win over BODYFIT_* variables, which win over the defaults
    settings = ServiceSettings(**{k: v for k, v in given.items() if v is not None})
    try:
        server.run_server(settings)
    except BodyfitError as exc:
        fail(exc)

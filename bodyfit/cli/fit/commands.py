"""``bodyfit fit``: one subcommand per input kind (``scan``, ``markers``, ``sequence``); ``bodyfit fit
FILE...`` without a kind runs ``auto``, which detects the kind from the files."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import typer
from typer.core import TyperGroup

from bodyfit.cli.common import (
    OUT_HELP,
    SCAN_FACING_HELP,
    SCAN_HEIGHT_HELP,
    SCAN_POSE_HELP,
    SCAN_SEX_HELP,
    SCAN_UP_HELP,
    SUBJECT_HELP,
    UNITS_HELP,
    FacingHint,
    HeightHint,
    PoseHint,
    SexHint,
    Units,
    UnitsOption,
    UpHint,
    fail,
    note,
    reported,
)
from bodyfit.cli.fit.kinds import DESCRIPTION, Kind, single_kind, wrong_kind
from bodyfit.cli.fit.markers import MarkerOptions
from bodyfit.cli.fit.scan import HELPER_SCANS
from bodyfit.wire.hints import PoseClass, Sex

AUTO = "auto"


class FitGroup(TyperGroup):
    """A group whose first argument may be a file instead of a subcommand: ``bodyfit fit walk.trc --out
    DIR`` runs ``bodyfit fit auto walk.trc --out DIR``, so every command written before the subcommands
    existed keeps working."""

    # ctx: the Context of the click that typer bundles privately, hence Any
    def parse_args(self, ctx: Any, args: list[str]) -> list[str]:
        if args and args[0] not in self.commands and args[0] not in ctx.help_option_names:
            args = [AUTO, *args]
        return super().parse_args(ctx, args)


app = typer.Typer(
    cls=FitGroup,
    no_args_is_help=True,
    add_completion=False,
    rich_markup_mode=None,
    help="Fit the body model to files, one subcommand per input kind. `bodyfit fit FILE...` without a kind "
    "detects it: .trc and .c3d are marker trials, an .npz holding `frames` is a registered sequence, "
    "anything else a mesh or scan. Positions in the outputs are in metres, joint coordinates in radians "
    "(degrees in .mot files, as OpenSim reads them), errors in millimetres.",
)

Out = Annotated[Path, typer.Option(help=OUT_HELP)]
PROCESSES_HELP = (
    "1 or 2 processes: 2 fits raw scans with a helper process on a second core (about 20% faster per scan "
    f"once it has started, 0.5 GB more memory). Default: 2 when {HELPER_SCANS} or more inputs are raw "
    "scans."
)
STATIC_HELP = "The subject's static (standing) trial, .trc or .c3d (positions in the unit its header states)."
STATIC_POSE_HELP = (
    "NAME=DEGREES: a coordinate held in the static trial's pose, in DEGREES as a lab's OpenSim scale setup "
    "writes it (unlike `bodyfit synth -c`, which takes radians), e.g. ankle_angle_r=0; repeat for more."
)
CALIBRATION_HELP = (
    "static (from the static trial), motion (from the trial itself; with --static and --static-pose the "
    "static trial then places the markers of the held coordinates' bodies) or auto (static when --static "
    "is given)."
)
MARKER_SET_HELP = "Marker protocol: auto (from the marker names), gait2392 or rajagopal."
MARKER_UP_HELP = "The lab's up axis: x, y or z with an optional sign (e.g. z, -y)."
FORWARD_HELP = "The lab's forward (walking) axis: x, y or z with an optional sign."
SKIN_HELP = "Also estimate the subject's skin from the markers: <trial>_skin.npz and <trial>_skin.glb."
FPS_HELP = "Frames per second (Hz) of the sequence, for the times in the .mot."
Calibration = Literal["auto", "static", "motion"]
OPTION_KINDS: dict[str, tuple[Kind, ...]] = {
    "--units": ("scan",),
    "--processes": ("scan",),
    "--facing": ("scan",),
    "--pose": ("scan",),
    "--sex": ("scan",),
    "--height-m": ("scan",),
    "--static": ("markers",),
    "--static-pose": ("markers",),
    "--calibration": ("markers",),
    "--marker-set": ("markers",),
    "--up": ("scan", "markers"),
    "--forward": ("markers",),
    "--skin": ("markers",),
    "--fps": ("sequence",),
    "--subject": ("scan", "sequence"),
}
Subject = Annotated[Path | None, typer.Option(exists=True, dir_okay=False, help=SUBJECT_HELP)]


@dataclass(frozen=True)
class ScanOptions:
    """`bodyfit fit scan`'s options: units, processes and the hints (:class:`~bodyfit.service.hints.ScanHints`
    fields, unchecked)."""

    units: str = "auto"
    processes: int | None = None
    up: str | None = None
    facing: str | None = None
    pose: str | None = None
    sex: str | None = None
    height_m: float | None = None
    subject: Path | None = None


def run_scans(files: list[Path], out: Path, options: ScanOptions) -> None:
    """Fit meshes and scans in this process (:func:`bodyfit.cli.fit.scan.fit_mesh_files`), the hints checked
    first (a bad one exits with status 2 and names the allowed values)."""
    from bodyfit.cli.fit.scan import fit_mesh_files

    with reported():
        from bodyfit.service.core import BodyService
        from bodyfit.service.hints import ScanHints

        o = options
        hints = ScanHints.given(o.up, o.facing, o.pose, o.sex, o.height_m)
        service = BodyService.load(fitters=False)
        body = None if o.subject is None else service.subject_body(o.subject.read_bytes())
        fit_mesh_files(service, files, out, o.units, o.processes, typer.echo, note, hints, body)
    typer.echo(f"wrote {len(files)} fits to {out}/ (fit.npz, fit.json, registration_*.ply, fit.mot)")


def run_markers(files: list[Path], out: Path, options: MarkerOptions) -> None:
    """Fit marker trials in this process (:func:`bodyfit.cli.fit.markers.fit_marker_trials`)."""
    from bodyfit.cli.fit.markers import fit_marker_trials

    with reported():
        fit_marker_trials(files, out, options, typer.echo)
    typer.echo(f"wrote {len(files)} marker fits to {out}/ (fit.json, <trial>.mot, <trial>.osim)")


def run_sequences(files: list[Path], out: Path, fps: float, subject: Path | None = None) -> None:
    """Fit registered sequences in this process (:func:`bodyfit.cli.fit.sequence.fit_sequence_files`), with
    the person of the ``subject`` file when one is given."""
    from bodyfit.cli.fit.sequence import fit_sequence_files

    with reported():
        from bodyfit.service.core import BodyService

        service = BodyService.load(fitters=False)
        body = None if subject is None else service.subject_body(subject.read_bytes())
        fit_sequence_files(service, files, out, fps, typer.echo, body)
    typer.echo(f"wrote {len(files)} sequence fits to {out}/ (fit.json, <name>.npz, <name>.mot)")


def _only(files: list[Path], kind: Kind) -> None:
    message = wrong_kind(files, kind)
    if message is not None:
        fail(message)


@app.command("scan")
def scan(
    files: Annotated[
        list[Path],
        typer.Argument(
            exists=True,
            dir_okay=False,
            help="Meshes or point clouds: .ply, .obj, .stl, .pcd, or .npz holding points (N, 3) or vertices.",
        ),
    ],
    out: Out = Path("out/fit"),
    units: UnitsOption = "auto",
    processes: Annotated[int | None, typer.Option(min=1, max=2, help=PROCESSES_HELP)] = None,
    up: UpHint = None,
    facing: FacingHint = None,
    pose: PoseHint = None,
    sex: SexHint = None,
    height_m: HeightHint = None,
    subject: Subject = None,
) -> None:
    """Fit meshes and scans, any placement.

    Meshes in our 13,348-vertex topology are fitted vertex to vertex (batched); meshes in SMPL's 6,890-vertex
    topology through the stored correspondence; anything else as a raw scan (any topology or a bare point
    cloud; orientation searched unless --up and --facing give it; no landmarks). The hints (--up, --facing,
    --pose, --sex, --height-m) go with every input; each report says how each was used. Writes fit.npz
    (shape, coordinates in radians, root in metres, registered vertices in our topology and joints, both in
    the input's frame, and to_model, the 4 x 4 map from the input's frame to the one the parameters pose the
    model in), fit.json (one error report per input: distances in mm both ways, joint-limit violations,
    iterations, time, confidence, hints), the registrations as .ply and the coordinates as an OpenSim .mot.
    With --subject every input is fitted as that person (`bodyfit rig`): pose and placement only.
    """
    _only(files, "scan")
    run_scans(files, out, ScanOptions(units, processes, up, facing, pose, sex, height_m, subject))


@app.command("markers")
def markers(
    files: Annotated[
        list[Path],
        typer.Argument(exists=True, dir_okay=False, help="Marker trials (.trc, .c3d) of one subject."),
    ],
    out: Out = Path("out/fit"),
    static: Annotated[Path | None, typer.Option(exists=True, dir_okay=False, help=STATIC_HELP)] = None,
    static_pose: Annotated[list[str] | None, typer.Option(help=STATIC_POSE_HELP)] = None,
    calibration: Annotated[Calibration, typer.Option(help=CALIBRATION_HELP)] = "auto",
    marker_set: Annotated[str, typer.Option(help=MARKER_SET_HELP)] = "auto",
    up: Annotated[str, typer.Option(help=MARKER_UP_HELP)] = "y",
    forward: Annotated[str, typer.Option(help=FORWARD_HELP)] = "x",
    skin: Annotated[bool, typer.Option("--skin/--no-skin", help=SKIN_HELP)] = True,
) -> None:
    """Fit motion-capture marker trials: the skeleton's coordinates per frame.

    OpenSim gait2392 or Rajagopal marker names. The subject is calibrated from the static trial (--static)
    or from the motion, then every frame is solved. Writes <trial>.mot (degrees, as OpenSim reads it),
    <trial>.osim (the scaled subject with its markers, for OpenSim), fit.json (one error report per
    trial: marker distances in mm, joint-limit violations, confidence) and, unless --no-skin,
    <trial>_skin.npz (the skin per frame) and <trial>_skin.glb (one frame).
    """
    _only(files, "markers")
    options = MarkerOptions(static, tuple(static_pose or ()), calibration, marker_set, up, forward, skin)
    run_markers(files, out, options)


@app.command("sequence")
def sequence(
    files: Annotated[
        list[Path],
        typer.Argument(
            exists=True,
            dir_okay=False,
            help="Registered sequences: .npz holding frames (T, 13348, 3) in metres, optionally weights "
            "(T, 13348); one person in time order.",
        ),
    ],
    out: Out = Path("out/fit"),
    fps: Annotated[float, typer.Option(min=0.001, help=FPS_HELP)] = 30.0,
    subject: Subject = None,
) -> None:
    """Fit registered mesh sequences: one shape and a pose per frame (with --subject, that person's body:
    a pose per frame only).

    Writes <name>.npz (shape, coordinates in radians, root in metres, vertices, joints, per-frame error_mm),
    <name>.mot and fit.json (frames per second, error in mm, jitter).
    """
    _only(files, "sequence")
    run_sequences(files, out, fps, subject)


@app.command(AUTO)
def auto(
    files: Annotated[
        list[Path],
        typer.Argument(
            exists=True,
            dir_okay=False,
            help="Files of one kind: meshes or scans, marker trials (.trc, .c3d) or registered sequences "
            "(.npz holding frames).",
        ),
    ],
    out: Out = Path("out/fit"),
    units: Annotated[Units | None, typer.Option(help=f"Scans: {UNITS_HELP}")] = None,
    processes: Annotated[int | None, typer.Option(min=1, max=2, help=f"Scans: {PROCESSES_HELP}")] = None,
    static: Annotated[
        Path | None, typer.Option(exists=True, dir_okay=False, help=f"Markers: {STATIC_HELP}")
    ] = None,
    static_pose: Annotated[list[str] | None, typer.Option(help=f"Markers: {STATIC_POSE_HELP}")] = None,
    calibration: Annotated[Calibration | None, typer.Option(help=f"Markers: {CALIBRATION_HELP}")] = None,
    marker_set: Annotated[str | None, typer.Option(help=f"Markers: {MARKER_SET_HELP}")] = None,
    up: Annotated[
        str | None,
        typer.Option(help=f"Markers: {MARKER_UP_HELP} Default: y. Scans: {SCAN_UP_HELP}"),
    ] = None,
    forward: Annotated[str | None, typer.Option(help=f"Markers: {FORWARD_HELP} Default: x.")] = None,
    skin: Annotated[
        bool | None, typer.Option("--skin/--no-skin", help=f"Markers: {SKIN_HELP} Default: --skin.")
    ] = None,
    fps: Annotated[float | None, typer.Option(min=0.001, help=f"Sequences: {FPS_HELP} Default: 30.")] = None,
    facing: Annotated[str | None, typer.Option(help=f"Scans: {SCAN_FACING_HELP}")] = None,
    pose: Annotated[PoseClass | None, typer.Option(help=f"Scans: {SCAN_POSE_HELP}")] = None,
    sex: Annotated[Sex | None, typer.Option(help=f"Scans: {SCAN_SEX_HELP}")] = None,
    height_m: Annotated[float | None, typer.Option(help=f"Scans: {SCAN_HEIGHT_HELP}")] = None,
    subject: Annotated[
        Path | None, typer.Option(exists=True, dir_okay=False, help=f"Scans and sequences: {SUBJECT_HELP}")
    ] = None,
) -> None:
    """Detect the kind of the files, then fit them as `scan`, `markers` or `sequence` do (the default when
    no kind is given: `bodyfit fit FILE...`). Every file of one run must be of one kind."""
    kind, mixed = single_kind(files)
    if kind is None:
        fail(mixed)
    given: dict[str, Any] = {
        "--units": units,
        "--processes": processes,
        "--static": static,
        "--static-pose": static_pose,
        "--calibration": calibration,
        "--marker-set": marker_set,
        "--up": up,
        "--forward": forward,
        "--skin": skin,
        "--fps": fps,
        "--facing": facing,
        "--pose": pose,
        "--sex": sex,
        "--height-m": height_m,
        "--subject": subject,
    }
    stray = [name for name, value in given.items() if value is not None and kind not in OPTION_KINDS[name]]
    if stray:
        owners = "; ".join(
            f"{name} is an option of `bodyfit fit {' or '.join(OPTION_KINDS[name])}`" for name in stray
        )
        fail(f"{owners}, but {files[0]} is {DESCRIPTION[kind]}; leave {' '.join(stray)} out")
    if kind == "markers":
        options = MarkerOptions(
            static,
            tuple(static_pose or ()),
            calibration or "auto",
            marker_set or "auto",
            up or "y",
            forward or "x",
            skin is not False,
        )
        run_markers(files, out, options)
    elif kind == "sequence":
        run_sequences(files, out, 30.0 if fps is None else fps, subject)
    else:
        scan_options = ScanOptions(units or "auto", processes, up, facing, pose, sex, height_m, subject)
        run_scans(files, out, scan_options)

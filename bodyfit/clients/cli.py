"""The ``bodyfit`` command line. Heavy modules are imported inside the commands that need them."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from bodyfit.clients.mesh_cli import HELPER_SCANS

if TYPE_CHECKING:
    from bodyfit.clients.marker_cli import MarkerOptions

app = typer.Typer(
    no_args_is_help=True,
    add_completion=False,
    rich_markup_mode=None,
    help="bodyfit: human bodies with a biomechanical skeleton.",
)


@app.command("build-assets")
def build_assets(
    out: Annotated[
        Path | None, typer.Option(help="Asset folder (default: assets/ of the checkout, or $BODYFIT_ASSETS).")
    ] = None,
    docs: Annotated[Path, typer.Option(help="Where docs/skeleton.md is written.")] = Path("docs"),
    quick: Annotated[
        bool, typer.Option(help="Small population (120 bodies, 60 posed): every step in about 2 minutes.")
    ] = False,
    children: Annotated[bool, typer.Option(help="Add children (ages 5-18) to the adult population.")] = False,
    bodies: Annotated[
        int | None, typer.Option(min=20, help="Population size (default 2000; 120 with --quick).")
    ] = None,
    seed: Annotated[int | None, typer.Option(help="Random seed of the population and poses.")] = None,
) -> None:
    """Build every model asset from PyPI sources (needs the `build` extra: anny, nimblephysics, opensim).

    Steps: skeleton from Rajagopal2015; bone mesh; body model from anny's population (template, landmarks,
    skeleton fits, joint regressor, bone and identity shape spaces, skinning weights); ONNX export; manifest
    with hashes and measured metrics.
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


@app.command("build-proxy")
def build_proxy(
    assets: Annotated[
        Path | None, typer.Option(help="Asset folder (default: assets/ of the checkout, or $BODYFIT_ASSETS).")
    ] = None,
) -> None:
    """Rebuild only path (b)'s SMPL-format proxy (smpl_proxy.npz, from anny's SOMA rig; needs the `build`
    extra) and record its hash in the manifest."""
    from bodyfit.models.build_assets import build_proxy_asset
    from bodyfit.models.errors import BodyfitError

    try:
        typer.echo(str(build_proxy_asset(assets)))
    except BodyfitError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc


@app.command("export-onnx")
def export_onnx(
    assets: Annotated[
        Path | None, typer.Option(help="Asset folder (default: assets/ of the checkout, or $BODYFIT_ASSETS).")
    ] = None,
) -> None:
    """Re-export body.onnx (float32, dynamic batch) from body.npz and record its hash in the manifest."""
    from bodyfit.models.build_assets import export_onnx as export
    from bodyfit.models.errors import BodyfitError

    try:
        typer.echo(str(export(assets)))
    except BodyfitError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc


@app.command()
def fit(
    meshes: Annotated[
        list[Path],
        typer.Argument(
            help="Meshes or point clouds (.ply, .obj, .stl, .pcd, .npz); registered mesh sequences (.npz "
            "holding frames (T, 13348, 3)); or motion-capture marker trials (.trc, .c3d) of one subject."
        ),
    ],
    out: Annotated[Path, typer.Option(help="Output folder.")] = Path("out/fit"),
    units: Annotated[str, typer.Option(help="Meshes: auto, m or mm.")] = "auto",
    processes: Annotated[
        int | None,
        typer.Option(
            min=1,
            max=2,
            help=f"1 or 2: 2 fits raw scans with a helper process on a second core (about 20% faster per "
            f"scan once it has started, 0.5 GB more memory). Default: 2 when {HELPER_SCANS} or more inputs "
            "are raw scans.",
        ),
    ] = None,
    static: Annotated[
        Path | None,
        typer.Option(help="Marker trials: the subject's static (standing) trial, .trc or .c3d."),
    ] = None,
    static_pose: Annotated[
        list[str] | None,
        typer.Option(
            help="Marker trials: NAME=DEGREES, a coordinate held in the static trial's pose, as a lab's "
            "OpenSim scale setup holds it (e.g. ankle_angle_r=0; repeat for more)."
        ),
    ] = None,
    calibration: Annotated[
        str,
        typer.Option(
            help="Marker trials: static (from the static trial), motion (from the trial itself; with "
            "--static and --static-pose the static trial then places the markers of the held coordinates' "
            "bodies) or auto (static when --static is given)."
        ),
    ] = "auto",
    marker_set: Annotated[str, typer.Option(help="Marker trials: auto, gait2392 or rajagopal.")] = "auto",
    up: Annotated[str, typer.Option(help="Marker trials: the lab's up axis (y, z, -z, ...).")] = "y",
    forward: Annotated[str, typer.Option(help="Marker trials: the lab's forward axis.")] = "x",
    fps: Annotated[
        float, typer.Option(min=0.001, help="Sequences: frames per second, for the .mot's times.")
    ] = 30.0,
) -> None:
    """Fit the body model to meshes and scans, any placement, or to motion-capture marker trials.

    Meshes in our 13,348-vertex topology are fitted vertex to vertex (batched); meshes in SMPL's 6,890-vertex
    topology through the stored correspondence; anything else as a raw scan (any topology or a bare point
    cloud; orientation searched; no landmarks). Writes fit.npz (shape, coordinates, root, registered vertices
    in our topology, joints), fit.json (one error report per input: distances in mm, joint-limit
    violations, iterations, time, confidence), the registrations as .ply and the coordinates as an OpenSim
    .mot.

    A registered sequence (an .npz holding frames (T, 13348, 3), optionally weights (T, 13348), one person
    in time order) gets one shape and a pose per frame: writes <name>.npz (shape, coordinates, root,
    vertices, joints, per-frame error_mm), <name>.mot and fit.json (frames per second, error, jitter).

    Marker trials (.trc, .c3d; OpenSim gait2392 or Rajagopal marker names) give the skeleton's coordinates
    per frame: the subject is calibrated from the static trial (--static) or from the motion, then every
    frame is solved. Writes <trial>.mot, <trial>.osim (the scaled subject with its markers, for OpenSim) and
    fit.json (one error report per trial: marker distances in mm, joint-limit violations, confidence).
    """
    from bodyfit.clients.marker_cli import MarkerOptions

    trials, sequences = _split_inputs(meshes)
    markers = MarkerOptions(static, tuple(static_pose or ()), calibration, marker_set, up, forward)
    wrote = _fit_files(meshes, trials, sequences, out, units, processes, fps, markers)
    typer.echo(f"wrote {wrote}")


def _split_inputs(meshes: list[Path]) -> tuple[list[Path], list[Path]]:
    """Returns the marker trials and the registered sequences among the inputs; exits with status 2 when
    the inputs mix trials, sequences and meshes."""
    from bodyfit.clients.marker_cli import is_marker_file
    from bodyfit.clients.sequence_cli import is_sequence_file

    trials = [path for path in meshes if is_marker_file(path)]
    sequences = [path for path in meshes if is_sequence_file(path)]
    if 0 < len(trials) + len(sequences) < len(meshes) or (trials and sequences):
        typer.echo(
            "error: fit marker trials (.trc, .c3d), sequences (.npz with frames) and meshes in separate runs",
            err=True,
        )
        raise typer.Exit(2)
    return trials, sequences


def _fit_files(
    meshes: list[Path],
    trials: list[Path],
    sequences: list[Path],
    out: Path,
    units: str,
    processes: int | None,
    fps: float,
    markers: MarkerOptions,
) -> str:
    """Returns what was written, once the marker trials, else the sequences, else the meshes are fitted;
    an error in the input is printed and exits with status 2."""
    from bodyfit.clients.marker_cli import fit_marker_trials
    from bodyfit.clients.mesh_cli import fit_mesh_files
    from bodyfit.clients.sequence_cli import fit_sequence_files
    from bodyfit.models.errors import BodyfitError
    from bodyfit.service.core import BodyService
    from bodyfit.service.errors import ServiceError

    try:
        if trials:
            fit_marker_trials(trials, out, markers, typer.echo)
            return f"{len(trials)} marker fits to {out}/ (fit.json, <trial>.mot, <trial>.osim)"
        if sequences:
            fit_sequence_files(BodyService.load(fitters=False), sequences, out, fps, typer.echo)
            return f"{len(sequences)} sequence fits to {out}/ (fit.json, <name>.npz, <name>.mot)"
        service = BodyService.load(fitters=False)
        fit_mesh_files(service, meshes, out, units, processes, typer.echo, _to_stderr)
        return f"{len(meshes)} fits to {out}/ (fit.npz, fit.json, registration_*.ply, fit.mot)"
    except (BodyfitError, ServiceError, ValueError, OSError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc


def _to_stderr(line: str) -> None:
    typer.echo(line, err=True)


@app.command()
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
    smpl_model: Annotated[
        Path | None,
        typer.Option(help="SMPL-family model file for upgrades (default $BODYFIT_SMPL_MODEL; none ships)."),
    ] = None,
    threads: Annotated[
        int | None, typer.Option(min=1, help="ONNX Runtime / torch threads (default $BODYFIT_THREADS).")
    ] = None,
) -> None:
    """Serve REST and gRPC over the built-in model (limits from BODYFIT_* variables, see the README).

    REST: /v1/model, /v1/synthesize, /v1/fit/scan, /v1/fit/sequence, /v1/upgrade, /healthz, /readyz,
    /metrics and the OpenAPI document at /docs. gRPC: service bodyfit.v1.Bodyfit with health and reflection.
    """
    from bodyfit.api.server import run_server
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
        run_server(settings)
    except BodyfitError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc


@app.command()
def synth(
    out: Annotated[Path, typer.Argument(help="Output file: .npz, .ply, .obj, .glb or .json.")],
    coordinate: Annotated[
        list[str] | None,
        typer.Option("--coordinate", "-c", help="NAME=RADIANS, repeatable (e.g. knee_angle_r=1.0)."),
    ] = None,
    shape: Annotated[
        str | None, typer.Option(help="Comma-separated shape coefficients (bone then identity).")
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
        typer.echo(
            f"error: {exc}; write coordinates as NAME=RADIANS and arrays as comma-separated numbers", err=True
        )
        raise typer.Exit(2) from exc
    if server is not None:
        from bodyfit.clients.errors import BodyfitClientError
        from bodyfit.clients.rest_client import Client

        try:
            with Client(server) as client:
                data = client.synthesize_file(fmt, shape=c, coordinates=values, root=r, skeleton=skeleton)
        except BodyfitClientError as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(2) from exc
    else:
        from bodyfit.models.errors import BodyfitError
        from bodyfit.service.core import BodyService, SynthRequest
        from bodyfit.service.errors import ServiceError
        from bodyfit.service.formats import encode_bodies

        try:
            service = BodyService.load(fitters=False)
            data = encode_bodies(service.synthesize(SynthRequest(c, values, r, skeleton)), fmt, faces=True)
        except (ServiceError, BodyfitError) as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(2) from exc
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_bytes(data)
    typer.echo(f"wrote {out} ({len(data):,} bytes)")


@app.command()
def upgrade(
    sequence: Annotated[Path, typer.Argument(help="AMASS-style .npz or SMPL .pkl sequence.")],
    smpl_model: Annotated[
        Path | None,
        typer.Option(
            help="SMPL-family model file (.npz, or .pkl without chumpy); default $BODYFIT_SMPL_MODEL."
        ),
    ] = None,
    out: Annotated[Path, typer.Option(help="Output folder.")] = Path("out/upgrade"),
    sex: Annotated[
        str | None,
        typer.Option(help="Path (b) shape hint: male, female or neutral (default: the file's gender)."),
    ] = None,
    height: Annotated[float | None, typer.Option(help="Path (b) shape hint: stature in metres.")] = None,
    mass: Annotated[float | None, typer.Option(help="Path (b) shape hint: body mass in kilograms.")] = None,
) -> None:
    """Upgrade an SMPL-format sequence to biomechanical coordinates: path (a) with an SMPL-family model file,
    else path (b) from the joint rotations alone (shape: from --sex/--height/--mass, else the population
    mean; the summary says which ran).

    Writes <name>.npz (coordinates with their names, root, joints, bone scales, per-frame error, bad-frame
    flags), <name>.json (summary: v2v error, frames/s, limit violations, largest frame-to-frame jump) and
    OpenSim files: <name>.osim (our skeleton scaled to the subject) and <name>.mot.
    """
    from tqdm import tqdm

    from bodyfit.io.smpl import read_smpl_sequence
    from bodyfit.models.body.model import BodyModel
    from bodyfit.models.errors import BodyfitError
    from bodyfit.models.upgrade.proxy import ShapeHints
    from bodyfit.models.upgrade.smpl_model import ENV_VAR, load_smpl_model
    from bodyfit.models.upgrade.upgrade import (
        upgrade_fitter,
        upgrade_from_rotations,
        upgrade_with_model,
        write_upgrade,
    )

    try:
        hints = ShapeHints.given(sex, height, mass)
        seq = read_smpl_sequence(sequence)
        given = smpl_model or os.environ.get(ENV_VAR)
        smpl = load_smpl_model(given) if given else None
        model = BodyModel.load()
        with tqdm(total=seq.n_frames, unit="frame", desc=sequence.name) as bar:

            def progress(done: int, total: int) -> None:
                bar.update(done - bar.n)

            if smpl is None:
                typer.echo("no SMPL-family model file: path (b), from the joint rotations alone", err=True)
                result = upgrade_from_rotations(seq, upgrade_fitter(model), hints=hints, progress=progress)
            else:
                result = upgrade_with_model(seq, smpl, upgrade_fitter(model), progress=progress)
    except (BodyfitError, OSError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    paths = write_upgrade(result, model, out, sequence.stem)
    summary = result.summary()
    v2v = "" if summary["v2v_mean_mm"] is None else f"v2v {summary['v2v_mean_mm']:.1f} mm, "
    typer.echo(
        f"{sequence.name}: {summary['frames']} frames, path ({result.path}), {v2v}{summary['fps']:.0f} "
        f"frames/s, {summary['limit_violations']} limit violations"
    )
    typer.echo("wrote " + ", ".join(str(p) for p in paths.values()))


@app.command("batch-upgrade")
def batch_upgrade_command(
    dataset: Annotated[
        Path, typer.Argument(help="Folder of AMASS-style .npz sequences (searched recursively).")
    ],
    out: Annotated[Path, typer.Argument(help="Output folder (the dataset's layout is kept).")],
    concurrency: Annotated[int, typer.Option(min=1, help="Sequences in flight at once.")] = 1,
    backend: Annotated[
        str, typer.Option(help="local, a server URL (http://host:8000), ray, or ray://host:10001.")
    ] = "local",
    smpl_model: Annotated[
        Path | None,
        typer.Option(help="SMPL-family model file for local / ray (default $BODYFIT_SMPL_MODEL)."),
    ] = None,
) -> None:
    """Upgrade a whole dataset tree; resumes (finished sequences are skipped) and reports failures at the end
    without stopping. Writes <out>/<relative path>.npz, .json, .osim and .mot per sequence."""
    from bodyfit.clients.batch import batch_upgrade
    from bodyfit.clients.errors import BodyfitClientError

    try:
        report = batch_upgrade(dataset, out, concurrency, backend, smpl_model)
    except (BodyfitClientError, OSError, ValueError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    for path, why in sorted(report.failed.items()):
        typer.echo(f"FAILED {path}: {why}", err=True)
    typer.echo(report.summary())
    if report.failed:
        raise typer.Exit(1)


@app.command()
def demo(
    out: Annotated[Path, typer.Option(help="Output folder.")] = Path("out/demo"),
    frames: Annotated[int, typer.Option(min=1, max=100000, help="Frames of the demo motion.")] = 120,
) -> None:
    """Pose the built-in skeleton through a short motion and write it: JSON, .npz and OpenSim .osim + .mot."""
    import numpy as np
    import trimesh

    from bodyfit.models.errors import BodyfitError
    from bodyfit.models.skeleton import Skeleton
    from bodyfit.models.skeleton.opensim_export import write_mot, write_osim

    try:
        skel = Skeleton.load()
    except BodyfitError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    t = np.arange(frames) / 60.0
    phase = 2 * np.pi * t  # one stride per second
    values = {
        "hip_flexion_r": 0.35 * np.sin(phase) + 0.15,
        "hip_flexion_l": -0.35 * np.sin(phase) + 0.15,
        "knee_angle_r": 0.6 * np.clip(np.sin(phase + 1.2), 0, None) + 0.05,
        "knee_angle_l": 0.6 * np.clip(-np.sin(phase + 1.2), 0, None) + 0.05,
        "arm_flex_r": -0.3 * np.sin(phase),
        "arm_flex_l": 0.3 * np.sin(phase),
        "elbow_flex_r": np.full(frames, 0.4),
        "elbow_flex_l": np.full(frames, 0.4),
        "thorax_rotation": 0.08 * np.sin(phase),
        "scapula_abduction_r": 0.1 * np.sin(phase),
        "scapula_abduction_l": -0.1 * np.sin(phase),
    }
    q = skel.coordinates(values, batch=frames)
    root = np.stack([1.2 * t, np.full(frames, 0.94), np.zeros(frames)], axis=1)
    pose = skel.forward(q, root)
    out.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        out / "pose.npz",
        coordinates=q,
        dof_names=np.array(skel.dof_names),
        root=root,
        body_names=np.array(skel.body_names),
        frames=pose.frames.numpy(),
        joint_centres=pose.joint_centres.numpy(),
    )
    first = {
        name: [round(float(v), 5) for v in pose.frames[0, i, :3, 3]] for i, name in enumerate(skel.body_names)
    }
    (out / "pose.json").write_text(json.dumps({"frame": 0, "body_origins_m": first}, indent=1) + "\n")
    write_osim(out / "skeleton.osim", skel.spec, name="bodyfit_demo")
    write_mot(out / "demo.mot", skel.spec, q, root, fps=60.0)
    bones = skel.bone_mesh()
    trimesh.Trimesh(skel.pose_bones(pose.frames[:1])[0].numpy(), bones.faces, process=False).export(
        out / "bones_frame0.ply"
    )
    files = "pose.npz, pose.json, skeleton.osim, demo.mot, bones_frame0.ply"
    typer.echo(f"wrote {frames} posed frames to {out}/ ({files})")


def main() -> None:  # pragma: no cover - console entry point
    app(sys.argv[1:])


if __name__ == "__main__":  # pragma: no cover
    main()

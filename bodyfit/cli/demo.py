"""``bodyfit demo``: the built-in skeleton posed through a short walking motion, written as JSON, .npz and
OpenSim files, with no server and no body model."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from bodyfit.cli.common import OUT_HELP, reported

if TYPE_CHECKING:
    import numpy as np

FPS = 60.0


def demo_motion(frames: int) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """A stride a second at :data:`FPS` frames per second: named coordinates, each (frames,) in radians,
    and the root (frames, 3) in metres (walking along +X at 1.2 m/s, pelvis 0.94 m high)."""
    import numpy as np

    t = np.arange(frames) / FPS
    phase = 2 * np.pi * t
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
    root = np.stack([1.2 * t, np.full(frames, 0.94), np.zeros(frames)], axis=1)
    return values, root


def demo(
    out: Annotated[Path, typer.Option(help=OUT_HELP)] = Path("out/demo"),
    frames: Annotated[
        int,
        typer.Option(min=1, max=100000, help=f"Frames of the demo motion, at {FPS:.0f} frames per second."),
    ] = 120,
) -> None:
    """Pose the built-in skeleton through a short motion and write it: JSON (body origins in metres), .npz
    (coordinates in radians, root in metres, body frames) and OpenSim .osim + .mot."""
    import numpy as np
    import trimesh

    from bodyfit.models.skeleton import Skeleton
    from bodyfit.models.skeleton.opensim_export import write_mot, write_osim

    with reported():
        skel = Skeleton.load()
    values, root = demo_motion(frames)
    q = skel.coordinates(values, batch=frames)
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
    write_mot(out / "demo.mot", skel.spec, q, root, fps=FPS)
    bones = skel.bone_mesh()
    trimesh.Trimesh(skel.pose_bones(pose.frames[:1])[0].numpy(), bones.faces, process=False).export(
        out / "bones_frame0.ply"
    )
    files = "pose.npz, pose.json, skeleton.osim, demo.mot, bones_frame0.ply"
    typer.echo(f"wrote {frames} posed frames to {out}/ ({files})")

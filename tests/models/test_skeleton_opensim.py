"""Our skeleton against OpenSim 4.6 itself: Rajagopal2015 parity and the round trip of our exports."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from bodyfit.models.rotations import rotation_angle_between
from bodyfit.models.skeleton import Skeleton
from bodyfit.models.skeleton.opensim_export import mot_columns, read_mot, write_mot, write_osim
from tests.conftest import random_pose

opensim = pytest.importorskip("opensim")
from bodyfit.models.skeleton.opensim_reference import OpenSimReference, pose_values  # noqa: E402
from bodyfit.models.skeleton.rajagopal import rajagopal_osim_path  # noqa: E402

N_POSES = 1000
ROOTS = ["pelvis_tx", "pelvis_ty", "pelvis_tz"]
# Bodies of ours that Rajagopal2015 has; thorax, head and the scapulae are parts of its torso.
TORSO_PARTS = ("thorax", "head", "scapula_r", "scapula_l")


def _errors(ours: torch.Tensor, ref: np.ndarray) -> tuple[float, float]:
    ref_t = torch.as_tensor(ref)
    pos = float((ours[..., :3, 3] - ref_t[..., :3, 3]).norm(dim=-1).max())
    rot = float(rotation_angle_between(ours[..., :3, :3], ref_t[..., :3, :3]).max())
    return pos, rot


def _segment_scales(skel: Skeleton, rng: np.random.Generator) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Random per-segment factors for Rajagopal's bodies; our torso parts share the torso's."""
    by_seg = {s: rng.uniform(0.8, 1.25, 3) for s in skel.segments if s not in TORSO_PARTS}
    ours = np.stack([by_seg.get(s, by_seg["torso"]) for s in skel.segments])
    return ours, by_seg


@pytest.mark.opensim
@pytest.mark.parametrize("scaled", [False, True], ids=["unscaled", "scaled"])
def test_rajagopal_parity_1000_poses(skeleton: Skeleton, scaled: bool) -> None:
    rng = np.random.default_rng(7 if scaled else 3)
    scales_ours, scales_osim = _segment_scales(skeleton, rng) if scaled else (None, None)
    ref = OpenSimReference(rajagopal_osim_path(), scales_osim)
    bodies = [b for b in skeleton.body_names if ref.model.getBodySet().contains(b)]
    assert len(bodies) == 22
    idx = [skeleton.body_names.index(b) for b in bodies]

    q = random_pose(skeleton, N_POSES, seed=11 if scaled else 5, rajagopal_only=True)
    root = rng.uniform(-1, 1, (N_POSES, 3))
    expected = np.empty((N_POSES, len(bodies), 4, 4))
    raj = [i for i, c in enumerate(skeleton.spec.coordinates) if c.rajagopal]
    names = [skeleton.dof_names[i] for i in raj]
    for n in range(N_POSES):
        ref.set_coordinates(pose_values(names, q[n, raj], ROOTS, root[n]))
        expected[n] = ref.body_frames(bodies)

    s = None if scales_ours is None else np.broadcast_to(scales_ours, (N_POSES, *scales_ours.shape))
    ours = skeleton.kinematics(torch.float64)(
        torch.as_tensor(q), torch.as_tensor(root), None if s is None else torch.as_tensor(s.copy())
    )
    pos, rot = _errors(ours.frames[:, idx], expected)
    assert pos <= 1e-5 and rot <= 1e-5, (pos, rot)
    assert pos < 1e-10  # in practice the two agree to machine precision


@pytest.mark.opensim
def test_exported_osim_and_mot_reproduce_our_kinematics(skeleton: Skeleton, tmp_path: Path) -> None:
    rng = np.random.default_rng(21)
    T = 40
    scales = rng.uniform(0.85, 1.2, (len(skeleton.segments), 3))
    q = random_pose(skeleton, T, seed=23)  # every DOF moves, extensions included
    root = rng.uniform(-1, 1, (T, 3))
    osim_path = write_osim(tmp_path / "subject.osim", skeleton.spec, scales, name="subject")
    mot_path = write_mot(tmp_path / "motion.mot", skeleton.spec, q, root, fps=100.0)

    # OpenSim's own reader accepts the .mot and sees our columns.
    table = opensim.TimeSeriesTable(str(mot_path))
    assert list(table.getColumnLabels()) == mot_columns(skeleton.spec)
    assert table.getNumRows() == T

    ref = OpenSimReference(osim_path)
    cols, _, in_degrees = read_mot(mot_path)
    assert in_degrees and cols[0] == "time"
    ours = skeleton.kinematics(torch.float64)(
        torch.as_tensor(q),
        torch.as_tensor(root),
        torch.as_tensor(np.broadcast_to(scales, (T, *scales.shape)).copy()),
    )
    worst = 0.0
    for t in range(T):
        row = np.array([table.getRowAtIndex(t)[i] for i in range(len(cols) - 1)])
        ref.set_coordinates(dict(zip(cols[1:], map(float, row))), degrees=True)
        frames = ref.body_frames(skeleton.body_names)
        worst = max(
            worst, float(np.linalg.norm(ours.frames[t, :, :3, 3].numpy() - frames[:, :3, 3], axis=-1).max())
        )
    assert worst <= 1e-3, worst  # the bound: 1 mm
    assert worst <= 1e-6  # measured: ~5e-10 m (the .mot's 10 significant digits and arc splines)


@pytest.mark.opensim
def test_exported_model_coordinates_match_skeleton(skeleton: Skeleton, tmp_path: Path) -> None:
    ref = OpenSimReference(write_osim(tmp_path / "m.osim", skeleton.spec))
    names = set(ref.coordinate_names)
    assert set(mot_columns(skeleton.spec)) <= names
    assert names - set(mot_columns(skeleton.spec)) == {"knee_angle_r_beta", "knee_angle_l_beta"}
    for c in skeleton.spec.coordinates:
        oc = ref.model.getCoordinateSet().get(c.name)
        assert (oc.getRangeMin(), oc.getRangeMax()) == pytest.approx(c.range)


@pytest.mark.opensim
def test_an_exported_model_carries_its_bones_and_opensim_places_them_as_we_do(
    skeleton: Skeleton, tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """write_osim writes each body's bones beside the model (Geometry/<body>_bones.obj): OpenSim loads the
    model without a missing-file warning (81 before), and the mesh it attaches, scaled and offset as the
    model says, lies where our bone mesh puts the body's bones."""
    scales = np.random.default_rng(8).uniform(0.85, 1.2, (len(skeleton.segments), 3))
    path = write_osim(tmp_path / "m.osim", skeleton.spec, scales, name="m")
    capfd.readouterr()
    model = opensim.Model(str(path))
    model.initSystem()
    logged = "".join(capfd.readouterr())
    assert "Couldn't find" not in logged, logged[-2000:]
    bones = skeleton.bone_mesh()
    checked = 0
    for i, body in enumerate(skeleton.spec.bodies):
        if not body.geometry:
            continue
        frame = opensim.PhysicalOffsetFrame.safeDownCast(
            model.getBodySet().get(body.name).getComponent(f"{body.name}_geometry")
        )
        mesh = opensim.Mesh.safeDownCast(frame.get_attached_geometry(0))
        offset = np.array([frame.get_translation().get(k) for k in range(3)])
        factors = np.array([mesh.get_scale_factors().get(k) for k in range(3)])
        obj = (tmp_path / mesh.get_mesh_file()).read_text().splitlines()
        v = np.array([[float(x) for x in line.split()[1:]] for line in obj if line.startswith("v ")])
        s = scales[skeleton.segments.index(body.segment)]
        ours = bones.vertices[bones.vertex_body == i].astype(np.float64) * s
        np.testing.assert_allclose(offset + v * factors, ours, atol=1e-6)
        checked += 1
    assert checked == sum(bool(b.geometry) for b in skeleton.spec.bodies) >= 20

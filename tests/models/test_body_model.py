"""The body model asset: template, held-out bodies, symmetry, gradients, ONNX parity, errors, hashes."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from bodyfit.models.assets import read_manifest, sha256
from bodyfit.models.body.geometry import winding_number
from bodyfit.models.body.model import BodyModel
from bodyfit.models.errors import (
    AssetError,
    CoordinateRangeError,
    NonFiniteError,
    ShapeError,
    UnknownCoordinateError,
)
from bodyfit.models.skeleton.model import twin_name
from tests.conftest import random_pose

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def body() -> BodyModel:
    return BodyModel.load()


def _random_inputs(body: BodyModel, n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    shape = rng.normal(size=(n, body.n_shape))
    q = random_pose(body.skeleton, n, seed)
    root = rng.normal(scale=0.2, size=(n, 3))
    return shape, q, root


def test_zero_parameters_reproduce_the_template(body: BodyModel) -> None:
    out = body.forward(dtype=torch.float64)
    assert out.vertices.shape == (1, body.n_vertices, 3)
    assert float(np.abs(out.vertices[0].numpy() - body.data["template"]).max()) < 1e-5
    # In the bind pose the skinning is the identity: the stored mean vertices come back exactly.
    bind = body.decoder(torch.float64)(
        torch.zeros(1, body.n_shape, dtype=torch.float64),
        torch.as_tensor(body.bind_coordinates[None]),
        torch.zeros(1, 3, dtype=torch.float64),
    )[0]
    assert float(np.abs(bind[0].numpy() - body.data["vertices_mean"]).max()) < 1e-6


def test_template_is_one_watertight_surface(body: BodyModel) -> None:
    import trimesh

    mesh = trimesh.Trimesh(body.data["template"], body.faces, process=False)
    assert mesh.is_watertight
    assert len(mesh.split(only_watertight=False)) == 1
    assert body.n_vertices == 13348
    # Y up, facing +X: the nose is the most forward point of the head, the feet are at the bottom.
    v = body.data["template"]
    lm = {name: v[i] for name, i in zip(body.landmark_names, body.data["landmarks"])}
    assert lm["pronasale"][0] > lm["C7"][0] + 0.1
    assert lm["vertex"][1] > lm["pronasale"][1] > lm["ASIS_r"][1] > lm["heel_r"][1]
    assert lm["heel_r"][1] < v[:, 1].min() + 0.05
    assert lm["ASIS_r"][2] > 0 > lm["ASIS_l"][2]  # +Z is the body's right


def test_every_heldout_body_has_its_joints_inside_its_skin(body: BodyModel) -> None:
    shapes = body.data["heldout_shape"]
    assert len(shapes) >= 10
    out = body.forward(shapes, dtype=torch.float64)
    for v, j in zip(out.vertices.numpy(), out.joints.numpy()):
        w = winding_number(v, body.faces, j)
        assert w.min() > 0.5, [body.joint_names[i] for i in np.flatnonzero(w <= 0.5)]


def test_mirrored_parameters_give_the_mirrored_mesh(body: BodyModel) -> None:
    shape, q, root = _random_inputs(body, 8, seed=3)
    root[:, 2] = 0.0
    mirror = body.data["mirror"]
    a = body.forward(shape, q, root, dtype=torch.float64)
    b = body.forward(shape, body.skeleton.mirror_coordinates(q), root, dtype=torch.float64)
    flip = np.array([1.0, 1.0, -1.0])
    gap = np.linalg.norm(a.vertices.numpy() - b.vertices.numpy()[:, mirror] * flip, axis=-1)
    assert gap.max() < 1e-3
    twin = [body.joint_names.index(twin_name(n)) for n in body.joint_names]
    assert np.abs(a.joints.numpy() - b.joints.numpy()[:, twin] * flip).max() < 1e-3


def test_gradients_match_finite_differences_in_float64(body: BodyModel) -> None:
    shape, q, root = _random_inputs(body, 2, seed=5)
    dec = body.decoder(torch.float64)
    probe = torch.randn(
        2, body.n_vertices, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0)
    )

    def f(c: torch.Tensor, qq: torch.Tensor, r: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        v, j, _, _ = dec(c, qq, r)
        return (v * probe).sum(dim=(1, 2)), j[:, :6].reshape(2, -1)

    args = tuple(torch.tensor(x * 0.8, requires_grad=True) for x in (shape, q, root))
    assert torch.autograd.gradcheck(f, args, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_the_skin_of_a_fixed_shape_is_the_decoder_s_and_so_are_its_gradients(body: BodyModel) -> None:
    """BodyDecoder.posed (vertices, and joints with them): whole template, a vertex subset and a template with
    offsets, in float64."""
    shape, q, root = _random_inputs(body, 3, seed=11)
    full = body.decoder(torch.float64)
    offsets = np.random.default_rng(2).normal(scale=0.01, size=(body.n_vertices, 3))
    for dec in (full, full.restricted(np.arange(0, body.n_vertices, 7)), full.with_offsets(offsets)):
        c = torch.as_tensor(shape[:1])
        qt = torch.tensor(q, requires_grad=True)
        rt = torch.tensor(root, requires_grad=True)
        ref, ref_joints, _, _ = dec(c.expand(3, -1), qt, rt)
        got = dec.posed(c)(qt, rt)
        assert got.shape == ref.shape
        assert float((got - ref).abs().max()) < 1e-12
        both, joints = dec.posed(c).with_joints(qt, rt)
        assert float((both - ref).abs().max()) < 1e-12
        assert joints.shape == ref_joints.shape
        assert float((joints - ref_joints).abs().max()) < 1e-12
        probe = torch.randn(ref.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
        g_ref = torch.autograd.grad((ref * probe).sum(), [qt, rt])
        g_got = torch.autograd.grad((got * probe).sum(), [qt, rt])
        for a, b in zip(g_got, g_ref, strict=True):
            assert float((a - b).abs().max()) < 1e-9 * max(1.0, float(b.abs().max()))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_any_batch_size_and_both_dtypes(body: BodyModel, dtype: torch.dtype) -> None:
    for n in (0, 1, 5):
        shape, q, root = _random_inputs(body, n, seed=n)
        out = body.forward(shape, q, root, dtype=dtype)
        assert out.vertices.shape == (n, body.n_vertices, 3) and out.vertices.dtype == dtype
        assert out.joints.shape == (n, len(body.joint_names), 3)
    shape, q, root = _random_inputs(body, 4, seed=9)
    a = body.forward(shape, q, root, dtype=torch.float32).vertices.double()
    b = body.forward(shape, q, root, dtype=torch.float64).vertices
    assert float((a - b).abs().max()) < 1e-5


def test_onnx_matches_torch_on_1000_parameter_sets(body: BodyModel) -> None:
    import onnxruntime as ort

    from bodyfit.models.assets import verified_asset

    sess = ort.InferenceSession(str(verified_asset("body.onnx")), providers=["CPUExecutionProvider"])
    shape, q, root = _random_inputs(body, 1000, seed=11)
    worst = 0.0
    for s in range(0, 1000, 100):
        part = {"shape": shape[s : s + 100], "coordinates": q[s : s + 100], "root": root[s : s + 100]}
        v, j = sess.run(None, {k: x.astype(np.float32) for k, x in part.items()})
        ref = body.forward(part["shape"], part["coordinates"], part["root"], dtype=torch.float64)
        worst = max(
            worst, float(np.abs(v - ref.vertices.numpy()).max()), float(np.abs(j - ref.joints.numpy()).max())
        )
    assert worst <= 1e-5


def test_skeleton_mesh_sits_inside_the_skin(body: BodyModel) -> None:
    """Bones of the trunk and limbs lie inside the skin (measured: >= 95% of their vertices). The thin
    distal parts (fingers, toes) and the face are not held to it: their skin is within millimetres."""
    out = body.forward(skeleton_mesh=True, dtype=torch.float64)
    assert out.bones is not None
    bones = out.bones[0].numpy()
    vertex_body = body.skeleton.bone_mesh().vertex_body
    idx = np.arange(0, len(bones), 7)
    inside = winding_number(out.vertices[0].numpy(), body.faces, bones[idx]) > 0.5
    names = body.skeleton.body_names
    for name in ("pelvis", "femur_r", "femur_l", "tibia_r", "tibia_l", "torso", "thorax", "humerus_r",
                 "humerus_l", "ulna_r", "ulna_l", "calcn_r", "calcn_l"):  # fmt: skip
        part = inside[vertex_body[idx] == names.index(name)]
        assert part.mean() > 0.9, (name, part.mean())


# --- bad input ---------------------------------------------------------------------------------------------
def test_wrong_coefficient_count_names_the_expected_shape(body: BodyModel) -> None:
    with pytest.raises(ShapeError, match=rf"\(1, {body.n_shape}\).*bone.*identity"):
        body.forward(np.zeros((1, body.n_shape + 1)))


def test_nan_coefficients_are_refused(body: BodyModel) -> None:
    shape = np.zeros((1, body.n_shape))
    shape[0, 2] = np.nan
    with pytest.raises(NonFiniteError, match="shape coefficients"):
        body.forward(shape)


def test_unknown_dof_and_out_of_range_values(body: BodyModel) -> None:
    with pytest.raises(UnknownCoordinateError, match="knee_angle_r"):
        body.skeleton.coordinates({"knee_angle_right": 0.3})
    q = body.skeleton.coordinates({"knee_angle_r": -0.5})
    with pytest.raises(CoordinateRangeError, match="knee_angle_r"):
        body.forward(coordinates=q)


def test_corrupted_body_asset_fails_at_load_with_rebuild_hint(tmp_path: Path) -> None:
    folder = tmp_path / "assets"
    shutil.copytree(REPO / "assets", folder)
    data = bytearray((folder / "body.npz").read_bytes())
    data[len(data) // 2] ^= 0xFF
    (folder / "body.npz").write_bytes(bytes(data))
    with pytest.raises(AssetError, match=r"corrupted or stale.*bodyfit build-assets"):
        BodyModel.load(folder)


def test_manifest_hashes_match_every_file() -> None:
    files = read_manifest()["files"]
    assert {"skeleton.json", "bones.npz", "body.npz", "body.onnx"} <= set(files)
    total = 0
    for name, entry in files.items():
        path = REPO / "assets" / name
        assert sha256(path) == entry["sha256"], name
        total += path.stat().st_size
    assert total <= 50 * 2**20
    metrics = files["body.npz"]["metrics"]
    assert metrics["population"]["bodies"] >= 2000 and metrics["population"]["held_out"] >= 200
    assert metrics["template"]["landmarks"] >= 40
    assert metrics["skinning_heldout_mm"]["after_mean"] < metrics["skinning_heldout_mm"]["before_mean"]


def test_each_vertex_belongs_to_the_body_at_its_place(body: BodyModel) -> None:
    """The highest template vertex is the head's, the lowest a foot's, the widest on each side that hand's;
    every index names a skeleton body."""
    v, owner, names = body.data["vertices_mean"], body.vertex_bodies, body.skeleton.body_names
    assert owner.shape == (body.n_vertices,) and owner.min() >= 0 and owner.max() < len(names)
    assert names[owner[v[:, 1].argmax()]] == "head"
    assert names[owner[v[:, 1].argmin()]] in ("calcn_r", "calcn_l", "toes_r", "toes_l")
    assert names[owner[v[:, 2].argmax()]] == "hand_r" and names[owner[v[:, 2].argmin()]] == "hand_l"


def test_derived_data_is_built_once_per_model_and_not_shared() -> None:
    a, b = BodyModel.load(), BodyModel.load()
    calls: list[int] = []

    def build() -> list[int]:
        calls.append(1)
        return [len(calls)]

    first = a.derived("test.value", build)
    assert a.derived("test.value", build) is first
    assert b.derived("test.value", build) == [2]
    assert len(calls) == 2

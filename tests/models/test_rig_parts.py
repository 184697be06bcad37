"""A person's own skinning weights and joint centres: each solve recovers what a subject was posed with, the
decoder carries them (zero changes give the body model's output bit for bit), the ONNX export of a subject's
decoder matches torch, and the raw scans' closest-point targets lie on the scan."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import torch

from bodyfit.io.scans import sample_surface
from bodyfit.models.body.model import BodyModel
from bodyfit.models.fitting.common.surface import point_to_surface
from bodyfit.models.rig.icp import closest_targets
from bodyfit.models.rig.joints import JointConfig, solve_joints
from bodyfit.models.rig.subject import PersonalParts
from bodyfit.models.rig.weights import (
    WeightConfig,
    adjacency,
    body_adjacency,
    candidate_bodies,
    skinning_columns,
    solve_weights,
)


@pytest.fixture(scope="module")
def model() -> BodyModel:
    return BodyModel.load()


def poses(model: BodyModel, n: int, seed: int, spread: float = 0.5) -> np.ndarray:
    lo, hi = model.skeleton.ranges[:, 0], model.skeleton.ranges[:, 1]
    return np.clip(np.random.default_rng(seed).uniform(lo, hi, (n, len(lo))) * spread, lo, hi)


def posed(
    model: BodyModel, parts: PersonalParts, shape: np.ndarray, q: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (n, V, 3) and joints (n, J, 3) of the person ``parts`` at poses q (n, n_dof)."""
    with torch.no_grad():
        out = parts.decoder(model)(
            torch.as_tensor(np.tile(shape, (len(q), 1))), torch.as_tensor(q), torch.zeros(len(q), 3).double()
        )
    return out[0].numpy(), out[1].numpy()


def spread_weights(model: BodyModel, rounds: int) -> np.ndarray:
    """The body model's weights diffused over the mesh (``rounds`` neighbour averages): another person's
    skinning, softer across every joint, rows still summing to one."""
    a = adjacency(model.faces, model.n_vertices) + sp.identity(model.n_vertices)
    step = sp.diags(1.0 / np.asarray(a.sum(axis=1)).ravel()) @ a
    w = np.asarray(model.data["weights"], np.float64)
    for _ in range(rounds):
        w = step @ w
    return w / w.sum(axis=1, keepdims=True)


def test_personal_decoders_change_nothing_at_the_models_own_weights_and_joints(model: BodyModel) -> None:
    q = torch.as_tensor(poses(model, 2, 1))
    c = torch.as_tensor(np.random.default_rng(1).normal(size=(2, model.n_shape)) * 0.5)
    r = torch.zeros(2, 3, dtype=torch.float64)
    generic = PersonalParts.generic(model)
    for skinning in ("lbs", "lbs_dq"):
        base = model.decoder(torch.float64, skinning)(c, q, r)
        own = model.scaled_decoder(generic.scale_offsets, torch.float64, skinning)
        for a, b in zip(base, own.with_weights(generic.weights)(c, q, r), strict=True):
            assert torch.equal(a, b)
    moved = model.scaled_decoder(generic.scale_offsets + 0.02, torch.float64)(c, q, r)
    bind = torch.as_tensor(np.tile(model.bind_coordinates, (2, 1)))
    at_bind = model.scaled_decoder(generic.scale_offsets + 0.02, torch.float64)(c, bind, r)[0]
    assert float((moved[1] - base[1]).abs().max()) > 0.01  # the joints moved
    assert float((at_bind - model.decoder(torch.float64)(c, bind, r)[0]).abs().max()) < 1e-6  # not the skin


def test_weights_are_recovered_from_a_person_posed_with_other_weights(model: BodyModel) -> None:
    """With the poses, joints and template known, the per-vertex solve finds the weights that pose the
    person: their skin matches the examples and held-out poses far better than the body model's weights."""
    shape = np.random.default_rng(2).normal(size=model.n_shape) * 0.5
    generic = PersonalParts.generic(model)
    truth = PersonalParts(spread_weights(model, 6), generic.offsets, generic.scale_offsets)
    q = poses(model, 9, 3)
    x, _ = posed(model, truth, shape, q)
    neighbours = adjacency(model.faces, model.n_vertices)
    candidates = candidate_bodies(generic.weights, neighbours, body_adjacency(model.skeleton.spec), 3, 0.01)
    columns, _ = skinning_columns(
        generic.decoder(model), shape, q[:6], np.zeros((6, 3)), model.bind_coordinates
    )
    cfg = WeightConfig(smoothness=1e-8)
    w = solve_weights(
        columns, x[:6], np.ones((6, model.n_vertices)), generic.weights, candidates, neighbours, cfg
    )
    assert np.all(w >= 0) and np.allclose(w.sum(axis=1), 1.0)
    solved, _ = posed(model, PersonalParts(w, generic.offsets, generic.scale_offsets), shape, q)
    before, _ = posed(model, generic, shape, q)
    err = np.linalg.norm(solved - x, axis=-1).mean(axis=1) * 1000.0
    was = np.linalg.norm(before - x, axis=-1).mean(axis=1) * 1000.0
    assert was.min() > 0.5, was
    assert err.max() < 0.03 * was.min(), (err, was)


def test_joint_centres_are_recovered_for_a_person_whose_joints_were_moved(model: BodyModel) -> None:
    """A person whose thighs, shins and upper arms are 8% longer and pelvis 6% wider than the shape space
    has them, seen in poses known only to about a degree: the joint solve (scale offsets with the poses)
    puts their joint centres back within a millimetre."""
    shape = np.random.default_rng(4).normal(size=model.n_shape) * 0.5
    generic = PersonalParts.generic(model)
    segments = model.skeleton.segments
    moved = generic.scale_offsets.copy()
    mean = np.asarray(model.data["scale_mean"], np.float64)
    for name, factor in (("femur_r", 0.08), ("femur_l", 0.08), ("tibia_r", 0.08), ("humerus_l", 0.08)):
        moved[segments.index(name), 1] = factor * mean[segments.index(name), 1]
    moved[segments.index("pelvis"), 2] = 0.06 * mean[segments.index("pelvis"), 2]
    truth = PersonalParts(generic.weights, generic.offsets, moved)
    q = poses(model, 6, 5)
    x, joints = posed(model, truth, shape, q)
    start = np.clip(q + np.random.default_rng(5).normal(size=q.shape) * 0.02, *model.skeleton.ranges.T)
    cfg = JointConfig(ridge=1e-9, stride=4, steps=3)
    solved, q_found, r_found = solve_joints(
        model, generic, shape, start, np.zeros((6, 3)), x, np.ones(x.shape[:2]), cfg
    )
    assert np.abs(r_found).max() < 0.002
    _, found = posed(model, PersonalParts(generic.weights, generic.offsets, solved), shape, q_found)
    _, before = posed(model, generic, shape, q)
    limbs = [model.joint_names.index(n) for n in ("hip_r", "knee_r", "ankle_r", "knee_l", "elbow_l")]
    was = np.linalg.norm(before - joints, axis=-1)[:, limbs].mean() * 1000.0
    err = np.linalg.norm(found - joints, axis=-1)[:, limbs].mean() * 1000.0
    assert was > 10.0 and err < 1.0, (was, err)
    limit = JointConfig().limit * np.abs(mean)
    capped, _, _ = solve_joints(model, generic, shape, q, np.zeros((6, 3)), x, np.ones(x.shape[:2]))
    assert np.all(np.abs(capped) <= limit + 1e-12)


def test_a_subject_decoder_exports_to_onnx_within_a_hundredth_of_a_millimetre(model: BodyModel) -> None:
    import onnxruntime as ort

    from bodyfit.models.body.onnx_export import export_body_onnx

    generic = PersonalParts.generic(model)
    rng = np.random.default_rng(6)
    parts = PersonalParts(
        spread_weights(model, 3), rng.normal(size=generic.offsets.shape) * 0.003, generic.scale_offsets + 0.03
    )
    session = ort.InferenceSession(
        export_body_onnx(parts.decoder(model, torch.float32), model.n_shape),
        providers=["CPUExecutionProvider"],
    )
    shape, q = rng.normal(size=(1, model.n_shape)) * 0.5, poses(model, 1, 7)
    feeds = {"shape": shape.astype(np.float32), "coordinates": q.astype(np.float32)}
    feeds["root"] = np.zeros((1, 3), np.float32)
    vertices, joints = session.run(["vertices", "joints"], feeds)
    ref_v, ref_j = posed(model, parts, shape[0], q)
    assert np.abs(vertices - ref_v).max() < 1e-5 and np.abs(joints - ref_j).max() < 1e-5


def test_closest_targets_lie_on_the_scan_and_move_only_across_it(model: BodyModel) -> None:
    """A mesh 6 mm outside a scan of it: every vertex's target is on the scan's surface, straight below."""
    v = posed(model, PersonalParts.generic(model), np.zeros(model.n_shape), poses(model, 1, 8))[0][0]
    points, _ = sample_surface(v, model.faces, 60_000, seed=0)
    from bodyfit.models.fitting.common.surface import vertex_normals

    normals = vertex_normals(v, model.faces)
    targets, confidence = closest_targets(v + 0.006 * normals, model.faces, points)
    seen = confidence > 0.1
    assert seen.mean() > 0.95
    off = np.abs(point_to_surface(targets[seen], v, model.faces))
    assert np.median(off) < 0.001 and np.median(np.linalg.norm(targets[seen] - v[seen], axis=1)) < 0.0015

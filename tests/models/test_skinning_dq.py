"""Swing-twist skinning (skinning="lbs_dq"): the dual-quaternion algebra, the twist rig read from the
skeleton, exactness where LBS is exact, rigid twists where LBS collapses, the model's other paths under it,
and the ONNX export's parity."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from benchmarks.personal import SEGMENTS, capped_volume, region
from bodyfit.models.body.model import BodyDecoder, BodyModel
from bodyfit.models.body.swing_twist import (
    TwistSkin,
    class_dual_quaternions,
    class_rigid,
    class_twists,
    cross,
    dual_quaternion_multiply,
    monomial_table,
    pair_rows,
    pair_weights,
    prune_twist_weights,
    quaternion_multiply,
    rigid_of_dual_quaternion,
    skin_columns,
    swing_transforms,
    twist_dual_quaternions,
    twist_rig,
)
from bodyfit.models.errors import BodyfitError
from bodyfit.models.rotations import axis_angle_matrix
from tests.conftest import random_pose

F64 = torch.float64


@pytest.fixture(scope="module")
def model() -> BodyModel:
    return BodyModel.load()


@pytest.fixture(scope="module")
def dq(model: BodyModel) -> BodyDecoder:
    return model.decoder(F64, "lbs_dq")


def _bind_with(model: BodyModel, values: dict[str, float], batch: int = 1) -> torch.Tensor:
    q = np.tile(model.bind_coordinates, (batch, 1))
    for name, value in values.items():
        q[:, model.dof_names.index(name)] = value
    return torch.as_tensor(q)


def _run(
    decoder: BodyDecoder, model: BodyModel, q: torch.Tensor, shape: np.ndarray | None = None
) -> np.ndarray:
    c = torch.zeros(len(q), model.n_shape, dtype=F64) if shape is None else torch.as_tensor(shape)
    return decoder(c, q, torch.zeros(len(q), 3, dtype=F64))[0].numpy()


def _descends(parents: list[int], body: int, ancestor: int) -> bool:
    while body >= 0:
        if body == ancestor:
            return True
        body = parents[body]
    return False


def test_dual_quaternion_algebra_matches_matrices() -> None:
    g = torch.Generator().manual_seed(0)
    a, b = torch.randn(4, 6, dtype=F64, generator=g), torch.randn(4, 6, dtype=F64, generator=g)
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    hamilton = torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ]
    )
    assert float((quaternion_multiply(a, b) - hamilton).abs().max()) < 1e-14
    assert float((cross(a[:3], b[:3]) - torch.linalg.cross(a[:3], b[:3], dim=0)).abs().max()) < 1e-14
    # A twist is the rotation about its line: Rodrigues about the axis, the centre fixed.
    angle = torch.randn(3, 2, dtype=F64, generator=g)
    axis = torch.nn.functional.normalize(torch.randn(3, 3, 1, dtype=F64, generator=g), dim=0)
    centre = torch.randn(3, 3, 2, dtype=F64, generator=g)
    T = rigid_of_dual_quaternion(twist_dual_quaternions(angle, axis, centre))
    R = axis_angle_matrix(axis[..., 0].T[:, None, :].expand(3, 2, 3), angle).permute(2, 3, 0, 1)
    assert float((T[:, :3] - R).abs().max()) < 1e-14
    assert float((T[:, 3] - (centre - (R * centre.unsqueeze(0)).sum(1))).abs().max()) < 1e-14
    # The dual-quaternion product composes the rigid motions as their matrices do.
    qa = twist_dual_quaternions(angle, axis, centre)
    qb = twist_dual_quaternions(angle.flip(0), axis.flip(1), centre.flip(1))
    Ta, Tb, Tab = (rigid_of_dual_quaternion(x) for x in (qa, qb, dual_quaternion_multiply(qa, qb)))
    rot = (Ta[:, :3].unsqueeze(2) * Tb[:, :3].unsqueeze(0)).sum(1)
    shift = (Ta[:, :3] * Tb[:, 3].unsqueeze(0)).sum(1) + Ta[:, 3]
    assert float((Tab[:, :3] - rot).abs().max()) < 1e-14
    assert float((Tab[:, 3] - shift).abs().max()) < 1e-14


def test_the_classes_twists_from_one_table_product_equal_their_chains_products(model: BodyModel) -> None:
    """The monomial table gives every class's dual quaternion, for any angles and bone coefficients, as the
    chain of joint twists does; the pair rows normalised give the dual-quaternion blend's rigid map."""
    rig = twist_rig(model.skeleton, model.data)
    g = np.random.default_rng(5)
    angle = torch.as_tensor(g.uniform(-3.0, 3.0, size=(4, len(rig.coordinate))))
    bone = torch.as_tensor(np.c_[np.ones(4), g.normal(size=(4, len(rig.centre) - 1))])
    centre = torch.einsum("bn,nkc->ckb", bone, torch.as_tensor(rig.centre))
    axis = torch.as_tensor(rig.axis.T[..., None])
    chain = torch.as_tensor(rig.chain)
    expected = class_twists(twist_dual_quaternions(angle.T, axis, centre), chain).permute(2, 0, 1)
    got = class_dual_quaternions(angle, bone, chain, torch.as_tensor(monomial_table(rig)))
    assert float((got - expected).abs().max()) < 1e-12
    rigid = rigid_of_dual_quaternion(expected.permute(1, 2, 0)).permute(3, 0, 1, 2).flatten(1, 2)
    assert float((class_rigid(got) - rigid).abs().max()) < 1e-12
    # A blend of two classes: the pair rows weighted and normalised are the blend's rigid map.
    t = np.zeros((1, rig.n_class))
    t[0, [2, 6]] = 0.3, 0.7
    pairs, weights = pair_weights(t)
    rows = (pair_rows(got, torch.as_tensor(pairs)) * torch.as_tensor(weights)).sum(-1)  # (B, 13)
    blend = (got * torch.as_tensor(t)).sum(-1)  # (B, 8)
    rigid = rigid_of_dual_quaternion((blend / blend[:, :4].norm(dim=1, keepdim=True)).T)  # (3, 4, B)
    assert float((rows[:, :12] / rows[:, 12:] - rigid.permute(2, 0, 1).flatten(1)).abs().max()) < 1e-12


def test_the_skin_columns_carry_each_vertex_by_its_twist_class(model: BodyModel) -> None:
    """A vertex whose twist lies in one class c is carried by its bodies' transforms S_j W_c (M_j where the
    body is in c); a vertex that blends classes by its bodies' swings S_j W_0 (M_j where the body is in the
    untwisted class 0). Each column holds the vertex's weight on that body."""
    rig = twist_rig(model.skeleton, model.data)
    weights = np.asarray(model.data["weights"], np.float64)
    twist = rig.class_weights(weights)
    extra, columns = skin_columns(weights, twist, rig.body_class)
    n_body = weights.shape[1]
    mixed = (twist != 0).sum(axis=1) > 1
    target = np.where(mixed, 0, np.argmax(twist, axis=1))
    assert len(extra) and (rig.body_class[extra[:, 0]] != extra[:, 1]).all()
    v, k = np.nonzero(columns)
    body = np.r_[np.arange(n_body), extra[:, 0]][k]
    cls = np.r_[rig.body_class, extra[:, 1]][k]
    assert (cls == target[v]).all()
    assert np.array_equal(columns[v, k], weights[v, body])
    assert len(v) == np.count_nonzero(weights)  # every weight in exactly one column
    assert (columns[mixed, n_body:] != 0).any() and (columns[~mixed, n_body:] != 0).any()


def test_the_skin_is_the_swings_applied_to_the_blended_twist(model: BodyModel, dq: BodyDecoder) -> None:
    """Every vertex moves by sum_j w_j S_j DLB_v(W) v, computed here per vertex from the classes' dual
    quaternions: the skin's columns, blocks and the blended vertices written into the rest change the cost
    only. A vertex put in the wrong column, block or place fails here."""
    B, V = 3, model.n_vertices
    q = torch.as_tensor(random_pose(model.skeleton, B, seed=11))
    shape = torch.as_tensor(np.random.default_rng(11).normal(size=(B, model.n_shape)))
    scales, coeffs = dq._shape_terms(shape)
    M = dq._transforms(dq.fk.frames_cm(q, None, scales), dq._bind_shift(coeffs))  # (3, 4, n_body, B)
    twists = dq.class_twists(q, coeffs)  # (8, n_class, B)
    S = swing_transforms(M, rigid_of_dual_quaternion(twists)[:, :, dq.body_class])
    blend = torch.einsum("vc,kcb->kvb", torch.as_tensor(dq._twist), twists)
    X = rigid_of_dual_quaternion(blend / blend[:4].norm(dim=0, keepdim=True))  # (3, 4, V, B)
    basis = torch.as_tensor(np.asarray(dq._basis, np.float64).reshape(len(dq._basis), -1))
    rest = (coeffs @ basis).reshape(B, 3, V).permute(1, 2, 0)  # (3, V, B)
    x = (X[:, :3] * rest.unsqueeze(0)).sum(1) + X[:, 3]
    Sv = torch.einsum("vj,ikjb->ikvb", torch.as_tensor(dq._weights), S)
    expected = ((Sv[:, :3] * x.unsqueeze(0)).sum(1) + Sv[:, 3]).permute(2, 1, 0)
    got = dq(shape, q, torch.zeros(B, 3, dtype=F64))[0]
    assert float((got - expected).abs().max()) < 1e-10
    skin = dq.skin
    assert isinstance(skin, TwistSkin) and sum(skin.sizes) == V and len(skin.mixed) > 0.1 * V


def test_small_twist_weights_are_folded_into_the_main_class() -> None:
    """Classes below the floor leave the blend and their weight goes to the vertex's main class, continuously
    in the weights; weights above it are lowered by the floor."""
    twist = np.array([[0.97, 0.03, 0.0], [0.5, 0.45, 0.05], [0.2, 0.0, 0.8], [1.0, 0.0, 0.0]])
    pruned = prune_twist_weights(twist, 0.05)
    assert np.allclose(pruned.sum(axis=1), 1.0)
    assert np.allclose(pruned, [[1.0, 0.0, 0.0], [0.6, 0.4, 0.0], [0.15, 0.0, 0.85], [1.0, 0.0, 0.0]])
    assert np.array_equal(prune_twist_weights(twist, 0.0), twist)
    near = prune_twist_weights(np.array([[0.95, 0.0501], [0.95, 0.0499]]), 0.05)
    assert np.abs(near[0] - near[1]).max() < 1e-3


def test_the_twist_joints_and_classes_come_from_the_skeleton(model: BodyModel) -> None:
    rig = twist_rig(model.skeleton, model.data)
    names = {model.dof_names[i] for i in rig.coordinate}
    sides = ("hip_rotation", "arm_rot", "pro_sup")
    assert names == {f"{n}_{s}" for n in sides for s in "rl"} | {"neck_rotation"}
    bodies = model.skeleton.body_names
    cls = {b: int(rig.body_class[bodies.index(b)]) for b in bodies}
    assert cls["pelvis"] == cls["thorax"] == cls["scapula_r"] == 0
    assert cls["humerus_r"] == cls["ulna_r"] != cls["radius_r"] == cls["hand_r"] != 0
    assert cls["femur_r"] == cls["tibia_r"] == cls["toes_r"] != cls["femur_l"]
    assert np.allclose(np.linalg.norm(rig.axis, axis=1), 1.0)


def test_every_twist_is_exactly_the_child_s_rotation_about_the_bind_axis(
    model: BodyModel, dq: BodyDecoder
) -> None:
    """With the other coordinates random, moving a twist coordinate alone leaves the swing of the joint's
    child unchanged (and every body outside the child's subtree): the joint's rotation factors as
    swing @ twist with the twist about the bind-pose axis through the joint centre. A wrong axis, centre or
    factor order fails here. (Bodies further down carry the twist in their swings, as they should: the knee
    bends about a femur turned by the hip's rotation.)"""
    rig = twist_rig(model.skeleton, model.data)
    q0 = torch.as_tensor(random_pose(model.skeleton, 3, seed=4))
    shape = torch.as_tensor(np.random.default_rng(4).normal(size=(3, model.n_shape)))
    scales, coeffs = dq._shape_terms(shape)

    def swings(q: torch.Tensor) -> torch.Tensor:
        return swing_transforms(
            transforms(q), rigid_of_dual_quaternion(dq.class_twists(q, coeffs))[:, :, dq.body_class]
        )

    def transforms(q: torch.Tensor) -> torch.Tensor:
        return dq._transforms(dq.fk.frames_cm(q, None, scales), dq._bind_shift(coeffs))

    base = swings(q0)
    spec = model.skeleton.spec
    parents = spec.body_parent_index
    for col in rig.coordinate:
        joint = next(j for j in spec.joints if any(a.coordinate == model.dof_names[col] for a in j.rotations))
        child = spec.body_names.index(joint.child)
        below = [b for b in range(len(parents)) if b != child and _descends(parents, b, child)]
        kept = [b for b in range(len(parents)) if b not in below]
        q = q0.clone()
        q[:, col] += 0.6
        assert float((swings(q) - base)[:, :, kept].abs().max()) < 1e-12, model.dof_names[col]
        assert float((transforms(q) - transforms(q0))[:, :, child].abs().max()) > 0.1  # the child did turn


def test_lbs_dq_equals_lbs_where_lbs_is_exact(model: BodyModel, dq: BodyDecoder) -> None:
    lbs = model.decoder(F64)
    q = torch.as_tensor(random_pose(model.skeleton, 4, seed=2))
    shape = np.random.default_rng(2).normal(size=(4, model.n_shape))
    single = np.asarray(model.data["weights"]).max(axis=1) > 1 - 1e-6
    a, b = _run(lbs, model, q, shape), _run(dq, model, q, shape)
    assert np.abs(a - b)[:, single].max() < 1e-9  # vertices on one body: its transform exactly
    assert np.abs(a - b).max() > 1e-3
    # With every twist coordinate at its bind value the twists are the identity: plain LBS everywhere.
    rig = twist_rig(model.skeleton, model.data)
    q[:, rig.coordinate] = torch.as_tensor(rig.bind)
    assert np.abs(_run(lbs, model, q, shape) - _run(dq, model, q, shape)).max() < 1e-9


def test_a_pure_twist_turns_the_forearm_rigidly_about_its_axis(model: BodyModel, dq: BodyDecoder) -> None:
    """Pronation alone: every forearm vertex keeps its distance to the pronation axis under lbs_dq, and
    the forearm keeps its volume; LBS pulls vertices towards the axis (candy wrapper)."""
    rig = twist_rig(model.skeleton, model.data)
    k = list(rig.coordinate).index(model.dof_names.index("pro_sup_r"))
    axis, centre = rig.axis[k], rig.centre[0, k]

    def distance(v: np.ndarray) -> np.ndarray:
        d = v - centre
        return np.linalg.norm(d - np.outer(d @ axis, axis), axis=1)

    mask, faces = region(model, SEGMENTS["forearm"], "r")
    rest = _run(dq, model, _bind_with(model, {}))[0]
    q = _bind_with(model, {"pro_sup_r": 0.0})
    twisted, linear = _run(dq, model, q)[0], _run(model.decoder(F64), model, q)[0]
    assert np.abs(distance(twisted) - distance(rest))[mask].max() < 1e-8
    assert (distance(rest) - distance(linear))[mask].max() > 3e-3
    volume = capped_volume(rest, model.faces[faces])
    assert abs(capped_volume(twisted, model.faces[faces]) / volume - 1.0) < 0.01
    assert capped_volume(linear, model.faces[faces]) / volume < 0.95


def test_the_fixed_shape_skin_offsets_and_restriction_follow_the_twist(
    model: BodyModel, dq: BodyDecoder
) -> None:
    q = torch.as_tensor(random_pose(model.skeleton, 2, seed=7))
    root = torch.zeros(2, 3, dtype=F64)
    c = torch.as_tensor(np.random.default_rng(7).normal(size=(1, model.n_shape)))
    full = dq(c.expand(2, -1), q, root)[0]
    assert float((dq.posed(c)(q, root) - full).abs().max()) < 1e-12
    subset = np.arange(0, model.n_vertices, 5)
    assert float((dq.restricted(subset)(c.expand(2, -1), q, root)[0] - full[:, subset]).abs().max()) < 1e-12
    offsets = np.random.default_rng(8).normal(scale=0.01, size=(model.n_vertices, 3))
    moved = dq.with_offsets(offsets)(c.expand(2, -1), q, root)[0]
    frames = dq(c.expand(2, -1), q, root)[2]
    expected = full.numpy() + np.einsum("bvij,vj->bvi", dq.blended_rotations(frames, q), offsets)
    assert np.abs(moved.numpy() - expected).max() < 1e-6  # as for LBS: the bind rotations hold to ~1e-6
    with pytest.raises(BodyfitError, match="coordinates"):
        dq.blended_rotations(frames)


def test_gradients_match_finite_differences(dq: BodyDecoder, model: BodyModel) -> None:
    sub = dq.restricted(np.arange(0, model.n_vertices, 97))
    q0 = random_pose(model.skeleton, 1, seed=3)
    probe = torch.randn(1, len(np.arange(0, model.n_vertices, 97)), 3, dtype=F64)

    def f(c: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        return (sub(c, q, torch.zeros(1, 3, dtype=F64))[0] * probe).sum()

    c = torch.tensor(np.random.default_rng(3).normal(size=(1, model.n_shape)) * 0.5, requires_grad=True)
    assert torch.autograd.gradcheck(f, (c, torch.tensor(q0, requires_grad=True)), eps=1e-6, atol=1e-6)


def test_the_model_takes_the_skinning_as_an_option(model: BodyModel) -> None:
    assert model.skinning == "lbs" and model.decoder(F64) is model.decoder(F64, "lbs")
    assert model.decoder(F64, "lbs_dq").skinning == "lbs_dq"
    with pytest.raises(BodyfitError, match="skinning must be one of"):
        model.decoder(F64, "dqs")
    with pytest.raises(BodyfitError, match="skinning must be one of"):
        BodyModel(model.skeleton, model.data, skinning="candy")
    q = random_pose(model.skeleton, 2, seed=1)
    a = model.forward(coordinates=q, dtype=F64, skinning="lbs_dq").vertices
    b = BodyModel(model.skeleton, model.data, skinning="lbs_dq").forward(coordinates=q, dtype=F64).vertices
    assert float((a - b).abs().max()) == 0.0


def test_onnx_export_matches_torch(model: BodyModel) -> None:
    import onnxruntime as ort

    from bodyfit.models.body.onnx_export import export_body_onnx

    session = ort.InferenceSession(
        export_body_onnx(model.decoder(torch.float32, "lbs_dq"), model.n_shape),
        providers=["CPUExecutionProvider"],
    )
    rng = np.random.default_rng(12)
    for batch in (1, 7):
        feed = {
            "shape": rng.normal(size=(batch, model.n_shape)).astype(np.float32),
            "coordinates": random_pose(model.skeleton, batch, seed=batch).astype(np.float32),
            "root": rng.normal(scale=0.2, size=(batch, 3)).astype(np.float32),
        }
        ref = model.decoder(F64, "lbs_dq")(*(torch.as_tensor(feed[k], dtype=F64) for k in feed))
        vertices, joints = session.run(None, feed)
        assert np.linalg.norm(vertices - ref[0].numpy(), axis=-1).max() < 1e-5
        assert np.abs(joints - ref[1].numpy()).max() < 1e-5

"""The bone mesh inside the skin: the winding-number measure itself, and the shipped assets against it."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from benchmarks.bones import (
    NAMED_POSES,
    Tally,
    pose_coordinates,
    region_of_vertices,
    skin_cavity,
    surface_distance,
)
from bodyfit.models.body.bone_geometry import apply_bone_geometry, fit_bone_geometry, principal_alignment
from bodyfit.models.body.geometry import (
    boundary_loops,
    cavity_faces,
    face_clusters,
    fast_winding_number,
    skin_envelope,
    winding_number,
)
from bodyfit.models.body.model import BodyModel
from bodyfit.models.skeleton.bones import BoneMesh


@pytest.fixture(scope="module")
def sphere() -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=4, radius=0.5)


def _box_points(centre: tuple[float, float, float], half: float) -> np.ndarray:
    box = trimesh.creation.box(extents=(2 * half, 2 * half, 2 * half))
    return np.asarray(box.vertices) + np.asarray(centre)


def test_box_inside_a_sphere_winds_once(sphere: trimesh.Trimesh) -> None:
    points = _box_points((0.1, 0.0, -0.05), 0.2)
    for wn in (winding_number, fast_winding_number):
        w = wn(np.asarray(sphere.vertices), np.asarray(sphere.faces), points)
        assert np.allclose(w, 1.0, atol=0.02), (wn.__name__, w)


def test_box_outside_a_sphere_winds_zero(sphere: trimesh.Trimesh) -> None:
    points = _box_points((0.9, 0.2, 0.0), 0.15)
    for wn in (winding_number, fast_winding_number):
        w = wn(np.asarray(sphere.vertices), np.asarray(sphere.faces), points)
        assert np.allclose(w, 0.0, atol=0.02), (wn.__name__, w)


def test_box_straddling_the_surface_is_split(sphere: trimesh.Trimesh) -> None:
    """A box across the surface: its corners beyond the radius are outside, the others inside."""
    points = _box_points((0.5, 0.0, 0.0), 0.1)
    w = fast_winding_number(np.asarray(sphere.vertices), np.asarray(sphere.faces), points)
    beyond = np.linalg.norm(points, axis=1) > 0.5
    assert np.array_equal(w < 0.5, beyond)


def test_fast_winding_number_matches_the_exact_sum_near_a_body_surface(sphere: trimesh.Trimesh) -> None:
    rng = np.random.default_rng(0)
    points = rng.normal(size=(400, 3)) * 0.3
    v, f = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    exact, fast = winding_number(v, f, points), fast_winding_number(v, f, points)
    assert np.abs(exact - fast).max() < 0.03
    assert np.array_equal(exact < 0.5, fast < 0.5)


def test_face_clusters_partition_the_faces() -> None:
    centroids = np.random.default_rng(1).uniform(size=(1000, 3))
    groups = face_clusters(centroids, leaf=32)
    assert max(len(g) for g in groups) <= 32
    assert np.array_equal(np.sort(np.concatenate(groups)), np.arange(1000))


def test_surface_distance_of_points_off_a_sphere(sphere: trimesh.Trimesh) -> None:
    points = np.array([[0.6, 0.0, 0.0], [0.0, 0.55, 0.0], [0.0, 0.0, -0.7]])
    d = surface_distance(np.asarray(sphere.vertices), np.asarray(sphere.faces), points)
    assert np.allclose(d, [0.1, 0.05, 0.2], atol=2e-3)


# --- the shipped assets ------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def body() -> BodyModel:
    return BodyModel.load()


def _outside(body: BodyModel, poses: list[str], shift: float = 0.0) -> dict:
    """Tally figures of the mean body in named poses, every 8th bone vertex, bones shifted by ``shift`` m
    forward."""
    pick = np.arange(0, len(body.skeleton.bone_mesh().vertices), 8)
    region = region_of_vertices(body)[pick]
    q = np.stack([pose_coordinates(body, NAMED_POSES[p]) for p in poses])
    out = body.forward(None if len(q) == 1 else np.zeros((len(q), body.n_shape)), q, skeleton_mesh=True,
                       dtype=torch.float64)  # fmt: skip
    assert out.bones is not None
    tally = Tally.empty()
    for i, name in enumerate(poses):
        bones = out.bones[i, pick].numpy() + np.array([shift, 0.0, 0.0])
        tally.add(name, out.vertices[i].numpy(), body.faces, bones, region, skin_cavity(body))
    return tally.figures()


# The shipped assets carry the bone meshes fitted inside the skin per body and per bone (mean body, every 8th
# bone vertex, these poses, against the skin with its mouth closed: about 0.02 outside; with one map per body
# only, 0.11-0.15), so a bound of 0.05 fails if the per-bone fit is lost; the trunk and the long bones of the
# limbs within about 6%.
SHIPPED_OUTSIDE_MAX = 0.05
INNER_REGIONS = ("ribs", "spine", "pelvis", "legs", "arms")
INNER_REGION_MAX = 0.08


def test_shipped_bones_mostly_inside_the_skin(body: BodyModel) -> None:
    figures = _outside(body, ["neutral", "crouch", "pro_sup_max"])
    assert figures["bones_outside_frac"] < SHIPPED_OUTSIDE_MAX, figures
    for region in INNER_REGIONS:
        assert figures["regions"][region]["outside_frac"] < INNER_REGION_MAX, (region, figures["regions"])


def test_bones_moved_out_of_the_skin_are_counted_outside(body: BodyModel) -> None:
    """The same measure on bones shifted 15 cm forward: well above the shipped assets' bound."""
    figures = _outside(body, ["neutral"], shift=0.15)
    assert figures["bones_outside_frac"] > 0.6
    assert figures["regions"]["ribs"]["max_mm"] > 50.0


def test_bone_geometry_fit_brings_a_protruding_bone_inside() -> None:
    """A 'skull' poking 2 cm out of a 10 cm skin is moved and scaled inside it, keeping most of its size."""
    skin = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    bone = trimesh.creation.icosphere(subdivisions=2, radius=0.04)
    vertices = np.asarray(bone.vertices) + np.array([0.08, 0.0, 0.0])
    zeros = np.zeros(len(vertices), np.int64)
    mesh = BoneMesh(vertices, np.asarray(bone.faces), zeros, zeros)
    skins = np.asarray(skin.vertices)[None]
    frames, scales = np.eye(4)[None, None], np.ones((1, 1, 3))
    before = fast_winding_number(skins[0], np.asarray(skin.faces), vertices) < 0.5
    geometry = fit_bone_geometry(mesh, ["head"], skins, np.asarray(skin.faces), frames, scales)
    moved = apply_bone_geometry(mesh, geometry)
    after = fast_winding_number(skins[0], np.asarray(skin.faces), moved) < 0.5
    assert before.mean() > 0.2
    assert after.mean() == 0.0
    assert np.linalg.svd(geometry[0, :, :3])[1].min() > 0.7


def test_envelope_caps_a_removed_face_patch_watertight_with_the_same_volume() -> None:
    """A box with one side's triangles taken out as a 'pocket' is closed again by the cap: watertight,
    outward, the box's volume; a point just inside the opening winds once."""
    box = trimesh.creation.box(extents=(0.2, 0.2, 0.2))
    v, f = np.asarray(box.vertices), np.asarray(box.faces)
    top = np.all(v[f][:, :, 2] > 0.09, axis=1)
    assert top.sum() == 2
    loops = boundary_loops(f[~top])
    assert [len(loop) for loop in loops] == [4]
    ev, ef = skin_envelope(v, f, top)
    closed = trimesh.Trimesh(ev, ef, process=False)
    assert closed.is_watertight and abs(closed.volume - 0.008) < 1e-9
    assert fast_winding_number(ev, ef, np.array([[0.0, 0.0, 0.099]]))[0] > 0.5


def test_cavity_faces_of_a_convex_surface_are_none(sphere: trimesh.Trimesh) -> None:
    v, f = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    assert not cavity_faces(v, f, np.ones(len(v), bool), step=0.05, close=2).any()


def test_shipped_skin_pockets_are_in_the_head_and_close_watertight(body: BodyModel) -> None:
    """The shipped assets' pockets (mouth, nostrils) lie on the head's skin; the envelope is watertight."""
    cavity = np.asarray(body.data["skin_cavity"], bool)
    assert 500 < cavity.sum() < 0.2 * len(cavity)
    head = np.asarray(body.data["weights"])[:, body.skeleton.body_names.index("head")]
    assert (head[body.faces[cavity]].mean(axis=1) > 0.5).mean() > 0.95
    skin = body.forward(dtype=torch.float64).vertices[0].numpy()
    ev, ef = skin_envelope(skin, body.faces, cavity)
    assert trimesh.Trimesh(ev, ef, process=False).is_watertight


def test_principal_alignment_recovers_a_turned_copy() -> None:
    rng = np.random.default_rng(0)
    points = rng.normal(size=(500, 3)) * np.array([0.08, 0.03, 0.01])
    R = trimesh.transformations.rotation_matrix(0.7, (0.3, 1.0, 0.2))[:3, :3]
    skin = points @ R.T + np.array([0.01, -0.02, 0.03])
    R_fit, t_fit = principal_alignment(points, skin)
    assert np.abs(points @ R_fit.T + t_fit - skin).max() < 1e-6

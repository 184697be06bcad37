"""Raw-scan fitting: mesh geometry helpers, non-rigid refinement, a whole fit of a turned, moved body in
millimetres, a real T-posed body as bare points fitted facing the right way, and bad input (too few points,
non-finite values, a shape that is not a body)."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from benchmarks import corrupt
from bodyfit.io.scans import ScanError, load_scan, sample_surface, scan_from_arrays
from bodyfit.models.body.anny_posed import random_poses
from bodyfit.models.body.model import BodyModel
from bodyfit.models.fitting.common.nonrigid import NonRigidConfig, refine_nonrigid
from bodyfit.models.fitting.common.surface import (
    coarse_faces,
    laplacian,
    point_to_surface,
    point_triangle_distance,
    vertex_faces,
    vertex_normals,
)
from bodyfit.models.fitting.registered.fitter import RegisteredFitter, Stage, farthest_point_subset
from bodyfit.models.fitting.registered.smpl_topology import SMPL_TO_BODY, SOURCE_DIR, read_obj
from bodyfit.models.fitting.scan.config import DEFAULT_BRANCHES, DEFAULT_PHASES, ScanFitConfig
from bodyfit.models.fitting.scan.fitter import (
    REACH_MM,
    ScanFit,
    ScanFitter,
    clean_points,
    orientation_candidates,
)
from bodyfit.models.fitting.scan.scene import NoPersonError

KINECT = Path(__file__).resolve().parents[1] / "data" / "scans" / "pcl_template_alignment_person.pcd"


@pytest.fixture(scope="module")
def model() -> BodyModel:
    return BodyModel.load()


@pytest.fixture(scope="module")
def fitter(model: BodyModel) -> ScanFitter:
    return ScanFitter(model)


def test_a_scan_fitter_shares_a_registered_fitter_of_its_model_only(
    model: BodyModel, fitter: ScanFitter
) -> None:
    """A ScanFitter can share another's RegisteredFitter (a service's); one of another model object is
    refused rather than fitted with the wrong template."""
    shared = ScanFitter(model, fitter=fitter.fitter)
    assert shared.fitter is fitter.fitter and shared.limbs.fitter is fitter.fitter
    with pytest.raises(ValueError, match="same BodyModel"):
        ScanFitter(BodyModel.load(), fitter=fitter.fitter)


def test_point_to_surface_matches_brute_force() -> None:
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    points = np.random.default_rng(0).normal(size=(300, 3)) * 0.4
    brute = point_triangle_distance(points[:, None, :], sphere.triangles[None]).min(axis=1)
    np.testing.assert_allclose(point_to_surface(points, sphere.vertices, sphere.faces), brute, atol=1e-12)
    # and it is the distance to a sphere, up to the facets' sagitta
    assert np.abs(brute - np.abs(np.linalg.norm(points, axis=1) - 0.5)).max() < 5e-3


def test_point_to_surface_is_the_nearest_ring_triangle_on_a_body(model: BodyModel) -> None:
    """On a concave mesh (the template: armpits, fingers) and points on both sides of it, every point's
    distance is that of the nearest triangle around its nearest vertex, measured in full."""
    v, f = model.data["vertices_mean"], model.faces
    rng = np.random.default_rng(1)
    points = v[rng.choice(len(v), 2000)] + rng.normal(0.0, 0.01, (2000, 3))
    ring = vertex_faces(f, len(v))[cKDTree(v).query(points)[1]]  # (N, K)
    full = point_triangle_distance(points[:, None, :], v[f[np.maximum(ring, 0)]])
    expected = np.where(ring >= 0, full, np.inf).min(axis=1)
    np.testing.assert_allclose(point_to_surface(points, v, f), expected, atol=1e-12)


def test_vertex_faces_and_laplacian() -> None:
    box = trimesh.creation.box()
    ring = vertex_faces(box.faces, len(box.vertices))
    for v in range(len(box.vertices)):
        expected = set(np.flatnonzero((box.faces == v).any(axis=1)))
        assert set(ring[v][ring[v] >= 0]) == expected
    L = laplacian(box.faces, len(box.vertices))
    np.testing.assert_allclose(L @ np.ones(len(box.vertices)), 0.0, atol=1e-12)  # constants are harmonic
    assert np.all(L.diagonal() == 1.0)


def test_farthest_point_subset_picks_the_point_farthest_from_those_picked() -> None:
    points = np.random.default_rng(3).normal(size=(400, 3))
    chosen = farthest_point_subset(points, 60)
    assert chosen[0] == np.argmin(np.linalg.norm(points - points.mean(0), axis=1))
    for k in range(1, len(chosen)):
        gap = cKDTree(points[chosen[:k]]).query(points)[0]
        assert gap[chosen[k]] == gap.max()
    assert len(set(chosen)) == 60 and len(farthest_point_subset(points, 1000)) == 400


def test_coarse_faces_close_a_sphere_and_face_outwards() -> None:
    """The dual of the regions of a spread subset of a sphere's vertices is a closed surface (Euler
    characteristic 2, every edge in two faces) oriented as the sphere: its normals point outwards."""
    sphere = trimesh.creation.icosphere(subdivisions=4)
    subset = np.sort(farthest_point_subset(sphere.vertices, 150))
    faces = coarse_faces(sphere.vertices, sphere.faces, subset)
    coarse = trimesh.Trimesh(sphere.vertices[subset], faces, process=False)
    assert coarse.is_watertight and coarse.euler_number == 2 and len(coarse.vertices) == 150
    normals = vertex_normals(coarse.vertices, faces)
    assert (np.einsum("vi,vi->v", normals, coarse.vertices) > 0.9).all()


def test_coarse_normals_follow_the_templates_on_its_dense_subset(model: BodyModel) -> None:
    """On the fitter's "dense" subset (6,500 of 13,348 vertices) the coarse mesh's normals are the
    template's, but where the subset thins the head, hands and toes: measured, half within 0.01 degrees,
    95% within 17, 99% within 40."""
    v, f = model.data["vertices_mean"], model.faces
    dense = RegisteredFitter(model).index["dense"]
    faces = coarse_faces(v, f, dense)
    cos = np.einsum("vi,vi->v", vertex_normals(v[dense], faces), vertex_normals(v, f)[dense])
    angle = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    np.testing.assert_array_less(np.percentile(angle, [50, 95, 99]), [1.0, 20.0, 45.0])


def test_nonrigid_refinement_moves_a_surface_onto_the_scan() -> None:
    small = trimesh.creation.icosphere(subdivisions=4, radius=0.48)
    points, _ = sample_surface(small.vertices * (0.5 / 0.48), small.faces, 20_000, seed=0)
    moved = refine_nonrigid(small.vertices, small.faces, points)
    before = np.abs(np.linalg.norm(small.vertices, axis=1) - 0.5).mean()
    after = np.abs(np.linalg.norm(moved, axis=1) - 0.5).mean()
    assert before > 0.019 and after < 0.004


def test_nonrigid_refinement_leaves_an_unseen_side_alone() -> None:
    # a thin slab seen from the front: scan points 1 cm in front of its front face, within reach of the back
    slab = trimesh.creation.box(extents=(0.4, 0.4, 0.02)).subdivide_to_size(0.01)
    v, f = np.asarray(slab.vertices), np.asarray(slab.faces)
    rng = np.random.default_rng(0)
    points = np.column_stack([rng.uniform(-0.15, 0.15, (5000, 2)), np.full(5000, 0.02)])
    front, back = v[:, 2] > 0, v[:, 2] < 0
    inner = (np.abs(v[:, :2]) < 0.1).all(axis=1)
    for seen, back_moves in ((None, True), (front, False)):
        dz = (refine_nonrigid(v, f, points, seen=seen) - v)[:, 2]
        assert abs(dz[front & inner].mean() - 0.01) < 1e-3
        assert (dz[back & inner].mean() > 0.02) == back_moves  # unseen, the back is not pulled through


def test_nonrigid_refinement_moves_vertices_across_the_surface_not_along_it() -> None:
    """Scan points on a 3 cm lattice 1 cm in front of a 1 cm mesh: the vertices move 1 cm forward and stay
    where they were along the surface; with the whole pull kept they slide towards the lattice's points."""
    slab = trimesh.creation.box(extents=(0.4, 0.4, 0.02)).subdivide_to_size(0.01)
    v, f = np.asarray(slab.vertices), np.asarray(slab.faces)
    g = np.arange(-0.15, 0.151, 0.03)
    points = np.column_stack([*(a.ravel() for a in np.meshgrid(g, g)), np.full(g.size**2, 0.02)])
    inner = (v[:, 2] > 0) & (np.abs(v[:, :2]) < 0.1).all(axis=1)
    moved = refine_nonrigid(v, f, points) - v
    assert abs(moved[inner, 2].mean() - 0.01) < 1.5e-3
    assert np.sqrt((moved[inner, :2] ** 2).sum(1).mean()) < 3e-4
    slid = refine_nonrigid(v, f, points, NonRigidConfig(tangential=1.0)) - v
    assert np.sqrt((slid[inner, :2] ** 2).sum(1).mean()) > 2e-3


def test_cleaning_drops_isolated_points() -> None:
    rng = np.random.default_rng(1)
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=0.5)
    surface, _ = sample_surface(sphere.vertices, sphere.faces, 50_000, seed=1)
    stray = rng.uniform(-1.5, 1.5, (200, 3))
    stray = stray[np.linalg.norm(stray, axis=1) > 0.8]
    kept = clean_points(np.concatenate([surface, stray]), voxel=0.01, neighbours=8, cutoff=3.0)
    assert len(kept) > 5000
    assert np.abs(np.linalg.norm(kept, axis=1) - 0.5).max() < 0.05  # no stray point survives


def test_cleaning_keeps_the_first_point_of_every_voxel() -> None:
    """One point per occupied 1 cm cell, the first in the scan's order, in that order: also when the scan
    spans so far (a stray point kilometres away) that the cells cannot be numbered in one integer."""
    rng = np.random.default_rng(5)
    near = rng.uniform(-0.05, 0.05, (3000, 3))  # 1,000 cells, three points each on average
    for points in (near, np.concatenate([near, [[4.0e7, -3.0e7, 2.0e7]]])):
        cell = np.floor(points / 0.01).astype(np.int64)
        first = [i for i in range(len(points)) if not (cell[:i] == cell[i]).all(1).any()]
        kept = clean_points(points, voxel=0.01, neighbours=1, cutoff=1e12)
        np.testing.assert_array_equal(kept, points[first])


def test_orientation_candidates_are_rotations_and_include_the_truth() -> None:
    rng = np.random.default_rng(2)
    points = rng.normal(size=(2000, 3)) * np.array([0.1, 0.8, 0.3])  # thin along x, tall along y
    R_true = Rotation.random(random_state=3).as_matrix()
    R = orientation_candidates(points @ R_true.T)
    assert R.shape == (24, 3, 3)
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-9)
    # one candidate undoes R_true up to the sign ambiguity of the heading (x and z flipped together)
    aligned = R @ R_true
    assert np.abs(np.abs(np.einsum("hii->hi", aligned)) - 1).sum(1).min() < 1e-2


@pytest.fixture(scope="module")
def fitted(model: BodyModel, fitter: ScanFitter) -> tuple[ScanFit, np.ndarray, list[str], np.ndarray]:
    """A body in a mild pose, sampled at 60k points, turned, moved, in millimetres, and its fit given the
    scan's orientation (the orientation search is not reliable yet, see BENCHMARKS.md), its ground truth,
    the fit's progress lines after the first and the scan's points (metres)."""
    # Body 13: its fit agrees across thread counts. Body 11 does not: float32 summation order alone moves
    # its mean error between 15 and 78 mm by putting one limb elsewhere (the limb search is not robust
    # yet; issue 4's open registration target).
    rng = np.random.default_rng(13)
    q = random_poses(model.skeleton, 1, rng, spread=0.0)
    shape = rng.normal(size=(1, model.n_shape)) * 0.7
    truth = model.forward(shape, q, np.zeros((1, 3)), dtype=torch.float64).vertices[0].numpy()
    points, _ = sample_surface(truth, model.faces, 60_000, seed=3)
    R = Rotation.from_euler("xyz", [70, 140, -20], degrees=True).as_matrix()
    t = np.array([0.4, -1.2, 2.0])
    scan = scan_from_arrays((points @ R.T + t) * 1000.0, units="auto")
    assert scan.source_units == "mm"
    steps: list[tuple[int, int, str]] = []
    fit = fitter.fit(scan, lambda *step: steps.append(step), orientation=R.T)
    # the steps counted in order, each telling the same total; the first says what is fitted
    assert [(done, total) for done, total, _ in steps] == [(k, 9) for k in range(10)]
    assert steps[0][2].endswith(" points cleaned; fitting a whole body"), steps[0][2]
    return fit, truth @ R.T + t, [line for *_, line in steps[1:]], scan.points


def test_scan_fit_recovers_a_turned_body(
    model: BodyModel, fitted: tuple[ScanFit, np.ndarray, list[str], np.ndarray]
) -> None:
    fit, truth, _, points = fitted
    error = np.linalg.norm(fit.registration - truth, axis=1) * 1000
    assert error.mean() < 15.0, error.mean()
    assert np.median(error) < 12.0, np.median(error)
    assert fit.report.distances.mean < 3.0
    assert fit.report.confident and fit.report.limit_violations == 0
    assert fit.report.extra["inlier_fraction"] > 0.95 and fit.report.extra["coverage"] > 0.9
    assert fit.report.extra["fitted_part"] == "whole body"
    # every scan point's own distance, in the scan's order (measured in parts on the fit's threads)
    assert np.array_equal(fit.point_distances, point_to_surface(points, fit.registration, model.faces))


def test_the_fit_goes_on_with_the_branch_that_scores_best_before_the_valley_phase(
    fitter: ScanFitter, fitted: tuple[ScanFit, np.ndarray, list[str], np.ndarray]
) -> None:
    report, lines = fitted[0].report, fitted[2]
    scores = report.extra["branch_scores"]
    assert len(scores) == len(DEFAULT_BRANCHES) == 2
    assert report.extra["branch"] == int(np.argmin(scores))
    assert report.extra["phase_scores"]["fine"] == pytest.approx(min(scores), abs=1e-5)
    runs = {p.stage.name: p.stage.iterations * p.rounds for p in DEFAULT_PHASES}
    branched = [runs[name] for name in ("shape", "limbs", "fine")]
    assert report.iterations == sum(runs.values()) + sum(branched)
    assert report.seconds > 0
    names = [p.stage.name for p in DEFAULT_PHASES]
    expected = [*names[:2], *(f"branch {b}: {n}" for b in (1, 2) for n in names[2:5]), names[5]]
    got = [line.split(": robust")[0] for line in lines]  # the branches run at once: theirs interleave
    assert got[:2] == expected[:2] and got[-1] == expected[-1] and sorted(got) == sorted(expected)
    for b in (1, 2):  # each branch's own phases in order
        assert [x for x in got if x.startswith(f"branch {b}")] == [f"branch {b}: {n}" for n in names[2:5]]
    assert len(lines) == fitter.progress_steps() == 9


def test_the_branches_fit_alike_one_after_the_other_or_at_once(model: BodyModel) -> None:
    """The branches run on threads of their own; each refines its own copy of the hypotheses, so running
    them at once gives the fit that running them one after the other gives."""
    rng = np.random.default_rng(5)
    q = random_poses(model.skeleton, 1, rng, spread=0.3)
    body = model.forward(np.zeros((1, model.n_shape)), q, np.zeros((1, 3)), dtype=torch.float64)
    points, _ = sample_surface(body.vertices[0].numpy(), model.faces, 20_000, seed=5)
    short = tuple(
        dataclasses.replace(p, stage=dataclasses.replace(p.stage, iterations=5)) for p in DEFAULT_PHASES
    )
    fits = [
        ScanFitter(model, ScanFitConfig(phases=short, nonrigid=None, single_view=False, workers=w)).fit(
            points, orientation=np.eye(3)
        )
        for w in (1, 2)
    ]
    assert fits[0].report.extra["branch_scores"] == fits[1].report.extra["branch_scores"]
    np.testing.assert_array_equal(fits[0].coordinates, fits[1].coordinates)
    np.testing.assert_array_equal(fits[0].registration, fits[1].registration)


def test_a_phase_in_rounds_takes_its_metric_again_where_each_round_ended(
    model: BodyModel, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A point-to-plane phase in rounds: each round's L-BFGS starts from the Gauss-Newton metric at the state
    the last round left, and the report counts every round's iterations."""
    rng = np.random.default_rng(5)
    q = random_poses(model.skeleton, 1, rng, spread=0.3)
    body = model.forward(np.zeros((1, model.n_shape)), q, np.zeros((1, 3)), dtype=torch.float64)
    points, _ = sample_surface(body.vertices[0].numpy(), model.faces, 20_000, seed=5)
    phases = tuple(
        dataclasses.replace(p, stage=dataclasses.replace(p.stage, iterations=3), rounds=3 if p.plane else 1)
        for p in DEFAULT_PHASES
    )
    # three iterations a phase leave the body short of the scan, which would read as loose clothing
    config = ScanFitConfig(
        phases=phases,
        branches=DEFAULT_BRANCHES[:1],
        nonrigid=None,
        single_view=False,
        workers=1,
        clothing=None,
    )
    fitter = ScanFitter(model, config)
    metrics: list[tuple[str, torch.Tensor]] = []  # (phase, u) where each metric was taken
    starts: list[tuple[str, torch.Tensor]] = []  # (stage, u) where each L-BFGS run started
    take_metric, optimise = fitter._metric, fitter.fitter.optimise

    def metric(hyp: Any, phase: Any, damping: float) -> torch.Tensor:
        metrics.append((phase.stage.name, hyp.state[0].clone()))
        return take_metric(hyp, phase, damping)

    def run(stage: Stage, z: Any, term: Any, metric: Any = None) -> tuple[int, float]:
        starts.append((stage.name, z[0].clone()))
        return optimise(stage, z, term, metric)

    monkeypatch.setattr(fitter, "_metric", metric)
    monkeypatch.setattr(fitter.fitter, "optimise", run)
    fit = fitter.fit(points, orientation=np.eye(3))
    assert [name for name, _ in metrics] == ["fine"] * 3 + ["valley"] * 3
    ran = [name for name, _ in starts]
    assert sorted(set(ran)) == sorted(p.stage.name for p in phases)
    # a run per round (the phases before the branches run their hypotheses in two halves, a run each)
    assert [name for name in ran if name in ("fine", "valley")] == ["fine"] * 3 + ["valley"] * 3
    rounds = [u for name, u in starts if name == "fine"]
    for (_, taken), u in zip(metrics[:3], rounds, strict=True):
        assert torch.equal(taken, u)  # each round's metric at the state it starts from
    assert not torch.equal(rounds[0], rounds[1]) and not torch.equal(rounds[1], rounds[2])
    assert fit.report.iterations == sum(p.stage.iterations * p.rounds for p in phases)


def test_scan_fit_parameters_reproduce_its_body(
    model: BodyModel, fitted: tuple[ScanFit, np.ndarray, list[str], np.ndarray]
) -> None:
    fit = fitted[0]
    out = model.forward(fit.shape[None], fit.coordinates[None], fit.root[None], dtype=torch.float64)
    S = np.linalg.inv(fit.scan_to_body)  # the parameters live in the body frame: scan = S @ body
    np.testing.assert_allclose(out.vertices[0].numpy() @ S[:3, :3].T + S[:3, 3], fit.vertices, atol=1e-5)


def test_scan_fit_rejects_bad_input(fitter: ScanFitter) -> None:
    with pytest.raises(ScanError, match="finite"):
        fitter.fit(np.full((1000, 3), np.nan))
    with pytest.raises(ScanError, match="at least"):
        fitter.fit(np.random.default_rng(0).normal(size=(250, 3)) * 0.3)
    with pytest.raises(ScanError, match="at least"):
        fitter.fit(np.zeros((0, 3)))
    with pytest.raises(ScanError, match="shape"):
        fitter.fit(np.zeros((10, 2)))


@pytest.mark.parametrize("extents", [(0.3, 1.7, 0.5), (0.2, 0.35, 0.25)], ids=["body-sized", "bust-sized"])
def test_a_box_is_no_person_and_never_a_confident_body(
    model: BodyModel, fitter: ScanFitter, extents: tuple[float, float, float]
) -> None:
    """A box of a body's size, or of a head and shoulders', holds no person: refused before any fit. With the
    scene separation off it is fitted (as a head and shoulders when bust-sized), never confidently."""
    box = trimesh.creation.box(extents=extents)
    points, _ = sample_surface(box.vertices, box.faces, 30_000, seed=0)
    with pytest.raises(NoPersonError, match=r"no person found in the scan: .*box"):
        fitter.fit(points)
    fit = ScanFitter(model, ScanFitConfig(scene=None), fitter=fitter.fitter).fit(points)
    assert not fit.report.confident
    assert any("orientation was searched" in r for r in fit.report.reasons)
    if extents[1] > 1.0:
        assert any("within" in r or "exceeds" in r for r in fit.report.reasons)
    else:
        assert fit.report.extra["fitted_part"] == "head and shoulders"
        assert any("less than a body" in r for r in fit.report.reasons)


@pytest.mark.parametrize("up", [(0.0, 0.0, 1.0), (0.0, -1.0, 0.0), (0.6, 0.0, 0.8)])
def test_orientation_candidates_about_a_known_up_axis(up: tuple[float, float, float]) -> None:
    """With the up axis known: 8 rotations, each with that up axis and a horizontal heading, 45 degrees
    apart, so any true heading is within 22.5 degrees of one of them."""
    points = np.random.default_rng(0).normal(size=(500, 3)) * [0.2, 0.8, 0.1]
    u = np.asarray(up)
    R = orientation_candidates(points, u)
    assert R.shape == (8, 3, 3)
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), (8, 3, 3)), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0)
    np.testing.assert_allclose(R[:, 1], np.broadcast_to(u, (8, 3)), atol=1e-12)
    np.testing.assert_allclose(R[:, 0] @ u, 0.0, atol=1e-12)
    for angle in np.linspace(0.0, 2 * np.pi, 37):
        heading = np.cos(angle) * R[0, 0] + np.sin(angle) * R[0, 2]
        assert np.degrees(np.arccos(np.clip(R[:, 0] @ heading, -1, 1))).min() <= 22.5 + 1e-9


def test_a_head_and_shoulders_is_fitted_as_one(model: BodyModel, fitter: ScanFitter) -> None:
    """A scan of a body's top 45 cm (turned, moved, orientation searched) is smaller than any body: it is
    fitted as a head and shoulders, never confidently, with the rest of the body in the start pose, and the
    head lands on the truth's (measured 1.5 mm; the whole-body phases folded a body into such scans)."""
    rng = np.random.default_rng(1)
    q = random_poses(model.skeleton, 1, rng, spread=0.15)
    shape = rng.normal(size=(1, model.n_shape)) * 0.5
    truth = model.forward(shape, q, np.zeros((1, 3)), dtype=torch.float64).vertices[0].numpy()
    points, _ = sample_surface(truth, model.faces, 40_000, seed=1)
    points = points[points[:, 1] > truth[:, 1].max() - 0.45]
    R = Rotation.random(random_state=1).as_matrix()
    t = np.array([0.3, 1.1, -0.4])
    steps: list[tuple[int, int, str]] = []
    fit = fitter.fit(points @ R.T + t, lambda *step: steps.append(step))
    report = fit.report
    assert report.extra["fitted_part"] == "head and shoulders"
    n = fitter.progress_steps(partial=True)
    assert n == 3 and [(done, total) for done, total, _ in steps] == [(k, n) for k in range(n + 1)]
    assert not report.confident and any("head and shoulders" in r for r in report.reasons)
    assert report.limit_violations == 0 and report.distances.mean < 4.0
    names = model.skeleton.body_names
    head = np.argmax(model.data["weights"], 1) == names.index("head")
    error = np.linalg.norm((fit.registration[head] - t) @ R - truth[head], axis=1) * 1000
    assert error.mean() < 10.0, error.mean()
    legs = [model.skeleton.dof_index(n) for n in ("hip_flexion_r", "knee_angle_l", "ankle_angle_r")]
    start = model.skeleton.inside(model.bind_coordinates, 0.1)
    np.testing.assert_allclose(fit.coordinates[legs], start[legs], atol=1e-5)


def test_the_real_kinect_head_and_shoulders_is_fitted_upright(model: BodyModel, fitter: ScanFitter) -> None:
    """The real Kinect capture (tests/data/scans), cropped to the person (nearer than 1 m): head and one
    shoulder in profile, with part of a desk. Fitted as a head and shoulders with the camera's axes given
    (+Y down, the person facing +X): the head's top meets the scan's and the body stands along the
    camera's -Y (the whole-body phases folded a whole body into these points)."""
    scan = load_scan(KINECT, drop_nonfinite=True)
    person = scan.points[scan.points[:, 2] < 1.0]
    to_body = np.diag([1.0, -1.0, -1.0])
    fit = fitter.fit(person, orientation=to_body)
    assert fit.report.extra["fitted_part"] == "head and shoulders" and not fit.report.confident
    assert fit.report.distances.mean < 2.5, fit.report.distances.mean
    up = np.array([0.0, -1.0, 0.0])  # in the camera's frame
    assert abs((fit.registration @ up).max() - (person @ up).max()) < 0.01
    names = model.skeleton.body_names
    head, thorax = names.index("head"), names.index("thorax")
    joints = model.forward(fit.shape[None], fit.coordinates[None], fit.root[None], dtype=torch.float64)
    frames = joints.frames[0].numpy()
    rise = fit.scan_to_body[:3, :3].T @ (frames[head, :3, 3] - frames[thorax, :3, 3])
    assert rise @ up > 0.9 * np.linalg.norm(rise), rise


def test_a_single_view_is_fitted_on_the_side_it_saw(model: BodyModel) -> None:
    """One depth camera's view of a body (orientation given): detected as a single view and reported as
    such; only the surface that faced the sensor is fitted, so the unseen back of the trunk is not pulled
    into the front (without the detection the trunk is pulled towards the front)."""
    rng = np.random.default_rng(13)
    q = random_poses(model.skeleton, 1, rng, spread=0.0)
    shape = rng.normal(size=(1, model.n_shape)) * 0.7
    truth = model.forward(shape, q, np.zeros((1, 3)), dtype=torch.float64).vertices[0].numpy()
    centre = truth.mean(0)
    camera = np.array([2.5, 0.2, 0.4])
    points, _ = corrupt.depth_camera_view(truth, model.faces, centre + camera, centre, (240, 320), rng=rng)
    names = model.skeleton.body_names
    trunk = np.isin(
        np.argmax(model.data["weights"], 1), [names.index(b) for b in ("pelvis", "torso", "thorax")]
    )
    errors = {}
    for single_view in (True, False):
        fit = ScanFitter(model, ScanFitConfig(single_view=single_view)).fit(points, orientation=np.eye(3))
        errors[single_view] = float(np.linalg.norm(fit.vertices - truth, axis=1)[trunk].mean() * 1000)
        if single_view:
            towards = np.array(fit.report.extra["single_view"])
            assert towards @ camera / np.linalg.norm(camera) > 0.9
            assert not fit.report.confident and any("one sensor's view" in r for r in fit.report.reasons)
            assert fit.report.predicted_error_mm is not None
            assert fit.report.limit_violations == 0
        else:
            assert fit.report.extra["single_view"] is None
    # measured: 7.1 mm against 13.0 on the trunk (31 against 122 before the phases' Gauss-Newton metric);
    # on another host of the same machine type (other floating-point rounding) 10.4 against 94.9
    assert errors[True] < 15.0 and errors[True] < 0.7 * errors[False], errors


def test_vertices_out_of_the_scans_reach_are_not_pulled_in_the_point_to_plane_phases(
    model: BodyModel, fitter: ScanFitter
) -> None:
    """The top 20 cm of a body is a hole in its scan: in a point-to-plane phase the head's vertices there
    feel no pull towards the hole's rim; in a point-to-point phase they do."""
    q = model.skeleton.inside(model.bind_coordinates, 0.1)[None]
    out = model.forward(np.zeros((1, model.n_shape)), q, np.zeros((1, 3)), dtype=torch.float64)
    whole = out.vertices[0].numpy()
    points, _ = sample_surface(whole, model.faces, 20_000, seed=1)
    points = points[points[:, 1] < whole[:, 1].max() - 0.2]
    v = whole[fitter.fitter.index["dense"]]  # the point-to-plane phases' vertices
    hyp = fitter._candidates(points, np.eye(3), None)
    hyp.points = (points - hyp.centre)[None]
    far = cKDTree(points).query(v)[0] > 2 * REACH_MM / 1000.0
    assert far.sum() > 100
    fine = next(p for p in DEFAULT_PHASES if p.plane)
    pulls = []
    for phase in (fine, dataclasses.replace(fine, plane=False)):
        verts = torch.tensor((v - hyp.centre)[None] * 1000.0, dtype=torch.float32, requires_grad=True)
        fitter._chamfer(hyp, phase)(verts).sum().backward()
        assert verts.grad is not None
        pulls.append(verts.grad[0].norm(dim=1).numpy())
    assert pulls[0][far].max() == 0.0 and pulls[1][far].min() > 0.0
    assert pulls[0][~far].max() > 0.0


def test_the_point_to_plane_phases_fit_the_dense_subset_with_its_coarse_normals(
    model: BodyModel, fitter: ScanFitter
) -> None:
    """The point-to-plane loss on the "dense" vertices: the model -> scan term alone (here) is their mean
    Geman-McClure distance to the nearest fit point and pulls them all; the scan -> model term alone is the
    fit points' mean distance to their nearest vertex's tangent plane (the coarse mesh's normals), the
    in-plane part weighted by ``tangential``. A subset without a surface cannot be fitted point-to-plane."""
    q = model.skeleton.inside(model.bind_coordinates, 0.1)[None]
    out = model.forward(np.zeros((1, model.n_shape)), q, np.zeros((1, 3)), dtype=torch.float64)
    dense = fitter.fitter.index["dense"]
    whole = out.vertices[0].numpy()
    points, _ = sample_surface(whole, model.faces, 20_000, seed=2)
    hyp = fitter._candidates(points, np.eye(3), None)
    hyp.points = (points - hyp.centre)[None]
    body = (whole[dense] - hyp.centre) * 1000.0
    phase = next(p for p in DEFAULT_PHASES if p.plane)
    assert phase.stage.vertices == "dense"
    s2 = phase.sigma_mm**2
    verts = torch.tensor(body[None], dtype=torch.float32, requires_grad=True)
    loss = fitter._chamfer(hyp, dataclasses.replace(phase, two_way=False))(verts)
    loss.sum().backward()
    assert verts.grad is not None and (verts.grad[0].norm(dim=1) > 0).double().mean() > 0.99
    d2 = cKDTree(hyp.points[0] * 1000.0).query(body)[0] ** 2
    rho = np.minimum(d2 * s2 / (d2 + s2), REACH_MM**2 * s2 / (REACH_MM**2 + s2))
    assert float(loss[0]) == pytest.approx(0.5 * rho.mean(), rel=1e-4)
    # the scan -> model term: the loss less its model -> scan part
    both = fitter._chamfer(hyp, phase)(torch.tensor(body[None], dtype=torch.float32))
    p_mm = hyp.points[0] * 1000.0
    nearest = cKDTree(body).query(p_mm)[1]
    n = vertex_normals(whole[dense], coarse_faces(model.data["vertices_mean"], model.faces, dense))[nearest]
    r = body[nearest] - p_mm
    along = np.einsum("ni,ni->n", r, n)
    t = fitter.config.tangential
    e2 = along**2 + t * ((r**2).sum(1) - along**2)
    assert float(both[0] - loss[0]) == pytest.approx((e2 * s2 / (e2 + s2)).mean(), rel=1e-3)
    with pytest.raises(ValueError, match="surface"):
        fitter._chamfer(
            hyp,
            dataclasses.replace(
                phase, stage=Stage(name="x", coordinates="all", shape="all", vertices="subset", iterations=1)
            ),
        )


def test_a_real_t_posed_body_given_as_bare_points_is_fitted_facing_forward(fitter: ScanFitter) -> None:
    """The CC BY man (SMPL topology, T-pose) as 6,890 bare points turned at random, orientation searched:
    facing him backwards with his legs crossed fits the points nearly as well until his limbs are posed
    (a near-tie after the shape phase), so two orientations go on through the limbs phase."""
    verts, _ = read_obj(SOURCE_DIR / "human_man.obj")
    rng = np.random.default_rng(0)
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    R *= np.sign(np.linalg.det(R))
    fit = fitter.fit(verts @ R.T)
    forward = R @ SMPL_TO_BODY.T @ np.array([1.0, 0.0, 0.0])  # the body's +X (forward) in the scan frame
    pelvis = (
        fitter.model.forward(fit.shape[None], fit.coordinates[None], fit.root[None], dtype=torch.float64)
        .frames[0, 0, :3, :3]
        .numpy()
    )
    fitted_forward = fit.scan_to_body[:3, :3].T @ pelvis[:, 0]
    assert fitted_forward @ forward > 0.9, fitted_forward @ forward
    assert fit.report.distances.mean < 2.5, fit.report.distances.mean

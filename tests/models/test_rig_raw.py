"""Personal rigs from raw scans: registrations whose shape is wrong (as a raw scan's fit is, far outside the
shape space) and the scans' own points. The rig's shape must come from the points, which all scans share,
not from the registrations."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from bodyfit.io.scans import sample_surface
from bodyfit.models.body.model import BodyDecoder, BodyModel
from bodyfit.models.fitting.common.surface import vertex_normals
from bodyfit.models.rig.build import RigConfig, build_rig
from bodyfit.models.rig.icp import ClosestConfig, normal_part


@pytest.fixture(scope="module")
def model() -> BodyModel:
    return BodyModel.load()


def posed(model: BodyModel, shape: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(n, V, 3) the body of ``shape`` at q (n, n_dof), standing about the origin."""
    with torch.no_grad():
        c = torch.as_tensor(np.tile(shape, (len(q), 1)))
        root = torch.as_tensor(np.tile([0.0, 0.95, 0.0], (len(q), 1)))
        return model.decoder(torch.float64)(c, torch.as_tensor(q), root)[0].numpy()


def rest(model: BodyModel, shape: np.ndarray, decoder: BodyDecoder | None = None) -> np.ndarray:
    """(V, 3) the body of ``shape`` in the bind pose, under ``decoder`` (default the model's)."""
    dec = decoder or model.decoder(torch.float64)
    with torch.no_grad():
        c, q = torch.as_tensor(shape[None]), torch.as_tensor(model.bind_coordinates[None])
        return dec(c, q, torch.zeros(1, 3, dtype=torch.float64))[0][0].numpy()


def test_the_template_of_a_rig_from_raw_scans_comes_from_their_points(model: BodyModel) -> None:
    """Three raw scans of one body and registrations of another shape in the same poses (9.6 mm from the
    scans' vertices, as a raw scan's fit of a body beyond the shape space is): fitted to all scans' points
    together, the rig's template ends within 3 mm of the person's, vertex by vertex; built on the
    registrations' correspondence alone (no joint fit of the points), it keeps their error along the
    surface, which closest points moved across it cannot undo."""
    rng = np.random.default_rng(21)
    lo, hi = model.skeleton.ranges[:, 0], model.skeleton.ranges[:, 1]
    q = np.clip(rng.uniform(lo, hi, (3, len(lo))) * 0.4, lo, hi)
    truth = rng.normal(size=model.n_shape) * 0.5
    wrong = truth + rng.normal(size=model.n_shape) * 0.53
    scans, registrations = posed(model, truth, q), posed(model, wrong, q)
    points = [sample_surface(v, model.faces, 20_000, seed=k)[0] for k, v in enumerate(scans)]
    person = rest(model, truth)
    errors = []
    for iterations in (25, 0):
        closest = ClosestConfig(rounds=1, chamfer_iterations=iterations)
        cfg = RigConfig(allow_undetermined=True, weights=None, joints=None, closest=closest)
        subject = build_rig(model, registrations, config=cfg, points=points).subject
        template = rest(model, subject.shape, subject.decoder(model, torch.float64))
        errors.append(float(np.linalg.norm(template - person, axis=-1).mean() * 1000.0))
    assert errors[0] < 3.0 and errors[1] > 2.0 * errors[0], errors


def test_raw_scans_poses_are_refitted_against_the_shared_rig(model: BodyModel) -> None:
    """Three raw scans of one body, registered in poses 3 degrees off in every coordinate (as a raw scan's
    fit is): the closest-point rounds hold each vertex where it is along the surface and keep most of the
    poses' error; a pose-only Chamfer refit of every scan against the rig (``repose_after``) brings the posed
    rig within half of that distance of the scans' vertices."""
    rng = np.random.default_rng(22)
    lo, hi = model.skeleton.ranges[:, 0], model.skeleton.ranges[:, 1]
    q = np.clip(rng.uniform(lo, hi, (3, len(lo))) * 0.4, lo, hi)
    shape = rng.normal(size=model.n_shape) * 0.5
    rotations = [i for i, name in enumerate(model.dof_names) if not name.startswith("pelvis_t")]
    off = q.copy()
    off[:, rotations] += np.radians(3.0) * rng.choice([-1.0, 1.0], (3, len(rotations)))
    registrations = posed(model, shape, np.clip(off, lo, hi))
    scans = posed(model, shape, q)
    points = [sample_surface(v, model.faces, 20_000, seed=k)[0] for k, v in enumerate(scans)]
    errors = []
    for after in ((), (0,)):
        closest = ClosestConfig(rounds=1, chamfer_iterations=0, repose_after=after, repose_iterations=60)
        cfg = RigConfig(allow_undetermined=True, weights=None, joints=None, closest=closest)
        subject = build_rig(model, registrations, config=cfg, points=points).subject
        with torch.no_grad():
            rig = subject.decoder(model, torch.float64)(
                torch.as_tensor(np.tile(subject.shape, (3, 1))),
                torch.as_tensor(subject.poses),
                torch.as_tensor(subject.roots),
            )[0].numpy()
        errors.append(float(np.linalg.norm(rig - scans, axis=-1).mean() * 1000.0))
    assert errors[0] > 5.0 and errors[1] < 0.5 * errors[0], errors


def test_offsets_from_raw_scans_move_the_template_across_its_surface_only(model: BodyModel) -> None:
    """Three raw scans of a body 8 mm thicker everywhere than the registrations' shape (a raw scan's fit of a
    body beyond the shape space): the offsets the rig learns from the scans' points lie along the
    template's normals (under 1% of their length along the surface), as raw points tell where the skin is
    and not which point of it a vertex is; with the whole step kept (``offset_tangential=1``) 6% of it
    slides the template along its surface."""
    rng = np.random.default_rng(23)
    lo, hi = model.skeleton.ranges[:, 0], model.skeleton.ranges[:, 1]
    q = np.clip(rng.uniform(lo, hi, (3, len(lo))) * 0.4, lo, hi)
    shape = rng.normal(size=model.n_shape) * 0.5
    template = rest(model, shape)
    thicker = model.decoder(torch.float64).with_offsets(0.008 * vertex_normals(template, model.faces))
    with torch.no_grad():
        c = torch.as_tensor(np.tile(shape, (3, 1)))
        root = torch.as_tensor(np.tile([0.0, 0.95, 0.0], (3, 1)))
        scans = thicker(c, torch.as_tensor(q), root)[0].numpy()
    points = [sample_surface(v, model.faces, 20_000, seed=k)[0] for k, v in enumerate(scans)]
    shares = []
    for tangential in (0.0, 1.0):
        closest = ClosestConfig(rounds=1, chamfer_iterations=0, repose_after=(), offset_tangential=tangential)
        cfg = RigConfig(allow_undetermined=True, weights=None, joints=None, closest=closest)
        subject = build_rig(model, posed(model, shape, q), config=cfg, points=points).subject
        normals = vertex_normals(rest(model, subject.shape), model.faces)
        across = np.einsum("vi,vi->v", normals, subject.offsets)[:, None] * normals
        along = np.linalg.norm(subject.offsets - across, axis=1).mean()
        shares.append(float(along / np.linalg.norm(subject.offsets, axis=1).mean()))
    assert shares[0] < 0.01 and shares[1] > 0.03, shares


def test_normal_part_keeps_the_step_across_the_surface(model: BodyModel) -> None:
    """A step with parts across and along the template's surface: the part across is kept whole, the part
    along scaled by the share asked for."""
    template = rest(model, np.zeros(model.n_shape))
    normals = vertex_normals(template, model.faces)
    along = np.cross(normals, [0.0, 0.0, 1.0]) * 0.003
    step = 0.005 * normals + along
    np.testing.assert_allclose(normal_part(step, template, model.faces, 0.0), 0.005 * normals, atol=1e-12)
    np.testing.assert_allclose(normal_part(step, template, model.faces, 0.5), 0.005 * normals + 0.5 * along)

"""Personal rigs: one person's shape and rest-pose offsets from several registered scans of them, the
portable subject file, and the refusals (too few scans, different people, poses that leave joints
undetermined, another model, an altered file)."""

from __future__ import annotations

import io

import numpy as np
import pytest
import torch

from benchmarks.personal_rig import soft_tissue
from bodyfit.models.body.model import BodyModel
from bodyfit.models.fitting.registered.fitter import RegisteredFitter
from bodyfit.models.rig.build import RigConfig, RigError, build_rig
from bodyfit.models.rig.fit import fit_registered
from bodyfit.models.rig.subject import Subject, SubjectError


@pytest.fixture(scope="module")
def model() -> BodyModel:
    return BodyModel.load()


def poses(model: BodyModel, n: int, seed: int, spread: float = 0.5) -> np.ndarray:
    """(n, n_dof) random poses within ``spread`` of every coordinate's range."""
    lo, hi = model.skeleton.ranges[:, 0], model.skeleton.ranges[:, 1]
    return np.clip(np.random.default_rng(seed).uniform(lo, hi, (n, len(lo))) * spread, lo, hi)


def person(model: BodyModel, shape: np.ndarray, offsets: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(n, V, 3) the person posed at q (n, n_dof), standing about the origin."""
    decoder = model.decoder(torch.float64).with_offsets(offsets)
    with torch.no_grad():
        c = torch.as_tensor(np.tile(shape, (len(q), 1)))
        root = torch.as_tensor(np.tile([0.0, 0.95, 0.0], (len(q), 1)))
        return decoder(c, torch.as_tensor(q), root)[0].numpy()


@pytest.fixture(scope="module")
def subject_scans(model: BodyModel) -> tuple[np.ndarray, np.ndarray]:
    """Nine meshes of one person outside the shape space (10 mm of smooth offsets): six to build from,
    three held out."""
    shape = np.random.default_rng(5).normal(size=model.n_shape) * 0.8
    x = person(model, shape, soft_tissue(model, 5), poses(model, 9, 6))
    return x[:6], x[6:]


@pytest.fixture(scope="module")
def built(model: BodyModel, subject_scans: tuple[np.ndarray, np.ndarray]) -> object:
    return build_rig(model, subject_scans[0], [f"pose{k}.ply" for k in range(6)])


def test_the_rig_explains_its_scans_and_new_poses(
    model: BodyModel, subject_scans: tuple[np.ndarray, np.ndarray], built: object
) -> None:
    """The generic model misses the person by about 10 mm (the offsets); the rig fits the scans it was built
    from, and held-out poses of the same person, to under a tenth of that."""
    from bodyfit.models.rig.build import RigBuild

    assert isinstance(built, RigBuild)
    assert built.generic_mm.min() > 5.0 and built.personal_mm.max() < 1.0
    held = subject_scans[1]
    generic = RegisteredFitter(model).fit(held)
    personal = fit_registered(model, built.subject, held)
    g = np.linalg.norm(generic.vertices - held, axis=-1).mean() * 1000.0
    p = np.linalg.norm(personal.vertices - held, axis=-1).mean() * 1000.0
    assert g > 5.0 and p < 0.1 * g, (g, p)
    assert built.subject.scans == tuple(f"pose{k}.ply" for k in range(6)) and not built.undetermined


def test_the_subject_file_round_trips_and_refuses_what_it_is_not(model: BodyModel, built: object) -> None:
    from bodyfit.models.rig.build import RigBuild

    assert isinstance(built, RigBuild)
    data = built.subject.to_bytes()
    back = Subject.from_bytes(data, model)
    np.testing.assert_array_equal(back.offsets, built.subject.offsets)
    np.testing.assert_array_equal(back.shape, built.subject.shape)
    assert back.report == built.subject.report
    with np.load(io.BytesIO(data)) as npz:
        arrays = {k: npz[k] for k in npz.files}
    arrays["offsets"] = arrays["offsets"] * 1.01
    altered = io.BytesIO()
    np.savez(altered, **arrays)
    with pytest.raises(SubjectError, match="do not match its sha256"):
        Subject.from_bytes(altered.getvalue())
    foreign = Subject(back.shape, back.offsets, "0" * 64, back.poses, back.roots)
    with pytest.raises(SubjectError, match="built for another body model"):
        Subject.from_bytes(foreign.to_bytes(), model)
    with pytest.raises(SubjectError, match="not a subject file"):
        Subject.from_bytes(b"not an npz")


def test_too_few_scans_and_other_people_are_refused(
    model: BodyModel, subject_scans: tuple[np.ndarray, np.ndarray]
) -> None:
    with pytest.raises(RigError, match="at least 3 scans"):
        build_rig(model, subject_scans[0][:2])
    stranger = np.random.default_rng(9).normal(size=model.n_shape) * 0.8
    other = person(model, stranger, soft_tissue(model, 9), poses(model, 1, 10))
    scans = np.concatenate([subject_scans[0][:4], other])
    with pytest.raises(RigError, match=r"^scan 4 \(\d+\.\d mm\): another person than the other scans"):
        build_rig(model, scans, config=RigConfig(allow_undetermined=True))


def test_poses_that_leave_joints_undetermined_are_named(
    model: BodyModel, subject_scans: tuple[np.ndarray, np.ndarray]
) -> None:
    """Three scans in nearly the same pose: every limb joint is named, with the fix; allowed, it builds and
    says which joints came from the shape space."""
    shape = np.random.default_rng(5).normal(size=model.n_shape) * 0.8
    still = person(model, shape, soft_tissue(model, 5), poses(model, 3, 6, spread=0.02))
    with pytest.raises(RigError, match=r"undetermined: hip_r, hip_l, .*elbow_l; each needs two scans"):
        build_rig(model, still)
    allowed = build_rig(model, still, config=RigConfig(allow_undetermined=True, rounds=1))
    assert "walker_knee_r" in allowed.undetermined and allowed.personal_mm.max() < 2.0

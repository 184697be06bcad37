"""Personal rigs: one person's shape, rest-pose offsets, skinning weights and joints from several registered
scans of them (or raw scans), the portable subject file, and the refusals (too few scans, different people,
poses that leave joints undetermined, another model, an older or altered file)."""

from __future__ import annotations

import io

import numpy as np
import pytest
import torch

from benchmarks.personal_rig import TISSUE_MM, soft_tissue
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
    """Nine meshes of one person outside the shape space (smooth soft tissue, 12 mm on the trunk): six to
    build from, three held out."""
    shape = np.random.default_rng(5).normal(size=model.n_shape) * 0.8
    x = person(model, shape, soft_tissue(model, 5), poses(model, 9, 6))
    return x[:6], x[6:]


@pytest.fixture(scope="module")
def built(model: BodyModel, subject_scans: tuple[np.ndarray, np.ndarray]) -> object:
    return build_rig(model, subject_scans[0], [f"pose{k}.ply" for k in range(6)])


def test_the_test_subjects_tissue_is_thick_on_the_trunk_and_thin_over_bone(model: BodyModel) -> None:
    """The soft tissue of the benchmark's subjects lies along the normals, and on each body's skin it is as
    thick on average as :data:`TISSUE_MM` says (within a third: it is random), 12 mm on the trunk and
    thighs, 2-3 mm on the head, hands and feet; it varies smoothly (a median 2 mm per cm along the edges)."""
    from bodyfit.models.fitting.common.surface import vertex_normals

    tissue = soft_tissue(model, 0)
    normals = vertex_normals(model.data["vertices_mean"], model.faces)
    along = np.einsum("vi,vi->v", tissue, normals)
    np.testing.assert_allclose(np.linalg.norm(tissue, axis=1), np.abs(along), rtol=1e-5, atol=1e-9)
    names, dom = model.skeleton.spec.body_names, model.vertex_bodies
    for body in ("pelvis", "thorax", "femur_r", "humerus_l", "tibia_r", "head", "hand_r", "toes_l"):
        mm = np.abs(along[dom == names.index(body)]).mean() * 1000.0
        expected = TISSUE_MM[body.removesuffix("_r").removesuffix("_l")]
        assert abs(mm - expected) < expected / 3.0, (body, mm, expected)
    v, e = model.data["vertices_mean"], model.faces[:, :2]
    slope = np.abs(along[e[:, 0]] - along[e[:, 1]]) / np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1)
    assert float(np.median(slope)) < 0.3, np.median(slope)


def test_the_rig_explains_its_scans_and_new_poses(
    model: BodyModel, subject_scans: tuple[np.ndarray, np.ndarray], built: object
) -> None:
    """The generic model misses the person by about 4.5 mm (the soft tissue); the rig fits the scans it was
    built from, and held-out poses of the same person, to under a tenth of that."""
    from bodyfit.models.rig.build import RigBuild

    assert isinstance(built, RigBuild)
    assert built.generic_mm.min() > 4.0 and built.personal_mm.max() < 0.4
    held = subject_scans[1]
    generic = RegisteredFitter(model).fit(held)
    personal = fit_registered(model, built.subject, held)
    g = np.linalg.norm(generic.vertices - held, axis=-1).mean() * 1000.0
    p = np.linalg.norm(personal.vertices - held, axis=-1).mean() * 1000.0
    assert g > 4.0 and p < 0.1 * g, (g, p)
    assert built.subject.scans == tuple(f"pose{k}.ply" for k in range(6)) and not built.undetermined


def _damaged_members(data: bytes, positions: int = 24) -> list[bytes]:
    """``data`` (an .npz) with one byte inverted among the first ``positions`` of each member's stored
    data: the start of its deflate stream, or of its .npy header."""
    import struct
    import zipfile

    out = []
    with zipfile.ZipFile(io.BytesIO(data)) as zf:
        infos = zf.infolist()
    for info in infos:
        name_len, extra_len = struct.unpack("<HH", data[info.header_offset + 26 : info.header_offset + 30])
        start = info.header_offset + 30 + name_len + extra_len
        for k in range(min(positions, info.compress_size)):
            out.append(data[: start + k] + bytes([data[start + k] ^ 0xFF]) + data[start + k + 1 :])
    return out


def test_the_subject_file_round_trips_and_refuses_what_it_is_not(model: BodyModel, built: object) -> None:
    from bodyfit.models.rig.build import RigBuild

    assert isinstance(built, RigBuild)
    data = built.subject.to_bytes()
    back = Subject.from_bytes(data, model)
    np.testing.assert_array_equal(back.offsets, built.subject.offsets)
    np.testing.assert_array_equal(back.shape, built.subject.shape)
    assert back.weights is not None and built.subject.weights is not None
    np.testing.assert_array_equal(back.weights, built.subject.weights)
    assert back.scale_offsets is not None and built.subject.scale_offsets is not None
    np.testing.assert_array_equal(back.scale_offsets, built.subject.scale_offsets)
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
    old = io.BytesIO()
    np.savez(old, **{**arrays, "format": np.array("bodyfit-subject-1")})
    with pytest.raises(SubjectError, match=r"older bodyfit .*rebuild it with `bodyfit rig`"):
        Subject.from_bytes(old.getvalue())
    with pytest.raises(SubjectError, match="not a subject file"):
        Subject.from_bytes(data[: len(data) // 2])  # cut short
    bomb = io.BytesIO()  # 2 MB compressed, 96 MB of zeros decompressed
    np.savez_compressed(bomb, **{**arrays, "offsets": np.zeros((4_000_000, 3))})
    with pytest.raises(SubjectError, match="MiB decompressed"):
        Subject.from_bytes(bomb.getvalue())
    # corrupt deflate streams and headers that no longer parse are refused; a change the decompressor
    # never reads (a code length of an unused symbol) leaves the same arrays, which are then accepted
    for damaged in _damaged_members(data):
        try:
            read = Subject.from_bytes(damaged)
        except SubjectError:
            continue
        np.testing.assert_array_equal(read.offsets, back.offsets)
        assert read.weights is not None and np.array_equal(read.weights, back.weights)
    from bodyfit.models.rig.subject import _digest

    lacking = {k: v for k, v in arrays.items() if k not in ("weights", "sha256")}
    lacking["offsets"] = lacking["offsets"] / 1.01
    short = io.BytesIO()
    np.savez(short, sha256=np.array(_digest(lacking)), **lacking)
    with pytest.raises(SubjectError, match="lacks weights"):
        Subject.from_bytes(short.getvalue())


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


def test_the_rig_finds_the_persons_own_weights_and_joints(model: BodyModel) -> None:
    """A person skinned with softer weights than the body model's, with 8% longer thighs and smooth soft
    tissue: the rig with its own weights and joints explains held-out poses at least 30% better than the
    same rig with the body model's (their recovery alone: ``test_rig_parts``)."""
    from bodyfit.models.rig.subject import PersonalParts
    from tests.models.test_rig_parts import spread_weights

    generic = PersonalParts.generic(model)
    mean = np.asarray(model.data["scale_mean"], np.float64)
    scales = generic.scale_offsets.copy()
    for name in ("femur_r", "femur_l"):
        scales[model.skeleton.segments.index(name), 1] = 0.08 * mean[model.skeleton.segments.index(name), 1]
    truth = PersonalParts(spread_weights(model, 6), soft_tissue(model, 7), scales)
    shape = np.random.default_rng(7).normal(size=model.n_shape) * 0.5
    q = poses(model, 9, 8)
    with torch.no_grad():
        x = truth.decoder(model)(
            torch.as_tensor(np.tile(shape, (9, 1))),
            torch.as_tensor(q),
            torch.zeros(9, 3, dtype=torch.float64),
        )[0].numpy()
    errors = []
    for cfg in (RigConfig(rounds=3), RigConfig(rounds=3, weights=None, joints=None)):
        built = build_rig(model, x[:6], config=cfg)
        fit = fit_registered(model, built.subject, x[6:])
        errors.append(np.linalg.norm(fit.vertices - x[6:], axis=-1).mean() * 1000.0)
    assert errors[0] < 0.7 * errors[1], errors


def test_raw_scans_pull_the_rig_onto_their_points(model: BodyModel) -> None:
    """Registrations that float 5 mm off their scans (a raw fit's error) and the scans' points: the rig built
    with the points lies on the person's surface, the one built from the registrations alone does not."""
    from bodyfit.io.scans import sample_surface
    from bodyfit.models.fitting.common.surface import point_to_surface, vertex_normals

    shape = np.random.default_rng(11).normal(size=model.n_shape) * 0.5
    truth = person(model, shape, soft_tissue(model, 11), poses(model, 4, 12))
    normals = vertex_normals(truth, model.faces)
    floating = truth + 0.005 * normals
    points = [sample_surface(v, model.faces, 20_000, seed=k)[0] for k, v in enumerate(truth)]
    cfg = RigConfig(allow_undetermined=True, rounds=2)
    gaps = []
    for given in (None, points):
        built = build_rig(model, floating, config=cfg, points=given)
        decoder = built.subject.decoder(model, torch.float64)
        with torch.no_grad():
            c = torch.as_tensor(np.tile(built.subject.shape, (4, 1)))
            posed = decoder(c, torch.as_tensor(built.subject.poses), torch.as_tensor(built.subject.roots))[0]
        gaps.append(
            np.mean(
                [np.abs(point_to_surface(posed[k].numpy(), truth[k], model.faces)).mean() for k in range(4)]
            )
        )
    assert gaps[0] > 0.003 and gaps[1] < 0.4 * gaps[0], gaps


def test_a_subject_fitted_to_a_raw_scan_of_a_new_pose_lands_closer_than_the_generic_fit(
    model: BodyModel, subject_scans: tuple[np.ndarray, np.ndarray], built: object
) -> None:
    """A raw scan (points only) of a held-out pose of the person: the service's fit with their subject lands
    within half the generic fit's error of the mesh. The generic fit reads the soft tissue as clothing and
    poses a body under it; the person's body, searched on the scan with their own shape, is not led by
    that pose."""
    from bodyfit.io.scans import Scan, sample_surface
    from bodyfit.models.rig.build import RigBuild
    from bodyfit.service.core import BodyService

    assert isinstance(built, RigBuild)
    service = BodyService.load(fitters=False)
    body = service.subject_body(built.subject.to_bytes())
    held = subject_scans[1]
    for k in (0, 1):
        points = sample_surface(held[k], model.faces, 20_000, seed=k)[0]
        scan = Scan(points, None, None, "m", len(points))
        g = np.linalg.norm(service.fit_mesh(scan).vertices - held[k], axis=-1).mean() * 1000.0
        p = np.linalg.norm(service.fit_mesh(scan, body=body).vertices - held[k], axis=-1).mean() * 1000.0
        assert p < 0.5 * g, (k, g, p)

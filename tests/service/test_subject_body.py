"""``subject=`` in the service core: the subject's body synthesized, fitted (registered meshes, raw scans,
sequences) and upgraded with its shape held fixed; subjects that cannot be used, or that contradict the
request, refused naming the field and the fix."""

from __future__ import annotations

import dataclasses
import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch

from bodyfit.io.scans import scan_from_arrays
from bodyfit.io.smpl import read_smpl_sequence
from bodyfit.models.fitting.common.surface import point_to_surface
from bodyfit.models.fitting.registered.smpl_topology import SOURCE_DIR, read_obj
from bodyfit.models.rig.subject import Subject, model_fingerprint
from bodyfit.models.skeleton.opensim_export import write_osim
from bodyfit.service.core import BodyService, MeshFit, SynthRequest
from bodyfit.service.errors import InvalidInputError
from tests.service.subject_files import damaged, make_subject

POSE = {"knee_angle_r": 0.6, "elbow_flex_l": 1.0, "arm_flex_r": 0.5, "hip_flexion_l": 0.4}
SEQUENCE = Path(__file__).resolve().parents[1] / "data" / "smpl_format" / "cmu_131_smpl.npz"


@pytest.fixture(scope="module")
def subject(body_service: BodyService) -> Subject:
    return make_subject(body_service.model)


def test_the_subjects_offsets_move_the_synthesized_skin(body_service: BodyService, subject: Subject) -> None:
    """In the rest (bind) pose the subject's skin is the generic body of its shape plus exactly its offsets;
    posed, each offset turns with its vertex's blended skinning rotation."""
    model = body_service.model
    body = body_service.subject_body(subject.to_bytes())
    assert body is not None and np.array_equal(body.shape, subject.shape)
    bind = torch.as_tensor(model.bind_coordinates[None], dtype=torch.float64)
    c = torch.as_tensor(subject.shape[None], dtype=torch.float64)
    zero = torch.zeros(1, 3, dtype=torch.float64)
    with torch.no_grad():
        personal = body.decoder(torch.float64)(c, bind, zero)[0][0].numpy()
        generic = model.decoder(torch.float64)(c, bind, zero)[0][0].numpy()
    assert np.abs(personal - generic - subject.offsets).max() < 1e-6
    q = model.skeleton.coordinates({k: np.array([v]) for k, v in POSE.items()})
    mine = body_service.synthesize(SynthRequest(coordinates=q, subject=subject.to_bytes())).vertices[0]
    plain = body_service.synthesize(SynthRequest(shape=subject.shape[None], coordinates=q)).vertices[0]
    out = model.forward(subject.shape[None], q, dtype=torch.float64)
    turn = model.decoder(torch.float64).blended_rotations(out.frames, torch.as_tensor(q))[0]
    expected = np.einsum("vij,vj->vi", turn, subject.offsets)
    assert np.abs(mine - plain - expected).max() < 2e-6
    assert np.abs(expected).max() > 0.01  # the offsets are large enough for the check to mean something


def test_a_registered_mesh_of_the_subject_fits_with_its_shape(
    body_service: BodyService, subject: Subject
) -> None:
    data = subject.to_bytes()
    q = body_service.model.skeleton.coordinates({k: np.array([v]) for k, v in POSE.items()})
    mesh = body_service.synthesize(SynthRequest(coordinates=q, subject=data)).vertices[0].astype(np.float64)
    scan = scan_from_arrays(mesh)
    personal = body_service.fit_mesh(scan, body=body_service.subject_body(data))
    generic = body_service.fit_mesh(scan)
    assert personal.fitted_as == generic.fitted_as == "registered"
    assert np.array_equal(personal.shape, subject.shape)
    assert personal.report.distances.mean < 0.2 < 2.0 < generic.report.distances.mean


def test_a_raw_scan_of_the_subject_fits_with_its_shape(body_service: BodyService, subject: Subject) -> None:
    """Every other vertex of the posed subject as a bare point cloud: fitted with the subject, the
    registration lies on the true surface (vertex to vertex) far closer than the generic model's, and the
    shape is the subject's."""
    data = subject.to_bytes()
    q = body_service.model.skeleton.coordinates({k: np.array([v]) for k, v in POSE.items()})
    truth = body_service.synthesize(SynthRequest(coordinates=q, subject=data)).vertices[0].astype(np.float64)
    scan = scan_from_arrays(truth[::2].copy())
    personal = body_service.fit_mesh(scan, body=body_service.subject_body(data))
    generic = body_service.fit_mesh(scan)
    assert personal.fitted_as == "raw scan" and np.array_equal(personal.shape, subject.shape)
    v2v = {
        k: np.linalg.norm(f.vertices - truth, axis=1).mean() * 1000
        for k, f in (("p", personal), ("g", generic))
    }
    assert v2v["p"] < 3.0 and v2v["p"] < 0.4 * v2v["g"], v2v


def test_an_smpl_topology_mesh_fits_with_the_subjects_shape(body_service: BodyService) -> None:
    """The CC BY woman (6,890 vertices) goes the SMPL-topology route with a subject too: with a subject of
    her own generic fit's shape, the fit keeps that shape and lies on her mesh, in her mesh's frame, as
    closely as the generic fit; a subject of another person's shape, held fixed, lies clearly farther off."""
    vertices, faces = read_obj(SOURCE_DIR / "human_woman.obj")
    scan = scan_from_arrays(vertices, faces)
    generic = body_service.fit_mesh(scan)
    model = body_service.model
    n_dof = model.skeleton.n_dof
    zero = np.zeros((model.n_vertices, 3))
    own = Subject(generic.shape, zero, model_fingerprint(model), np.zeros((1, n_dof)), np.zeros((1, 3)))
    other = make_subject(model, seed=3, amplitude_mm=0.0)
    fits = {k: body_service.fit_mesh(scan, body=body_service.subject_body(s.to_bytes()))
            for k, s in (("own", own), ("other", other))}  # fmt: skip
    assert generic.fitted_as == fits["own"].fitted_as == fits["other"].fitted_as == "SMPL topology"
    assert np.array_equal(fits["own"].shape, own.shape) and np.array_equal(fits["other"].shape, other.shape)
    faces = np.asarray(model.faces, np.int64)

    def off_mm(fit: MeshFit) -> tuple[float, float]:
        """The woman's vertices to the fit's registration and to its parametric body (the subject's skin,
        posed by the answered parameters and carried into the input's frame), mean mm."""
        with torch.no_grad():
            posed = model.forward(fit.shape[None], fit.coordinates[None], fit.root[None], dtype=torch.float64)
        R, t = fit.to_model[:3, :3], fit.to_model[:3, 3]
        parametric = (posed.vertices[0].numpy() - t) @ R
        return tuple(point_to_surface(vertices, v, faces).mean() * 1000 for v in (fit.vertices, parametric))

    off = {"generic": off_mm(generic), **{k: off_mm(f) for k, f in fits.items()}}
    assert off["own"][0] < off["generic"][0] + 1.0 and off["own"][0] < 5.0, off
    assert off["own"][1] < off["generic"][1] + 1.0 and off["other"][1] > off["own"][1] + 2.0, off


def test_a_sequence_of_the_subject_keeps_its_shape(body_service: BodyService, subject: Subject) -> None:
    data = subject.to_bytes()
    bend = np.linspace(0.2, 1.0, 4)
    q = body_service.model.skeleton.coordinates({"knee_angle_r": bend, "elbow_flex_l": bend})
    frames = body_service.synthesize(SynthRequest(coordinates=q, subject=data)).vertices
    personal = body_service.fit_sequence(frames, body=body_service.subject_body(data))
    generic = body_service.fit_sequence(frames)
    assert np.array_equal(personal.shape, subject.shape) and personal.offsets is None
    mine = np.mean([r.distances.mean for r in personal.reports])
    theirs = np.mean([r.distances.mean for r in generic.reports])
    assert mine < 2.0 and mine < 0.3 * theirs, (mine, theirs)


def test_the_upgrades_osim_carries_the_subjects_bone_scales(body_service: BodyService) -> None:
    """A subject of long bones (its bone coefficients at +1.5 SD): the upgrade keeps its shape, its
    result's scales are the subject decoder's, and the .osim written is the one of those scales."""
    model = body_service.model
    tall = make_subject(model, seed=1)
    shape = tall.shape.copy()
    shape[: model.n_bone] = 1.5
    tall = Subject(shape, tall.offsets, tall.model, tall.poses, tall.roots, tall.scans)
    body = body_service.subject_body(tall.to_bytes())
    assert body is not None
    sequence = read_smpl_sequence(SEQUENCE)
    result = body_service.upgrade(sequence, body=body)
    plain = body_service.upgrade(sequence)
    assert np.array_equal(result.shape, shape)
    with torch.no_grad():
        args = (torch.as_tensor(shape[None], dtype=torch.float32), torch.zeros(1, model.skeleton.n_dof))
        scales = body.decoder(torch.float32)(*args, torch.zeros(1, 3))[3].numpy()[0]
    assert np.array_equal(result.scales, scales) and np.abs(result.scales - plain.scales).max() > 0.01
    assert any("subject file" in note for note in result.notes)
    osim = body_service.upgrade_files(result, "walk")["osim"]
    with tempfile.TemporaryDirectory() as tmp:
        reference = write_osim(
            Path(tmp) / "walk.osim", model.skeleton.spec, scales, name="walk", geometry=False
        )
        assert osim == reference.read_bytes()


def test_unusable_subjects_are_refused_naming_the_field(body_service: BodyService, subject: Subject) -> None:
    data = subject.to_bytes()
    for what, broken in damaged(data):
        with pytest.raises(InvalidInputError) as caught:
            body_service.subject_body(broken)
        assert caught.value.field == "subject", what
        assert "subject" in caught.value.detail and (
            "rig" in caught.value.detail or "sha256" in caught.value.detail
        )
    foreign = Subject(subject.shape, subject.offsets, "0" * 64, subject.poses, subject.roots)
    with pytest.raises(InvalidInputError, match="another body model") as caught:
        body_service.subject_body(foreign.to_bytes())
    assert caught.value.field == "subject"


@pytest.mark.parametrize(
    ("extra", "field"),
    [
        ({"shape": np.zeros((1, 32))}, "shape"),
        ({"measurements": {"stature": 1.8}}, "measurements"),
        ({"sex": "male"}, "sex"),
    ],
)
def test_a_subject_with_shape_parameters_is_contradictory(
    body_service: BodyService, subject: Subject, extra: dict[str, object], field: str
) -> None:
    request = SynthRequest(subject=subject.to_bytes(), **extra)  # type: ignore[arg-type]
    with pytest.raises(
        InvalidInputError, match=f"give a subject or {field}, not both.*drop {field}"
    ) as caught:
        body_service.synthesize(request)
    assert caught.value.field == field


def test_an_upgrade_with_a_subject_and_shape_hints_is_contradictory(
    body_service: BodyService, subject: Subject
) -> None:
    from bodyfit.service.core import shape_hints

    body = body_service.subject_body(subject.to_bytes())
    with pytest.raises(InvalidInputError, match="give a subject or shape hints"):
        body_service.upgrade(read_smpl_sequence(SEQUENCE), hints=shape_hints("male", 1.8, None), body=body)


def test_the_upgrade_takes_the_subjects_own_joint_centres(
    body_service: BodyService, subject: Subject
) -> None:
    """A subject whose joint centres sit off the shape space's (segment scale offsets of +0.04): the
    upgrade's scales are those of the subject's decoder, not the shape space's for the subject's shape."""
    model = body_service.model
    offsets = np.full(np.asarray(model.data["scale_mean"]).shape, 0.04)
    moved = dataclasses.replace(subject, scale_offsets=offsets)
    body = body_service.subject_body(moved.to_bytes())
    assert body is not None
    clip = read_smpl_sequence(SEQUENCE)
    short = dataclasses.replace(
        clip, poses=clip.poses[:6], trans=clip.trans[:6], bad_frames=clip.bad_frames[:6]
    )
    result = body_service.upgrade(short, body=body)
    with torch.no_grad():
        space = model.forward(moved.shape[None]).scales.numpy()[0]
    assert np.allclose(result.scales, space + offsets, atol=1e-5)

"""Upgrading the same body motion stored in SMPL's, SMPL-H's and SMPL-X's layouts: the body coordinates do
not depend on the layout, and SMPL's finger block (hand joints 22-23, which only the 72-value layout
carries) is set to rest and reported."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from bodyfit.io.smpl import SmplSequence, read_smpl_sequence, smpl_sequence
from bodyfit.models.body.model import BodyModel
from bodyfit.models.upgrade.smpl_model import SmplModel, load_smpl_model
from bodyfit.models.upgrade.upgrade import flat_hands, upgrade_fitter, upgrade_with_model

DATA = Path(__file__).resolve().parents[1] / "data" / "smpl_format"
FRAMES = 12


@pytest.fixture(scope="module")
def smpl() -> SmplModel:
    return load_smpl_model(DATA / "smpl_like_model.npz")


@pytest.fixture(scope="module")
def clip() -> SmplSequence:
    seq = read_smpl_sequence(DATA / "cmu_131_smpl.npz")
    n = FRAMES
    return replace(seq, poses=seq.poses[:n], trans=seq.trans[:n], bad_frames=seq.bad_frames[:n])


def _layout(seq: SmplSequence, width: int, curl_deg: float) -> SmplSequence:
    """The clip stored as ``width`` values per frame; in SMPL's 72, its hand joints curl by ``curl_deg``."""
    T = seq.n_frames
    poses = seq.poses.copy()
    poses[:, 22:24, 2] = np.radians(curl_deg) * np.linspace(0.0, 1.0, T)[:, None]
    flat = np.zeros((T, width))
    body = 72 if width == 72 else 66
    flat[:, :body] = poses.reshape(T, 72)[:, :body]
    return smpl_sequence({"poses": flat, "trans": seq.trans, "betas": seq.betas, "mocap_framerate": seq.fps})


def test_flat_hands_sets_only_the_hand_joints_to_rest(clip: SmplSequence) -> None:
    curled = _layout(clip, 72, 40.0)
    flat, notes = flat_hands(curled)
    assert np.abs(flat.poses[:, 22:24]).max() == 0.0
    np.testing.assert_array_equal(flat.poses[:, :22], curled.poses[:, :22])
    assert len(notes) == 1 and "hand joints 22-23" in notes[0] and "40 degrees" in notes[0]
    plain = _layout(clip, 156, 0.0)
    same, none = flat_hands(plain)
    assert none == [] and same is plain  # nothing to set: the sequence as given


def test_the_three_layouts_give_the_same_coordinates(smpl: SmplModel, clip: SmplSequence) -> None:
    """SMPL (72 values, the fingers curling by up to 40 degrees), SMPL-H (156) and SMPL-X (165) files of the
    same body motion: the same coordinates to the bit, the curl reported in the notes."""
    # SMPL-H and SMPL-X files read as the same sequence (their body joints, no hand joints): one fit stands
    # for both.
    np.testing.assert_array_equal(_layout(clip, 165, 40.0).poses, _layout(clip, 156, 40.0).poses)
    fitter = upgrade_fitter(BodyModel.load())
    results = {w: upgrade_with_model(_layout(clip, w, 40.0), smpl, fitter) for w in (72, 156)}
    np.testing.assert_array_equal(results[156].coordinates, results[72].coordinates)
    assert any("hand joints 22-23" in n for n in results[72].notes)
    assert not any("hand joints 22-23" in n for n in results[156].notes)

"""The scan fit's grid searches on their own: the head's, hands' and toes' search (``_search_distal``) finds
the pose of a body sampled from the model, and keeps a pose that is already right."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from bodyfit.models.body.model import BodyModel
from bodyfit.models.fitting.scan_fit import ScanFitter, _Hypotheses
from bodyfit.models.fitting.scan_io import sample_surface

# grid values of DISTAL_SEARCH (10% in from each range's limits), in degrees
TRUTH_DEG = {
    "neck_rotation": 32.0,
    "neck_extension": -18.0,
    "neck_bending": 0.0,
    "pro_sup_r": 45.0,
    "wrist_flex_r": 35.0,
    "wrist_dev_r": 5.0,
}


@pytest.fixture(scope="module")
def model() -> BodyModel:
    return BodyModel.load()


def _start(model: BodyModel) -> np.ndarray:
    return model.skeleton.inside(model.bind_coordinates, 0.1)  # the scan fit's start


def _hypothesis(fitter: ScanFitter, points: np.ndarray, q: np.ndarray) -> _Hypotheses:
    model = fitter.model
    state = fitter.fitter.start_state(q[None], np.zeros((1, 3)), np.zeros((1, model.n_shape)))
    return _Hypotheses(np.eye(3)[None], np.zeros(3), points[None], state, searched=False)


def _searched(fitter: ScanFitter, hyp: _Hypotheses) -> np.ndarray:
    fitter._search_distal(hyp)
    return fitter.fitter.parameters(hyp.state)[1][0].double().numpy()


def test_distal_search_finds_the_head_and_hand(model: BodyModel) -> None:
    skel = model.skeleton
    truth = _start(model)
    for name, deg in TRUTH_DEG.items():
        truth[skel.dof_index(name)] = np.radians(deg)
    body = model.forward(np.zeros((1, model.n_shape)), truth[None], np.zeros((1, 3)), dtype=torch.float64)
    points, _ = sample_surface(body.vertices[0].numpy(), model.faces, 40_000, seed=0)
    fitter = ScanFitter(model)
    found = _searched(fitter, _hypothesis(fitter, points, _start(model)))
    for name, deg in TRUTH_DEG.items():
        assert abs(np.degrees(found[skel.dof_index(name)]) - deg) < 1.0, name
    # the left hand was right from the start and stays within a grid step
    d = skel.dof_index("pro_sup_l")
    assert abs(found[d] - truth[d]) < np.radians(18.0)


def test_distal_search_keeps_a_pose_that_is_already_right(model: BodyModel) -> None:
    q = _start(model)
    q[model.skeleton.dof_index("neck_rotation")] = np.radians(7.0)  # between grid values
    body = model.forward(np.zeros((1, model.n_shape)), q[None], np.zeros((1, 3)), dtype=torch.float64)
    points, _ = sample_surface(body.vertices[0].numpy(), model.faces, 40_000, seed=1)
    fitter = ScanFitter(model)
    found = _searched(fitter, _hypothesis(fitter, points, q))
    np.testing.assert_allclose(found, q, atol=1e-3)  # float32 state

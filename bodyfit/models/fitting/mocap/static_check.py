"""Does a static trial belong to the motion it calibrates? Protocol and subject, from the markers alone.

A static trial calibrates a subject only when it shows the same markers, stuck on the same person, as the
motion. Both are checked before any fitting, from measurements that need no model:

* protocol: the share of the motion's markers (those of the chosen set) that the static trial also shows.
  A trial from another lab's protocol names its markers otherwise and shares few or none.
* subject: the distance between two markers on the same rigid body (two pelvis markers, a thigh cluster's
  markers, a marker pair across the shank) is the same in every frame of one subject, up to skin motion;
  the median relative difference of these distances between the static trial and the motion is about 1% for
  one subject and 7-8% across subjects on the OpenSim example data (the clusters sit elsewhere on another
  person, whose bones also have other lengths). This is the marker-pair measurement that OpenSim's
  ScaleTool scales segments with (S. L. Delp et al., "OpenSim: Open-Source Software to Create and Analyze
  Dynamic Simulations of Movement", IEEE Transactions on Biomedical Engineering 54(11), 2007), used here
  as a test of identity rather than a scale.

A static trial from another protocol or another subject is refused (:class:`~.marker_sets.MarkerSetError`
naming the numbers): calibrating from it would give wrong scales and marker locations, and a silent
fallback would hide a wrong file from the user.
"""

from __future__ import annotations

import itertools
import warnings
from dataclasses import dataclass

import numpy as np

from bodyfit.io.mocap import MarkerTrial
from bodyfit.models.fitting.mocap.marker_sets import MarkerSetDef, MarkerSetError, normalise_name

MIN_SHARED_FRACTION = 0.5  # of the motion's set markers the static trial must show
MIN_SHARED = 6  # and at least this many
MAX_PAIR_DIFFERENCE = 0.04  # median relative difference of same-body marker distances (one subject: ~0.01)
MIN_PAIRS = 3  # same-body pairs needed to judge the subject


@dataclass(frozen=True)
class StaticCheck:
    """What :func:`check_static` measured.

    Attributes:
        shared: markers of the set in both trials; in_motion: markers of the set in the motion.
        pairs: same-body marker pairs measured in both.
        pair_difference: median relative difference of their distances (NaN without pairs).
        pair_difference_p90: its 90th percentile.
    """

    shared: int
    in_motion: int
    pairs: int
    pair_difference: float
    pair_difference_p90: float

    def as_dict(self) -> dict[str, float | int]:
        return {
            "shared_markers": self.shared,
            "motion_markers": self.in_motion,
            "same_body_pairs": self.pairs,
            "pair_distance_difference": self.pair_difference,
            "pair_distance_difference_p90": self.pair_difference_p90,
        }


def _median_positions(trial: MarkerTrial, names: list[str]) -> np.ndarray:
    """(T, M, 3) positions of ``names`` in ``trial`` (names normalised as the sets match them)."""
    index = {normalise_name(n): i for i, n in enumerate(trial.names)}
    return trial.positions[:, [index[n] for n in names]]


def pair_distances(trial: MarkerTrial, names: list[str], pairs: list[tuple[int, int]]) -> np.ndarray:
    """(P,) median over frames of the distance between markers ``names[i]`` and ``names[j]`` per pair (m;
    NaN for a pair never seen together)."""
    if not pairs:
        return np.zeros(0)
    positions = _median_positions(trial, names)
    i, j = np.asarray(pairs).T
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # pairs never seen together
        return np.nanmedian(np.linalg.norm(positions[:, i] - positions[:, j], axis=-1), axis=0)


def check_static(motion: MarkerTrial, static: MarkerTrial, defn: MarkerSetDef) -> StaticCheck:
    """Measure whether ``static`` shows the markers of ``motion`` on the same subject (see the module
    docstring).

    Raises:
        MarkerSetError: another protocol (fewer than half of the motion's markers, or fewer than 6, in the
            static trial) or another subject (same-body marker distances differ by more than 4% median).
    """
    in_motion = [n for n in defn.names if n in {normalise_name(m) for m in motion.names}]
    in_static = {normalise_name(m) for m in static.names}
    shared = [n for n in in_motion if n in in_static]
    if len(shared) < max(MIN_SHARED, MIN_SHARED_FRACTION * len(in_motion)):
        raise MarkerSetError(
            f"the static trial shows {len(shared)} of the motion's {len(in_motion)} {defn.name} markers: it "
            "follows another marker protocol (other marker names). Pass the static trial recorded with the "
            "motion's markers, or calibrate from the motion (static=None)"
        )
    body = {m.name: m.body for m in defn.markers}
    pairs = [
        (i, j) for i, j in itertools.combinations(range(len(shared)), 2) if body[shared[i]] == body[shared[j]]
    ]
    d_motion = pair_distances(motion, shared, pairs)
    d_static = pair_distances(static, shared, pairs)
    ok = np.isfinite(d_motion) & np.isfinite(d_static)
    rel = np.abs(d_motion - d_static)[ok] / np.maximum(d_motion, d_static)[ok]
    check = StaticCheck(
        len(shared),
        len(in_motion),
        int(ok.sum()),
        float(np.median(rel)) if len(rel) else float("nan"),
        float(np.percentile(rel, 90)) if len(rel) else float("nan"),
    )
    if check.pairs >= MIN_PAIRS and check.pair_difference > MAX_PAIR_DIFFERENCE:
        raise MarkerSetError(
            f"the static trial looks like another subject: the distances between markers on the same body "
            f"differ from the motion's by {check.pair_difference * 100:.1f}% (median over {check.pairs} "
            f"pairs; one subject's trials differ by about 1%, at most {MAX_PAIR_DIFFERENCE * 100:.0f}% is "
            "accepted). Pass this subject's static trial, or calibrate from the motion (static=None)"
        )
    return check

"""Calibration of our measurement definitions to ANSUR II's measurers: one offset per measurement.

Our landmarks are vertices and extreme points of the model's skin; ANSUR II's are palpated on the person
(cervicale is the spine of C7 under the skin, the radiale the head of the radius, the buttock height the
buttock's lowest fold). Where the two differ, they differ by nearly the same distance on everyone, so each
measurement gets an offset, in proportion to the body's stature (it is given for a body of
:data:`~bodyfit.models.anthropometry.tapes.REFERENCE_STATURE`): the mean difference between the survey's
value and ours on bodies built from ANSUR II subjects (the alternation below). Stature and weight are not
offset: the top of the head and the scale are the same instruments on both.

The offsets were learned on the training split of ``benchmarks/anthropometry.py`` (seed 39, 200 subjects
per sex; ``python benchmarks/anthropometry.py calibrate`` prints them): the benchmark's test subjects are
never seen. Alternation (as in a calibration of an instrument against a reference, each round a
least-squares step): build bodies for the targets minus the current offsets; add the mean of what is left
unmet to the offsets; three rounds.
"""

from __future__ import annotations

import numpy as np

from bodyfit.models.anthropometry.tapes import REFERENCE_STATURE
from bodyfit.models.body.model import BodyModel

FIXED = ("stature", "weightkg")
"""Measurements taken the same way on both (no offset)."""

# Metres for a body of REFERENCE_STATURE, added to our measurement to give the ANSUR II measurer's
# (benchmarks/anthropometry.py calibrate). Measurements without an ANSUR II column have none.
OFFSETS: dict[str, float] = {
    "acromialheight": -0.0092,
    "cervicaleheight": 0.0247,
    "suprasternaleheight": 0.0093,
    "chestheight": -0.0058,
    "waistheightomphalion": 0.0074,
    "iliocristaleheight": -0.0154,
    "buttockheight": -0.0294,
    "trochanterionheight": 0.0115,
    "crotchheight": 0.0138,
    "kneeheightmidpatella": -0.009,
    "lateralfemoralepicondyleheight": 0.0161,
    "lateralmalleolusheight": 0.0118,
    "tragiontopofhead": 0.0121,
    "sittingheight": -0.013,
    "acromionradialelength": 0.0048,
    "radialestylionlength": 0.033,
    "sleeveoutseam": 0.0289,
    "handlength": -0.002,
    "footlength": 0.0114,
    "balloffootlength": 0.0013,
    "footbreadthhorizontal": -0.0003,
    "biacromialbreadth": 0.0075,
    "bicristalbreadth": -0.0207,
    "bimalleolarbreadth": 0.0049,
    "hipbreadth": -0.0229,
    "buttockdepth": -0.0103,
    "chestbreadth": -0.042,
    "chestdepth": -0.0051,
    "waistbreadth": -0.0064,
    "waistdepth": -0.0057,
    "headbreadth": 0.0067,
    "headlength": 0.0013,
    "chestcircumference": 0.0005,
    "waistcircumference": 0.019,
    "buttockcircumference": -0.0073,
    "neckcircumference": -0.0472,
    "thighcircumference": -0.008,
    "calfcircumference": -0.0148,
    "anklecircumference": -0.0133,
    "wristcircumference": -0.0036,
    "headcircumference": 0.0237,
}


def learn_offsets(
    model: BodyModel, rows: dict[str, np.ndarray], names: list[str], rounds: int = 3
) -> dict[str, float]:
    """Offsets (metres) that make bodies built from survey rows meet them on average.

    Args:
        model: the :class:`~bodyfit.models.body.model.BodyModel`.
        rows: sex -> (N, M) measurements in ``names`` order (the survey's, NaN where it has no column).
        names: the measurement names (:data:`~bodyfit.models.anthropometry.inverse.NAMES`).
        rounds: alternations.
    Returns:
        name -> offset, the current :data:`OFFSETS` included, for every measurement the rows have except
        :data:`FIXED`.
    """
    from bodyfit.models.anthropometry.inverse import fit_measurements, sex_prior_mean

    extra = np.zeros(len(names))
    free = np.array([n not in FIXED for n in names])
    for _ in range(rounds):
        left = []
        for sex, t in rows.items():
            size = t[:, names.index("stature"), None] / REFERENCE_STATURE  # offsets scale with the body
            _, achieved = fit_measurements(model, t - extra * size, sex_prior_mean(model, sex))
            left.append((t - extra * size - achieved) / size)
        unmet = np.concatenate(left)
        count = np.isfinite(unmet).sum(0)
        mean = np.where(count > 0, np.nansum(unmet, 0) / np.maximum(count, 1), 0.0)
        extra += np.where(free, mean, 0.0)
    have = np.isfinite(np.concatenate(list(rows.values()))).any(0) & free
    return {n: round(OFFSETS.get(n, 0.0) + float(extra[i]), 4) for i, n in enumerate(names) if have[i]}

"""Calibration of our measurement definitions to ANSUR II's measurers: a scale and an offset per measurement.

Our landmarks are vertices and extreme points of the model's skin; ANSUR II's are palpated on the person
(cervicale is the spine of C7 under the skin, the radiale the head of the radius, the buttock height the
buttock's lowest fold). Where the two differ, they differ by nearly the same distance on everyone, or by a
nearly fixed fraction of what is measured (a tape pulled tighter over soft tissue, a landmark that sits
relatively lower on longer segments), so each measurement gets a scale and an offset, the offset in
proportion to the body's stature (it is given for a body of
:data:`~bodyfit.models.anthropometry.tapes.REFERENCE_STATURE`). The mass gets a scale only, folded into
:data:`~bodyfit.models.anthropometry.measure.DENSITY`. Stature is not calibrated: the top of the head is
the same point on both.

The calibration is learned on the training split of ``benchmarks/anthropometry.py`` (seed 39, 200
subjects per sex; ``python benchmarks/anthropometry.py calibrate`` prints it): the benchmark's test
subjects are never seen. It is the fixed point of an alternation (:func:`learn_calibration`, as in a
calibration of an instrument against a reference, each round a least-squares step): build bodies for the
survey's values under the current calibration; regress the survey's values on our definitions' raw values
of those bodies, the scale shrunk towards one; three rounds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from bodyfit.models.anthropometry.tapes import REFERENCE_STATURE
from bodyfit.models.body.model import BodyModel

FIXED = ("stature", "weightkg")
"""Measurements without a scale and an offset: the stature (the same on both) and the mass (its scale is
the density)."""

# Per measurement, the factor our definition's value is multiplied by before the offset is added (1 where
# absent; benchmarks/anthropometry.py calibrate).
SCALES: dict[str, float] = {
    "acromialheight": 0.8778,
    "cervicaleheight": 0.9144,
    "suprasternaleheight": 0.986,
    "chestheight": 1.4067,
    "waistheightomphalion": 1.07,
    "iliocristaleheight": 1.1773,
    "buttockheight": 0.9889,
    "trochanterionheight": 1.096,
    "crotchheight": 1.089,
    "kneeheightmidpatella": 1.0526,
    "lateralfemoralepicondyleheight": 1.0688,
    "lateralmalleolusheight": 0.6603,
    "tragiontopofhead": 1.0526,
    "sittingheight": 1.1342,
    "acromionradialelength": 1.1951,
    "radialestylionlength": 1.2769,
    "sleeveoutseam": 1.6112,
    "handlength": 0.6898,
    "footlength": 0.7985,
    "balloffootlength": 0.7945,
    "footbreadthhorizontal": 0.7769,
    "biacromialbreadth": 0.989,
    "bicristalbreadth": 0.8102,
    "bimalleolarbreadth": 0.764,
    "hipbreadth": 1.0359,
    "buttockdepth": 0.935,
    "chestbreadth": 0.9043,
    "chestdepth": 1.0032,
    "waistbreadth": 1.0481,
    "waistdepth": 0.9742,
    "headbreadth": 1.2795,
    "headlength": 1.1693,
    "chestcircumference": 1.1025,
    "waistcircumference": 1.0591,
    "buttockcircumference": 1.0405,
    "neckcircumference": 0.9093,
    "thighcircumference": 1.0257,
    "calfcircumference": 0.9672,
    "anklecircumference": 0.7762,
    "wristcircumference": 0.7118,
    "headcircumference": 1.5295,
}

# Metres for a body of REFERENCE_STATURE, added to our measurement (after its scale) to give the ANSUR II
# measurer's. Measurements without an ANSUR II column have neither.
OFFSETS: dict[str, float] = {
    "acromialheight": 0.1624,
    "cervicaleheight": 0.1489,
    "suprasternaleheight": 0.031,
    "chestheight": -0.5079,
    "waistheightomphalion": -0.0643,
    "iliocristaleheight": -0.2013,
    "buttockheight": -0.0155,
    "trochanterionheight": -0.0702,
    "crotchheight": -0.0562,
    "kneeheightmidpatella": -0.0355,
    "lateralfemoralepicondyleheight": -0.0158,
    "lateralmalleolusheight": 0.0287,
    "tragiontopofhead": 0.0055,
    "sittingheight": -0.1302,
    "acromionradialelength": -0.0517,
    "radialestylionlength": -0.0213,
    "sleeveoutseam": -0.2856,
    "handlength": 0.0572,
    "footlength": 0.0603,
    "balloffootlength": 0.0394,
    "footbreadthhorizontal": 0.021,
    "biacromialbreadth": 0.0037,
    "bicristalbreadth": 0.0301,
    "bimalleolarbreadth": 0.0198,
    "hipbreadth": -0.0427,
    "buttockdepth": 0.0073,
    "chestbreadth": -0.0137,
    "chestdepth": -0.0057,
    "waistbreadth": -0.0238,
    "waistdepth": -0.0005,
    "headbreadth": -0.034,
    "headlength": -0.0312,
    "chestcircumference": -0.1003,
    "waistcircumference": -0.036,
    "buttockcircumference": -0.0558,
    "neckcircumference": -0.0155,
    "thighcircumference": -0.0245,
    "calfcircumference": -0.0031,
    "anklecircumference": 0.0379,
    "wristcircumference": 0.0448,
    "headcircumference": -0.2649,
}


def calibrated(values: dict[str, torch.Tensor], size: torch.Tensor) -> dict[str, torch.Tensor]:
    """Our definitions' values (name -> (B,)) as ANSUR II's measurers would take them: ``scale * value +
    offset * size``, with ``size`` (B,) the bodies' statures over
    :data:`~bodyfit.models.anthropometry.tapes.REFERENCE_STATURE` (so that a body scaled by s still measures
    s times as much)."""
    return {name: SCALES.get(name, 1.0) * v + OFFSETS.get(name, 0.0) * size for name, v in values.items()}


@dataclass(frozen=True)
class Calibration:
    """A learned calibration: ``scales`` and ``offsets`` (name -> value, as :data:`SCALES` and
    :data:`OFFSETS`) and ``density`` (kg/m^3), the mass's scale folded into
    :data:`~bodyfit.models.anthropometry.measure.DENSITY`."""

    scales: dict[str, float]
    offsets: dict[str, float]
    density: float


def _slope(x: np.ndarray, y: np.ndarray, shrink: float) -> tuple[float, float]:
    """Scale and intercept of y on x (n,), the least-squares slope shrunk towards 1 by ``shrink`` (the
    ridge penalty ``shrink * Sxx * (a - 1)^2``; 0: least squares, inf: an offset alone)."""
    xm, ym = x.mean(), y.mean()
    sxx = ((x - xm) ** 2).sum()
    if not np.isfinite(shrink) or sxx <= 0:
        return 1.0, float(ym - xm)
    a = (((x - xm) * (y - ym)).sum() + shrink * sxx) / ((1.0 + shrink) * sxx)
    return float(a), float(ym - a * xm)


def learn_calibration(
    model: BodyModel,
    rows: dict[str, np.ndarray],
    names: list[str],
    rounds: int = 3,
    shrink: float = 1.0,
) -> Calibration:
    """The scales, offsets and density that make bodies built from survey rows meet them.

    Block-coordinate descent on the squared residuals of the rows over both the bodies and the
    calibration: build every body for the rows under the current calibration (targets mapped back through
    it), then fit each measurement's scale and offset to the survey's values against our definitions' raw
    values on those bodies, in units of the body's size, by ridge regression with the scale shrunk towards
    one (A. E. Hoerl and R. W. Kennard, "Ridge regression: biased estimation for nonorthogonal problems",
    Technometrics 12(1), 1970): a free scale would also stretch what the shape space cannot vary. The mass
    gets a scale only (a density: mass goes with the cube of the size).

    Args:
        model: the :class:`~bodyfit.models.body.model.BodyModel`.
        rows: sex -> (N, M) measurements in ``names`` order (the survey's, NaN where it has no column).
        names: the measurement names (:data:`~bodyfit.models.anthropometry.inverse.NAMES`).
        rounds: alternations.
        shrink: the ridge weight of the scale's pull towards one (see :func:`_slope`).
    Returns:
        :class:`Calibration` for every measurement the rows have except :data:`FIXED` (and the mass's
        density), starting from and replacing the current :data:`SCALES` and :data:`OFFSETS`.
    """
    from bodyfit.models.anthropometry.inverse import fit_measurements, sex_prior_mean
    from bodyfit.models.anthropometry.measure import DENSITY

    M = len(names)
    a0 = np.array([SCALES.get(n, 1.0) for n in names])
    b0 = np.array([OFFSETS.get(n, 0.0) for n in names])
    a, b = a0.copy(), b0.copy()
    mass = names.index("weightkg")
    free = np.array([n not in FIXED for n in names])
    targets = np.concatenate(list(rows.values()))
    size = targets[:, names.index("stature"), None] / REFERENCE_STATURE
    for _ in range(rounds):
        raw = []
        for sex, t in rows.items():
            s = t[:, names.index("stature"), None] / REFERENCE_STATURE
            goal = a0 * (t - b * s) / a + b0 * s  # what the current definitions must read for t
            goal[:, mass] = t[:, mass] * a0[mass] / a[mass]
            _, achieved = fit_measurements(model, goal, sex_prior_mean(model, sex))
            raw.append((achieved - b0 * s) / a0)
        r = np.concatenate(raw)
        for m in np.flatnonzero(free | (np.arange(M) == mass)):
            ok = np.isfinite(targets[:, m])
            if not ok.any():
                continue
            if m == mass:
                a[m] = float((targets[ok, m] * r[ok, m]).sum() / (r[ok, m] ** 2).sum())
            else:
                a[m], b[m] = _slope(r[ok, m] / size[ok, 0], targets[ok, m] / size[ok, 0], shrink)
    have = np.isfinite(targets).any(0) & free & (np.arange(M) != mass)
    return Calibration(
        scales={n: round(float(a[i]), 4) for i, n in enumerate(names) if have[i]},
        offsets={n: round(float(b[i]), 4) for i, n in enumerate(names) if have[i]},
        density=round(float(DENSITY * a[mass] / a0[mass]), 1),
    )

"""Plausible ranges of every measurement, per sex: where a request stops being a body.

Each range is the 0.1st to 99.9th percentile of ANSUR II (and, where it has the measurement, NHANES
2017-2020 adults) for that sex, widened by 15% of its log-ratio on each side (a factor of about 1.05-1.3),
so that only values beyond the surveyed adults are refused. The relaxed forearm tape, which neither survey
takes, uses ANSUR II's flexed forearm. Values in metres, kilograms for ``weightkg``; computed from
../shared/data/anthropometry by :func:`derive_range`.
"""

from __future__ import annotations

import numpy as np

from bodyfit.models.anthropometry.definitions import MEASUREMENTS, canonical
from bodyfit.models.errors import BodyfitError

SEXES = ("male", "female")


class ImplausibleMeasurementError(BodyfitError):
    """A measurement lies outside the plausible adult range, or contradicts another one."""


def derive_range(values: np.ndarray, widen: float = 0.15) -> tuple[float, float]:
    """(low, high) of one measurement's survey values (n,): the 0.1-99.9 percentiles widened by ``widen``
    of their log-ratio on each side."""
    lo, hi = np.percentile(np.asarray(values, np.float64), [0.1, 99.9])
    w = widen * np.log(hi / lo)
    return float(lo * np.exp(-w)), float(hi * np.exp(w))


# name -> ((male low, high), (female low, high)).
RANGES: dict[str, tuple[tuple[float, float], tuple[float, float]]] = {
    "stature": ((1.461, 2.05), (1.352, 1.897)),
    "acromialheight": ((1.211, 1.71), (1.112, 1.577)),
    "cervicaleheight": ((1.281, 1.781), (1.161, 1.645)),
    "suprasternaleheight": ((1.218, 1.691), (1.104, 1.568)),
    "chestheight": ((1.079, 1.539), (0.957, 1.402)),
    "waistheightomphalion": ((0.868, 1.281), (0.768, 1.187)),
    "iliocristaleheight": ((0.87, 1.29), (0.791, 1.204)),
    "buttockheight": ((0.704, 1.128), (0.64, 1.04)),
    "trochanterionheight": ((0.715, 1.135), (0.659, 1.05)),
    "crotchheight": ((0.674, 1.069), (0.604, 0.984)),
    "kneeheightmidpatella": ((0.384, 0.621), (0.335, 0.566)),
    "lateralfemoralepicondyleheight": ((0.394, 0.616), (0.349, 0.59)),
    "lateralmalleolusheight": ((0.053, 0.096), (0.044, 0.083)),
    "tragiontopofhead": ((0.106, 0.156), (0.101, 0.153)),
    "sittingheight": ((0.776, 1.066), (0.739, 0.977)),
    "acromionradialelength": ((0.269, 0.409), (0.242, 0.38)),
    "radialestylionlength": ((0.211, 0.338), (0.183, 0.308)),
    "sleeveoutseam": ((0.484, 0.73), (0.427, 0.674)),
    "handlength": ((0.157, 0.24), (0.147, 0.226)),
    "footlength": ((0.222, 0.327), (0.203, 0.296)),
    "balloffootlength": ((0.162, 0.247), (0.147, 0.219)),
    "footbreadthhorizontal": ((0.082, 0.127), (0.073, 0.114)),
    "biacromialbreadth": ((0.337, 0.5), (0.297, 0.439)),
    "bicristalbreadth": ((0.21, 0.352), (0.189, 0.376)),
    "bimalleolarbreadth": ((0.06, 0.094), (0.053, 0.083)),
    "hipbreadth": ((0.264, 0.469), (0.264, 0.491)),
    "buttockdepth": ((0.164, 0.371), (0.158, 0.354)),
    "chestbreadth": ((0.224, 0.367), (0.203, 0.361)),
    "chestdepth": ((0.171, 0.368), (0.165, 0.373)),
    "waistbreadth": ((0.22, 0.485), (0.193, 0.459)),
    "waistdepth": ((0.142, 0.424), (0.128, 0.385)),
    "headbreadth": ((0.133, 0.183), (0.128, 0.171)),
    "headlength": ((0.172, 0.227), (0.162, 0.222)),
    "chestcircumference": ((0.78, 1.432), (0.683, 1.316)),
    "waistcircumference": ((0.622, 1.468), (0.561, 1.324)),
    "waistcircumferenceiliaccrest": ((0.575, 1.821), (0.549, 1.884)),
    "buttockcircumference": ((0.712, 1.735), (0.709, 1.911)),
    "neckcircumference": ((0.311, 0.521), (0.265, 0.432)),
    "thighcircumference": ((0.432, 0.9), (0.435, 0.906)),
    "calfcircumference": ((0.291, 0.533), (0.273, 0.506)),
    "anklecircumference": ((0.179, 0.298), (0.166, 0.29)),
    "upperarmcircumference": ((0.188, 0.603), (0.175, 0.623)),
    "forearmcircumference": ((0.233, 0.409), (0.204, 0.35)),
    "wristcircumference": ((0.143, 0.218), (0.128, 0.191)),
    "headcircumference": ((0.513, 0.642), (0.491, 0.651)),
    "weightkg": ((36.591, 216.238), (30.802, 213.896)),
}


# Heights as fractions of the stature: (low, high) over ANSUR II men and women, widened as above. A
# height given together with the stature must keep its fraction (an inseam of 1 m under a stature of 1.4 m
# is not a body).
STATURE_FRACTIONS: dict[str, tuple[float, float]] = {
    "acromialheight": (0.783, 0.855),
    "cervicaleheight": (0.831, 0.890),
    "suprasternaleheight": (0.789, 0.846),
    "chestheight": (0.666, 0.779),
    "waistheightomphalion": (0.547, 0.654),
    "iliocristaleheight": (0.555, 0.664),
    "buttockheight": (0.445, 0.582),
    "trochanterionheight": (0.457, 0.583),
    "crotchheight": (0.423, 0.546),
    "kneeheightmidpatella": (0.242, 0.318),
    "lateralfemoralepicondyleheight": (0.247, 0.324),
    "lateralmalleolusheight": (0.029, 0.054),
    "tragiontopofhead": (0.059, 0.096),
    "sittingheight": (0.467, 0.576),
}


# The mean ANSUR II man and woman: name -> (male, female), metres and kilograms. Bodies built for a given
# sex start from, and are drawn towards, the body that has these measurements.
ANSUR_MEANS: dict[str, tuple[float, float]] = {
    "stature": (1.756, 1.628),
    "acromialheight": (1.441, 1.335),
    "cervicaleheight": (1.517, 1.396),
    "suprasternaleheight": (1.439, 1.33),
    "chestheight": (1.291, 1.172),
    "waistheightomphalion": (1.056, 0.9801),
    "iliocristaleheight": (1.062, 0.9957),
    "buttockheight": (0.8879, 0.8337),
    "trochanterionheight": (0.9009, 0.8454),
    "crotchheight": (0.8459, 0.7823),
    "kneeheightmidpatella": (0.4884, 0.449),
    "lateralfemoralepicondyleheight": (0.4917, 0.4659),
    "lateralmalleolusheight": (0.0729, 0.06275),
    "tragiontopofhead": (0.1311, 0.1265),
    "sittingheight": (0.9183, 0.8566),
    "acromionradialelength": (0.3352, 0.3112),
    "radialestylionlength": (0.2679, 0.2413),
    "sleeveoutseam": (0.5931, 0.5436),
    "handlength": (0.1933, 0.1811),
    "footlength": (0.2712, 0.2463),
    "balloffootlength": (0.2009, 0.1821),
    "footbreadthhorizontal": (0.1019, 0.09271),
    "biacromialbreadth": (0.4157, 0.3653),
    "bicristalbreadth": (0.2754, 0.2733),
    "bimalleolarbreadth": (0.07478, 0.06705),
    "hipbreadth": (0.3457, 0.3538),
    "buttockdepth": (0.2458, 0.2329),
    "chestbreadth": (0.2894, 0.2693),
    "chestdepth": (0.2538, 0.2474),
    "waistbreadth": (0.3264, 0.2999),
    "waistdepth": (0.2378, 0.213),
    "headbreadth": (0.1543, 0.1478),
    "headlength": (0.1995, 0.1898),
    "chestcircumference": (1.059, 0.9469),
    "waistcircumference": (0.9406, 0.8609),
    "buttockcircumference": (1.02, 1.021),
    "neckcircumference": (0.3976, 0.3298),
    "thighcircumference": (0.6251, 0.6161),
    "calfcircumference": (0.3923, 0.3733),
    "anklecircumference": (0.2293, 0.2157),
    "wristcircumference": (0.1759, 0.1548),
    "headcircumference": (0.5744, 0.5611),
    "weightkg": (85.52, 67.76),
}


def plausible_range(name: str, sex: str | None = None) -> tuple[float, float]:
    """(low, high) of measurement ``name`` (or an alias) for ``sex`` ("male", "female", or None: either)."""
    male, female = RANGES[canonical(name)]
    if sex is None:
        return min(male[0], female[0]), max(male[1], female[1])
    return male if sex == "male" else female


def check_sex(sex: str | None) -> None:
    """Raises ImplausibleMeasurementError unless ``sex`` is None, "male" or "female"."""
    if sex is not None and sex not in SEXES:
        raise ImplausibleMeasurementError(f"sex must be 'male', 'female' or None; got {sex!r}")


def check_measurements(values: dict[str, float], sex: str | None = None) -> dict[str, float]:
    """The request under canonical names, checked: every value finite and within its plausible range, and
    every height in proportion to the stature when both are given.

    Args:
        values: name or alias -> value in metres (kilograms for the weight).
        sex: "male", "female" or None.
    Returns:
        canonical name -> value.
    Raises:
        UnknownMeasurementError: a name is not known (with suggestions).
        ImplausibleMeasurementError: a value outside its range (named, with the range), a name given twice,
            or a height out of proportion to the stature (:data:`STATURE_FRACTIONS`).
    """
    check_sex(sex)
    out: dict[str, float] = {}
    for name, value in values.items():
        key = canonical(name)
        if key in out:
            raise ImplausibleMeasurementError(f"{name!r} gives {key!r} a second time; give it once")
        x = float(value)
        lo, hi = plausible_range(key, sex)
        unit = MEASUREMENTS[key].unit
        if not np.isfinite(x) or not lo <= x <= hi:
            who = f"an adult {sex}" if sex else "an adult"
            raise ImplausibleMeasurementError(
                f"{key} = {x:g} {unit} is not plausible for {who}: expected {lo:g} to {hi:g} {unit}"
            )
        out[key] = x
    stature = out.get("stature")
    for key, x in out.items():
        if stature is None or key not in STATURE_FRACTIONS:
            continue
        lo, hi = STATURE_FRACTIONS[key]
        if not lo * stature <= x <= hi * stature:
            raise ImplausibleMeasurementError(
                f"{key} = {x:g} m contradicts the stature {stature:g} m: expected {lo * stature:.3f} to "
                f"{hi * stature:.3f} m ({lo:g} to {hi:g} of the stature)"
            )
    return out

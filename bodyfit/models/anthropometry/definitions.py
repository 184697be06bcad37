"""The measurements: names, kinds, units, their ANSUR II / NHANES columns and their definitions.

Names are the ANSUR II column names where the survey has the measurement (C. C. Gordon, C. L. Blackwell,
B. Bradtmiller, J. L. Parham, P. Barrientos, S. P. Paquette, B. D. Corner, J. M. Carson, J. C. Venezia,
B. M. Rockwell, M. Mucher and S. Kristensen, "2012 Anthropometric Survey of U.S. Army Personnel: Methods
and Summary Statistics", Technical Report NATICK/TR-15/007, U.S. Army Natick Soldier Research, Development
and Engineering Center, 2014); landmarks and postures follow ISO 7250-1:2017 "Basic human body measurements
for technological design - Part 1: Body measurement definitions and landmarks" and ISO 8559-1:2017 "Size
designation of clothes - Part 1: Anthropometric definitions for body measurement". Values are in metres,
``weightkg`` in kilograms. Bilateral measurements are taken on the right side, as ANSUR II measures them.

The body is measured standing in the measuring posture (:func:`bodyfit.models.anthropometry.measure.
measuring_pose`); heights are vertical distances above the floor, the lowest point of the soles.
"""

from __future__ import annotations

import difflib
from dataclasses import dataclass

from bodyfit.models.errors import BodyfitError

KINDS = ("height", "length", "breadth", "circumference", "mass")


class UnknownMeasurementError(BodyfitError):
    """A measurement name is not one of :data:`MEASUREMENTS`."""


@dataclass(frozen=True)
class Measurement:
    """One measurement: ``kind`` is one of :data:`KINDS`; ``ansur`` the ANSUR II column (millimetres, or
    tenths of a kilogram for the weight) or None; ``nhanes`` the NHANES 2017-2020 P_BMX column
    (centimetres or kilograms) or None; ``definition`` how it is taken on our body."""

    name: str
    kind: str
    ansur: str | None
    nhanes: str | None
    definition: str

    @property
    def unit(self) -> str:
        return "kg" if self.kind == "mass" else "m"


def _m(name: str, kind: str, definition: str, ansur: bool = True, nhanes: str | None = None) -> Measurement:
    return Measurement(name, kind, name if ansur else None, nhanes, definition)


_HEIGHTS = (
    _m("stature", "height", "top of the head (highest skin point) above the floor", nhanes="BMXHT"),
    _m("acromialheight", "height", "mean height of the right and left acromion landmarks"),
    _m("cervicaleheight", "height", "height of the C7 (cervicale) landmark"),
    _m("suprasternaleheight", "height", "height of the suprasternale (jugular notch) landmark"),
    _m("chestheight", "height", "height of the bust points: the most anterior chest point on each side"),
    _m("waistheightomphalion", "height", "height of the omphalion (navel) landmark"),
    _m("iliocristaleheight", "height", "mean height of the iliac crest landmarks"),
    _m("buttockheight", "height", "height of the buttock point: the most posterior point of the buttocks"),
    _m(
        "trochanterionheight",
        "height",
        "height of the right hip joint centre, level with the top of the greater trochanter",
    ),
    _m("crotchheight", "height", "height of the crotch: the lowest midline point between the legs (inseam)"),
    _m(
        "kneeheightmidpatella",
        "height",
        "height of the right knee joint centre (mid-epicondyles), level with mid-patella",
    ),
    _m("lateralfemoralepicondyleheight", "height", "height of the right lateral femoral epicondyle"),
    _m("lateralmalleolusheight", "height", "height of the right ankle joint centre (mid-malleoli)"),
    _m("tragiontopofhead", "height", "stature less the mean height of the tragion landmarks"),
    _m(
        "sittingheight",
        "height",
        "stature less the crotch height: the seat taken at the crotch level of the standing body "
        "(ANSUR II sitting height is 8-10 mm larger on average, SD 15 mm)",
    ),
)
_LENGTHS = (
    _m("acromionradialelength", "length", "right acromion to radiale (lateral humeral epicondyle landmark)"),
    _m("radialestylionlength", "length", "right radiale to stylion (radial styloid landmark)"),
    _m("sleeveoutseam", "length", "acromion-radiale plus radiale-stylion: the tape down the straight arm"),
    _m("handlength", "length", "right wrist (midpoint of the styloid landmarks) to dactylion (fingertip)"),
    _m("footlength", "length", "right foot's extent along its axis (heel landmark to toe tip, horizontal)"),
    _m("balloffootlength", "length", "rearmost heel point to the first metatarsal head along the foot axis"),
)
_BREADTHS = (
    _m("footbreadthhorizontal", "breadth", "right foot's horizontal extent across its axis"),
    _m("biacromialbreadth", "breadth", "distance between the acromion landmarks"),
    _m("bicristalbreadth", "breadth", "distance between the iliac crest landmarks (on the skin)"),
    _m("bimalleolarbreadth", "breadth", "distance between the right lateral and medial malleoli"),
    _m("hipbreadth", "breadth", "left-right extent of the buttock section"),
    _m("buttockdepth", "breadth", "front-back extent of the buttock section"),
    _m("chestbreadth", "breadth", "left-right extent of the chest section"),
    _m("chestdepth", "breadth", "front-back extent of the chest section"),
    _m("waistbreadth", "breadth", "left-right extent of the waist (omphalion) section"),
    _m("waistdepth", "breadth", "front-back extent of the waist (omphalion) section"),
    _m("headbreadth", "breadth", "left-right extent of the head above the ears (3.5 cm above tragion)"),
    _m("headlength", "breadth", "front-back extent of the head above the nose (4 cm above pronasale)"),
)
_CIRCUMFERENCES = (
    _m("chestcircumference", "circumference", "horizontal tape around the torso at the bust points' height"),
    _m("waistcircumference", "circumference", "horizontal tape around the torso at the omphalion"),
    _m(
        "waistcircumferenceiliaccrest",
        "circumference",
        "horizontal tape around the torso at the iliac crests (NHANES waist)",
        ansur=False,
        nhanes="BMXWAIST",
    ),
    _m(
        "buttockcircumference",
        "circumference",
        "horizontal tape around both buttocks at the buttock point's height (NHANES hip)",
        nhanes="BMXHIP",
    ),
    _m("neckcircumference", "circumference", "tape around the neck perpendicular to its axis, at mid-neck"),
    _m("thighcircumference", "circumference", "horizontal tape around the right thigh 2 cm below the crotch"),
    _m("calfcircumference", "circumference", "largest horizontal tape around the right calf"),
    _m(
        "anklecircumference", "circumference", "smallest horizontal tape around the right leg above the ankle"
    ),
    _m(
        "upperarmcircumference",
        "circumference",
        "tape around the relaxed right upper arm, perpendicular to it, midway from acromion to elbow "
        "(NHANES arm circumference; ANSUR measures the flexed biceps instead)",
        ansur=False,
        nhanes="BMXARMC",
    ),
    _m(
        "forearmcircumference",
        "circumference",
        "largest tape around the relaxed right forearm, perpendicular to it "
        "(ANSUR measures it flexed instead)",
        ansur=False,
    ),
    _m(
        "wristcircumference",
        "circumference",
        "tape around the right wrist at the styloids, across the forearm",
    ),
    _m("headcircumference", "circumference", "largest horizontal tape around the head above the ears"),
)
_MASS = (
    _m(
        "weightkg",
        "mass",
        "volume enclosed by the skin times the body density (:data:`~bodyfit.models.anthropometry."
        "measure.DENSITY`)",
        nhanes="BMXWT",
    ),
)

MEASUREMENTS: dict[str, Measurement] = {
    m.name: m for m in (*_HEIGHTS, *_LENGTHS, *_BREADTHS, *_CIRCUMFERENCES, *_MASS)
}

# Everyday names accepted as input, mapped onto the measurement names.
ALIASES: dict[str, str] = {
    "mass": "weightkg",
    "weight": "weightkg",
    "height": "stature",
    "chest": "chestcircumference",
    "waist": "waistcircumference",
    "hip": "buttockcircumference",
    "hips": "buttockcircumference",
    "inseam": "crotchheight",
    "neck": "neckcircumference",
    "thigh": "thighcircumference",
    "calf": "calfcircumference",
    "biceps": "upperarmcircumference",
    "forearm": "forearmcircumference",
    "wrist": "wristcircumference",
    "ankle": "anklecircumference",
    "head": "headcircumference",
    "shoulder_breadth": "biacromialbreadth",
}


def canonical(name: str) -> str:
    """The measurement name for ``name`` or one of :data:`ALIASES`.

    Raises:
        UnknownMeasurementError: with the closest known names as suggestions.
    """
    if name in MEASUREMENTS:
        return name
    if name in ALIASES:
        return ALIASES[name]
    known = [*MEASUREMENTS, *ALIASES]
    close = difflib.get_close_matches(name.lower().replace("_", "").replace(" ", ""), known, n=3, cutoff=0.5)
    hint = f"; did you mean {', '.join(repr(c) for c in close)}?" if close else ""
    raise UnknownMeasurementError(
        f"unknown measurement {name!r}{hint} Known measurements: {', '.join(MEASUREMENTS)}"
    )

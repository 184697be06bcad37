"""Virtual marker sets on our skeleton: the OpenSim gait2392 and Rajagopal2015 laboratory protocols.

gait2392 is OpenSim's lower-limb and trunk model after S. L. Delp, J. P. Loan, M. G. Hoy, F. E. Zajac, E. L.
Topp and J. M. Rosen, "An interactive graphics-based model of the lower extremity to study orthopaedic
surgical procedures", IEEE Transactions on Biomedical Engineering 37(8), 1990; Rajagopal2015 is the model of
A. Rajagopal, C. L. Dembia, M. S. DeMers, D. D. Delp, J. L. Hicks and S. L. Delp, "Full-Body Musculoskeletal
Model for Muscle-Driven Simulation of Human Gait", IEEE Transactions on Biomedical Engineering 63(10), 2016.

A virtual marker is a body of our skeleton and a point in that body's frame before segment scaling. Its
default location comes from one of two sources, or the mean of several:

* ``raj:NAME``: a marker of the MarkerSet inside Rajagopal2015.osim (:data:`RAJAGOPAL_MARKERS`, copied
  verbatim from the file in nimblephysics 0.10.52; a test checks the copy). Our bodies carry Rajagopal's
  frames, so these need no fitting; markers on Rajagopal's single torso are re-expressed in our thorax
  (the upper trunk above our added thoracic joints) at the neutral pose.
* ``lm:NAME``: a bony landmark vertex of our template skin (:mod:`bodyfit.models.body.landmarks`) on the
  mean body at the neutral pose, moved outwards along the skin normal by the marker's ``offset`` (a 14 mm
  marker on a 2-3 mm base sits about 10 mm off the skin). With ``near`` set, the skin vertex nearest to
  the landmark moved by ``near`` (m, right side; mirrored for the left) is used instead: the toe marker
  sits on the nail of the hallux, 1 cm behind its tip, where a marker can stay on (not at the tip itself,
  which touches the floor).

``anatomical`` markers sit on palpated bony landmarks: they scale the subject and set its static pose.
The others (thigh and shank clusters, forearm and midfoot markers) are technical: wherever the lab put
them, calibration places them from the data. The gait2392 protocol's head and arm markers are technical
too: the head marker sits on a cap or headband rather than the vertex, and labs put the elbow and wrist
markers where their own model places them (the Hamner pipeline's marker placement moves them up to 11 cm
from its generic model, and puts ``Wrist.Med`` on the radial side of its forearm), so their default
places carry no anatomical meaning. The gait2392 ``Acromium`` sits on our template's acromion landmark,
lateral of the shoulder joint centre over the humeral head where the marker is stuck, not at Rajagopal's
``RACR`` (4 cm medial of that centre): calibrating from ``RACR`` widens the thorax by 50-60% to reach a
subject's acromion markers, which carries the shoulder joints outwards and the arm coordinates with them.
``weight`` is the inverse-kinematics weight (the values of
the OpenSim example setups). ``locked`` DOFs are held at a value because the protocol cannot see them
(subtalar and mtp as in OpenSim's setups, wrists without hand markers); ``soft`` DOFs (our added spine
and scapula joints) are pulled gently towards neutral so the Rajagopal DOFs explain what they can.
``calibration_held`` DOFs are held near neutral while calibration places technical markers on the bodies
they move: a constant offset of such a coordinate and a rotation of those markers' places are the same
motion of the markers (the wrist markers about the forearm's axis and ``pro_sup``), so the markers alone
cannot fix the coordinate's zero; holding it sets that zero where the model defines it (0: the forearm
supinated, as OpenSim's arm models define it), instead of wherever the first frames' noise leaves it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from bodyfit.models.errors import BodyfitError

# Rajagopal2015.osim MarkerSet: name -> (Rajagopal body, location in metres).
RAJAGOPAL_MARKERS: dict[str, tuple[str, tuple[float, float, float]]] = {
    "RACR": ("torso", (-0.003, 0.425, 0.13)),
    "LACR": ("torso", (-0.003, 0.425, -0.13)),
    "C7": ("torso", (-0.085, 0.435, 0.00165426)),
    "CLAV": ("torso", (0.04, 0.38, 0.017)),
    "RASH": ("torso", (0.05, 0.3715, 0.17)),
    "RPSH": ("torso", (-0.05, 0.3715, 0.17)),
    "LASH": ("torso", (0.05, 0.3715, -0.17)),
    "LPSH": ("torso", (-0.058, 0.3715, -0.17)),
    "RSJC": ("humerus_r", (0.0, 0.0, 0.0)),
    "RUA1": ("humerus_r", (0.0, -0.05, 0.02)),
    "RUA2": ("humerus_r", (0.0, -0.2, 0.02)),
    "RUA3": ("humerus_r", (0.03, -0.13, 0.02)),
    "RLEL": ("humerus_r", (0.015, -0.28, 0.04)),
    "RMEL": ("humerus_r", (0.00225, -0.286, -0.046)),
    "RFAsuperior": ("ulna_r", (0.00460453, -0.0800579, 0.0453196)),
    "RFAradius": ("radius_r", (0.0005, -0.225, 0.05)),
    "RFAulna": ("radius_r", (-0.022, -0.225, -0.022)),
    "LSJC": ("humerus_l", (0.0, 0.0, 0.0)),
    "LUA1": ("humerus_l", (0.0, -0.05, -0.02)),
    "LUA2": ("humerus_l", (0.0, -0.2, -0.02)),
    "LUA3": ("humerus_l", (0.03, -0.13, -0.02)),
    "LLEL": ("humerus_l", (0.015, -0.28, -0.04)),
    "LMEL": ("humerus_l", (0.00225005, -0.286, 0.046)),
    "LFAsuperior": ("ulna_l", (0.00460453, -0.0800579, -0.0453196)),
    "LFAradius": ("radius_l", (0.0005, -0.225, -0.05)),
    "LFAulna": ("radius_l", (-0.022, -0.225, 0.022)),
    "RASI": ("pelvis", (0.00953047, 0.0180816, 0.128464)),
    "LASI": ("pelvis", (0.00953047, 0.0180816, -0.128464)),
    "RPSI": ("pelvis", (-0.155, 0.035, 0.045)),
    "LPSI": ("pelvis", (-0.155, 0.035, -0.045)),
    "LHJC": ("femur_l", (0.0, 0.0, 0.0)),
    "RHJC": ("femur_r", (0.0, 0.0, 0.0)),
    "RTH1": ("femur_r", (0.018, -0.15, 0.064)),
    "RTH2": ("femur_r", (0.08, -0.23, 0.0047)),
    "RTH3": ("femur_r", (0.01, -0.3, 0.06)),
    "RLFC": ("femur_r", (0.0, -0.404, 0.05)),
    "RMFC": ("femur_r", (0.0, -0.404, -0.05)),
    "RKJC": ("tibia_r", (0.001731, -0.002389, -0.008452)),
    "RTB1": ("tibia_r", (-0.00166178, -0.156488, 0.0492394)),
    "RTB2": ("tibia_r", (0.0369643, -0.230107, -0.00391699)),
    "RTB3": ("tibia_r", (0.0113793, -0.295236, 0.0553541)),
    "RLMAL": ("tibia_r", (-0.005, -0.3888, 0.053)),
    "RMMAL": ("tibia_r", (0.006, -0.3888, -0.038)),
    "RAJC": ("talus_r", (0.0, 0.0, 0.0)),
    "RCAL": ("calcn_r", (-0.025, 0.02, -0.005)),
    "RTOE": ("calcn_r", (0.205, 0.0297308, -0.03)),
    "RMT5": ("calcn_r", (0.145, 0.02491, 0.059)),
    "LTH1": ("femur_l", (0.018, -0.15, -0.064)),
    "LTH2": ("femur_l", (0.08, -0.23, -0.0047)),
    "LTH3": ("femur_l", (0.01, -0.3, -0.06)),
    "LLFC": ("femur_l", (0.0, -0.404, -0.05)),
    "LMFC": ("femur_l", (0.0, -0.404, 0.05)),
    "LKJC": ("tibia_l", (0.001731, -0.002389, 0.008452)),
    "LTB1": ("tibia_l", (-0.00166178, -0.156488, -0.0492394)),
    "LTB2": ("tibia_l", (0.0369643, -0.230107, 0.00391699)),
    "LTB3": ("tibia_l", (0.0113793, -0.295236, -0.0553541)),
    "LLMAL": ("tibia_l", (-0.005, -0.3888, -0.053)),
    "LMMAL": ("tibia_l", (0.006, -0.3888, 0.038)),
    "LAJC": ("talus_l", (0.0, 0.0, 0.0)),
    "LCAL": ("calcn_l", (-0.025, 0.02, 0.005)),
    "LTOE": ("calcn_l", (0.205, 0.02973, 0.03)),
    "LMT5": ("calcn_l", (0.145, 0.024909, -0.059)),
    "REJC": ("ulna_r", (0.0, 0.0, 0.0)),
    "LEJC": ("ulna_l", (0.0, 0.0, 0.0)),
    "R_tibial_plateau": ("tibia_r", (-0.00808954, -0.017, -0.00148474)),
    "L_tibial_plateau": ("tibia_l", (-0.00808954, -0.017, 0.00148474)),
}
SKIN_OFFSET = 0.010  # m, marker centre above the skin for landmark sources


class MarkerSetError(BodyfitError):
    """A marker set name is unknown, or a trial shares too few markers with it."""


@dataclass(frozen=True)
class MarkerDef:
    """One virtual marker: the name used in trial files, our body, its sources (``raj:`` / ``lm:`` names,
    averaged), whether it is anatomical, its IK weight and, for landmark sources, its skin offset (m)
    and an optional displacement ``near`` (m, our frame at the neutral pose, right side) to a nearby
    skin point."""

    name: str
    body: str
    sources: tuple[str, ...]
    anatomical: bool
    weight: float = 1.0
    offset: float = SKIN_OFFSET
    near: tuple[float, float, float] | None = None


@dataclass(frozen=True)
class MarkerSetDef:
    """A named protocol: its markers, DOFs held fixed (name -> radians), DOFs pulled to neutral and DOFs
    held near neutral while technical markers are placed (see the module docstring)."""

    name: str
    markers: tuple[MarkerDef, ...]
    locked: tuple[tuple[str, float], ...]
    soft: tuple[str, ...]
    calibration_held: tuple[str, ...] = ()

    @property
    def names(self) -> list[str]:
        return [m.name for m in self.markers]


Row = tuple[str, str, tuple[str, ...], bool, float]
HALLUX_NAIL = (-0.010, 0.005, 0.0)  # from the toe-tip landmark to the nail of the hallux


def _sided(rows: list[Row], near: dict[str, tuple[float, float, float]] | None = None) -> list[MarkerDef]:
    """Expand right/left templates: ``{S}`` -> R/L, ``{s}`` -> r/l in names, bodies and sources; ``near``
    (by template name) displacements are mirrored (z -> -z) for the left side."""
    out = []
    for name, body, sources, anat, weight in rows:
        shift = (near or {}).get(name)
        for S, s, sign in (("R", "r", 1.0), ("L", "l", -1.0)):
            fill = {"S": S, "s": s}
            out.append(
                MarkerDef(
                    name.format(**fill),
                    body.format(**fill),
                    tuple(src.format(**fill) for src in sources),
                    anat,
                    weight,
                    near=None if shift is None else (shift[0], shift[1], sign * shift[2]),
                )
            )
    return out


_LOCK_FEET_HANDS = tuple(
    (f"{dof}_{s}", 0.0)
    for s in ("r", "l")
    for dof in ("subtalar_angle", "mtp_angle", "wrist_flex", "wrist_dev")
)
_SOFT = tuple(
    [
        "thorax_extension",
        "thorax_bending",
        "thorax_rotation",
        "neck_extension",
        "neck_bending",
        "neck_rotation",
    ]
    + [f"scapula_{d}_{s}" for s in ("r", "l") for d in ("abduction", "elevation", "upward_rot")]
)

GAIT2392 = MarkerSetDef(
    "gait2392",
    (
        MarkerDef("V.Sacral", "pelvis", ("raj:RPSI", "raj:LPSI"), True, 10.0),
        MarkerDef("Sternum", "thorax", ("lm:suprasternale", "lm:xiphoid"), False, 1.0),
        MarkerDef("Top.Head", "head", ("lm:vertex",), False, 0.1),
        *_sided(
            [
                ("{S}.ASIS", "pelvis", ("raj:{S}ASI",), True, 10.0),
                ("{S}.Thigh.Upper", "femur_{s}", ("raj:{S}TH1",), False, 1.0),
                ("{S}.Thigh.Front", "femur_{s}", ("raj:{S}TH2",), False, 1.0),
                ("{S}.Thigh.Rear", "femur_{s}", ("raj:{S}TH3",), False, 1.0),
                ("{S}.Knee.Lat", "femur_{s}", ("raj:{S}LFC",), True, 1.0),
                ("{S}.Knee.Med", "femur_{s}", ("raj:{S}MFC",), True, 1.0),
                ("{S}.Shank.Upper", "tibia_{s}", ("raj:{S}TB1",), False, 1.0),
                ("{S}.Shank.Front", "tibia_{s}", ("raj:{S}TB2",), False, 1.0),
                ("{S}.Shank.Rear", "tibia_{s}", ("raj:{S}TB3",), False, 1.0),
                ("{S}.Ankle.Lat", "tibia_{s}", ("raj:{S}LMAL",), True, 1.0),
                ("{S}.Ankle.Med", "tibia_{s}", ("raj:{S}MMAL",), True, 1.0),
                ("{S}.Heel", "calcn_{s}", ("raj:{S}CAL",), True, 10.0),
                ("{S}.Midfoot.Sup", "calcn_{s}", ("raj:{S}CAL", "raj:{S}TOE", "raj:{S}TOE"), False, 1.0),
                ("{S}.Midfoot.Lat", "calcn_{s}", ("raj:{S}MT5",), False, 1.0),
                ("{S}.Toe.Lat", "calcn_{s}", ("lm:fifth_metatarsal_head_{s}",), False, 1.0),
                ("{S}.Toe.Med", "calcn_{s}", ("lm:first_metatarsal_head_{s}",), False, 1.0),
                ("{S}.Toe.Tip", "toes_{s}", ("lm:toe_tip_{s}",), True, 10.0),
                ("{S}.Acromium", "scapula_{s}", ("lm:acromion_{s}",), True, 0.5),
                ("{S}.Bicep", "humerus_{s}", ("raj:{S}UA3",), False, 1.0),
                ("{S}.Elbow", "humerus_{s}", ("raj:{S}LEL",), False, 1.0),
                ("{S}.Wrist.Med", "radius_{s}", ("raj:{S}FAulna",), False, 1.0),
                ("{S}.Wrist.Lat", "radius_{s}", ("raj:{S}FAradius",), False, 1.0),
                ("{S}.Temple", "head", ("lm:tragion_{s}",), False, 0.1),
            ],
            near={"{S}.Toe.Tip": HALLUX_NAIL},
        ),
    ),
    _LOCK_FEET_HANDS,
    _SOFT,
    ("pro_sup_r", "pro_sup_l"),
)

_TORSO_OURS = {"RACR", "LACR", "C7", "CLAV", "RASH", "RPSH", "LASH", "LPSH"}
_TECHNICAL = {"RASH", "RPSH", "LASH", "LPSH", "RFAsuperior", "LFAsuperior"} | {
    f"{S}{c}{i}" for S in "RL" for c in ("UA", "TH", "TB") for i in (1, 2, 3)
}
_HEAVY = {"RASI", "LASI", "RPSI", "LPSI", "RCAL", "LCAL", "RTOE", "LTOE"}

RAJAGOPAL = MarkerSetDef(
    "rajagopal",
    (
        *(
            MarkerDef(
                name,
                "thorax" if name in _TORSO_OURS else body,
                (f"raj:{name}",),
                name not in _TECHNICAL,
                10.0 if name in _HEAVY else 1.0,
            )
            for name, (body, _) in RAJAGOPAL_MARKERS.items()
            if "plateau" not in name
        ),
        # The names of the walking trials of the Rajagopal pipeline (ExpData/static_walk_1.trc).
        MarkerDef("S2", "pelvis", ("raj:RPSI", "raj:LPSI"), False, 1.0),
        *_sided(
            [
                ("{S}.Shoulder", "thorax", ("raj:{S}ACR",), True, 1.0),
                ("{S}.Clavicle", "thorax", ("lm:suprasternale",), False, 1.0),
                ("{S}.Biceps", "humerus_{s}", ("raj:{S}UA3",), False, 1.0),
                ("{S}.Elbow", "humerus_{s}", ("raj:{S}LEL",), True, 1.0),
                ("{S}.MElbow", "humerus_{s}", ("raj:{S}MEL",), True, 1.0),
                ("{S}.Forearm", "ulna_{s}", ("raj:{S}FAsuperior",), False, 1.0),
                ("{S}.Wrist", "radius_{s}", ("raj:{S}FAradius",), False, 1.0),
                ("{S}.ASIS", "pelvis", ("raj:{S}ASI",), True, 10.0),
                ("{S}.PSIS", "pelvis", ("raj:{S}PSI",), True, 10.0),
                ("{S}.TH1", "femur_{s}", ("raj:{S}TH1",), False, 1.0),
                ("{S}.TH2", "femur_{s}", ("raj:{S}TH2",), False, 1.0),
                ("{S}.TH3", "femur_{s}", ("raj:{S}TH3",), False, 1.0),
                ("{S}.TH4", "femur_{s}", ("raj:{S}TH2", "raj:{S}TH3"), False, 1.0),
                ("{S}.Knee", "femur_{s}", ("raj:{S}LFC",), True, 1.0),
                ("{S}.MKnee", "femur_{s}", ("raj:{S}MFC",), True, 1.0),
                ("{S}.SH1", "tibia_{s}", ("raj:{S}TB1",), False, 1.0),
                ("{S}.SH2", "tibia_{s}", ("raj:{S}TB2",), False, 1.0),
                ("{S}.SH3", "tibia_{s}", ("raj:{S}TB3",), False, 1.0),
                ("{S}.SH4", "tibia_{s}", ("raj:{S}TB2", "raj:{S}TB3"), False, 1.0),
                ("{S}.Ankle", "tibia_{s}", ("raj:{S}LMAL",), True, 1.0),
                ("{S}.MAnkle", "tibia_{s}", ("raj:{S}MMAL",), True, 1.0),
                ("{S}.Heel", "calcn_{s}", ("raj:{S}CAL",), True, 10.0),
                ("{S}.MT5", "calcn_{s}", ("raj:{S}MT5",), True, 1.0),
                ("{S}.Toe", "calcn_{s}", ("raj:{S}TOE",), True, 10.0),
                ("{S}_HJC", "femur_{s}", ("raj:{S}HJC",), True, 1.0),
                ("{S}.KneeJoint", "femur_{s}", ("raj:{S}LFC", "raj:{S}MFC"), True, 1.0),
                ("{S}.AnkleJoint", "tibia_{s}", ("raj:{S}LMAL", "raj:{S}MMAL"), True, 1.0),
            ]
        ),
    ),
    _LOCK_FEET_HANDS,
    _SOFT,
    ("pro_sup_r", "pro_sup_l"),
)

MARKER_SETS: dict[str, MarkerSetDef] = {s.name: s for s in (GAIT2392, RAJAGOPAL)}
MarkerSetName = Literal["auto", "gait2392", "rajagopal"]
"""A marker set by name, or ``"auto"``: the set sharing most names with the trial."""


def normalise_name(name: str) -> str:
    """Marker names as matched against a set: C3D subject prefixes (``Subject:RASI``) dropped."""
    return name.rsplit(":", 1)[-1].strip()


def choose_marker_set(
    names: list[str] | tuple[str, ...], marker_set: MarkerSetName | str = "auto"
) -> MarkerSetDef:
    """The marker set for a trial's marker names: a named one, or (``"auto"``) the one sharing most names.

    Raises:
        MarkerSetError: unknown name, or no set shares at least 6 markers with the trial.
    """
    present = {normalise_name(n) for n in names}
    if marker_set != "auto":
        if marker_set not in MARKER_SETS:
            raise MarkerSetError(
                f"unknown marker set {marker_set!r}; choose one of {', '.join(['auto', *MARKER_SETS])}"
            )
        chosen = MARKER_SETS[marker_set]
    else:
        chosen = max(MARKER_SETS.values(), key=lambda s: len(present & set(s.names)))
    shared = present & set(chosen.names)
    if len(shared) < 6:
        raise MarkerSetError(
            f"the trial shares {len(shared)} marker names with the {chosen.name} set (at least 6 needed). "
            f"Rename the markers to the set's names (e.g. {', '.join(chosen.names[:5])}) or pick "
            f"marker_set= one of {', '.join(MARKER_SETS)}."
        )
    return chosen

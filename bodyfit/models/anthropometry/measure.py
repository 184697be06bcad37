"""Measure bodies of the model: heights, lengths, breadths, tape circumferences and mass, batched.

:func:`measure` synthesizes bodies from shape coefficients (in the measuring posture unless coordinates
are given) and measures them; :func:`measure_vertices` measures skin vertices in our topology directly;
:func:`measure_torch` is the differentiable core both use. Every definition is in
:mod:`bodyfit.models.anthropometry.definitions` and docs/anthropometry.md.
"""

from __future__ import annotations

import numpy as np
import torch

from bodyfit.models.anthropometry.calibration import calibrated
from bodyfit.models.anthropometry.definitions import MEASUREMENTS
from bodyfit.models.anthropometry.regions import Topology, topology
from bodyfit.models.anthropometry.sections import closed_volume
from bodyfit.models.anthropometry.tapes import (
    REFERENCE_STATURE,
    Cutter,
    arm_tapes,
    head_tapes,
    leg_tapes,
    torso_tapes,
)
from bodyfit.models.body.model import BodyModel
from bodyfit.models.errors import ShapeError
from bodyfit.models.skeleton.model import check_finite

# Whole-body density (kg/m^3) that turns the skin's enclosed volume into mass: the weight's scale in the
# calibration to ANSUR II (calibration.py; benchmarks/anthropometry.py calibrate), which makes bodies built
# for ANSUR II subjects' lengths and tapes weigh what the subjects did. Tissue densities are 900 (fat) to
# 1,100 (fat-free mass) kg/m^3 (W. E. Siri, "Body composition from fluid spaces and density: analysis of
# methods", in J. Brozek and A. Henschel (eds.), Techniques for Measuring Body Composition, National
# Academy of Sciences, 1961), an adult's 1,030-1,070 before the air in the lungs.
DENSITY = 1039.0

# Width (metres, for a body of REFERENCE_STATURE) over which the bust and buttock points are averaged.
SOFT_EXTREME = 0.002

# Coordinates that keep their bind-pose value in the measuring posture: the arms stay in the template's
# rest A-pose, away from the torso, where the skin is undeformed; everything else is zero (standing
# erect, legs straight, head level).
_ARM_PREFIXES = ("scapula_", "arm_", "elbow_", "pro_sup_", "wrist_")


def measuring_pose(model: BodyModel) -> np.ndarray:
    """The measuring posture (n_dof,): standing erect, legs straight and together as the skeleton's zero
    pose, arms in the template's A-pose so that every torso section passes under the armpits."""
    q = np.zeros(model.skeleton.n_dof)
    bind = model.bind_coordinates
    for i, name in enumerate(model.dof_names):
        if name.startswith(_ARM_PREFIXES):
            q[i] = bind[i]
    return q


def body_in_pose(
    model: BodyModel, shape: torch.Tensor, coordinates: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Skin vertices (B, V, 3) and joints (B, J, 3) of shapes (B, n_shape) at coordinates (B, n_dof),
    default :func:`measuring_pose`; differentiable in ``shape``. The measuring posture holds two
    coordinates outside their limits (the template's rest pose), so the decoder is called unchecked."""
    B = shape.shape[0]
    if coordinates is None:
        coordinates = torch.as_tensor(measuring_pose(model), dtype=shape.dtype).expand(B, -1)
    decoder = model.decoder(shape.dtype)
    vertices, joints, _, _ = decoder(shape, coordinates, torch.zeros(B, 3, dtype=shape.dtype))
    return vertices, joints


def measure(
    model: BodyModel, shape: np.ndarray, coordinates: np.ndarray | None = None
) -> dict[str, np.ndarray]:
    """Measure bodies of the model.

    Args:
        model: the body model.
        shape: (B, n_shape) shape coefficients, or (n_shape,) for one body.
        coordinates: (B, n_dof) coordinates in ``model.dof_names`` order (checked against their limits),
            or None for the measuring posture (:func:`measuring_pose`): heights are only meaningful on a
            body standing on +y.
    Returns:
        name -> (B,) float64 values in metres (``weightkg`` in kilograms), in :data:`MEASUREMENTS` order.
    Raises:
        ShapeError, NonFiniteError, CoordinateRangeError: as :meth:`BodyModel.forward`.
    """
    c = np.asarray(shape, np.float64)
    c = c[None] if c.ndim == 1 else c
    shape_t = model.validate_shape(c, len(c), torch.float32)
    q = None
    if coordinates is not None:
        q, _, _ = model.skeleton.validate(coordinates, None, dtype=torch.float32)
        if q.shape[0] != len(c):
            raise ShapeError(f"coordinates must have one row per shape ({len(c)}); got {q.shape[0]}")
    with torch.no_grad():
        vertices, joints = body_in_pose(model, shape_t, q)
        out = measure_torch(topology(model), vertices, joints)
    return {k: v.double().numpy() for k, v in out.items()}


def measure_vertices(
    model: BodyModel, vertices: np.ndarray, joints: np.ndarray | None = None
) -> dict[str, np.ndarray]:
    """Measure skin meshes in our topology (a fit's registration, a synthesized body).

    Args:
        vertices: (B, V, 3) or (V, 3) metres, standing on +y.
        joints: (B, J, 3) the anatomical joint centres in ``model.joint_names`` order, or None to regress
            them from the vertices (``joint_regressor``, within about 2 cm: only the limb axes use them).
    Returns:
        As :func:`measure`.
    """
    v = np.asarray(vertices, np.float64)
    v = v[None] if v.ndim == 2 else v
    if v.ndim != 3 or v.shape[1:] != (model.n_vertices, 3):
        raise ShapeError(f"vertices must have shape (B, {model.n_vertices}, 3); got {np.shape(vertices)}")
    check_finite("vertices", v)
    topo = topology(model)
    j = (
        np.einsum("jv,bvc->bjc", topo.joint_regressor, v)
        if joints is None
        else np.asarray(joints, np.float64)
    )
    with torch.no_grad():
        out = measure_torch(topo, torch.as_tensor(v), torch.as_tensor(j))
    return {k: t.double().numpy() for k, t in out.items()}


def measure_torch(
    topo: Topology,
    vertices: torch.Tensor,
    joints: torch.Tensor,
    paths: dict[str, torch.Tensor] | None = None,
) -> dict[str, torch.Tensor]:
    """The differentiable core: every measurement of skin vertices (B, V, 3) and joints (B, J, 3) ->
    name -> (B,) tensors, in :data:`MEASUREMENTS` order. With ``paths`` a dict, each tape's path (B, k, 3)
    is recorded there (for figures)."""
    p = _points(topo, vertices, joints)
    size = (p["top"] - p["floor"]) / REFERENCE_STATURE
    cut = Cutter(topo, vertices, size, paths)
    out: dict[str, torch.Tensor] = {}
    out.update(_heights(p))
    out.update(_lengths(topo, vertices, p))
    out.update(torso_tapes(cut, p))
    out.update(head_tapes(cut, p))
    out.update(leg_tapes(cut, p))
    out.update(arm_tapes(cut, p))
    out["weightkg"] = closed_volume(vertices, topo.faces) * DENSITY
    # Calibrated to ANSUR II's measurers (calibration.py): a scale and an offset per definition, the offset
    # in proportion to the body's size as every length is.
    return calibrated({name: out[name] for name in MEASUREMENTS}, size)


def _points(topo: Topology, v: torch.Tensor, joints: torch.Tensor) -> dict[str, torch.Tensor]:
    """Named points (B, 3) and levels (B,): landmarks, joints, extreme points, the floor and the top."""
    p: dict[str, torch.Tensor] = {n: v[:, i] for n, i in topo.landmarks.items()}
    p.update({f"joint_{n}": joints[:, i] for i, n in enumerate(topo.joint_names)})
    cand = topo.candidates
    p["floor"] = v[:, cand["feet"], 1].min(1).values
    p["top"] = v[:, cand["head"], 1].max(1).values
    p["crotch"] = v[:, cand["crotch"], 1].min(1).values
    # Soft extremes: a rounded surface's extreme is a patch, not a vertex; weighting the candidates within
    # a few millimetres of it keeps the point (and the planes hung on it) smooth in the shape.
    width = SOFT_EXTREME * (p["top"] - p["floor"]) / REFERENCE_STATURE
    for side in ("r", "l"):
        p[f"bust_{side}"] = _soft_extreme(v[:, cand[f"bust_{side}"]], 0, 1.0, width)
    p["buttock"] = _soft_extreme(v[:, cand["buttock"]], 0, -1.0, width)
    return p


def _soft_extreme(points: torch.Tensor, axis: int, sign: float, width: torch.Tensor) -> torch.Tensor:
    """The softmax-weighted mean (B, 3) of points (B, n, 3) by ``sign`` times their ``axis`` coordinate
    over ``width`` (B,) metres: the extreme point, averaged over the candidates within a few widths of it."""
    weights = torch.softmax(sign * points[..., axis] / width[:, None], dim=1)
    return (weights[..., None] * points).sum(1)


def _heights(p: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    floor = p["floor"]

    def h(*names: str) -> torch.Tensor:
        return torch.stack([p[n][:, 1] for n in names]).mean(0) - floor

    stature = p["top"] - floor
    crotch = p["crotch"] - floor
    return {
        "stature": stature,
        "acromialheight": h("acromion_r", "acromion_l"),
        "cervicaleheight": h("C7"),
        "suprasternaleheight": h("suprasternale"),
        "chestheight": h("bust_r", "bust_l"),
        "waistheightomphalion": h("omphalion"),
        "iliocristaleheight": h("iliac_crest_r", "iliac_crest_l"),
        "buttockheight": h("buttock"),
        "trochanterionheight": h("joint_hip_r"),
        "crotchheight": crotch,
        "kneeheightmidpatella": h("joint_knee_r"),
        "lateralfemoralepicondyleheight": h("lateral_femoral_epicondyle_r"),
        "lateralmalleolusheight": h("joint_ankle_r"),
        "tragiontopofhead": p["top"] - 0.5 * (p["tragion_r"][:, 1] + p["tragion_l"][:, 1]),
        "sittingheight": stature - crotch,
    }


def _dist(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (a - b).norm(dim=-1)


def _lengths(topo: Topology, v: torch.Tensor, p: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Straight landmark distances and the foot's extents along and across its horizontal axis."""
    upper = _dist(p["acromion_r"], p["lateral_humeral_epicondyle_r"])
    # The forearm's landmarks turn about its axis with pronation; its joint centres do not.
    fore = _dist(p["joint_elbow_r"], p["joint_wrist_r"])
    wrist = 0.5 * (p["radial_styloid_r"] + p["ulnar_styloid_r"])
    axis = p["toe_tip_r"] - p["heel_r"]
    axis = torch.stack([axis[:, 0], torch.zeros_like(axis[:, 0]), axis[:, 2]], -1)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    across = torch.stack([-axis[:, 2], torch.zeros_like(axis[:, 0]), axis[:, 0]], -1)
    foot = v[:, topo.candidates["foot_r"]]
    along = (foot * axis[:, None]).sum(-1)
    side = (foot * across[:, None]).sum(-1)
    heel = along.min(1).values
    return {
        "acromionradialelength": upper,
        "radialestylionlength": fore,
        "sleeveoutseam": upper + fore,
        "handlength": _dist(wrist, p["dactylion_r"]),
        "footlength": along.max(1).values - heel,
        "balloffootlength": (p["first_metatarsal_head_r"] * axis).sum(-1) - heel,
        "footbreadthhorizontal": side.max(1).values - side.min(1).values,
        "biacromialbreadth": _dist(p["acromion_r"], p["acromion_l"]),
        "bicristalbreadth": _dist(p["iliac_crest_r"], p["iliac_crest_l"]),
        "bimalleolarbreadth": _dist(p["lateral_malleolus_r"], p["medial_malleolus_r"]),
    }

"""A scan fit's hints (:class:`ScanHints`): checked once for every transport, turned into what the fitters
take (an orientation, start coordinates) and recorded in the report with how each was used."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np
import torch

from bodyfit.models.body.model import BodyModel
from bodyfit.models.upgrade.proxy import ShapeHintError, ShapeHints
from bodyfit.service.errors import InvalidInputError
from bodyfit.wire.hints import Axis, PoseClass, axis_name, pose_class

# The fitted body's standing height may differ from a given height by this much (m) before the fit is
# reported not confident: a stated height is often off by 2-3 cm (shoes, posture, rounding), a fit of the
# wrong units or with the legs folded away by far more.
HEIGHT_TOLERANCE_M = 0.08
# Each pose class's coordinates (degrees) over the bind pose; "standing" is the fitters' own default start.
POSE_DEGREES: dict[str, dict[str, float]] = {
    "standing": {},
    "sitting": {"hip_flexion_r": 90.0, "hip_flexion_l": 90.0, "knee_angle_r": 90.0, "knee_angle_l": 90.0},
    "a-pose": {"arm_add_r": -45.0, "arm_add_l": -45.0, "elbow_flex_r": 0.0, "elbow_flex_l": 0.0},
    "t-pose": {"arm_add_r": -90.0, "arm_add_l": -90.0, "elbow_flex_r": 0.0, "elbow_flex_l": 0.0},
}
_UNIT = {"x": 0, "y": 1, "z": 2}
T = TypeVar("T")


def _checked(parse: Callable[[str], T], text: str | None, field: str) -> T | None:
    """``parse(text)``, None for no text; its ValueError as the 422 of ``field``."""
    if not text:
        return None
    try:
        return parse(text)
    except ValueError as exc:
        raise InvalidInputError(str(exc), field=field) from None


def unit_axis(axis: Axis) -> np.ndarray:
    """(3,) the unit vector of a signed axis ("+z" -> (0, 0, 1))."""
    v = np.zeros(3)
    v[_UNIT[axis[1]]] = 1.0 if axis[0] == "+" else -1.0
    return v


@dataclass(frozen=True)
class ScanHints:
    """What the user says about a scan; None where nothing was said. up, facing: signed axes of the scan's
    frame (:data:`bodyfit.wire.hints.AXES`); pose: a start pose class; sex; height_m: standing height (m)."""

    up: Axis | None = None
    facing: Axis | None = None
    pose: PoseClass | None = None
    sex: str | None = None
    height_m: float | None = None

    @classmethod
    def given(
        cls,
        up: str | None = None,
        facing: str | None = None,
        pose: str | None = None,
        sex: str | None = None,
        height_m: float | None = None,
    ) -> ScanHints:
        """The hints from optional request fields (an empty text counts as none given).

        Raises:
            InvalidInputError: naming the hint at fault and the values it may take.
        """
        u = _checked(lambda text: axis_name(text, "up"), up, "up")
        f = _checked(lambda text: axis_name(text, "facing"), facing, "facing")
        p = _checked(pose_class, pose, "pose")
        if u is not None and f is not None and u[1] == f[1]:
            raise InvalidInputError(
                f"facing must be perpendicular to up; got up {u} and facing {f}", field="facing"
            )
        try:
            ShapeHints.given(sex or None, height_m, None)
        except ShapeHintError as exc:
            raise InvalidInputError(str(exc), field=exc.field) from exc
        return cls(u, f, p, sex or None, height_m)

    def given_names(self) -> list[str]:
        """The hints given, by name."""
        return [name for name, value in self.values().items() if value is not None]

    def values(self) -> dict[str, Any]:
        return {
            "up": self.up,
            "facing": self.facing,
            "pose": self.pose,
            "sex": self.sex,
            "height_m": self.height_m,
        }

    def orientation(self) -> np.ndarray | None:
        """(3, 3) the rotation from the scan's axes to the body's (+X forward, +Y up, +Z to the right), the
        convention of ``ScanFitter.fit(orientation=)``, when up and facing are both given; else None."""
        if self.up is None or self.facing is None:
            return None
        forward, up = unit_axis(self.facing), unit_axis(self.up)
        return np.stack([forward, up, np.cross(forward, up)])

    def up_only(self) -> np.ndarray | None:
        """(3,) the scan's up direction when up is given without facing (``ScanFitter.fit(up=)``: the
        orientation search keeps it); else None."""
        return unit_axis(self.up) if self.up is not None and self.facing is None else None

    def start(self, model: BodyModel) -> np.ndarray | None:
        """(n_dof,) the start coordinates of the pose class (:data:`POSE_DEGREES` over the bind pose, within
        the limits; the fitters move a start further inside them), or None without a pose class or for
        "standing" (the fitters' default start)."""
        if self.pose is None or not POSE_DEGREES[self.pose]:
            return None
        skel = model.skeleton
        q = np.asarray(model.bind_coordinates, np.float64).copy()
        for name, degrees in POSE_DEGREES[self.pose].items():
            q[skel.dof_index(name)] = np.radians(degrees)
        return skel.inside(q, 0.0)


def standing_height(model: BodyModel, shape: np.ndarray) -> float:
    """The standing height (m, sole to vertex) of the body of ``shape`` (n_shape,) in the neutral pose (every
    coordinate 0, moved inside its limits): legs straight, arms hanging."""
    q = model.skeleton.inside(np.zeros(model.skeleton.n_dof), 0.0)
    with torch.no_grad():
        out = model.forward(
            np.asarray(shape, np.float64)[None], q[None], np.zeros((1, 3)), dtype=torch.float64
        )
    y = out.vertices[0, :, 1].numpy()
    return float(y.max() - y.min())


@dataclass(frozen=True)
class HintUse:
    """How a fit used its hints: ``notes`` per hint name (what was done with it) and the names ``used``."""

    notes: dict[str, str]
    used: frozenset[str]

    def record(self, hints: ScanHints) -> dict[str, dict[str, Any]]:
        """The report's ``extra["hints"]``: per given hint, its value, whether it was used and how."""
        return {
            name: {"value": value, "used": name in self.used, "how": self.notes[name]}
            for name, value in hints.values().items()
            if value is not None
        }


def hint_use(
    hints: ScanHints, route: str, orientation_used: bool, start_used: bool, up_used: bool = False
) -> HintUse:
    """How a fit of ``route`` ("registered", "SMPL topology", "raw scan") used ``hints``: the orientation
    and start pose as the caller passed them on; sex is recorded only (no fitter has a sex-specific shape
    prior); height is checked after the fit (:func:`height_check`)."""
    notes: dict[str, str] = {}
    used: set[str] = set()
    if hints.up is not None or hints.facing is not None:
        if orientation_used:
            what = "the scan's orientation" if route == "raw scan" else "the mesh's orientation"
            instead = (
                "in place of a search" if route == "raw scan" else "in place of SMPL's (+y up, facing +z)"
            )
            note = f"used as {what}, {instead}"
            used |= {"up", "facing"}
        elif route == "registered":
            note = "recorded: a mesh in our topology is placed by its own vertices"
        else:
            note = "recorded: the orientation is used when up and facing are both given"
        notes["up"] = notes["facing"] = note
        if up_used:
            notes["up"] = "used: the orientation search tried headings about this up axis only"
            used.add("up")
    if hints.pose is not None:
        if start_used or (hints.pose == "standing" and route == "raw scan"):
            notes["pose"] = f"the fit started from the {hints.pose} pose class"
            used.add("pose")
        else:
            notes["pose"] = (
                "recorded: a mesh with a known topology is placed by its vertices, not a start pose"
            )
    if hints.sex is not None:
        notes["sex"] = "recorded: the fitters have no sex-specific shape prior"
    return HintUse(notes, frozenset(used))


def height_check(
    model: BodyModel, shape: np.ndarray, height_m: float, partial: bool
) -> tuple[str, str | None]:
    """The height hint's note and, when the fitted body's standing height (:func:`standing_height`) differs
    from ``height_m`` by more than :data:`HEIGHT_TOLERANCE_M`, the reason the fit is not confident; a head
    and shoulders (``partial``) is not checked (its legs are the shape space's guess)."""
    if partial:
        return "recorded: a head and shoulders does not show the height", None
    fitted = standing_height(model, shape)
    note = f"checked: the fitted body stands {fitted:.2f} m tall"
    if abs(fitted - height_m) <= HEIGHT_TOLERANCE_M:
        return note, None
    return note, (
        f"the fitted body stands {fitted:.2f} m tall but the height hint says {height_m:.2f} m: the fit is "
        "wrong (check the scan's units and orientation), or the hint is"
    )

"""What a user may say about a scan, the same on every interface (REST form fields, gRPC ``FitScanRequest``,
the SDK's ``fit_scan`` and ``bodyfit fit scan``): its up axis and the axis the person faces, a start pose
class, and the person's sex and height. The server checks them (a 422 / INVALID_ARGUMENT naming the allowed
values); the SDK checks the names here before sending."""

from __future__ import annotations

from typing import Literal, get_args

Axis = Literal["+x", "-x", "+y", "-y", "+z", "-z"]
"""A signed axis of the scan's own frame."""
AXES: tuple[Axis, ...] = get_args(Axis)
PoseClass = Literal["standing", "sitting", "a-pose", "t-pose"]
"""A start pose class: standing (arms hanging, the fitters' default start), sitting (hips and knees bent 90
degrees), a-pose (arms 45 degrees from the sides), t-pose (arms horizontal)."""
POSE_CLASSES: tuple[PoseClass, ...] = get_args(PoseClass)
Sex = Literal["male", "female", "neutral"]
SEXES: tuple[Sex, ...] = get_args(Sex)
HINT_NAMES = ("up", "facing", "pose", "sex", "height_m")
"""The hints' names, as every interface spells them (the command line: ``--up``, ..., ``--height-m``)."""
UP_HELP = (
    "the scan's up axis, in its own frame: +x, -x, +y, -y, +z or -z (a bare x, y or z is +); with facing, "
    "the orientation is not searched"
)
FACING_HELP = (
    "the scan axis the person faces (their front points along it), perpendicular to up: +x, -x, +y, -y, +z "
    "or -z"
)
POSE_HELP = (
    "the start pose class: standing (the default start), sitting, a-pose (arms 45 degrees out) or t-pose "
    "(arms horizontal)"
)
SEX_HELP = "the person's sex: male, female or neutral (recorded in the report)"
HEIGHT_HELP = (
    "the person's standing height in metres, 1.2 to 2.3 (the fitted body's height is checked against it)"
)


def axis_name(text: str, field: str = "up") -> Axis:
    """The signed axis ``text`` names ("+z", "-Y", "x"), as one of :data:`AXES`.

    Raises:
        ValueError: text that names no axis; the message names ``field`` and the allowed values.
    """
    key = text.strip().lower()
    key = key if key[:1] in ("+", "-") else f"+{key}"
    for axis in AXES:
        if axis == key:
            return axis
    raise ValueError(f"{field} must be one of {', '.join(AXES)} (a bare x, y or z is +); got {text!r}")


def pose_class(text: str) -> PoseClass:
    """The pose class ``text`` names (any case: "A-pose" is "a-pose").

    Raises:
        ValueError: text that names no class; the message names the allowed values.
    """
    key = text.strip().lower()
    for name in POSE_CLASSES:
        if name == key:
            return name
    raise ValueError(f"pose must be one of {', '.join(POSE_CLASSES)}; got {text!r}")

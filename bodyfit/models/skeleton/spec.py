"""Skeleton description: bodies, joints, transform axes, coordinates. Pure data, JSON round-trippable.

Every joint is described the way OpenSim describes a CustomJoint (S. L. Delp et al., "OpenSim: Open-Source
Software to Create and Analyze Dynamic Simulations of Movement", IEEE Transactions on Biomedical Engineering
54(11), 2007; A. Seth et al., "OpenSim: Simulating musculoskeletal dynamics and neuromuscular control to study
human and animal movement", PLoS Computational Biology 14(7), 2018), which covers all joint types we use (pin,
universal, ball, the Walker knee, our spine and scapula sub-joints):

    X_child_in_parent = X_parent_offset @ X_FM(q) @ inverse(X_child_offset)
    X_FM(q) = [R(a1, f1(q)) R(a2, f2(q)) R(a3, f3(q)),  f4(q) b4 + f5(q) b5 + f6(q) b6]

with three rotation axes ``a_i`` applied body-fixed in order, and three translation axes ``b_i`` expressed in
the joint's parent offset frame F. Each ``f`` is a :class:`Function` of one coordinate (or a constant).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

FunctionKind = Literal["constant", "linear", "spline", "sine", "arc"]


@dataclass(frozen=True)
class Function:
    """A scalar function of one coordinate value ``x``.

    kinds and parameters:
      * ``constant``: ``value``.
      * ``linear``: ``slope * x + intercept``.
      * ``spline``: cubic spline through knots ``x`` / ``y`` with Forsythe-Malcolm-Moler end conditions
        (OpenSim SimmSpline; see :func:`~bodyfit.models.skeleton.functions.fmm_spline_second_derivatives`).
      * ``sine``: ``amplitude * sin(omega * x + phase) + offset`` (OpenSim Sine).
      * ``arc``: ``a * (sin x - (1 - cos x) / x) + b * (sin x / x - cos x)``: the offset of the base of a
        constant-curvature segment of length ``a`` or ``b`` bent by ``x`` (see :mod:`.build`).
    """

    kind: FunctionKind
    params: dict[str, Any]

    def to_json(self) -> dict[str, Any]:
        return {"kind": self.kind, **self.params}

    @staticmethod
    def from_json(d: dict[str, Any]) -> Function:
        d = dict(d)
        kind = d.pop("kind")
        return Function(kind, d)


def is_identity(fn: Function) -> bool:
    """True for the function that *is* its coordinate (LinearFunction slope 1, intercept 0)."""
    return fn.kind == "linear" and fn.params["slope"] == 1.0 and fn.params["intercept"] == 0.0


def translation_scale_weights(axis: tuple[float, float, float], fn: Function) -> tuple[float, float, float]:
    """How a translation function along ``axis`` scales with its segment's (x, y, z) scale factors s.

    The function is multiplied by ``w . s`` with ``w = |axis| / sum |axis|``. For the axis-aligned
    translation axes of Rajagopal2015 this is exactly OpenSim's rule (``sum_j |axis_j| s_j``); the
    normalisation keeps unit scale factors a no-op for oblique axes too. A translation that is itself a
    coordinate is never scaled (w = 0), as in OpenSim.
    """
    if is_identity(fn):
        return (0.0, 0.0, 0.0)
    a = [abs(v) for v in axis]
    total = sum(a)
    return (a[0] / total, a[1] / total, a[2] / total)


@dataclass(frozen=True)
class TransformAxis:
    """One of the six axes of a joint's spatial transform."""

    axis: tuple[float, float, float]
    coordinate: str | None
    function: Function

    def to_json(self) -> dict[str, Any]:
        return {"axis": list(self.axis), "coordinate": self.coordinate, "function": self.function.to_json()}

    @staticmethod
    def from_json(d: dict[str, Any]) -> TransformAxis:
        return TransformAxis(tuple(d["axis"]), d["coordinate"], Function.from_json(d["function"]))


Vec3 = tuple[float, float, float]
X_AXIS: Vec3 = (1.0, 0.0, 0.0)
Y_AXIS: Vec3 = (0.0, 1.0, 0.0)
Z_AXIS: Vec3 = (0.0, 0.0, 1.0)


def fixed_axis(axis: Vec3) -> TransformAxis:
    """A transform axis that does not move (constant 0)."""
    return TransformAxis(axis, None, Function("constant", {"value": 0.0}))


def coordinate_axis(axis: Vec3, coordinate: str) -> TransformAxis:
    """A transform axis whose value is the coordinate itself."""
    return TransformAxis(axis, coordinate, Function("linear", {"slope": 1.0, "intercept": 0.0}))


@dataclass(frozen=True)
class Offset:
    """A frame fixed on a body: translation (m) and XYZ body-fixed Euler orientation (rad)."""

    translation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    orientation: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class Joint:
    """A joint between ``parent`` (a body name, or ``ground``) and ``child``.

    ``rotations`` and ``translations`` hold three :class:`TransformAxis` each. Translation functions
    are scaled by the scale factors of ``scale_segment`` (OpenSim scales them with the parent body).
    ``kind`` records what the joint is anatomically (``custom``, ``pin``, ``universal``, ``walker_knee``,
    ``spine_arc``, ``scapulothoracic``...), for documentation and export.
    """

    name: str
    kind: str
    parent: str
    child: str
    parent_offset: Offset
    child_offset: Offset
    rotations: tuple[TransformAxis, TransformAxis, TransformAxis]
    translations: tuple[TransformAxis, TransformAxis, TransformAxis]
    scale_segment: str


@dataclass(frozen=True)
class Body:
    """A rigid body. ``segment`` names the scale segment it belongs to (itself for anatomical bodies;
    the owning segment for massless sub-segment links). Inertia: (xx, yy, zz, xy, xz, yz) about the
    centre of mass, in the body frame. ``geometry`` lists bone mesh files (Rajagopal2015 names)."""

    name: str
    segment: str
    mass: float
    mass_center: tuple[float, float, float]
    inertia: tuple[float, float, float, float, float, float]
    geometry: tuple[str, ...] = ()
    geometry_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    is_link: bool = False


@dataclass(frozen=True)
class Coordinate:
    """A named generalized coordinate (DOF). ``rajagopal``: it exists in Rajagopal2015 with this name
    and meaning. ``range_source`` says where the range comes from."""

    name: str
    joint: str
    motion: Literal["rotational", "translational"]
    range: tuple[float, float]
    range_source: str
    rajagopal: bool
    description: str = ""


@dataclass(frozen=True)
class SkeletonSpec:
    """The whole skeleton. ``joints[i]`` moves ``bodies[i]``; joints are in topological order (a body's
    parent comes before it). ``coordinates`` are the named DOFs in their canonical order;
    ``root_coordinates`` are the global translation (pelvis_tx, pelvis_ty, pelvis_tz)."""

    bodies: tuple[Body, ...]
    joints: tuple[Joint, ...]
    coordinates: tuple[Coordinate, ...]
    root_coordinates: tuple[Coordinate, ...]
    segments: tuple[str, ...]
    metadata: dict[str, Any] = field(default_factory=dict)

    # -- lookups -------------------------------------------------------------------------------------
    @property
    def dof_names(self) -> list[str]:
        return [c.name for c in self.coordinates]

    @property
    def body_names(self) -> list[str]:
        return [b.name for b in self.bodies]

    @property
    def body_segment_index(self) -> list[int]:
        """For each body, the index in ``segments`` of the scale segment it belongs to."""
        seg = {s: i for i, s in enumerate(self.segments)}
        return [seg[b.segment] for b in self.bodies]

    @property
    def body_parent_index(self) -> list[int]:
        """For each body, the index of its parent body (-1 for ground). Joint i moves body i."""
        names = self.body_names
        assert [j.child for j in self.joints] == names, "joints must be listed in body order"
        return [-1 if j.parent == "ground" else names.index(j.parent) for j in self.joints]

    def body_index(self, name: str) -> int:
        return self.body_names.index(name)

    def joint(self, name: str) -> Joint:
        for j in self.joints:
            if j.name == name:
                return j
        raise KeyError(name)

    def coordinate(self, name: str) -> Coordinate:
        for c in (*self.coordinates, *self.root_coordinates):
            if c.name == name:
                return c
        raise KeyError(name)

    # -- JSON ----------------------------------------------------------------------------------------
    def to_json(self) -> dict[str, Any]:
        def joint_json(j: Joint) -> dict[str, Any]:
            d = asdict(j)
            d["rotations"] = [a.to_json() for a in j.rotations]
            d["translations"] = [a.to_json() for a in j.translations]
            return d

        return {
            "format": "bodyfit-skeleton/1",
            "metadata": self.metadata,
            "segments": list(self.segments),
            "bodies": [asdict(b) for b in self.bodies],
            "joints": [joint_json(j) for j in self.joints],
            "coordinates": [asdict(c) for c in self.coordinates],
            "root_coordinates": [asdict(c) for c in self.root_coordinates],
        }

    @staticmethod
    def from_json(d: dict[str, Any]) -> SkeletonSpec:
        if d.get("format") != "bodyfit-skeleton/1":
            raise ValueError(f"not a bodyfit skeleton file (format={d.get('format')!r})")

        def tup(x: Any) -> Any:
            return tuple(x) if isinstance(x, list) else x

        def offset(o: dict[str, Any]) -> Offset:
            return Offset(tup(o["translation"]), tup(o["orientation"]))

        bodies = tuple(Body(**{k: tup(v) for k, v in b.items()}) for b in d["bodies"])
        joints = tuple(
            Joint(
                name=j["name"],
                kind=j["kind"],
                parent=j["parent"],
                child=j["child"],
                parent_offset=offset(j["parent_offset"]),
                child_offset=offset(j["child_offset"]),
                rotations=tuple(TransformAxis.from_json(a) for a in j["rotations"]),  # type: ignore[arg-type]
                translations=tuple(TransformAxis.from_json(a) for a in j["translations"]),  # type: ignore[arg-type]
                scale_segment=j["scale_segment"],
            )
            for j in d["joints"]
        )
        coords = tuple(Coordinate(**{k: tup(v) for k, v in c.items()}) for c in d["coordinates"])
        roots = tuple(Coordinate(**{k: tup(v) for k, v in c.items()}) for c in d["root_coordinates"])
        return SkeletonSpec(bodies, joints, coords, roots, tuple(d["segments"]), d.get("metadata", {}))

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_json(), indent=1) + "\n")

    @staticmethod
    def load(path: str | Path) -> SkeletonSpec:
        return SkeletonSpec.from_json(json.loads(Path(path).read_text()))

"""Read Rajagopal2015.osim (shipped inside the nimblephysics wheel) into a :class:`SkeletonSpec`.

The model of A. Rajagopal, C. L. Dembia, M. S. DeMers, D. D. Delp, J. L. Hicks and S. L. Delp, "Full-Body
Musculoskeletal Model for Muscle-Driven Simulation of Human Gait", IEEE Transactions on Biomedical Engineering
63(10), 2016.

Build time only. The file is in OpenSim 3 format; OpenSim 4.6 (the ``build`` extra) upgrades it to the
4.0 document layout, which is then read with ElementTree. nimblephysics itself is never imported.
"""

from __future__ import annotations

import importlib.util
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path

from bodyfit.models.errors import AssetError
from bodyfit.models.skeleton.spec import (
    X_AXIS,
    Y_AXIS,
    Z_AXIS,
    Body,
    Coordinate,
    Function,
    Joint,
    Offset,
    TransformAxis,
    coordinate_axis,
    fixed_axis,
)

RAJAGOPAL_RELPATH = Path("models/rajagopal_data/Rajagopal2015.osim")
ROOT_TRANSLATIONS = ("pelvis_tx", "pelvis_ty", "pelvis_tz")


def nimblephysics_data_dir() -> Path:
    """Folder of Rajagopal2015 data inside the installed nimblephysics package (not imported)."""
    spec = importlib.util.find_spec("nimblephysics")
    if spec is None or not spec.submodule_search_locations:
        raise AssetError(
            "the nimblephysics package is not installed; it carries Rajagopal2015.osim. "
            "Install the build extra: pip install 'bodyfit[build]'"
        )
    return Path(next(iter(spec.submodule_search_locations))) / RAJAGOPAL_RELPATH.parent


def rajagopal_osim_path() -> Path:
    path = nimblephysics_data_dir() / RAJAGOPAL_RELPATH.name
    if not path.is_file():
        raise AssetError(f"Rajagopal2015.osim not found at {path}; reinstall nimblephysics")
    return path


def upgraded_document(path: Path) -> ET.Element:
    """The model as an OpenSim 4.0 XML document (upgraded by OpenSim itself)."""
    try:
        import opensim
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise AssetError("building the skeleton needs opensim 4.6: pip install 'bodyfit[build]'") from exc
    model = opensim.Model(str(path))
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "model40.osim"
        model.printToXML(str(out))
        return ET.parse(out).getroot()


def _vec(text: str | None) -> tuple[float, ...]:
    return tuple(float(v) for v in (text or "").split())


def _function(el: ET.Element) -> Function:
    tag = el.tag
    if tag == "Constant":
        return Function("constant", {"value": float(el.findtext("value", "0"))})
    if tag == "LinearFunction":
        slope, intercept = _vec(el.findtext("coefficients"))
        return Function("linear", {"slope": slope, "intercept": intercept})
    if tag == "SimmSpline":
        return Function("spline", {"x": list(_vec(el.findtext("x"))), "y": list(_vec(el.findtext("y")))})
    raise AssetError(f"unsupported OpenSim function {tag}")


def _axis(el: ET.Element, coupled: dict[str, str]) -> TransformAxis:
    names = (el.findtext("coordinates") or "").split()
    if len(names) > 1:
        raise AssetError("transform axes driven by several coordinates are not supported")
    coord = coupled.get(names[0], names[0]) if names else None
    fn_el = next(c for c in el if c.tag not in ("coordinates", "axis"))
    fn = _function(fn_el)
    if coord is None and fn.kind != "constant":
        fn = Function("constant", {"value": 0.0})
    return TransformAxis(tuple(_vec(el.findtext("axis"))), coord, fn)  # type: ignore[arg-type]


def _joint_frame(joint: ET.Element, socket: str) -> tuple[str, Offset]:
    """(body name, offset) of the joint's frame named by ``socket``."""
    frames = {f.get("name"): f for f in joint.iter("PhysicalOffsetFrame")}
    f = frames[joint.findtext(socket)]
    body = (f.findtext("socket_parent") or "").split("/")[-1]
    t, o = _vec(f.findtext("translation")), _vec(f.findtext("orientation"))
    return body, Offset((t[0], t[1], t[2]), (o[0], o[1], o[2]))


def _identity_couplers(model: ET.Element) -> dict[str, str]:
    """Dependent -> independent coordinate name of every CoordinateCouplerConstraint (identity only)."""
    coupled: dict[str, str] = {}
    for c in model.iter("CoordinateCouplerConstraint"):
        fn = c.find("coupled_coordinates_function")
        lin = fn.find("LinearFunction") if fn is not None else None
        if lin is None or _vec(lin.findtext("coefficients")) != (1.0, 0.0):
            raise AssetError("only identity coordinate couplers are supported")
        coupled[c.findtext("dependent_coordinate_name", "")] = c.findtext("independent_coordinate_names", "")
    return coupled


def _bodies(model: ET.Element) -> dict[str, Body]:
    """Body name -> Body of the model's BodySet, each its own segment."""
    bodies: dict[str, Body] = {}
    for b in model.find("BodySet/objects") or []:
        meshes = tuple(m.findtext("mesh_file", "") for m in b.iter("Mesh"))
        bodies[b.get("name", "")] = Body(
            name=b.get("name", ""),
            segment=b.get("name", ""),
            mass=float(b.findtext("mass", "0")),
            mass_center=_vec(b.findtext("mass_center")),  # type: ignore[arg-type]
            inertia=_vec(b.findtext("inertia")),  # type: ignore[arg-type]
            geometry=meshes,
        )
    return bodies


_Axes = tuple[TransformAxis, ...]


def _joint_axes(j: ET.Element, coupled: dict[str, str]) -> tuple[_Axes, _Axes, str]:
    """(rotation axes, translation axes, joint kind) of a joint element, by its OpenSim joint type."""
    names = [c.get("name", "") for c in j.iter("Coordinate")]
    kind = j.tag
    if kind == "CustomJoint":
        axes = [_axis(a, coupled) for a in j.iter("TransformAxis")]
        jkind = "walker_knee" if j.get("name", "").startswith("walker_knee") else "custom"
        return tuple(axes[:3]), tuple(axes[3:]), jkind
    fixed_translations = (fixed_axis(X_AXIS), fixed_axis(Y_AXIS), fixed_axis(Z_AXIS))
    if kind == "PinJoint":
        rot = (coordinate_axis(Z_AXIS, names[0]), fixed_axis(X_AXIS), fixed_axis(Y_AXIS))
        return rot, fixed_translations, "pin"
    if kind == "UniversalJoint":
        rot = (coordinate_axis(X_AXIS, names[0]), coordinate_axis(Y_AXIS, names[1]), fixed_axis(Z_AXIS))
        return rot, fixed_translations, "universal"
    if kind == "WeldJoint":
        rot = (fixed_axis(X_AXIS), fixed_axis(Y_AXIS), fixed_axis(Z_AXIS))
        return rot, rot, "weld"
    raise AssetError(f"unsupported joint type {kind} ({j.get('name')})")


def _joint(j: ET.Element, coupled: dict[str, str]) -> Joint:
    """The Joint of a joint element, scaled with its parent."""
    parent, p_off = _joint_frame(j, "socket_parent_frame")
    child, c_off = _joint_frame(j, "socket_child_frame")
    rot, trans, jkind = _joint_axes(j, coupled)
    if j.get("name", "").startswith("patellofemoral"):
        jkind = "patellofemoral"
    return Joint(j.get("name", ""), jkind, parent, child, p_off, c_off, rot, trans, parent)  # type: ignore[arg-type]


def _joint_coordinates(j: ET.Element, coupled: dict[str, str]) -> list[Coordinate]:
    """The independent coordinates a joint element declares (coupled ones left out)."""
    coords: list[Coordinate] = []
    for c in j.iter("Coordinate"):
        name = c.get("name", "")
        if name in coupled:
            continue
        lo, hi = _vec(c.findtext("range"))
        motion = "translational" if name in ROOT_TRANSLATIONS else "rotational"
        coords.append(
            Coordinate(name, j.get("name", ""), motion, (lo, hi), "Rajagopal2015.osim", True)  # type: ignore[arg-type]
        )
    return coords


def _topological_order(joints: list[Joint]) -> list[Joint]:
    """The joints with parents before children (the ground first); AssetError if they are not a tree."""
    ordered: list[Joint] = []
    placed = {"ground"}
    pending = list(joints)
    while pending:
        ready = [jt for jt in pending if jt.parent in placed]
        if not ready:
            raise AssetError("the joint graph is not a tree rooted at ground")
        for jt in ready:
            ordered.append(jt)
            placed.add(jt.child)
            pending.remove(jt)
    return ordered


def parse_model(doc: ET.Element) -> tuple[list[Body], list[Joint], list[Coordinate]]:
    """Bodies, joints (topological order) and coordinates of an OpenSim 4 document.

    Coordinates made dependent by a CoordinateCouplerConstraint with the identity function (the
    patellofemoral ``knee_angle_*_beta``) are replaced by their independent coordinate.
    """
    model = doc.find("Model")
    assert model is not None
    coupled = _identity_couplers(model)
    bodies = _bodies(model)
    joints: list[Joint] = []
    coords: list[Coordinate] = []
    for j in model.find("JointSet/objects") or []:
        joints.append(_joint(j, coupled))
        coords += _joint_coordinates(j, coupled)
    ordered = _topological_order(joints)
    body_list = [bodies[j.child] for j in ordered]
    return body_list, ordered, coords

"""Export the skeleton to OpenSim: a scaled ``.osim`` model and ``.mot`` coordinate files.

OpenSim: S. L. Delp et al., "OpenSim: Open-Source Software to Create and Analyze Dynamic Simulations of
Movement", IEEE Transactions on Biomedical Engineering 54(11), 2007; A. Seth et al., "OpenSim: Simulating
musculoskeletal dynamics and neuromuscular control to study human and animal movement", PLoS Computational
Biology 14(7), 2018.

Serving-time code: plain XML, no opensim import. Every joint is written as an OpenSim ``CustomJoint``
(Rajagopal's pin and universal joints are CustomJoints with one or two rotation axes), so the model uses
only OpenSim-native components: spine arcs and scapula paths become sub-joints through light link bodies
with SimmSpline / Sine functions, and the patella keeps Rajagopal's coupled ``knee_angle_*_beta``
coordinate with a CoordinateCouplerConstraint. Scaling is baked in: offsets, translation functions, mass
and inertia of the written model are those of the scaled skeleton, so OpenSim needs no ScaleTool step.
:func:`write_osim` also writes the bones beside the model (``Geometry/<body>_bones.obj``, from the shipped
bone mesh), so OpenSim finds every mesh the model names and shows the skeleton without other files.
"""

from __future__ import annotations

import io
import math
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from bodyfit.models.skeleton.bones import BoneMesh
from bodyfit.models.skeleton.functions import evaluate_function
from bodyfit.models.skeleton.spec import (
    Body,
    Function,
    Joint,
    SkeletonSpec,
    is_identity,
    translation_scale_weights,
)

ARC_KNOTS = 61  # SimmSpline samples of an arc function over its coordinate range (error < 1e-8 m)
LINK_MASS = 1e-4  # kg; OpenSim needs a little mass on the sub-segment links
LINK_INERTIA = 1e-7
AXIS_NAMES = ("rotation1", "rotation2", "rotation3", "translation1", "translation2", "translation3")
GEOMETRY_DIR = "Geometry"  # beside the .osim: one of the folders OpenSim searches for mesh files


def _fmt(values: Sequence[float] | np.ndarray) -> str:
    return " ".join(repr(float(v)) for v in values)


def _sub(parent: ET.Element, tag: str, text: str | None = None, **attrs: str) -> ET.Element:
    el = ET.SubElement(parent, tag, attrs)
    if text is not None:
        el.text = text
    return el


def _function_xml(parent: ET.Element, fn: Function, k: float, coord_range: tuple[float, float]) -> None:
    """Write ``fn`` multiplied by ``k`` (a translation scale; 1 for rotations)."""
    p = fn.params
    if fn.kind == "constant":
        _sub(_sub(parent, "Constant", name="function"), "value", repr(k * p["value"]))
    elif fn.kind == "linear":
        el = _sub(parent, "LinearFunction", name="function")
        _sub(el, "coefficients", _fmt([k * p["slope"], k * p["intercept"]]))
    elif fn.kind == "spline":
        el = _sub(parent, "SimmSpline", name="function")
        _sub(el, "x", _fmt(p["x"]))
        _sub(el, "y", _fmt(np.asarray(p["y"]) * k))
    elif fn.kind == "sine":
        el = _sub(parent, "Sine", name="function")
        _sub(el, "amplitude", repr(k * p["amplitude"]))
        _sub(el, "omega", repr(p["omega"]))
        _sub(el, "phase", repr(p["phase"]))
        _sub(el, "offset", repr(k * p["offset"]))
    elif fn.kind == "arc":
        lo, hi = coord_range
        pad = 0.05 * (hi - lo)
        x = np.linspace(lo - pad, hi + pad, ARC_KNOTS)
        el = _sub(parent, "SimmSpline", name="function")
        _sub(el, "x", _fmt(x))
        _sub(el, "y", _fmt(k * evaluate_function(fn, x)))
    else:  # pragma: no cover - the spec only holds the kinds above
        raise ValueError(f"cannot export function kind {fn.kind}")


def _offset_frame(
    parent: ET.Element, name: str, body_path: str, translation: np.ndarray, orientation: Sequence[float]
) -> None:
    f = _sub(parent, "PhysicalOffsetFrame", name=name)
    _sub(f, "socket_parent", body_path)
    _sub(f, "translation", _fmt(translation))
    _sub(f, "orientation", _fmt(orientation))


def _body_xml(parent: ET.Element, body: Body, s: np.ndarray, mesh_file: str | None) -> None:
    el = _sub(parent, "Body", name=body.name)
    volume = float(np.prod(s))
    inertia: tuple[float, ...]
    if body.is_link:
        mass, inertia = LINK_MASS, (LINK_INERTIA,) * 3 + (0.0,) * 3
    else:
        # Mass scales with volume; inertia with mass times the squared mean length scale.
        mass = body.mass * volume
        inertia = tuple(v * volume * float(np.mean(s)) ** 2 for v in body.inertia)
    _sub(el, "mass", repr(mass))
    _sub(el, "mass_center", _fmt(np.asarray(body.mass_center) * s))
    _sub(el, "inertia", _fmt(inertia))
    if body.geometry:
        comps = _sub(el, "components")
        f = _sub(comps, "PhysicalOffsetFrame", name=f"{body.name}_geometry")
        _sub(f, "socket_parent", "..")
        _sub(f, "translation", _fmt(np.asarray(body.geometry_offset) * s))
        _sub(f, "orientation", "0 0 0")
        geoms = _sub(f, "attached_geometry")
        for mesh in [mesh_file] if mesh_file else body.geometry:
            m = _sub(geoms, "Mesh", name=mesh.rsplit(".", 1)[0].rsplit("/", 1)[-1])
            _sub(m, "scale_factors", _fmt(s))
            _sub(m, "mesh_file", mesh)


Marker = tuple[str, str, Sequence[float]]  # (name, body, location in the body frame before scaling, m)


def _body_scales(spec: SkeletonSpec, scales: np.ndarray | None) -> dict[str, np.ndarray]:
    """Body name (and ``ground``) -> (3,) scale factors of its segment; ``scales`` is (n_seg, 3) or None."""
    seg = {s: i for i, s in enumerate(spec.segments)}
    S = np.ones((len(spec.segments), 3)) if scales is None else np.asarray(scales, np.float64)
    out = {b.name: S[seg[b.segment]] for b in spec.bodies}
    out["ground"] = np.ones(3)
    return out


def _model_header(doc: ET.Element, name: str) -> ET.Element:
    """The ``Model`` element under ``doc``, with credits, units and gravity."""
    model = _sub(doc, "Model", name=name)
    _sub(
        model,
        "credits",
        "bodyfit skeleton: Rajagopal2015 (Rajagopal et al. 2016) with spine and scapula joints",
    )
    _sub(model, "publications", "Rajagopal A. et al. (2016) IEEE TBME 63(10):2068-79")
    _sub(model, "length_units", "meters")
    _sub(model, "force_units", "N")
    _sub(model, "gravity", "0 -9.8066500000000005 0")
    return model


def _local_coordinates(joint: Joint, owned: set[str]) -> dict[str, str]:
    """Coordinate -> the name this joint writes it under, in order of first appearance.

    A coordinate already in ``owned`` (written by an earlier joint) gets a coupled ``<name>_beta`` twin.
    """
    local: dict[str, str] = {}
    for ax in (*joint.rotations, *joint.translations):
        if ax.coordinate and ax.coordinate not in local:
            local[ax.coordinate] = f"{ax.coordinate}_beta" if ax.coordinate in owned else ax.coordinate
    return local


def _coordinates_xml(jel: ET.Element, local: dict[str, str], ranges: dict[str, tuple[float, float]]) -> None:
    """Write the joint's ``coordinates``: one Coordinate per entry of ``local``, with its source's range."""
    coords = _sub(jel, "coordinates")
    for src, cname in local.items():
        c = _sub(coords, "Coordinate", name=cname)
        _sub(c, "default_value", "0")
        _sub(c, "range", _fmt(ranges[src]))
        _sub(c, "clamped", "true")
        _sub(c, "locked", "false")


def _joint_frames_xml(jel: ET.Element, joint: Joint, body_scale: dict[str, np.ndarray]) -> None:
    """Write the joint's parent and child offset frames, their translations scaled with their bodies."""
    frames = _sub(jel, "frames")
    parent_path = "/ground" if joint.parent == "ground" else f"/bodyset/{joint.parent}"
    _offset_frame(
        frames,
        f"{joint.parent}_offset",
        parent_path,
        np.asarray(joint.parent_offset.translation) * body_scale[joint.parent],
        joint.parent_offset.orientation,
    )
    _offset_frame(
        frames,
        f"{joint.child}_offset",
        f"/bodyset/{joint.child}",
        np.asarray(joint.child_offset.translation) * body_scale[joint.child],
        joint.child_offset.orientation,
    )


def _spatial_transform_xml(
    jel: ET.Element,
    joint: Joint,
    local: dict[str, str],
    ranges: dict[str, tuple[float, float]],
    s_f: np.ndarray,
) -> None:
    """Write the joint's six TransformAxis; translation functions are scaled by ``s_f`` (3,)."""
    st = _sub(jel, "SpatialTransform")
    for k, (axname, ax) in enumerate(zip(AXIS_NAMES, (*joint.rotations, *joint.translations))):
        ta = _sub(st, "TransformAxis", name=axname)
        _sub(ta, "coordinates", local[ax.coordinate] if ax.coordinate else "")
        _sub(ta, "axis", _fmt(ax.axis))
        factor = 1.0
        if k >= 3 and not is_identity(ax.function):
            factor = float(np.asarray(translation_scale_weights(ax.axis, ax.function)) @ s_f)
        rng = ranges.get(ax.coordinate, (-math.pi, math.pi)) if ax.coordinate else (-1.0, 1.0)
        _function_xml(ta, ax.function, factor, rng)


def _jointset_xml(
    model: ET.Element, spec: SkeletonSpec, body_scale: dict[str, np.ndarray]
) -> list[tuple[str, str]]:
    """Write the JointSet; returns the (independent, dependent) coordinate pairs that need a coupler."""
    ranges = {c.name: c.range for c in (*spec.coordinates, *spec.root_coordinates)}
    segments = set(spec.segments)
    jointset = _sub(_sub(model, "JointSet", name="jointset"), "objects")
    owned: set[str] = set()
    couplers: list[tuple[str, str]] = []
    for j in spec.joints:
        jel = _sub(jointset, "CustomJoint", name=j.name)
        _sub(jel, "socket_parent_frame", f"{j.parent}_offset")
        _sub(jel, "socket_child_frame", f"{j.child}_offset")
        local = _local_coordinates(j, owned)
        couplers += [(src, cname) for src, cname in local.items() if cname != src]
        owned.update(src for src, cname in local.items() if cname == src)
        _coordinates_xml(jel, local, ranges)
        _joint_frames_xml(jel, j, body_scale)
        s_f = body_scale[j.scale_segment] if j.scale_segment in segments else np.ones(3)
        _spatial_transform_xml(jel, j, local, ranges, s_f)
    return couplers


def _markerset_xml(
    model: ET.Element, markers: Sequence[Marker], bodies: set[str], body_scale: dict[str, np.ndarray]
) -> None:
    """Write the MarkerSet, locations scaled with their bodies; ValueError for a marker not on ``bodies``."""
    mset = _sub(_sub(model, "MarkerSet", name="markerset"), "objects")
    for marker_name, body, location in markers:
        if body not in bodies:
            raise ValueError(f"marker {marker_name!r} is on {body!r}, which is not a body of the skeleton")
        m = _sub(mset, "Marker", name=marker_name)
        _sub(m, "socket_parent_frame", f"/bodyset/{body}")
        _sub(m, "location", _fmt(np.asarray(location, np.float64) * body_scale[body]))
        _sub(m, "fixed", "false")


def _constraintset_xml(model: ET.Element, couplers: Sequence[tuple[str, str]]) -> None:
    """Write one identity CoordinateCouplerConstraint per (independent, dependent) pair."""
    cset = _sub(_sub(model, "ConstraintSet", name="constraintset"), "objects")
    for indep, dep in couplers:
        c = _sub(cset, "CoordinateCouplerConstraint", name=f"{dep}_coupler")
        _sub(c, "isEnforced", "true")
        fn = _sub(_sub(c, "coupled_coordinates_function"), "LinearFunction")
        _sub(fn, "coefficients", "1 0")
        _sub(c, "independent_coordinate_names", indep)
        _sub(c, "dependent_coordinate_name", dep)
        _sub(c, "scale_factor", "1")


def osim_document(
    spec: SkeletonSpec,
    scales: np.ndarray | None = None,
    name: str = "bodyfit",
    markers: Sequence[Marker] | None = None,
    mesh_files: dict[str, str] | None = None,
) -> ET.ElementTree:
    """The skeleton as an OpenSim 4 document.

    Args:
        spec: the skeleton.
        scales: (n_seg, 3) per-segment scale factors (``spec.segments`` order), or None for ones.
        name: the model name.
        markers: optional MarkerSet: ``(name, body, location)`` with the location in the body's frame
            before scaling (it is scaled with the body, like everything else in the written model).
        mesh_files: body name -> the one mesh file holding its bones (:func:`write_bone_geometry`); bodies
            not in it name Rajagopal's own ``.vtp`` files, which OpenSim finds only in its installation.
    """
    mesh_files = mesh_files or {}
    body_scale = _body_scales(spec, scales)
    doc = ET.Element("OpenSimDocument", Version="40000")
    model = _model_header(doc, name)
    bodyset = _sub(_sub(model, "BodySet", name="bodyset"), "objects")
    for b in spec.bodies:
        _body_xml(bodyset, b, body_scale[b.name], mesh_files.get(b.name))
    couplers = _jointset_xml(model, spec, body_scale)
    if markers:
        _markerset_xml(model, markers, {b.name for b in spec.bodies}, body_scale)
    if couplers:
        _constraintset_xml(model, couplers)
    tree = ET.ElementTree(doc)
    ET.indent(tree, space="\t")
    return tree


def write_osim(
    path: str | Path,
    spec: SkeletonSpec,
    scales: np.ndarray | None = None,
    name: str = "bodyfit",
    markers: Sequence[Marker] | None = None,
    geometry: bool = True,
    bones: BoneMesh | None = None,
) -> Path:
    """Write a scaled OpenSim model of ``spec`` (optionally with a MarkerSet; see :func:`osim_document`)
    and, with ``geometry``, its bones beside it (:func:`write_bone_geometry`, from ``bones`` or the
    shipped bone mesh), so that the folder is self-contained."""
    path = Path(path)
    mesh_files = None
    if geometry:
        mesh_files = write_bone_geometry(path.parent, spec, bones or BoneMesh.load(spec))
    osim_document(spec, scales, name, markers, mesh_files).write(path, encoding="UTF-8", xml_declaration=True)
    return path


def write_bone_geometry(folder: str | Path, spec: SkeletonSpec, bones: BoneMesh) -> dict[str, str]:
    """Write each body's bones as a Wavefront OBJ in ``folder/Geometry``: vertices in the body's geometry
    frame before scaling (the model scales them with ``scale_factors``), triangles as in the bone mesh.

    Returns:
        body name -> the file's path relative to ``folder`` (``Geometry/<body>_bones.obj``), for every body
        with bones.
    """
    out = Path(folder) / GEOMETRY_DIR
    out.mkdir(parents=True, exist_ok=True)
    files = {}
    for i, body in enumerate(spec.bodies):
        mine = np.flatnonzero(bones.vertex_body == i)
        if not body.geometry or not len(mine):
            continue
        index = np.full(len(bones.vertices), -1)
        index[mine] = np.arange(len(mine))
        faces = index[bones.faces]
        faces = faces[(faces >= 0).all(axis=1)]
        vertices = bones.vertices[mine].astype(np.float64) - np.asarray(body.geometry_offset)
        buf = io.StringIO()
        buf.write(f"# {body.name} bones (bodyfit), metres in the body's geometry frame\n")
        np.savetxt(buf, vertices, fmt="v %.7g %.7g %.7g")
        np.savetxt(buf, faces + 1, fmt="f %d %d %d")
        name = f"{body.name}_bones.obj"
        (out / name).write_text(buf.getvalue())
        files[body.name] = f"{GEOMETRY_DIR}/{name}"
    return files


def mot_columns(spec: SkeletonSpec) -> list[str]:
    """Coordinate columns of our .mot files: the named DOFs, then pelvis_tx / ty / tz."""
    return [*spec.dof_names, *(c.name for c in spec.root_coordinates)]


def write_mot(
    path: str | Path,
    spec: SkeletonSpec,
    q: np.ndarray,
    root: np.ndarray | None = None,
    times: np.ndarray | None = None,
    fps: float = 60.0,
    name: str = "bodyfit_coordinates",
) -> Path:
    """Write an OpenSim coordinates file (.mot): rotations in degrees, translations in metres.

    Args:
        q: (T, n_dof) coordinates in radians; root: (T, 3) metres or None; times: (T,) s or None (``fps``).
    """
    q = np.atleast_2d(np.asarray(q, np.float64))
    T = q.shape[0]
    root = np.zeros((T, 3)) if root is None else np.atleast_2d(np.asarray(root, np.float64))
    times = np.arange(T) / fps if times is None else np.asarray(times, np.float64)
    data = np.concatenate([times[:, None], np.degrees(q), root], axis=1)
    cols = ["time", *mot_columns(spec)]
    lines = [
        name,
        "version=1",
        f"nRows={T}",
        f"nColumns={len(cols)}",
        "inDegrees=yes",
        "endheader",
        "\t".join(cols),
    ]
    lines += ["\t".join(f"{v:.10g}" for v in row) for row in data]
    path = Path(path)
    path.write_text("\n".join(lines) + "\n")
    return path


def read_mot(path: str | Path) -> tuple[list[str], np.ndarray, bool]:
    """Read a .mot / .sto file: (column names including ``time``, (T, n_col) values, in_degrees)."""
    lines = Path(path).read_text().splitlines()
    end = next(i for i, line in enumerate(lines) if line.strip().lower() == "endheader")
    pairs = (line.partition("=") for line in lines[:end] if "=" in line)
    header = {k.strip(): v.strip() for k, _, v in pairs}
    cols = lines[end + 1].split("\t")
    data = np.array([[float(v) for v in line.split()] for line in lines[end + 2 :] if line.strip()])
    return cols, data.reshape(-1, len(cols)), header.get("inDegrees", "yes").lower() == "yes"


__all__ = ["mot_columns", "osim_document", "read_mot", "write_mot", "write_osim"]

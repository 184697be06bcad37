"""Build bodyfit's skeleton from Rajagopal2015 plus the joints SKEL adds (build time only).

Rajagopal2015: A. Rajagopal, C. L. Dembia, M. S. DeMers, D. D. Delp, J. L. Hicks and S. L. Delp, "Full-Body
Musculoskeletal Model for Muscle-Driven Simulation of Human Gait", IEEE Transactions on Biomedical Engineering
63(10), 2016. SKEL: M. Keller, K. Werling, S. Shin, S. Delp, S. Pujades, C. K. Liu and M. J. Black, "From Skin
to Skeleton: Towards Biomechanically Accurate 3D Digital Humans", ACM Transactions on Graphics 42(6) (SIGGRAPH
Asia), 2023, whose constant-curvature spine and scapula sliding on the thorax are built here as OpenSim
joints.

What is added to Rajagopal2015 (whose bodies, joints, axes and ranges are kept exactly):

* **Thoracic and cervical spine.** The torso is split: ``torso`` keeps Rajagopal's body frame and its
  ``back`` ball joint (lumbar_extension / bending / rotation keep their OpenSim meaning), ``thorax`` hangs
  from T12/L1 and ``head`` (head and neck) from C7/T1. Each is a constant-curvature segment of length L
  driven by extension (about z), bending (about x) and axial rotation (about y). The arc is built as two
  sub-joints through a massless link: extension bends the segment in the sagittal plane, then bending in
  the frontal plane, each exactly a circular arc of length L; the child frame sits at the segment's
  base, so the offset of the base is L*(g1, g2) of the bend angle (see ``arc`` in :mod:`.spec`). The
  chain is continuous: the cervical base is the tip of the thoracic arc.
* **Scapulae** slide on a thoracic ellipsoid of revolution (horizontal radius r_h, vertical radius r_v):
  abduction (protraction +) moves the scapula around the thorax's vertical axis, elevation moves it up
  the meridian while tilting it, upward rotation turns it about the outward surface normal. Two sub-joints
  (abduction; elevation + upward rotation); the humerus (Rajagopal's ``acromial`` joint, arm_flex / add /
  rot) hangs from the scapula. At zero scapula coordinates every Rajagopal body is exactly where
  Rajagopal2015 puts it.
* **Unlocked** subtalar, mtp and wrist coordinates with literature ranges.

Left and right limits are identical (checked at build time); the left side of each added joint is the
mirror image of the right.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from bodyfit.models.skeleton.rajagopal import (
    ROOT_TRANSLATIONS,
    parse_model,
    rajagopal_osim_path,
    upgraded_document,
)
from bodyfit.models.skeleton.spec import (
    X_AXIS,
    Y_AXIS,
    Z_AXIS,
    Body,
    Coordinate,
    Function,
    Joint,
    Offset,
    SkeletonSpec,
    TransformAxis,
    Vec3,
    coordinate_axis,
    fixed_axis,
)

Vec = Vec3
X, Y, Z = X_AXIS, Y_AXIS, Z_AXIS

# --- anatomy in Rajagopal's torso frame (origin at L5/S1), read off the torso bone geometry ------------
# (hat_spine.vtp: vertebral bodies; hat_ribs_scap.vtp: ribcage and scapulae; C7 marker at y = 0.435).
THORACOLUMBAR: Vec = (-0.03, 0.18, 0.0)  # T12/L1 vertebral body centre
THORACIC_LENGTH = 0.24  # T12/L1 -> C7/T1
CERVICAL_LENGTH = 0.08  # C7/T1 -> skull base (C0/C1)
SCAPULA_CONTACT_R: Vec = (-0.07, 0.33, 0.09)  # scapula on the posterior ribcage (right)
THORAX_AXIS: tuple[float, float] = (0.0, 0.0)  # (x, z) of the ribcage's vertical axis
THORAX_VERTICAL_RADIUS = 0.15

# Segment masses of P. de Leva, "Adjustments to Zatsiorsky-Seluyanov's segment inertia parameters", Journal of
# Biomechanics 29(9), 1996, as fractions of Rajagopal's head-arms-trunk "torso":
# head+neck 6.94 %, upper+middle trunk 32.29 %, lower trunk 11.17 % of body mass (sum 50.4 %).
MASS_SPLIT = {"torso": 11.17 / 50.4, "thorax": 32.29 / 50.4 - 0.02, "head": 6.94 / 50.4}
SCAPULA_MASS_FRACTION = 0.01  # of the torso mass, each side, taken from the thorax

deg = math.radians


def _rng(lo_deg: float, hi_deg: float) -> tuple[float, float]:
    return (deg(lo_deg), deg(hi_deg))


AAOS = "AAOS normative ROM (Greene & Heckman 1994)"
# name -> (range, source, description). Sides get the same range.
EXTRA_RANGES: dict[str, tuple[tuple[float, float], str, str]] = {
    "subtalar_angle": (_rng(-15, 35), f"{AAOS}: inversion 35, eversion 15 deg", "+ = inversion"),
    "mtp_angle": (_rng(-45, 70), f"{AAOS}: first MTP extension 70, flexion 45 deg", "+ = toe extension"),
    "wrist_flex": (_rng(-70, 80), f"{AAOS}: wrist flexion 80, extension 70 deg", "+ = flexion"),
    "wrist_dev": (_rng(-20, 30), f"{AAOS}: radial deviation 20, ulnar deviation 30 deg", "+ = ulnar"),
}
SPINE_RANGES = {
    "thorax_extension": (
        _rng(-30, 20),
        "White & Panjabi 1990, thoracic segmental ROM summed T1-T12 (flexion 30, extension 20 deg)",
        "+ = extension",
    ),
    "thorax_bending": (
        _rng(-25, 25),
        "White & Panjabi 1990, thoracic lateral bending",
        "+ = bend to the left",
    ),
    "thorax_rotation": (
        _rng(-30, 30),
        "White & Panjabi 1990, thoracic axial rotation",
        "+ = turn to the left",
    ),
    "neck_extension": (_rng(-45, 45), f"{AAOS}: cervical flexion 45, extension 45 deg", "+ = extension"),
    "neck_bending": (_rng(-45, 45), f"{AAOS}: cervical lateral bending 45 deg", "+ = bend to the left"),
    "neck_rotation": (_rng(-60, 60), f"{AAOS}: cervical rotation 60 deg", "+ = turn to the left"),
}
SCAPULA_RANGES = {
    "scapula_abduction": (
        _rng(-25, 35),
        "Ludewig et al. 2009 (JBJS 91:378), McClure et al. 2001 (JSES 10:269): protraction/retraction",
        "+ = protraction",
    ),
    "scapula_elevation": (
        _rng(-10, 30),
        "Ludewig et al. 2009: scapular elevation/depression",
        "+ = elevation",
    ),
    "scapula_upward_rot": (_rng(-10, 60), "Ludewig et al. 2009: upward rotation up to ~50 deg", "+ = upward"),
}


# --- small helpers --------------------------------------------------------------------------------------
def _sine(axis: Vec, coord: str, amplitude: float, phase: float, offset: float) -> TransformAxis:
    fn = Function("sine", {"amplitude": amplitude, "omega": 1.0, "phase": phase, "offset": offset})
    return TransformAxis(axis, coord, fn)


def _arc(axis: Vec, coord: str, a: float = 0.0, b: float = 0.0) -> TransformAxis:
    return TransformAxis(axis, coord, Function("arc", {"a": a, "b": b}))


def _sub(a: Vec, b: Vec) -> Vec:
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


def _unit(v: np.ndarray) -> Vec:
    v = v / np.linalg.norm(v)
    return (float(v[0]), float(v[1]), float(v[2]))


def _link(name: str, segment: str) -> Body:
    return Body(name, segment, 0.0, (0.0, 0.0, 0.0), (0.0,) * 6, is_link=True)


def mirror_side(name: str) -> str:
    """Right-side name -> left-side name (``_r`` suffix -> ``_l``)."""
    return name[:-2] + "_l" if name.endswith("_r") else name


def mirror_point(v: Vec) -> Vec:
    """Mirror a position or translation axis across the sagittal plane (z -> -z)."""
    return (v[0], v[1], -v[2])


def mirror_joint(j: Joint) -> Joint:
    """Mirror a joint across the sagittal plane (z -> -z).

    Positions and translation axes reflect; rotation axes are pseudo-vectors, so they reflect and flip;
    XYZ Euler offsets (a, b, c) become (-a, -b, c).
    """

    def rot_axis(v: Vec) -> Vec:
        return (-v[0], -v[1], v[2])

    def off(o: Offset) -> Offset:
        return Offset(mirror_point(o.translation), (-o.orientation[0], -o.orientation[1], o.orientation[2]))

    def ax(a: TransformAxis, f: Callable[[Vec], Vec]) -> TransformAxis:
        coord = mirror_side(a.coordinate) if a.coordinate else None
        return TransformAxis(f(a.axis), coord, a.function)

    r0, r1, r2 = (ax(a, rot_axis) for a in j.rotations)
    t0, t1, t2 = (ax(a, mirror_point) for a in j.translations)

    return replace(
        j,
        name=mirror_side(j.name),
        parent=mirror_side(j.parent),
        child=mirror_side(j.child),
        parent_offset=off(j.parent_offset),
        child_offset=off(j.child_offset),
        rotations=(r0, r1, r2),
        translations=(t0, t1, t2),
        scale_segment=mirror_side(j.scale_segment),
    )


# --- the added joints -----------------------------------------------------------------------------------
def spine_joints(prefix: str, parent: str, link: str, child: str, base: Vec, length: float) -> list[Joint]:
    """Constant-curvature spine segment (``prefix``_extension / _bending / _rotation) from ``base``.

    Args:
        base: the segment's base in the parent body frame.
        length: arc length L (m).
    Returns:
        two sub-joints: parent -> link (extension about z), link -> child (bending about x, rotation
        about y). The child frame is at the segment's base, axis-aligned with the parent at zero.
    """
    ext, bend, rot = f"{prefix}_extension", f"{prefix}_bending", f"{prefix}_rotation"
    # Extension e about z moves the base by L*(g1(e), g2(e), 0); bending b about x by L*(0, g2(b), -g1(b)).
    a = Joint(
        f"{prefix}_extension",
        "spine_arc",
        parent,
        link,
        Offset(base),
        Offset(),
        (coordinate_axis(Z, ext), fixed_axis(X), fixed_axis(Y)),
        (_arc(X, ext, a=length), _arc(Y, ext, b=length), fixed_axis(Z)),
        child,
    )
    b = Joint(
        prefix,
        "spine_arc",
        link,
        child,
        Offset(),
        Offset(),
        (coordinate_axis(X, bend), coordinate_axis(Y, rot), fixed_axis(Z)),
        (fixed_axis(X), _arc(Y, bend, b=length), _arc(Z, bend, a=-length)),
        child,
    )
    return [a, b]


def scapula_joints_right(thorax_base: Vec, contact: Vec) -> list[Joint]:
    """Right scapulothoracic sub-joints; ``contact`` is the scapula's rest point (torso frame)."""
    centre = np.array([THORAX_AXIS[0], contact[1], THORAX_AXIS[1]])
    radial = np.array(contact) - centre
    r_h = float(np.linalg.norm(radial))
    phi0 = math.atan2(-radial[2], radial[0])  # Ry(phi0) @ x = radial direction
    n = np.array(_unit(radial))
    tangent = _unit(np.cross(n, np.array(Y)))  # elevation turns the normal towards +y
    a = Joint(
        "scapulothoracic_abduction_r",
        "scapulothoracic",
        "thorax",
        "scapulothoracic_link_r",
        Offset(_sub(contact, thorax_base)),
        Offset(),
        (coordinate_axis(Y, "scapula_abduction_r"), fixed_axis(X), fixed_axis(Z)),
        (
            # r_h * (cos(phi0 + a) - cos(phi0)) along x, -r_h * (sin(phi0 + a) - sin(phi0)) along z
            _sine(X, "scapula_abduction_r", r_h, phi0 + math.pi / 2, -r_h * math.cos(phi0)),
            fixed_axis(Y),
            _sine(Z, "scapula_abduction_r", -r_h, phi0, r_h * math.sin(phi0)),
        ),
        "thorax",
    )
    nv: Vec = (float(n[0]), float(n[1]), float(n[2]))
    b = Joint(
        "scapulothoracic_r",
        "scapulothoracic",
        "scapulothoracic_link_r",
        "scapula_r",
        Offset(),
        Offset(),
        (
            coordinate_axis(tangent, "scapula_elevation_r"),
            coordinate_axis(nv, "scapula_upward_rot_r"),
            fixed_axis(_unit(np.cross(tangent, n))),
        ),
        (
            _sine(nv, "scapula_elevation_r", r_h, math.pi / 2, -r_h),  # r_h (cos e - 1) along the normal
            _sine(Y, "scapula_elevation_r", THORAX_VERTICAL_RADIUS, 0.0, 0.0),  # r_v sin e upwards
            fixed_axis(tangent),
        ),
        "thorax",
    )
    return [a, b]


def _split_mass(
    torso: Body, name: str, fraction: float, com: Vec, geometry: tuple[str, ...], origin: Vec
) -> Body:
    inertia = tuple(v * fraction for v in torso.inertia)
    offset = (-origin[0], -origin[1], -origin[2])
    return Body(name, name, torso.mass * fraction, com, inertia, geometry, offset)  # type: ignore[arg-type]


def _added_bodies(torso: Body) -> dict[str, Body]:
    """Name -> Body of the bodies added to Rajagopal's: the split torso, spine links and both scapulae."""
    cervical_base: Vec = (THORACOLUMBAR[0], THORACOLUMBAR[1] + THORACIC_LENGTH, THORACOLUMBAR[2])
    new_bodies = {
        "torso": _split_mass(
            torso, "torso", MASS_SPLIT["torso"], (-0.04, 0.09, 0.0), ("hat_spine.vtp",), (0, 0, 0)
        ),
        "thorax": _split_mass(
            torso, "thorax", MASS_SPLIT["thorax"], (0.03, 0.1, 0.0), ("hat_ribs_scap.vtp",), THORACOLUMBAR
        ),
        "head": _split_mass(
            torso,
            "head",
            MASS_SPLIT["head"],
            (0.05, 0.12, 0.0),
            ("hat_skull.vtp", "hat_jaw.vtp"),
            cervical_base,
        ),
        "thoracic_link": _link("thoracic_link", "thorax"),
        "cervical_link": _link("cervical_link", "head"),
        "scapulothoracic_link_r": _link("scapulothoracic_link_r", "thorax"),
        "scapula_r": Body(
            "scapula_r",
            "scapula_r",
            torso.mass * SCAPULA_MASS_FRACTION,
            (0.03, 0.0, 0.03),
            (0.001,) * 3 + (0.0,) * 3,
        ),
    }
    for name in ("scapulothoracic_link_r", "scapula_r"):
        b = new_bodies[name]
        new_bodies[mirror_side(name)] = replace(
            b,
            name=mirror_side(name),
            segment=mirror_side(b.segment),
            mass_center=(*b.mass_center[:2], -b.mass_center[2]),
        )
    return new_bodies


def _added_joints() -> list[Joint]:
    """The joints added to Rajagopal's: thoracic and cervical spine, then both scapulothoracic chains."""
    added = spine_joints("thorax", "torso", "thoracic_link", "thorax", THORACOLUMBAR, THORACIC_LENGTH)
    added += spine_joints(
        "neck", "thorax", "cervical_link", "head", (0.0, THORACIC_LENGTH, 0.0), CERVICAL_LENGTH
    )
    scap_r = scapula_joints_right(THORACOLUMBAR, SCAPULA_CONTACT_R)
    added += scap_r + [mirror_joint(j) for j in scap_r]
    return added


def _arms_on_scapulae(joints: list[Joint]) -> list[Joint]:
    """Rajagopal's joints with each ``acromial_*`` joint re-hung from (and scaled with) its scapula."""
    out: list[Joint] = []
    for j in joints:
        if j.name.startswith("acromial_"):
            side = j.name[-1]
            contact = SCAPULA_CONTACT_R if side == "r" else mirror_point(SCAPULA_CONTACT_R)
            j = replace(
                j,
                parent=f"scapula_{side}",
                parent_offset=Offset(_sub(j.parent_offset.translation, contact), j.parent_offset.orientation),
                scale_segment=f"scapula_{side}",
            )
        out.append(j)
    return out


def _coordinate_owners(added: list[Joint]) -> dict[str, str]:
    """Added coordinate -> the sub-joint whose axes it drives first."""
    owner: dict[str, str] = {}
    for jt in added:
        for a in (*jt.rotations, *jt.translations):
            if a.coordinate:
                owner.setdefault(a.coordinate, jt.name)
    return owner


def _named_coordinates(coords: list[Coordinate], owner: dict[str, str]) -> list[Coordinate]:
    """Rajagopal's coordinates but the root translations (unlocked ranges applied), with the scapula
    coordinates inserted before each arm_flex and the spine ones after lumbar_rotation."""
    named: list[Coordinate] = []
    for c in coords:
        if c.name in ROOT_TRANSLATIONS:
            continue
        base = c.name[:-2] if c.name[-2:] in ("_r", "_l") else c.name
        if c.name.startswith("arm_flex"):
            side = c.name[-1]
            for stem, (rng, src, desc) in SCAPULA_RANGES.items():
                name = f"{stem}_{side}"
                named.append(Coordinate(name, owner[name], "rotational", rng, src, False, desc))
        if base in EXTRA_RANGES:
            rng, src, desc = EXTRA_RANGES[base]
            c = replace(c, range=rng, range_source=f"unlocked; {src}", description=desc)
        named.append(c)
        if c.name == "lumbar_rotation":
            for name, (rng, src, desc) in SPINE_RANGES.items():
                named.append(Coordinate(name, owner[name], "rotational", rng, src, False, desc))
    return named


def build_skeleton() -> SkeletonSpec:
    """The bodyfit skeleton: Rajagopal2015 plus spine, scapulae and unlocked coordinates."""
    path = rajagopal_osim_path()
    bodies, joints, coords = parse_model(upgraded_document(path))
    body = {b.name: b for b in bodies}
    body.update(_added_bodies(body["torso"]))
    added = _added_joints()
    ordered = _depth_first(_arms_on_scapulae(joints) + added)

    # Coordinates: Rajagopal's (with the unlocked ranges), then the added ones after lumbar / before arms.
    named = _named_coordinates(coords, _coordinate_owners(added))
    roots = tuple(next(c for c in coords if c.name == n) for n in ROOT_TRANSLATIONS)

    bodies_out = tuple(body[j.child] for j in ordered)
    segments = tuple(b.name for b in bodies_out if not b.is_link)
    spec = SkeletonSpec(
        bodies_out,
        tuple(ordered),
        tuple(named),
        roots,
        segments,
        {
            "name": "bodyfit skeleton",
            "source": "Rajagopal2015.osim (nimblephysics wheel) + bodyfit spine and scapula joints",
            "thoracic_length_m": THORACIC_LENGTH,
            "cervical_length_m": CERVICAL_LENGTH,
        },
    )
    check_symmetric(spec)
    return spec


def _depth_first(joints: list[Joint]) -> list[Joint]:
    """Joints in depth-first order from the ground, children in the order given."""
    children: dict[str, list[Joint]] = {}
    for j in joints:
        children.setdefault(j.parent, []).append(j)
    out: list[Joint] = []

    def visit(body: str) -> None:
        for j in children.get(body, []):
            out.append(j)
            visit(j.child)

    visit("ground")
    if len(out) != len(joints):
        raise ValueError("joints do not form a tree rooted at the ground")
    return out


def check_symmetric(spec: SkeletonSpec) -> None:
    """Raise if any right-side coordinate's range differs from its left twin's."""
    by_name = {c.name: c for c in spec.coordinates}
    for c in spec.coordinates:
        if c.name.endswith("_r"):
            twin = by_name[mirror_side(c.name)]
            if not np.allclose(c.range, twin.range):
                raise ValueError(f"{c.name} range {c.range} differs from {twin.name} {twin.range}")

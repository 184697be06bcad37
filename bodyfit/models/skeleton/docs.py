"""docs/skeleton.md generated from the skeleton asset: one row per DOF."""

from __future__ import annotations

import math

from bodyfit.models.skeleton.spec import SkeletonSpec


def _axis_text(v: tuple[float, float, float]) -> str:
    names = {(1.0, 0.0, 0.0): "+x", (-1.0, 0.0, 0.0): "-x", (0.0, 1.0, 0.0): "+y", (0.0, -1.0, 0.0): "-y"}
    names.update({(0.0, 0.0, 1.0): "+z", (0.0, 0.0, -1.0): "-z"})
    key = (float(round(v[0], 12)), float(round(v[1], 12)), float(round(v[2], 12)))
    return names.get(key, "(" + ", ".join(f"{c:.3f}" for c in v) + ")")


def skeleton_markdown(spec: SkeletonSpec) -> str:
    """Markdown table of the skeleton's DOFs (name, body, joint type, axis, range, source)."""
    rows = []
    for c in spec.coordinates:
        joint = spec.joint(c.joint)
        axis = "-"
        for kind, axes in (("rot", joint.rotations), ("trans", joint.translations)):
            for a in axes:
                if a.coordinate == c.name and a.function.kind == "linear":
                    axis = f"{kind} {_axis_text(a.axis)}"
        lo, hi = (math.degrees(v) for v in c.range)
        origin = "Rajagopal2015" if c.rajagopal else "bodyfit"
        rows.append(
            f"| `{c.name}` | {joint.child} | {joint.kind} (`{joint.name}`) | {axis} | {lo:.1f} .. {hi:.1f} | "
            f"{origin} | {c.range_source} | {c.description} |"
        )
    n_body = sum(1 for b in spec.bodies if not b.is_link)
    header = [
        "# Skeleton",
        "",
        "Generated from `assets/skeleton.json` by `bodyfit build-assets`; do not edit by hand.",
        "",
        f"{len(spec.coordinates)} named DOFs plus root translation "
        f"({', '.join(c.name for c in spec.root_coordinates)}, metres); {n_body} bodies "
        f"({len(spec.bodies) - n_body} massless sub-segment links); {len(spec.segments)} scale segments.",
        "",
        "Frames follow OpenSim: +Y up, +X forward, +Z right. Axes are given in the joint's parent frame "
        "(after the parent offset's orientation), as in the .osim file. Rajagopal2015 DOFs keep OpenSim's "
        "name, axis, range and meaning; `q = 0` is OpenSim's neutral pose. The knee's coupled translations "
        "and rotations (Walker et al. 1988) and the patella follow `knee_angle_*` through splines.",
        "",
        "| DOF | moves body | joint | axis | range (deg) | origin | range source | sign |",
        "|---|---|---|---|---|---|---|---|",
    ]
    notes = [
        "",
        "## Joints added to Rajagopal2015",
        "",
        "- **Spine.** `torso` keeps Rajagopal's frame and `back` ball joint at L5/S1 (lumbar DOFs, OpenSim "
        "meaning). `thorax` hangs from T12/L1 and `head` (head and neck) from C7/T1, each on a "
        "constant-curvature segment (arc length "
        f"{spec.metadata.get('thoracic_length_m', 0):.2f} m thoracic, "
        f"{spec.metadata.get('cervical_length_m', 0):.2f} m cervical, scaled with the segment): extension "
        "bends it in the sagittal plane, then bending in the frontal plane, each an exact circular arc; "
        "axial rotation turns the segment about its own axis. The cervical base sits at the tip of the "
        "thoracic arc, so the spine stays continuous.",
        "- **Scapulae** slide on an ellipsoid of revolution around the thorax (abduction around its vertical "
        "axis, elevation up its meridian with the matching tilt, upward rotation about the surface normal). "
        "The humerus hangs from the scapula through Rajagopal's `acromial` joint. With all added DOFs at "
        "zero every Rajagopal body sits exactly where Rajagopal2015 puts it.",
        "- **Unlocked** subtalar, mtp and wrist coordinates (locked in Rajagopal2015), literature ranges.",
        "",
        "In exported .osim files the added joints are OpenSim CustomJoints through light link bodies "
        "(`thoracic_link`, `cervical_link`, `scapulothoracic_link_*`); the patella keeps Rajagopal's coupled "
        "`knee_angle_*_beta` coordinate.",
    ]
    return "\n".join(header + rows + notes) + "\n"

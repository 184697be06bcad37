"""The tape measurements: circumferences and the breadths and depths of the same sections.

Each tape is a plane section of one of the template's section edge sets (:mod:`.regions`), through a
point and along a normal derived from the body's landmarks, joints and extreme points; its length is the
perimeter of the section's convex hull (:mod:`.sections`). Where a definition asks for the largest or the
smallest tape over a stretch of a limb (the calf, the ankle, the forearm, the head), the planes step along
the stretch and the extreme is taken.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from bodyfit.models.anthropometry.regions import Topology
from bodyfit.models.anthropometry.sections import (
    crossings,
    plane_basis,
    polygon_extent,
    polygon_perimeter,
    support_polygon,
)

# Distances below are for a body of REFERENCE_STATURE and scale with the body's stature, so that a body
# scaled by s measures s times as much. Vertical offsets (metres) of planes and extents from the landmarks
# they hang on:
THIGH_BELOW_CROTCH = 0.02
HEAD_ABOVE_EARS = 0.035
HEAD_ABOVE_NOSE = 0.04
# The neck's axis runs from the C7/T1 joint to the midpoint of the tragions (the ear canals, level with
# the skull base); the tape's plane crosses it this far along, at the level of the laryngeal prominence,
# where ANSUR II places its tape.
NECK_LEVEL = 0.45
REFERENCE_STATURE = 1.7


@dataclass
class Cutter:
    """Plane sections of one batch of bodies: vertices (B, V, 3) on ``topo``; ``scale`` (B,) each body's
    stature over :data:`REFERENCE_STATURE` (radii and offsets scale with it). With ``paths`` a dict, every
    tape's hull polygon (B, k, 3) in world coordinates is recorded there under its measurement's name."""

    topo: Topology
    v: torch.Tensor
    scale: torch.Tensor
    paths: dict[str, torch.Tensor] | None = field(default=None)

    def polygon(
        self,
        edges: str,
        origin: torch.Tensor,
        normal: torch.Tensor,
        offsets: torch.Tensor | None = None,
        radius: float | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Sections of the ``edges`` set by planes with unit ``normal`` (B, 3) through ``origin`` (B, 3)
        moved by ``offsets`` (B, L) along the normal (default one plane through the origin). Only crossings
        within ``radius`` (scaled) of each plane's origin count when it is given.

        Returns:
            the hulls' support polygons (B * L, k, 2) in plane coordinates, the planes' origins (B * L, 3)
            and axes u, w (B * L, 3).
        """
        offsets = torch.zeros(len(origin), 1, dtype=origin.dtype) if offsets is None else offsets
        B, L = offsets.shape
        vertices, local = self.topo.section_index(edges)
        points, valid = crossings(self.v[:, vertices], local, origin, normal, offsets)
        if radius is not None:
            limit = (radius * self.scale).repeat_interleave(L)[:, None]
            valid = valid & (points.norm(dim=-1) < limit)
        n = normal.repeat_interleave(L, 0)
        u, w = plane_basis(n)
        o = (origin[:, None] + offsets[..., None] * normal[:, None]).reshape(B * L, 3)
        return support_polygon(points, valid, u, w), o, u, w

    def tape(
        self, name: str, edges: str, origin: torch.Tensor, normal: torch.Tensor, radius: float | None = None
    ) -> torch.Tensor:
        """The tape length (B,) of one plane per body (see :meth:`polygon`)."""
        poly, o, u, w = self.polygon(edges, origin, normal, radius=radius)
        self._record(name, poly, o, u, w)
        return polygon_perimeter(poly)

    def extreme_tape(
        self,
        name: str,
        edges: str,
        origin: torch.Tensor,
        normal: torch.Tensor,
        offsets: torch.Tensor,
        largest: bool,
        radius: float | None = None,
    ) -> torch.Tensor:
        """The largest (or smallest) tape (B,) over planes at ``offsets`` (B, L) metres along ``normal``
        (B, 3) from ``origin`` (B, 3)."""
        B, L = offsets.shape
        poly, o, u, w = self.polygon(edges, origin, normal, offsets, radius)
        length = polygon_perimeter(poly).reshape(B, L)
        pick = length.argmax(1) if largest else length.argmin(1)
        rows = torch.arange(B) * L + pick
        self._record(name, poly[rows], o[rows], u[rows], w[rows])
        return length[torch.arange(B), pick]

    def _record(
        self, name: str, poly: torch.Tensor, origin: torch.Tensor, u: torch.Tensor, w: torch.Tensor
    ) -> None:
        if self.paths is not None:
            world = origin[:, None] + poly[..., :1] * u[:, None] + poly[..., 1:] * w[:, None]
            self.paths[name] = world.detach()


def _up(like: torch.Tensor) -> torch.Tensor:
    n = torch.zeros_like(like)
    n[:, 1] = 1.0
    return n


def _at_height(point: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """``point`` (B, 3) moved to height ``y`` (B,)."""
    return torch.stack([point[:, 0], y, point[:, 2]], -1)


def _unit(a: torch.Tensor) -> torch.Tensor:
    return a / a.norm(dim=-1, keepdim=True)


def torso_tapes(cut: Cutter, p: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Horizontal torso and hip sections: their tapes and extents (plane u is forward x, w is -z)."""
    v = cut.v
    up = _up(p["omphalion"])
    x_axis = torch.tensor([[1.0, 0.0]], dtype=v.dtype).expand(len(v), 2)
    z_axis = torch.tensor([[0.0, 1.0]], dtype=v.dtype).expand(len(v), 2)
    bust_y = 0.5 * (p["bust_r"][:, 1] + p["bust_l"][:, 1])
    crest_y = 0.5 * (p["iliac_crest_r"][:, 1] + p["iliac_crest_l"][:, 1])
    out = {}
    for name, edges, origin in (
        ("chest", "chest", _at_height(p["omphalion"], bust_y)),
        ("waist", "waist", p["omphalion"]),
        ("waistcircumferenceiliaccrest", "waist", _at_height(p["omphalion"], crest_y)),
        ("buttock", "hips", p["buttock"]),
    ):
        key = name if name.endswith("crest") else f"{name}circumference"
        poly, o, u, w = cut.polygon(edges, origin, up)
        cut._record(key, poly, o, u, w)
        out[key] = polygon_perimeter(poly)
        out[f"{name}_breadth"] = polygon_extent(poly, z_axis)
        out[f"{name}_depth"] = polygon_extent(poly, x_axis)
    return {
        "chestcircumference": out["chestcircumference"],
        "waistcircumference": out["waistcircumference"],
        "waistcircumferenceiliaccrest": out["waistcircumferenceiliaccrest"],
        "buttockcircumference": out["buttockcircumference"],
        "chestbreadth": out["chest_breadth"],
        "chestdepth": out["chest_depth"],
        "waistbreadth": out["waist_breadth"],
        "waistdepth": out["waist_depth"],
        "hipbreadth": out["buttock_breadth"],
        "buttockdepth": out["buttock_depth"],
    }


def head_tapes(cut: Cutter, p: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Head breadth and length (extents of the skin above the ears and above the nose) and the largest
    horizontal tape between 25% and 60% of the way from the ears to the top of the head."""
    v = cut.v
    head = v[:, cut.topo.candidates["head"]]
    ears = 0.5 * (p["tragion_r"][:, 1] + p["tragion_l"][:, 1])
    above_ears = head[..., 1] > (ears + HEAD_ABOVE_EARS * cut.scale)[:, None]
    above_nose = head[..., 1] > (p["pronasale"][:, 1] + HEAD_ABOVE_NOSE * cut.scale)[:, None]
    offsets = (p["top"] - ears)[:, None] * torch.linspace(0.25, 0.6, 8, dtype=v.dtype)
    centre = _at_height(0.5 * (p["tragion_r"] + p["tragion_l"]), ears)
    return {
        "headbreadth": _masked_extent(head[..., 2], above_ears),
        "headlength": _masked_extent(head[..., 0], above_nose),
        "headcircumference": cut.extreme_tape(
            "headcircumference", "head", centre, _up(centre), offsets, True
        ),
    }


def _masked_extent(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """max - min (B,) of values (B, n) where mask (B, n)."""
    inf = torch.full_like(values, torch.inf)
    return torch.where(mask, values, -inf).max(1).values - torch.where(mask, values, inf).min(1).values


def leg_tapes(cut: Cutter, p: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Thigh (horizontal, just below the crotch), calf (the largest horizontal tape 10-50% of the way from
    the knee to the ankle) and ankle (the smallest, 4-14 cm above the lateral malleolus)."""
    v = cut.v
    up = _up(p["omphalion"])
    knee, ankle = p["joint_knee_r"], p["joint_ankle_r"]
    shank = (knee[:, 1] - ankle[:, 1])[:, None]
    malleolus = _at_height(ankle, p["lateral_malleolus_r"][:, 1])
    thigh = _at_height(knee, p["crotch"] - THIGH_BELOW_CROTCH * cut.scale)
    calf_levels = -shank * torch.linspace(0.1, 0.5, 9, dtype=v.dtype)
    ankle_levels = cut.scale[:, None] * torch.linspace(0.04, 0.14, 6, dtype=v.dtype)
    return {
        "thighcircumference": cut.tape("thighcircumference", "thigh", thigh, up),
        "calfcircumference": cut.extreme_tape("calfcircumference", "shank", knee, up, calf_levels, True),
        "anklecircumference": cut.extreme_tape(
            "anklecircumference", "shank", malleolus, up, ankle_levels, False
        ),
    }


def arm_tapes(cut: Cutter, p: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Neck (across the neck's axis, see :data:`NECK_LEVEL`), upper arm (across
    the humerus, midway from acromion to elbow), forearm (the largest tape across it 10-40% of the way from
    elbow to wrist) and wrist (across the forearm at the styloids)."""
    v = cut.v
    ears = 0.5 * (p["tragion_r"] + p["tragion_l"])
    neck_axis = _unit(ears - p["joint_cervicothoracic"])
    neck_mid = p["joint_cervicothoracic"] + NECK_LEVEL * (ears - p["joint_cervicothoracic"])
    shoulder, elbow, wrist = p["joint_shoulder_r"], p["joint_elbow_r"], p["joint_wrist_r"]
    arm_axis, fore_axis = _unit(elbow - shoulder), _unit(wrist - elbow)
    fore_levels = (wrist - elbow).norm(dim=-1)[:, None] * torch.linspace(0.1, 0.4, 7, dtype=v.dtype)
    styloids = 0.5 * (p["radial_styloid_r"] + p["ulnar_styloid_r"])
    mid_arm = 0.5 * (p["acromion_r"] + elbow)
    return {
        "neckcircumference": cut.tape("neckcircumference", "neck", neck_mid, neck_axis, 0.09),
        "upperarmcircumference": cut.tape("upperarmcircumference", "upperarm", mid_arm, arm_axis, 0.12),
        "forearmcircumference": cut.extreme_tape(
            "forearmcircumference", "forearm", elbow, fore_axis, fore_levels, True, 0.1
        ),
        "wristcircumference": cut.tape("wristcircumference", "forearm", styloids, fore_axis, 0.07),
    }

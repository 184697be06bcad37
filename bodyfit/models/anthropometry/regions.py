"""Index sets on the template that the measurements are defined on, built once per body model.

Every body of the model shares the template's topology, so a set of vertices or edges picked on the
template is the same set on every body. Regions are the vertices whose largest skinning weight lies on
given skeleton bodies (the torso without the arms, the right leg, the right arm, the head); a plane
section is taken over a region's edges so that a horizontal plane at the chest does not also cut the
arms. Candidate sets hold the vertices an extreme point is searched among on each body (the lowest
point of the crotch, the most anterior point of each breast, the most posterior point of the buttocks):
the extreme itself is found per body, because it moves across the surface as the shape changes.

All positions used to pick the sets are the template's (the mean body at zero coordinates), in the
model's frame: metres, +x forward, +y up, +z the body's right.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from bodyfit.models.anthropometry.sections import mesh_edges
from bodyfit.models.body.model import BodyModel

# Skeleton bodies whose vertices make up each region (by largest skinning weight).
_TORSO = ("pelvis", "torso", "thorax", "cervical_link", "scapula_r", "scapula_l")
_REGION_BODIES: dict[str, tuple[str, ...]] = {
    "torso": _TORSO,
    "hips": (*_TORSO, "femur_r", "femur_l"),
    "leg_r": ("pelvis", "femur_r", "patella_r", "tibia_r", "talus_r", "calcn_r", "toes_r"),
    "foot_r": ("calcn_r", "toes_r"),
    "feet": ("calcn_r", "toes_r", "calcn_l", "toes_l"),
    "arm_r": ("humerus_r", "ulna_r", "radius_r", "hand_r"),
    "neck": ("head", "cervical_link", "thorax"),
    "head": ("head",),
}
# Regions that keep only the right side of the template (z > 0): the pelvis's share of the right leg.
_RIGHT_ONLY = ("leg_r",)


@dataclass(frozen=True)
class Topology:
    """The template's index sets for :func:`measure_vertices`.

    Attributes:
        landmarks: landmark name -> template vertex index (the model's bony landmarks).
        regions: region name -> (n,) vertex indices.
        edges: section name -> (E, 2) the edges its planes can cross: those with an end in the section's
            region and near the section on the template (:func:`_section_edges`).
        candidates: extreme-point name -> (n,) vertex indices searched on each body.
        faces: (F, 3) int64 tensor of the closed skin, outward winding.
        joint_names: names of the joints a body's joints array holds, in order.
        joint_regressor: (J, V) float64: joints of a mesh given without them.
    """

    landmarks: dict[str, int]
    regions: dict[str, np.ndarray]
    edges: dict[str, np.ndarray]
    candidates: dict[str, np.ndarray]
    faces: torch.Tensor
    joint_names: list[str]
    joint_regressor: np.ndarray
    _local: dict[str, tuple[torch.Tensor, torch.Tensor]] = field(
        default_factory=dict, repr=False, compare=False
    )

    def section_index(self, name: str) -> tuple[torch.Tensor, torch.Tensor]:
        """The vertices (n,) a section's edges touch and its edges (E, 2) as indices into them, as tensors:
        a plane's signed distance is then taken once per vertex, not twice per edge. Cached."""
        if name not in self._local:
            vertices, local = np.unique(self.edges[name], return_inverse=True)
            self._local[name] = (torch.as_tensor(vertices), torch.as_tensor(local.reshape(-1, 2)))
        return self._local[name]


def topology(model: BodyModel) -> Topology:
    """The model's :class:`Topology`, built on first use and kept for the model's lifetime."""
    return model.derived("anthropometry.topology", lambda: build_topology(model))


def build_topology(model: BodyModel) -> Topology:
    """Pick the regions, edges and candidate sets of ``model``'s template (see the module docstring)."""
    template = np.asarray(model.data["template"], np.float64)
    body_names = model.skeleton.spec.body_names
    dominant = model.vertex_bodies
    regions: dict[str, np.ndarray] = {}
    for name, bodies in _REGION_BODIES.items():
        keep = np.isin(dominant, [body_names.index(b) for b in bodies if b in body_names])
        if name in _RIGHT_ONLY:
            keep &= template[:, 2] > 0.0
        regions[name] = np.flatnonzero(keep)
    landmarks = {n: int(i) for n, i in zip(model.landmark_names, model.data["landmarks"])}
    centres = np.asarray(model.data["joint_regressor"], np.float64) @ template
    joints = dict(zip(model.joint_names, centres))
    candidates = _candidates(template, _midline(model), regions, landmarks, joints)
    crotch = float(template[candidates["crotch"], 1].min())
    return Topology(
        landmarks=landmarks,
        regions=regions,
        edges=_section_edges(template, mesh_edges(model.faces), regions, landmarks, joints, crotch),
        candidates=candidates,
        faces=torch.as_tensor(model.faces, dtype=torch.long),
        joint_names=list(model.joint_names),
        joint_regressor=np.asarray(model.data["joint_regressor"], np.float64),
    )


def _midline(model: BodyModel) -> np.ndarray:
    """(V,) bool: the template's vertices on the sagittal plane (their own mirror image)."""
    mirror = np.asarray(model.data["mirror"])
    return np.asarray(mirror == np.arange(len(mirror)))


# How far (metres, on the template) past the landmarks that bound a section its edge set reaches: the
# planes hang on landmarks that move with the surface, so across the shape space they cross edges within
# a few centimetres of where they cross the template's; tests check the bands against the whole surface.
_BAND = 0.08


def _section_edges(
    t: np.ndarray,
    edges: np.ndarray,
    regions: dict[str, np.ndarray],
    landmarks: dict[str, int],
    joints: dict[str, np.ndarray],
    crotch: float,
) -> dict[str, np.ndarray]:
    """Each section's edge set: edges with an end in its region and within its template band (a height
    range for the horizontal sections, a ball for the sections across the neck and arm).

    Args:
        t: (V, 3) template; edges: (E, 2) all edges; regions, landmarks: as in :class:`Topology`; joints:
            name -> (3,) template joint centres; crotch: the template's crotch height.
    """
    y = {n: t[i, 1] for n, i in landmarks.items()}
    upper_arm = 0.5 * (t[landmarks["acromion_r"]] + joints["elbow_r"])
    forearm = 0.5 * (joints["elbow_r"] + joints["wrist_r"])
    ears = 0.5 * (t[landmarks["tragion_r"]] + t[landmarks["tragion_l"]])
    neck = 0.55 * joints["cervicothoracic"] + 0.45 * ears
    fore_half = 0.5 * float(np.linalg.norm(joints["wrist_r"] - joints["elbow_r"]))
    bands: dict[str, tuple[str, tuple[float, float] | tuple[np.ndarray, float], float]] = {
        "chest": ("torso", (y["xiphoid"] - 0.1, y["suprasternale"]), _BAND),
        "waist": (
            "torso",
            (min(y["omphalion"], y["iliac_crest_r"]), max(y["omphalion"], y["iliac_crest_r"])),
            _BAND,
        ),
        "hips": ("hips", (crotch, y["iliac_crest_r"]), _BAND),
        "thigh": ("leg_r", (crotch - 0.04, crotch), _BAND),
        "shank": ("leg_r", (y["lateral_malleolus_r"], joints["knee_r"][1]), 0.03),
        "head": ("head", (y["tragion_r"] + 0.02, y["tragion_r"] + 0.08), 0.02),
        "neck": ("neck", (neck, 0.09), 0.02),
        "upperarm": ("arm_r", (upper_arm, 0.12), 0.02),
        "forearm": ("arm_r", (forearm, fore_half), 0.03),
    }
    out = {}
    for name, (region, (a, b), margin) in bands.items():
        inside = np.zeros(len(t), bool)
        inside[regions[region]] = True
        if np.ndim(a) == 0:
            inside &= (t[:, 1] > float(a) - margin) & (t[:, 1] < float(b) + margin)
        else:
            inside &= np.linalg.norm(t - a, axis=1) < float(b) + margin
        out[name] = edges[inside[edges].any(1)]
    return out


def _candidates(
    t: np.ndarray,
    midline: np.ndarray,
    regions: dict[str, np.ndarray],
    landmarks: dict[str, int],
    joints: dict[str, np.ndarray],
) -> dict[str, np.ndarray]:
    """Vertex sets whose extreme points are the crotch, bust points, buttock point, head top and soles.

    Args:
        t: (V, 3) template; midline: (V,) bool, the vertices that are their own mirror image (on the
            sagittal plane; the inner thighs of legs held together come near it, but are not on it);
            regions, landmarks: as in :class:`Topology`; joints: name -> (3,) a template
            point near each joint centre.
    """
    hips, torso = regions["hips"], regions["torso"]
    hip_y, knee_y = joints["hip_r"][1], joints["knee_r"][1]
    crotch = hips[(t[hips, 1] < hip_y) & (t[hips, 1] > knee_y) & midline[hips]]
    # The bust points lie between the xiphoid and the suprasternale levels (ISO 8559-1: bust point).
    top = t[landmarks["suprasternale"], 1] - 0.06
    bottom = t[landmarks["xiphoid"], 1]
    front = torso[
        (t[torso, 0] > t[landmarks["xiphoid"], 0] - 0.08) & (t[torso, 1] < top) & (t[torso, 1] > bottom)
    ]
    bust_r = front[(t[front, 2] > 0.03) & (t[front, 2] < 0.17)]
    bust_l = front[(t[front, 2] < -0.03) & (t[front, 2] > -0.17)]
    crest_y = t[landmarks["iliac_crest_r"], 1]
    back = hips[(t[hips, 0] < joints["hip_r"][0]) & (t[hips, 1] < crest_y) & (t[hips, 1] > knee_y + 0.2)]
    return {
        "crotch": crotch,
        "bust_r": bust_r,
        "bust_l": bust_l,
        "buttock": back,
        "head": regions["head"],
        "feet": regions["feet"],
        "foot_r": regions["foot_r"],
    }

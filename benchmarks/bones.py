"""Bones inside the skin: how much of the bone mesh lies outside the posed skin, over bodies and poses.

What is measured
----------------
* Bodies: the mean body and ``n_bodies`` shapes drawn from N(0, 1) in the model's shape space (fixed seed):
  plausible adults of the population.
* Poses, for every body: named poses (``neutral``; ``arms_raised``: full abduction with the scapulae;
  ``crouch``; ``pro_sup_min`` / ``pro_sup_max`` with the elbows at 90 degrees; ``wrist_min`` / ``wrist_max``:
  flexion and deviation at their lower / upper limits together; ``mtp_min`` / ``mtp_max``) and
  ``n_random`` poses uniform within 80% of every range about its middle, pelvis upright. Named poses are
  clipped into the ranges.
* ``bones_outside_frac``: the fraction of bone-mesh vertices (every ``stride``-th) whose generalised winding
  number with respect to the posed skin's envelope is below 0.5 (``geometry.fast_winding_number``), over all
  bodies and poses. The envelope is the skin with its oral and nasal pockets closed over their openings
  (``geometry.skin_envelope``): the teeth and palate lie in the mouth, which the skin surface lines, and are
  not outside the body. The same per region (skull, hands, forearms, arms, shoulders, ribs, spine, pelvis,
  legs, feet) and per pose. ``max_mm``: the largest distance from an outside bone vertex to the skin surface
  (exact point-to-triangle distance to the triangles around its nearest skin vertices).
* Twist diagnostic (mean body, one side): for pro_sup, wrist flexion, wrist deviation and mtp at their lower
  limit, zero and upper limit, the angle between the skin's and the bones' principal axes of the hand (palm
  normal and long axis; skin vertices weighted at least 0.9 to the hand) and of the toes (plantar normal).
  Skin and bones that mean the same by a coordinate give angles that are small and do not change with it.

Usage::

    python benchmarks/bones.py            # 12 bodies, 6 random poses each, every 2nd bone vertex
    python benchmarks/bones.py --quick    # 3 bodies, 2 random poses, every 6th vertex (about a minute)
    python benchmarks/bones.py --json     # the last line of stdout is one JSON object with the figures
    python benchmarks/bones.py --assets build/assets-candidate   # another asset folder
    python benchmarks/bones.py --quick --render build/bones.png      # also a see-through picture
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy.spatial import cKDTree

from bodyfit.models.body.geometry import fast_winding_number, skin_envelope
from bodyfit.models.body.model import BodyModel
from bodyfit.models.skeleton.model import PELVIS_ROTATIONS

# Named poses: DOF name -> degrees, both sides unless the name has one; "min" / "max" mean the limit.
NAMED_POSES: dict[str, dict[str, float | str]] = {
    "neutral": {},
    "arms_raised": {"arm_add": "min", "scapula_upward_rot": "max", "scapula_elevation": 20},
    "crouch": {"hip_flexion": 110, "knee_angle": 120, "ankle_angle": 25, "lumbar_extension": -20},
    "pro_sup_min": {"elbow_flex": 90, "pro_sup": "min"},
    "pro_sup_max": {"elbow_flex": 90, "pro_sup": "max"},
    "wrist_min": {"wrist_flex": "min", "wrist_dev": "min"},
    "wrist_max": {"wrist_flex": "max", "wrist_dev": "max"},
    "mtp_min": {"mtp_angle": "min"},
    "mtp_max": {"mtp_angle": "max"},
}

# Bone-mesh regions: region -> body names without their side.
REGIONS: dict[str, tuple[str, ...]] = {
    "skull": ("head",),
    "hands": ("hand",),
    "forearms": ("radius", "ulna"),
    "arms": ("humerus",),
    "shoulders": ("scapula",),
    "ribs": ("thorax",),
    "spine": ("torso", "cervical_link", "thoracic_link"),
    "pelvis": ("pelvis",),
    "legs": ("femur", "tibia", "patella"),
    "feet": ("talus", "calcn", "toes"),
}


@dataclass(frozen=True)
class Settings:
    """How much work one run does."""

    n_bodies: int
    n_random: int
    stride: int
    seed: int
    quick: bool


def pose_coordinates(body: BodyModel, spec: dict[str, float | str]) -> np.ndarray:
    """(n_dof,) coordinates of a named pose (:data:`NAMED_POSES`), clipped into the ranges."""
    sk = body.skeleton
    lo, hi = sk.ranges[:, 0], sk.ranges[:, 1]
    q = np.zeros(sk.n_dof)
    for name, value in spec.items():
        names = [name] if name in sk.dof_names else [f"{name}_r", f"{name}_l"]
        for n in names:
            i = sk.dof_index(n)
            q[i] = lo[i] if value == "min" else hi[i] if value == "max" else np.deg2rad(float(value))
    return np.clip(q, lo, hi)


def random_coordinates(body: BodyModel, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, n_dof) poses uniform within 80% of every range about its middle, pelvis upright."""
    lo, hi = body.skeleton.ranges[:, 0], body.skeleton.ranges[:, 1]
    q = 0.5 * (lo + hi) + 0.4 * (hi - lo) * rng.uniform(-1.0, 1.0, (n, len(lo)))
    for name in PELVIS_ROTATIONS:
        q[:, body.skeleton.dof_index(name)] = 0.0
    return q


def region_of_vertices(body: BodyModel) -> np.ndarray:
    """(V_bone,) region index (into :data:`REGIONS`) of every bone-mesh vertex."""
    names = body.skeleton.body_names
    base = [n[:-2] if n.endswith(("_r", "_l")) else n for n in names]
    region_of_body = np.full(len(names), -1)
    for r, bodies in enumerate(REGIONS.values()):
        for b, stem in enumerate(base):
            if stem in bodies:
                region_of_body[b] = r
    return region_of_body[body.skeleton.bone_mesh().vertex_body]


def skin_cavity(body: BodyModel) -> np.ndarray | None:
    """(F,) bool faces of the skin's oral and nasal pockets, when the assets carry them."""
    cavity = body.data.get("skin_cavity")
    return None if cavity is None else np.asarray(cavity, bool)


def surface_distance(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, k: int = 8) -> np.ndarray:
    """Distance (P,) from points (P, 3) to a triangle mesh: the nearest of the triangles around each point's
    ``k`` nearest vertices (exact point-to-triangle distances)."""
    import trimesh

    if len(points) == 0:
        return np.zeros(0)
    incident: list[list[int]] = [[] for _ in range(len(vertices))]
    for f, tri in enumerate(faces):
        for v in tri:
            incident[v].append(f)
    used = np.unique(faces)  # a surface may leave vertices out (the skin's envelope leaves its cavities)
    width = max(len(x) for x in incident)
    table = np.array([x + [x[0]] * (width - len(x)) for x in incident if x])  # (V_used, width), padded
    _, near = cKDTree(vertices[used]).query(points, k=k)
    cand = table[near].reshape(len(points), -1)  # (P, k * width)
    tris = vertices[faces[cand.ravel()]]
    closest = trimesh.triangles.closest_point(tris, np.repeat(points, cand.shape[1], axis=0))
    dist = np.linalg.norm(closest - np.repeat(points, cand.shape[1], axis=0), axis=1)
    return dist.reshape(len(points), -1).min(axis=1)


@dataclass
class Tally:
    """Counts of bone vertices outside the skin, per region and per pose, and the deepest protrusions."""

    outside: np.ndarray  # (n_region,)
    total: np.ndarray  # (n_region,)
    max_m: np.ndarray  # (n_region,)
    per_pose: dict[str, list[float]]

    @classmethod
    def empty(cls) -> Tally:
        n = len(REGIONS)
        return cls(np.zeros(n), np.zeros(n), np.zeros(n), {})

    def add(
        self,
        pose: str,
        skin: np.ndarray,
        faces: np.ndarray,
        bones: np.ndarray,
        region: np.ndarray,
        cavity: np.ndarray | None = None,
    ) -> None:
        """One posed body: skin (V, 3), its faces, bone points (P, 3) and their regions (P,); ``cavity``
        (F,) bool: the skin's pockets, closed before the test (:func:`skin_envelope`)."""
        if cavity is not None:
            skin, faces = skin_envelope(skin, faces, cavity)
        out = fast_winding_number(skin, faces, bones) < 0.5
        depth = surface_distance(skin, faces, bones[out])
        for r in range(len(REGIONS)):
            sel = region == r
            self.outside[r] += out[sel].sum()
            self.total[r] += sel.sum()
            if (out & sel).any():
                self.max_m[r] = max(self.max_m[r], float(depth[sel[out]].max()))
        self.per_pose.setdefault(pose, []).append(float(out.mean()))

    def figures(self) -> dict[str, Any]:
        return {
            "bones_outside_frac": round(float(self.outside.sum() / self.total.sum()), 5),
            "regions": {
                name: {
                    "outside_frac": round(float(self.outside[r] / max(self.total[r], 1)), 4),
                    "max_mm": round(float(self.max_m[r]) * 1e3, 1),
                }
                for r, name in enumerate(REGIONS)
            },
            "poses": {name: round(float(np.mean(v)), 4) for name, v in self.per_pose.items()},
        }


def measure_outside(body: BodyModel, settings: Settings) -> dict[str, Any]:
    """:class:`Tally` figures of the mean body and ``n_bodies`` sampled ones over the named and random
    poses."""
    rng = np.random.default_rng(settings.seed)
    shapes = np.concatenate([np.zeros((1, body.n_shape)), rng.normal(size=(settings.n_bodies, body.n_shape))])
    pick = np.arange(0, len(body.skeleton.bone_mesh().vertices), settings.stride)
    region = region_of_vertices(body)[pick]
    named = {name: pose_coordinates(body, spec) for name, spec in NAMED_POSES.items()}
    cavity = skin_cavity(body)
    tally = Tally.empty()
    for shape in shapes:
        poses = list(named.items()) + [
            ("random", q) for q in random_coordinates(body, settings.n_random, rng)
        ]
        q = np.stack([p for _, p in poses])
        out = body.forward(np.repeat(shape[None], len(q), axis=0), q, skeleton_mesh=True, dtype=torch.float64)
        assert out.bones is not None
        for i, (name, _) in enumerate(poses):
            tally.add(name, out.vertices[i].numpy(), body.faces, out.bones[i, pick].numpy(), region, cavity)
    return {**tally.figures(), "n_bodies": len(shapes), "n_poses_per_body": len(named) + settings.n_random}


def _principal_axes(points: np.ndarray) -> np.ndarray:
    """(3, 3) rows: principal axes of points (P, 3), largest variance first."""
    return np.linalg.svd(points - points.mean(axis=0), full_matrices=False)[2]


def _axis_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle in degrees between two undirected axes."""
    return float(np.degrees(np.arccos(np.clip(abs(float(a @ b)), 0.0, 1.0))))


def twist_diagnostic(body: BodyModel) -> dict[str, dict[str, dict[str, float]]]:
    """Skin-versus-bone angles of the right hand and toes as pro_sup, wrist and mtp sweep their ranges (mean
    body). Returns coordinate -> value label -> angle name -> degrees."""
    sk = body.skeleton
    names = sk.body_names
    bones = sk.bone_mesh()
    weights = np.asarray(body.data["weights"], np.float64)
    parts = {"hand": names.index("hand_r"), "toes": names.index("toes_r")}
    skin_sel = {k: weights[:, b] >= 0.9 for k, b in parts.items()}
    bone_sel = {k: bones.vertex_body == b for k, b in parts.items()}
    base = {"elbow_flex_r": np.deg2rad(90.0)}
    out: dict[str, dict[str, dict[str, float]]] = {}
    for dof in ("pro_sup_r", "wrist_flex_r", "wrist_dev_r", "mtp_angle_r"):
        i = sk.dof_index(dof)
        lo, hi = sk.ranges[i]
        values = {"min": lo, "zero": float(np.clip(0.0, lo, hi)), "max": hi}
        out[dof] = {}
        for label, value in values.items():
            q = sk.coordinates({**base, dof: value})
            res = body.forward(None, q, skeleton_mesh=True, dtype=torch.float64)
            assert res.bones is not None
            skin, bone = res.vertices[0].numpy(), res.bones[0].numpy()
            part = "toes" if dof.startswith("mtp") else "hand"
            s_ax, b_ax = _principal_axes(skin[skin_sel[part]]), _principal_axes(bone[bone_sel[part]])
            out[dof][label] = {
                "normal_deg": round(_axis_angle_deg(s_ax[2], b_ax[2]), 1),
                "long_axis_deg": round(_axis_angle_deg(s_ax[0], b_ax[0]), 1),
            }
    return out


# Picture: the mean body neutral and with pronated forearms; whole body, head and right hand, front and side;
# each pose with a see-through skin (the bones inside) and an opaque one (bones that poke through show).
_CLOSE_UPS = (("body", None, 0.0), ("head", "head", 0.13), ("right hand", "hand_r", 0.12))
_SKINS = (("see-through", 0.35), ("opaque", 1.0))


def render_figure(body: BodyModel, path: Path) -> None:
    """Save a picture of the mean body's skin with the bones inside (rows: neutral and ``pro_sup_max``, each
    with a see-through and an opaque skin; columns: whole body, head and right hand, each from the front and
    the side)."""
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/ is not installed
    from benchmarks.render import RenderMesh, label_grid, render, save_png, tile

    faces = body.skeleton.bone_mesh().faces
    names = body.skeleton.body_names
    images, rows = [], []
    for pose in ("neutral", "pro_sup_max"):
        q = pose_coordinates(body, NAMED_POSES[pose])[None]
        out = body.forward(None, q, skeleton_mesh=True, dtype=torch.float64)
        assert out.bones is not None
        skin, bones = out.vertices[0].numpy(), out.bones[0].numpy()
        for label, opacity in _SKINS:
            rows.append(f"{pose}, {label}")
            meshes = [
                RenderMesh(bones, faces, (0.93, 0.90, 0.80)),
                RenderMesh(skin, body.faces, (0.85, 0.55, 0.45), opacity=opacity),
            ]
            for _, part, r in _CLOSE_UPS:
                bounds = None
                if part is not None:
                    centre = bones[body.skeleton.bone_mesh().vertex_body == names.index(part)].mean(axis=0)
                    bounds = (centre - r, centre + r)
                images += [render(meshes, view, (240, 240), bounds=bounds) for view in ("front", "side")]
    grid = tile(images, columns=2 * len(_CLOSE_UPS))
    titles = [f"{name} {view}" for name, _, _ in _CLOSE_UPS for view in ("front", "side")]
    caption = "bones inside the skin (mean body): see-through, and opaque where only protruding bone shows"
    save_png(label_grid(grid, [titles], rows, caption=caption), path)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0] if __doc__ else None)
    parser.add_argument("--quick", action="store_true", help="3 bodies, 2 random poses, every 6th vertex")
    parser.add_argument("--json", action="store_true", help="print the figures as one JSON object last")
    parser.add_argument("--seed", type=int, default=0, help="random seed of the shapes and poses (default 0)")
    parser.add_argument("--assets", type=Path, default=None, help="asset folder (default: the checkout's)")
    parser.add_argument("--render", type=Path, default=None, help="also save a see-through picture (PNG)")
    return parser.parse_args(argv)


def settings_for(quick: bool, seed: int = 0) -> Settings:
    """The quick run's or the full run's sample."""
    if quick:
        return Settings(n_bodies=2, n_random=2, stride=6, seed=seed, quick=True)
    return Settings(n_bodies=11, n_random=6, stride=2, seed=seed, quick=False)


def measure(body: BodyModel, settings: Settings) -> dict[str, Any]:
    """Every figure of the run (no printing): the outside fractions, the twist check, the time taken."""
    t0 = time.perf_counter()
    figures = measure_outside(body, settings)
    figures["twist"] = twist_diagnostic(body)
    figures.update(
        {"quick": settings.quick, "stride": settings.stride, "seconds": round(time.perf_counter() - t0, 1)}
    )
    return figures


def run(quick: bool) -> dict[str, Any]:
    """``bones_outside_frac`` and its per-region and per-pose figures on the shipped assets, for
    ``benchmarks/fit.py``."""
    figures = measure(BodyModel.load(), settings_for(quick))
    return {
        "bones_outside_frac": figures["bones_outside_frac"],
        "bones_outside_by_region": {k: r["outside_frac"] for k, r in figures["regions"].items()},
    }


def main(argv: list[str] | None = None) -> dict[str, Any]:
    args = parse_args(argv)
    settings = settings_for(args.quick, args.seed)
    body = BodyModel.load(args.assets)
    if args.render is not None:
        render_figure(body, args.render)
    figures = measure(body, settings)
    print(
        f"bones_outside_frac {figures['bones_outside_frac']:.4f} over {figures['n_bodies']} bodies x "
        f"{figures['n_poses_per_body']} poses (every {settings.stride}th bone vertex)"
    )
    for name, r in figures["regions"].items():
        print(f"  {name:10s} outside {r['outside_frac']:.3f}  max {r['max_mm']:5.1f} mm")
    for name, frac in figures["poses"].items():
        print(f"  pose {name:12s} {frac:.3f}")
    for dof, rows in figures["twist"].items():
        cells = ", ".join(
            f"{k}: normal {v['normal_deg']} / long {v['long_axis_deg']} deg" for k, v in rows.items()
        )
        print(f"  skin vs bones, {dof}: {cells}")
    if args.json:
        print(json.dumps(figures))
    return figures


if __name__ == "__main__":
    main()

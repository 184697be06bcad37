"""Personal-model benchmark (issue 40): swing-twist skinning against plain LBS, personal rigs
(:mod:`benchmarks.personal_rig`: ``rig_ratio``, ``rig_param_mm``, ``rig_build_s``) and a shape space grown
from scans (:mod:`benchmarks.grow_space`: ``grow_ratio``, ``grow_rounds``, ``grow_accepted``), one run.

What is measured
----------------
* Skinning (``skinning="lbs"`` against ``"lbs_dq"``, :mod:`bodyfit.models.body.swing_twist`): the mean body
  in its bind pose (where both skins are the stored template) with one twist coordinate set to each end of
  the test: ``pro_sup_r`` 0 and 90 degrees (the forearm; the bind pose is at 55), ``arm_rot_r`` -90 and +90
  (the upper arm), ``hip_rotation_r`` -40 and +40 (the thigh), ``neck_rotation`` -60 and +60 (neck and
  head). Full runs add a random shape (seed 0) and the left side.
* Region of a segment: the skin vertices whose largest skinning weight is on that segment's bodies (forearm:
  ulna, radius; upper arm: humerus; thigh: femur; neck and head: cervical link, head) and the faces with
  all three corners among them.
* ``volume kept``: the region's posed volume over its bind-pose volume. The region is closed by capping
  every boundary loop with a fan of triangles to the loop's mean point, and its volume is the divergence
  theorem's sum of signed tetrahedra over faces and caps. LBS blends frames twisted apart into matrices
  that shrink the cross-section (the candy wrapper); the cap follows the same skin, so the ratio reads the
  collapse.
* ``intersecting``: the fraction of a region's faces whose centroid, pushed 1 mm out along the face normal,
  lies inside the posed skin (generalised winding number over the whole skin above 0.5): skin folded into
  itself. A proxy for self-intersection, not an exact triangle-triangle test; about ``PROBES`` faces per
  region, evenly spaced in face order.
* Keys: ``dq_volume_kept_min`` and ``lbs_volume_kept_min``, the smallest volume kept over the forearm and
  upper-arm cases (the issue's target: within 3 % of rest under lbs_dq, so >= 0.97); ``*_volume_kept_all_min``
  over every case; the per-case table in ``skinning_table``.
* Speed: each skinning's decoder exported to ONNX (float32), run in ONNX Runtime on the CPU with one thread
  and every graph optimisation, the two sessions alternating on the same random inputs, median over
  ``ONNX_REPEATS`` calls of the calling thread's CPU time (ONNX Runtime runs in it with one thread; other
  processes on a shared machine stretch wall time by however long they hold the core, not CPU time):
  ``lbs_onnx_ms_b1``, ``dq_onnx_ms_b1``, ``lbs_onnx_ms_b64``, ``dq_onnx_ms_b64`` and
  ``dq_onnx_slowdown_b1``, ``dq_onnx_slowdown_b64`` (dq over lbs; the target is <= 1.10).
  ``dq_onnx_parity_max_m``: the largest vertex distance between the lbs_dq ONNX model and the float64 torch
  decoder on the timed inputs (target <= 1e-5 m).

Usage::

    python benchmarks/personal.py [--quick] [--json]
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from bodyfit.models.body.geometry import winding_number
from bodyfit.models.body.model import BodyModel

ROOT = Path(__file__).resolve().parents[1]

# (case, segment bodies, twist coordinate, its value in degrees)
SEGMENTS = {
    "forearm": ("ulna", "radius"),
    "upper_arm": ("humerus",),
    "thigh": ("femur",),
    "neck_head": ("cervical_link", "head"),
}
TWISTS = (
    ("forearm", "pro_sup", 0.0),
    ("forearm", "pro_sup", 90.0),
    ("upper_arm", "arm_rot", -90.0),
    ("upper_arm", "arm_rot", 90.0),
    ("thigh", "hip_rotation", -40.0),
    ("thigh", "hip_rotation", 40.0),
    ("neck_head", "neck_rotation", -60.0),
    ("neck_head", "neck_rotation", 60.0),
)
TARGET_SEGMENTS = ("forearm", "upper_arm")
TARGET_VOLUME_KEPT = 0.97
TARGET_SLOWDOWN = 1.10
ONNX_REPEATS = {1: 400, 64: 40}
PUSH_M = 1e-3
PROBES = 150  # faces probed per region, evenly spaced in face order


def region(model: BodyModel, bodies: tuple[str, ...], side: str) -> tuple[np.ndarray, np.ndarray]:
    """Vertex mask (V,) and face indices of the skin dominated by ``bodies`` (names without side suffix
    get ``_r`` / ``_l``)."""
    names = model.skeleton.body_names
    wanted = {names.index(b if b in names else f"{b}_{side}") for b in bodies}
    dominant = np.asarray(model.data["weights"]).argmax(axis=1)
    mask = np.isin(dominant, sorted(wanted))
    faces = np.flatnonzero(mask[model.faces].all(axis=1))
    return mask, faces


def capped_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Volume (m^3) enclosed by an open patch of a consistently oriented mesh once each boundary loop is
    capped by a fan to the loop's mean point: (1/6) sum of det[p0, p1, p2] over faces and caps.

    Args:
        vertices: (V, 3); faces: (F, 3) the patch.
    """
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    key = {tuple(e) for e in edges.tolist()}
    boundary = np.array([e for e in edges.tolist() if (e[1], e[0]) not in key], np.int64).reshape(-1, 2)
    p = vertices[faces]
    total = float(np.einsum("fi,fi->f", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum())
    if len(boundary):
        n = len(vertices)
        graph = coo_matrix((np.ones(len(boundary)), (boundary[:, 0], boundary[:, 1])), shape=(n, n))
        _, label = connected_components(graph, directed=False)
        loops = label[boundary[:, 0]]
        centre = np.zeros((label.max() + 1, 3))
        ends = np.unique(boundary[:, 0])
        np.add.at(centre, label[ends], vertices[ends])
        centre /= np.maximum(np.bincount(label[ends], minlength=len(centre)), 1)[:, None]
        a, b, c = vertices[boundary[:, 1]], vertices[boundary[:, 0]], centre[loops]
        total += float(np.einsum("fi,fi->f", a, np.cross(b, c)).sum())
    return total / 6.0


def intersecting_fraction(vertices: np.ndarray, faces: np.ndarray, patch: np.ndarray) -> float:
    """Fraction of the faces ``patch`` (indices into faces (F, 3)) whose centroid, pushed ``PUSH_M`` out
    along the face normal, lies inside the closed skin (vertices (V, 3), faces)."""
    patch = patch[:: max(1, len(patch) // PROBES)]
    p = vertices[faces[patch]]
    normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    probe = p.mean(axis=1) + PUSH_M * normal
    return float((winding_number(vertices, faces, probe) > 0.5).mean())


def _skin(
    model: BodyModel, skinning: str, shape: np.ndarray, coordinate: str | None, degrees: float
) -> np.ndarray:
    """Skin vertices (V, 3) of one shape (n_shape,) in the bind pose with ``coordinate`` (None: none) set to
    ``degrees``. The decoder is called directly: the bind pose itself lies slightly outside two knee and
    scapula limits, which :meth:`BodyModel.forward` would refuse."""
    q = model.bind_coordinates.copy()
    if coordinate is not None:
        q[model.dof_names.index(coordinate)] = np.radians(degrees)
    args = (torch.as_tensor(shape[None]), torch.as_tensor(q[None]), torch.zeros(1, 3, dtype=torch.float64))
    return model.decoder(torch.float64, skinning)(*args)[0][0].numpy()


def skinning_table(model: BodyModel, quick: bool) -> list[dict[str, Any]]:
    """One row per (shape, side, twist case): volume kept and intersecting fraction under both skinnings."""
    shapes = [("mean", np.zeros(model.n_shape))]
    if not quick:
        shapes.append(("random", np.random.default_rng(0).normal(size=model.n_shape)))
    rows = []
    for shape_name, shape in shapes:
        rest = _skin(model, "lbs", shape, None, 0.0)
        for side in ("r",) if quick else ("r", "l"):
            for segment, coordinate, degrees in TWISTS:
                if side == "l" and coordinate == "neck_rotation":
                    continue
                name = coordinate if coordinate == "neck_rotation" else f"{coordinate}_{side}"
                _, faces = region(model, SEGMENTS[segment], side)
                row: dict[str, Any] = {
                    "shape": shape_name,
                    "segment": segment if segment == "neck_head" else f"{segment}_{side}",
                    "coordinate": name,
                    "degrees": degrees,
                }
                v0 = capped_volume(rest, model.faces[faces])
                for key, skinning in (("lbs", "lbs"), ("dq", "lbs_dq")):
                    v = _skin(model, skinning, shape, name, degrees)
                    row[f"{key}_volume_kept"] = capped_volume(v, model.faces[faces]) / v0
                    row[f"{key}_intersecting"] = intersecting_fraction(v, model.faces, faces)
                rows.append(row)
    return rows


def skinning_keys(model: BodyModel, quick: bool) -> dict[str, Any]:
    """The volume and self-intersection keys and their table (module docstring)."""
    rows = skinning_table(model, quick)
    target = [r for r in rows if r["segment"].rsplit("_", 1)[0] in TARGET_SEGMENTS]
    out: dict[str, Any] = {}
    for key in ("lbs", "dq"):
        out[f"{key}_volume_kept_min"] = min(r[f"{key}_volume_kept"] for r in target)
        out[f"{key}_volume_kept_all_min"] = min(r[f"{key}_volume_kept"] for r in rows)
        out[f"{key}_intersecting_max"] = max(r[f"{key}_intersecting"] for r in rows)
    out["dq_volume_target_met"] = out["dq_volume_kept_min"] >= TARGET_VOLUME_KEPT
    out["skinning_table"] = rows
    return out


def _session(data: bytes) -> Any:
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    options.inter_op_num_threads = 1
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    return ort.InferenceSession(data, options, providers=["CPUExecutionProvider"])


def onnx_keys(model: BodyModel, quick: bool) -> dict[str, Any]:
    """ONNX Runtime timings of both skinnings at B = 1 and 64 and the lbs_dq model's parity (module
    docstring)."""
    from bodyfit.models.body.onnx_export import export_body_onnx

    torch.set_num_threads(1)
    sessions = {
        key: _session(export_body_onnx(model.decoder(torch.float32, skinning), model.n_shape))
        for key, skinning in (("lbs", "lbs"), ("dq", "lbs_dq"))
    }
    rng = np.random.default_rng(1)
    out: dict[str, Any] = {}
    parity = 0.0
    for batch, repeats in ONNX_REPEATS.items():
        repeats = repeats // 4 if quick else repeats
        q = model.bind_coordinates + rng.uniform(-0.4, 0.4, size=(batch, model.skeleton.n_dof))
        limits = np.array([c.range for c in model.skeleton.spec.coordinates])
        q = np.clip(q, limits[:, 0], limits[:, 1])
        feed = {
            "shape": rng.normal(size=(batch, model.n_shape)).astype(np.float32),
            "coordinates": q.astype(np.float32),
            "root": rng.normal(scale=0.1, size=(batch, 3)).astype(np.float32),
        }
        times: dict[str, list[float]] = {key: [] for key in sessions}
        for s in sessions.values():
            s.run(None, feed)
        for _ in range(repeats):
            for key, s in sessions.items():
                start = time.thread_time()
                s.run(None, feed)
                times[key].append(time.thread_time() - start)
        for key in sessions:
            out[f"{key}_onnx_ms_b{batch}"] = 1e3 * float(np.median(times[key]))
        out[f"dq_onnx_slowdown_b{batch}"] = out[f"dq_onnx_ms_b{batch}"] / out[f"lbs_onnx_ms_b{batch}"]
        torch_in = [torch.as_tensor(feed[k], dtype=torch.float64) for k in ("shape", "coordinates", "root")]
        ref = model.decoder(torch.float64, "lbs_dq")(*torch_in)[0].numpy()
        got = sessions["dq"].run(None, feed)[0]
        parity = max(parity, float(np.linalg.norm(got - ref, axis=-1).max()))
    out["dq_onnx_parity_max_m"] = parity
    out["dq_onnx_target_met"] = (
        max(out["dq_onnx_slowdown_b1"], out["dq_onnx_slowdown_b64"]) <= TARGET_SLOWDOWN
    )
    return out


GALLERY_CASES = (
    ("forearm", "pro_sup_r", 0.0),
    ("forearm", "pro_sup_r", 90.0),
    ("upper_arm", "arm_rot_r", -90.0),
    ("upper_arm", "arm_rot_r", 90.0),
)


def skinning_gallery(path: str = "docs/skinning_arm.png", size: tuple[int, int] = (360, 300)) -> None:
    """Render the mean body's right forearm or upper arm (the measured regions) under LBS and lbs_dq for
    each of ``GALLERY_CASES``, seen from the front, into one labelled PNG: one row per case, both columns at
    the row's scale."""
    sys.path.insert(0, str(ROOT))  # benchmarks/ is not installed
    from benchmarks.render import RenderMesh, label_grid, render, save_png, tile

    model = BodyModel.load()
    shape = np.zeros(model.n_shape)
    images = []
    for segment, coordinate, degrees in GALLERY_CASES:
        mask, faces = region(model, SEGMENTS[segment], "r")
        skins = [_skin(model, skinning, shape, coordinate, degrees) for skinning in ("lbs", "lbs_dq")]
        points = np.concatenate([v[mask] for v in skins])
        bounds = (points.min(axis=0) - 0.01, points.max(axis=0) + 0.01)
        meshes = [RenderMesh(v, model.faces[faces], (0.85, 0.66, 0.56)) for v in skins]
        images += [render([mesh], "front", size, bounds=bounds) for mesh in meshes]
    titles = [f"{s.replace('_', ' ')}\n{c} {d:+.0f} deg" for s, c, d in GALLERY_CASES]
    caption = (
        "The measured skin regions of the mean body, from the front, in the bind pose with one twist "
        "coordinate changed (bind: pro_sup_r +55, arm_rot_r +12 deg)."
    )
    save_png(label_grid(tile(images, columns=2), [["LBS", "LBS + DQ twist"]], titles, caption), path)


def run(quick: bool) -> dict[str, Any]:
    """Every key group of the benchmark: swing-twist skinning, its ONNX speed, personal rigs
    (:mod:`benchmarks.personal_rig`) and the grown shape space (:mod:`benchmarks.grow_space`)."""
    from benchmarks import grow_space, personal_rig

    model = BodyModel.load()
    return {
        **skinning_keys(model, quick),
        **onnx_keys(model, quick),
        **personal_rig.run(quick),
        **grow_space.run(quick),
    }


def main(argv: list[str] | None = None) -> None:
    sys.path.insert(0, str(ROOT))  # benchmarks/ is not installed
    from benchmarks.bench_cli import bench_main

    bench_main(
        run,
        "Personal models: swing-twist skinning against LBS, personal rigs, a grown shape space.",
        "mean body, right side, fewer repeats; one rig subject of each kind; the small scan collection",
        argv,
    )


if __name__ == "__main__":
    main()

"""Encoders of synthesized bodies into the formats clients ask for: npz, ply, obj, glb and json.

``npz`` (the default and the fastest) holds every array; the mesh formats hold the skin (and the skeleton
mesh when asked for) with their triangles; ``json`` is for small batches and quick looks.
"""

from __future__ import annotations

import gc
import io
import json
import math
from dataclasses import dataclass
from typing import Any, cast

import numpy as np
import trimesh

from bodyfit.service.errors import InvalidInputError

MEDIA_TYPES = {
    "npz": "application/x-npz",
    "ply": "application/x-ply",
    "obj": "model/obj",
    "glb": "model/gltf-binary",
    "json": "application/json",
}
FORMATS = tuple(MEDIA_TYPES)


@dataclass(frozen=True)
class Bodies:
    """Posed bodies.

    vertices (B, V, 3) float32 metres; faces (F, 3) int32; joints (B, J, 3) float32 with ``joint_names``;
    bones (B, Vb, 3) float32 and bone_faces (Fb, 3) when the skeleton mesh was asked for, else None.
    """

    vertices: np.ndarray
    faces: np.ndarray
    joints: np.ndarray
    joint_names: tuple[str, ...]
    bones: np.ndarray | None = None
    bone_faces: np.ndarray | None = None

    @property
    def batch(self) -> int:
        return int(self.vertices.shape[0])


def npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    """Uncompressed .npz of ``arrays`` (no pickled objects)."""
    buf = io.BytesIO()
    np.savez(buf, allow_pickle=False, **arrays)
    return buf.getvalue()


def encode_bodies(bodies: Bodies, fmt: str, faces: bool = False) -> bytes:
    """Encode ``bodies`` as ``fmt`` (one of :data:`FORMATS`). ``faces`` adds the triangles to npz / json
    (mesh formats always carry them). ply and obj hold one body: ask for B = 1 or use npz / glb."""
    if fmt not in MEDIA_TYPES:
        raise InvalidInputError(f"unknown format {fmt!r}; choose one of {', '.join(FORMATS)}", field="format")
    if bodies.batch < 1:
        raise InvalidInputError("no bodies to encode: ask for at least one (B >= 1)", field="batch")
    if fmt == "npz":
        return npz_bytes(_arrays(bodies, faces))
    if fmt == "json":
        doc = {k: _json_list(v) for k, v in _arrays(bodies, faces).items()}
        return json.dumps(doc, separators=(",", ":"), allow_nan=False).encode()
    if fmt == "glb":
        return _glb(bodies)
    if bodies.batch != 1:
        raise InvalidInputError(
            f"{fmt} holds one body but {bodies.batch} were asked for; send one parameter set, or use npz or "
            "glb for a batch",
            field="format",
        )
    meshes = [m for _, m in _meshes(bodies, 0)]
    mesh = cast(trimesh.Trimesh, trimesh.util.concatenate(meshes)) if len(meshes) > 1 else meshes[0]
    out = mesh.export(file_type=fmt)
    return out if isinstance(out, bytes) else str(out).encode()


def _glb(bodies: Bodies) -> bytes:
    """The bodies as one glTF binary scene. trimesh's meshes and scene hold reference cycles, which Python
    frees only at a full collection: one is run here, or a large scene's memory (hundreds of MB for hundreds
    of bodies) stays resident until one happens."""
    scene = trimesh.Scene()
    for b in range(bodies.batch):
        for name, mesh in _meshes(bodies, b):
            scene.add_geometry(mesh, node_name=f"{name}_{b}", geom_name=f"{name}_{b}")
    data = bytes(scene.export(file_type="glb"))
    del scene
    gc.collect()
    return data


def json_ready(value: Any) -> Any:
    """``value`` (dicts, lists, tuples, numbers, numpy arrays and scalars) as plain JSON values, with every
    NaN or infinite float as None (null): JSON has no NaN, ``json.dumps`` would write a literal no parser
    accepts and a strict encoder raises. Results are checked finite before they are encoded; this keeps
    the encoders from failing on what is NaN by definition (an undefined statistic)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: json_ready(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_ready(v) for v in value]
    if isinstance(value, np.ndarray):
        return _json_list(value)
    if isinstance(value, np.generic):
        return json_ready(value.item())
    return value


def json_bytes(doc: Any) -> bytes:
    """``doc`` as compact JSON (:func:`json_ready`: NaN and infinities become null, never a failure)."""
    return json.dumps(json_ready(doc), separators=(",", ":"), allow_nan=False).encode()


def _json_list(a: np.ndarray) -> Any:
    """An array as nested lists; non-finite floats as None (checked in numpy first: the common all-finite
    array is converted at tolist's speed)."""
    if a.dtype.kind == "f" and not np.isfinite(a).all():
        return json_ready(a.tolist())
    return a.tolist()


def _arrays(bodies: Bodies, faces: bool) -> dict[str, np.ndarray]:
    arrays: dict[str, np.ndarray] = {
        "vertices": bodies.vertices,
        "joints": bodies.joints,
        "joint_names": np.array(bodies.joint_names),
    }
    if faces:
        arrays["faces"] = bodies.faces
    if bodies.bones is not None and bodies.bone_faces is not None:
        arrays["bones"] = bodies.bones
        if faces:
            arrays["bone_faces"] = bodies.bone_faces
    return arrays


def _meshes(bodies: Bodies, b: int) -> list[tuple[str, trimesh.Trimesh]]:
    out = [("skin", trimesh.Trimesh(bodies.vertices[b], bodies.faces, process=False))]
    if bodies.bones is not None and bodies.bone_faces is not None:
        out.append(("skeleton", trimesh.Trimesh(bodies.bones[b], bodies.bone_faces, process=False)))
    return out

"""The public skeleton object: named DOFs, validation, bounded parameterisation, forward kinematics."""

from __future__ import annotations

import difflib
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch

from bodyfit.models.assets import verified_asset
from bodyfit.models.errors import CoordinateRangeError, NonFiniteError, ShapeError, UnknownCoordinateError
from bodyfit.models.skeleton.bones import BoneMesh, pose_bones
from bodyfit.models.skeleton.bounds import from_coordinates, to_coordinates
from bodyfit.models.skeleton.kinematics import Pose, SkeletonKinematics
from bodyfit.models.skeleton.spec import SkeletonSpec

SKELETON_ASSET = "skeleton.json"
# The pelvis orientation: R = Rz(tilt) Rx(list) Ry(rotation) (see rotations.zxy_angles).
PELVIS_ROTATIONS = ("pelvis_tilt", "pelvis_list", "pelvis_rotation")
# Midline DOFs whose sign flips in a left-right mirror image (the rest swap sides, sign kept).
LATERAL_DOFS = frozenset({
    "pelvis_list", "pelvis_rotation", "lumbar_bending", "lumbar_rotation",
    "thorax_bending", "thorax_rotation", "neck_bending", "neck_rotation",
})  # fmt: skip


def twin_name(name: str) -> str:
    """The other side's name (``x_r`` <-> ``x_l``); midline names map to themselves."""
    if name.endswith("_r"):
        return name[:-2] + "_l"
    if name.endswith("_l"):
        return name[:-2] + "_r"
    return name


RANGE_TOLERANCE = 1e-9


def _as_tensor(x: torch.Tensor | np.ndarray, dtype: torch.dtype | None) -> torch.Tensor:
    t = torch.as_tensor(x)
    if not (t.is_floating_point()):
        t = t.to(dtype or torch.float32)
    return t.to(dtype) if dtype is not None else t


class Skeleton:
    """A loaded skeleton. Holds the spec and its compiled kinematics; no mutable state is exposed."""

    def __init__(self, spec: SkeletonSpec, folder: Path | None = None) -> None:
        self.spec = spec
        self._folder = folder
        self._fk: dict[torch.dtype, SkeletonKinematics] = {}
        self._bones: BoneMesh | None = None
        self.ranges = np.array([c.range for c in spec.coordinates], dtype=np.float64)  # (n_dof, 2)

    @classmethod
    def load(cls, folder: Path | None = None) -> Skeleton:
        """Load the built-in skeleton asset (hash-checked against the manifest)."""
        return cls(SkeletonSpec.load(verified_asset(SKELETON_ASSET, folder)), folder)

    # -- names -----------------------------------------------------------------------------------------
    @property
    def dof_names(self) -> list[str]:
        return self.spec.dof_names

    @property
    def n_dof(self) -> int:
        return len(self.spec.coordinates)

    @property
    def segments(self) -> list[str]:
        return list(self.spec.segments)

    @property
    def body_names(self) -> list[str]:
        return self.spec.body_names

    def dof_index(self, name: str) -> int:
        try:
            return self.dof_names.index(name)
        except ValueError:
            raise self._unknown(name) from None

    def mirror_coordinates(self, q: np.ndarray) -> np.ndarray:
        """Coordinates of the left-right mirror image (z -> -z) of a pose. q: (B, n_dof) -> (B, n_dof)."""
        out = np.empty_like(q)
        for i, name in enumerate(self.dof_names):
            out[:, self.dof_index(twin_name(name))] = -q[:, i] if name in LATERAL_DOFS else q[:, i]
        return out

    def twin_bodies(self) -> list[int]:
        """Index of each body's mirror twin (itself on the midline)."""
        return [self.body_names.index(twin_name(n)) for n in self.body_names]

    def _unknown(self, name: str) -> UnknownCoordinateError:
        close = difflib.get_close_matches(name, self.dof_names, n=3)
        hint = f" Did you mean {', '.join(close)}?" if close else ""
        return UnknownCoordinateError(
            f"unknown coordinate {name!r}.{hint} Valid names: GET the model info or Skeleton.dof_names "
            f"({self.n_dof} DOFs, e.g. {', '.join(self.dof_names[:4])}, ...)."
        )

    def coordinates(self, values: Mapping[str, float | np.ndarray], batch: int | None = None) -> np.ndarray:
        """Named values -> a (B, n_dof) coordinate array (missing DOFs are 0 = neutral).

        Args:
            values: DOF name -> scalar or (B,) array, in radians.
            batch: B; inferred from the arrays when omitted.
        Raises:
            UnknownCoordinateError: a name is not a DOF of this skeleton.
        """
        arrays = {k: np.atleast_1d(np.asarray(v, dtype=np.float64)) for k, v in values.items()}
        for k in arrays:
            if k not in self.dof_names:
                raise self._unknown(k)
        B = batch or max((len(a) for a in arrays.values()), default=1)
        q = np.zeros((B, self.n_dof))
        for k, a in arrays.items():
            if a.ndim != 1 or len(a) not in (1, B):
                raise ShapeError(f"coordinate {k!r} has shape {a.shape}; give a scalar or a ({B},) array")
            q[:, self.dof_index(k)] = a
        return q

    # -- validation --------------------------------------------------------------------------------------
    def validate(
        self,
        q: torch.Tensor | np.ndarray,
        root: torch.Tensor | np.ndarray | None = None,
        scales: torch.Tensor | np.ndarray | None = None,
        dtype: torch.dtype | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
        """Check shapes, finiteness and ranges; return tensors of one dtype.

        Values are never clamped silently: use :meth:`from_unbounded` to map free values into range.

        Args:
            q: (B, n_dof) coordinates in the order of :attr:`dof_names` (radians / metres).
            root: (B, 3) root translation in metres, or None.
            scales: (B, n_seg, 3) positive per-segment scale factors, or None.
            dtype: the dtype of the returned tensors; None keeps ``q``'s (float32 for integer input).

        Returns:
            ``(q, root, scales)`` as tensors of one dtype (``root`` and ``scales`` None when not given).

        Raises:
            ShapeError: an array does not have the shape above.
            NonFiniteError: an array holds NaN or infinite values.
            CoordinateRangeError: a coordinate is outside its joint limits, or a scale factor is not positive.
        """
        qt = _as_tensor(q, dtype)
        if qt.ndim != 2 or qt.shape[1] != self.n_dof:
            raise ShapeError(
                f"coordinates must have shape (B, {self.n_dof}) in the order of Skeleton.dof_names; "
                f"got {tuple(qt.shape)}. Use Skeleton.coordinates({{name: value}}) to build it by name."
            )
        B = qt.shape[0]
        check_finite("coordinates", qt)
        self.check_range(qt)
        rt = st = None
        if root is not None:
            rt = _as_tensor(root, qt.dtype)
            if tuple(rt.shape) != (B, 3):
                raise ShapeError(
                    f"root translation must have shape ({B}, 3) in metres; got {tuple(rt.shape)}"
                )
            check_finite("root translation", rt)
        if scales is not None:
            st = _as_tensor(scales, qt.dtype)
            n = len(self.spec.segments)
            if tuple(st.shape) != (B, n, 3):
                raise ShapeError(
                    f"scale factors must have shape ({B}, {n}, 3), one (x, y, z) factor per segment in the "
                    f"order of Skeleton.segments; got {tuple(st.shape)}"
                )
            check_finite("scale factors", st)
            if bool((st <= 0).any()):
                raise CoordinateRangeError("scale factors must be positive (1 = the unscaled skeleton)")
        return qt, rt, st

    def check_range(self, q: torch.Tensor) -> None:
        """Raise CoordinateRangeError naming every DOF outside its range."""
        lo = torch.as_tensor(self.ranges[:, 0], dtype=q.dtype) - RANGE_TOLERANCE
        hi = torch.as_tensor(self.ranges[:, 1], dtype=q.dtype) + RANGE_TOLERANCE
        bad = ((q < lo) | (q > hi)).any(0)
        if bool(bad.any()):
            parts = []
            for i in torch.nonzero(bad).flatten().tolist()[:5]:
                vals = q[:, i]
                worst = float(vals.min()) if float(vals.min()) < lo[i] else float(vals.max())
                lo_i, hi_i = self.ranges[i]
                parts.append(f"{self.dof_names[i]}={worst:.4g} rad (range {lo_i:.4g}..{hi_i:.4g})")
            raise CoordinateRangeError(
                "coordinates outside their joint limits: " + "; ".join(parts) + ". Clamp them yourself or "
                "pass unconstrained values through Skeleton.from_unbounded."
            )

    def inside(self, q: np.ndarray, margin: float) -> np.ndarray:
        """Coordinates moved at least ``margin`` (a fraction of each range) inside the limits: a start
        point for fitting through :meth:`to_unbounded`. q: (..., n_dof) -> (..., n_dof)."""
        lo, hi = self.ranges[:, 0], self.ranges[:, 1]
        pad = margin * (hi - lo)
        return np.clip(q, lo + pad, hi - pad)

    # -- bounded parameterisation -------------------------------------------------------------------------
    def from_unbounded(self, u: torch.Tensor) -> torch.Tensor:
        """(B, n_dof) unconstrained values -> coordinates strictly inside their ranges.

        The tanh bound of :mod:`~bodyfit.models.skeleton.bounds` (eq. 6 of Wang et al., "BLSM: A Bone-Level
        Skinned Model of the Human Mesh", ECCV 2020).
        """
        lo, hi = (torch.as_tensor(self.ranges[:, k], dtype=u.dtype, device=u.device) for k in (0, 1))
        return to_coordinates(u, lo, hi)

    def to_unbounded(self, q: torch.Tensor) -> torch.Tensor:
        """Inverse of :meth:`from_unbounded` for in-range coordinates (checked)."""
        self.check_range(q)
        lo, hi = (torch.as_tensor(self.ranges[:, k], dtype=q.dtype, device=q.device) for k in (0, 1))
        return from_coordinates(q, lo, hi)

    # -- kinematics --------------------------------------------------------------------------------------
    def kinematics(self, dtype: torch.dtype = torch.float32) -> SkeletonKinematics:
        """The torch FK module (buffers only) for ``dtype``; built once per dtype."""
        if dtype not in self._fk:
            self._fk[dtype] = SkeletonKinematics(self.spec, dtype)
        return self._fk[dtype]

    def bone_mesh(self) -> BoneMesh:
        """The bone mesh asset (loaded on first use, hash-checked)."""
        if self._bones is None:
            self._bones = BoneMesh.load(self.spec, self._folder)
        return self._bones

    def pose_bones(
        self, frames: torch.Tensor, scales: torch.Tensor | np.ndarray | None = None
    ) -> torch.Tensor:
        """Bone mesh vertices (B, V, 3) for body frames (B, n_body, 4, 4) from :meth:`forward` (same
        scales); triangles are ``bone_mesh().faces``."""
        bones = self.bone_mesh()
        s = None if scales is None else torch.as_tensor(scales, dtype=frames.dtype)
        return pose_bones(
            torch.as_tensor(bones.vertices),
            torch.as_tensor(bones.vertex_body),
            torch.as_tensor(bones.vertex_segment),
            frames,
            s,
        )

    def forward(
        self,
        q: torch.Tensor | np.ndarray,
        root: torch.Tensor | np.ndarray | None = None,
        scales: torch.Tensor | np.ndarray | None = None,
    ) -> Pose:
        """Validated forward kinematics. See :class:`SkeletonKinematics`."""
        qt, rt, st = self.validate(q, root, scales)
        return self.kinematics(qt.dtype)(qt, rt, st)


def check_finite(what: str, t: torch.Tensor | np.ndarray) -> None:
    """Raise :class:`NonFiniteError` naming ``what`` and the first bad index if t holds NaN or inf."""
    ok = np.isfinite(t) if isinstance(t, np.ndarray) else torch.isfinite(t).numpy(force=True)
    if not ok.all():
        bad = [int(i) for i in np.argwhere(~ok)[0]]
        raise NonFiniteError(
            f"{what} contain NaN or infinite values (first at index {bad}); send finite numbers"
        )

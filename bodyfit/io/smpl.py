"""Readers of SMPL-format motion: AMASS-style ``.npz`` and SMPL ``.pkl`` files.

Accepted keys: ``poses`` (T, 72) SMPL or (T, 156) SMPL-H / (T, 165) SMPL-X layouts (the first 66 values
are the root and 21 body joints; SMPL's hand joints 22-23 come from positions 66-72 when the layout is
SMPL's, else stay zero), or ``global_orient`` (T, 3) + ``body_pose`` (T, 63 or 69); ``trans`` (T, 3);
``betas`` (K,) or (T, K); ``gender`` (neutral, male or female; absent or empty: neutral);
``mocap_framerate`` or ``mocap_frame_rate`` (or ``fps``); ``surface_model_type``. Frames holding NaN or
infinite values, or implausible ones (:data:`POSE_LIMIT_RAD`, :data:`TRANS_LIMIT_M`), are flagged in
``bad_frames``, not dropped; betas beyond :data:`BETAS_LIMIT_SD` are refused.

An .npz is never loaded whole: only these arrays are read, each checked from its .npy header first (numeric
poses, trans, betas and frame rate; text gender; shapes; frames against ``max_frames``; the total against
``max_bytes``) by :func:`bodyfit.io.npz.read_npz`.

The layouts are those of SMPL (M. Loper, N. Mahmood, J. Romero, G. Pons-Moll and M. J. Black, "SMPL: A Skinned
Multi-Person Linear Model", ACM Transactions on Graphics 34(6), 2015), SMPL-H (J. Romero, D. Tzionas and M. J.
Black, "Embodied Hands: Modeling and Capturing Hands and Bodies Together", ACM Transactions on Graphics 36(6),
2017) and SMPL-X (G. Pavlakos et al., "Expressive Body Capture: 3D Hands, Face, and Body from a Single Image",
IEEE/CVF Conference on Computer Vision and Pattern Recognition (CVPR), 2019), as AMASS distributes them (N.
Mahmood, N. Ghorbani, N. F. Troje, G. Pons-Moll and M. J. Black, "AMASS: Archive of Motion Capture as Surface
Shapes", IEEE/CVF International Conference on Computer Vision (ICCV), 2019).
"""

from __future__ import annotations

import os
import pickle
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from bodyfit.io.errors import FileFormatError
from bodyfit.io.npz import DEFAULT_MAX_BYTES, NUMBER, TEXT, ArraySpec, Dim, npz_keys, read_npz
from bodyfit.models.errors import BodyfitError

GENDERS = ("neutral", "male", "female")
BETAS_LIMIT_SD = 10.0
"""Largest accepted |beta|: SMPL's shape coefficients are in standard deviations of its shape space, and
AMASS's subjects lie within about 4; beyond 10 they describe no human (another model's coefficients, or a
unit mistake)."""
POSE_LIMIT_RAD = 100.0
"""Largest plausible rotation-vector length (radians, about 16 turns; an unwrapped angle may pass pi). A frame
with a longer one, or a root farther than :data:`TRANS_LIMIT_M`, is flagged in ``bad_frames`` with the
non-finite ones: float64 keeps no useful precision in a 1e30-radian rotation."""
TRANS_LIMIT_M = 1000.0
EXPECTED = (
    "poses (T, 72 | 156 | 165) or global_orient (T, 3) + body_pose (T, 63 | 69), trans (T, 3), betas, "
    "gender, mocap_framerate or mocap_frame_rate"
)


class SmplSequenceError(BodyfitError):
    """An SMPL-format sequence file is unreadable or malformed; the message names the field."""


@dataclass(frozen=True)
class SmplSequence:
    """poses (T, 24, 3) axis-angle of SMPL's body joints; trans (T, 3) metres; betas (K,); gender; fps;
    bad_frames (T,) True where the input held NaN / inf or implausible values (zeroed here and flagged);
    surface_model_type (as given, or "smpl"); source: the file name."""

    poses: np.ndarray
    trans: np.ndarray
    betas: np.ndarray
    gender: str
    fps: float
    bad_frames: np.ndarray
    surface_model_type: str = "smpl"
    source: str = ""

    @property
    def n_frames(self) -> int:
        return len(self.poses)


def read_smpl_sequence(
    path: str | os.PathLike[str], *, max_frames: int | None = None, max_bytes: int = DEFAULT_MAX_BYTES
) -> SmplSequence:
    """Read an AMASS-style .npz or an SMPL .pkl (a .pkl is unpickled: only for files you trust).

    Args:
        path: the file; max_frames: the most frames an .npz may declare (None: no limit); max_bytes: the
            most bytes its arrays may decompress to.
    Raises:
        FileLimitError: an .npz declaring more frames or bytes than allowed.
        SmplSequenceError: unreadable file, missing or malformed fields (named, with what was expected).
    """
    p = Path(path)
    if p.suffix == ".npz":
        return smpl_sequence(_read_amass(p, p.name, max_frames, max_bytes), p.name)
    try:
        if p.suffix == ".pkl":
            with p.open("rb") as f:
                data = pickle.load(f, encoding="latin1")
        else:
            raise SmplSequenceError(f"{p.name}: SMPL-format sequences are .npz (AMASS) or .pkl files")
    except SmplSequenceError:
        raise
    except (
        OSError,
        ValueError,
        EOFError,
        zipfile.BadZipFile,
        pickle.UnpicklingError,
        ModuleNotFoundError,
    ) as exc:
        raise SmplSequenceError(f"cannot read {p.name}: {exc}") from None
    if not isinstance(data, dict):
        raise SmplSequenceError(
            f"{p.name} holds a {type(data).__name__}; expected a dictionary with {EXPECTED}"
        )
    return smpl_sequence(data, p.name)


def read_smpl_npz(
    data: bytes,
    source: str = "upload.npz",
    *,
    max_frames: int | None = None,
    max_bytes: int = DEFAULT_MAX_BYTES,
) -> SmplSequence:
    """An AMASS-style .npz given as bytes (never unpickled, never decompressed past its checked headers:
    safe for uploads).

    Args:
        data: the file; source: its name in messages; max_frames: the most frames it may declare (None: no
            limit); max_bytes: the most bytes its arrays may decompress to.
    Raises:
        FileLimitError: more frames or bytes than allowed (from the headers).
        SmplSequenceError: not an .npz, or missing / malformed fields.
    """
    return smpl_sequence(_read_amass(data, source, max_frames, max_bytes), source)


def _read_amass(
    source: bytes | Path, name: str, max_frames: int | None, max_bytes: int
) -> dict[str, np.ndarray]:
    """The AMASS arrays of an .npz, checked from their headers: poses (T, 72 | 156 | 165) (or global_orient
    (T, 3) + body_pose (T, 63 | 69)), trans (T, 3), betas (K,) / (1, K) / (T, K) numbers; gender and
    surface_model_type short texts; the frame rate a number."""
    T = Dim("T", max_frames, "frames", "split the sequence into shorter files")
    K = Dim("K", 1000, "betas", "SMPL-family models have a few hundred betas at most")
    text = ArraySpec(((), (1,), (0,)), TEXT, required=False, max_bytes=1024, hint="numpy.array('female')")
    rate = ArraySpec(((), (1,)), NUMBER, required=False, hint="frames per second")
    specs = {
        "poses": ArraySpec(((T, 72), (T, 156), (T, 165)), NUMBER, required=False, hint="axis-angle"),
        "global_orient": ArraySpec(((T, 3),), NUMBER, required=False),
        "body_pose": ArraySpec(((T, 63), (T, 69)), NUMBER, required=False),
        "trans": ArraySpec(((T, 3),), NUMBER, required=False, hint="metres"),
        "betas": ArraySpec(((K,), (1, K), (T, K)), NUMBER, required=False),
        "gender": text,
        "surface_model_type": text,
        "mocap_framerate": rate,
        "mocap_frame_rate": rate,
        "fps": rate,
    }
    try:
        if "poses" in npz_keys(source, name="the file"):  # the split layout's arrays are then not read
            del specs["global_orient"], specs["body_pose"]
        return read_npz(source, specs, max_bytes=max_bytes, name="the file")
    except FileFormatError as exc:
        raise SmplSequenceError(f"cannot read {name}: {exc}") from None


def smpl_sequence(data: dict[str, Any], source: str = "") -> SmplSequence:
    """Validate a dictionary of SMPL-format arrays (see the module docstring)."""
    where = source or "the sequence"
    poses = _poses(data, where)
    T = len(poses)
    if T == 0:
        raise SmplSequenceError(f"{where}: poses has zero frames; send at least one frame")
    trans = _array(data, "trans", where, np.zeros((T, 3)))
    if trans.shape != (T, 3):
        raise SmplSequenceError(f"{where}: trans must have shape ({T}, 3) to match poses; got {trans.shape}")
    betas = _array(data, "betas", where, np.zeros(10))
    if betas.ndim == 2:
        if len(betas) not in (1, T):
            raise SmplSequenceError(f"{where}: betas of shape {betas.shape} match neither 1 nor {T} frames")
        betas = betas.mean(0)
    if betas.ndim != 1 or not np.isfinite(betas).all():
        raise SmplSequenceError(f"{where}: betas must be a finite (K,) vector; got shape {betas.shape}")
    if (np.abs(betas) > BETAS_LIMIT_SD).any():
        raise SmplSequenceError(
            f"{where}: betas must lie within [-{BETAS_LIMIT_SD:g}, {BETAS_LIMIT_SD:g}] (standard deviations "
            f"of SMPL's shape space); got {float(np.abs(betas).max()):.6g}: send SMPL-family betas"
        )
    gender = _text(data.get("gender", "")).strip().lower() or "neutral"  # absent or empty: neutral
    if gender not in GENDERS:
        raise SmplSequenceError(f"{where}: unknown gender {gender!r}; use one of {', '.join(GENDERS)}")
    fps = _fps(data, where)
    with np.errstate(invalid="ignore", over="ignore"):
        bad = ~(np.isfinite(poses).all(axis=(1, 2)) & np.isfinite(trans).all(axis=1))
        bad |= (np.linalg.norm(np.where(bad[:, None, None], 0.0, poses), axis=2) > POSE_LIMIT_RAD).any(axis=1)
        bad |= (np.abs(np.where(bad[:, None], 0.0, trans)) > TRANS_LIMIT_M).any(axis=1)
    if bad.all():
        raise SmplSequenceError(
            f"{where}: every frame holds NaN or infinite values, rotations longer than {POSE_LIMIT_RAD:g} "
            f"rad or a translation beyond {TRANS_LIMIT_M:g} m; poses are axis-angle radians, trans metres"
        )
    poses = np.where(bad[:, None, None], 0.0, poses)
    trans = np.where(bad[:, None], 0.0, trans)
    model_type = _text(data.get("surface_model_type", "smpl")).lower()
    return SmplSequence(poses, trans, betas, gender, fps, bad, model_type, source)


def _array(data: dict[str, Any], key: str, where: str, default: np.ndarray) -> np.ndarray:
    if key not in data:
        return default
    try:
        return np.asarray(data[key], np.float64)
    except (TypeError, ValueError):
        raise SmplSequenceError(f"{where}: {key} is not a numeric array") from None


def _poses(data: dict[str, Any], where: str) -> np.ndarray:
    if "poses" in data:
        p = _array(data, "poses", where, np.zeros((0, 72)))
        if p.ndim != 2 or p.shape[1] not in (72, 156, 165):
            raise SmplSequenceError(
                f"{where}: poses must be (T, 72) SMPL, (T, 156) SMPL-H or (T, 165) SMPL-X; got {p.shape}"
            )
        body = np.zeros((len(p), 72))
        body[:, : 72 if p.shape[1] == 72 else 66] = p[:, : 72 if p.shape[1] == 72 else 66]
        return body.reshape(len(p), 24, 3)
    if "global_orient" in data and "body_pose" in data:
        g = _array(data, "global_orient", where, np.zeros((0, 3)))
        b = _array(data, "body_pose", where, np.zeros((0, 69)))
        if g.ndim != 2 or g.shape[1] != 3 or b.ndim != 2 or b.shape[1] not in (63, 69) or len(g) != len(b):
            raise SmplSequenceError(
                f"{where}: global_orient must be (T, 3) and body_pose (T, 63 | 69); got {g.shape}, {b.shape}"
            )
        body = np.zeros((len(g), 72))
        body[:, :3], body[:, 3 : 3 + b.shape[1]] = g, b
        return body.reshape(len(g), 24, 3)
    found = ", ".join(sorted(data)) or "nothing"
    raise SmplSequenceError(f"{where} holds {found}; expected {EXPECTED}")


def _fps(data: dict[str, Any], where: str) -> float:
    for key in ("mocap_framerate", "mocap_frame_rate", "fps"):
        if key in data:
            try:
                fps = float(np.asarray(data[key]).reshape(-1)[0])
            except (TypeError, ValueError, IndexError):
                raise SmplSequenceError(f"{where}: {key} is not a number") from None
            if not np.isfinite(fps) or fps <= 0:
                raise SmplSequenceError(
                    f"{where}: {key} must be a positive number of frames per second; got {fps}"
                )
            return fps
    raise SmplSequenceError(f"{where}: no frame rate; add mocap_framerate (frames per second)")


def _text(value: Any) -> str:
    a = np.asarray(value)
    if a.size == 0:
        return ""
    if a.dtype.kind == "S":
        return bytes(a.reshape(-1)[0]).decode(errors="replace")
    return str(a.reshape(-1)[0]) if a.size else ""

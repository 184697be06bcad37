"""Checks that an SMPL-format sequence's poses are SMPL's axis-angle radians, with messages that say what was
found instead: rotation matrices, quaternions or 6D rotations (recognised from the array's shape), or
degrees (recognised from the rotations' lengths).

The layouts are SMPL's (M. Loper, N. Mahmood, J. Romero, G. Pons-Moll and M. J. Black, "SMPL: A Skinned
Multi-Person Linear Model", ACM Transactions on Graphics 34(6), 2015: one axis-angle vector per joint) as
AMASS distributes them (N. Mahmood, N. Ghorbani, N. F. Troje, G. Pons-Moll and M. J. Black, "AMASS: Archive
of Motion Capture as Surface Shapes", ICCV 2019); the 6D representation is that of Y. Zhou, C. Barnes, J. Lu,
J. Yang and H. Li, "On the Continuity of Rotation Representations in Neural Networks", CVPR 2019.
"""

from __future__ import annotations

import io
import os
import zipfile
from pathlib import Path

import numpy as np

from bodyfit.io.smpl import SmplSequence, SmplSequenceError, read_smpl_sequence

DEGREE_LIKE_RAD = np.pi  # body joints' median rotation beyond this: degrees, not radians
BODY_JOINTS = slice(1, 22)  # SMPL's body joints without the root (hands are often zero)
JOINT_COUNTS = (21, 22, 23, 24, 52, 55)  # body without or with the root, SMPL, SMPL-H, SMPL-X
LAYOUTS = ((9, "rotation matrices (3 x 3 per joint)"), (6, "6D rotations"), (4, "quaternions"))
EXPECTED_LAYOUT = (
    "expected axis-angle in radians, 3 values per joint: poses (T, 72) SMPL, (T, 156) SMPL-H or "
    "(T, 165) SMPL-X"
)


def check_axis_angle(sequence: SmplSequence) -> None:
    """Refuse poses that are not axis-angle radians: in degrees, a body joint's rotation is far beyond half a
    turn (a walk's joints turn by well under 90 degrees, about 1.5 rad), so the median length over the good
    frames' moved body joints tells them apart.

    Raises:
        SmplSequenceError: naming what was found and what is expected.
    """
    good = sequence.poses[~sequence.bad_frames, BODY_JOINTS]
    norms = np.linalg.norm(good, axis=-1)
    moved = norms[norms > 1e-9]
    median = float(np.median(moved)) if len(moved) else 0.0
    if median > DEGREE_LIKE_RAD:
        where = sequence.source or "the sequence"
        raise SmplSequenceError(
            f"{where}: the body joints' rotations have a median length of {median:.1f}, more than half a "
            f"turn: they look like degrees; {EXPECTED_LAYOUT}"
        )


def pose_layout(shape: tuple[int, ...]) -> str | None:
    """What a ``poses`` array of ``shape`` holds when it is not axis-angle: rotation matrices, 6D rotations
    or quaternions for one of :data:`JOINT_COUNTS` joints (None: not recognised, or axis-angle)."""
    if len(shape) == 4 and shape[2:] == (3, 3):
        return LAYOUTS[0][1]
    if len(shape) < 2 or (len(shape) == 2 and shape[1] in (72, 156, 165)):
        return None
    per_frame = int(np.prod(shape[1:]))
    for width, name in LAYOUTS:
        if (len(shape) == 3 and shape[2] == width) or any(per_frame == width * n for n in JOINT_COUNTS):
            return name
    return None


def npz_poses_shape(source: bytes | Path) -> tuple[int, ...] | None:
    """The shape of an .npz's ``poses`` from its .npy header alone (None: no readable ``poses``)."""
    try:
        archive = zipfile.ZipFile(io.BytesIO(source) if isinstance(source, bytes) else source)
        with archive as zf, zf.open("poses.npy") as f:
            version = np.lib.format.read_magic(f)
            header = np.lib.format.read_array_header_1_0 if version == (1, 0) else None
            shape, _, _ = (header or np.lib.format.read_array_header_2_0)(f)
    except (OSError, KeyError, ValueError, zipfile.BadZipFile, RuntimeError, NotImplementedError):
        return None  # unreadable here (encrypted, unknown compression...): the reader's own error stands
    return tuple(int(n) for n in shape)


def layout_error(source: bytes | Path, where: str) -> SmplSequenceError | None:
    """The error naming the layout of an .npz whose ``poses`` are rotation matrices, quaternions or 6D
    rotations, and the expected one; None when its poses are not recognised as such."""
    shape = npz_poses_shape(source)
    layout = None if shape is None else pose_layout(shape)
    if layout is None:
        return None
    return SmplSequenceError(
        f"{where}: poses of shape {shape} look like {layout}; {EXPECTED_LAYOUT} (scipy's Rotation.as_rotvec "
        "converts)"
    )


def read_sequence(path: str | os.PathLike[str], **limits: int | None) -> SmplSequence:
    """:func:`bodyfit.io.smpl.read_smpl_sequence` (``limits``: its max_frames / max_bytes), then the checks
    of this module: poses in another rotation layout, or in degrees, are refused naming the expected one.

    Raises:
        SmplSequenceError: as the reader, or naming the layout found and the one expected.
        FileLimitError: as the reader.
    """
    p = Path(path)
    try:
        sequence = read_smpl_sequence(p, **limits)  # type: ignore[arg-type]
    except SmplSequenceError:
        error = layout_error(p, p.name) if p.suffix == ".npz" else None
        if error is not None:
            raise error from None
        raise
    check_axis_angle(sequence)
    return sequence

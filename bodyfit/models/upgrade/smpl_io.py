"""Deprecated: moved to :mod:`bodyfit.io.smpl`;
this path will be removed in the next release. Its public names are re-exported from there.
"""

from bodyfit.io.smpl import (
    BETAS_LIMIT_SD,
    EXPECTED,
    GENDERS,
    POSE_LIMIT_RAD,
    TRANS_LIMIT_M,
    SmplSequence,
    SmplSequenceError,
    read_smpl_npz,
    read_smpl_sequence,
    smpl_sequence,
)

__all__ = [
    "BETAS_LIMIT_SD",
    "EXPECTED",
    "GENDERS",
    "POSE_LIMIT_RAD",
    "TRANS_LIMIT_M",
    "SmplSequence",
    "SmplSequenceError",
    "read_smpl_npz",
    "read_smpl_sequence",
    "smpl_sequence",
]

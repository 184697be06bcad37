"""Deprecated: moved to :mod:`bodyfit.io.pcd`;
this path will be removed in the next release. Its public names are re-exported from there.
"""

from bodyfit.io.pcd import (
    LZF_MAX_RATIO,
    THIN,
    lzf_decompress,
    read_pcd,
)

__all__ = [
    "LZF_MAX_RATIO",
    "THIN",
    "lzf_decompress",
    "read_pcd",
]

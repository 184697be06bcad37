"""What `bodyfit fit` without a kind takes each file for, and the messages for a wrong or mixed kind."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bodyfit.cli.fit.kinds import detect_kind, single_kind, wrong_kind


@pytest.mark.parametrize(
    ("name", "arrays", "kind"),
    [
        ("walk.trc", None, "markers"),
        ("WALK.C3D", None, "markers"),
        ("scan.ply", None, "scan"),
        ("cloud.pcd", None, "scan"),
        ("seq.npz", {"frames": np.zeros((2, 4, 3))}, "sequence"),
        ("seq_w.npz", {"frames": np.zeros((2, 4, 3)), "weights": np.ones((2, 4))}, "sequence"),
        ("points.npz", {"points": np.zeros((4, 3))}, "scan"),
        ("both.npz", {"frames": np.zeros((2, 4, 3)), "vertices": np.zeros((4, 3))}, "scan"),
        ("broken.npz", b"not a zip", "scan"),
    ],
)
def test_the_kind_of_a_file(tmp_path: Path, name: str, arrays: object, kind: str) -> None:
    path = tmp_path / name
    if isinstance(arrays, dict):
        np.savez(path, **arrays)
    else:
        path.write_bytes(arrays if isinstance(arrays, bytes) else b"")
    assert detect_kind(path) == kind


def test_wrong_and_mixed_kinds_are_explained(tmp_path: Path) -> None:
    np.savez(tmp_path / "seq.npz", frames=np.zeros((2, 4, 3)))
    trc, ply, seq = tmp_path / "a.trc", tmp_path / "b.ply", tmp_path / "seq.npz"
    assert wrong_kind([trc, tmp_path / "c.c3d"], "markers") is None
    message = wrong_kind([trc, ply], "markers")
    assert message is not None and message.startswith(f"{ply} is a mesh or scan")
    assert f"`bodyfit fit scan {ply}`" in message
    assert single_kind([trc, tmp_path / "c.c3d"]) == ("markers", "")
    kind, mixed = single_kind([seq, trc, ply])
    assert kind is None
    assert "sequences: seq.npz; marker trials: a.trc; meshes or scans: b.ply" in mixed

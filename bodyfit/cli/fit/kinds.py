"""Which kind of input a file is, for ``bodyfit fit FILE...`` without a kind, and the message that says
what to run instead when a file is given to the wrong kind."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Literal

from bodyfit.cli.fit.markers import is_marker_file
from bodyfit.cli.fit.sequence import SEQUENCE_KEY, is_sequence_file

Kind = Literal["scan", "markers", "sequence"]

KINDS: tuple[Kind, ...] = ("scan", "markers", "sequence")
DESCRIPTION: dict[Kind, str] = {
    "scan": "a mesh or scan (.ply, .obj, .stl, .pcd, or an .npz of points or vertices)",
    "markers": "a motion-capture marker trial (.trc, .c3d)",
    "sequence": f"a registered sequence (an .npz holding {SEQUENCE_KEY} (T, 13348, 3))",
}
PLURAL: dict[Kind, str] = {"scan": "meshes or scans", "markers": "marker trials", "sequence": "sequences"}


def detect_kind(path: Path) -> Kind:
    """``markers`` by the suffix (.trc, .c3d); ``sequence`` for an .npz holding ``frames`` and neither
    ``points`` nor ``vertices``; ``scan`` for anything else (its reader then says what is wrong with it)."""
    if is_marker_file(path):
        return "markers"
    if is_sequence_file(path):
        return "sequence"
    return "scan"


def wrong_kind(paths: Sequence[Path], expected: Kind) -> str | None:
    """None when every path is of the ``expected`` kind; else what the first other one is and the command
    that fits it."""
    for path in paths:
        kind = detect_kind(path)
        if kind != expected:
            return (
                f"{path} is {DESCRIPTION[kind]}, not {DESCRIPTION[expected]}; fit it with "
                f"`bodyfit fit {kind} {path}`, or `bodyfit fit {path}`, which detects the kind"
            )
    return None


def single_kind(paths: Sequence[Path]) -> tuple[Kind | None, str]:
    """The kind shared by every path, or None and a message naming each kind found and the commands that fit
    them in separate runs."""
    found: dict[Kind, list[str]] = {}
    for path in paths:
        found.setdefault(detect_kind(path), []).append(path.name)
    if len(found) == 1:
        return next(iter(found)), ""
    listed = "; ".join(f"{PLURAL[kind]}: {', '.join(names)}" for kind, names in found.items())
    commands = ", ".join(f"`bodyfit fit {kind} FILE...`" for kind in found)
    return None, f"the inputs are of different kinds ({listed}); fit each kind in a separate run: {commands}"

"""BVH motion files (Biovision hierarchy): skeleton, channels, frames, and world joint poses by FK.

A BVH file has no units and no declared axes. :func:`read_bvh` takes ``units`` (metres per file unit) and
``rotation`` (file axes to ours, see :func:`~bodyfit.io.mocap.lab_rotation`); the defaults
suit the common convention of a Y-up file whose character faces +Z at rest (the CMU database's BVH
conversions among them), mapped to our world (+Y up, +X forward, +Z right). CMU files are in their ASF
unit of 1/0.45 inch: pass ``units=CMU_UNITS``.

Rotation channels compose in the order they are listed, as rotations about the joint's parent-aligned
axes: ``CHANNELS 3 Zrotation Xrotation Yrotation`` means ``R = Rz Rx Ry``. Values are degrees. Position
channels give the joint's translation from its parent and replace the OFFSET on their axes (the OFFSET is
the rest value), as Blender's importer and bvhio read them: exporters that write the root's first-frame
position as its OFFSET (LAFAN1-style files) would otherwise place it twice as far.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bodyfit.io.mocap import MocapFormatError, lab_rotation

CMU_UNITS = 0.0254 / 0.45  # metres per unit of the CMU database's skeletons (ASF length unit 0.45 inch)
CHANNELS = ("Xposition", "Yposition", "Zposition", "Xrotation", "Yrotation", "Zrotation")
_AXIS = {"X": 0, "Y": 1, "Z": 2}


@dataclass(frozen=True)
class BvhJoint:
    """One joint: name, parent index (-1 for the root), offset from the parent (file units, file axes),
    channel names in file order, and the end-site offset when the joint ends a chain (else None)."""

    name: str
    parent: int
    offset: np.ndarray
    channels: tuple[str, ...]
    end_site: np.ndarray | None = None


@dataclass(frozen=True)
class BvhMotion:
    """A parsed BVH file.

    Attributes:
        joints: in file order (parents before children).
        values: (T, n_channels) the motion block as written (file units and degrees).
        frame_time: seconds per frame.
        units: metres per file unit (applied by :meth:`world`).
        rotation: (3, 3) file axes to ours (applied by :meth:`world`).
        source: file name, for messages.
    """

    joints: tuple[BvhJoint, ...]
    values: np.ndarray
    frame_time: float
    units: float = 1.0
    rotation: np.ndarray | None = None
    source: str = "BVH"

    @property
    def names(self) -> list[str]:
        return [j.name for j in self.joints]

    @property
    def n_frames(self) -> int:
        return int(self.values.shape[0])

    @property
    def rate(self) -> float:
        """Frames per second."""
        return 1.0 / self.frame_time

    def index(self, name: str) -> int:
        """Joint index by name; raises :class:`MocapFormatError` naming the joints when absent."""
        names = self.names
        if name not in names:
            raise MocapFormatError(f"{self.source} has no joint {name!r}; joints: {', '.join(names)}")
        return names.index(name)

    def local(self) -> tuple[np.ndarray, np.ndarray]:
        """Per-frame joint rotations (T, J, 3, 3) and translations (T, J, 3) relative to the parent, file
        axes and units (a position channel replaces the OFFSET on its axis)."""
        T, J = self.n_frames, len(self.joints)
        R = np.broadcast_to(np.eye(3), (T, J, 3, 3)).copy()
        t = np.zeros((T, J, 3))
        col = 0
        for j, joint in enumerate(self.joints):
            t[:, j] = joint.offset
            for name in joint.channels:
                v = self.values[:, col]
                col += 1
                axis = _AXIS[name[0]]
                if name.endswith("position"):
                    t[:, j, axis] = v
                else:
                    R[:, j] = R[:, j] @ _axis_rotation(axis, np.radians(v))
        return R, t

    def world(self, end_sites: bool = False) -> tuple[np.ndarray, np.ndarray, list[str]]:
        """World joint poses by forward kinematics, in metres and our axes.

        Args:
            end_sites: also return the end sites (as ``<joint>_end``, rotation of their joint).
        Returns:
            positions (T, J', 3), rotations (T, J', 3, 3) mapping the joint's file-frame axes to our world
            (at the rest pose every rotation is ``self.rotation``), and the names.
        """
        R_loc, t_loc = self.local()
        R = np.empty_like(R_loc)
        p = np.empty_like(t_loc)
        for j, joint in enumerate(self.joints):
            if joint.parent < 0:
                R[:, j], p[:, j] = R_loc[:, j], t_loc[:, j]
            else:
                Rp = R[:, joint.parent]
                R[:, j] = Rp @ R_loc[:, j]
                p[:, j] = p[:, joint.parent] + np.einsum("tij,tj->ti", Rp, t_loc[:, j])
        names = self.names
        if end_sites:
            extra = [(j, jt.end_site) for j, jt in enumerate(self.joints) if jt.end_site is not None]
            p_end = [p[:, j] + np.einsum("tij,j->ti", R[:, j], off) for j, off in extra]
            if extra:
                p = np.concatenate([p, np.stack(p_end, axis=1)], axis=1)
                R = np.concatenate([R, R[:, [j for j, _ in extra]]], axis=1)
                names = names + [self.joints[j].name + "_end" for j, _ in extra]
        M = np.eye(3) if self.rotation is None else self.rotation
        return np.einsum("ij,tkj->tki", M, p) * self.units, M @ R, names


def _axis_rotation(axis: int, angle: np.ndarray) -> np.ndarray:
    """(T, 3, 3) rotations by ``angle`` (T,) radians about coordinate axis ``axis``."""
    c, s = np.cos(angle), np.sin(angle)
    R = np.zeros((*angle.shape, 3, 3))
    i, k = (axis + 1) % 3, (axis + 2) % 3
    R[..., axis, axis] = 1.0
    R[..., i, i] = c
    R[..., k, k] = c
    R[..., k, i] = s
    R[..., i, k] = -s
    return R


class _Tokens:
    """Whitespace tokens with their line numbers, for error messages."""

    def __init__(self, lines: list[str], source: str) -> None:
        self.items = [(tok, n + 1) for n, line in enumerate(lines) for tok in line.split()]
        self.pos = 0
        self.source = source

    def error(self, message: str) -> MocapFormatError:
        line = self.items[min(self.pos, len(self.items) - 1)][1] if self.items else 0
        return MocapFormatError(f"{self.source} line {line}: {message}")

    def next(self, what: str) -> str:
        if self.pos >= len(self.items):
            raise MocapFormatError(f"{self.source}: file ends where {what} was expected")
        tok = self.items[self.pos][0]
        self.pos += 1
        return tok

    def expect(self, word: str) -> None:
        tok = self.next(repr(word))
        if tok.upper() != word.upper():
            self.pos -= 1
            raise self.error(f"expected {word!r}, found {tok!r}")

    def number(self, what: str) -> float:
        tok = self.next(what)
        try:
            value = float(tok)
        except ValueError:
            self.pos -= 1
            raise self.error(f"expected a number for {what}, found {tok!r}") from None
        if not np.isfinite(value):
            self.pos -= 1
            raise self.error(f"{what} is not finite ({tok})")
        return value


def _parse_joint(tok: _Tokens, name: str, parent: int, joints: list[BvhJoint]) -> None:
    tok.expect("{")
    tok.expect("OFFSET")
    offset = np.array([tok.number(f"{name}'s offset") for _ in range(3)])
    channels: tuple[str, ...] = ()
    if tok.pos < len(tok.items) and tok.items[tok.pos][0].upper() == "CHANNELS":
        tok.next("CHANNELS")
        count = tok.number(f"{name}'s channel count")
        if count != int(count) or not 0 <= count <= 6:
            raise tok.error(f"{name}: channel count must be 0 to 6, found {count:g}")
        channels = tuple(tok.next(f"{name}'s channels") for _ in range(int(count)))
        bad = [c for c in channels if c not in CHANNELS]
        if bad:
            raise tok.error(f"{name}: unknown channel {bad[0]!r}; channels are {', '.join(CHANNELS)}")
        if len(set(channels)) != len(channels):
            raise tok.error(f"{name}: a channel is listed twice ({' '.join(channels)})")
    index = len(joints)
    joints.append(BvhJoint(name, parent, offset, channels))
    while True:
        word = tok.next(f"a JOINT, End Site or '}}' inside {name}")
        key = word.upper()
        if key == "}":
            return
        if key == "JOINT":
            _parse_joint(tok, tok.next("a joint name"), index, joints)
        elif key == "END":
            tok.expect("Site")
            tok.expect("{")
            tok.expect("OFFSET")
            end = np.array([tok.number(f"{name}'s end site") for _ in range(3)])
            tok.expect("}")
            joints[index] = BvhJoint(name, parent, offset, channels, end)
        else:
            tok.pos -= 1
            raise tok.error(f"expected JOINT, End Site or '}}' inside {name}, found {word!r}")


def parse_bvh(
    text: str, units: float = 1.0, rotation: np.ndarray | None = None, source: str = "BVH"
) -> BvhMotion:
    """Parse the text of a BVH file.

    Args:
        text: the whole file.
        units: metres per file unit (``CMU_UNITS`` for the CMU database).
        rotation: (3, 3) file axes to ours; default: file Y up, character facing +Z (``lab_rotation("y",
            "z")``). Pass ``np.eye(3)`` to keep the file's axes.
        source: name used in messages.
    Raises:
        MocapFormatError: malformed hierarchy or motion block, with the line.
    """
    M = _checked_rotation(units, rotation)
    lines = text.splitlines()
    split = next((n for n, line in enumerate(lines) if line.strip().upper() == "MOTION"), None)
    if split is None:
        raise MocapFormatError(f"{source}: no MOTION section; is this a BVH file?")
    joints = _parse_hierarchy(lines[:split], source)
    n_frames, frame_time = _parse_motion_header(lines, split, source)
    values = _parse_frames(lines, split, n_frames, sum(len(j.channels) for j in joints), source)
    return BvhMotion(tuple(joints), values, frame_time, units, M, source)


def _checked_rotation(units: float, rotation: np.ndarray | None) -> np.ndarray:
    """Returns the (3, 3) rotation from file axes to ours (default: Y up, facing +Z), after checking
    ``units`` and that the rotation is proper."""
    if not (np.isfinite(units) and units > 0):
        raise MocapFormatError(f"units must be a positive number of metres per file unit; got {units}")
    M = lab_rotation("y", "z") if rotation is None else np.asarray(rotation, np.float64)
    if M.shape != (3, 3) or not np.allclose(M @ M.T, np.eye(3), atol=1e-6) or np.linalg.det(M) < 0:
        raise MocapFormatError("rotation must be a proper 3x3 rotation (file axes to ours)")
    return M


def _parse_hierarchy(lines: list[str], source: str) -> list[BvhJoint]:
    """Returns the joints of the HIERARCHY block (the lines before MOTION), parents before children,
    with unique names."""
    tok = _Tokens(lines, source)
    tok.expect("HIERARCHY")
    tok.expect("ROOT")
    joints: list[BvhJoint] = []
    _parse_joint(tok, tok.next("the root's name"), -1, joints)
    if tok.pos != len(tok.items):
        raise tok.error(f"unexpected {tok.items[tok.pos][0]!r} after the hierarchy (one ROOT supported)")
    names = [j.name for j in joints]
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise MocapFormatError(f"{source}: joint names must be unique; repeated: {', '.join(dup)}")
    return joints


def _parse_motion_header(lines: list[str], split: int, source: str) -> tuple[float, float]:
    """Returns the frame count (a whole number >= 0, as a float) and the frame time in seconds (> 0)
    from the two lines after MOTION (line index ``split``)."""
    header = _Tokens(lines[split + 1 : split + 3], source)
    header.items = [(t, n + split + 2) for t, n in header.items]
    header.expect("Frames:")
    n_frames = header.number("the frame count")
    header.expect("Frame")
    header.expect("Time:")
    frame_time = header.number("the frame time")
    if n_frames != int(n_frames) or n_frames < 0:
        raise MocapFormatError(f"{source}: frame count must be a whole number >= 0; got {n_frames:g}")
    if frame_time <= 0:
        raise MocapFormatError(f"{source}: frame time must be positive seconds; got {frame_time:g}")
    return n_frames, frame_time


def _parse_frames(lines: list[str], split: int, n_frames: float, n_channels: int, source: str) -> np.ndarray:
    """Returns the (n_frames, n_channels) finite channel values from the non-blank lines after the
    MOTION header."""
    rows = [line for line in lines[split + 3 :] if line.strip()]
    if len(rows) != int(n_frames):
        raise MocapFormatError(f"{source}: header says {int(n_frames)} frames but {len(rows)} follow")
    values = np.empty((len(rows), n_channels))
    for k, row in enumerate(rows):
        fields = row.split()
        if len(fields) != n_channels:
            raise MocapFormatError(
                f"{source} line {split + 4 + k}: {len(fields)} values, the hierarchy has "
                f"{n_channels} channels"
            )
        try:
            values[k] = [float(f) for f in fields]
        except ValueError:
            raise MocapFormatError(f"{source} line {split + 4 + k}: a value is not a number") from None
    if not np.isfinite(values).all():
        k = int(np.flatnonzero(~np.isfinite(values).all(axis=1))[0])
        raise MocapFormatError(f"{source} frame {k}: values must be finite")
    return values


def read_bvh(path: str | Path, units: float = 1.0, rotation: np.ndarray | None = None) -> BvhMotion:
    """Read a BVH file. See :func:`parse_bvh`."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise MocapFormatError(f"cannot read {p}: {exc.strerror}") from exc
    return parse_bvh(text, units, rotation, p.name)

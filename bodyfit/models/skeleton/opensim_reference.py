"""OpenSim as the reference for our kinematics (tests and benchmarks; needs the `build` extra).

Setting coordinates the exact way: locked coordinates silently ignore ``setValue``, so every coordinate is
unlocked and unclamped before the system is built; coupled ``*_beta`` coordinates get their independent
coordinate's value; constraints are not enforced (``realizePosition`` never moves coordinates).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np


class OpenSimReference:
    """An OpenSim model ready for forward kinematics of named coordinates."""

    def __init__(self, osim_path: str | Path, scales: dict[str, np.ndarray] | None = None) -> None:
        import opensim

        self.osim = opensim
        self.model = opensim.Model(str(osim_path))
        for c in self.model.getCoordinateSet():
            c.setDefaultLocked(False)
            c.setDefaultClamped(False)
        self.state = self.model.initSystem()
        if scales:
            scale_set = opensim.ScaleSet()
            for name, factors in scales.items():
                sc = opensim.Scale()
                sc.setSegmentName(name)
                sc.setScaleFactors(opensim.Vec3(*(float(v) for v in factors)))
                sc.setApply(True)
                scale_set.cloneAndAppend(sc)
            self.model.scale(self.state, scale_set, False)
            self.state = self.model.initSystem()
        self._coords = self.model.getCoordinateSet()
        self._bodies = self.model.getBodySet()
        names = [self._coords.get(i).getName() for i in range(self._coords.getSize())]
        self.coordinate_names = names
        self._rotational = {
            n: self._coords.get(n).getMotionType() == opensim.Coordinate.Rotational for n in names
        }

    def set_coordinates(self, values: dict[str, float], degrees: bool = False) -> None:
        """Set coordinates by name (rotations in radians unless ``degrees``); ``*_beta`` twins follow."""
        for name, v in values.items():
            value = float(np.radians(v)) if degrees and self._rotational[name] else float(v)
            self._coords.get(name).setValue(self.state, value, False)
            twin = f"{name}_beta"
            if self._coords.contains(twin):
                self._coords.get(twin).setValue(self.state, value, False)
        self.model.realizePosition(self.state)

    def body_frame(self, name: str) -> np.ndarray:
        """(4, 4) transform of body ``name`` in ground at the current state."""
        T: Any = self._bodies.get(name).getTransformInGround(self.state)
        out = np.eye(4)
        out[:3, 3] = [T.p().get(k) for k in range(3)]
        out[:3, :3] = [[T.R().get(a, b) for b in range(3)] for a in range(3)]
        return out

    def body_frames(self, names: list[str]) -> np.ndarray:
        """(n, 4, 4) transforms of the named bodies."""
        return np.stack([self.body_frame(n) for n in names])


def pose_values(names: list[str], q: np.ndarray, root_names: list[str], root: np.ndarray) -> dict[str, float]:
    """One frame's coordinates as a name -> value dict (q and root in radians / metres)."""
    return {**dict(zip(names, map(float, q))), **dict(zip(root_names, map(float, root)))}

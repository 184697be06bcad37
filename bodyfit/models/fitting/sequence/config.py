"""How a registered-mesh sequence is fitted (:class:`.fitter.SequenceFitter`): the settings and the pose
stages of its keyframes and of every frame."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bodyfit.models.fitting.registered.stages import Stage, check_at_least
from bodyfit.models.fitting.sequence.basins import BasinCheck
from bodyfit.models.fitting.sequence.offsets import OffsetConfig

KEY_STAGES = (Stage(name="key_pose", coordinates="all", shape="none", vertices="subset", iterations=40),)
FRAME_STAGES = (Stage(name="pose", coordinates="all", shape="none", vertices="subset", iterations=24),)
PELVIS_WEIGHT = 0.5  # skinning weight above which a vertex belongs to the pelvis, for the heading
FRAME_BASINS = BasinCheck()
# Pose keyframes are ``stride`` frames apart, over which real motion turns a joint by tens of degrees: only a
# change beyond that is questioned.
KEY_BASINS = BasinCheck(jump=float(np.radians(30.0)), rounds=2)
# Coordinates the basin check leaves out: the distal ones (the forearm's twist, the wrist's, the foot's
# subtalar and toe joints) move few vertices, so their fits wander by more than the check's jump from frame to
# frame without a change of basin, and a basin change there moves little skin.
BASIN_FREE = ("pro_sup_", "wrist_", "subtalar_", "mtp_")


@dataclass(frozen=True, kw_only=True)
class SequenceConfig:
    """keyframes: frames (spread evenly) the shape is fitted on; stride: frames between pose keyframes;
    chunk: frames fitted together, and the size of the blocks a fit streams (memory only: frames are
    independent given the keyframes);
    pose_subset: vertices of the farthest-point subset the pose stages ("subset") fit;
    key_stages / frame_stages: pose-only stages (shape "none") for pose keyframes and for every frame;
    blend: weight b of the centred three-frame blend of the joint coordinates (all but the pelvis's) after
    the per-frame fits, ``q[t] <- (1 - 2 b) q[t] + b (q[t-1] + q[t+1])``: symmetric in time, so it adds
    no lag; a convex combination, so it stays within the limits; 0 turns it off;
    offsets: fit the person's rest-pose offsets (:mod:`.offsets`: surface detail
    beyond the shape space) on the shape keyframes and fit every pose with them; None: shape space only;
    workers: threads a chunk's pose fits are split over (frames are independent problems);
    key_basins / basins: the check that neighbouring pose keyframes / frames sit in one basin of the pose fit
    (:mod:`.basins`: a pair that jumps is re-solved, each frame from the other's pose); None turns it off;
    basin_free: prefixes of the coordinates the check leaves out (:data:`BASIN_FREE`);
    start_margin: every pose fit starts at least this fraction of each coordinate's range inside its limits:
    the bounded mapping is flat at a limit, so a fit started there stays there whatever the input says, while
    from the margin a coordinate the input pushes to its limit still gets there.

    Raises:
        ValueError: a count below one, a blend outside [0, 0.5), or a pose stage that fits the shape (the
            message names the field).
    """

    keyframes: int = 8
    stride: int = 8
    chunk: int = 256
    pose_subset: int = 400
    key_stages: tuple[Stage, ...] = KEY_STAGES
    frame_stages: tuple[Stage, ...] = FRAME_STAGES
    blend: float = 0.02
    offsets: OffsetConfig | None = None
    workers: int = 2
    key_basins: BasinCheck | None = KEY_BASINS
    basins: BasinCheck | None = FRAME_BASINS
    basin_free: tuple[str, ...] = BASIN_FREE
    start_margin: float = 0.03

    def __post_init__(self) -> None:
        for stage in (*self.key_stages, *self.frame_stages):
            if stage.shape != "none":
                raise ValueError(
                    f"sequence pose stages keep the shape frozen; stage {stage.name!r} fits it "
                    f"(SequenceConfig.key_stages and frame_stages need shape='none')"
                )
        for name in ("keyframes", "stride", "chunk", "pose_subset", "workers"):
            check_at_least("SequenceConfig", name, getattr(self, name), 1)
        if not 0.0 <= self.blend < 0.5:
            raise ValueError(f"SequenceConfig.blend must be in [0, 0.5); got {self.blend!r}")
        if not 0.0 <= self.start_margin < 0.5:
            raise ValueError(f"SequenceConfig.start_margin must be in [0, 0.5); got {self.start_margin!r}")

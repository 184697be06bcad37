"""How a registered-mesh sequence is fitted (:class:`.fitter.SequenceFitter`): the settings and the pose
stages of its keyframes and of every frame."""

from __future__ import annotations

from dataclasses import dataclass

from bodyfit.models.fitting.registered.stages import Stage, check_at_least
from bodyfit.models.fitting.sequence.offsets import OffsetConfig

KEY_STAGES = (Stage(name="key_pose", coordinates="all", shape="none", vertices="subset", iterations=40),)
FRAME_STAGES = (Stage(name="pose", coordinates="all", shape="none", vertices="subset", iterations=24),)
PELVIS_WEIGHT = 0.5  # skinning weight above which a vertex belongs to the pelvis, for the heading


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
    workers: threads a chunk's pose fits are split over (frames are independent problems).

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

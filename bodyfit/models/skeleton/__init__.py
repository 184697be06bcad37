"""The biomechanical skeleton: Rajagopal2015 (OpenSim-exact) plus spine and scapula joints."""

from bodyfit.models.skeleton.kinematics import Pose, SkeletonKinematics
from bodyfit.models.skeleton.model import Skeleton
from bodyfit.models.skeleton.spec import SkeletonSpec

__all__ = ["Pose", "Skeleton", "SkeletonKinematics", "SkeletonSpec"]

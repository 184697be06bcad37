"""The biomechanical skeleton: Rajagopal2015 (OpenSim-exact) plus spine and scapula joints.

Rajagopal2015 is the full-body model of A. Rajagopal, C. L. Dembia, M. S. DeMers, D. D. Delp, J. L. Hicks and
S. L. Delp, "Full-Body Musculoskeletal Model for Muscle-Driven Simulation of Human Gait", IEEE Transactions on
Biomedical Engineering 63(10), 2016. The added spine and scapula joints follow M. Keller, K. Werling, S. Shin,
S. Delp, S. Pujades, C. K. Liu and M. J. Black, "From Skin to Skeleton: Towards Biomechanically Accurate 3D
Digital Humans" (SKEL), ACM Transactions on Graphics 42(6) (SIGGRAPH Asia), 2023.
"""

from bodyfit.models.skeleton.kinematics import Pose, SkeletonKinematics
from bodyfit.models.skeleton.model import Skeleton
from bodyfit.models.skeleton.spec import SkeletonSpec

__all__ = ["Pose", "Skeleton", "SkeletonKinematics", "SkeletonSpec"]

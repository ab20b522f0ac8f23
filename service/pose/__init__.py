"""Pose sets from object-scope keypoint sets (PURSE, Yang & Pavone, CVPR 2023): membership,
an estimate inside the set, and bounds on the pose error."""

from .bounds import InnerBound
from .camera import as_camera_matrix, camera_matrix_problems
from .membership import Membership, Pose, membership, pose_in_set
from .pose_sets import (
    PoseCheck,
    PoseOptions,
    PoseSets,
    check_pose_request,
    estimate_pose_sets,
    instance_pose_sets,
)
from .relaxation import OuterBound, relaxation_available

__all__ = [
    "InnerBound",
    "Membership",
    "OuterBound",
    "Pose",
    "PoseCheck",
    "PoseOptions",
    "PoseSets",
    "as_camera_matrix",
    "camera_matrix_problems",
    "check_pose_request",
    "estimate_pose_sets",
    "instance_pose_sets",
    "membership",
    "pose_in_set",
    "relaxation_available",
]

"""Pose sets from object-scope keypoint sets (PURSE, Yang & Pavone, CVPR 2023): membership,
an estimate inside the set, and bounds on the pose error."""

from .camera import as_camera_matrix, camera_matrix_problems
from .membership import Pose, membership, pose_in_set
from .pose_sets import (
    PoseOptions,
    PoseSets,
    check_pose_request,
    estimate_pose_sets,
    instance_pose_sets,
)

__all__ = [
    "Pose",
    "PoseOptions",
    "PoseSets",
    "as_camera_matrix",
    "camera_matrix_problems",
    "check_pose_request",
    "estimate_pose_sets",
    "instance_pose_sets",
    "membership",
    "pose_in_set",
]

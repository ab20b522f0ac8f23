"""Conformal keypoint service: keypoint prediction sets with a coverage guarantee."""

__version__ = "0.1.0"

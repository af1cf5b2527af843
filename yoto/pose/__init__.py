"""The pose stage: a contact pair and an object model in, T_world_object out."""

from yoto.pose.pipeline import PoseEstimate, estimate_pose

__all__ = ["PoseEstimate", "estimate_pose"]

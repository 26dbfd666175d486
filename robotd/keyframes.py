"""Keyframe selection: which floor frames the map keeps (no I/O).

A frame becomes a keyframe when the robot has moved ``distance_m`` or turned
``rotation_rad`` since the last keyframe, judged on the fused odometry at the frame's
stamp (paper 003 Sec. IV: consecutive keyframes overlap enough for visual odometry and a
revisit overlaps some keyframe by J >= r).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from robotd.base.geometry import between_floats as relative_pose


@dataclass
class KeyframeSelector:
    """Chooses keyframes by distance or rotation travelled since the last one."""

    distance_m: float
    rotation_rad: float
    last_pose: np.ndarray | None = None

    def offer(self, pose_xyyaw: np.ndarray) -> bool:
        """True (and remember the pose) when ``pose_xyyaw`` should become a keyframe."""
        if self.last_pose is None:
            self.last_pose = pose_xyyaw.copy()
            return True
        dx_m, dy_m, dyaw_rad = relative_pose(self.last_pose, pose_xyyaw)
        if math.hypot(dx_m, dy_m) >= self.distance_m or abs(dyaw_rad) >= self.rotation_rad:
            self.last_pose = pose_xyyaw.copy()
            return True
        return False


def downsample(image: np.ndarray, width_px: int) -> np.ndarray | None:
    """Grey image resized to ``width_px`` wide (aspect kept), or None when width is 0."""
    if width_px <= 0:
        return None
    grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    h, w = grey.shape
    if w <= width_px:
        return grey
    height = max(1, round(h * width_px / w))
    return cv2.resize(grey, (width_px, height), interpolation=cv2.INTER_AREA)

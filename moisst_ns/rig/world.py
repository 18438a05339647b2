"""``WorldFrame``: how the dataset's metric world maps into nerfstudio's normalised model frame.

``model = scale * (world - center)`` (no rotation, so extrinsics keep their axes and metric results map back
exactly), and cameras change from OpenCV axes (x right, y down, z forward) to nerfstudio's OpenGL axes (x right,
y up, z backward). The dataparser fits it once; the calibration optimiser, the datamanager and the baseline use the
same object. No nerfstudio import.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from jaxtyping import Float
from torch import Tensor

OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])
"""Right-multiplying a camera pose by this flips its y and z axes (OpenCV <-> OpenGL); it is its own inverse."""


@dataclass(frozen=True)
class WorldFrame:
    """The normalisation of a dataset's world: ``model = scale * (world - center)``."""

    center: Float[np.ndarray, "3"]
    """World point mapped to the model origin, metres."""
    scale: float
    """Model units per metre."""

    @classmethod
    def fit(cls, positions: Float[np.ndarray, "num 3"], half_extent: float) -> "WorldFrame":
        """Centre the trajectory's bounding box and scale its largest half extent to ``half_extent`` model units.

        Args:
            positions: reference trajectory positions, metres.
            half_extent: target half extent, model units.

        Returns:
            The frame.
        """
        center = 0.5 * (positions.min(0) + positions.max(0))
        largest = max(float(np.abs(positions - center).max()), 1e-3)
        return cls(center=center, scale=half_extent / largest)

    def camera_to_model(self, world_T_camera: Float[Tensor, "*batch 4 4"]) -> Float[Tensor, "*batch 4 4"]:
        """Metric OpenCV ``world_T_camera`` -> nerfstudio's normalised OpenGL camera-to-world (same dtype)."""
        flip = torch.as_tensor(OPENCV_TO_OPENGL, dtype=world_T_camera.dtype, device=world_T_camera.device)
        pose = world_T_camera @ flip
        return torch.cat([torch.cat([pose[..., :3, :3], self.points_to_model(pose[..., :3, 3])[..., None]], -1), pose[..., 3:, :]], -2)

    def points_to_model(self, points: Float[Tensor, "*batch 3"]) -> Float[Tensor, "*batch 3"]:
        """Metric world points -> model units."""
        return self.scale * (points - torch.as_tensor(self.center, dtype=points.dtype, device=points.device))

    def camera_to_world(self, model_c2w: Float[np.ndarray, "*batch 4 4"]) -> Float[np.ndarray, "*batch 4 4"]:
        """Inverse of ``camera_to_model`` (numpy): nerfstudio OpenGL camera-to-world -> metric OpenCV ``world_T_camera``."""
        pose = np.array(model_c2w, dtype=np.float64, copy=True)
        pose[..., :3, 3] = pose[..., :3, 3] / self.scale + self.center
        return pose @ OPENCV_TO_OPENGL

"""``RayLayout``: where each kind of ray sits in a MOISST training batch (one name for what the datamanager builds
and the model reads). No nerfstudio import."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Optional


@dataclass(frozen=True)
class RayLayout:
    """Camera rays first (the first ``num_patch`` of them as ``patch_size`` x ``patch_size`` patches, one patch's
    rays consecutive, row by row), then ``num_lidar`` LiDAR rays."""

    num_camera: int
    """Camera rays, at the front of the batch."""
    num_lidar: int = 0
    """LiDAR rays, after the camera rays."""
    num_patch: int = 0
    """How many of the camera rays (from the front) form patches; 0: none."""
    patch_size: int = 1
    """Patch side, pixels (1: no patches)."""

    @property
    def camera(self) -> slice:
        return slice(0, self.num_camera)

    @property
    def lidar(self) -> Optional[slice]:
        """The LiDAR rays' slice, or None when there are none."""
        return slice(self.num_camera, self.num_camera + self.num_lidar) if self.num_lidar else None

    @property
    def has_patches(self) -> bool:
        """Whether the patch losses can run: whole patches of more than one pixel."""
        return self.patch_size > 1 and self.num_patch > 0 and self.num_patch % (self.patch_size**2) == 0

    def without_patches(self) -> "RayLayout":
        """The same layout once the camera rays were filtered (patches broken)."""
        return replace(self, num_patch=0)

"""Stand-in for the one open3d call that ``ns-train moisst`` makes once its stages are loaded (``--pipeline.stages-from``):
``PointCloud(Vector3dVector(points)).voxel_down_sample(voxel).points``, the voxel means, as open3d 0.20 computes them
(grid anchored half a voxel below the cloud's minimum). For the GPU machine of ``scripts/device/gpu_measure.sh`` only: open3d's
wheel (105 MB) cannot travel there (64 MiB). Output order differs from open3d's (voxel index order here)."""

import numpy as np


class utility:  # noqa: N801 (open3d's names)
    @staticmethod
    def Vector3dVector(points):  # noqa: N802
        return np.asarray(points, dtype=np.float64).reshape(-1, 3)


class geometry:  # noqa: N801
    class PointCloud:
        def __init__(self, points=None):
            self.points = np.zeros((0, 3)) if points is None else np.asarray(points, dtype=np.float64)

        def voxel_down_sample(self, voxel_size: float) -> "geometry.PointCloud":
            origin = self.points.min(axis=0) - 0.5 * voxel_size
            index = np.floor((self.points - origin) / voxel_size).astype(np.int64)
            _, inverse, counts = np.unique(index, axis=0, return_inverse=True, return_counts=True)
            sums = np.zeros((len(counts), 3))
            np.add.at(sums, inverse.reshape(-1), self.points)
            return geometry.PointCloud(sums / counts[:, None])

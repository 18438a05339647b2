"""Shared test helpers."""

import hashlib
from pathlib import Path

import pytest

KITTI_RAW = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "kitti-raw-2011_09_26_drive_0048"
"""The shared real drive (../shared/data/README.md); tests that need it are marked ``needs_kitti_raw``."""
KITTI_DRIVE = "2011_09_26_drive_0048_sync"
needs_kitti_raw = pytest.mark.skipif(not (KITTI_RAW / KITTI_DRIVE).is_dir(),
                                     reason=f"KITTI raw drive 0048 not found at {KITTI_RAW} (see ../shared/data/README.md)")


def tree_hash(folder: Path) -> str:
    """One digest of every file's relative path and bytes under ``folder`` (to prove a dataset was not written)."""
    digest = hashlib.sha256()
    for path in sorted(folder.rglob("*")):
        if path.is_file():
            digest.update(str(path.relative_to(folder)).encode())
            digest.update(path.read_bytes())
    return digest.hexdigest()


def file_hashes(root: Path) -> dict:
    """sha256 of every file under ``root``, by relative path (to prove two outputs byte-identical)."""
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(root.rglob("*")) if p.is_file()}


def planar_distance_view(view):
    """``view`` (a ``lidar_view.ReferenceView``) with each frame's distance map replaced by a plane
    ``a_f x + b_f y + 5`` (slopes differing per frame) and its exact gradient: bilinear interpolation is then exact,
    so a residual Jacobian can be checked against finite differences without the map's kinks."""
    from dataclasses import replace

    import numpy as np

    from moisst_ns.stages.camera.lidar_map import ImageStack

    stack = view.distance
    frames, h, w = stack.intensity.shape
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    a, b = np.linspace(0.3, 1.1, frames), np.linspace(-0.7, 0.5, frames)
    planes = np.stack([a[f] * x + b[f] * y + 5.0 for f in range(frames)])
    gradient = np.stack([np.stack([np.full_like(x, a[f]), np.full_like(x, b[f])]) for f in range(frames)])
    return replace(view, distance=ImageStack(planes, gradient, stack.model))


def render_still(scene, intr, world_T_cam, supersample=1):
    """A synthetic camera image at one fixed pose: (uint8 RGB (h, w, 3), fraction of each pixel's rays that hit)."""
    from moisst_ns.datasets.synth_effects import to_uint8
    from moisst_ns.datasets.synth_render import render_frame

    rgb, hit = render_frame(scene, intr, lambda _: world_T_cam[None], 0.0, supersample=supersample)
    return to_uint8(rgb), hit


def scene_distance(scene, points):
    """Unsigned distance of world points (N, 3) to the nearest surface of a synthetic ``Scene``, metres."""
    import numpy as np
    import open3d as o3d

    return scene.raycasting.compute_distance(o3d.core.Tensor(np.asarray(points, dtype=np.float32))).numpy()

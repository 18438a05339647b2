"""The view a LiDAR shares with the reference camera, in 3D: the reference camera's features must lie on its surfaces.

The reference camera's SIFT features, triangulated from its known poses (``camera_map.feature_map``, the camera stage's
map without a LiDAR), are points of the world that the LiDAR scanned too. Placed with a wrong lever arm the LiDAR's
surfaces move away from them: the median point-to-plane distance from the features to the nearest planar LiDAR point
(``feature_distances``) is least at the right lever arm. On KITTI raw 0048, profiled from the factory calibration, it
is least within 10 cm of it across the drive (lateral) and vertically; along the drive its basin is shallow (the
features' depth error lies along the viewing rays). The LiDAR-first stage uses it for the lever-arm components that
its motion fit and the depth edges (``lidar_view``) left undetermined (docs/lidar-first.md, "Triangulated features").
No nerfstudio import.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import List, Optional

import numpy as np
import open3d as o3d
from jaxtyping import Bool, Float

from moisst_ns.rig.format import Calibration, Rig
from moisst_ns.rig.geometry import ReferenceTrajectory
from moisst_ns.rig.trust import finite_or_none
from moisst_ns.stages.camera.camera_map import FeatureMapConfig, feature_map
from moisst_ns.stages.camera.lidar_map import NoMapError
from moisst_ns.stages.lidar.lidar_geometry import Extrinsic, place_points, trajectory_at

MAX_DISTANCE = 0.5
"""A feature farther than this from every planar LiDAR point has nothing to land on and is not used, metres."""
SPAN, STEP = 0.6, 0.1
"""Half-span and step of the coarse profile per lever-arm component, metres (a prior error beyond it is out of reach)."""
FINE = 0.025
"""Step of the fine profile (one coarse step either side of the coarse minimum), metres."""
ROUNDS = 2
"""Coordinate-wise rounds of coarse profiles over the components searched."""
CONFIRM_SHARE = 0.95
"""A component is placed when the fine profile's minimum is inside it in at least this share of ``BOOTSTRAP``
resamples of the features, their minima scatter by at most a typical prior error, and the features of the drive's two
halves put it within ``hold`` typical errors of each other (the depth edges' rules, ``lidar_view.CONFIRM_SHARE``)."""
BOOTSTRAP = 200


@dataclass
class FeatureView:
    """The reference camera's triangulated features and which half of the drive each is nearest."""

    points: Float[np.ndarray, "num 3"]
    """World points, metres."""
    first_half: Bool[np.ndarray, "num"]
    """True where the trajectory passes nearest the feature in the first half of the drive."""

    @classmethod
    def of(cls, rig: Rig, traj: ReferenceTrajectory) -> Optional["FeatureView"]:
        """The features of ``rig``'s reference camera, or None (not a camera, or too few features triangulate)."""
        if rig.sensors[rig.reference_sensor].type != "camera":
            return None
        try:
            points = feature_map(rig, Calibration.from_rig(rig), FeatureMapConfig(patch_points=0), log=lambda line: None)
        except NoMapError:
            return None
        stamps = np.asarray(rig.trajectory_stamps, dtype=np.float64) - float(rig.trajectory_stamps[0])
        _, positions, _, _ = traj.pose_and_rates(stamps)
        nearest = np.argmin(np.linalg.norm(points[:, None, :] - positions[None, :, :], axis=2), axis=1)
        return cls(points, stamps[nearest] < np.median(stamps))


def feature_distances(traj: ReferenceTrajectory, ext: Extrinsic, scans, keep: np.ndarray, view: FeatureView,
                      increment: Float[np.ndarray, "7"]) -> Float[np.ndarray, "num"]:
    """Distance (metres) from each feature to the plane of its nearest planar LiDAR point among ``keep`` (indices into
    the ``ScanSet`` ``scans``) placed by eq. 1-2 at ``ext.updated(increment)``; NaN beyond ``MAX_DISTANCE``."""
    at = ext.updated(increment)
    world = place_points(traj, at, scans.points[keep], scans.times[keep])
    index = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(world))
    index.knn_index()
    found, dist2 = index.knn_search(o3d.core.Tensor(view.points), 1)
    near = found.numpy()[:, 0].astype(np.int64)
    rot, _, _, _ = trajectory_at(traj, scans.times[keep[near]], at.time_offset)
    normals = np.einsum("nij,nj->ni", rot, scans.normals[keep[near]] @ at.rotation.T)
    distance = np.abs(np.einsum("ni,ni->n", view.points - world[near], normals))
    return np.where(dist2.numpy()[:, 0] <= MAX_DISTANCE**2, distance, np.nan)


@dataclass
class FeaturePlacement:
    """What the features placed among the lever-arm components searched (``place_by_features``)."""

    columns: List[int]
    """The Jacobian columns searched (lever arm: 3-5)."""
    accepted: List[int]
    increment: Float[np.ndarray, "7"]
    """The profiles' minima on ``accepted`` (0 elsewhere)."""
    sigma: Float[np.ndarray, "7"]
    """Per accepted column the largest of the resamples' scatter, half the halves' difference and the fine step; NaN
    elsewhere; metres."""
    notes: List[str]
    features: int
    """Features within ``MAX_DISTANCE`` of the LiDAR at the start."""

    def to_json(self) -> dict:
        return {"columns": self.columns, "accepted": self.accepted, "increment": self.increment.tolist(),
                "sigma": [finite_or_none(v) for v in self.sigma], "notes": self.notes, "features": self.features}


def place_by_features(traj: ReferenceTrajectory, ext: Extrinsic, scans, view: FeatureView, columns: List[int], hold: float,
                      typical: Float[np.ndarray, "7"]) -> FeaturePlacement:
    """Place the lever-arm ``columns`` (Jacobian order, 3-5) by the features, everything else at ``ext``.

    Coarse profiles of the median feature distance (``SPAN``, ``STEP``), one column at a time with the others at their
    current minimum (``ROUNDS``), then per column a fine profile (``FINE``) over one coarse step either side: its
    minimum is the placement when ``CONFIRM_SHARE``'s rules hold; a column that fails stays at ``ext``.

    Returns:
        The accepted columns, their increment and sigma (``FeaturePlacement``).
    """
    world = place_points(traj, ext, scans.points, scans.times)
    reach = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(view.points))
    reach.knn_index()
    _, dist2 = reach.knn_search(o3d.core.Tensor(world), 1)
    keep = np.flatnonzero(scans.planar & (dist2.numpy()[:, 0] <= (SPAN + STEP + MAX_DISTANCE) ** 2))
    cols = [c for c in columns if 3 <= c < 6]
    start = feature_distances(traj, ext, scans, keep, view, np.zeros(7)) if len(keep) else np.full(len(view.points), np.nan)
    used = int(np.isfinite(start).sum())
    if not cols or used < 50:
        return FeaturePlacement(list(columns), [], np.zeros(7), np.full(7, np.nan), [f"{used} features near the LiDAR's surfaces"] if cols else [], used)

    def profile(base: np.ndarray, c: int, offsets: np.ndarray) -> np.ndarray:
        return np.stack([feature_distances(traj, ext, scans, keep, view, base + np.eye(7)[c] * o) for o in offsets])

    best = np.zeros(7)
    coarse = np.arange(-SPAN, SPAN + STEP / 2, STEP)
    for _ in range(ROUNDS):
        for c in cols:
            best[c] = coarse[np.argmin(np.nanmedian(profile(best * (np.arange(7) != c), c, coarse), axis=1))]
    accepted, notes, sigma = [], [], np.full(7, np.nan)
    rng = np.random.default_rng(0)
    for c in cols:
        offsets = best[c] + np.arange(-STEP, STEP + FINE / 2, FINE)
        d = profile(best * (np.arange(7) != c), c, offsets)
        ok = np.isfinite(d).all(axis=0)
        d, first = d[:, ok], view.first_half[ok]
        best[c] = offsets[np.argmin(np.median(d, axis=1))]
        draws = rng.integers(0, d.shape[1], size=(BOOTSTRAP, d.shape[1]))
        low = np.array([np.argmin(np.median(d[:, k], axis=1)) for k in draws])
        inside = float(np.mean((low > 0) & (low < len(offsets) - 1)))
        scatter = float(np.std(offsets[low]))
        halves = [offsets[np.argmin(np.median(d[:, h], axis=1))] if h.sum() >= 25 else np.nan for h in (first, ~first)]
        apart = abs(halves[0] - halves[1]) / 2
        if not (inside >= CONFIRM_SHARE and scatter <= typical[c] and apart <= hold * typical[c]):
            notes.append(f"column {c}: not confirmed (minimum {best[c]:+.3f} m inside the fine profile in {inside:.0%} of resamples, "
                         f"scatter {scatter:.3g} m, halves {halves[0]:+.3f} / {halves[1]:+.3f} m)")
            best[c] = 0.0
            continue
        accepted.append(c)
        sigma[c] = max(scatter, apart, FINE)
    increment = np.where(np.isin(np.arange(7), accepted), best, 0.0)
    return FeaturePlacement(list(columns), accepted, increment, sigma, notes, used)

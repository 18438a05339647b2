"""A camera placed on the LiDAR map by its own motion: what its own images triangulate must lie on the map's surfaces.

The photometric registration compares a camera's grey levels with the reference camera's and with its own frames'
over map points. A side camera shares no instant with the reference camera, and its own frames, taken as it moves
across its view, sample the map alike wherever its lever arm puts it: its cost hardly sees a lever-arm error and the
descent ends in a wrong minimum (idealised plaza seed 1's ``cam_left``: 138 cm off from the truth, at 4.5x the
reference camera's cost). Its own structure does see it. SIFT matches between its own frames up to ``max_gap`` apart
(``camera_map.sift_frames``, ``ratio_matches``, an essential-matrix RANSAC against movers and mismatches), triangulated
(``camera_map.triangulate``) from the poses the reference trajectory gives the camera for a calibration (rig format
eq. 2: ``Traj(t + delta) ref_T_c``, each row at its own time under a rolling shutter), form a metric cloud whose place
in the world moves with the extrinsic and the offset; point-to-plane distances to the map (its normals from open3d)
give the 7 corrections of eq. 12 (``scipy.optimize.least_squares``, soft L1), nearest neighbours re-found as the
search radius shrinks (ICP). From the paper's perturbation the coarse radii start from a grid over delta, the start
keeping most points within the last coarse radius continuing. Measured: docs/lab/2026-12-02-own-motion.md.
No nerfstudio import.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Callable, List, Optional, Tuple

import numpy as np
import open3d as o3d
import torch
from jaxtyping import Float, Int
from scipy.optimize import least_squares

from moisst_ns.rig.format import Rig
from moisst_ns.stages.camera.camera_config import CameraRegistrationConfig
from moisst_ns.stages.camera.camera_result import CameraResult, corrected
from moisst_ns.rig.geometry import ReferenceTrajectory, calibrated_extrinsic, row_time
from moisst_ns.stages.camera.camera_guards import SCALE, bounds, convergence_tail
from moisst_ns.stages.camera.camera_map import camera_matrix, distortion, ratio_matches, sift_frames, triangulate
from moisst_ns.stages.trust.observability import SOLVER_NAMES, TYPICAL_ERROR
from moisst_ns.stages.trust.uncertainty_math import least_squares_sigma


@dataclass
class DeltaGridConfig:
    """The settings a camera's fits by its own motion share (``OwnMotionConfig``, ``own_tracks.OwnTracksConfig``)."""

    max_time_offset: float = 0.2
    """The coarse starts span the prior's delta +- this, seconds."""
    time_grid: float = 0.05
    """Spacing of the coarse starts' delta grid, seconds."""
    coarse_matches: int = 4000
    """The starts' solves use every k-th match, at most this many."""
    hold_out: int = 5
    """Every ``hold_out``-th frame's matches (own tracks: track) are held back from the fit for its held-back loss."""

    def starts(self) -> List[np.ndarray]:
        """The coarse starts' corrections: zero but for delta, on the grid."""
        steps = int(round(self.max_time_offset / self.time_grid))
        return [np.r_[np.zeros(6), k * self.time_grid] for k in range(-steps, steps + 1)]


@dataclass
class OwnMotionConfig(DeltaGridConfig):
    """Settings of a camera's own-motion fit against the map."""

    features: int = 2000
    """SIFT features per frame."""
    ratio: float = 0.75
    """Lowe's ratio test."""
    max_gap: int = 3
    """Each frame is matched with the next ``max_gap`` frames."""
    ransac_px: float = 1.0
    """Inlier threshold of each pair's essential-matrix RANSAC, pixels."""
    min_parallax_deg: float = 1.0
    """Least angle between a match's two viewing rays, degrees."""
    coarse_radii: Tuple[float, ...] = (2.0, 1.0, 0.5)
    """Search radii of the nearest map point from every start, metres (one solve each)."""
    fine_radius: float = 0.12
    """Search radius of the fine solves from the kept start, metres."""
    fine_iterations: int = 8
    """At most this many fine solves; they stop once one moves the cloud by less than ``stop_m``."""
    stop_m: float = 0.001
    """RMS move of the cloud that ends the fine solves, metres."""
    normal_radius: float = 0.25
    """Radius of the map's normal estimate, metres."""
    min_points: int = 1000
    """Fewer matches than this on the map at the fine radius: the camera is not placed."""


@dataclass
class OwnMatches:
    """A camera's matches between its own frames: the observations' frames, normalised coordinates and rows."""

    frame_a: Int[np.ndarray, "n"]
    frame_b: Int[np.ndarray, "n"]
    xy_a: Float[np.ndarray, "n 2"]
    xy_b: Float[np.ndarray, "n 2"]
    row_a: Float[np.ndarray, "n"]
    """Image row of the first observation, pixels (its time under a rolling shutter)."""
    row_b: Float[np.ndarray, "n"]
    stamps: Float[np.ndarray, "frames"]
    """The frames' stamps, seconds since the trajectory's first."""
    readout: float
    height: int
    key_a: Optional[Int[np.ndarray, "n"]] = None
    """The first observation's keypoint, numbered over all the camera's frames (``own_tracks.tracks`` chains them)."""
    key_b: Optional[Int[np.ndarray, "n"]] = None

    def subset(self, keep: np.ndarray) -> "OwnMatches":
        keys = [None if k is None else k[keep] for k in (self.key_a, self.key_b)]
        return OwnMatches(self.frame_a[keep], self.frame_b[keep], self.xy_a[keep], self.xy_b[keep], self.row_a[keep], self.row_b[keep],
                          self.stamps, self.readout, self.height, *keys)


@dataclass
class MapSurface:
    """The map with a normal per point and a nearest-neighbour index (open3d)."""

    points: Float[np.ndarray, "num 3"]
    normals: Float[np.ndarray, "num 3"]
    index: object

    @classmethod
    def of(cls, world: Float[np.ndarray, "num 3"], radius: float) -> "MapSurface":
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(world))
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=30))
        index = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(world))
        index.knn_index()
        return cls(world, np.asarray(cloud.normals), index)

    def nearest(self, points: Float[np.ndarray, "n 3"]) -> Tuple[Int[np.ndarray, "n"], Float[np.ndarray, "n"]]:
        """Index of each point's nearest map point and the distance to it, metres."""
        if not len(points):
            return np.zeros(0, dtype=np.int64), np.zeros(0)
        found, dist2 = self.index.knn_search(o3d.core.Tensor(np.ascontiguousarray(points)), 1)
        return found.numpy()[:, 0].astype(np.int64), np.sqrt(dist2.numpy()[:, 0])


def own_matches(rig: Rig, name: str, config: OwnMotionConfig, downscale: int = 1) -> OwnMatches:
    """SIFT matches of ``name``'s frames with their next ``max_gap``, the essential matrix's RANSAC inliers of each pair;
    the keypoints found on the images shrunk ``downscale`` times (``sift_frames``).

    Raises:
        CameraStageError: an image cannot be read (``sift_frames``).
    """
    import cv2

    spec = rig.sensors[name]
    frames = sorted(rig.frames_of(name), key=lambda f: f.timestamp)
    K, dist = camera_matrix(spec.intrinsics), distortion(spec.intrinsics)
    keys, descs = sift_frames(rig, frames, config.features, downscale)
    first = np.cumsum([0] + [len(k) for k in keys])  # each frame's first keypoint's number
    parts = []
    for a in range(len(frames)):
        for b in range(a + 1, min(a + 1 + config.max_gap, len(frames))):
            ia, ib = ratio_matches(descs[a], descs[b], config.ratio)
            if len(ia) < 8:
                continue
            xy = [cv2.undistortPoints(keys[f][i].reshape(-1, 1, 2), K, dist).reshape(-1, 2) for f, i in ((a, ia), (b, ib))]
            E, mask = cv2.findEssentialMat(xy[0], xy[1], np.eye(3), method=cv2.RANSAC, prob=0.999, threshold=config.ransac_px / K[0, 0])
            if E is None:
                continue
            m = mask.ravel().astype(bool)
            parts.append((np.full(m.sum(), a), np.full(m.sum(), b), xy[0][m], xy[1][m], keys[a][ia][m, 1] + 0.5, keys[b][ib][m, 1] + 0.5,
                          first[a] + ia[m], first[b] + ib[m]))
    empty = (np.zeros(0), np.zeros(0), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0))
    cat = [np.concatenate(c) for c in zip(*(parts or [empty]))]
    stamps = np.array([f.timestamp for f in frames], dtype=np.float64) - float(rig.trajectory_stamps[0])
    return OwnMatches(cat[0].astype(np.int64), cat[1].astype(np.int64), *cat[2:6], stamps, float(spec.readout_time), int(spec.intrinsics["h"]),
                      cat[6].astype(np.int64), cat[7].astype(np.int64))


def observation_poses(theta: Float[np.ndarray, "7"], frame: Int[np.ndarray, "n"], row: Float[np.ndarray, "n"], stamps: Float[np.ndarray, "frames"],
                      readout: float, height: int, traj: ReferenceTrajectory, prior: Float[np.ndarray, "4 4"],
                      prior_offset: float) -> Float[np.ndarray, "n 4 4"]:
    """``world_T_c`` of each observation (its frame, its image row) at the corrections ``theta`` (rotation vector rad,
    lever arm m, delta s; eq. 12): eq. 2 at the frame's stamp, each row at its own time under a rolling shutter."""
    th = torch.from_numpy(np.asarray(theta, dtype=np.float64))
    X = calibrated_extrinsic(torch.from_numpy(np.asarray(prior, dtype=np.float64)), th[:3], th[3:6])
    at = prior_offset + float(theta[6])
    if readout:
        return (traj(torch.from_numpy(stamps[frame] + at + row_time(row, readout, height))) @ X).numpy()
    return (traj(torch.from_numpy(stamps + at)) @ X).numpy()[frame]


def own_cloud(theta: Float[np.ndarray, "7"], matches: OwnMatches, traj: ReferenceTrajectory, prior: Float[np.ndarray, "4 4"],
              prior_offset: float, min_parallax_deg: float = 0.0) -> Tuple[Float[np.ndarray, "n 3"], np.ndarray]:
    """The matches triangulated from the camera's poses at the corrections ``theta`` (rotation vector rad, lever arm m,
    delta s; eq. 12), world frame, metres; and which are in front of both views with at least ``min_parallax_deg``."""
    poses = [observation_poses(theta, f, r, matches.stamps, matches.readout, matches.height, traj, prior, prior_offset)
             for f, r in ((matches.frame_a, matches.row_a), (matches.frame_b, matches.row_b))]
    proj = [np.linalg.inv(p)[:, :3] for p in poses]
    world = triangulate(proj[0], proj[1], matches.xy_a, matches.xy_b)
    depth = [np.einsum("nj,nj->n", q[:, 2, :3], np.nan_to_num(world)) + q[:, 2, 3] for q in proj]
    rays = [p[:, :3, 3] - np.nan_to_num(world) for p in poses]
    cos = np.sum(rays[0] * rays[1], 1) / np.maximum(np.linalg.norm(rays[0], axis=1) * np.linalg.norm(rays[1], axis=1), 1e-12)
    ok = np.isfinite(world).all(1) & (depth[0] > 0.5) & (depth[1] > 0.5) & (cos < np.cos(np.deg2rad(min_parallax_deg)))
    return np.nan_to_num(world), ok


@dataclass
class OwnMotionFit:
    """The fit's outcome: corrections, sigma parts (solver order: rad, m, s) and the held-back loss."""

    theta: Float[np.ndarray, "7"]
    sigma_formal: Float[np.ndarray, "7"]
    sigma_split: Float[np.ndarray, "7"]
    """The farther half of the drive's fit from the whole's."""
    sigma_baseline: Float[np.ndarray, "7"]
    """On the map: half the difference of the fits of the next frame's matches and of the farther ones' (the
    triangulation's error falls with the baseline: where they part, its bias does); by own tracks: the farther of the
    short and the long tracks' fits from the whole (``own_tracks.OwnTracksConfig.short_span``)."""
    sigma_convergence: Float[np.ndarray, "7"]
    """On the map: the descent's remaining distance (``convergence_tail``); by own tracks: zeros."""
    points: int
    """Matches on the map at the fine radius; by own tracks: tracks kept."""
    loss_prior: float
    """Held-back loss at the prior: mean distance of the held-back frames' points to the map, capped at the last coarse
    radius, metres; by own tracks: mean angle of the held-back tracks' observations to their points, capped, pixels."""
    loss_estimate: float
    sigma_resolution: Float[np.ndarray, "7"] = field(default_factory=lambda: np.zeros(7))
    """By own tracks: ``camera_guards.resolution_spread`` of the fit and the same fit on keypoints found at 1/2
    resolution (a bias of the keypoints that every track shares); on the map: zeros."""

    @property
    def sigma(self) -> Float[np.ndarray, "7"]:
        """The fit's sigma: the largest of its formal, split-half, baseline, convergence and resolution parts."""
        return np.fmax.reduce([self.sigma_formal, self.sigma_split, self.sigma_baseline, self.sigma_convergence, self.sigma_resolution])


def _solve(theta: np.ndarray, matches: OwnMatches, surface: MapSurface, radius: float, parallax: float, traj, prior, offset):
    """One point-to-plane solve, the nearest map points found at ``theta`` within ``radius``: (theta, kept, solution)."""
    world, ok = own_cloud(theta, matches, traj, prior, offset, parallax)
    found, d = surface.nearest(world[ok])
    kept = np.flatnonzero(ok)[d < radius]
    q, n = surface.points[found[d < radius]], surface.normals[found[d < radius]]
    if len(kept) < 7:
        return theta, kept, None
    sub = matches.subset(kept)

    def residuals(x: np.ndarray) -> np.ndarray:
        p, good = own_cloud(x, sub, traj, prior, offset)
        return np.where(good, np.sum((p - q) * n, axis=1), 0.0)

    solution = least_squares(residuals, theta, loss="soft_l1", f_scale=min(radius / 4, 0.05), diff_step=1e-7, x_scale=SCALE[:7])
    return solution.x, kept, solution


def _loss(theta, matches: OwnMatches, surface: MapSurface, cap: float, traj, prior, offset) -> float:
    world, ok = own_cloud(theta, matches, traj, prior, offset)
    return float(np.mean(np.minimum(surface.nearest(world[ok])[1], cap))) if ok.any() else cap


def _fine(theta, matches, surface, config, traj, prior, offset, iterations):
    history, solution, kept = [theta.copy()], None, np.zeros(0, dtype=np.int64)
    before = own_cloud(theta, matches, traj, prior, offset)[0]
    for _ in range(iterations):
        theta, kept, solution = _solve(theta, matches, surface, config.fine_radius, config.min_parallax_deg, traj, prior, offset)
        history.append(theta.copy())
        after = own_cloud(theta, matches, traj, prior, offset)[0]
        if solution is None or np.sqrt(np.mean(np.sum((after - before) ** 2, 1))) < config.stop_m:
            break
        before = after
    return theta, kept, solution, history


def fit_own_motion(traj: ReferenceTrajectory, matches: OwnMatches, surface: MapSurface, prior: Float[np.ndarray, "4 4"], prior_offset: float,
                   config: OwnMotionConfig, log: Callable[[str], None] = print, sensor: str = "camera",
                   start: Optional[np.ndarray] = None) -> Optional[OwnMotionFit]:
    """The camera's 7 corrections from its own matches against the map (module docstring).

    Args:
        traj: the reference trajectory.
        matches: ``own_matches`` of the camera.
        surface: the map (``MapSurface.of``).
        prior: prior ``ref_T_c``; prior_offset: prior delta, seconds.
        config: settings.
        log: where progress lines go; sensor: the camera's name for them.
        start: corrections to refine from at the fine radius alone (a drawn trajectory's refit), None: the delta grid.

    Returns:
        The fit, or None when fewer than ``config.min_points`` matches lie on the map at the fine radius.
    """
    held = matches.frame_a % config.hold_out == config.hold_out - 1
    fit, back = matches.subset(~held), matches.subset(held)
    args = (traj, prior, prior_offset)
    if start is None:
        best, coarse = None, fit.subset(slice(None, None, max(1, len(fit.frame_a) // config.coarse_matches)))
        for theta in config.starts():
            delta = theta[6]
            for radius in config.coarse_radii:
                theta, kept, _ = _solve(theta, coarse, surface, radius, config.min_parallax_deg, *args)
            log(f"[own-motion] {sensor}: start at delta {delta * 1000:+.0f} ms from the prior: {len(kept)} of {len(coarse.frame_a)} matches "
                f"within {config.coarse_radii[-1]:g} m of the map")
            if best is None or len(kept) > len(best[1]):
                best = (theta, kept)
        start = best[0]
    theta, kept, solution, history = _fine(np.asarray(start, dtype=np.float64), fit, surface, config, *args, config.fine_iterations)
    if solution is None or len(kept) < config.min_points:
        log(f"[own-motion] {sensor}: {len(kept)} matches on the map within {config.fine_radius:g} m (the fit needs {config.min_points}): not placed")
        return None
    weights = (1 + (solution.fun / min(config.fine_radius / 4, 0.05)) ** 2) ** -0.25  # the square root of soft L1's IRLS weight
    formal = least_squares_sigma(solution.jac * weights[:, None], solution.fun * weights, fit.frame_a[kept]).sigma
    middle, gap = len(matches.stamps) // 2, fit.frame_b - fit.frame_a
    halves = [_fine(theta, fit.subset(h), surface, config, *args, 2)[0] for h in (fit.frame_b < middle, fit.frame_a >= middle)]
    split = np.max([np.abs(h - theta) for h in halves], axis=0)
    baselines = [_fine(theta, fit.subset(h), surface, config, *args, 2)[0] for h in (gap == 1, gap > 1)] if config.max_gap > 1 else [theta] * 2
    baseline = np.abs(baselines[0] - baselines[1]) / 2
    cap = config.coarse_radii[-1]
    result = OwnMotionFit(theta, np.asarray(formal), split, baseline, convergence_tail(np.asarray(history)), len(kept),
                          _loss(np.zeros(7), back, surface, cap, *args), _loss(theta, back, surface, cap, *args))
    log(f"[own-motion] {sensor}: {len(kept)} matches on the map within {config.fine_radius:g} m after {len(history) - 1} fine solves; "
        f"held-back loss {result.loss_estimate * 100:.2f} cm (prior {result.loss_prior * 100:.2f} cm)")
    return result


OWN = OwnMotionConfig()  # the own-motion fit's settings


def own_motion_result(fit: Optional[OwnMotionFit], kept: CameraResult, config: CameraRegistrationConfig, log: Callable[[str], None],
                      begun: float, source: str = "lidar") -> CameraResult:
    """``kept`` (a camera the photometric fit left at its prior, or could not fit) placed by its own motion: ``fit``, of
    its matches against the LiDAR map (``fit_own_motion``, ``source`` "lidar") or its tracks against the trajectory alone
    (``own_tracks.fit_own_tracks``, "features"); or ``kept`` again, its note extended, where the fit places nothing
    (None), its held-back loss is no lower than the prior's, it lies beyond the stage's bounds (``camera_guards.bounds``)
    or the drive's halves disagree by more than ``max_split_half`` typical errors. sigma is ``OwnMotionFit.sigma``;
    ``history`` stays the photometric fit's; ``begun``: when the fit began (``time.perf_counter``)."""
    on_map = source == "lidar"
    unit = "m" if on_map else "px"
    apart = [] if fit is None else [SOLVER_NAMES[i] for i in np.flatnonzero(fit.sigma_split > config.max_split_half * TYPICAL_ERROR)]
    beyond = [] if fit is None else [SOLVER_NAMES[i] for i in np.flatnonzero(np.abs(fit.theta) >= 0.999 * bounds(config))]
    why = (("its own matches do not lie on the map" if on_map else "its own tracks do not agree on the trajectory's poses") if fit is None else
           f"its own motion's held-back loss {fit.loss_estimate:.4g} {unit} is no lower than the prior's {fit.loss_prior:.4g} {unit}" if not fit.loss_estimate < fit.loss_prior else
           f"its own motion puts it beyond its bound on {', '.join(beyond)}" if beyond else
           f"the two halves of the drive place it apart on {', '.join(apart)} by more than {config.max_split_half:g}x a typical prior error" if apart else "")
    if why:
        log(f"[camera-registration] {kept.sensor}: {why}; it keeps its prior")
        return replace(kept, note=f"{kept.note}; by its own motion: {why}")
    pose, offset = corrected(kept.prior, kept.prior_offset, fit.theta)
    what = f"{fit.points} of its own matches on the map" if on_map else f"{fit.points} of its own tracks on the reference trajectory's poses"
    log(f"[camera-registration] {kept.sensor}: " + (f"the photometric fit kept its prior ({kept.note or 'held-back check'}); placed by its own motion instead"
                                                     if on_map else "placed by its own tracks on the trajectory"))
    return replace(kept, estimate=pose, time_offset=offset, sigma=fit.sigma.tolist(), cost_prior=fit.loss_prior, cost_estimate=fit.loss_estimate,
                   kept_prior=False, note="", sigma_formal=fit.sigma_formal.tolist(), sigma_split=fit.sigma_split.tolist(), blind=[], significance=[],
                   start=f"own motion ({what}; {'the photometric fit' if on_map else 'alone'}: {kept.note or 'held-back check'})",
                   sigma_resolution=[] if on_map else fit.sigma_resolution.tolist(), sigma_convergence=fit.sigma_convergence.tolist(), held_there=False, wall_s=kept.wall_s + time.perf_counter() - begun)

"""A LiDAR placed against what two cameras triangulate at the same instant (issue 34: the shared view of a straight drive).

The LiDAR-first stage places a LiDAR by its scans' consistency along the drive: on an almost straight drive that leaves
its lever arm and roll undetermined (KITTI raw 0048), and it calibrates the LiDAR in the frame the trajectory is given
in, which a real trajectory source need not share with the reference camera (KITTI's OXTS trajectory is turned 0.67 /
0.45° from image_00). Here, per reference frame, SIFT matches between the reference camera and another registered camera
that sees the same instant are triangulated from their two poses (``camera_map.triangulate``); each point must
lie on the surface of the LiDAR's scan of that instant, placed by eq. 1-2: point-to-plane residuals, each weighted by
its noise (the plane's and the stereo depth's along the plane's normal), Huber, fitted in the LiDAR's rotation and lever
arm (its time offset held: on a straight drive it trades with the along-track lever arm) and, per camera pair, a shift of
the second camera's centre (what the pair's own calibration error does to its triangulation: along the baseline a depth
scale, which the LiDAR's range pins; along the reference camera's axis a depth error that grows across the image, which
tilts the road like a roll of the LiDAR). Only the milliseconds between the
cameras' and the scan's instants pass through the trajectory, so its drift and turn do not enter, and a moving car is
seen where both sensors see it. A parameter is placed where its sigma (``InstantPlacement.sigma``) is below a typical
prior error; what the LiDAR takes from here: ``lidar_placement``. No nerfstudio import.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np
import open3d as o3d
import torch
from jaxtyping import Float

from moisst_ns.rig.format import Calibration, Rig
from moisst_ns.rig.geometry import ReferenceTrajectory, row_time
from moisst_ns.rig.trust import PARAMETERS, parameter_difference
from moisst_ns.stages.camera.camera_map import camera_matrix, distortion, sift_frames, ratio_matches, triangulate
from moisst_ns.stages.lidar.lidar_geometry import Extrinsic, placement_jacobian, place_points
from moisst_ns.stages.lidar.lidar_scans import ScanSet, moving_points
from moisst_ns.stages.trust.observability import JACOBIAN_ORDER, TEST_STEPS, huber_weights
from moisst_ns.stages.trust.uncertainty_math import least_squares_sigma

PIXEL_SIGMA = 0.5
"""A matched keypoint's position noise, pixels."""
PLANE_SIGMA = 0.02
"""A LiDAR surface's noise beside its neighbourhood's thickness, metres."""
MIN_BASELINE = 0.2
"""Camera pairs closer than this triangulate depth too noisily to use, metres."""
DEPTH_RANGE = (2.0, 40.0)
"""Triangulated points kept within this depth of the reference camera, metres."""
SAME_INSTANT = 0.05
"""A camera frame or scan within this of a reference frame (after the time offsets) sees its instant, seconds."""
RADII = (2.0, 1.0, 0.5, 0.3, 0.2, 0.15, 0.15)
"""Nearest-neighbour radius of each outer iteration (coarse to fine), metres."""
HUBER = 1.5
"""Huber scale of the weighted residuals (sigmas)."""
MIN_ROWS = 200
"""Fewer point-to-plane rows than this place nothing."""
MOVER_ANGLE = np.deg2rad(1.0)
"""A match whose line of sight passes this close to a LiDAR point on a mover is left out, radians: the keypoint lies
on the car in the reference image, whose body the sweep samples every fraction of a degree (its outline may have
moved more: a car 20 m/s faster, 10 m away, 3 deg in 25 ms). 3 deg left out 38 % of KITTI raw 0048's matches and
tilted its Velodyne 0.19 deg (0.05 without; 1 deg: 9 %, 0.08 deg)."""


@dataclass
class InstantPoints:
    """One camera pair's triangulated matches at one reference frame, world frame."""

    time: float
    """The reference frame's instant, seconds since ``t0``."""
    origin: Float[np.ndarray, "num 3"]
    """The reference camera's centre each match was seen from (its row's pose with a rolling shutter), metres."""
    ray: Float[np.ndarray, "num 3"]
    """From there to the triangulated point, metres: the point at depth scale ``s`` is ``origin + s * ray``."""
    depth_sigma: Float[np.ndarray, "num"]
    """The depth noise along the ray, metres."""
    shift_gradient: Float[np.ndarray, "num 2"]
    """How the point's depth scale along ``ray`` (1 as triangulated) grows with a shift of the second camera's centre,
    per metre, along the pair's baseline and along the reference camera's axis orthogonal to it (``shift_axes``)."""
    pair: int
    """Index of the camera pair (its shifts)."""


@dataclass
class InstantPlacement:
    """What the shared instant says about one LiDAR."""

    estimate: Extrinsic
    """The fit of every parameter but the time offset."""
    sigma: List[float]
    """Per ``PARAMETERS`` (m, rad; the time offset's nan): the frame-clustered sigma (the pairs' shifts marginalised),
    at least half the difference of the drive's halves and of the camera pairs fitted alone, and the whole difference
    to the fit with the pairs as calibrated (shifts held at 0: where the data and the cameras' calibration disagree,
    what the shifts did to the placement)."""
    placed: List[str]
    """The parameters whose sigma is below a typical prior error."""
    rows: int
    cameras: List[str]
    shifts: List[List[float]] = field(default_factory=list)
    """The shift of each camera pair's second camera fitted with the LiDAR, metres, along ``shift_axes`` (0: the pair
    as calibrated)."""
    along_track: List[float] = field(default_factory=list)
    """The mean velocity in the reference frame, m/s: a time-offset error ``e`` moves the placed lever arm by
    ``-along_track * e`` (the time offset is held)."""
    taken: List[str] = field(default_factory=list)
    """The parameters the LiDAR's calibration took from here (``place_lidars``)."""
    turn: List[float] = field(default_factory=list)
    """When the motion's estimate lies in another frame (``place_lidars``): the rotation vector (rad, about the
    reference sensor's axes) that carries the trajectory's frame to the reference sensor's, about the LiDAR's axes where
    the motion's and the shared instants' rotations differ by more than their combined sigma (``trajectory_turn``);
    else empty."""

    def to_json(self) -> dict:
        return {"T_ref_sensor": self.estimate.matrix().tolist(), "sigma": [None if not np.isfinite(s) else float(s) for s in self.sigma],
                "placed": self.placed, "rows": self.rows, "cameras": self.cameras, "shifts": self.shifts, "along_track": self.along_track,
                "taken": self.taken, **({"turn_rotvec": self.turn} if self.turn else {})}


def shift_axes(baseline: Float[np.ndarray, "3"]) -> Float[np.ndarray, "2 3"]:
    """The directions a camera pair's second camera is let shift in, reference camera's frame: along the
    baseline (a depth scale) and along the reference camera's axis orthogonal to it (a depth error that grows across the
    image); the third, across both, moves the triangulated depth hardly at all."""
    along = baseline / np.linalg.norm(baseline)
    axis = np.array([0.0, 0.0, 1.0]) - along[2] * along
    return np.stack([along, axis / max(np.linalg.norm(axis), 1e-9)])


def shift_sigmas(camera_sigma: Optional[Sequence[float]], along: Float[np.ndarray, "3"], baseline: Float[np.ndarray, "3"]) -> Float[np.ndarray, "2"]:
    """The prior sigma of a camera pair's two shifts (``shift_axes``), metres: the camera's position sigma and, along
    the drive, its time offset's.

    Args:
        camera_sigma: the camera's registration sigma (Jacobian order: rad, m, s), or None.
        along: the velocity in the reference camera's frame, m/s.
        baseline: the camera's position from the reference camera's, metres.

    Returns:
        Per shift; inf (free) without a sigma, or where its position's or offset's is not finite (not determined, or not
        measured: a NaN there once made the placement's solve fail).
    """
    sig = np.full(7, np.inf) if camera_sigma is None else np.asarray(camera_sigma, dtype=np.float64)
    if not np.isfinite(sig[3:7]).all():
        return np.full(2, np.inf)
    cov = np.diag(sig[3:6] ** 2) + sig[6] ** 2 * np.outer(along, along)
    axes = shift_axes(baseline)
    return np.sqrt(np.einsum("ij,jk,ik->i", axes, cov, axes))


def pairs_with_reference(rig: Rig, calibration: Optional[Calibration] = None) -> List[str]:
    """The cameras ``calibration`` (default: the rig's priors) puts ``MIN_BASELINE`` or more from the reference camera:
    those that may place a LiDAR at the same instants (none when the reference sensor is not a camera)."""
    if rig.sensors[rig.reference_sensor].type != "camera":
        return []
    T = (calibration or Calibration.from_rig(rig)).T_ref_sensor
    ref = np.asarray(T[rig.reference_sensor], dtype=np.float64)
    return [n for n, s in rig.sensors.items() if n != rig.reference_sensor and s.type == "camera"
            and np.linalg.norm(np.asarray(T[n], dtype=np.float64)[:3, 3] - ref[:3, 3]) >= MIN_BASELINE]


def instant_points(rig: Rig, traj: ReferenceTrajectory, calibration: Calibration, camera: str, pair: int, features: int = 4000,
                   ratio: float = 0.8) -> List[InstantPoints]:
    """The reference camera's matches with ``camera`` at the same instants, triangulated from each match's two poses
    (at its rows' times with a rolling shutter; ``camera_map.triangulate``), kept within ``DEPTH_RANGE`` of both
    cameras and reprojecting within 1 pixel in ``camera``."""
    import cv2

    ref = rig.reference_sensor
    t0 = float(rig.trajectory_stamps[0])
    frames = {n: sorted(rig.frames_of(n), key=lambda f: f.timestamp) for n in (ref, camera)}
    at = {n: np.array([f.timestamp for f in frames[n]]) - t0 + float(calibration.time_offset[n]) for n in (ref, camera)}
    nearest = [int(np.argmin(np.abs(at[camera] - t))) for t in at[ref]]
    used = [(k, j) for k, j in enumerate(nearest) if abs(at[camera][j] - at[ref][k]) <= SAME_INSTANT]
    keys = {ref: sift_frames(rig, [frames[ref][k] for k, _ in used], features), camera: sift_frames(rig, [frames[camera][j] for _, j in used], features)}

    def poses(name: str, frame: int, xy: np.ndarray) -> np.ndarray:
        """``world_T_camera`` of each keypoint (n, 4, 4): at its row's time with a rolling shutter."""
        spec = rig.sensors[name]
        t = at[name][frame] + row_time(xy[:, 1] + 0.5, float(spec.readout_time), int(spec.intrinsics["h"]))
        return (traj(torch.from_numpy(np.asarray(t, dtype=np.float64))) @ torch.from_numpy(np.asarray(calibration.T_ref_sensor[name], dtype=np.float64))).numpy()

    axes = shift_axes(np.asarray(calibration.T_ref_sensor[camera], dtype=np.float64)[:3, 3] - np.asarray(calibration.T_ref_sensor[ref], dtype=np.float64)[:3, 3])
    out = []
    for i, (k, j) in enumerate(used):
        ia, ib = ratio_matches(keys[ref][1][i], keys[camera][1][i], ratio)
        if len(ia) < 8:
            continue
        xy = {ref: keys[ref][0][i][ia], camera: keys[camera][0][i][ib]}
        norm = {n: cv2.undistortPoints(xy[n].reshape(-1, 1, 2), camera_matrix(rig.sensors[n].intrinsics),
                                       distortion(rig.sensors[n].intrinsics)).reshape(-1, 2) for n in (ref, camera)}
        pose = {ref: poses(ref, k, xy[ref]), camera: poses(camera, j, xy[camera])}
        inv = {n: np.linalg.inv(pose[n]) for n in (ref, camera)}
        world = triangulate(inv[ref][:, :3], inv[camera][:, :3], norm[ref], norm[camera])
        cam = {n: np.einsum("nij,nj->ni", inv[n][:, :3, :3], np.nan_to_num(world)) + inv[n][:, :3, 3] for n in (ref, camera)}
        depth = np.where(np.abs(cam[camera][:, 2:]) > 1e-9, cam[camera][:, 2:], 1e-9)
        reproj = np.linalg.norm(cam[camera][:, :2] / depth - norm[camera], axis=1) * float(rig.sensors[camera].intrinsics["fl_x"])
        ok = np.isfinite(world).all(axis=1) & (reproj < 1.0)
        for n in (ref, camera):
            ok &= (cam[n][:, 2] > DEPTH_RANGE[0]) & (cam[n][:, 2] < DEPTH_RANGE[1])
        origin, ray = pose[ref][ok, :3, 3], world[ok] - pose[ref][ok, :3, 3]
        baseline = np.linalg.norm(pose[camera][ok, :3, 3] - origin, axis=1)
        sigma = np.sum(ray**2, axis=1) / (float(rig.sensors[ref].intrinsics["fl_x"]) * np.maximum(baseline, 1e-6)) * PIXEL_SIGMA
        # origin + l * ray = c + m * seen, with c moved by dc: dl = dc . (seen x (ray x seen)) / |ray x seen|^2
        seen = world[ok] - pose[camera][ok, :3, 3]
        normal = np.cross(ray, seen)
        gradient = np.cross(seen, normal) / np.maximum(np.sum(normal**2, axis=1), 1e-12)[:, None]
        out.append(InstantPoints(float(at[ref][k]), origin, ray, sigma, np.einsum("nji,nj->ni", pose[ref][ok, :3, :3], gradient) @ axes.T, pair))
    return out


def _off_movers(traj: ReferenceTrajectory, ext: Extrinsic, scans: ScanSet, moving: np.ndarray, pts: InstantPoints) -> InstantPoints:
    """``pts`` less the matches whose line of sight from the reference camera passes within ``MOVER_ANGLE`` of a point
    the LiDAR sees moving (``lidar_scans.moving_points``) in its scan nearest to their instant: a moving car's point
    seen by two cameras milliseconds apart triangulates off the car (a car 10 m/s faster moves 22 cm in the 22 ms
    between the synthetic street's two cameras), and the LiDAR sees it at yet another instant."""
    k = int(np.argmin(np.abs(scans.stamps + ext.time_offset - pts.time)))
    part = scans.scan(k)
    movers = np.flatnonzero(moving[part]) + part.start
    if not len(movers) or not len(pts.ray):
        return pts
    world = place_points(traj, ext, scans.points[movers], scans.times[movers])
    centre = pts.origin.mean(axis=0)
    seen = (world - centre) / np.linalg.norm(world - centre, axis=1, keepdims=True)
    ray = pts.ray / np.linalg.norm(pts.ray, axis=1, keepdims=True)
    index = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(seen))
    index.knn_index()
    _, dist2 = index.knn_search(o3d.core.Tensor(ray), 1)
    keep = dist2.numpy()[:, 0] > (2 * np.sin(MOVER_ANGLE / 2)) ** 2
    return replace(pts, origin=pts.origin[keep], ray=pts.ray[keep], depth_sigma=pts.depth_sigma[keep], shift_gradient=pts.shift_gradient[keep])


def _shifted(ray: Float[np.ndarray, "num 3"], gradient: Float[np.ndarray, "num 2"], shift: Float[np.ndarray, "*num 2"]) -> Float[np.ndarray, "num 3"]:
    """The ray (metres) to the point triangulated with the pair's second camera shifted by ``shift`` (metres, along
    ``shift_axes``), to first order: its depth scale ``1 + gradient . shift``."""
    return (1.0 + np.sum(gradient * shift, axis=-1))[:, None] * ray


def _rows(traj: ReferenceTrajectory, ext: Extrinsic, scans: ScanSet, sets: Sequence[InstantPoints], shifts: np.ndarray, radius: float):
    """Point-to-plane correspondences: each triangulated point (its pair's camera shifted by ``shifts[pair]``) and its
    nearest planar LiDAR point of the scan at its instant within ``radius`` (world frame). Returns (LiDAR point index,
    world normal, origin, ray as triangulated, its depth scale's gradient by the shift (num, 2), pair, weight, set)."""
    rows, indices = [], {}
    for s, pts in enumerate(sets):
        k = int(np.argmin(np.abs(scans.stamps + ext.time_offset - pts.time)))
        if abs(scans.stamps[k] + ext.time_offset - pts.time) > SAME_INSTANT or not len(pts.ray):
            continue
        part = scans.scan(k)
        if k not in indices:  # each scan placed and indexed once, whichever camera pairs see its instant
            indices[k] = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(place_points(traj, ext, scans.points[part], scans.times[part])))
            indices[k].knn_index()
        ray = _shifted(pts.ray, pts.shift_gradient, shifts[pts.pair])
        found, dist2 = indices[k].knn_search(o3d.core.Tensor(pts.origin + ray), 1)
        g = found.numpy()[:, 0].astype(np.int64) + part.start
        keep = (dist2.numpy()[:, 0] < radius**2) & scans.planar[g]
        world_R_ref = traj.pose_and_rates(np.array([pts.time]))[0][0]  # the scan's turn over its sweep is neglected here
        normal = scans.normals[g[keep]] @ (world_R_ref @ ext.rotation).T
        along = np.abs(np.sum(normal * ray[keep], axis=1)) / np.linalg.norm(ray[keep], axis=1)
        weight = 1.0 / np.sqrt(PLANE_SIGMA**2 + scans.thickness[g[keep]] ** 2 + (along * pts.depth_sigma[keep]) ** 2)
        rows.append((g[keep], normal, pts.origin[keep], pts.ray[keep], pts.shift_gradient[keep],
                     np.full(keep.sum(), pts.pair), weight, np.full(keep.sum(), s)))
    return [np.concatenate(c) for c in zip(*rows)] if rows else None


def fit_instant(traj: ReferenceTrajectory, start: Extrinsic, scans: ScanSet, sets: Sequence[InstantPoints], pairs: int,
                radii: Sequence[float] = RADII, shift_sigma: Optional[np.ndarray] = None) -> Tuple[Extrinsic, np.ndarray, int, np.ndarray]:
    """Gauss-Newton (Huber IRLS) of the rotation, lever arm and the pairs' camera shifts, coarse to fine radii, each
    shift under a Gaussian prior of ``shift_sigma`` (pairs, 2; metres; inf or None: free; 0: held).

    Returns:
        (the estimate, the shifts (pairs, 2) m, rows used, the frame-clustered sigma in Jacobian order (rotation, lever
        arm; rad, m)).
    """
    ext, shifts, sigma, rows = start, np.zeros((pairs, 2)), np.full(6, np.inf), 0
    prior = np.zeros(2 * pairs) if shift_sigma is None else 1.0 / np.maximum(np.asarray(shift_sigma, dtype=np.float64).ravel(), 1e-9)
    for radius in radii:
        found = _rows(traj, ext, scans, sets, shifts, radius)
        if found is None or len(found[0]) < MIN_ROWS:
            return ext, shifts, 0 if found is None else len(found[0]), np.full(6, np.inf)
        g, normal, origin, ray0, gradient, pair, weight, which = found
        for _ in range(3):
            ray = _shifted(ray0, gradient, shifts[pair])
            nx, jac = placement_jacobian(traj, ext, np.zeros(7), scans.points[g], scans.times[g], normal)
            res = weight * (np.sum(normal * (origin + ray), axis=1) - nx)
            J = np.zeros((len(g), 6 + 2 * pairs))
            J[:, :6] = -weight[:, None] * jac[:, :6]
            for i in range(2):
                J[np.arange(len(g)), 6 + 2 * pair + i] = weight * np.sum(normal * ray0, axis=1) * gradient[:, i]
            root = np.sqrt(huber_weights(res, HUBER))
            # the shifts' prior: one row each, its own cluster
            J_all = np.vstack([J * root[:, None], np.hstack([np.zeros((len(prior), 6)), np.diag(prior)])])
            res_all = np.concatenate([res * root, prior * shifts.ravel()])
            step = np.linalg.lstsq(J_all, -res_all, rcond=None)[0]
            ext = ext.updated(np.concatenate([step[:6], [0.0]]))
            shifts = shifts + step[6:].reshape(pairs, 2)
        rows = len(g)
        sigma = least_squares_sigma(J_all, res_all, np.concatenate([which, -1 - np.arange(len(prior))])).sigma[:6]
    return ext, shifts, rows, sigma


def place_lidar(rig: Rig, calibration: Calibration, lidar: str, scans: ScanSet, cameras: Sequence[str],
                log: Callable[[str], None] = print, camera_sigma: Optional[Dict[str, Sequence[float]]] = None) -> "InstantPlacement | None":
    """The LiDAR ``lidar`` against ``cameras`` (registered, in ``calibration``) and the reference camera at the same
    instants, from its estimate in ``calibration``; None when no pair of them has ``MIN_BASELINE`` or ``MIN_ROWS``.

    Args:
        rig: the dataset (its reference sensor a camera).
        calibration: the cameras' and the LiDAR's current estimate.
        lidar: the LiDAR's name.
        scans: its scans (``lidar_scans.load_scans``).
        cameras: the cameras that may pair with the reference camera.
        log: where progress lines go.
        camera_sigma: per camera, its registration's sigma (Jacobian order: rad, m, s): the prior of its pair's shifts
            (``shift_sigmas``; none: free).
    """
    traj = ReferenceTrajectory.of(rig)
    ref = np.asarray(calibration.T_ref_sensor[rig.reference_sensor], dtype=np.float64)
    far = pairs_with_reference(rig, calibration)
    usable = [c for c in cameras if c in far]
    found = {c: instant_points(rig, traj, calibration, c, 0) for c in usable}
    usable = [c for c in usable if sum(len(p.ray) for p in found[c])]
    sets = [replace(p, pair=i) for i, c in enumerate(usable) for p in found[c]]
    if sum(len(s.ray) for s in sets) < MIN_ROWS:
        return None
    rot, _, _, velocity = traj.pose_and_rates(np.array([p.time for p in sets]))
    along = np.mean(np.einsum("nji,nj->ni", rot, velocity), axis=0)
    shift_sigma = np.stack([shift_sigmas(None if camera_sigma is None else camera_sigma.get(c), along,
                                         np.asarray(calibration.T_ref_sensor[c], dtype=np.float64)[:3, 3] - ref[:3, 3]) for c in usable])
    T = np.asarray(calibration.T_ref_sensor[lidar], dtype=np.float64)
    start = Extrinsic(T[:3, :3].copy(), T[:3, 3].copy(), float(calibration.time_offset[lidar]))
    # a moving car is not where both sensors see it: the cameras of a pair and the sweep are milliseconds apart, and
    # on a street the cars' fronts and backs are among the few surfaces that fix the along-track lever arm
    # (eight cars on the synthetic street seed 2 took it 1.34 m off, placed under a sigma of 8 cm; left out: 0.9 m
    # under 29 cm, not placed)
    moving = moving_points(traj, start, scans)
    scans = replace(scans, planar=scans.planar & ~moving)
    sets = [_off_movers(traj, start, scans, moving, s) for s in sets]
    whole, shifts, rows, formal = fit_instant(traj, start, scans, sets, len(usable), shift_sigma=shift_sigma)
    if rows < MIN_ROWS:
        return None
    middle = np.median([s.time for s in sets])
    halves = [fit_instant(traj, whole, scans, [s for s in sets if (s.time < middle) == first], len(usable), RADII[-3:], shift_sigma=shift_sigma)
              for first in (True, False)]
    apart = np.full(6, np.inf)
    if all(h[2] >= MIN_ROWS for h in halves):
        apart = np.abs(parameter_difference(halves[0][0].matrix(), 0.0, halves[1][0].matrix(), 0.0)[:6])
    fixed = fit_instant(traj, whole, scans, sets, len(usable), RADII[-3:], shift_sigma=np.zeros((len(usable), 2)))
    if fixed[2] >= MIN_ROWS:  # the pairs as calibrated: where the data pull the shifts where the cameras do not put them
        apart = np.fmax(apart, 2 * np.abs(parameter_difference(whole.matrix(), 0.0, fixed[0].matrix(), 0.0)[:6]))
    if len(usable) > 1:  # each camera pair alone: what the cameras' own calibration errors do
        alone = [fit_instant(traj, whole, scans, [replace(s, pair=0) for s in sets if s.pair == i], 1, RADII[-3:], shift_sigma=shift_sigma[i:i + 1])
                 for i in range(len(usable))]
        fits = [a[0].matrix() for a in alone if a[2] >= MIN_ROWS]
        for a in fits[1:]:
            apart = np.fmax(apart, np.abs(parameter_difference(fits[0], 0.0, a, 0.0)[:6]))
    sigma = [float(max(formal[JACOBIAN_ORDER[i]], apart[i] / 2)) for i in range(6)] + [float("nan")]
    placed = [p for p, s, typical in zip(PARAMETERS[:6], sigma, TEST_STEPS) if s <= typical]
    log(f"[camera-registration] {lidar} against {', '.join(usable)} at the same instants: {rows} rows ({moving.mean():.1%} of its points on movers, "
        "left out); sigma "
        + ", ".join(f"{p} {s * (100 if i < 3 else np.rad2deg(1.0)):.3g}" for i, (p, s) in enumerate(zip(PARAMETERS[:6], sigma)))
        + f" (cm, deg); pair shifts {', '.join('(' + ', '.join(f'{100 * v:.2f}' for v in d) + ')' for d in shifts)} cm under sigma "
        + f"{', '.join('(' + ', '.join(f'{100 * v:.3g}' for v in d) + ')' for d in shift_sigma)} cm; placed: {', '.join(placed) or 'nothing'}")
    return InstantPlacement(whole, sigma, placed, rows, list(usable), shifts.tolist(), [float(v) for v in along])

"""The view a LiDAR shares with the reference camera: its depth edges must fall on the reference camera's image edges.

Motion alone leaves a LiDAR's lever arm and its roll undetermined on a straight drive (``observability``), but the
reference camera's poses are known, and in a single frame a LiDAR point at a depth discontinuity (the near side of a
jump in range between neighbours of one ring: a pole, a car, a building corner) projects onto the occluding contour
the camera sees as an image edge. A lever-arm error of 10 cm moves those projections by ``f * 0.1 / depth`` pixels
(3.6 px at 10 m for KITTI at half size), whatever the drive does. Residual: the distance (pixels) from a LiDAR edge
point's projection, in the reference frame nearest its scan in time, to the nearest Canny edge of that image (a
distance transform, capped at ``MAX_DISTANCE``: chamfer matching, as edge-based LiDAR-camera calibration does,
e.g. Levinson and Thrun, RSS 2013; Yuan et al., RA-L 2021). Its derivative is the distance's image gradient pulled
back to the world, ``R (d u / d x_cam)^T grad D``, times eq. 1-2's placement Jacobian
(``lidar_geometry.placement_jacobian`` along that direction). The LiDAR-first stage fits these residuals jointly with
its point-to-plane ones, each kind in units of its own robust scatter (``lidar_first.SharedView``).

Measured and dropped first: two-view photometric consistency (a LiDAR point's grey level in two reference frames
1.5 m apart). Shifting the whole cloud moves both projections alike, so it sees the lever arm only through parallax
(sigma of the vertical and along-track lever arm 21 m and 68 m on a straight 320x240 street drive), and its coarse
pyramid levels prefer the cloud pushed 3 m ahead (less parallax, smaller differences). No nerfstudio import.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import List, Optional, Tuple

import numpy as np
import torch
from jaxtyping import Float, Int

from moisst_ns.rig.format import Rig
from moisst_ns.rig.geometry import row_times
from moisst_ns.stages.lidar_geometry import Extrinsic, Trajectory, place_points, placement_jacobian
from moisst_ns.stages.lidar_map import CameraStageError, ImageStack, PinholeModel, bilinear, project, visible

MIN_DEPTH = 3.0
"""Points nearer than this to the camera are not used (the vehicle, and a pixel's footprint varies fast), metres."""
MAX_DISTANCE = 30.0
"""The distance transform is capped here, pixels (beyond, a point has no edge to go to)."""
EDGE_PERCENTILES = (80.0, 92.0)
"""Canny's hysteresis thresholds: these percentiles of the image's gradient magnitude (adapts to each image's contrast
and exposure)."""
RING_BIN_DEG = 0.15
"""Points of one laser share an elevation: points are grouped into rings by elevation bins of this width, degrees."""
NEIGHBOUR_DEG = 0.6
"""Two points of a ring are neighbours when their azimuths differ by less than this, degrees."""
JUMP = (0.5, 0.1)
"""A point is a depth edge when a ring neighbour lies farther by more than ``JUMP[0]`` metres plus ``JUMP[1]`` of its
range (the near side of a discontinuity: its silhouette is what the camera sees)."""


@dataclass
class ReferenceView:
    """The reference camera's frames: known poses and each image's edge distance transform."""

    sensor: str
    stamps: Float[np.ndarray, "frames"]
    """Seconds since the trajectory's ``t0`` (reference clock)."""
    poses: Float[np.ndarray, "frames 4 4"]
    """``world_T_ref`` of every frame (eq. 1 at its stamp)."""
    distance: ImageStack
    """Distance to the nearest edge (pixels, capped at ``MAX_DISTANCE``) and its gradient, full resolution."""
    readout: float = 0.0
    """The camera's rolling-shutter readout time, seconds (0: global shutter: every point seen from ``poses``)."""


def reference_camera(traj: Trajectory, view: ReferenceView, frame: Int[np.ndarray, "num"], world: Float[np.ndarray, "num 3"]):
    """World points in their reference frames' camera frame, each from the pose at its row's time (a rolling shutter:
    ``geometry.row_times``; the reference camera's pose is eq. 1 itself).

    Returns:
        (camera-frame points, metres; and at each point's time: ``world_R_ref``, ``world_t_ref``, body angular rate
        (rad/s), velocity (m/s) (``Trajectory.pose_and_rates``))
    """
    def at(tau):
        rot, pos, omega, vel = traj.pose_and_rates(view.stamps[frame] + tau)
        return np.einsum("nji,nj->ni", rot, world - pos), rot, pos, omega, vel

    model = view.distance.model
    tau = row_times(lambda t: project(model, torch.from_numpy(at(t)[0]))[0][:, 1].numpy(), view.readout, model.height)
    return at(tau)


def edge_distance(grey: Float[np.ndarray, "h w"]) -> Float[np.ndarray, "h w"]:
    """Distance (pixels) from every pixel to the nearest Canny edge of ``grey`` (uint8), capped at ``MAX_DISTANCE``."""
    import cv2

    blurred = cv2.GaussianBlur(grey, (5, 5), 1.0)
    magnitude = np.hypot(cv2.Sobel(blurred, cv2.CV_32F, 1, 0), cv2.Sobel(blurred, cv2.CV_32F, 0, 1))
    low, high = np.percentile(magnitude, EDGE_PERCENTILES)
    edges = cv2.Canny(blurred, float(low), float(max(high, low + 1.0)), L2gradient=True)
    if not edges.any():
        return np.full(grey.shape, MAX_DISTANCE, dtype=np.float32)
    return np.minimum(cv2.distanceTransform(255 - edges, cv2.DIST_L2, 5), MAX_DISTANCE).astype(np.float32)


def reference_view(rig: Rig, traj: Trajectory) -> "ReferenceView | None":
    """The reference camera's frames, or None when the reference sensor is not a camera.

    Raises:
        CameraStageError: an image is missing, unreadable or not of rig.json's size.
    """
    import cv2

    ref = rig.reference_sensor
    if rig.sensors[ref].type != "camera":
        return None
    frames = sorted(rig.frames_of(ref), key=lambda f: f.timestamp)
    intr = rig.sensors[ref].intrinsics
    maps = []
    for frame in frames:
        path = rig.root / frame.file_path
        grey = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) if path.is_file() else None
        if grey is None or grey.shape != (int(intr["h"]), int(intr["w"])):
            raise CameraStageError(f"{path}: file_path: missing, not an image or not rig.json's {intr['w']}x{intr['h']} (sensors.{ref})")
        maps.append(edge_distance(grey))
    distance = np.stack(maps)
    gy, gx = np.gradient(distance, axis=(1, 2))
    stamps = np.array([f.timestamp for f in frames]) - float(rig.trajectory_stamps[0])
    rot, pos, _, _ = traj.pose_and_rates(stamps)
    poses = np.tile(np.eye(4), (len(stamps), 1, 1))
    poses[:, :3, :3], poses[:, :3, 3] = rot, pos
    return ReferenceView(ref, stamps, poses, ImageStack(distance, np.stack([gx, gy], axis=1).astype(np.float32), PinholeModel.of(intr)),
                         float(rig.sensors[ref].readout_time))


def depth_edges(points: Float[np.ndarray, "num 3"]) -> Int[np.ndarray, "edges"]:
    """Indices of a scan's points on the near side of a range discontinuity between neighbours of one ring.

    Args:
        points: one scan, in the LiDAR frame (z up, a spinning scanner), metres.

    Returns:
        Indices into ``points``.
    """
    rng = np.linalg.norm(points, axis=1)
    azimuth = np.degrees(np.arctan2(points[:, 1], points[:, 0]))
    ring = np.floor(np.degrees(np.arcsin(points[:, 2] / np.maximum(rng, 1e-9))) / RING_BIN_DEG).astype(np.int64)
    order = np.lexsort((azimuth, ring))
    r, az, rg = rng[order], azimuth[order], ring[order]
    same = (rg[1:] == rg[:-1]) & (np.abs(az[1:] - az[:-1]) < NEIGHBOUR_DEG)
    jump = r[1:] - r[:-1]
    near_prev = same & (jump < -(JUMP[0] + JUMP[1] * r[1:]))  # point i+1 nearer than its predecessor i
    near_next = same & (jump > JUMP[0] + JUMP[1] * r[:-1])  # point i nearer than its successor i+1
    edge = np.zeros(len(points), dtype=bool)
    edge[1:] |= near_prev
    edge[:-1] |= near_next
    return np.sort(order[edge])


@dataclass
class ViewRows:
    """Residual rows: point ``point`` (global scan index) seen in reference frame ``frame``."""

    point: Int[np.ndarray, "rows"]
    frame: Int[np.ndarray, "rows"]


def view_rows(traj: Trajectory, ext: Extrinsic, scans, view: ReferenceView, edges: List[np.ndarray], scan_ids,
              max_gap: float) -> ViewRows:
    """Each scan's depth-edge points that the reference frame nearest it in time sees unoccluded (z-buffer of the
    scan itself from that frame).

    Args:
        traj, ext: trajectory and the LiDAR calibration the scans are placed with.
        scans: the stage's ``ScanSet``.
        view: the reference camera's frames.
        edges: per scan, its depth-edge points (indices within the scan, ``depth_edges``).
        scan_ids: the scans to use.
        max_gap: a scan farther than this in time from every reference frame is not used, seconds.

    Returns:
        The rows (empty when no frame sees any edge point).
    """
    from moisst_ns.stages.camera_config import CameraRegistrationConfig  # its z-buffer settings, one place

    c = CameraRegistrationConfig()
    points, frames = [], []
    model = view.distance.model
    for k in scan_ids:
        gap = np.abs(view.stamps - (scans.stamps[k] + ext.time_offset))
        a = int(np.argmin(gap))
        if gap[a] > max_gap or len(edges[k]) == 0:
            continue
        part = scans.scan(int(k))
        world = place_points(traj, ext, scans.points[part], scans.times[part])
        if view.readout:
            cam = reference_camera(traj, view, np.full(len(world), a), world)[0]
        else:
            cam = (world - view.poses[a, :3, 3]) @ view.poses[a, :3, :3]
        uv, z = (t.numpy() for t in project(model, torch.from_numpy(cam)))
        seen = visible(uv, z, model, c.zbuffer_cell, c.occlusion_margin_m, c.occlusion_margin_fraction, c.max_depth) & (z > MIN_DEPTH)
        keep = edges[k][seen[edges[k]]]
        points.append(keep + part.start), frames.append(np.full(len(keep), a))
    if not points:
        return ViewRows(np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64))
    return ViewRows(np.concatenate(points), np.concatenate(frames))


def view_residuals(traj: Trajectory, ext: Extrinsic, scans, view: ReferenceView, rows: ViewRows,
                   increment: Float[np.ndarray, "7"]) -> Tuple[Float[np.ndarray, "rows"], Float[np.ndarray, "rows 7"]]:
    """Distance (pixels) from each row's projection at ``ext.updated(increment)`` to the nearest image edge, and its
    Jacobian with respect to ``increment`` (pixels per radian / metre / second). A projection that leaves the image
    reads the border (gradient 0 across it): scoring it otherwise made fits gain by pushing points out of the image.
    With a rolling shutter each point is seen from its row's pose, and the row moves with the point: at the fixed
    point ``tau = g(v)``, ``dtau/dx = g' dv/dx / (1 - g' dv/dtau)`` joins the projection's derivative."""
    cur = ext.updated(increment)
    points, times = scans.points[rows.point], scans.times[rows.point]
    world = place_points(traj, cur, points, times)
    stack = view.distance
    if view.readout:
        cam_np, rot, _, omega, vel = reference_camera(traj, view, rows.frame, world)
        cam = torch.from_numpy(cam_np).requires_grad_(True)
    else:
        poses = torch.from_numpy(view.poses[rows.frame])
        cam = torch.einsum("nji,nj->ni", poses[:, :3, :3], torch.from_numpy(world) - poses[:, :3, 3]).requires_grad_(True)
        rot = view.poses[rows.frame, :3, :3]
    uv, _ = project(stack.model, cam)
    du = torch.autograd.grad(uv[:, 0].sum(), cam, retain_graph=True)[0].numpy()
    dv = torch.autograd.grad(uv[:, 1].sum(), cam)[0].numpy()
    raw = uv.detach().numpy()
    limit = np.array([stack.model.width, stack.model.height], dtype=np.float64) - 0.5 - 1e-6
    clamped = np.clip(np.nan_to_num(raw, nan=0.5), 0.5, limit)
    value, grad, _ = bilinear(stack, rows.frame, clamped)
    grad = np.where(clamped == raw, grad, 0.0)
    direction = np.einsum("nij,nj->ni", rot, grad[:, :1] * du + grad[:, 1:] * dv)
    if view.readout:  # the row's time follows the point: d cam / d tau = -omega x cam - R^T velocity
        cam_tau = -np.cross(omega, cam_np) - np.einsum("nji,nj->ni", rot, vel)
        u_tau, v_tau = np.einsum("ni,ni->n", du, cam_tau), np.einsum("ni,ni->n", dv, cam_tau)
        g_v = view.readout / max(stack.model.height - 1, 1)
        tau_x = g_v * np.einsum("nij,nj->ni", rot, dv) / (1.0 - g_v * v_tau)[:, None]
        direction += (grad[:, 0] * u_tau + grad[:, 1] * v_tau)[:, None] * tau_x
    _, jac = placement_jacobian(traj, ext, increment, points, times, direction)
    return value, jac


@dataclass
class SharedView:
    """The shared-view part of the fit: the reference frames, every scan's depth edges and the current rows."""

    view: ReferenceView
    edges: List[np.ndarray]
    """Per scan, its depth-edge points (indices within the scan, ``lidar_view.depth_edges``)."""
    rows: Optional[ViewRows] = None
    scale: float = 0.0
    """Metres per pixel the edge distances are multiplied by in the joint fit: the point-to-plane residuals' robust
    scatter over the edge distances' (``1.4826 * median |r|`` of each, at the outer iteration's start)."""

    @classmethod
    def of(cls, rig: Rig, traj: Trajectory, scans) -> Optional["SharedView"]:
        """The shared view of the rig's reference camera for the ``lidar_first.ScanSet`` ``scans``, or None when the
        reference sensor is not a camera.

        Raises:
            CameraStageError: a reference image is missing, unreadable or not of rig.json's size.
        """
        view = reference_view(rig, traj)
        if view is None:
            return None
        return cls(view, [depth_edges(scans.points[scans.scan(k)]) for k in range(len(scans.stamps))])

    def at(self, traj: Trajectory, ext: Extrinsic, scans, pairs: np.ndarray, plane: Float[np.ndarray, "num"]) -> "SharedView":
        """The rows seen at ``ext`` by the scans of ``pairs`` (a scan pairs with the reference frame nearest it in time,
        within 0.6 of the reference camera's median frame interval) and their ``scale`` against the point-to-plane
        residuals ``plane`` (metres) of the same iteration."""
        gap = 0.6 * float(np.median(np.diff(self.view.stamps))) if len(self.view.stamps) > 1 else 0.05
        rows = view_rows(traj, ext, scans, self.view, self.edges, np.unique(pairs), gap)
        if len(rows.point) == 0 or len(plane) == 0:
            return replace(self, rows=rows, scale=0.0)
        edge = view_residuals(traj, ext, scans, self.view, rows, np.zeros(7))[0]
        return replace(self, rows=rows, scale=float(np.median(np.abs(plane)) / max(float(np.median(np.abs(edge))), 1e-3)))

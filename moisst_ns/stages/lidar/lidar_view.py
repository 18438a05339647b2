"""The view a LiDAR shares with the reference camera: its depth edges must fall on the reference camera's image edges.

Cost: the distance (pixels) from a LiDAR depth-edge point's projection, in the reference frame nearest its scan in
time, to the nearest Canny edge (chamfer matching, capped at ``MAX_DISTANCE``). The LiDAR-first stage uses it to place
what the drive's halves hold at the prior (``search_held``: a global grid confirmed per parameter, not a local fit).
docs/lidar-first.md, "The shared view", has the rules, what was tried and dropped, and the measurements
(docs/lab/2026-11-25-kitti-shared-view.md). No nerfstudio import.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable, List, Optional

import numpy as np
import torch
from jaxtyping import Float, Int

from moisst_ns.rig.format import Rig
from moisst_ns.rig.geometry import ReferenceTrajectory, row_times
from moisst_ns.rig.trust import finite_or_none
from moisst_ns.stages.lidar.lidar_edges import scan_edges
from moisst_ns.stages.lidar.lidar_geometry import Extrinsic, place_points, placer_at
from moisst_ns.stages.camera.lidar_map import ImageStack, PinholeModel, bilinear, project, read_grey, visible
from moisst_ns.stages.camera.photometric import huber_costs

MIN_DEPTH = 3.0
"""Points nearer than this to the camera are not used (the vehicle, and a pixel's footprint varies fast), metres."""
MAX_DISTANCE = 30.0
"""The distance transform is capped here, pixels (beyond, a point has no edge to go to)."""
EDGE_PERCENTILES = (80.0, 92.0)
"""Canny's hysteresis thresholds: these percentiles of the image's gradient magnitude (adapts to each image's contrast
and exposure)."""
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


def reference_camera(traj: ReferenceTrajectory, view: ReferenceView, frame: Int[np.ndarray, "num"],
                     world: Float[np.ndarray, "num 3"]) -> Float[np.ndarray, "num 3"]:
    """World points (metres) in their reference frames' camera frame, each from the pose at its row's time (a rolling
    shutter: ``geometry.row_times``; the reference camera's pose is eq. 1 itself; global shutter: ``view.poses``)."""
    if not view.readout:
        poses = view.poses[frame]
        return np.einsum("nji,nj->ni", poses[:, :3, :3], world - poses[:, :3, 3])

    def at(tau):
        rot, pos, _, _ = traj.pose_and_rates(view.stamps[frame] + tau)
        return np.einsum("nji,nj->ni", rot, world - pos)

    model = view.distance.model
    return at(row_times(lambda t: project(model, torch.from_numpy(at(t)))[0][:, 1].numpy(), view.readout, model.height))


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


def reference_view(rig: Rig, traj: ReferenceTrajectory) -> "ReferenceView | None":
    """The reference camera's frames, or None when the reference sensor is not a camera.

    Raises:
        CameraStageError: an image is missing, unreadable or not of rig.json's size.
    """
    ref = rig.reference_sensor
    if rig.sensors[ref].type != "camera":
        return None
    frames = sorted(rig.frames_of(ref), key=lambda f: f.timestamp)
    distance = np.stack([edge_distance(read_grey(rig, ref, frame.file_path)) for frame in frames])
    stamps = np.array([f.timestamp for f in frames]) - float(rig.trajectory_stamps[0])
    rot, pos, _, _ = traj.pose_and_rates(stamps)
    poses = np.tile(np.eye(4), (len(stamps), 1, 1))
    poses[:, :3, :3], poses[:, :3, 3] = rot, pos
    return ReferenceView(ref, stamps, poses, ImageStack.of(distance, PinholeModel.of(rig.sensors[ref].intrinsics)), float(rig.sensors[ref].readout_time))


@dataclass
class ViewRows:
    """Residual rows: point ``point`` (global scan index) seen in reference frame ``frame``."""

    point: Int[np.ndarray, "rows"]
    frame: Int[np.ndarray, "rows"]


def view_rows(traj: ReferenceTrajectory, ext: Extrinsic, scans, view: ReferenceView, edges: List[np.ndarray], scan_ids,
              max_gap: float) -> ViewRows:
    """Each scan's depth-edge points that the reference frame nearest it in time sees unoccluded (z-buffer of the
    scan itself from that frame).

    Args:
        traj, ext: trajectory and the LiDAR calibration the scans are placed with.
        scans: the stage's ``ScanSet``.
        view: the reference camera's frames.
        edges: per scan, its depth-edge points (indices within the scan, ``scan_edges``).
        scan_ids: the scans to use.
        max_gap: a scan farther than this in time from every reference frame is not used, seconds.

    Returns:
        The rows (empty when no frame sees any edge point).
    """
    points, frames = [], []
    model = view.distance.model
    for k in scan_ids:
        gap = np.abs(view.stamps - (scans.stamps[k] + ext.time_offset))
        a = int(np.argmin(gap))
        if gap[a] > max_gap or len(edges[k]) == 0:
            continue
        part = scans.scan(int(k))
        world = place_points(traj, ext, scans.points[part], scans.times[part])
        cam = reference_camera(traj, view, np.full(len(world), a), world)
        uv, z = (t.numpy() for t in project(model, torch.from_numpy(cam)))
        seen = visible(uv, z, model) & (z > MIN_DEPTH)
        keep = edges[k][seen[edges[k]]]
        points.append(keep + part.start), frames.append(np.full(len(keep), a))
    if not points:
        return ViewRows(np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64))
    return ViewRows(np.concatenate(points), np.concatenate(frames))


def view_residuals(traj: ReferenceTrajectory, ext: Extrinsic, scans, view: ReferenceView, rows: ViewRows,
                   increment: Float[np.ndarray, "7"], placer: Optional[Callable] = None) -> Float[np.ndarray, "rows"]:
    """Distance (pixels) from each row's projection at ``ext.updated(increment)`` to the nearest image edge. A
    projection that leaves the image reads the border: scoring it otherwise made fits gain by pushing points out of the
    image. With a rolling shutter each point is seen from its row's pose (``reference_camera``). ``placer``: eq. 1 at
    the rows' times and ``ext``'s time offset (``placer_at``), when the caller keeps it for increments that leave the
    time offset alone (``search_held``)."""
    moved = ext.updated(increment)
    world = place_points(traj, moved, scans.points[rows.point], scans.times[rows.point], None if increment[6] != 0 else placer)
    uv = project(view.distance.model, torch.from_numpy(reference_camera(traj, view, rows.frame, world)))[0].numpy()
    limit = np.array([view.distance.model.width, view.distance.model.height], dtype=np.float64) - 0.5 - 1e-6
    return bilinear(view.distance, rows.frame, np.clip(np.nan_to_num(uv, nan=0.5), 0.5, limit))[0]


@dataclass
class SharedView:
    """The reference camera's frames, every scan's depth edges and the rows seen at an estimate."""

    view: ReferenceView
    edges: List[np.ndarray]
    """Per scan, its depth-edge points (indices within the scan, ``lidar_edges.scan_edges``)."""
    spacing: float
    """The scans' median neighbour spacing (``lidar_edges.scan_edges``), radians."""
    rows: Optional[ViewRows] = None

    @classmethod
    def of(cls, rig: Rig, traj: ReferenceTrajectory, scans) -> Optional["SharedView"]:
        """The shared view of the rig's reference camera for the ``lidar_first.ScanSet`` ``scans``, or None when the
        reference sensor is not a camera.

        Raises:
            CameraStageError: a reference image is missing, unreadable or not of rig.json's size.
        """
        view = reference_view(rig, traj)
        if view is None:
            return None
        edges, spacing = zip(*(scan_edges(scans.points[scans.scan(k)]) for k in range(len(scans.stamps))))
        return cls(view, list(edges), float(np.median(spacing)))

    def bias(self, scans) -> Float[np.ndarray, "7"]:
        """Per Jacobian column, how far the depth edges' placement may be biased (m, rad; 0 for the time offset): half
        the neighbour spacing, at the rows' median range for a lever arm (``rows`` must be drawn: ``at``)."""
        ranges = np.linalg.norm(scans.points[self.rows.point], axis=1)
        return np.r_[np.full(3, self.spacing / 2), np.full(3, self.spacing / 2 * (np.median(ranges) if len(ranges) else 0.0)), 0.0]

    def at(self, traj: ReferenceTrajectory, ext: Extrinsic, scans, pairs: np.ndarray) -> "SharedView":
        """The rows seen at ``ext`` by the scans of ``pairs`` (a scan pairs with the reference frame nearest it in time,
        within 0.6 of the reference camera's median frame interval)."""
        gap = 0.6 * float(np.median(np.diff(self.view.stamps))) if len(self.view.stamps) > 1 else 0.05
        return replace(self, rows=view_rows(traj, ext, scans, self.view, self.edges, np.unique(pairs), gap))


# A global search of what the drive's motion left undetermined ----------------------------------------------------

GRID = (np.deg2rad(6.0), np.deg2rad(1.0), 0.6, 0.1)
"""Half-span and step of the shared view's coarse grid: rotations (rad), then the lever arm (m); a prior error beyond
the half-span is out of its reach."""
REFINEMENTS = 2
"""Finer grids after the coarse one, each a quarter of the previous step over one previous step either side."""
HUBER_PX = 2.0
"""The grid's cost: the mean Huber loss of the edge distances with this threshold, pixels."""
CONFIRM_SHARE = 0.95
"""A column is confirmed when the median edge distance, profiled along it around the grid's minimum (rows redrawn
there; two coarse steps either side, half a step apart), is least inside the profile in at least this share of
``BOOTSTRAP`` resamples of the reference frames (rows resampled frame by frame: the rows of one frame share its image
and pose; on 4 KITTI frames the median's profile had noise minima 10 % deep) and those minima scatter by at most the
stage's hold (``hold`` typical errors): that scatter is the column's sigma."""
BOOTSTRAP = 200


@dataclass
class ViewSearch:
    """What the shared view placed among the parameters the drive's motion left undetermined (``search_held``)."""

    columns: List[int]
    """The Jacobian columns searched (rotation vector 0-2, lever arm 3-5)."""
    accepted: List[int]
    """The columns the view placed (``search_held``'s rules)."""
    increment: Float[np.ndarray, "7"]
    """The grid's minimum on ``accepted`` (0 elsewhere): ``ext.updated(increment)`` is the placed estimate."""
    sigma: Float[np.ndarray, "7"]
    """Per column: the largest of half the halves' difference, the resamples' scatter, the finest step, the coupling
    shift and the depth edges' bias (half the neighbour spacing, at the rows' median range for a lever arm); NaN
    where not accepted; m, rad."""
    notes: List[str]
    """Why a column was not accepted, one entry each."""
    evaluations: int

    def to_json(self) -> dict:
        return {"columns": self.columns, "accepted": self.accepted, "increment": self.increment.tolist(),
                "sigma": [finite_or_none(v) for v in self.sigma], "notes": self.notes, "evaluations": self.evaluations}


def search_held(traj: ReferenceTrajectory, ext: Extrinsic, scans, shared: SharedView, pairs: np.ndarray, columns: List[int], hold: float,
                typical: Float[np.ndarray, "7"]) -> ViewSearch:
    """Place ``columns`` (the parameters the drive's motion left undetermined) by the shared view, the other parameters at
    ``ext``.

    Two costs of the edge distances, because neither alone is safe (docs/lab/2026-11-25-kitti-shared-view.md): the
    **mean** Huber cost (``HUBER_PX``) has a wide basin (on KITTI raw 0048 its joint grid took the roll from 5.2° to
    0.8° and the vertical lever arm from 50 to 2.5 cm) but is biased along the drive (it kept falling as the cloud
    moved 1 m forward: far points crowd towards the vanishing point's dense edges); the **median** is least at the
    factory calibration in every direction there, but its basin is narrow. So: a joint grid of the mean, coarse to fine
    (``GRID``, ``REFINEMENTS``), over ``columns``; then each column is confirmed by the median at the grid's minimum,
    with the rows (``shared.rows`` are those seen at ``ext``) drawn again there: its profile along the column is least
    inside it, robustly (``CONFIRM_SHARE``), and the halves of the drive (rows of the earlier and the later scans) put
    the mean's minimum within ``hold`` typical errors (``typical``, per column) of each other. A column that fails goes
    back to ``ext`` (the halves' failures together, then the least confirmed one at a time) and the grid is searched
    again over the others: their joint minimum with a wrong value of it is not theirs (KITTI raw 0048 with the
    lateral lever arm held 50 cm off: the roll placed 5.6° off before this rule). Last, **coupling**: each column
    left at ``ext`` is moved to either edge of the grid (what the search leaves undetermined, within its reach) and the
    grid searched again; a placed column whose minimum then moves by more than one typical error goes back too (there,
    with 2 typical errors instead, the vertical lever arm was placed 32 cm off beside a roll left 5° off), and the
    shift joins its sigma.

    Returns:
        The accepted columns, their increment and sigma (``ViewSearch``).
    """
    evaluations, at_times = 0, {}

    def distances(rows: ViewRows, increment: np.ndarray) -> np.ndarray:
        """``view_residuals`` with eq. 1 prepared once per row set (the search never moves the time offset;
        the rows are kept with it so that their ``id`` is not reused)."""
        nonlocal evaluations
        evaluations += 1
        if id(rows) not in at_times:
            at_times[id(rows)] = (rows, placer_at(traj, scans.times[rows.point], ext.time_offset))
        return view_residuals(traj, ext, scans, shared.view, rows, increment, at_times[id(rows)][1])

    def increment_of(cols: List[int], values: np.ndarray) -> np.ndarray:
        increment = np.zeros(7)
        increment[cols] = values
        return increment

    rows = shared.rows
    first = scans.stamps[np.searchsorted(scans.offsets, rows.point, side="right") - 1] < np.median(scans.stamps)
    span = lambda c: GRID[0] if c < 3 else GRID[2]  # a column's half-span and coarse step
    step = lambda c: GRID[1] if c < 3 else GRID[3]

    def grid(cols: List[int], centre: np.ndarray, spans: np.ndarray, steps: np.ndarray, base: np.ndarray):
        axes = [c + np.arange(-s, s + d / 2, d) for c, s, d in zip(centre, spans, steps)]
        values = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, len(cols))
        costs = np.array([(lambda h: (h.mean(), h[first].mean(), h[~first].mean()))(huber_costs(distances(rows, base + increment_of(cols, v)), HUBER_PX))
                          for v in values])
        return values[np.argmin(costs, axis=0)]  # minima of the whole drive, the first and the second half

    def joint(cols: List[int], base: np.ndarray):
        """The grid's minima over ``cols`` (coarse to fine) with the other columns at ``base``: whole drive, halves, and
        the finest step."""
        spans, finest = np.array([span(c) for c in cols]), np.array([step(c) for c in cols])
        best, a, b = grid(cols, np.zeros(len(cols)), spans, finest, base)
        for _ in range(REFINEMENTS):
            spans, finest = finest, finest / 4
            best, a, b = grid(cols, best, spans, finest, base)
        return best, a, b, finest

    cols = [c for c in columns if c < 6]
    if not cols or len(rows.point) == 0:
        return ViewSearch(list(columns), [], np.zeros(7), np.full(7, np.nan), ["no depth edge in view"] if cols else [], 0)
    notes: List[str] = []
    accepted, spread = cols, {}
    while accepted:  # the grid over what is left: a column sent back to ``ext`` changes the others' joint minimum
        best, a, b, finest = joint(accepted, np.zeros(7))
        found, halves, fine = dict(zip(accepted, best)), dict(zip(accepted, np.abs(a - b) / 2)), dict(zip(accepted, finest))
        apart = [c for c in accepted if halves[c] > hold * typical[c]]
        if apart:
            notes += [f"column {c}: the halves of the drive disagree" for c in apart]
            accepted = [c for c in accepted if c not in apart]
            continue
        at = increment_of(accepted, np.array([found[c] for c in accepted]))
        seen = shared.at(traj, ext.updated(at), scans, pairs).rows
        frames = np.unique(seen.frame)
        rng = np.random.default_rng(0)
        draws = [np.concatenate([np.flatnonzero(seen.frame == f) for f in rng.choice(frames, len(frames))]) for _ in range(BOOTSTRAP)]
        base = distances(seen, at)
        shares, profiles = {}, {}
        for c in accepted:
            offsets = np.arange(-4, 5) * step(c) / 2
            d = np.stack([base if o == 0 else distances(seen, at + increment_of([c], np.array([o]))) for o in offsets])
            profiles[c] = np.median(d, axis=1)
            low = np.argmin(np.stack([np.median(d[:, k], axis=1) for k in draws]), axis=1)  # per resample
            spread[c] = float(np.std(offsets[low]))
            shares[c] = float(np.mean((low > 0) & (low < len(offsets) - 1))) if spread[c] <= hold * typical[c] else 0.0
        worst = min(accepted, key=lambda c: shares[c])
        if shares[worst] < CONFIRM_SHARE:  # only the least confirmed goes back: a column at a wrong minimum spoils the others
            notes.append(f"column {worst}: the median edge distance does not confirm the mean's minimum ("
                         + ", ".join(f"{v:.2f}" for v in profiles[worst]) + f" px, two coarse steps either side; least inside in {shares[worst]:.0%} of resamples, scatter {spread[worst]:.3g})")
            accepted = [c for c in accepted if c != worst]
            continue
        shift = {c: 0.0 for c in accepted}  # what the columns left undetermined could do to the placed ones
        for r in (c for c in cols if c not in accepted):
            for sign in (-1.0, 1.0):
                again = joint(accepted, increment_of([r], np.array([sign * span(r)])))[0]
                for c, v in zip(accepted, again):
                    shift[c] = max(shift[c], abs(v - found[c]))
        worst = max(accepted, key=lambda c: shift[c] / typical[c])
        if shift[worst] <= typical[worst]:
            break
        notes.append(f"column {worst}: its minimum moves by {shift[worst]:.3g} when a column the view does not place moves "
                     "across the grid")
        accepted = [c for c in accepted if c != worst]
    increment, sigma = np.zeros(7), np.full(7, np.nan)
    bias = shared.bias(scans)
    for c in accepted:
        increment[c], sigma[c] = found[c], max(halves[c], spread[c], fine[c], shift[c], bias[c])
    return ViewSearch(list(columns), accepted, increment, sigma, notes, evaluations)

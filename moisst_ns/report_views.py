"""The report's pictures (``moisst-report``, ``moisst_ns.report``): (a) LiDAR points over camera frames with the prior
and the calibrated rig, (b) the model's render at a camera frame's calibrated pose with the calibrated LiDAR points
and the median depth residual between them (the run's scene check). Poses come from the rig's pose model (eq. 1-2),
projection and drawing from ``report_images``; ``make_renders`` imports nerfstudio, the rest does not.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import numpy as np

from moisst_ns.report_images import depth_colors, depth_range, draw_points, pick_evenly, project_points, side_by_side


# --- rig poses of LiDAR and camera frames ---------------------------------------------------------------------


def lidar_points_world(calib, sensor: int, stamp_rel: float, points: np.ndarray, times: Optional[np.ndarray], prior: bool) -> np.ndarray:
    """A LiDAR scan in the world frame: each point at the pose of its own time (de-skewed by the rig model).

    Args:
        calib: the run's ``RigCalibration``.
        sensor: the LiDAR's sensor index.
        stamp_rel: the frame's own-clock stamp minus ``t0``, seconds.
        points: (N, 3) points in the LiDAR frame.
        times: (N,) per-point offsets from the stamp, or None (all at the stamp).
        prior: use the priors instead of the calibration.

    Returns:
        (N, 3) world points, metres, float64.
    """
    stamps = np.full(1, stamp_rel) if times is None else stamp_rel + np.asarray(times, dtype=np.float64)
    poses = sensor_poses(calib, sensor, stamps, prior)
    pts = np.asarray(points, dtype=np.float64)
    if times is None:
        return pts @ poses[0, :3, :3].T + poses[0, :3, 3]
    return np.einsum("nij,nj->ni", poses[:, :3, :3], pts) + poses[:, :3, 3]


def sensor_poses(calib, sensor: int, stamps_rel: np.ndarray, prior: bool) -> np.ndarray:
    """(N, 4, 4) ``world_T_sensor`` (metres) of one sensor at own-clock times minus ``t0``, with the calibration (or
    the priors)."""
    import torch

    fn = calib.prior_sensor_poses if prior else calib.sensor_poses
    device = calib.prior_extrinsics.device
    with torch.no_grad():
        stamps = torch.as_tensor(stamps_rel, dtype=torch.float64, device=device)
        return fn(torch.full(stamps.shape, sensor, dtype=torch.long, device=device), stamps).cpu().numpy()


def project_scans(calib, scans, camera: int, stamp_rel: float, intrinsics, prior: bool):
    """Every scan of ``_scans`` projected into a camera frame (sensor ``camera`` at ``stamp_rel``): concatenated
    ``report_images.project_points`` outputs (uv, z, mask)."""
    cam_pose = sensor_poses(calib, camera, np.full(1, stamp_rel), prior)[0]
    parts = [project_points(lidar_points_world(calib, lidar, t_lidar, points, times, prior), cam_pose, intrinsics)
             for _, _, lidar, t_lidar, points, times in scans]
    return tuple(np.concatenate(p) for p in zip(*parts))


def nearest_lidar_frames(rig, calib, camera: str, stamp: float) -> List[Tuple[str, Any]]:
    """For each LiDAR of the rig, its frame nearest in reference-clock time (calibrated offsets) to a camera frame.

    Args:
        rig: the dataset's ``Rig``.
        calib: the run's ``RigCalibration``.
        camera: the camera's name.
        stamp: the camera frame's own-clock stamp (absolute).

    Returns:
        ``[(lidar name, FrameSpec)]``.
    """
    names = calib.data.sensor_names
    deltas = calib.time_offsets().detach().cpu().numpy()
    t_ref = stamp + deltas[names.index(camera)]
    out = []
    for name, spec in rig.sensors.items():
        if spec.type != "lidar":
            continue
        frames = rig.frames_of(name)
        times = np.array([f.timestamp for f in frames]) + deltas[names.index(name)]
        out.append((name, frames[int(np.argmin(np.abs(times - t_ref)))]))
    return out


# --- the report -----------------------------------------------------------------------------------------------


@dataclass
class _Overlay:
    """One prior / calibrated overlay pair, as report.md lists it."""

    camera: str
    """Camera name."""
    frame: int
    """Index of the frame among the camera's frames (rig.json order)."""
    lidar_frames: str
    """The LiDAR frames drawn (``<lidar> <file name>``, comma separated)."""
    prior_in_image: int
    """Points inside the image with the priors."""
    calibrated_in_image: int
    """Points inside the image with the calibration."""
    files: Dict[str, str]
    """``prior``, ``calibrated``, ``side_by_side`` -> PNG path."""


def _save(image: np.ndarray, path: Path) -> str:
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.asarray(image, dtype=np.uint8)).save(path)
    return path.as_posix()


def _scans(rig, calib, camera: str, stamp: float, min_range: float, max_range: float):
    from moisst_ns.rig.format import load_lidar_scan

    names = calib.data.sensor_names
    for lidar, frame in nearest_lidar_frames(rig, calib, camera, stamp):
        points, times, _ = load_lidar_scan(rig.root / frame.file_path, min_range=min_range)
        keep = np.linalg.norm(points, axis=1) <= max_range
        yield lidar, frame, names.index(lidar), frame.timestamp - calib.data.t0, points[keep], None if times is None else times[keep]


def make_overlays(rig, calib, out_dir: Path, frames_per_camera: int, min_range: float, max_range: float) -> List[_Overlay]:
    """(a): prior vs calibrated LiDAR overlays for ``frames_per_camera`` frames of every camera."""
    from PIL import Image

    names = calib.data.sensor_names
    results = []
    for camera, spec in rig.sensors.items():
        if spec.type != "camera":
            continue
        intr, frames = spec.intrinsics, rig.frames_of(camera)
        for k in pick_evenly(len(frames), frames_per_camera):
            frame = frames[k]
            with Image.open(rig.root / frame.file_path) as img:
                image = np.asarray(img.convert("RGB"))
            t_cam = frame.timestamp - calib.data.t0
            scans = list(_scans(rig, calib, camera, frame.timestamp, min_range, max_range))
            used = [f"{lidar} {Path(lframe.file_path).name}" for lidar, lframe, *_ in scans]
            projected = {mode: project_scans(calib, scans, names.index(camera), t_cam, intr, mode == "prior") for mode in ("prior", "calibrated")}
            vmin, vmax = depth_range(*(z[m] for _, z, m in projected.values()))
            radius = max(0, round(image.shape[1] / 640))
            panels = {mode: draw_points(image, uv, z, mask, vmin, vmax, radius) for mode, (uv, z, mask) in projected.items()}
            files = {mode: _save(panel, out_dir / "overlays" / f"{camera}_{k:04d}_{mode}.png") for mode, panel in panels.items()}
            files["side_by_side"] = _save(side_by_side(panels["prior"], panels["calibrated"]), out_dir / "overlays" / f"{camera}_{k:04d}_side_by_side.png")
            counts = [int(projected[mode][2].sum()) for mode in ("prior", "calibrated")]
            results.append(_Overlay(camera, k, ", ".join(used), *counts, files))
    return results


def training_index(optimizer, sensor: int, stamp_rel: float) -> int:
    """Index of a camera frame among the run's training frames (matched by sensor and stamp)."""
    sensors = optimizer.frame_sensor.cpu().numpy()
    stamps = optimizer.frame_stamps.cpu().numpy()
    hits = np.flatnonzero((sensors == sensor) & (np.abs(stamps - stamp_rel) < 1e-9))
    if hits.size == 0:
        raise ValueError(f"sensor {sensor} frame at {stamp_rel} s is not a training frame of the run")
    return int(hits[0])


def make_renders(rig, pipeline, out_dir: Path, render_width: int, min_range: float, max_range: float) -> List[Dict[str, Any]]:
    """(b): per camera, the model's render at its first frame's calibrated pose, with the calibrated LiDAR points."""
    import torch

    from nerfstudio.cameras.cameras import CAMERA_MODEL_TO_TYPE, Cameras

    model = pipeline.model
    opt = model.camera_optimizer
    calib = opt.rig
    names = calib.data.sensor_names
    results = []
    was_training = model.training
    model.eval()
    try:
        for camera, spec in rig.sensors.items():
            if spec.type != "camera":
                continue
            intr, frame = spec.intrinsics, rig.frames_of(camera)[0]
            t_cam = frame.timestamp - calib.data.t0
            index = training_index(opt, names.index(camera), t_cam)
            with torch.no_grad():
                c2w = opt.frame_c2w(torch.tensor([index]))[:, :3, :4].float().cpu()
            cameras = Cameras(
                camera_to_worlds=c2w,
                fx=float(intr["fl_x"]), fy=float(intr["fl_y"]), cx=float(intr["cx"]), cy=float(intr["cy"]),
                width=int(intr["w"]), height=int(intr["h"]),
                distortion_params=torch.tensor([[intr["k1"], intr["k2"], intr.get("k3", 0.0), intr.get("k4", 0.0), intr["p1"], intr["p2"]]]).float(),
                camera_type=CAMERA_MODEL_TO_TYPE[intr["camera_model"]],
            )
            scale = min(1.0, render_width / float(intr["w"]))
            if scale < 1.0:
                cameras.rescale_output_resolution(scale)
            with torch.no_grad():
                outputs = model.get_outputs_for_camera(cameras)
                norms = cameras.generate_rays(camera_indices=0, keep_shape=True).metadata["directions_norm"]
            rgb = (outputs["rgb"].clamp(0, 1).cpu().numpy() * 255.0 + 0.5).astype(np.uint8)
            # distance along the ray (model units) -> camera z-depth in metres
            depth_z = (outputs["expected_depth"].cpu() / norms.cpu()).numpy()[..., 0] / float(opt.world_scale)
            small = {"fl_x": float(cameras.fx), "fl_y": float(cameras.fy), "cx": float(cameras.cx), "cy": float(cameras.cy),
                     "w": int(cameras.width), "h": int(cameras.height)}
            small.update({k: intr.get(k, 0.0) for k in ("k1", "k2", "k3", "k4", "p1", "p2")})
            scans = _scans(rig, calib, camera, frame.timestamp, min_range, max_range)
            uv, z, mask = project_scans(calib, scans, names.index(camera), t_cam, small, prior=False)
            vmin, vmax = depth_range(z[mask])
            stem = out_dir / "renders" / f"{camera}_0000"  # its first frame
            files = {
                "rendered": _save(rgb, stem.with_name(stem.name + "_rendered.png")),
                "rendered_depth": _save(depth_colors(depth_z.ravel(), vmin, vmax).reshape(*depth_z.shape, 3), stem.with_name(stem.name + "_rendered_depth.png")),
                "rendered_lidar": _save(draw_points(rgb, uv, z, mask, vmin, vmax), stem.with_name(stem.name + "_rendered_lidar.png")),
            }
            cols, rows = np.floor(uv[mask, 0]).astype(int), np.floor(uv[mask, 1]).astype(int)
            residual = np.abs(depth_z[rows, cols] - z[mask])
            results.append({"camera": camera, "size": (int(cameras.width), int(cameras.height)), "files": files, "points": int(mask.sum()),
                            "median_depth_residual_m": float(np.median(residual)) if residual.size else float("nan"),
                            "median_lidar_depth_m": float(np.median(z[mask])) if residual.size else float("nan")})
    finally:
        model.train(was_training)
    return results

"""Test helper: write a tiny KITTI-360 sequence, in exactly the dataset's download layout, from a synthetic rig.

The truth is known: ``image_00`` = moisst-synth's reference ``cam_front`` (its rectified frame), ``image_01`` =
``cam_front_right``, ``image_02`` = ``cam_left`` rendered with a MEI fisheye model, ``velodyne`` = ``lidar``.
The vehicle pose frame, ``R_rect_00`` and ``R_rect_01`` are arbitrary non-trivial transforms, so a loader that
composes them wrongly does not recover the rig. Timestamps are written on the reference clock (true offsets
folded in), as KITTI-360 assumes its own timestamps are right: the dataset's calibration is then the exact truth.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from moisst_ns.datasets.kitti360 import MeiCamera, format_timestamp
from moisst_ns.datasets.rig_writer import inverse, rigid
from moisst_ns.rig.format import load_lidar_scan, load_rig, load_tum
from moisst_ns.datasets.synth import SynthConfig, build_scene, make_path, make_rig
from moisst_ns.datasets.synth_rig import _orthonormalise, rot_x, rot_y, rot_z

SEQUENCE = "2013_05_28_drive_0000_sync"
BASE_NS = int(np.datetime64("2013-05-28T08:00:00", "ns").astype(np.int64))
NAMES = {"image_00": "cam_front", "image_01": "cam_front_right", "image_02": "cam_left", "velodyne": "lidar"}
# Pose frame (x forward, y left, z up) <- unrectified camera 0, and the two rectifying rotations.
POSE_T_CAM0 = np.array([[0.0371, -0.0476, 0.9982, 1.5], [-0.9993, 0.0019, 0.0372, 0.03], [-0.0036, -0.9989, -0.0475, -0.2], [0, 0, 0, 1.0]])
R_RECT_00 = rot_x(0.004) @ rot_y(-0.003) @ rot_z(0.002)
R_RECT_01 = rot_x(-0.002) @ rot_y(0.005) @ rot_z(-0.001)
SKIPPED_POSE = 3  # "not every frame has a pose"


def _orthonormal(pose: np.ndarray) -> np.ndarray:
    out = pose.copy()
    out[:3, :3] = _orthonormalise(pose[:3, :3])
    return out


def _row(pose: np.ndarray, rows: int = 3) -> str:
    return " ".join(repr(float(v)) for v in pose[:rows].reshape(-1))


def fisheye_model(size: int) -> MeiCamera:
    """A MEI model covering a bit more than a hemisphere on a size x size image."""
    return MeiCamera(xi=1.2, k1=0.05, k2=0.01, p1=2e-4, p2=-1e-4, gamma1=0.56 * size, gamma2=0.55 * size,
                     u0=(size - 1) / 2.0 + 0.3, v0=(size - 1) / 2.0 - 0.2, width=size, height=size)


def mei_unproject(camera: MeiCamera, pixels: np.ndarray) -> np.ndarray:
    """Unit ray directions (N, 3) of pixels (N, 2) (pixel centres at integers) of a MEI camera: the inverse of
    ``MeiCamera.project``, the distortion inverted with OpenCV's iteration."""
    import cv2

    c = camera
    uv = np.asarray(pixels, dtype=np.float64).reshape(-1, 1, 2)
    K = np.array([[c.gamma1, 0.0, c.u0], [0.0, c.gamma2, c.v0], [0.0, 0.0, 1.0]])
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    m = cv2.undistortPointsIter(uv, K, np.array([c.k1, c.k2, c.p1, c.p2]), None, None, criteria).reshape(-1, 2)
    r2 = (m * m).sum(axis=1)
    factor = (c.xi + np.sqrt(1.0 + (1.0 - c.xi**2) * r2)) / (1.0 + r2)
    d = np.stack([factor * m[:, 0], factor * m[:, 1], factor - c.xi], axis=1)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def write_sample(root: Path, native: Path | None = None, width: int = 64, height: int = 48, frames: int = 8,
                 seed: int = 3, fisheye_size: int = 96) -> dict:
    """Write ``root`` (KITTI-360 layout) and, unless given, the native synthetic rig it comes from.

    Returns:
        {"root", "native", "sequence", "truth": {kitti sensor: T_rect0_sensor}, "stamps": {kitti sensor: seconds on
        the reference clock}, "fisheye": MeiCamera}
    """
    from PIL import Image

    config = SynthConfig(out=native or root.parent / "native", width=width, height=height, frames=frames, seed=seed,
                         perturb="none")
    if native is None:
        make_rig(config)
    rig = load_rig(config.out)
    gt = json.loads((config.out / "ground_truth.json").read_text())["sensors"]
    truth = {k: np.array(gt[v]["T_ref_sensor"]) for k, v in NAMES.items()}
    offsets = {k: gt[v]["time_offset"] for k, v in NAMES.items()}

    pose_T_rect0 = _orthonormal(POSE_T_CAM0) @ rigid(R_RECT_00.T)
    cam_to_pose = {
        "image_00": _orthonormal(POSE_T_CAM0),
        "image_01": pose_T_rect0 @ truth["image_01"] @ rigid(R_RECT_01),
        "image_02": pose_T_rect0 @ truth["image_02"],
        # no image_03 in this sample: the calibration files still list it, as the real ones do
        "image_03": pose_T_rect0 @ truth["image_02"] @ rigid(rot_z(np.pi)),
    }
    velo_T_cam0 = inverse(truth["velodyne"]) @ rigid(R_RECT_00)

    seq = root / "data_2d_raw" / SEQUENCE
    calib = root / "calibration"
    calib.mkdir(parents=True)
    (calib / "calib_cam_to_pose.txt").write_text("".join(f"{k}: {_row(v)}\n" for k, v in cam_to_pose.items()))
    (calib / "calib_cam_to_velo.txt").write_text(_row(velo_T_cam0) + "\n")
    intr = rig.sensors["cam_front"].intrinsics
    K = np.array([[intr["fl_x"], 0.0, intr["cx"] - 0.5], [0.0, intr["fl_y"], intr["cy"] - 0.5], [0.0, 0.0, 1.0]])
    lines = ["calib_time: 09-Jan-2012 13:57:47", "corner_dist: 9.950000e-02"]
    for n, R, baseline in (("00", R_RECT_00, 0.0), ("01", R_RECT_01, -0.6 * intr["fl_x"])):
        P = np.hstack([K, np.array([[baseline], [0.0], [0.0]])])
        lines += [f"S_{n}: 1.392000e+03 5.120000e+02", f"S_rect_{n}: {width}.0 {height}.0",
                  f"R_rect_{n}: {_row(R)}", f"P_rect_{n}: {_row(P)}"]
    (calib / "perspective.txt").write_text("\n".join(lines) + "\n")
    mei = fisheye_model(fisheye_size)
    for cam in ("image_02", "image_03"):
        (calib / f"{cam}.yaml").write_text(
            "%YAML:1.0\n---\nmodel_type: MEI\n" f"camera_name: {cam}\nimage_width: {mei.width}\nimage_height: {mei.height}\n"
            f"mirror_parameters:\n   xi: {mei.xi!r}\n"
            f"distortion_parameters:\n   k1: {mei.k1!r}\n   k2: {mei.k2!r}\n   p1: {mei.p1!r}\n   p2: {mei.p2!r}\n"
            f"projection_parameters:\n   gamma1: {mei.gamma1!r}\n   gamma2: {mei.gamma2!r}\n   u0: {mei.u0!r}\n   v0: {mei.v0!r}\n"
        )

    # Timestamps on the reference clock (truth folded in), as KITTI-360's own.
    stamps = {}
    for kitti, name in NAMES.items():
        own = np.array([f.timestamp for f in rig.frames_of(name)])
        stamps[kitti] = own + offsets[kitti]
        folder = (root / "data_3d_raw" / SEQUENCE / "velodyne_points") if kitti == "velodyne" else seq / kitti
        folder.mkdir(parents=True)
        ns = BASE_NS + np.round(stamps[kitti] * 1e9).astype(np.int64)
        (folder / "timestamps.txt").write_text("".join(format_timestamp(int(t)) + "\n" for t in ns))

    # Frames.
    for kitti in ("image_00", "image_01"):
        (seq / kitti / "data_rect").mkdir()
        for k, f in enumerate(rig.frames_of(NAMES[kitti])):
            shutil.copyfile(rig.root / f.file_path, seq / kitti / "data_rect" / f"{k:010d}.png")
    velo = root / "data_3d_raw" / SEQUENCE / "velodyne_points" / "data"
    velo.mkdir()
    for k, f in enumerate(rig.frames_of("lidar")):
        points, _, _ = load_lidar_scan(rig.root / f.file_path)
        np.hstack([points, np.zeros((len(points), 1), np.float32)]).astype(np.float32).tofile(velo / f"{k:010d}.bin")

    # The fisheye camera, rendered through the MEI model at cam_left's true poses.
    import torch

    from moisst_ns.rig.geometry import ReferenceTrajectory

    traj = ReferenceTrajectory.from_tum(*load_tum(rig.root / rig.trajectory_file))
    scene = build_scene(config, make_path(config))
    (seq / "image_02" / "data_rgb").mkdir()
    uu, vv = np.meshgrid(np.arange(mei.width, dtype=np.float64), np.arange(mei.height, dtype=np.float64))
    dirs_cam = mei_unproject(mei, np.stack([uu.ravel(), vv.ravel()], axis=1))
    for k, t in enumerate(stamps["image_02"]):
        world_T_cam = traj(torch.tensor([t], dtype=torch.float64) - traj.t0)[0].numpy() @ truth["image_02"]
        rgb, _ = scene.colour(world_T_cam[:3, 3], dirs_cam @ world_T_cam[:3, :3].T, 1.0 / mei.gamma1)
        image = (np.clip(rgb.reshape(mei.height, mei.width, 3), 0, 1) * 255 + 0.5).astype(np.uint8)
        Image.fromarray(image).save(seq / "image_02" / "data_rgb" / f"{k:010d}.png")

    # Poses at image_00 frames, one frame without a pose.
    poses_dir = root / "data_poses" / SEQUENCE
    poses_dir.mkdir(parents=True)
    ref = traj(torch.from_numpy(stamps["image_00"]) - traj.t0).numpy()
    keep = [k for k in range(len(ref)) if k != SKIPPED_POSE]
    (poses_dir / "poses.txt").write_text("".join(f"{k} {_row(ref[k] @ inverse(pose_T_rect0))}\n" for k in keep))
    (poses_dir / "cam0_to_world.txt").write_text("".join(f"{k} {_row(ref[k], 4)}\n" for k in keep))
    return {"root": root, "native": config.out, "sequence": SEQUENCE, "truth": truth, "stamps": stamps, "fisheye": mei,
            "reference_poses": ref, "pose_frames": keep}

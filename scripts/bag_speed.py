#!/usr/bin/env python
"""Issue 39's speed target: a 60 s bag with 3 cameras at 10 Hz and a LiDAR at 10 Hz converts in <= 60 s on 2 cores,
memory bounded by one frame per topic.

Writes a synthetic bag into /tmp (rosbags' writer, through tests/test_bags.py's ``BagWriter``): 3 raw rgb8 cameras
(640x480 by default, with camera_info), an Ouster-like LiDAR (64 x 1024 points: x, y, z, intensity float32, t uint32
ns), /odom Odometry at 100 Hz and /tf_static; then runs ``moisst-bag-to-rig`` on it as a child process and prints its
wall time and peak RSS (the child's, from getrusage). Run it with OMP_NUM_THREADS=1 on a shared machine:

    OMP_NUM_THREADS=1 .venv/bin/python scripts/bag_speed.py [--format ros1|mcap|sqlite3] [--seconds 60]
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from test_bags import BagWriter  # noqa: E402


def texture(width: int, height: int, rng: np.random.Generator) -> np.ndarray:
    """A smooth colour pattern with mild noise (PNG compresses it like a camera frame, not like white noise)."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float32)
    rgb = np.stack([np.sin(u / 17.0) + np.cos(v / 23.0), np.sin((u + v) / 31.0), np.cos(u / 11.0 - v / 29.0)], axis=-1)
    rgb = (rgb - rgb.min()) / (rgb.max() - rgb.min()) * 220.0 + rng.normal(0.0, 4.0, rgb.shape)
    return np.clip(rgb, 0, 255).astype(np.uint8)


def write_bag(path: Path, kind: str, seconds: float, width: int, height: int, beams: int, columns: int) -> None:
    rng = np.random.default_rng(0)
    base = texture(width + 200, height, rng)
    t0 = 1_700_000_000 * 10**9
    period = 10**8
    cams = ("cam_front", "cam_left", "cam_right")
    intr = {"w": width, "h": height, "fl_x": 0.8 * width, "fl_y": 0.8 * width, "cx": width / 2, "cy": height / 2}
    azimuth = np.repeat(np.linspace(0.0, 2 * np.pi, columns, endpoint=False), beams)
    elevation = np.tile(np.deg2rad(np.linspace(-22.5, 22.5, beams)), columns)
    ranges = 5.0 + 20.0 * rng.random(beams * columns)
    xyz = np.stack([ranges * np.cos(elevation) * np.cos(azimuth), ranges * np.cos(elevation) * np.sin(azimuth),
                    ranges * np.sin(elevation)], axis=1).astype(np.float32)
    t_ns = (np.repeat(np.arange(columns), beams) * (period // columns)).astype(np.uint32)
    with BagWriter(path, kind) as bag:
        edges = [("base_link", c, np.eye(4)) for c in cams] + [("base_link", "os_lidar", np.eye(4))]
        bag.write("/tf_static", bag.transforms(t0, edges), t0)
        steps = int(round(seconds * 100))
        for step in range(steps):  # 10 ms steps: odometry every step, sensors every 10th at their own phase
            ns = t0 + step * period // 10
            pose = np.eye(4)
            pose[0, 3] = 8.0 * step / 100
            bag.write("/odom", bag.odometry(ns, "map", "base_link", pose), ns + 2_000_000)
            k, phase = divmod(step, 10)
            if phase in (0, 3, 6):
                name = cams[phase // 3]
                bag.write(f"/{name}/camera_info", bag.camera_info(ns, name, intr), ns + 5_000_000)
                shift = (k * 7 + phase * 13) % 200
                bag.write(f"/{name}/image_raw", bag.image(ns, name, base[:, shift:shift + width], "rgb8"), ns + 5_000_000)
            if phase == 8:
                cloud = bag.cloud(ns, "os_lidar", x=xyz[:, 0] + np.float32(0.01 * k), y=xyz[:, 1], z=xyz[:, 2],
                                  intensity=np.full(len(xyz), 100.0, np.float32), t=t_ns)
                bag.write("/os_lidar/points", cloud, ns + 8_000_000)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--format", choices=("ros1", "mcap", "sqlite3"), default="ros1")
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--beams", type=int, default=64)
    parser.add_argument("--columns", type=int, default=1024)
    parser.add_argument("--dir", type=Path, default=Path("/tmp/moisst-bag-speed"))
    parser.add_argument("--keep", action="store_true", help="keep the bag and the rig")
    args = parser.parse_args()

    shutil.rmtree(args.dir, ignore_errors=True)
    args.dir.mkdir(parents=True)
    bag = args.dir / ("drive.bag" if args.format == "ros1" else "drive")
    start = time.perf_counter()
    write_bag(bag, args.format, args.seconds, args.width, args.height, args.beams, args.columns)
    size = sum(p.stat().st_size for p in ([bag] if bag.is_file() else bag.rglob("*")))
    print(f"bag: {bag} ({args.format}, {size / 2**30:.2f} GiB, {args.seconds:g} s: 3 cameras {args.width}x{args.height} rgb8 "
          f"at 10 Hz, LiDAR {args.beams}x{args.columns} points at 10 Hz, odometry at 100 Hz) written in {time.perf_counter() - start:.1f} s")

    cams = [f"--camera=/{c}/image_raw" for c in ("cam_front", "cam_left", "cam_right")]
    cmd = [str(Path(sys.executable).parent / "moisst-bag-to-rig"), str(bag), "--out", str(args.dir / "rig"), "--trajectory", "/odom",
           *cams, "--lidar", "/os_lidar/points"]
    print("$ " + " ".join(cmd), flush=True)
    start = time.perf_counter()
    result = subprocess.run(cmd, env={**os.environ, "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1")})
    wall = time.perf_counter() - start
    peak_mib = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024  # KiB on Linux
    out = sum(p.stat().st_size for p in (args.dir / "rig").rglob("*") if p.is_file()) if result.returncode == 0 else 0
    frame_mib = args.width * args.height * 3 / 2**20
    print(f"conversion: exit {result.returncode}, wall {wall:.1f} s (target <= 60 s), peak RSS {peak_mib:.0f} MiB "
          f"(one image is {frame_mib:.2f} MiB, one scan {args.beams * args.columns * 20 / 2**20:.2f} MiB; the bag "
          f"{size / 2**20:.0f} MiB), rig {out / 2**30:.2f} GiB")
    if not args.keep:
        shutil.rmtree(args.dir, ignore_errors=True)
    sys.exit(result.returncode)


if __name__ == "__main__":
    main()

"""``moisst-bag-to-rig`` (``moisst_ns.datasets.rosbag``) on bags these tests write with rosbags' own writers.

A small ``moisst-synth`` rig (6 frames, 64x48) goes into a ROS 1 ``.bag`` and into ROS 2 bags (MCAP, sqlite3) -
cameras as raw ``Image`` (rgb8 / bgr8) or PNG ``CompressedImage`` with their ``camera_info``, the LiDAR as
``PointCloud2`` with a float64 ``time`` field, the priors on ``/tf_static``, the trajectory as ``Odometry`` (ROS 1) or
``/tf`` of a base frame linked to the reference camera by ``/tf_static`` (ROS 2) - and comes back as a rig whose
stamps (to the nanosecond), images, points (bit for bit), per-point times and intrinsics equal the original's, and
whose priors and trajectory equal it to rounding (they travel as quaternions).
"""

import dataclasses
import json
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from PIL import Image
from scipy.spatial.transform import Rotation

from moisst_ns.datasets.rosbag import BagConfig, convert
from moisst_ns.datasets.rosbag_msgs import BagError, MessageError, camera_intrinsics, cloud_arrays
from moisst_ns.rig.format import Calibration, load_lidar_scan, load_rig

from helpers import tree_hash

BIN = Path(sys.executable).parent
LATENCY_NS = 1_500_000
"""Receive time = header stamp + this (so --stamp header and --stamp receive differ)."""
BASE_T_REF = np.array([[0.0, 0.0, 1.0, 1.2], [-1.0, 0.0, 0.0, 0.1], [0.0, -1.0, 0.0, 1.6], [0.0, 0.0, 0.0, 1.0]])
"""base_link <- cam_front (a camera looking forward, 1.6 m up) in the ROS 2 bags' /tf_static."""


class BagWriter:
    """Writes messages into a ROS 1 ``.bag`` or a ROS 2 bag (``mcap`` / ``sqlite3``), in the order given (receive time
    order); a context manager. Also used by scripts/bag_speed.py."""

    def __init__(self, path: Path, kind: str):
        from rosbags.typesys import Stores, get_typestore

        self.path, self.kind, self.conns = path, kind, {}
        self.store = get_typestore(Stores.ROS1_NOETIC if kind == "ros1" else Stores.ROS2_HUMBLE)
        if "tf2_msgs/msg/TFMessage" not in self.store.types:  # rosbags' noetic store lacks it
            from rosbags.typesys import get_types_from_msg

            self.store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
        self.t = self.store.types

    def __enter__(self) -> "BagWriter":
        if self.kind == "ros1":
            from rosbags.rosbag1 import Writer

            self.writer, self.serialize = Writer(self.path), self.store.serialize_ros1
        else:
            from rosbags.rosbag2 import StoragePlugin, Writer

            plugin = StoragePlugin.MCAP if self.kind == "mcap" else StoragePlugin.SQLITE3
            self.writer, self.serialize = Writer(self.path, version=9, storage_plugin=plugin), self.store.serialize_cdr
        self.writer.open()
        return self

    def __exit__(self, *exc) -> None:
        self.writer.close()

    def write(self, topic: str, msg, receive_ns: int) -> None:
        if topic not in self.conns:
            self.conns[topic] = self.writer.add_connection(topic, msg.__msgtype__, typestore=self.store)
        self.writer.write(self.conns[topic], receive_ns, self.serialize(msg, msg.__msgtype__))

    def write_sorted(self, events: list) -> None:
        """``[(receive_ns, topic, msg)]`` in receive-time order (stable)."""
        for receive_ns, topic, msg in sorted(events, key=lambda e: e[0]):
            self.write(topic, msg, receive_ns)

    def header(self, ns: int, frame: str):
        stamp = self.t["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
        extra = {"seq": 0} if self.kind == "ros1" else {}
        return self.t["std_msgs/msg/Header"](stamp=stamp, frame_id=frame, **extra)

    def image(self, ns, frame, rgb: np.ndarray, encoding: str):
        pixels = rgb[..., ::-1] if encoding == "bgr8" else rgb
        return self.t["sensor_msgs/msg/Image"](header=self.header(ns, frame), height=rgb.shape[0], width=rgb.shape[1], encoding=encoding,
                                               is_bigendian=0, step=rgb.shape[1] * 3, data=np.ascontiguousarray(pixels).reshape(-1))

    def compressed(self, ns, frame, data: bytes, fmt: str):
        return self.t["sensor_msgs/msg/CompressedImage"](header=self.header(ns, frame), format=fmt, data=np.frombuffer(data, np.uint8))

    def camera_info(self, ns, frame, intr: dict):
        """ROS camera_info of moisst-rig intrinsics (pixel centres at +0.5 -> OpenCV's integers)."""
        K = [intr["fl_x"], 0.0, intr["cx"] - 0.5, 0.0, intr["fl_y"], intr["cy"] - 0.5, 0.0, 0.0, 1.0]
        P = K[:3] + [0.0] + K[3:6] + [0.0] + K[6:] + [0.0]
        roi = self.t["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        keys = ("D", "K", "R", "P") if self.kind == "ros1" else ("d", "k", "r", "p")
        values = (np.zeros(5), np.array(K), np.eye(3).reshape(-1), np.array(P))
        return self.t["sensor_msgs/msg/CameraInfo"](header=self.header(ns, frame), height=intr["h"], width=intr["w"],
                                                    distortion_model="plumb_bob", binning_x=0, binning_y=0, roi=roi,
                                                    **dict(zip(keys, values)))

    def cloud(self, ns, frame, **columns: np.ndarray):
        """PointCloud2 of named columns (each a numpy type PointField knows), packed in order."""
        codes = {"int8": 1, "uint8": 2, "int16": 3, "uint16": 4, "int32": 5, "uint32": 6, "float32": 7, "float64": 8}
        dtype = np.dtype([(name, col.dtype) for name, col in columns.items()])
        rec = np.empty(len(next(iter(columns.values()))), dtype=dtype)
        for name, col in columns.items():
            rec[name] = col
        fields = [self.t["sensor_msgs/msg/PointField"](name=n, offset=dtype.fields[n][1], datatype=codes[dtype.fields[n][0].name], count=1)
                  for n in columns]
        return self.t["sensor_msgs/msg/PointCloud2"](header=self.header(ns, frame), height=1, width=len(rec), fields=fields,
                                                     is_bigendian=False, point_step=dtype.itemsize, row_step=dtype.itemsize * len(rec),
                                                     data=rec.view(np.uint8).reshape(-1), is_dense=False)

    def _parts(self, T: np.ndarray):
        x, y, z, w = Rotation.from_matrix(T[:3, :3]).as_quat()
        return self.t["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w), T[:3, 3]

    def transforms(self, ns, edges):
        """TFMessage of ``[(parent, child, parent_T_child)]``."""
        out = []
        for parent, child, T in edges:
            q, p = self._parts(T)
            tf = self.t["geometry_msgs/msg/Transform"](translation=self.t["geometry_msgs/msg/Vector3"](x=p[0], y=p[1], z=p[2]), rotation=q)
            out.append(self.t["geometry_msgs/msg/TransformStamped"](header=self.header(ns, parent), child_frame_id=child, transform=tf))
        return self.t["tf2_msgs/msg/TFMessage"](transforms=out)

    def odometry(self, ns, parent, child, T):
        q, p = self._parts(T)
        pose = self.t["geometry_msgs/msg/Pose"](position=self.t["geometry_msgs/msg/Point"](x=p[0], y=p[1], z=p[2]), orientation=q)
        zero = self.t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
        twist = self.t["geometry_msgs/msg/TwistWithCovariance"](twist=self.t["geometry_msgs/msg/Twist"](linear=zero, angular=zero),
                                                                covariance=np.zeros(36))
        return self.t["nav_msgs/msg/Odometry"](header=self.header(ns, parent), child_frame_id=child,
                                               pose=self.t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
                                               twist=twist)


def ns_of(seconds: float) -> int:
    return round(seconds * 1e9)


def pose(position, quat_xyzw) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = Rotation.from_quat(quat_xyzw).as_matrix(), position
    return T


def rig_to_bag(rig_dir: Path, path: Path, kind: str, compressed=(), bgr=()) -> Path:
    """Write a moisst-rig as a bag; ROS 1: /odom Odometry map -> cam_front and /tf_static cam_front -> sensor; ROS 2: /tf
    map -> base_link and /tf_static base_link -> every sensor."""
    rig, bag, events = load_rig(rig_dir), BagWriter(path, kind), []
    ref = rig.reference_sensor
    if kind == "ros1":
        edges = [(ref, n, s.T_ref_sensor) for n, s in rig.sensors.items() if n != ref]
    else:
        edges = [("base_link", n, BASE_T_REF @ s.T_ref_sensor) for n, s in rig.sensors.items()]
    t0 = ns_of(rig.trajectory_stamps[0]) - 10**8
    events.append((t0, "/tf_static", bag.transforms(t0, edges)))
    for t, p, q in zip(rig.trajectory_stamps, rig.trajectory_positions, rig.trajectory_quats_xyzw):
        ns = ns_of(t)
        if kind == "ros1":
            events.append((ns + LATENCY_NS, "/odom", bag.odometry(ns, "map", ref, pose(p, q))))
        else:
            events.append((ns + LATENCY_NS, "/tf", bag.transforms(ns, [("map", "base_link", pose(p, q) @ np.linalg.inv(BASE_T_REF))])))
    for frame in rig.frames:
        ns, name, file = ns_of(frame.timestamp), frame.sensor, rig.root / frame.file_path
        if rig.sensors[name].type == "lidar":
            points, times, _ = load_lidar_scan(file)
            msg = bag.cloud(ns, name, x=points[:, 0], y=points[:, 1], z=points[:, 2], intensity=np.ones(len(points), np.float32), time=times)
            events.append((ns + LATENCY_NS, f"/{name}/points", msg))
            continue
        events.append((ns + LATENCY_NS, f"/{name}/camera_info", bag.camera_info(ns, name, rig.sensors[name].intrinsics)))
        if name in compressed:
            events.append((ns + LATENCY_NS, f"/{name}/image_raw/compressed", bag.compressed(ns, name, file.read_bytes(), "png")))
        else:
            rgb = np.asarray(Image.open(file).convert("RGB"))
            events.append((ns + LATENCY_NS, f"/{name}/image_raw", bag.image(ns, name, rgb, "bgr8" if name in bgr else "rgb8")))
    with bag:
        bag.write_sorted(events)
    return path


@pytest.fixture(scope="module")
def synth(tmp_path_factory) -> Path:
    from moisst_ns.datasets.synth import SynthConfig, make_rig

    return make_rig(SynthConfig(out=tmp_path_factory.mktemp("synth") / "rig", seed=0, frames=6, width=64, height=48))


@pytest.fixture(scope="module")
def ros1_bag(synth, tmp_path_factory) -> Path:
    return rig_to_bag(synth, tmp_path_factory.mktemp("ros1") / "drive.bag", "ros1")


def config_for(bag: Path, out: Path, compressed=(), **kw) -> BagConfig:
    cams = [f"/{n}/image_raw" + ("/compressed" if n in compressed else "") for n in ("cam_front", "cam_front_right", "cam_left")]
    trajectory = "/odom" if bag.suffix == ".bag" else "/tf"
    return BagConfig(bags=(bag,), out=out, trajectory=trajectory, camera=tuple(cams), lidar=("/lidar/points",), **kw)


def check_round_trip(orig: Path, out: Path, priors_atol: float, exact_priors=()) -> None:
    a, b = load_rig(orig), load_rig(out)
    assert b.reference_sensor == a.reference_sensor and list(b.sensors) == list(a.sensors)
    origin = json.loads((out / "rig.json").read_text())["metadata"]["time_origin_ns"]
    assert origin == 1000 * 10**9  # the whole second before the first frame
    for name, sa in a.sensors.items():
        sb = b.sensors[name]
        assert sb.type == sa.type and sb.intrinsics == sa.intrinsics, name
        if name in exact_priors:
            assert np.array_equal(sb.T_ref_sensor, sa.T_ref_sensor) and sb.time_offset == sa.time_offset, name
        else:
            np.testing.assert_allclose(sb.T_ref_sensor, sa.T_ref_sensor, atol=priors_atol, rtol=0, err_msg=name)
            assert sb.time_offset == 0.0
        fa, fb = a.frames_of(name), b.frames_of(name)
        assert [ns_of(f.timestamp) for f in fa] == [ns_of(f.timestamp) + origin for f in fb], name  # to the nanosecond
        for x, y in zip(fa, fb):
            if sa.type == "camera":
                assert np.array_equal(np.asarray(Image.open(a.root / x.file_path)), np.asarray(Image.open(b.root / y.file_path)))
            else:
                with np.load(a.root / x.file_path) as za, np.load(b.root / y.file_path) as zb:
                    assert zb["points"].dtype == np.float32 and zb["points"].tobytes() == za["points"].tobytes()
                    assert zb["times"].dtype == np.float64 and zb["times"].tobytes() == za["times"].tobytes()
    assert [ns_of(t) for t in a.trajectory_stamps] == [ns_of(t) + origin for t in b.trajectory_stamps]
    np.testing.assert_allclose(b.trajectory_positions, a.trajectory_positions, atol=1e-9, rtol=0)
    np.testing.assert_allclose(np.abs(np.sum(b.trajectory_quats_xyzw * a.trajectory_quats_xyzw, axis=1)), 1.0, atol=1e-12)


def test_ros1_round_trip(synth, ros1_bag, tmp_path):
    before = tree_hash(ros1_bag.parent)
    lines = []
    out = convert(config_for(ros1_bag, tmp_path / "rig"), log=lines.append)
    check_round_trip(synth, out, priors_atol=1e-12)
    assert tree_hash(ros1_bag.parent) == before  # the bag's folder is only read
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rig"]  # no temporary folder left
    assert lines == ["lidar: per-point times from 'time' (float64, seconds from the header stamp)"]
    meta = json.loads((out / "rig.json").read_text())["metadata"]
    assert meta["priors"] == {"cam_front": "reference", "cam_front_right": "/tf_static", "cam_left": "/tf_static", "lidar": "/tf_static"}


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_ros2_round_trip(synth, tmp_path, storage):
    """Compressed PNG (bytes copied), bgr8, a /tf trajectory of base_link, priors through base_link, the LiDAR's from
    --priors (exact, time offset included)."""
    bag = rig_to_bag(synth, tmp_path / "bag" / "drive", storage, compressed=("cam_left",), bgr=("cam_front",))
    orig = load_rig(synth)
    Calibration(orig.reference_sensor, {n: orig.sensors[n].T_ref_sensor for n in ("cam_front", "lidar")},
                {n: orig.sensors[n].time_offset for n in ("cam_front", "lidar")}).write(tmp_path / "priors.json")
    config = config_for(bag, tmp_path / "rig", compressed=("cam_left",), trajectory_frames=("map", "base_link"),
                        priors=tmp_path / "priors.json")
    out = convert(config)
    check_round_trip(synth, out, priors_atol=1e-12, exact_priors=("lidar",))
    pngs = sorted((synth / "images" / "cam_left").iterdir())
    assert [p.read_bytes() for p in pngs] == [p.read_bytes() for p in sorted((out / "images" / "cam_left").iterdir())]


def test_window_every_receive_stamps(synth, ros1_bag, tmp_path):
    out = convert(config_for(ros1_bag, tmp_path / "rig", stamp="receive", every=2, start=0.2, duration=0.3, time_origin=0))
    a, b = load_rig(synth), load_rig(out)
    start = ns_of(min(f.timestamp for f in a.frames)) - 10**8  # the bag's first message: /tf_static
    for name in a.sensors:
        window = [ns_of(f.timestamp) + LATENCY_NS for f in a.frames_of(name)
                  if start + 2 * 10**8 <= ns_of(f.timestamp) + LATENCY_NS < start + 5 * 10**8]
        assert [round(f.timestamp * 1e9) for f in b.frames_of(name)] == window[::2], name


def test_bad_input_is_one_line_and_writes_nothing(ros1_bag, tmp_path):
    before, out = tree_hash(ros1_bag.parent), tmp_path / "rig"
    cases = [
        (dict(camera=("/cam_front/image_raw", "/cam_rear/image_raw")), "/cam_rear/image_raw: no such topic; the bag has: /cam_front/camera_info "
         "(sensor_msgs/msg/CameraInfo), /cam_front/image_raw (sensor_msgs/msg/Image), "),
        (dict(camera=("/odom",)), "/odom: unsupported message type 'nav_msgs/msg/Odometry' for a camera sensor"),
        (dict(camera=("/cam_front/image_raw",), lidar=("/cam_left/image_raw",)), "unsupported message type 'sensor_msgs/msg/Image' for a lidar sensor"),
        (dict(trajectory="/lidar/points"), "/lidar/points: unsupported message type 'sensor_msgs/msg/PointCloud2' for a trajectory"),
        (dict(start=100.0), "--start: empty time window: the bag lasts 0.6"),
        (dict(start=0.3, duration=0.01), "/cam_front_right/image_raw: no messages in the time window [0.3, "),
        (dict(trajectory_frames=("map", "base_link")), "/odom: 0 poses in the time window (need 2) from map to base_link; "
         "(parent, child) frames seen: [('map', 'cam_front')]"),
    ]
    for change, expected in cases:
        config = dataclasses.replace(config_for(ros1_bag, out), **change)
        with pytest.raises(BagError) as err:
            convert(config)
        assert str(err.value).startswith(str(ros1_bag)) and expected in str(err.value), (change, str(err.value))
        assert "\n" not in str(err.value)
        assert not out.exists() and sorted(tmp_path.iterdir()) == [], change
    assert tree_hash(ros1_bag.parent) == before


def test_failure_midway_keeps_the_old_dataset(synth, tmp_path):
    """A camera_info that disagrees with the images: the error comes after frames were written (to the temporary
    folder); --overwrite's old dataset stays as it was. (And without /tf_static a prior is the identity, said.)"""
    rig = load_rig(synth)
    with BagWriter(tmp_path / "bad.bag", "ros1") as bag:
        for k, frame in enumerate(rig.frames_of("cam_front")):
            ns, rgb = ns_of(frame.timestamp), np.asarray(Image.open(synth / frame.file_path).convert("RGB"))
            bag.write("/cam_front/camera_info", bag.camera_info(ns, "cam_front", rig.sensors["cam_front"].intrinsics), ns)
            bag.write("/cam_front/image_raw", bag.image(ns, "cam_front", rgb if k < 3 else rgb[:24, :32].copy(), "rgb8"), ns)
            bag.write("/odom", bag.odometry(ns, "map", "cam_front", np.eye(4)), ns)
            bag.write("/cam_left/camera_info", bag.camera_info(ns, "cam_left", rig.sensors["cam_left"].intrinsics), ns)
            bag.write("/cam_left/image_raw", bag.image(ns, "cam_left", rgb, "rgb8"), ns)
    old = tmp_path / "old"
    config = BagConfig(bags=(tmp_path / "bad.bag",), out=old, trajectory="/odom", camera=("/cam_front/image_raw", "/cam_left/image_raw"))
    lines = []
    convert(dataclasses.replace(config, duration=0.25), log=lines.append)  # the first three frames are good
    assert lines == ["warning: /tf_static does not link 'cam_left' (cam_left) to 'cam_front': prior = identity"]
    assert np.array_equal(load_rig(old).sensors["cam_left"].T_ref_sensor, np.eye(4)) and len(load_rig(old).frames) == 6
    before = tree_hash(old)
    with pytest.raises(BagError, match=r"bad\.bag: /cam_front/image_raw: message at \d+ ns \(receive time\): image is 32x24, "
                                       r"its camera_info says 64x48"):
        convert(dataclasses.replace(config, overwrite=True))
    assert tree_hash(old) == before and sorted(p.name for p in tmp_path.iterdir()) == ["bad.bag", "old"]


def test_cli_error_and_summary(ros1_bag, tmp_path):
    out = tmp_path / "rig"
    args = [str(BIN / "moisst-bag-to-rig"), str(ros1_bag), "--out", str(out), "--trajectory", "/odom", "--camera", "/cam_front/image_raw"]
    bad = subprocess.run(args + ["--lidar", "/velodyne_points"], capture_output=True, text=True)
    assert bad.returncode == 2 and not out.exists()
    assert bad.stderr.splitlines() == [f"moisst-bag-to-rig: error: {ros1_bag}: /velodyne_points: no such topic; the bag has: "
                                       + ", ".join(f"{t} ({m})" for t, m in sorted(TOPICS.items()))]
    good = subprocess.run(args + ["--camera", "/cam_left/image_raw=left", "--lidar", "/lidar/points"], capture_output=True, text=True)
    assert good.returncode == 0, good.stderr
    assert good.stdout.startswith(f"moisst-bag-to-rig: wrote {out} (drive.bag, cam_front 6 frames, left 6 frames, lidar 6 frames")
    assert good.stderr.splitlines() == ["moisst-bag-to-rig: lidar: per-point times from 'time' (float64, seconds from the header stamp)"]


TOPICS = {"/cam_front/camera_info": "sensor_msgs/msg/CameraInfo", "/cam_front/image_raw": "sensor_msgs/msg/Image",
          "/cam_front_right/camera_info": "sensor_msgs/msg/CameraInfo", "/cam_front_right/image_raw": "sensor_msgs/msg/Image",
          "/cam_left/camera_info": "sensor_msgs/msg/CameraInfo", "/cam_left/image_raw": "sensor_msgs/msg/Image",
          "/lidar/points": "sensor_msgs/msg/PointCloud2", "/odom": "nav_msgs/msg/Odometry", "/tf_static": "tf2_msgs/msg/TFMessage"}


def _cloud(columns: dict, pad: int = 0, big: bool = False, stamp_ns: int = 5 * 10**9 + 250_000_000):
    """A duck-typed PointCloud2 (2 rows) of ``columns``, rows padded by ``pad`` bytes."""
    codes = {"uint32": 6, "float32": 7, "float64": 8}
    dtype = np.dtype([(n, c.dtype.newbyteorder(">" if big else "<")) for n, c in columns.items()])
    rec = np.empty(len(next(iter(columns.values()))), dtype)
    for n, c in columns.items():
        rec[n] = c
    rows = rec.view(np.uint8).reshape(2, -1)
    data = np.concatenate([rows, np.zeros((2, pad), np.uint8)], axis=1).reshape(-1)
    fields = [SimpleNamespace(name=n, offset=dtype.fields[n][1], datatype=codes[c.dtype.name], count=1) for n, c in columns.items()]
    header = SimpleNamespace(stamp=SimpleNamespace(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9))
    return SimpleNamespace(header=header, fields=fields, is_bigendian=big, point_step=dtype.itemsize, width=len(rec) // 2,
                           height=2, row_step=rows.shape[1] + pad, data=data)


def test_point_time_fields():
    xyz = {k: np.array([1.5, -2.0, 3.25, 0.5], np.float32) * (i + 1) for i, k in enumerate("xyz")}
    stamp = 5 * 10**9 + 250_000_000
    ouster = _cloud({**xyz, "t": np.array([0, 1000, 50_000_000, 99_999_999], np.uint32)}, pad=3)
    points, times, how = cloud_arrays(ouster, stamp + 10_000_000)  # frame stamped 10 ms after the header
    assert np.array_equal(points, np.stack([xyz[k] for k in "xyz"], 1)) and "'t' (uint32, nanoseconds from the header" in how
    np.testing.assert_allclose(times, [-0.01, -0.009999, 0.04, 0.089999999], atol=1e-15)
    epoch = 1_700_000_000_250_000_000  # absolute stamps: float64 seconds hold them to ~0.2 us, float64 ns to 256 ns
    hesai = _cloud({**xyz, "timestamp": 1_700_000_000.25 + np.array([0.0, 0.01, 0.05, 0.1])}, big=True)
    assert np.allclose(cloud_arrays(hesai, epoch)[1], [0.0, 0.01, 0.05, 0.1], rtol=0, atol=1e-6)
    assert cloud_arrays(hesai, epoch)[2].endswith("absolute seconds)") and cloud_arrays(hesai, epoch)[0][2, 2] == np.float32(9.75)
    livox = _cloud({**xyz, "timestamp": epoch + np.array([0.0, 1e5, 2e5, 3e5])})
    assert np.allclose(cloud_arrays(livox, epoch)[1], [0.0, 1e-4, 2e-4, 3e-4], rtol=0, atol=1e-6)
    assert cloud_arrays(livox, epoch)[2].endswith("absolute nanoseconds)")
    assert cloud_arrays(_cloud(xyz), stamp)[1] is None
    with pytest.raises(MessageError, match="no field 'z'"):
        cloud_arrays(_cloud({"x": xyz["x"], "y": xyz["y"]}), stamp)


def test_camera_info_distortion():
    info = SimpleNamespace(width=640, height=480, distortion_model="plumb_bob", D=[-0.1, 0.02, 0.001, -0.002, 0.003],
                           K=[500.0, 0.0, 319.5, 0.0, 510.0, 239.5, 0.0, 0.0, 1.0])
    assert camera_intrinsics(info, 2) == {"camera_model": "OPENCV", "w": 320, "h": 240, "fl_x": 250.0, "fl_y": 255.0, "cx": 160.0,
                                          "cy": 120.0, "k1": -0.1, "k2": 0.02, "p1": 0.001, "p2": -0.002, "k3": 0.003}
    info.distortion_model, info.D = "equidistant", [0.1, 0.0, 0.0, 0.0]
    with pytest.raises(MessageError, match="unsupported distortion model 'equidistant'"):
        camera_intrinsics(info, 1)

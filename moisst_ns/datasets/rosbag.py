"""ROS bags to ``moisst-rig/1`` (``moisst-bag-to-rig``): ROS 1 and ROS 2 (sqlite3, MCAP) bags read with the pure-Python
``rosbags`` library, streamed one message at a time into a temporary folder beside ``--out`` that is moved into place
only when everything succeeded. Frames, stamps, priors and options: ``docs/bags.md``; message decoding is in
``moisst_ns.datasets.rosbag_msgs``.
"""

from __future__ import annotations

import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Callable, Dict, List, Literal, Optional, Tuple

import numpy as np
import tyro

from moisst_ns.datasets.rig_writer import prepare_out, write_rig, write_trajectory
from moisst_ns.datasets.rosbag_msgs import (CAMERA_INFO, CLOUD, COMPRESSED, IMAGE, POSES, TF, BagError, MessageError,
                                            StaticTf, camera_intrinsics, cloud_arrays, frame_name, poses_of, rigid,
                                            stamp_ns, write_image)
from moisst_ns.rig.format import check_name, load_calibration, load_rig

GENERIC_PARTS = {"image_raw", "image_color", "image_rect", "image_rect_color", "image_mono", "image", "compressed",
                 "points", "points_raw", "pointcloud", "cloud"}
"""Topic components left out of a default sensor name (``/cam_front/image_raw`` -> ``cam_front``)."""
TRAJECTORY_PAD_S = 1.0
"""Poses are read this much beyond the time window on both sides (frames at its edges interpolate)."""
INSIDE = "must not be inside the bag {source} (the bag is only read)"


@dataclass
class BagConfig:
    """Convert ROS bags (ROS 1, ROS 2 sqlite3 or MCAP) to a moisst-rig/1 dataset, streaming them."""

    bags: Annotated[Tuple[Path, ...], tyro.conf.Positional, tyro.conf.arg(metavar="BAG")]
    """ROS 1 .bag files (several: the parts of one recording), or ROS 2 bags (a folder with metadata.yaml, or a bare
    .db3 / .mcap). Read only."""
    out: Path
    """Output dataset folder (must be absent or empty unless --overwrite); written only if the conversion succeeds."""
    trajectory: str
    """The reference trajectory's topic: nav_msgs/Odometry, geometry_msgs/PoseStamped or PoseWithCovarianceStamped,
    or tf2_msgs/TFMessage (/tf, with --trajectory-frames)."""
    camera: Annotated[Tuple[str, ...], tyro.conf.UseAppendAction] = ()
    """TOPIC[=NAME], repeatable: a camera (sensor_msgs/Image or CompressedImage); its intrinsics from the first
    message of the camera_info beside it (/ns/image_raw[/compressed] -> /ns/camera_info). NAME default: the topic
    without generic parts (/cam_front/image_raw -> cam_front)."""
    lidar: Annotated[Tuple[str, ...], tyro.conf.UseAppendAction] = ()
    """TOPIC[=NAME], repeatable: a LiDAR (sensor_msgs/PointCloud2: x, y, z, and the per-point time field t, time or
    timestamp when present), written as .npz points (float32) + times (seconds from the frame's stamp)."""
    reference: Optional[str] = None
    """TOPIC[=NAME] of the reference sensor (its frame is the rig's reference; added if not among --camera/--lidar).
    Default: the first --camera (else the first --lidar)."""
    trajectory_frames: Optional[Tuple[str, str]] = None
    """WORLD CHILD: the poses taken from --trajectory (tf: the transform WORLD -> CHILD; Odometry/PoseStamped: only
    messages whose header.frame_id is WORLD, and CHILD names the posed frame). Default: every message; the posed
    frame is Odometry's child_frame_id, or the reference sensor's frame for PoseStamped."""
    trajectory_extrinsic: Optional[Tuple[float, float, float, float, float, float, float]] = None
    """X Y Z QX QY QZ QW: the reference sensor's pose in the posed frame (metres, unit quaternion), when the poses are
    another frame's (e.g. the INS) that /tf_static does not link to the reference sensor's frame."""
    priors: Optional[Path] = None
    """A calibration.json-schema file (T_ref_sensor, time_offset) whose sensors' priors replace /tf_static's."""
    stamp: Literal["header", "receive"] = "header"
    """Frame and pose stamps: 'header' = header.stamp (each sensor's own clock); 'receive' = the recorder's receive
    time (the recording machine's clock, plus transport latency)."""
    every: int = 1
    """Keep every K-th frame of each sensor (poses are all kept)."""
    start: float = 0.0
    """Start of the time window, seconds after the bag's first message (receive time)."""
    duration: Optional[float] = None
    """Length of the time window, seconds (default: to the end of the bag)."""
    downscale: int = 1
    """Shrink every image by this integer factor (INTER_AREA; intrinsics scaled accordingly)."""
    time_origin: Optional[int] = None
    """Nanoseconds subtracted from every stamp (recorded in rig.json's metadata). Default: the whole second at or
    before the first kept frame (rig timestamps keep every nanosecond); 0 keeps absolute stamps (float64: ~0.2 us)."""
    overwrite: bool = False
    """Replace the converter's outputs in a non-empty --out."""

    @property
    def source(self) -> str:
        """The bags' names, for the summary line."""
        return ", ".join(p.name for p in self.bags)


@dataclass
class _Sensor:
    name: str
    topic: str
    kind: str
    """camera or lidar."""
    msgtype: str = ""
    frame_id: Optional[str] = None
    info: Optional[Dict[str, object]] = None
    """Camera intrinsics (rig.json keys, after --downscale)."""
    size: Tuple[int, int] = (0, 0)
    """Camera: (w, h) of its images in the bag (camera_info)."""
    frames: List[Tuple[int, str]] = field(default_factory=list)
    """(stamp ns, file path relative to the dataset)."""
    seen: int = 0
    """Messages of the time window so far (for --every)."""
    note: str = ""


def _label(bags) -> str:
    return " + ".join(str(b) for b in bags)


def _split(spec: str) -> Tuple[str, str]:
    topic, _, name = spec.partition("=")
    if not name:
        parts = [p for p in topic.split("/") if p]
        name = "_".join([p for p in parts if p not in GENERIC_PARTS] or parts[-1:])
    check_name(name, "(command line)", f"sensor name of {spec}")
    return topic, name


def _sensors(config: BagConfig) -> Tuple[Dict[str, _Sensor], str]:
    """Sensors of the command line (name -> _Sensor, in order, reference first) and the reference's name."""
    specs = [(s, "camera") for s in config.camera] + [(s, "lidar") for s in config.lidar]
    if not specs and config.reference is None:
        raise BagError("(command line)", "--camera/--lidar", "no sensor given")
    ref_topic, ref_name = _split(config.reference) if config.reference else _split(specs[0][0])
    sensors: Dict[str, _Sensor] = {}
    for spec, kind in ([] if any(_split(s)[0] == ref_topic for s, _ in specs) else [(config.reference, "")]) + specs:
        topic, name = _split(spec)
        if topic == ref_topic and "=" in (config.reference or ""):
            name = ref_name
        if name in sensors or any(s.topic == topic for s in sensors.values()):
            raise BagError("(command line)", topic, f"sensor {name!r} / topic {topic!r} given twice")
        sensors[name] = _Sensor(name, topic, kind)
    ref = next(n for n, s in sensors.items() if s.topic == ref_topic)
    return {ref: sensors[ref], **{n: s for n, s in sensors.items() if n != ref}}, ref


def _check_config(config: BagConfig) -> None:
    problems = {"--every": config.every < 1, "--downscale": config.downscale < 1, "--start": not config.start >= 0,
                "--duration": config.duration is not None and not config.duration > 0, "BAG": not config.bags}
    for flag, bad in problems.items():
        if bad:
            raise BagError("(command line)", flag, "must be >= 1" if flag in ("--every", "--downscale") else
                           "needs at least one bag" if flag == "BAG" else "must be > 0" if flag == "--duration" else "must be >= 0")
    for bag in config.bags:
        if not bag.exists():
            raise BagError(bag, "(bag)", "not found")
    if len({b.suffix == ".bag" for b in config.bags}) > 1:
        raise BagError(_label(config.bags), "(bag)", "mixes ROS 1 .bag files and ROS 2 bags; convert one kind at a time")
    prepare_out(config.out, config.bags, config.overwrite, BagError, INSIDE, clear=False)


def _topic(reader, bags, topic: str, wanted: Tuple[str, ...], what: str) -> list:
    """The connections of ``topic``; a missing topic lists the bag's topics, a wrong type names it."""
    conns = [c for c in reader.connections if c.topic == topic]
    if not conns:
        present = ", ".join(f"{t} ({i.msgtype})" for t, i in sorted(reader.topics.items()))
        raise BagError(_label(bags), topic, f"no such topic; the bag has: {present or 'no topics'}")
    bad = [c.msgtype for c in conns if c.msgtype not in wanted]
    if bad:
        raise BagError(_label(bags), topic, f"unsupported message type {bad[0]!r} for {what} (expected {' or '.join(wanted)})")
    return conns


def _camera_info(reader, bags, sensor: _Sensor, factor: int) -> None:
    candidate = sensor.topic.removesuffix("/compressed").rsplit("/", 1)[0] + "/camera_info"
    conns = _topic(reader, bags, candidate, (CAMERA_INFO,), f"the camera_info of {sensor.topic}")
    for conn, _, raw in reader.messages(connections=conns):
        try:
            info = reader.deserialize(raw, conn.msgtype)
            sensor.info, sensor.size = camera_intrinsics(info, factor), (int(info.width), int(info.height))
            return
        except MessageError as err:
            raise BagError(_label(bags), candidate, str(err)) from None
    raise BagError(_label(bags), candidate, "has no message")


def _window(config: BagConfig, reader, bags) -> Tuple[int, int]:
    lo = reader.start_time + round(config.start * 1e9)
    hi = reader.end_time if config.duration is None else min(reader.end_time, lo + round(config.duration * 1e9))
    if lo >= reader.end_time:
        raise BagError(_label(bags), "--start", f"empty time window: the bag lasts {(reader.end_time - reader.start_time) * 1e-9:.3f} s, "
                       f"--start is {config.start} s")
    return lo, hi


def _stream(config: BagConfig, reader, bags, sensors: Dict[str, _Sensor], traj_conns: list, window: Tuple[int, int],
            tmp: Path) -> list:
    """Write every kept frame into ``tmp`` (one message at a time); returns the trajectory's poses
    ``[(stamp ns, parent, child, parent_T_child)]``."""
    by_topic = {s.topic: s for s in sensors.values()}
    conns = [c for c in reader.connections if c.topic in by_topic] + traj_conns
    pad = round(TRAJECTORY_PAD_S * 1e9)
    poses, seen_pairs = [], set()
    for conn, receive_ns, raw in reader.messages(connections=conns, start=max(window[0] - pad, 0), stop=window[1] + pad):
        sensor = by_topic.get(conn.topic)
        in_window = window[0] <= receive_ns < window[1]
        if sensor is not None and (not in_window or sensor.seen % config.every):
            sensor.seen += in_window
            continue
        try:
            msg = reader.deserialize(raw, conn.msgtype)
            if sensor is None:
                for parent, child, header, T in poses_of(msg, conn.msgtype):
                    seen_pairs.add((parent, child))
                    if config.trajectory_frames is None or (parent, child or config.trajectory_frames[1]) == tuple(config.trajectory_frames):
                        poses.append((stamp_ns(header) if config.stamp == "header" else receive_ns, parent, child, T))
                continue
            sensor.seen += 1
            frame_ns = stamp_ns(msg.header) if config.stamp == "header" else receive_ns
            sensor.frame_id = frame_name(msg.header.frame_id) if sensor.frame_id is None else sensor.frame_id
            stem = tmp / ("images" if sensor.kind == "camera" else "lidar") / sensor.name / f"{len(sensor.frames):06d}"
            if sensor.kind == "camera":
                suffix = write_image(msg, conn.msgtype, stem, sensor.size, config.downscale)
            else:
                points, times, sensor.note = cloud_arrays(msg, frame_ns)
                if len(points) == 0:
                    continue
                suffix = ".npz"
                np.savez(stem.with_suffix(suffix), points=points, **({} if times is None else {"times": times}))
        except MessageError as err:
            raise BagError(_label(bags), conn.topic, f"message at {receive_ns} ns (receive time): {err}") from None
        sensor.frames.append((frame_ns, stem.with_suffix(suffix).relative_to(tmp).as_posix()))
    if traj_conns and len(poses) < 2:
        raise BagError(_label(bags), config.trajectory, f"{len(poses)} poses in the time window (need 2)" + (
            f" from {config.trajectory_frames[0]} to {config.trajectory_frames[1]}; (parent, child) frames seen: "
            f"{sorted(seen_pairs)[:20]}" if config.trajectory_frames else ""))
    return poses


def _trajectory_extrinsic(config: BagConfig, bags, poses: list, ref: _Sensor, static: StaticTf) -> Tuple[np.ndarray, str]:
    """``posed_T_ref`` (4, 4) and where it came from."""
    posed = config.trajectory_frames[1] if config.trajectory_frames else poses[0][2]
    if config.trajectory_extrinsic is not None:
        try:
            return rigid(config.trajectory_extrinsic[:3], config.trajectory_extrinsic[3:]), "--trajectory-extrinsic"
        except MessageError as err:
            raise BagError("(command line)", "--trajectory-extrinsic", str(err)) from None
    if not posed or posed == ref.frame_id:
        return np.eye(4), f"the poses are the reference sensor's ({ref.frame_id})"
    found = static.lookup(posed, ref.frame_id)
    if found is None:
        raise BagError(_label(bags), config.trajectory, f"its poses are of frame {posed!r}, which /tf_static does not link to the "
                       f"reference sensor's frame {ref.frame_id!r}; pass --trajectory-extrinsic X Y Z QX QY QZ QW")
    return found, f"/tf_static {posed} <- {ref.frame_id}"


def _priors(config: BagConfig, sensors: Dict[str, _Sensor], ref: str, static: StaticTf, given, log) -> Tuple[dict, dict]:
    """name -> (T_ref_sensor, time_offset), and name -> where each came from (``given``: the --priors file)."""
    priors, sources = {ref: (np.eye(4), 0.0)}, {ref: "reference"}
    for name, s in sensors.items():
        if name == ref:
            continue
        if given is not None and name in given.T_ref_sensor:
            priors[name], sources[name] = (given.T_ref_sensor[name], given.time_offset[name]), f"--priors {config.priors}"
            continue
        found = static.lookup(sensors[ref].frame_id, s.frame_id)
        priors[name], sources[name] = (np.eye(4) if found is None else found, 0.0), "/tf_static" if found is not None else "identity"
        if found is None:
            log(f"warning: /tf_static does not link {s.frame_id!r} ({name}) to {sensors[ref].frame_id!r}: prior = identity")
    return priors, sources


def convert(config: BagConfig, log: Optional[Callable[[str], None]] = None) -> Path:
    """Write the ``moisst-rig/1`` dataset of ``config`` into ``config.out``; returns that folder.

    Args:
        log: receives one line per note (which per-point time field a LiDAR has, priors left at identity).
    """
    from rosbags.highlevel import AnyReader, AnyReaderError
    from rosbags.rosbag1 import ReaderError as Reader1Error
    from rosbags.rosbag2 import ReaderError as Reader2Error
    from rosbags.typesys import Stores, get_typestore

    log = log or (lambda line: None)
    _check_config(config)
    sensors, ref = _sensors(config)
    given = load_calibration(config.priors) if config.priors else None
    if given is not None and given.reference_sensor != ref:
        raise BagError(config.priors, "reference_sensor", f"is {given.reference_sensor!r}, the reference sensor here is {ref!r}")
    bags = [Path(b) for b in config.bags]
    errors = (AnyReaderError, Reader1Error, Reader2Error)
    try:
        reader = AnyReader(bags, default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except (*errors, FileNotFoundError) as err:
        raise BagError(_label(bags), "(bag)", f"unreadable: {err}") from None
    try:
        return _convert(config, reader, bags, sensors, ref, given, log)
    except errors as err:
        raise BagError(_label(bags), "(bag)", f"unreadable: {err}") from None
    finally:
        reader.close()


def _convert(config: BagConfig, reader, bags, sensors: Dict[str, _Sensor], ref: str, given, log) -> Path:
    for s in sensors.values():
        wanted = {"camera": (IMAGE, COMPRESSED), "lidar": (CLOUD,), "": (IMAGE, COMPRESSED, CLOUD)}[s.kind]
        s.msgtype = _topic(reader, bags, s.topic, wanted, f"a {s.kind or 'reference'} sensor")[0].msgtype
        s.kind = s.kind or ("lidar" if s.msgtype == CLOUD else "camera")
    traj_conns = _topic(reader, bags, config.trajectory, POSES, "a trajectory")
    if traj_conns[0].msgtype == TF and config.trajectory_frames is None:
        raise BagError(_label(bags), config.trajectory, "a tf trajectory needs --trajectory-frames WORLD CHILD")
    for s in sensors.values():
        if s.kind == "camera":
            _camera_info(reader, bags, s, config.downscale)
    static, static_conns = StaticTf(), [c for c in reader.connections if c.topic == "/tf_static" and c.msgtype == TF]
    for conn, _, raw in reader.messages(connections=static_conns) if static_conns else ():  # no connections = every message
        static.add(reader.deserialize(raw, conn.msgtype))
    window = _window(config, reader, bags)

    out = Path(config.out)
    anchor = out.absolute().parent
    while not anchor.exists():
        anchor = anchor.parent
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-", dir=anchor))
    try:
        for s in sensors.values():
            (tmp / ("images" if s.kind == "camera" else "lidar") / s.name).mkdir(parents=True)
        poses = _stream(config, reader, bags, sensors, traj_conns, window, tmp)
        for s in sensors.values():
            if not s.frames:
                raise BagError(_label(bags), s.topic, f"no messages in the time window [{config.start}, "
                               f"{'end' if config.duration is None else config.start + config.duration}) s after the bag's start")
            if s.note:
                log(f"{s.name}: per-point times from {s.note}")
        posed_T_ref, extrinsic_source = _trajectory_extrinsic(config, bags, poses, sensors[ref], static)
        priors, sources = _priors(config, sensors, ref, static, given, log)
        first = min(ns for s in sensors.values() for ns, _ in s.frames)
        origin = config.time_origin if config.time_origin is not None else first - first % 1_000_000_000
        stamps, unique = np.unique(np.array([p[0] for p in poses], dtype=np.int64), return_index=True)  # sorted, first of equal
        write_trajectory(tmp / "reference_poses.txt", np.array([(int(ns) - origin) / 10**9 for ns in stamps]),
                         np.stack([poses[i][3] for i in unique]) @ posed_T_ref,
                         header=f"world_T_{ref} from {config.trajectory} ({config.stamp} stamps - {origin} ns): "
                                "timestamp tx ty tz qx qy qz qw")
        frames = [{"sensor": s.name, "timestamp": (ns - origin) / 10**9, "file_path": rel} for s in sensors.values() for ns, rel in s.frames]
        meta = {
            "generator": "moisst-bag-to-rig", "bags": [str(b) for b in bags], "stamps": config.stamp,
            "clock": "header.stamp: each sensor's own clock" if config.stamp == "header" else "receive time: the recorder's clock",
            "time_origin_ns": int(origin), "time_origin_utc": str(np.datetime64(int(origin), "ns")),
            "topics": {n: s.topic for n, s in sensors.items()}, "frame_ids": {n: s.frame_id for n, s in sensors.items()},
            "priors": sources, "lidar_times": {n: s.note for n, s in sensors.items() if s.kind == "lidar"},
            "trajectory": {"topic": config.trajectory, "type": traj_conns[0].msgtype, "extrinsic": extrinsic_source},
            "every": config.every, "start": config.start, "duration": config.duration, "downscale": config.downscale,
        }
        write_rig(tmp, ref, list(sensors), [n for n, s in sensors.items() if s.kind == "lidar"],
                  {n: s.info for n, s in sensors.items() if s.info}, frames, priors, meta)
        load_rig(tmp)  # the result is checked before it is moved into place
        prepare_out(out, bags, config.overwrite, BagError, INSIDE)
        for entry in sorted(tmp.iterdir()):
            shutil.move(str(entry), str(out / entry.name))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out

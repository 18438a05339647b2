"""The ROS messages ``moisst-bag-to-rig`` reads (``moisst_ns.datasets.rosbag``), decoded from rosbags' deserialised
objects: images (``sensor_msgs/Image``, ``CompressedImage``), ``camera_info``, ``PointCloud2`` (x, y, z and the
per-point time field), poses (``Odometry``, ``PoseStamped``, ``PoseWithCovarianceStamped``, ``tf``) and ``/tf_static``.

ROS 1 and ROS 2 messages differ here only in ``camera_info``'s field case (``K``/``k``) and the header's ``seq``.
A problem with one message raises ``MessageError`` (no bag or topic: the caller adds them and raises ``BagError``).
numpy only at import; OpenCV and Pillow inside the functions that need them.
"""

from __future__ import annotations

from collections import deque
from pathlib import Path
from typing import Dict, Optional, Sequence, Tuple

import numpy as np
from jaxtyping import Float, Float32, UInt8

from moisst_ns.datasets.rig_writer import inverse, scaled_intrinsics, shrink
from moisst_ns.rig.format import RigFormatError

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
CLOUD = "sensor_msgs/msg/PointCloud2"
TF = "tf2_msgs/msg/TFMessage"
POSES = ("nav_msgs/msg/Odometry", "geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/PoseWithCovarianceStamped", TF)
"""Message types a --trajectory topic may have."""
ENCODINGS = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1, "8UC1": 1, "8UC3": 3, "8UC4": 4}
"""Raw image encodings read (channels); 8UC3/8UC4 are taken as BGR/BGRA, as OpenCV writes them."""
POINT_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
"""``sensor_msgs/PointField`` datatype -> numpy type."""
TIME_FIELDS = ("t", "time", "timestamp")
"""Per-point time fields, first found wins: Ouster ``t`` (ns), Velodyne ``time`` (s), Hesai/Livox ``timestamp``."""


class BagError(RigFormatError):
    """A bag (or a command line) the converter refuses: one line ``<bag>: <topic>: <problem>``."""


class MessageError(ValueError):
    """One message cannot be converted (the caller names the bag, the topic and the message)."""


def stamp_ns(header) -> int:
    """A header's stamp, integer nanoseconds (ROS ``sec`` + ``nanosec``)."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def frame_name(frame_id: str) -> str:
    """A tf frame id without ROS 1's optional leading ``/``."""
    return frame_id.lstrip("/")


def rigid(translation: Sequence[float], quat_xyzw: Sequence[float]) -> Float[np.ndarray, "4 4"]:
    """4x4 pose from a translation (metres) and a quaternion ``x, y, z, w`` (normalised here)."""
    q = np.asarray(quat_xyzw, dtype=np.float64)
    norm = np.linalg.norm(q)
    if not np.all(np.isfinite(q)) or abs(norm - 1.0) > 1e-3:
        raise MessageError(f"quaternion {q.tolist()} is not a unit quaternion")
    x, y, z, w = q / norm if abs(norm - 1.0) > 1e-12 else q
    pose = np.eye(4)
    pose[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                    [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                    [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    pose[:3, 3] = np.asarray(translation, dtype=np.float64)
    if not np.all(np.isfinite(pose)):
        raise MessageError("pose contains NaN or inf")
    return pose


def _rigid_of(p, q) -> Float[np.ndarray, "4 4"]:
    """``rigid`` of a message's point or vector ``p`` (x, y, z) and quaternion ``q`` (x, y, z, w)."""
    return rigid((p.x, p.y, p.z), (q.x, q.y, q.z, q.w))


def poses_of(msg, msgtype: str) -> list:
    """The poses one trajectory message holds.

    Returns:
        ``[(parent frame, child frame ('' when the message does not name it), header, parent_T_child (4, 4) metres)]``:
        every transform of a ``TFMessage``, else the one pose.
    """
    if msgtype == TF:
        return [(frame_name(t.header.frame_id), frame_name(t.child_frame_id), t.header,
                 _rigid_of(t.transform.translation, t.transform.rotation)) for t in msg.transforms]
    child = frame_name(msg.child_frame_id) if msgtype == "nav_msgs/msg/Odometry" else ""
    pose = msg.pose if msgtype == "geometry_msgs/msg/PoseStamped" else msg.pose.pose
    return [(frame_name(msg.header.frame_id), child, msg.header, _rigid_of(pose.position, pose.orientation))]


class StaticTf:
    """The tree of ``/tf_static`` transforms; ``lookup`` composes them along the path between two frames."""

    def __init__(self) -> None:
        self.edges: Dict[str, Dict[str, np.ndarray]] = {}
        """frame a -> {neighbour b: b_T_a}."""

    def add(self, msg) -> None:
        """Add every transform of a ``tf2_msgs/TFMessage`` (parent_T_child and its inverse)."""
        for parent, child, _, T in poses_of(msg, TF):
            self.edges.setdefault(child, {})[parent] = T
            self.edges.setdefault(parent, {})[child] = inverse(T)

    def lookup(self, target: str, source: str) -> Optional[Float[np.ndarray, "4 4"]]:
        """``target_T_source`` (maps points of frame ``source`` into ``target``), or None when not linked."""
        if target == source:
            return np.eye(4)
        seen, queue = {source: np.eye(4)}, deque([source])
        while queue:
            frame = queue.popleft()
            for nxt, nxt_T_frame in self.edges.get(frame, {}).items():
                if nxt not in seen:
                    seen[nxt] = nxt_T_frame @ seen[frame]
                    if nxt == target:
                        return seen[nxt]
                    queue.append(nxt)
        return None


def _field(msg, name: str):
    """A camera_info field by its ROS 2 name (``k``) or ROS 1 name (``K``)."""
    return getattr(msg, name) if hasattr(msg, name) else getattr(msg, name.upper())


def camera_intrinsics(info, factor: int) -> Dict[str, object]:
    """moisst-rig intrinsics of a ``camera_info`` (``K``, ``D``; OpenCV pixel centres at integers -> +0.5) after
    shrinking by ``factor``: ``PINHOLE`` without distortion, ``OPENCV`` for ``plumb_bob`` (k1 k2 p1 p2 k3) or a
    ``rational_polynomial`` whose k4..k6 are 0."""
    K = np.asarray(_field(info, "k"), dtype=np.float64).reshape(3, 3)
    if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.all(np.isfinite(K)):
        raise MessageError(f"camera_info K {K.ravel().tolist()} has no positive focal lengths")
    if int(info.width) <= 0 or int(info.height) <= 0:
        raise MessageError(f"camera_info size {info.width}x{info.height} is not positive")
    D = [float(v) for v in _field(info, "d")]
    model = info.distortion_model
    intr = scaled_intrinsics(K, (int(info.width), int(info.height)), factor)
    if not any(D):
        return intr
    if model not in ("plumb_bob", "rational_polynomial") or any(D[5:]) or len(D) < 4:
        raise MessageError(f"unsupported distortion model {model!r} with D = {D} (moisst-rig/1 takes plumb_bob: "
                           "k1 k2 p1 p2 k3; or rational_polynomial with k4..k6 = 0)")
    k1, k2, p1, p2, k3 = (D + [0.0])[:5]
    return {**intr, "camera_model": "OPENCV", "k1": k1, "k2": k2, "p1": p1, "p2": p2, "k3": k3}


def raw_pixels(msg) -> UInt8[np.ndarray, "h w 3"]:
    """A ``sensor_msgs/Image`` as a BGR uint8 array (grey becomes 3 equal channels, alpha is dropped)."""
    import cv2

    channels = ENCODINGS.get(msg.encoding)
    if channels is None:
        raise MessageError(f"unsupported image encoding {msg.encoding!r} (supported: {', '.join(ENCODINGS)})")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.asarray(msg.data, dtype=np.uint8)
    if step < w * channels or data.size < h * step:
        raise MessageError(f"image data holds {data.size} bytes, {w}x{h} {msg.encoding} with step {step} needs {h * step}")
    pixels = data[: h * step].reshape(h, step)[:, : w * channels].reshape(h, w, channels)
    code = {"rgb8": cv2.COLOR_RGB2BGR, "rgba8": cv2.COLOR_RGBA2BGR, "bgra8": cv2.COLOR_BGRA2BGR, "8UC4": cv2.COLOR_BGRA2BGR,
            "mono8": cv2.COLOR_GRAY2BGR, "8UC1": cv2.COLOR_GRAY2BGR}.get(msg.encoding)
    return np.ascontiguousarray(pixels) if code is None else cv2.cvtColor(pixels, code)


def write_image(msg, msgtype: str, stem: Path, size: Tuple[int, int], factor: int) -> str:
    """Write one camera message to ``stem`` + suffix; returns the suffix.

    ``CompressedImage`` PNG / JPEG bytes are copied unchanged (``factor`` 1); raw images, and every image shrunk by
    ``factor`` > 1 (``cv2.INTER_AREA``), are written as PNG (lossless).

    Args:
        size: (w, h) the camera_info gives, pixels; the image must have it.
    """
    import cv2

    if msgtype == COMPRESSED:
        fmt = msg.format.lower()
        suffix = ".png" if "png" in fmt else ".jpg" if ("jpeg" in fmt or "jpg" in fmt) else None
        if suffix is None or "compresseddepth" in fmt.replace(" ", ""):
            raise MessageError(f"unsupported CompressedImage format {msg.format!r} (png or jpeg)")
        data = np.asarray(msg.data, dtype=np.uint8)
        if factor == 1:
            import io

            from PIL import Image

            with Image.open(io.BytesIO(data.tobytes())) as img:
                shape = img.size
            _check_size(shape, size)
            stem.with_suffix(suffix).write_bytes(data.tobytes())
            return suffix
        pixels = cv2.imdecode(data, cv2.IMREAD_COLOR)
        if pixels is None:
            raise MessageError(f"CompressedImage ({msg.format}) does not decode")
    else:
        pixels = raw_pixels(msg)
    _check_size((pixels.shape[1], pixels.shape[0]), size)
    if not cv2.imwrite(str(stem.with_suffix(".png")), shrink(pixels, factor)):
        raise MessageError(f"cannot write {stem.with_suffix('.png')}")
    return ".png"


def _check_size(shape: Tuple[int, int], size: Tuple[int, int]) -> None:
    if tuple(shape) != tuple(size):
        raise MessageError(f"image is {shape[0]}x{shape[1]}, its camera_info says {size[0]}x{size[1]}")


def cloud_arrays(msg, frame_ns: int) -> Tuple[Float32[np.ndarray, "n 3"], Optional[Float[np.ndarray, " n"]], str]:
    """x, y, z and per-point time offsets of a ``sensor_msgs/PointCloud2``.

    The time field is the first of ``TIME_FIELDS`` present; its unit and base are told by its type and size: an
    integer field holds nanoseconds, a float field seconds; values above 1e14 are absolute nanoseconds, float values
    above 1e6 absolute seconds (Hesai), smaller ones are relative to the header stamp (Ouster ``t``, Velodyne ``time``).

    Args:
        frame_ns: the frame's stamp (header or receive time), integer nanoseconds: the times are offsets from it.

    Returns:
        (points (N, 3) float32 metres in the cloud's frame (float32 fields copied bit for bit; NaN kept), time
        offsets (N,) seconds or None without a time field, one line saying which field was read and how).
    """
    fields = {f.name: f for f in msg.fields}
    missing = [n for n in "xyz" if n not in fields]
    if missing:
        raise MessageError(f"PointCloud2 has no field {missing[0]!r} (fields: {', '.join(fields)})")
    time_name = next((n for n in TIME_FIELDS if n in fields), None)
    names = ["x", "y", "z"] + ([time_name] if time_name else [])
    bad = [n for n in names if fields[n].datatype not in POINT_TYPES or fields[n].count != 1]
    if bad:
        raise MessageError(f"PointCloud2 field {bad[0]!r} has datatype {fields[bad[0]].datatype}, count {fields[bad[0]].count}")
    endian = ">" if msg.is_bigendian else "<"
    dtype = np.dtype({"names": names, "formats": [endian + POINT_TYPES[fields[n].datatype] for n in names],
                      "offsets": [fields[n].offset for n in names], "itemsize": int(msg.point_step)})
    w, h, row = int(msg.width), int(msg.height), int(msg.row_step)
    data = np.asarray(msg.data, dtype=np.uint8)
    if row < w * msg.point_step or data.size < h * row:
        raise MessageError(f"PointCloud2 data holds {data.size} bytes, {w}x{h} points of {msg.point_step} bytes need more")
    flat = data[: h * row] if row == w * msg.point_step else data[: h * row].reshape(h, row)[:, : w * msg.point_step].reshape(-1)
    rec = np.frombuffer(np.ascontiguousarray(flat), dtype=dtype, count=w * h)
    points = np.stack([rec[n] for n in "xyz"], axis=-1).astype(np.float32)
    if time_name is None:
        return points, None, "no per-point time field (t, time, timestamp): none written"
    values = rec[time_name]
    integer, top = values.dtype.kind in "iu", float(np.abs(values).max()) if len(values) else 0.0
    kind = f"{time_name!r} ({values.dtype.name}"
    if top > 1e14:
        times = (values.astype(np.int64) - frame_ns) * 1e-9 if integer else (values - float(frame_ns)) * 1e-9
        return points, times, kind + ", absolute nanoseconds)"
    if not integer and top > 1e6:
        times = (values - float(frame_ns // 1_000_000_000)) - (frame_ns % 1_000_000_000) * 1e-9
        return points, times, kind + ", absolute seconds)"
    times = values * 1e-9 if integer else values.astype(np.float64)
    shift = stamp_ns(msg.header) - frame_ns
    return points, times + shift * 1e-9 if shift else times, kind + (", nanoseconds" if integer else ", seconds") + " from the header stamp)"

"""Tests of the ``moisst-rig/1`` loader/validator (moisst_ns/rig/format.py, contract in docs/rig-format.md).

One tiny synthetic rig (64x48, 3 frames per sensor, 3 cameras + LiDAR) is generated once per module and never
modified; every bad-input test copies it into its own ``tmp_path``, breaks one thing and checks that
``RigFormatError`` says, on one line, which file, which field and what is wrong.
"""

from __future__ import annotations

import hashlib
import json
import re
import shutil
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
from PIL import Image

from moisst_ns.rig.format import (
    FORMAT,
    TOP_KEYS,
    Calibration,
    RigFormatError,
    load_calibration,
    load_lidar_scan,
    load_rig,
    load_tum,
    rig_to_json,
    write_tum,
)
from moisst_ns.datasets.synth import SynthConfig, make_rig

REF = "cam_front"
CAM = "cam_left"  # a non-reference camera of the synthetic rig
LIDAR = "lidar"
TRAJ = "reference_poses.txt"


# ----------------------------------------------------------------------------------------------------------------
# Fixtures and helpers


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    """A valid tiny rig; read-only for the tests (copy it before editing)."""
    out = tmp_path_factory.mktemp("format") / "rig"
    return make_rig(
        SynthConfig(out=out, width=64, height=48, frames=3, lidar=True, lidar_beams=8, lidar_azimuth_steps=128, lidar_max_points=400)
    )


@pytest.fixture
def rig_dir(dataset, tmp_path) -> Path:
    """A private copy of the dataset, free to edit."""
    return Path(shutil.copytree(dataset, tmp_path / "rig"))


def read_json(root: Path, name: str = "rig.json") -> dict:
    return json.loads((root / name).read_text())


def edit_json(root: Path, edit: Callable[[dict], None], name: str = "rig.json") -> None:
    raw = read_json(root, name)
    edit(raw)
    (root / name).write_text(json.dumps(raw, indent=1))


def frame_index(root: Path, sensor: str, nth: int = 0) -> int:
    """Index in rig.json's frames of the ``nth`` frame of ``sensor``."""
    return [i for i, f in enumerate(read_json(root)["frames"]) if f["sensor"] == sensor][nth]


def file_hashes(root: Path) -> dict:
    return {str(p.relative_to(root)): (hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else "dir") for p in sorted(root.rglob("*"))}


def expect_error(call: Callable[[], object], file: Path | str, field: str, phrase: str) -> RigFormatError:
    """``call()`` raises RigFormatError: one line ``<file>: <field>: <problem>``, problem matching ``phrase``."""
    with pytest.raises(RigFormatError) as info:
        call()
    err = info.value
    msg = str(err)
    assert "\n" not in msg and "\r" not in msg, msg
    assert msg == f"{err.file}: {err.field}: {err.problem}", msg
    assert Path(err.file).resolve() == Path(file).resolve(), msg
    assert Path(file).name in msg, msg
    assert err.field == field, msg
    assert msg.startswith(f"{err.file}: {field}: "), msg
    assert re.search(phrase, err.problem), msg
    return err


def rig_error(root: Path, field: str, phrase: str, file: Path | None = None) -> RigFormatError:
    return expect_error(lambda: load_rig(root), file if file is not None else root / "rig.json", field, phrase)


# ----------------------------------------------------------------------------------------------------------------
# Valid data, round trips, read-only loading


def test_synthetic_rig_is_valid(dataset):
    rig = load_rig(dataset)
    assert rig.reference_sensor == REF
    assert set(rig.sensors) == {REF, "cam_front_right", CAM, LIDAR}
    assert rig.sensors[LIDAR].type == "lidar" and rig.sensors[LIDAR].intrinsics == {}
    assert len(rig.frames) == 4 * 3 and all(len(rig.frames_of(n)) == 3 for n in rig.sensors)
    assert rig.trajectory_file == TRAJ and len(rig.trajectory_stamps) == 3
    np.testing.assert_allclose(np.linalg.norm(rig.trajectory_quats_xyzw, axis=1), 1.0, atol=1e-12)
    assert load_rig(dataset / "rig.json").frames == rig.frames  # the rig.json path works too


def test_round_trip_rig_json(dataset, rig_dir):
    rig = load_rig(dataset)
    (rig_dir / "rig.json").write_text(json.dumps(rig_to_json(rig), indent=1) + "\n")
    again = load_rig(rig_dir)
    assert again.reference_sensor == rig.reference_sensor
    assert again.trajectory_file == rig.trajectory_file
    assert list(again.sensors) == list(rig.sensors)
    for name, s in rig.sensors.items():
        t = again.sensors[name]
        assert (t.name, t.type, t.time_offset, t.intrinsics) == (s.name, s.type, s.time_offset, s.intrinsics)
        assert np.array_equal(t.T_ref_sensor, s.T_ref_sensor)
    assert again.frames == rig.frames
    assert np.array_equal(again.trajectory_stamps, rig.trajectory_stamps)
    assert np.array_equal(again.trajectory_positions, rig.trajectory_positions)
    assert np.array_equal(again.trajectory_quats_xyzw, rig.trajectory_quats_xyzw)
    assert rig_to_json(again) == rig_to_json(rig)
    assert rig_to_json(rig)["format"] == FORMAT


def test_round_trip_tum_exact(tmp_path):
    rng = np.random.default_rng(3)
    stamps = 1.7e9 + np.cumsum(rng.uniform(1e-3, 0.2, 40))
    positions = rng.normal(size=(40, 3)) * 123.456
    quats = rng.normal(size=(40, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    write_tum(tmp_path / "a.txt", stamps, positions, quats)
    s, p, q = load_tum(tmp_path / "a.txt")
    assert np.array_equal(s, stamps) and np.array_equal(p, positions) and np.array_equal(q, quats)
    write_tum(tmp_path / "b.txt", s, p, q)
    assert (tmp_path / "a.txt").read_text() == (tmp_path / "b.txt").read_text()


def test_tum_comments_blank_lines_and_renormalisation(tmp_path):
    path = tmp_path / "t.txt"
    path.write_text("# header\n\n1.0 0 0 0 0 0 0 1  # trailing comment\n   \n2.0 1 2 3 0 0 0 1.0005\n")
    s, p, q = load_tum(path)
    assert s.tolist() == [1.0, 2.0] and p.tolist() == [[0, 0, 0], [1, 2, 3]]
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-15)  # within 1e-3 of unit: renormalised


def test_loading_never_writes_into_the_dataset(dataset):
    before = file_hashes(dataset)
    rig = load_rig(dataset)
    load_calibration(dataset / "ground_truth.json")
    for frame in rig.frames_of(LIDAR):
        load_lidar_scan(dataset / frame.file_path)
    assert file_hashes(dataset) == before


def test_check_files_false_skips_file_checks(rig_dir):
    i = frame_index(rig_dir, CAM)
    (rig_dir / read_json(rig_dir)["frames"][i]["file_path"]).unlink()
    assert len(load_rig(rig_dir, check_files=False).frames) == 12
    rig_error(rig_dir, f"frames[{i}].file_path", "file not found")


def test_comment_and_metadata_are_allowed(rig_dir):
    edit_json(rig_dir, lambda r: r.update(comment="hello", metadata={"any": [1, 2]}))
    load_rig(rig_dir)


def test_opencv_camera_with_distortion_is_valid(rig_dir):
    edit_json(rig_dir, lambda r: r["sensors"][CAM].update(camera_model="OPENCV", k1=-0.1, k2=0.01, p1=1e-3, p2=-1e-3))
    intr = load_rig(rig_dir).sensors[CAM].intrinsics
    assert (intr["camera_model"], intr["k1"], intr["p2"], intr["k3"]) == ("OPENCV", -0.1, -1e-3, 0.0)


# ----------------------------------------------------------------------------------------------------------------
# rig.json: file, JSON, top level


def test_rig_json_not_found(rig_dir):
    (rig_dir / "rig.json").unlink()
    rig_error(rig_dir, "rig.json", "file not found")


def test_invalid_json(rig_dir):
    (rig_dir / "rig.json").write_text('{\n "format": "moisst-rig/1",\n "sensors": {,}\n}\n')
    rig_error(rig_dir, "line 3, column 14", "invalid JSON: Expecting property name enclosed in double quotes$")


def test_truncated_json_names_line_and_column(rig_dir):
    text = (rig_dir / "rig.json").read_text()
    cut = text.index('"', text.index('"frames"') + 12) + 4  # inside a string of the frames list
    (rig_dir / "rig.json").write_text(text[:cut])
    line = text[:cut].count("\n") + 1
    column = cut - (text.rfind("\n", 0, cut) + 1) - 3  # the string's opening quote
    rig_error(rig_dir, f"line {line}, column {column}", "invalid JSON: Unterminated string starting there$")


def test_missing_dataset_folder_says_so(tmp_path):
    with pytest.raises(RigFormatError) as info:
        load_rig(tmp_path / "no" / "such")
    assert str(info.value) == f"{tmp_path / 'no' / 'such'}: dataset: folder not found"


def test_folder_without_rig_json_says_so(tmp_path):
    with pytest.raises(RigFormatError, match=r"rig\.json: rig\.json: file not found \(the dataset folder has no rig\.json\)$"):
        load_rig(tmp_path)


def test_top_level_not_an_object(rig_dir):
    (rig_dir / "rig.json").write_text("[1, 2]")
    rig_error(rig_dir, "(top level)", "must be a JSON object")


@pytest.mark.parametrize("key", TOP_KEYS)
def test_missing_top_level_key(rig_dir, key):
    edit_json(rig_dir, lambda r: r.pop(key))
    rig_error(rig_dir, key, "^missing$")


def test_unknown_top_level_key(rig_dir):
    edit_json(rig_dir, lambda r: r.update(sensor_list=[]))
    rig_error(rig_dir, "sensor_list", "unknown key")


@pytest.mark.parametrize("value, field, problem", [
    ([0.01], "trajectory_accuracy", "must be an object of"), ({"noise_cm": 1.0}, "trajectory_accuracy.noise_cm", "unknown key"),
    ({"drift_m": -0.01}, "trajectory_accuracy.drift_m", "must be a finite number >= 0, got -0.01"),
    ({"noise_deg": "0.1"}, "trajectory_accuracy.noise_deg", "must be a finite number"), ({"noise_m": True}, "trajectory_accuracy.noise_m", "finite")])
def test_bad_trajectory_accuracy(rig_dir, value, field, problem):
    edit_json(rig_dir, lambda r: r.update(trajectory_accuracy=value))
    rig_error(rig_dir, field, problem)


def test_trajectory_accuracy_read_and_written_back(rig_dir):
    assert "trajectory_accuracy" not in rig_to_json(load_rig(rig_dir))  # none stated: none written
    edit_json(rig_dir, lambda r: r.update(trajectory_accuracy={"noise_m": 0.02, "drift_deg": 0.1}))
    rig = load_rig(rig_dir)
    assert (rig.trajectory_accuracy.noise_m, rig.trajectory_accuracy.noise_deg, rig.trajectory_accuracy.drift_deg) == (0.02, 0.0, 0.1)
    assert rig_to_json(rig)["trajectory_accuracy"] == {"noise_m": 0.02, "noise_deg": 0.0, "drift_m": 0.0, "drift_deg": 0.1}


def test_message_stays_on_one_line_with_line_breaks_in_keys(rig_dir):
    edit_json(rig_dir, lambda r: r.update({"bad\nkey\r": 1}))
    rig_error(rig_dir, "bad\\nkey\\r", "unknown key")


@pytest.mark.parametrize("value", ["moisst-rig/2", "moisst-rig", 1])
def test_wrong_format_string(rig_dir, value):
    edit_json(rig_dir, lambda r: r.update(format=value))
    rig_error(rig_dir, "format", "expected 'moisst-rig/1', got")


@pytest.mark.parametrize("key, value, phrase", [("sensors", {}, "non-empty object"), ("sensors", [], "non-empty object"), ("frames", [], "non-empty list"), ("frames", {}, "non-empty list")])
def test_empty_sensors_or_frames(rig_dir, key, value, phrase):
    edit_json(rig_dir, lambda r: r.update({key: value}))
    rig_error(rig_dir, key, phrase)


# ----------------------------------------------------------------------------------------------------------------
# sensors


@pytest.mark.parametrize(
    "sensor, key, phrase",
    [
        (CAM, "T_ref_sensor", "^missing$"),
        (LIDAR, "T_ref_sensor", "^missing$"),
        (CAM, "type", "must be one of"),
        (CAM, "fl_x", r"missing \(required for a camera\)"),
        (CAM, "camera_model", r"missing \(required for a camera\)"),
        (CAM, "h", r"missing \(required for a camera\)"),
    ],
)
def test_missing_sensor_key(rig_dir, sensor, key, phrase):
    edit_json(rig_dir, lambda r: r["sensors"][sensor].pop(key))
    rig_error(rig_dir, f"sensors.{sensor}.{key}", phrase)


def test_missing_time_offset_defaults_to_zero(rig_dir):
    edit_json(rig_dir, lambda r: r["sensors"][CAM].pop("time_offset"))
    assert load_rig(rig_dir).sensors[CAM].time_offset == 0.0


@pytest.mark.parametrize("sensor, key, stype", [(CAM, "focal", "camera"), (LIDAR, "fl_x", "lidar"), (LIDAR, "w", "lidar")])
def test_unknown_sensor_key(rig_dir, sensor, key, stype):
    edit_json(rig_dir, lambda r: r["sensors"][sensor].update({key: 1}))
    rig_error(rig_dir, f"sensors.{sensor}.{key}", f"unknown key for a {stype}")


@pytest.mark.parametrize("stype", ["radar", "Camera", None])
def test_unknown_sensor_type(rig_dir, stype):
    edit_json(rig_dir, lambda r: r["sensors"][CAM].update(type=stype))
    rig_error(rig_dir, f"sensors.{CAM}.type", r"must be one of \('camera', 'lidar'\), got")


def test_sensor_not_an_object(rig_dir):
    edit_json(rig_dir, lambda r: r["sensors"].update({CAM: [1]}))
    rig_error(rig_dir, f"sensors.{CAM}", "must be an object")


def _scaled(m):
    m[:3, :3] *= 1.1


def _reflected(m):
    m[:3, 0] *= -1.0


def _last_row(m):
    m[3] = [0.0, 0.0, 0.5, 1.0]


def _nan(m):
    m[0, 3] = np.nan


def _inf(m):
    m[1, 1] = np.inf


@pytest.mark.parametrize(
    "make, phrase",
    [
        (_scaled, "not orthonormal"),
        (_reflected, r"determinant \+1"),
        (_last_row, r"last row must be \[0, 0, 0, 1\]"),
        (_nan, "NaN or inf"),
        (_inf, "NaN or inf"),
        (lambda m: m[:3], r"expected a 4x4 matrix, got shape \(3, 4\)"),
        (lambda m: m.ravel(), r"expected a 4x4 matrix, got shape \(16,\)"),
        (lambda m: [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1]], "must be a 4x4 list of numbers"),
        (lambda m: [["a"] * 4] * 4, "must be a 4x4 list of numbers"),
    ],
    ids=["scaled", "reflection", "last-row", "nan", "inf", "3x4", "flat", "ragged", "strings"],
)
def test_matrix_not_rigid(rig_dir, make, phrase):
    def edit(raw):
        m = np.array(raw["sensors"][CAM]["T_ref_sensor"])
        out = make(m)  # the mutators edit m in place and return None; the others return the new value
        out = m if out is None else out
        raw["sensors"][CAM]["T_ref_sensor"] = out.tolist() if isinstance(out, np.ndarray) else out

    edit_json(rig_dir, edit)
    rig_error(rig_dir, f"sensors.{CAM}.T_ref_sensor", phrase)


def test_slightly_off_rigid_matrix_is_accepted(rig_dir):
    """Tolerance 1e-4: JSON round-off of a rotation is fine."""
    edit_json(rig_dir, lambda r: r["sensors"][CAM].update(T_ref_sensor=(np.eye(4) + 1e-6 * np.triu(np.ones((4, 4)), 1) * [[1], [1], [1], [0]]).tolist()))
    load_rig(rig_dir)


@pytest.mark.parametrize("name", ["cam_rear", ["cam_front"], None])
def test_reference_sensor_missing_from_sensors(rig_dir, name):
    edit_json(rig_dir, lambda r: r.update(reference_sensor=name))
    rig_error(rig_dir, "reference_sensor", "is not one of the sensors")


def test_reference_sensor_non_identity_extrinsic(rig_dir):
    def edit(raw):
        raw["sensors"][REF]["T_ref_sensor"][0][3] = 0.1

    edit_json(rig_dir, edit)
    rig_error(rig_dir, f"sensors.{REF}.T_ref_sensor", "must be the identity")


def test_reference_sensor_non_zero_time_offset(rig_dir):
    edit_json(rig_dir, lambda r: r["sensors"][REF].update(time_offset=0.01))
    rig_error(rig_dir, f"sensors.{REF}.time_offset", "must be 0")


@pytest.mark.parametrize("value", ["0.1", None, True, float("nan"), float("inf")])
def test_time_offset_not_a_number(rig_dir, value):
    edit_json(rig_dir, lambda r: r["sensors"][CAM].update(time_offset=value))
    rig_error(rig_dir, f"sensors.{CAM}.time_offset", "must be a finite number")


@pytest.mark.parametrize("model", ["OPENCV_FISHEYE", "SIMPLE_PINHOLE", "pinhole", "EQUIRECTANGULAR"])
def test_unsupported_camera_model(rig_dir, model):
    edit_json(rig_dir, lambda r: r["sensors"][CAM].update(camera_model=model))
    rig_error(rig_dir, f"sensors.{CAM}.camera_model", f"unsupported camera model '{model}'; supported: PINHOLE, OPENCV")


@pytest.mark.parametrize("key", ["k1", "k2", "p1", "p2", "k3", "k4"])
def test_pinhole_with_distortion(rig_dir, key):
    edit_json(rig_dir, lambda r: r["sensors"][CAM].update({key: 0.01}))
    rig_error(rig_dir, f"sensors.{CAM}.camera_model", "PINHOLE cameras take no distortion")


@pytest.mark.parametrize(
    "key, value, phrase",
    [
        ("w", 0, "must be a positive integer, got 0"),
        ("h", -48, "must be a positive integer, got -48"),
        ("w", 64.0, "must be a positive integer, got 64.0"),
        ("w", "64", "must be a positive integer"),
        ("w", True, "must be a positive integer"),
        ("fl_x", 0, "must be > 0, got 0"),
        ("fl_y", -51.2, "must be > 0"),
        ("fl_x", "51.2", "must be a finite number"),
        ("cx", None, "must be a finite number"),
        ("k1", "0", "must be a finite number"),
    ],
)
def test_bad_intrinsics(rig_dir, key, value, phrase):
    edit_json(rig_dir, lambda r: r["sensors"][CAM].update({key: value}))
    rig_error(rig_dir, f"sensors.{CAM}.{key}", phrase)


@pytest.mark.parametrize("name", ["cam/left", "..", ".", "a\\b", "a:b", " cam", "cam ", "", "a\nb", "a\tb"])
def test_bad_sensor_name(rig_dir, name):
    def edit(raw):
        raw["sensors"][name] = raw["sensors"].pop(CAM)
        for f in raw["frames"]:
            if f["sensor"] == CAM:
                f["sensor"] = name

    edit_json(rig_dir, edit)
    err = rig_error(rig_dir, f"sensors.{name}".replace("\n", "\\n"), "invalid sensor name")
    assert repr(name) in err.problem


def test_sensor_with_no_frames(rig_dir):
    edit_json(rig_dir, lambda r: r.update(frames=[f for f in r["frames"] if f["sensor"] != CAM]))
    rig_error(rig_dir, f"sensors.{CAM}", "has no frames")


# ----------------------------------------------------------------------------------------------------------------
# frames and their files


@pytest.mark.parametrize("name", ["cam_rear", ["cam_left"], 3])
def test_frame_names_unknown_sensor(rig_dir, name):
    edit_json(rig_dir, lambda r: r["frames"][3].update(sensor=name))
    rig_error(rig_dir, "frames[3].sensor", f"unknown sensor {re.escape(repr(name))}")


@pytest.mark.parametrize("key", ["sensor", "timestamp", "file_path"])
def test_frame_missing_key(rig_dir, key):
    edit_json(rig_dir, lambda r: r["frames"][3].pop(key))
    rig_error(rig_dir, f"frames[3].{key}", "^missing$")


def test_frame_unknown_key(rig_dir):
    edit_json(rig_dir, lambda r: r["frames"][3].update(time=1.0))
    rig_error(rig_dir, "frames[3].time", "unknown key")


def test_frame_not_an_object(rig_dir):
    edit_json(rig_dir, lambda r: r["frames"].__setitem__(3, "images/x.png"))
    rig_error(rig_dir, "frames[3]", "must be an object")


@pytest.mark.parametrize("value", ["1000.0", None, float("nan")])
def test_frame_timestamp_not_a_number(rig_dir, value):
    edit_json(rig_dir, lambda r: r["frames"][3].update(timestamp=value))
    rig_error(rig_dir, "frames[3].timestamp", "must be a finite number")


@pytest.mark.parametrize("sensor", [CAM, LIDAR])
def test_frame_file_not_found(rig_dir, sensor):
    i = frame_index(rig_dir, sensor, 1)
    rel = read_json(rig_dir)["frames"][i]["file_path"]
    (rig_dir / rel).unlink()
    rig_error(rig_dir, f"frames[{i}].file_path", f"file not found: .*{re.escape(rel)}$")


@pytest.mark.parametrize(
    "path, phrase",
    [
        ("../x.png", "points outside the dataset folder"),
        ("images/../../x.png", "points outside the dataset folder"),
        ("/tmp/x.png", "must be relative to the dataset folder"),
        ("", "must be a non-empty relative path"),
        (None, "must be a non-empty relative path"),
    ],
)
def test_frame_file_path_escapes_dataset(rig_dir, path, phrase):
    if path == "../x.png":  # exists, so only the path rule can refuse it
        Image.new("RGB", (64, 48)).save(rig_dir.parent / "x.png")
    edit_json(rig_dir, lambda r: r["frames"][3].update(file_path=path))
    rig_error(rig_dir, "frames[3].file_path", phrase)


@pytest.mark.parametrize("sensor, suffix, stype", [(CAM, ".npz", "camera"), (CAM, ".bmp", "camera"), (LIDAR, ".png", "lidar"), (LIDAR, ".pcd", "lidar")])
def test_frame_file_wrong_type(rig_dir, sensor, suffix, stype):
    i = frame_index(rig_dir, sensor)
    edit_json(rig_dir, lambda r: r["frames"][i].update(file_path=f"data/x{suffix}"))
    rig_error(rig_dir, f"frames[{i}].file_path", f"a {stype} frame must be one of")


def test_image_size_not_w_x_h(rig_dir):
    i = frame_index(rig_dir, CAM, 2)
    image = rig_dir / read_json(rig_dir)["frames"][i]["file_path"]
    Image.new("RGB", (32, 24), (10, 20, 30)).save(image)
    rig_error(rig_dir, f"frames[{i}] (sensor {CAM})", "image is 32x24, rig.json says w x h = 64x48", file=image)


def test_image_transposed_size(rig_dir):
    i = frame_index(rig_dir, REF)
    image = rig_dir / read_json(rig_dir)["frames"][i]["file_path"]
    Image.new("RGB", (48, 64)).save(image)
    rig_error(rig_dir, f"frames[{i}] (sensor {REF})", "image is 48x64", file=image)


def test_unreadable_image(rig_dir):
    i = frame_index(rig_dir, CAM)
    image = rig_dir / read_json(rig_dir)["frames"][i]["file_path"]
    image.write_bytes(b"not a png")
    rig_error(rig_dir, f"frames[{i}].file_path", "unreadable image", file=image)


# ----------------------------------------------------------------------------------------------------------------
# the TUM trajectory


def write_poses(root: Path, text: str) -> Path:
    path = root / TRAJ
    path.write_text(text)
    return path


GOOD_LINES = ["1000.0 0 0 0 0 0 0 1", "1000.1 1 0 0 0 0 0 1", "1000.2 2 0 0 0 0 0 1"]


def test_trajectory_file_not_found(rig_dir):
    (rig_dir / TRAJ).unlink()
    rig_error(rig_dir, "trajectory", "file not found", file=rig_dir / TRAJ)


def test_trajectory_path_escapes_dataset(rig_dir):
    edit_json(rig_dir, lambda r: r.update(trajectory="../" + TRAJ))
    rig_error(rig_dir, "trajectory", "points outside the dataset folder")


@pytest.mark.parametrize("lines", [GOOD_LINES[:1], [], ["# only a comment"]])
def test_fewer_than_two_poses(rig_dir, lines):
    path = write_poses(rig_dir, "\n".join(lines) + "\n")
    rig_error(rig_dir, "poses", f"needs at least 2 poses, got {len([x for x in lines if not x.startswith('#')])}", file=path)


@pytest.mark.parametrize("stamps, bad", [((1000.0, 1000.1, 1000.1), 3), ((1000.0, 999.9, 1000.2), 2)])
def test_timestamps_not_increasing(rig_dir, stamps, bad):
    path = write_poses(rig_dir, "".join(f"{t} {k} 0 0 0 0 0 1\n" for k, t in enumerate(stamps)))
    rig_error(rig_dir, "timestamp", rf"strictly increasing \(pose {bad}\)", file=path)


def test_non_unit_quaternion(rig_dir):
    path = write_poses(rig_dir, "\n".join([GOOD_LINES[0], "1000.1 1 0 0 0 0 0 1.1", GOOD_LINES[2]]) + "\n")
    rig_error(rig_dir, "quaternion of pose 2", r"not a unit quaternion \(norm 1.100000\)", file=path)


@pytest.mark.parametrize(
    "bad_line, field, phrase",
    [
        ("1000.1 1 0 0 0 0 1", "line 3", "expected 8 values 'timestamp tx ty tz qx qy qz qw', got 7"),
        ("1000.1 1 0 0 0 0 0 1 5", "line 3", "got 9"),
        ("1000.1,1,0,0,0,0,0,1", "line 3", "got 1"),
        ("1000.1 one 0 0 0 0 0 1", "line 3", "not a number"),
        ("1000.1 nan 0 0 0 0 0 1", "poses", "contains NaN or inf"),
    ],
)
def test_malformed_tum_line(rig_dir, bad_line, field, phrase):
    path = write_poses(rig_dir, "\n".join(["# timestamp tx ty tz qx qy qz qw", GOOD_LINES[0], bad_line, GOOD_LINES[2]]) + "\n")
    rig_error(rig_dir, field, phrase, file=path)


# ----------------------------------------------------------------------------------------------------------------
# LiDAR scans


def scan_error(path: Path, field: str, phrase: str) -> RigFormatError:
    return expect_error(lambda: load_lidar_scan(path), path, field, phrase)


def test_synthetic_npz_scans_load(dataset):
    rig = load_rig(dataset)
    for frame in rig.frames_of(LIDAR):
        points, times, dropped = load_lidar_scan(dataset / frame.file_path)
        assert points.dtype == np.float32 and points.ndim == 2 and points.shape[1] == 3 and len(points) > 0
        assert times is not None and times.shape == (len(points),) and dropped == 0
        assert np.all((times >= 0) & (times < 0.1))


def test_npy_and_bin_scans_load(tmp_path):
    pts = np.random.default_rng(0).normal(size=(10, 3)) * 10
    np.save(tmp_path / "a.npy", pts)
    points, times, dropped = load_lidar_scan(tmp_path / "a.npy")
    assert points.dtype == np.float32 and np.array_equal(points, pts.astype(np.float32)) and times is None and dropped == 0
    xyzi = np.concatenate([pts, np.full((10, 1), 0.5)], axis=1).astype(np.float32)
    xyzi.tofile(tmp_path / "a.bin")
    points, times, dropped = load_lidar_scan(tmp_path / "a.bin")
    assert np.array_equal(points, xyzi[:, :3]) and times is None and dropped == 0


def test_empty_lidar_scan(tmp_path):
    np.save(tmp_path / "e.npy", np.zeros((0, 3), np.float32))
    scan_error(tmp_path / "e.npy", "array", r"\(empty scan\)")


@pytest.mark.parametrize("shape", [(10, 4), (10,), (2, 5, 3)])
def test_lidar_wrong_shape(tmp_path, shape):
    np.save(tmp_path / "w.npy", np.ones(shape, np.float32))
    scan_error(tmp_path / "w.npy", "array", re.escape(f"expected an (N, 3) array, got shape {shape}"))


def test_npz_points_wrong_shape(tmp_path):
    np.savez(tmp_path / "w.npz", points=np.ones((10, 4), np.float32))
    scan_error(tmp_path / "w.npz", "points", r"expected an \(N, 3\) array")


def test_npz_times_length_mismatch(tmp_path):
    np.savez(tmp_path / "t.npz", points=np.ones((10, 3), np.float32), times=np.zeros(9))
    scan_error(tmp_path / "t.npz", "times", r"expected shape \(10,\) to match points, got \(9,\)")


def test_npz_times_not_finite(tmp_path):
    times = np.zeros(10)
    times[4] = np.nan
    np.savez(tmp_path / "t.npz", points=np.ones((10, 3), np.float32), times=times)
    scan_error(tmp_path / "t.npz", "times", "contains NaN or inf")


def test_npz_without_points(tmp_path):
    np.savez(tmp_path / "p.npz", xyz=np.ones((10, 3), np.float32))
    scan_error(tmp_path / "p.npz", "points", "missing array")


@pytest.mark.parametrize("size", [5 * 4, (4 * 7 + 3) * 4, 8 * 4 + 1, 3])
def test_bin_size_not_multiple_of_four_floats(tmp_path, size):
    (tmp_path / "k.bin").write_bytes(np.ones(size // 4 + 1, np.float32).tobytes()[:size])
    scan_error(tmp_path / "k.bin", "data", rf"{size} bytes is not a multiple of 16 \(4 floats\)")


def test_nan_points_dropped_and_counted(tmp_path):
    pts = np.arange(30, dtype=np.float32).reshape(10, 3) + 1.0
    pts[2, 0] = np.nan
    pts[5, 1] = np.inf
    pts[7] = np.nan
    times = np.linspace(0.0, 0.09, 10)
    np.savez(tmp_path / "n.npz", points=pts, times=times)
    points, kept_times, dropped = load_lidar_scan(tmp_path / "n.npz")
    keep = [0, 1, 3, 4, 6, 8, 9]
    assert dropped == 3
    assert np.array_equal(points, pts[keep]) and np.array_equal(kept_times, times[keep])


def test_all_nan_scan_raises(tmp_path):
    np.save(tmp_path / "n.npy", np.full((5, 3), np.nan, np.float32))
    scan_error(tmp_path / "n.npy", "array", "no points left after dropping non-finite points")


@pytest.mark.parametrize(
    "name, content, field, phrase",
    [
        ("c.npz", b"PK\x03\x04 truncated zip", "data", "unreadable"),
        ("c.npy", b"garbage", "data", "unreadable"),
        ("c.pcd", b"# .PCD v0.7", "file_path", "unsupported LiDAR file type '.pcd'"),
    ],
)
def test_unreadable_lidar_file(tmp_path, name, content, field, phrase):
    (tmp_path / name).write_bytes(content)
    scan_error(tmp_path / name, field, phrase)


def test_lidar_file_not_found(tmp_path):
    scan_error(tmp_path / "none.npy", "file_path", "file not found")


def test_lidar_non_real_dtype(tmp_path):
    np.save(tmp_path / "c.npy", np.ones((4, 3), complex))
    scan_error(tmp_path / "c.npy", "array", "expected real numbers")


# ----------------------------------------------------------------------------------------------------------------
# ground_truth.json / calibration.json


def test_load_calibration_good(dataset, tmp_path):
    cal = load_calibration(dataset / "ground_truth.json")
    rig = load_rig(dataset)
    assert cal.reference_sensor == REF and set(cal.T_ref_sensor) == set(rig.sensors) == set(cal.time_offset)
    assert np.array_equal(cal.T_ref_sensor[REF], np.eye(4)) and cal.time_offset[REF] == 0.0
    assert all(0.02 <= abs(cal.time_offset[n]) <= 0.06 for n in rig.sensors if n != REF)
    cal.write(tmp_path / "calibration.json")
    again = load_calibration(tmp_path / "calibration.json")
    assert again.to_json() == cal.to_json()
    prior = Calibration.from_rig(rig)
    assert prior.reference_sensor == REF and np.array_equal(prior.T_ref_sensor[CAM], rig.sensors[CAM].T_ref_sensor)


def test_a_trajectory_carried_to_the_reference_sensor(dataset, tmp_path):
    """``trajectory_T_reference`` survives calibration.json, and the dataparser's ``apply_prior_calibration`` carries the
    rig's trajectory by it: every pose becomes ``trajectory(t) @ T``, exactly; a non-rigid one is refused by field."""
    from scipy.spatial.transform import Rotation

    from moisst_ns.data.dataparser import apply_prior_calibration

    T = np.eye(4)
    T[:3, :3], T[:3, 3] = Rotation.from_rotvec([0.01, -0.02, 0.005]).as_matrix(), [0.1, 0.0, -0.2]
    cal = load_calibration(dataset / "ground_truth.json")
    cal.trajectory_T_reference = T
    cal.write(tmp_path / "calibration.json")
    again = load_calibration(tmp_path / "calibration.json")
    np.testing.assert_array_equal(again.trajectory_T_reference, T)
    assert load_calibration(dataset / "ground_truth.json").trajectory_T_reference is None
    rig, before = load_rig(dataset), load_rig(dataset)
    apply_prior_calibration(rig, again, tmp_path / "calibration.json")
    for i in range(len(rig.trajectory_stamps)):
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = Rotation.from_quat(before.trajectory_quats_xyzw[i]).as_matrix(), before.trajectory_positions[i]
        carried = pose @ T
        np.testing.assert_allclose(Rotation.from_quat(rig.trajectory_quats_xyzw[i]).as_matrix(), carried[:3, :3], atol=1e-12)
        np.testing.assert_allclose(rig.trajectory_positions[i], carried[:3, 3], atol=1e-12)
    raw = json.loads((tmp_path / "calibration.json").read_text())
    raw["trajectory_T_reference"][0][0] = 2.0
    (tmp_path / "calibration.json").write_text(json.dumps(raw))
    expect_error(lambda: load_calibration(tmp_path / "calibration.json"), tmp_path / "calibration.json", "trajectory_T_reference", "not orthonormal")


def test_load_calibration_non_rigid(rig_dir):
    def edit(raw):
        m = np.array(raw["sensors"][CAM]["T_ref_sensor"])
        m[:3, :3] *= 2.0
        raw["sensors"][CAM]["T_ref_sensor"] = m.tolist()

    edit_json(rig_dir, edit, "ground_truth.json")
    expect_error(lambda: load_calibration(rig_dir / "ground_truth.json"), rig_dir / "ground_truth.json", f"sensors.{CAM}.T_ref_sensor", "not orthonormal")


@pytest.mark.parametrize(
    "content, field, phrase",
    [
        (None, "(file)", "file not found"),
        ("{bad", "line 1, column 2", "invalid JSON: Expecting property name enclosed in double quotes"),
        ("[]", "(top level)", "must be a JSON object"),
        ('{"sensors": {}}', "reference_sensor", "^missing$"),
        ('{"reference_sensor": "a"}', "sensors", "^missing$"),
        ('{"reference_sensor": "b", "sensors": {"a": {"T_ref_sensor": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}}}', "reference_sensor", "is not in sensors"),
        ('{"reference_sensor": ["a"], "sensors": {}}', "reference_sensor", "is not in sensors"),
        ('{"reference_sensor": "a", "sensors": {"a": {}}}', "sensors.a.T_ref_sensor", "^missing$"),
        ('{"reference_sensor": "a", "sensors": {"a": {"T_ref_sensor": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]], "time_offset": "x"}}}', "sensors.a.time_offset", "finite number"),
        ('{"reference_sensor": "a/b", "sensors": {"a/b": {"T_ref_sensor": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}}}', "sensors.a/b", "invalid sensor name"),
    ],
)
def test_load_calibration_errors(tmp_path, content, field, phrase):
    path = tmp_path / "calibration.json"
    if content is not None:
        path.write_text(content)
    expect_error(lambda: load_calibration(path), path, field, phrase)

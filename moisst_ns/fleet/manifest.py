"""The fleet manifest (TOML; its format: ``docs/fleet.md``): which drives to calibrate, of which vehicle, with which
``moisst-calibrate`` options. Everything is checked before any work starts; the first problem raises ``FleetError``
with one line naming the manifest, the table and the field.
"""

from __future__ import annotations

import dataclasses
import re
import tomllib
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Tuple

from moisst_ns.fleet import FleetError
from moisst_ns.calibrate import CalibrateConfig

FLEET_OWNED = ("dataset", "output_dir", "viewer", "viewer_host", "resume", "threads")
"""CalibrateConfig fields the fleet sets itself (the manifest may not): the dataset comes from ``dataset``, the
output folder is ``OUT/<vehicle>/<id>``, torch threads are ``--cpus-per-drive``, no viewer, resume is per drive."""
DRIVE_KEYS = ("id", "vehicle", "dataset")
NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


@dataclass
class Drive:
    """One drive of the manifest."""

    id: str
    """Unique drive name (also its output folder ``OUT/<vehicle>/<id>``)."""
    vehicle: str
    """The vehicle it was driven with; drives of one vehicle are combined into its consensus calibration."""
    dataset: Path
    """Its moisst-rig/1 dataset folder (absolute, resolved against the manifest's folder)."""
    options: Dict[str, Any] = field(default_factory=dict)
    """``moisst-calibrate`` options for this drive: the manifest's ``[calibrate]`` table, then its own overrides."""


@dataclass
class Manifest:
    """A validated manifest."""

    path: Path
    """The manifest file."""
    drives: List[Drive]
    """Every drive, in manifest order (the drives of a vehicle are taken to be in the order they were driven)."""

    def vehicles(self) -> Dict[str, List[Drive]]:
        """Drives per vehicle, in manifest order."""
        out: Dict[str, List[Drive]] = {}
        for drive in self.drives:
            out.setdefault(drive.vehicle, []).append(drive)
        return out


def _check_value(file: Path, where: str, key: str, value: Any, kind: Any) -> Any:
    """``value`` checked against the CalibrateConfig type ``kind`` (Optional, Literal, bool, int, float, str)."""
    origin, args = typing.get_origin(kind), typing.get_args(kind)
    if origin is typing.Union:  # Optional[X]: TOML has no null, so the value must be an X
        kind = next(a for a in args if a is not type(None))
        origin, args = typing.get_origin(kind), typing.get_args(kind)
    if origin is typing.Literal:
        if value not in args:
            raise FleetError(f"{file}: {where}.{key}: must be one of {', '.join(map(repr, args))}, got {value!r}")
        return value
    if kind is bool:
        ok = isinstance(value, bool)
    elif kind is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
    elif kind is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        value = float(value) if ok else value
    elif kind is str:
        ok = isinstance(value, str)
    else:
        raise FleetError(f"{file}: {where}.{key}: this option cannot be set from a manifest")
    if not ok:
        raise FleetError(f"{file}: {where}.{key}: must be {getattr(kind, '__name__', kind)}, got {value!r}")
    return value


def _options(file: Path, where: str, table: Dict[str, Any], allowed: Dict[str, Any], extra: Tuple[str, ...] = ()) -> Dict[str, Any]:
    out = {}
    for key, value in table.items():
        if key in extra:
            continue
        if key in FLEET_OWNED:
            raise FleetError(f"{file}: {where}.{key}: set by moisst-fleet itself, not by the manifest")
        if key not in allowed:
            raise FleetError(f"{file}: {where}: unknown key {key!r} (known: {', '.join(extra + tuple(allowed))})")
        out[key] = _check_value(file, where, key, value, allowed[key])
    return out


def drive_dir(out: Path, drive: Drive) -> Path:
    """A drive's output folder, ``OUT/<vehicle>/<id>``."""
    return out / drive.vehicle / drive.id


def load_manifest(path: Path | str) -> Manifest:
    """Read and validate a manifest: TOML syntax, keys, types, unique ids, every dataset folder holding rig.json.

    Args:
        path: the manifest file.

    Returns:
        The manifest, datasets resolved against its folder.

    Raises:
        FleetError: the first problem, in one line naming the file and the field.
    """
    file = Path(path)
    if not file.is_file():
        raise FleetError(f"{file}: manifest not found")
    try:
        raw = tomllib.loads(file.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as err:
        raise FleetError(f"{file}: not valid TOML: {err}") from None
    unknown = sorted(set(raw) - {"drive", "calibrate"})
    if unknown:
        raise FleetError(f"{file}: unknown top-level key {unknown[0]!r} (known: drive, calibrate)")
    hints = typing.get_type_hints(CalibrateConfig)  # the moisst-calibrate options a manifest may set, and their types
    allowed = {f.name: hints[f.name] for f in dataclasses.fields(CalibrateConfig) if f.name not in FLEET_OWNED}
    calibrate = raw.get("calibrate", {})
    if not isinstance(calibrate, dict):
        raise FleetError(f"{file}: calibrate: must be a table ([calibrate])")
    calibrate = _options(file, "calibrate", calibrate, allowed)
    tables = raw.get("drive")
    if not isinstance(tables, list) or not tables or not all(isinstance(t, dict) for t in tables):
        raise FleetError(f"{file}: drive: at least one [[drive]] table is needed")
    drives, seen = [], {}
    for k, table in enumerate(tables):
        where = f"drive[{k}]"
        for key in DRIVE_KEYS:
            if key not in table:
                raise FleetError(f"{file}: {where}.{key}: missing")
            if not isinstance(table[key], str) or not table[key]:
                raise FleetError(f"{file}: {where}.{key}: must be a non-empty string, got {table[key]!r}")
        where = f"drive[{k}] ({table['id']})"
        for key in ("id", "vehicle"):
            if not NAME.match(table[key]):
                raise FleetError(f"{file}: {where}.{key}: {table[key]!r} is not a folder name (letters, digits, '_', '.', '-')")
        if table["id"] in seen:
            raise FleetError(f"{file}: {where}.id: {table['id']!r} duplicates drive[{seen[table['id']]}]")
        seen[table["id"]] = k
        options = {**calibrate, **_options(file, where, table, allowed, DRIVE_KEYS)}
        dataset = (file.parent / table["dataset"]).resolve()
        if not (dataset / "rig.json").is_file():
            what = "no such folder" if not dataset.exists() else "no rig.json in it"
            raise FleetError(f"{file}: {where}.dataset: {table['dataset']!r} ({dataset}): {what}")
        drives.append(Drive(table["id"], table["vehicle"], dataset, options))
    return Manifest(file, drives)

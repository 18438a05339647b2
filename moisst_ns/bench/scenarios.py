"""Scenario files of ``moisst-bench``: the shipped ones (package data) and their validation."""

from __future__ import annotations

import tomllib
from pathlib import Path

LOSS_SWITCHES = {"no-depth": "depth_loss", "no-dssim": "dssim_loss", "no-depth-smoothness": "depth_smoothness_loss"}
OPTIMISE = ("both", "spatial", "temporal")


class BenchError(ValueError):
    """A scenario file is malformed: ``<file>: <field>: <problem>``."""



# ----------------------------------------------------------------------------------------------------------------
# Scenarios


def packaged_scenarios(name: str) -> Path:
    """The path of a scenario file shipped inside the package (works from a wheel as from a checkout).

    Args:
        name: ``"quick"`` or ``"full"``.

    Returns:
        The path of ``moisst_ns/scenarios/bench-<name>.toml``.
    """
    from importlib.resources import files

    return Path(str(files("moisst_ns") / "scenarios" / f"bench-{name}.toml"))


def load_scenarios(path: Path) -> dict:
    """Read and validate a scenario file."""
    path = Path(path)
    if not path.is_file():
        raise BenchError(f"{path}: (file): not found")
    try:
        raw = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as err:
        raise BenchError(f"{path}: (toml): {err}") from None
    for key in ("name", "steps", "rays", "lidar_rays", "last", "rig", "seeds", "case"):
        if key not in raw:
            raise BenchError(f"{path}: {key}: missing")
    for key in ("steps", "rays", "last"):
        if not isinstance(raw[key], int) or raw[key] < 1:
            raise BenchError(f"{path}: {key}: must be a positive integer, got {raw[key]!r}")
    if not raw["seeds"] or any(not (isinstance(s, list) and len(s) == 2 and isinstance(s[0], int) and s[1] in ("street", "plaza")) for s in raw["seeds"]):
        raise BenchError(f"{path}: seeds: must be a non-empty list of [seed, 'street' | 'plaza'] pairs")
    from moisst_ns.datasets.synth import SynthConfig

    settings = set(SynthConfig.__dataclass_fields__) - {"out", "seed", "layout", "perturb"}
    for key in ("width", "height", "frames"):
        if key not in raw["rig"]:
            raise BenchError(f"{path}: rig.{key}: missing")
    unknown = sorted(set(raw["rig"]) - settings)
    if unknown:
        raise BenchError(f"{path}: rig.{unknown[0]}: unknown moisst-synth setting")
    floor = raw.get("floor")
    if floor is not None:
        for key in ("steps", "register_steps", "depth_rays"):
            value = floor.get(key, 1)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise BenchError(f"{path}: floor.{key}: must be a positive integer, got {value!r}")
        if floor.get("seeds", "all") not in ("all", "first"):
            raise BenchError(f"{path}: floor.seeds: must be 'all' or 'first'")
        unknown = sorted(set(floor) - {"steps", "register_steps", "depth_rays", "seeds"})
        if unknown:
            raise BenchError(f"{path}: floor.{unknown[0]}: unknown key")
    ids = set()
    for i, case in enumerate(raw["case"]):
        where = f"case[{i}]"
        if "id" not in case or case["id"] in ids:
            raise BenchError(f"{path}: {where}.id: missing or repeated")
        ids.add(case["id"])
        perturb = case.get("perturb", {})
        for key in ("translation", "rotation", "time"):
            value = perturb.get(key)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or value < 0:
                raise BenchError(f"{path}: {where}.perturb.{key}: must be a number >= 0, got {value!r}")
        if case.get("optimise", "both") not in OPTIMISE:
            raise BenchError(f"{path}: {where}.optimise: must be one of {OPTIMISE}, got {case.get('optimise')!r}")
        for loss in case.get("losses", []):
            if loss not in LOSS_SWITCHES:
                raise BenchError(f"{path}: {where}.losses: unknown {loss!r}; known: {sorted(LOSS_SWITCHES)}")
        patch = case.get("patch_size", None)
        if patch is not None and (isinstance(patch, bool) or not isinstance(patch, int) or patch < 1):
            raise BenchError(f"{path}: {where}.patch_size: must be a positive integer, got {patch!r}")
        if case.get("seeds", "all") not in ("all", "first"):
            raise BenchError(f"{path}: {where}.seeds: must be 'all' or 'first'")
        if not case.get("tables"):
            raise BenchError(f"{path}: {where}.tables: missing (which table cells this case fills)")
    return raw


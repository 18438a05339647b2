"""What every console script shares: turning an error into one line on stderr and exit status 2; the dataset
converters' main."""

from __future__ import annotations

import sys
from typing import Callable, NoReturn


def fail(tool: str, message: object) -> NoReturn:
    """Print ``<tool>: error: <message>`` (one line: line breaks escaped) on stderr and exit with status 2."""
    one_line = str(message).replace("\r", "\\r").replace("\n", "\\n")
    print(f"{tool}: error: {one_line}", file=sys.stderr)
    raise SystemExit(2)


def run_converter(tool: str, config_type: type, convert: Callable, name: str, log: bool = False) -> None:
    """Parse ``config_type`` from the command line, ``convert`` it and print ``<tool>: wrote OUT (NAME, <sensor> <n>
    frames, ..., perturb P) in S s`` (P: ``none`` for a config without ``perturb``); a ``RigFormatError`` ends in ``fail``.

    Args:
        name: the config field naming what was converted (``sequence``, ``drive``).
        log: ``convert`` takes a ``log`` callback: its lines go to stderr as ``<tool>: <line>``.
    """
    import json
    import time

    import tyro

    from moisst_ns.rig.format import RigFormatError

    config = tyro.cli(config_type)
    start = time.perf_counter()
    try:
        out = convert(config, log=lambda line: print(f"{tool}: {line}", file=sys.stderr)) if log else convert(config)
    except RigFormatError as err:
        fail(tool, err)
    counts: dict = {}
    for frame in json.loads((out / "rig.json").read_text())["frames"]:
        counts[frame["sensor"]] = counts.get(frame["sensor"], 0) + 1
    print(f"{tool}: wrote {out} ({getattr(config, name)}, " + ", ".join(f"{n} {c} frames" for n, c in counts.items())
          + f", perturb {getattr(config, 'perturb', 'none')}) in {time.perf_counter() - start:.1f} s")

"""``moisst-synth OUT``: a synthetic rig dataset with exact ground truth (``moisst_ns.datasets.synth``)."""

from __future__ import annotations

import json
import time

import tyro

from moisst_ns.cli.common import fail
from moisst_ns.datasets.synth import REFERENCE, SynthConfig, SynthError, make_rig


def main() -> None:
    """Console script ``moisst-synth``."""
    config = tyro.cli(SynthConfig)
    start = time.perf_counter()
    try:
        out = make_rig(config)
    except SynthError as err:
        fail("moisst-synth", err)
    truth = json.loads((out / "ground_truth.json").read_text())["sensors"]
    offsets = ", ".join(f"{n} {1000 * s['time_offset']:+.1f} ms" for n, s in truth.items() if n != REFERENCE)
    effects = json.loads((out / "rig.json").read_text())["metadata"].get("effects", {})
    effects = f"; effects: {', '.join(f'{k} {v}' for k, v in effects.items())}" if effects else ""
    print(f"moisst-synth: wrote {out} ({config.layout}, seed {config.seed}, {config.frames} frames/sensor, "
          f"perturb {config.perturb}) in {time.perf_counter() - start:.1f} s; true offsets: {offsets}{effects}")


if __name__ == "__main__":
    main()

"""``moisst-bench``: the paper's protocol on synthetic rigs (``moisst_ns.bench``)."""

from __future__ import annotations

import tyro

from moisst_ns.bench import BenchConfig, BenchError, run_bench
from moisst_ns.cli.common import fail
from moisst_ns.quiet import quiet_third_party


def main() -> None:
    """Console script ``moisst-bench``."""
    cfg = tyro.cli(BenchConfig)
    if cfg.quick and cfg.full:
        fail("moisst-bench", "--quick and --full are exclusive")
    if cfg.speed and (cfg.quick or cfg.full or cfg.scenarios is not None):
        fail("moisst-bench", "--speed measures only the speed table: it takes no --quick, --full or --scenarios")
    quiet_third_party()  # known-harmless third-party warnings hidden; PYTHONWARNINGS=default shows everything
    try:
        run_bench(cfg)
    except BenchError as err:
        fail("moisst-bench", err)


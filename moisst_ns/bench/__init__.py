"""``moisst-bench``: the paper's protocol on synthetic rigs (``run``), its scenario files (``scenarios``), its tables
and plots (``tables``) and the nerfacto baseline (``baseline``)."""

from moisst_ns.bench.run import REPO, BenchConfig, make_bench_rig, run_bench
from moisst_ns.bench.scenarios import BenchError, load_scenarios, packaged_scenarios
from moisst_ns.bench.tables import pooled, time_to_target

__all__ = ["REPO", "BenchConfig", "BenchError", "load_scenarios", "make_bench_rig", "packaged_scenarios", "pooled",
           "run_bench", "time_to_target"]

"""`ns-train ARGS` in this process, then one line with torch.cuda.max_memory_allocated / max_memory_reserved.

Used by scripts/device/gpu_measure.sh (no console scripts there: the packages are unpacked, not installed). The line
is also printed when the run is stopped by SIGTERM (`timeout`) or fails.
"""

from __future__ import annotations

import atexit
import signal
import sys
import time

T0 = time.monotonic()


def _report() -> None:
    try:
        import torch

        if torch.cuda.is_available() and torch.cuda.is_initialized():
            mib = 2**20
            print(
                f"[gpu_measure] max_memory_allocated {torch.cuda.max_memory_allocated() / mib:.0f} MiB, "
                f"max_memory_reserved {torch.cuda.max_memory_reserved() / mib:.0f} MiB, "
                f"process wall {time.monotonic() - T0:.1f} s",
                flush=True,
            )
        else:
            print(f"[gpu_measure] CUDA not used in this process; process wall {time.monotonic() - T0:.1f} s", flush=True)
    except Exception as err:  # noqa: BLE001 - a report, never a failure
        print(f"[gpu_measure] no memory figure: {err!r}", flush=True)


def _on_term(signum, frame) -> None:  # noqa: ARG001
    print(f"[gpu_measure] stopped by signal {signum} (timeout)", flush=True)
    sys.exit(124)


atexit.register(_report)
signal.signal(signal.SIGTERM, _on_term)

from nerfstudio.scripts.train import entrypoint  # noqa: E402

sys.argv[0] = "ns-train"
entrypoint()

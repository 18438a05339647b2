"""Compatibility shims for nerfstudio 1.1.5 on current torch (applied when ``moisst_ns`` is imported), and the
LPIPS stand-in that keeps torchmetrics from downloading AlexNet weights at run time.

torch >= 2.6 loads checkpoints with ``weights_only=True``; nerfstudio 1.1.5 checkpoints hold numpy scalars
(e.g. scheduler and optimiser state), which that loader refuses, so ``ns-viewer``, ``ns-export``, ``ns-eval`` and
resuming would fail. We allow-list exactly those numpy types instead of turning the safe loader off.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor, nn


def allow_numpy_in_checkpoints() -> None:
    """Register numpy scalar reconstruction helpers and dtypes as safe globals for ``torch.load``."""
    add = getattr(torch.serialization, "add_safe_globals", None)
    if add is None:  # torch < 2.4: weights_only defaults to False, nothing to do
        return
    safe = [np.core.multiarray.scalar, np.dtype, np.ndarray, np.core.multiarray._reconstruct]
    for name in ("Float64DType", "Float32DType", "Int64DType", "Int32DType", "BoolDType"):
        dtype_cls = getattr(getattr(np, "dtypes", None), name, None)
        if dtype_cls is not None:
            safe.append(dtype_cls)
    add(safe)


class _NoLPIPS(nn.Module):
    """Stands in for torchmetrics' LPIPS, whose AlexNet weights would be downloaded at run time."""

    def __init__(self, **kwargs) -> None:
        super().__init__()

    def forward(self, *args, **kwargs) -> Tensor:
        return torch.tensor(float("nan"))

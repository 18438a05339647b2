"""Compatibility shims for nerfstudio 1.1.5 on current torch (applied when ``moisst_ns`` is imported), and the
LPIPS stand-in that keeps torchmetrics from downloading AlexNet weights at run time.

torch >= 2.6 loads checkpoints with ``weights_only=True``; nerfstudio 1.1.5 checkpoints hold numpy scalars
(e.g. scheduler and optimiser state), which that loader refuses, so ``ns-viewer``, ``ns-export``, ``ns-eval`` and
resuming would fail. We allow-list exactly those numpy types instead of turning the safe loader off.
"""

from __future__ import annotations

from contextlib import contextmanager
from typing import Iterator

import numpy as np
import torch
from torch import Tensor, nn


def allow_numpy_in_checkpoints() -> None:
    """Register numpy scalar reconstruction helpers and dtypes as safe globals for ``torch.load``."""
    safe = [np.core.multiarray.scalar, np.dtype, np.ndarray, np.core.multiarray._reconstruct]
    for name in ("Float64DType", "Float32DType", "Int64DType", "Int32DType", "BoolDType"):
        dtype_cls = getattr(getattr(np, "dtypes", None), name, None)
        if dtype_cls is not None:
            safe.append(dtype_cls)
    torch.serialization.add_safe_globals(safe)


class _NoLPIPS(nn.Module):
    """Stands in for torchmetrics' LPIPS, whose AlexNet weights would be downloaded at run time."""

    def __init__(self, **kwargs) -> None:
        super().__init__()

    def forward(self, *args, **kwargs) -> Tensor:
        return torch.tensor(float("nan"))


@contextmanager
def without_lpips() -> Iterator[None]:
    """Within it, torchmetrics' LPIPS is ``_NoLPIPS`` (for nerfacto's ``populate_modules``, which builds one)."""
    from torchmetrics.image import lpip

    original, lpip.LearnedPerceptualImagePatchSimilarity = lpip.LearnedPerceptualImagePatchSimilarity, _NoLPIPS
    try:
        yield
    finally:
        lpip.LearnedPerceptualImagePatchSimilarity = original

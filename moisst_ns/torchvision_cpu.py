"""Let PyPI's torchvision import beside a CPU-only build of torch.

PyPI's torchvision wheels for Linux x86_64 are CUDA builds: their C extension (``torchvision/_C.so``) links
``libtorch_cuda.so``, which a CPU build of torch does not ship. torchvision then runs without its C operators, as it
is designed to, except that ``torchvision/_meta_registrations.py`` registers fake kernels for ``torchvision::nms``
and ``torchvision::qnms`` unconditionally, and that raises ``operator torchvision::nms does not exist``: the whole
``import torchvision`` fails, and with it nerfstudio (``nerfstudio.pipelines.base_pipeline`` imports
``torchvision.utils``).

``define_missing_ops`` declares the schemas of those two operators (no kernel: calling ``torchvision.ops.nms`` still
raises, and nothing on our paths calls it; ``torchvision.utils`` and ``torchvision.transforms``, which nerfstudio
uses, are plain torch). ``scripts/install.sh`` installs a ``.pth`` line that calls ``install`` at interpreter start,
only when it installed a CPU torch beside a CUDA torchvision; ``install`` only adds an import hook (no torch import
until something imports torchvision), so every process of the venv (our commands, ``ns-train``, pytest) gets it.
"""

from __future__ import annotations

import sys

SCHEMAS = (
    "nms(Tensor dets, Tensor scores, float iou_threshold) -> Tensor",
    "qnms(Tensor dets, Tensor scores, float iou_threshold) -> Tensor",
)
_LIBRARY = []  # keeps the torch.library.Library alive


def needed() -> bool:
    """A CPU build of torch beside a CUDA build of torchvision (from the installed versions, without importing)."""
    from importlib import metadata  # here, not at module level: this module is imported at every interpreter start

    try:
        torch_version, tv_version = metadata.version("torch"), metadata.version("torchvision")
    except metadata.PackageNotFoundError:
        return False
    return "+cpu" in torch_version and "+cpu" not in tv_version


def define_missing_ops() -> bool:
    """Declare ``torchvision::nms`` / ``qnms`` when torchvision's C extension cannot provide them; True if it did."""
    if _LIBRARY or not needed():
        return False
    import torch

    lib = torch.library.Library("torchvision", "FRAGMENT")
    for schema in SCHEMAS:
        name = schema.split("(", 1)[0]
        if not _has_schema(name):
            lib.define(schema)
    _LIBRARY.append(lib)
    return True


def _has_schema(name: str) -> bool:
    import torch

    try:
        getattr(torch.ops.torchvision, name).default
        return True
    except (AttributeError, RuntimeError):
        return False


class _BeforeTorchvision:
    """Meta-path hook: runs ``define_missing_ops`` once, just before torchvision is first imported."""

    def find_spec(self, name, path=None, target=None):
        if name == "torchvision":
            sys.meta_path.remove(self)
            define_missing_ops()
        return None  # the normal finders import it


def install() -> None:
    """Called from the venv's ``moisst_torchvision_cpu.pth``; cheap (no torch import)."""
    if "torchvision" in sys.modules:
        define_missing_ops()
    elif not any(isinstance(f, _BeforeTorchvision) for f in sys.meta_path):
        sys.meta_path.insert(0, _BeforeTorchvision())

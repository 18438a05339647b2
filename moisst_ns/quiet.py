"""Quiet by default: hide the third-party warnings we know to be harmless, and nothing else.

Each entry of ``KNOWN_HARMLESS`` names the warning's category, the module it is attributed to and the start of its
message, and says why it is harmless here. Anything not listed still shows (a new warning after an upgrade is
news). ``--verbose`` on a ``moisst-*`` command skips all of this, as does a ``-W`` option or ``PYTHONWARNINGS``
(the user's own filters win). No torch or nerfstudio import here: the filters must be in place before they are
imported, since several of these warnings fire at import time.
"""

from __future__ import annotations

import sys
import warnings
from typing import List, Tuple

KNOWN_HARMLESS: List[Tuple[type, str, str, str]] = [
    # (category, module regex, message regex, why it is harmless)
    (FutureWarning, r"torch\.jit\._script", r"`torch\.jit\.script` is deprecated",
     "nerfstudio 1.1.5 scripts small helpers with torch.jit.script; deprecated, still works"),
    (FutureWarning, r"nerfstudio\.", r"`torch\.cuda\.amp\.(custom_fwd|custom_bwd|GradScaler)\(args\.\.\.\)` is deprecated",
     "nerfstudio 1.1.5 uses the torch.cuda.amp spellings; same behaviour, and mixed precision is off on the CPU"),
    (UserWarning, r"nerfstudio\.cameras\.cameras", r"Using a non-tuple sequence for multidimensional indexing is deprecated",
     "nerfstudio 1.1.5's ray generation; the rays are checked exact against the synthetic truth by the tests"),
    (UserWarning, r"nerfstudio\.engine\.optimizers", r"Detected call of `lr_scheduler\.step\(\)` before `optimizer\.step\(\)`",
     "a parameter group that did not step yet (e.g. the calibration held during the warm-up): its schedule "
     "starts one step later"),
    (UserWarning, r"nerfstudio\.utils\.writer", r"Converting a tensor with requires_grad=True to a scalar",
     "nerfstudio's logger reads loss values as floats"),
]
"""The third-party warnings hidden by default (measured on a ``moisst-calibrate --max-num-iterations 5`` run)."""


def _no_tcnn_banner(module_name: str) -> None:
    """Stands in for nerfstudio's 'Install tcnn for speedups' banner: on the CPU there is no tcnn to install."""


def quiet_third_party(verbose: bool = False) -> bool:
    """Install the filters of ``KNOWN_HARMLESS`` and silence nerfstudio's tcnn banner.

    Args:
        verbose: show everything (do nothing).

    Returns:
        Whether anything was hidden (False with ``verbose`` or with the user's own ``-W`` / ``PYTHONWARNINGS``).
    """
    if verbose or sys.warnoptions:
        return False
    for category, module, message, _why in KNOWN_HARMLESS:
        warnings.filterwarnings("ignore", message=message, category=category, module=module)
    try:
        import nerfstudio.utils.printing as printing  # rich only; light
    except ImportError:
        return True
    printing.print_tcnn_speed_warning = _no_tcnn_banner
    for name in ("nerfstudio.field_components.encodings", "nerfstudio.field_components.mlp"):
        module = sys.modules.get(name)  # already imported (e.g. under ns-train): patch its own reference too
        if module is not None and hasattr(module, "print_tcnn_speed_warning"):
            module.print_tcnn_speed_warning = _no_tcnn_banner
    return True

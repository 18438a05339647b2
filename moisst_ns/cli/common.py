"""What every console script shares: turning an error into one line on stderr and exit status 2."""

from __future__ import annotations

import sys
from typing import NoReturn


def fail(tool: str, message: object) -> NoReturn:
    """Print ``<tool>: error: <message>`` (one line: line breaks escaped) on stderr and exit with status 2."""
    one_line = str(message).replace("\r", "\\r").replace("\n", "\\n")
    print(f"{tool}: error: {one_line}", file=sys.stderr)
    raise SystemExit(2)

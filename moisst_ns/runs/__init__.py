"""Everything about a run folder: the history CSV (one schema, one writer, one reader), opening a run, the output
folder check, error tables and summaries. Used by ``cli/*``, the report and the benchmark; nothing here imports
``moisst_ns.cli``. Errors are ``RunError`` with a one-line message; only ``cli/`` turns them into exit codes."""


ERROR_KEYS = ("translation_cm", "rotation_deg", "time_ms")
"""The error of a sensor's calibration against the ground truth: translation (cm), rotation (deg), time (ms)."""


class RunError(ValueError):
    """A run folder, config.yml, history or output folder that cannot be used; the message is one line."""

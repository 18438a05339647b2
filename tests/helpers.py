"""Shared test helpers."""

import hashlib
from pathlib import Path


def tree_hash(folder: Path) -> str:
    """One digest of every file's relative path and bytes under ``folder`` (to prove a dataset was not written)."""
    digest = hashlib.sha256()
    for path in sorted(folder.rglob("*")):
        if path.is_file():
            digest.update(str(path.relative_to(folder)).encode())
            digest.update(path.read_bytes())
    return digest.hexdigest()

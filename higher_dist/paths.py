"""Folders a command writes into: made on demand, or refused in one line that names the flag."""
from __future__ import annotations

from pathlib import Path


def ensure_folder(path: Path, flag: str) -> None:
    """Make `path` a folder (parents too), or refuse by name with a one-line ValueError: a file in the way,
    or a folder that cannot be made."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise ValueError(f"{flag} {path}: is a file, not a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ValueError(f"{flag} {path}: cannot make this folder ({e.strerror})") from None

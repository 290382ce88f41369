"""A run directory: config.json, metrics.jsonl and atomic checkpoints.

Checkpoints are written to a temporary file and renamed over the old one, so a crash mid-write leaves
the previous checkpoint intact. They are loaded with `torch.load(weights_only=True)`: numpy arrays are
stored as tagged tensors, so no pickle of arbitrary objects is involved.
"""
from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from higher_dist import metrics as m
from higher_dist.config import Config
from higher_dist.paths import ensure_folder

_ND = "__ndarray__"


class RunDir:
    def __init__(self, path: str | os.PathLike, tensorboard: bool = False):
        self.path = Path(path)
        ensure_folder(self.path, "--run-dir")
        self._tb = None
        if tensorboard:
            try:
                from torch.utils.tensorboard import SummaryWriter
            except ImportError as e:
                raise ValueError("tensorboard: the tensorboard package is not installed "
                                 "(pip install 'higher-dist[tensorboard]')") from e
            self._tb = SummaryWriter(str(self.path / "tensorboard"))

    @property
    def metrics_path(self) -> Path:
        return self.path / "metrics.jsonl"

    def write_config(self, cfg: Config) -> None:
        atomic_write_bytes(self.path / "config.json", cfg.to_json().encode())

    def append_metrics(self, record: dict[str, Any]) -> None:
        record = {m.TIME: round(time.time(), 3), **record}
        with open(self.metrics_path, "a") as f:
            f.write(json.dumps(plain_record(record)) + "\n")
        if self._tb is not None:
            # Every number of the record, against env frames, as TensorBoard scalars.
            step = int(record.get(m.FRAMES) or 0)
            for key, value in record.items():
                if isinstance(value, (int, float)) and not isinstance(value, bool) and key != m.TIME:
                    self._tb.add_scalar(key, value, step)
            self._tb.flush()

    def read_metrics(self) -> list[dict[str, Any]]:
        return read_metrics(self.metrics_path)

    def checkpoint_path(self, role: str) -> Path:
        return self.path / f"{role}.ckpt"

    def save_checkpoint(self, role: str, state: dict[str, Any]) -> Path:
        path = self.checkpoint_path(role)
        atomic_write(path, lambda tmp: torch.save(_to_tensors(state), tmp), fsync=True)
        return path

    def load_checkpoint(self, role: str) -> dict[str, Any] | None:
        path = self.checkpoint_path(role)
        if not path.exists():
            return None
        return _from_tensors(torch.load(path, map_location="cpu", weights_only=True))


def load_or_refuse(path: Path, what: str, load: Callable[[], None]) -> None:
    """Run `load` (a load_state_dict of a checkpoint read from `path`); torch's refusal of other shapes or
    names (a checkpoint of another version's `what`) becomes a ValueError that names the file."""
    try:
        load()
    except RuntimeError as e:
        raise ValueError(f"--resume: {path} does not fit this version's {what}, start a new run "
                         f"({str(e).splitlines()[-1].strip()})") from None


def read_metrics(path: str | os.PathLike) -> list[dict[str, Any]]:
    """Every complete JSON line of a metrics file (a torn last line from a crash is skipped)."""
    out = []
    try:
        with open(path) as f:
            for line in f:
                try:
                    out.append(json.loads(line))
                except json.JSONDecodeError:
                    continue
    except FileNotFoundError:
        pass
    return out


def last_record(path: str | os.PathLike, max_bytes: int = 1 << 18) -> dict[str, Any] | None:
    """The newest complete JSON line of a metrics file, reading only its end: a supervisor polling a run for
    days must not parse (and hold) the whole, ever-growing file each time."""
    try:
        with open(path, "rb") as f:
            f.seek(0, os.SEEK_END)
            size = f.tell()
            f.seek(max(0, size - max_bytes))
            tail = f.read()
    except FileNotFoundError:
        return None
    for line in reversed(tail.splitlines()):
        try:
            record = json.loads(line)
        except (json.JSONDecodeError, UnicodeDecodeError):
            continue  # a torn last line, or the first, cut line of the window
        if isinstance(record, dict):
            return record
    return None


def atomic_write(path: Path, write: Callable[[Path], None], fsync: bool = False) -> None:
    """`write` fills a temporary file beside `path`, which is then renamed over it: a reader (or a crash)
    sees the old file or the new one, never half of one."""
    tmp = path.with_suffix(path.suffix + f".tmp{os.getpid()}")
    write(tmp)
    if fsync:
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())
    os.replace(tmp, path)


def atomic_write_bytes(path: Path, data: bytes) -> None:
    atomic_write(path, lambda tmp: tmp.write_bytes(data))


def plain_record(obj: Any) -> Any:
    """A copy of a metrics record in plain Python values: numpy scalars as numbers, tuples as lists, and
    NaN or infinity as None (the wire refuses non-finite numbers; a metric that has none is "no data")."""
    if isinstance(obj, dict):
        return {str(k): plain_record(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [plain_record(v) for v in obj]
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


def _to_tensors(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return {_ND: torch.from_numpy(np.ascontiguousarray(obj))}
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, dict):
        return {k: _to_tensors(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(_to_tensors(v) for v in obj)
    return obj


def _from_tensors(obj: Any) -> Any:
    if isinstance(obj, dict):
        if set(obj) == {_ND}:
            return obj[_ND].numpy()
        return {k: _from_tensors(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(_from_tensors(v) for v in obj)
    return obj

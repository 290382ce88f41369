"""Which torch device a part of the run uses: the one place that reads `auto`."""
from __future__ import annotations

import torch


def resolve_device(name: str) -> torch.device:
    """`auto`: the first CUDA device when torch sees one, else the CPU; `cpu`; `cuda` or `cuda:N`. A CUDA
    device on a machine without one is refused by name rather than failing at the first tensor."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(name)
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(f"device: {name!r} asked for, but torch sees no CUDA device here "
                             "(use --device cpu, or auto to take a GPU only where there is one)")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise ValueError(f"device: {name!r} asked for, but torch sees {torch.cuda.device_count()} CUDA device(s)")
    return device

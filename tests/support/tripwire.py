"""Stand-ins for ground truth in tests that prove a learned relabeller never reads it."""
from __future__ import annotations


class Tripwire:
    """Any use of it (other than passing it along) raises."""

    def __getattr__(self, name):
        raise RuntimeError(f"ground truth read: .{name}")

    def __array__(self, *args, **kwargs):
        raise RuntimeError("ground truth read: __array__")

    def __getitem__(self, key):
        raise RuntimeError("ground truth read: []")

    def __iter__(self):
        raise RuntimeError("ground truth read: iter")

    def __len__(self):
        raise RuntimeError("ground truth read: len")

    def __eq__(self, other):
        raise RuntimeError("ground truth read: ==")

    __hash__ = object.__hash__


class PassedAlong(Tripwire):
    """Ground truth that may be handed on (indexed, copied into a relabelled copy) but never looked at:
    comparing it, turning it into an array or iterating it raises."""

    def __getitem__(self, key):
        return PassedAlong()

    def copy(self):
        return PassedAlong()

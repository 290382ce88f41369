"""The learner's compute bound on this core: FLOPs per sample of one update, and the rate one torch thread
runs those very operations at.

- FLOPs are counted on the real thing: `dqn_terms` (online forward on s, online forward on s' for the
  double-DQN argmax, target forward on s') and the backward of its loss, at the bench's batch, under a
  dispatch mode that applies torch.utils.flop_counter's formulas (2 FLOPs per multiply-add of matrix
  products and convolutions, the GRU's included: on the CPU it runs as matrix products). Embedding
  gathers, elementwise ops, clipping and Adam carry no counted FLOPs. `analytic_flops` counts the same
  forwards from the layer shapes alone, as a cross-check.
- The rate: every counted call (op, shapes, strides, arguments) is replayed alone on fresh tensors and
  timed best-of-N on one thread, so the bound is what these kernels reach on these shapes with no
  Python, sampling, small-op or optimizer time between them. bound samples/s = GFLOP/s / FLOPs per sample.
"""
from __future__ import annotations

import time
from collections import Counter

import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_map
from torch.utils.flop_counter import flop_registry

from higher_dist.launch.layout import machine
from higher_dist.learning.networks import InstructionEncoder, QNetwork
from higher_dist.world.language import PAD


class _Recorder(TorchDispatchMode):
    """Records each FLOP-carrying call once per distinct (op, arguments' shapes and strides)."""

    def __init__(self):
        super().__init__()
        self.calls: Counter = Counter()
        self.flops: dict = {}
        self.replay: dict = {}

    @property
    def total(self) -> int:
        return sum(self.flops[key] * n for key, n in self.calls.items())

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        out = func(*args, **kwargs)
        formula = flop_registry.get(func.overloadpacket)
        if formula is not None:
            key = (func, tree_map(_meta, (args, kwargs)).__repr__())
            self.calls[key] += 1
            if key not in self.flops:
                self.flops[key] = int(formula(*args, **kwargs, out_val=out))
                self.replay[key] = (func, tree_map(_meta, args), tree_map(_meta, kwargs))
        return out


class _TensorMeta:
    """A tensor's shape, strides and dtype (a leaf to pytree, unlike a tuple)."""

    def __init__(self, t: torch.Tensor):
        self.shape, self.stride, self.dtype = tuple(t.shape), tuple(t.stride()), t.dtype

    def __repr__(self) -> str:
        return f"T{self.shape}{self.stride}{self.dtype}"

    def fresh(self) -> torch.Tensor:
        # Through a flat storage: broadcast (stride-0) arguments cannot be written in place.
        size = 1 + sum((n - 1) * st for n, st in zip(self.shape, self.stride)) if all(self.shape) else 0
        flat = torch.zeros(size, dtype=self.dtype)
        if flat.is_floating_point():
            flat.normal_()
        return flat.as_strided(self.shape, self.stride)


def _meta(x):
    return _TensorMeta(x) if isinstance(x, torch.Tensor) else x


def _fresh(x):
    return x.fresh() if isinstance(x, _TensorMeta) else x


def record(fn) -> _Recorder:
    """Run `fn()` under the recorder: `.total` is its counted FLOPs."""
    with _Recorder() as rec:
        fn()
    return rec


def count_update(learner, tensors: dict[str, torch.Tensor]) -> _Recorder:
    """The learner's loss forward and backward once on `tensors`, eager, under the recorder; no step."""
    from higher_dist.learning.dqn import dqn_terms

    def update():
        loss = dqn_terms(learner.online, learner.target, huber_delta=learner.cfg.huber_delta,
                         double=learner.cfg.double, joint_online=learner.cfg.joint_online, **tensors)[0]
        loss.backward()

    learner.online.zero_grad(set_to_none=True)
    rec = record(update)
    learner.online.zero_grad(set_to_none=True)
    return rec


def time_calls(rec: _Recorder, repeats: int = 15) -> float:
    """Seconds per update of the recorded calls replayed alone: each distinct call's best of `repeats`
    times its count. Runs on the caller's torch threads (the bench sets one)."""
    total = 0.0
    with torch.no_grad():
        for key, (func, args, kwargs) in rec.replay.items():
            args, kwargs = tree_map(_fresh, args), tree_map(_fresh, kwargs)
            func(*args, **kwargs)  # first call: oneDNN picks and caches its kernel
            best = float("inf")
            for _ in range(repeats):
                t0 = time.perf_counter()
                func(*args, **kwargs)
                best = min(best, time.perf_counter() - t0)
            total += best * rec.calls[key]
    return total


def peak_gflops(n: int = 1024, repeats: int = 5) -> float:
    """GFLOP/s of one large float32 matrix product (n x n x n): the core's peak for reference."""
    a, b = torch.randn(n, n), torch.randn(n, n)
    a @ b
    best = min(_timed(lambda: a @ b) for _ in range(repeats))
    return 2 * n ** 3 / best / 1e9


def _timed(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def analytic_forward_flops(net: QNetwork, mission_steps: int) -> dict[str, int]:
    """Per-sample FLOPs (2 per multiply-add, biases not counted) of `net`'s parts from its layer shapes:
    'text' (word embedding and GRU over `mission_steps` words) and 'q' (convolutions, FiLM, head)."""
    view = net.view
    q, size = 0, view.view_size
    for conv in view.convs:
        size = size - conv.kernel_size[0] + 1 + 2 * conv.padding[0]
        q += 2 * conv.in_channels * conv.out_channels * conv.kernel_size[0] * conv.kernel_size[1] * size * size
    for conv in view.film_blocks:  # padded: the map keeps its size
        q += 2 * conv.in_channels * conv.out_channels * conv.kernel_size[0] * conv.kernel_size[1] * size * size
    linears = [net.trunk] + ([net.film] if net.fusion == "film" else [])
    linears += [net.value, net.advantage] if net.dueling else [net.q]
    q += sum(2 * m.in_features * m.out_features for m in linears)
    if isinstance(net.text, InstructionEncoder):
        gru = net.text.gru
        # Torch's CPU GRU runs the hidden product at every step, the first (h0 = 0) included.
        text = mission_steps * 2 * 3 * gru.hidden_size * (gru.input_size + gru.hidden_size)
    else:  # bag of words: the sum is additions only, then one linear layer
        text = 2 * net.text.out.in_features * net.text.out.out_features
    return {"text": text, "q": q}


def analytic_update_flops(net: QNetwork, mission_steps: int, double: bool = True) -> int:
    """Per-sample FLOPs of an update from layer shapes: online text + q(s) with grad, backward 2x that,
    online q(s') for the double-DQN argmax, target text + q(s'). The backward's exact count skips a few
    products (no gradient for the GRU's zero initial state), so the counted figure sits slightly under."""
    f = analytic_forward_flops(net, mission_steps)
    online = f["text"] + f["q"]
    return 3 * online + (f["q"] if double else 0) + online


def bound(learner, tensors: dict[str, torch.Tensor]) -> dict[str, float]:
    """The compute bound of `learner`'s update on this batch: FLOPs per sample (counted, and from layer
    shapes when the online forwards are separate), GFLOP/s of its ops alone, bound samples/s."""
    b = int(tensors["action"].shape[0])
    rec = count_update(learner, tensors)
    seconds = time_calls(rec)
    steps = int((tensors["mission"] != PAD).sum(dim=1).max())
    out = {"flops_per_sample": rec.total / b, "gflops": rec.total / seconds / 1e9, "bound_samples_per_s": b / seconds,
           "peak_gflops": peak_gflops()}
    if not learner.cfg.joint_online:
        out["analytic_flops_per_sample"] = analytic_update_flops(learner.online, steps, learner.cfg.double)
    return out


def bound_lines(figures: dict[str, float], batch_size: int, measured: dict[str, float]) -> list[str]:
    """The printed lines: the bound, each measured row's CPU samples/s against it, the machine."""
    f = figures
    analytic = f.get("analytic_flops_per_sample")
    shapes = f" ({analytic / 1e6:.3f} from layer shapes)" if analytic else ""
    lines = [f"compute bound at B={batch_size}, one thread: {f['flops_per_sample'] / 1e6:.3f} MFLOP/sample counted"
             f"{shapes}; these ops alone run at {f['gflops']:.1f} GFLOP/s (one 1024^3 matmul: "
             f"{f['peak_gflops']:.1f}) -> bound {f['bound_samples_per_s']:,.0f} samples/s"]
    for name, cpu_samples in measured.items():
        lines.append(f"  {name}: {cpu_samples:,.0f} samples per CPU-second = "
                     f"{cpu_samples / f['bound_samples_per_s']:.0%} of the bound")
    lines.append(f"machine: {machine()}")
    return lines

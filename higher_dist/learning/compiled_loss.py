"""The DQN loss compiled with torch.compile (inductor, C++ kernels for the CPU), built off the hot path.

Compiling costs 10-100 s on a loaded 2-core machine the first time (the FX graph cache under
/tmp/torchinductor_$USER makes later starts cheaper), while the compiled step measured ~1.4x the eager
samples per CPU-second at batch 64-256 (docs/benchmarks.md). So the learner never waits for it:
`start` traces and compiles on a background thread, on clones of the parameters and an example batch,
and the learner keeps stepping eagerly until `ready`. Any failure (no C++ compiler, an unsupported
op) leaves `failed` set with the reason, and the learner stays eager for good.

Tracing is not thread-safe in one way that matters here: while AOTAutograd traces (make_fx, an FX
tracer), `torch.nn.Module.__call__` is patched for the whole process, so a module called from another
thread at that moment is routed into the trace (it raises, or worse, lands in the graph). `TRACING_GATE`
keeps them apart: the build holds it exclusively, and every other user of modules in the process (the
learner's updates, the evaluator thread) enters it shared. Updates skip while a build runs rather than
wait (the learner keeps receiving), so a cold compile costs its own length of learning, once.

The compiled function takes the parameters as inputs (torch.func.functional_call over a module that
holds both networks), so the graph compiled on the clones runs on the live parameters without a
recompile, and autograd reaches the live `.grad`s.
"""
from __future__ import annotations

import contextlib
import logging
import threading
from typing import Callable

import torch
from torch import nn

from higher_dist.learning.networks import traced_path

log = logging.getLogger("higher.compile")


class TracingGate:
    """Many module users at once, or one compile build alone; a waiting build goes first (new users are
    refused or wait), so back-to-back updates cannot starve it."""

    def __init__(self):
        self._cond = threading.Condition()
        self._users = 0
        self._building = False
        self._build_waiting = 0

    def try_enter(self) -> bool:
        """Enter as a module user unless a build runs or waits; the caller must `leave` after."""
        with self._cond:
            if self._building or self._build_waiting:
                return False
            self._users += 1
            return True

    @contextlib.contextmanager
    def using(self):
        """Use modules, waiting for a running or waiting build first (off the learner's hot path)."""
        with self._cond:
            self._cond.wait_for(lambda: not (self._building or self._build_waiting))
            self._users += 1
        try:
            yield
        finally:
            self.leave()

    def leave(self) -> None:
        with self._cond:
            self._users -= 1
            self._cond.notify_all()

    @contextlib.contextmanager
    def building(self):
        with self._cond:
            self._build_waiting += 1
            self._cond.wait_for(lambda: self._users == 0 and not self._building)
            self._build_waiting -= 1
            self._building = True
        try:
            yield
        finally:
            with self._cond:
                self._building = False
                self._cond.notify_all()


TRACING_GATE = TracingGate()  # one per process: the patch it guards against is process-wide


class _Loss(nn.Module):
    """Both networks as submodules, so one parameter dict names all of them."""

    def __init__(self, terms: Callable, online: nn.Module, target: nn.Module, options: dict):
        super().__init__()
        self.terms, self.online, self.target, self.options = terms, online, target, options

    def forward(self, obs, mission, action, reward, discount, next_obs, weights):
        return self.terms(self.online, self.target, obs, mission, action, reward, discount, next_obs, weights,
                          **self.options)


class CompiledLoss:
    """`terms(online, target, **batch, **options)` (dqn.dqn_terms) over the live networks, compiled;
    call only once `ready`."""

    def __init__(self, terms: Callable, online: nn.Module, target: nn.Module, **options):
        self._module = _Loss(terms, online, target, options)
        # Parameters only: buffers (constants of the encoding) stay the modules' own, and passing them
        # too would alias them, which Dynamo guards against (a blocking recompile on the first call).
        self._live = dict(self._module.named_parameters())
        self._fn: Callable | None = None
        self._thread: threading.Thread | None = None
        self.failed: str | None = None
        self._shapes: dict[str, tuple] = {}

    @property
    def ready(self) -> bool:
        return self._fn is not None

    @property
    def started(self) -> bool:
        return self._thread is not None or self.ready or self.failed is not None

    def start(self, example: dict[str, torch.Tensor], background: bool = True) -> None:
        """Compile for batches shaped like `example` (a dict of the loss's tensors); on a daemon thread
        unless `background` is False (benchmarks and tests, which want the compiled path at once)."""
        if self.started:
            return
        # Parameters like the live ones: Dynamo guards on the type, and a plain tensor here would
        # recompile, blocking, on the first real call.
        clones = {name: nn.Parameter(t.detach().clone(), requires_grad=t.requires_grad)
                  for name, t in self._live.items()}
        example = {name: t.clone() for name, t in example.items()}
        self._shapes = {name: (t.shape, t.dtype) for name, t in example.items()}
        if not background:  # benchmarks and tests: one thread, which may be inside the gate already
            self._build_alone(clones, example)
            return
        self._thread = threading.Thread(target=self._build, args=(clones, example), name="compile-loss",
                                        daemon=True)
        self._thread.start()

    def accepts(self, batch: dict[str, torch.Tensor]) -> bool:
        """Ready and compiled for this batch's shapes and dtypes. Any other batch goes eager: a
        recompile would block the caller for as long as the first compile took."""
        return self.ready and all((t.shape, t.dtype) == self._shapes.get(name) for name, t in batch.items())

    def wait(self, timeout: float | None = None) -> bool:
        """Block until the background compile ends; True when the compiled path is ready."""
        if self._thread is not None:
            self._thread.join(timeout)
        return self.ready

    def _build(self, params: dict[str, torch.Tensor], example: dict[str, torch.Tensor]) -> None:
        with TRACING_GATE.building():
            self._build_alone(params, example)

    def _build_alone(self, params: dict[str, torch.Tensor], example: dict[str, torch.Tensor]) -> None:
        try:
            import torch._dynamo

            # The instruction encoder holds an nn.GRU (its weights; the compiled path unrolls the
            # recurrence): without this Dynamo refuses to look at the module at all.
            torch._dynamo.config.allow_rnn = True
            # Every CompiledLoss compiles the same Python function, so Dynamo counts each one (another
            # batch size, another learner in the same process: benchmarks, tests) as a recompile of it;
            # past the limit (8) it would silently run eager.
            torch._dynamo.config.recompile_limit = max(torch._dynamo.config.recompile_limit, 64)
            module = self._module

            def functional(state: dict[str, torch.Tensor], batch: dict[str, torch.Tensor]):
                return torch.func.functional_call(module, state, (), batch)

            fn = torch.compile(functional, dynamic=False)
            # One forward and backward on the clones compiles both graphs; the clones' grads are
            # thrown away with them.
            with traced_path():
                loss = fn(params, example)[0]
            loss.backward()
            self._fn = fn
            log.info("compiled DQN loss ready")
        except Exception as exc:  # noqa: BLE001 - any failure means: stay eager, and say why
            self.failed = f"{type(exc).__name__}: {exc}"[:500]
            log.warning("torch.compile of the DQN loss failed, staying eager: %s", self.failed)

    def __call__(self, batch: dict[str, torch.Tensor]):
        if self._fn is None:
            raise RuntimeError("CompiledLoss called before it is ready")
        with traced_path():  # a recompile (new guards) traces the same graph-friendly forms
            return self._fn(self._live, batch)

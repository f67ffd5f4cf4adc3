"""Replay a sampler's velocity function from a CUDA graph (issue 28: generation is launch-bound).

One network call of the paper preset over a 10 s clip is ~3,000 small kernels; launched one by
one from Python, an Euler step costs tens of milliseconds whatever the GPU, while the kernels
themselves run in a few. A CUDA graph records the call's kernels once and replays them with
one launch. ``GraphedVelocity(velocity)`` wraps any ``velocity(x, t) -> v`` whose work is pure
device work (``dualflow.flow.guided_velocity``: the network, guidance; the reactive actor
stream is computed in the warm-up calls and read from the same tensors at every replay):

* the first call, with x (B, T, D) and t (B,) on a CUDA device, runs ``warmup`` eager calls
  on a side stream (allocator and library handles settle, cached tensors are made), then
  captures one call into a graph whose inputs are static copies of x and t;
* every call copies x and t into those inputs, replays the graph and returns a copy of the
  output (so a caller may keep it across calls: Heun's two velocities);
* a call with another shape, dtype or device is an error: one graph serves one sampling run.

Results equal the eager calls' up to float rounding (the same kernels). Off the GPU, or when
the capture fails (an operation that cannot be captured), the wrapper calls ``velocity``
eagerly and says so once (``GraphedVelocity.eager_reason``).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable

import torch

from dualflow.errors import DualFlowError

VelocityFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


class GraphedVelocity:
    """``velocity(x, t)`` replayed from a CUDA graph captured at the first call (module docstring)."""

    def __init__(self, velocity: VelocityFn, warmup: int = 2):
        self.velocity = velocity
        self.warmup = int(warmup)
        self.graph: torch.cuda.CUDAGraph | None = None
        self.eager_reason: str | None = None
        self._x = self._t = self._out = None

    def __call__(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        if self.eager_reason is not None:
            return self.velocity(x, t)
        if self.graph is None:
            if not x.is_cuda:
                self.eager_reason = f"inputs on {x.device}, not a CUDA device"
                return self.velocity(x, t)
            self._capture(x, t)
            if self.graph is None:
                return self.velocity(x, t)
        for name, given, static in (("x", x, self._x), ("t", t, self._t)):
            if given.shape != static.shape or given.dtype != static.dtype or given.device != static.device:
                raise DualFlowError(
                    f"GraphedVelocity: {name} {tuple(given.shape)} {given.dtype} on {given.device} differs from the "
                    f"captured {tuple(static.shape)} {static.dtype} on {static.device}; make a new one per sampling run"
                )
        self._x.copy_(x)
        self._t.copy_(t)
        self.graph.replay()
        return self._out.clone()

    def _capture(self, x: torch.Tensor, t: torch.Tensor) -> None:
        self._x, self._t = x.detach().clone(), t.detach().clone()
        side = torch.cuda.Stream(device=x.device)
        side.wait_stream(torch.cuda.current_stream(x.device))
        with torch.cuda.stream(side):
            for _ in range(self.warmup):
                self.velocity(self._x, self._t)
        torch.cuda.current_stream(x.device).wait_stream(side)
        graph = torch.cuda.CUDAGraph()
        try:
            with torch.cuda.graph(graph):
                self._out = self.velocity(self._x, self._t)
        except RuntimeError as exc:  # something in the call cannot be captured: run eagerly
            self.eager_reason = f"CUDA graph capture failed ({str(exc).splitlines()[0]})"
            warnings.warn(f"dualflow: {self.eager_reason}; sampling runs eagerly", RuntimeWarning, stacklevel=3)
            return
        self.graph = graph

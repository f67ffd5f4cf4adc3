"""Replay a sampler's work from a CUDA graph (issue 28: sampling is launch-bound on a GPU).

One network call of the paper preset over a 10 s clip is ~1,500 small kernels; launched one
by one from Python, an Euler step costs tens of milliseconds whatever the GPU, while the
kernels themselves run in a few. A CUDA graph records the kernels of a call once and replays
them with one launch. ``GraphedCall(fn)`` wraps any ``fn(*tensors) -> tensor | tuple of
tensors`` whose work is pure device work:

* the first call, with every input on a CUDA device, runs ``warmup`` eager calls on a side
  stream (allocator and library handles settle, caches the call keeps are made), then
  captures one call into a graph whose inputs are static copies of the given ones;
* every call copies its inputs into those, replays the graph and returns copies of the
  outputs (so a caller may keep them across calls: Heun's two velocities);
* a call with another shape, dtype or device is an error: one graph serves one shape.

Uses: ``GraphedVelocity`` (``dualflow.flow.generate``: ``velocity(x, t)``, the reactive actor
stream computed in the warm-up calls and read from the same tensors at every replay) and a
streamed window's whole generation (``dualflow.streaming``, ``StreamConfig.cuda_graph``).

Results equal the eager calls' up to float rounding (the same kernels). Off the GPU, or when
the capture fails (an operation that cannot be captured), the wrapper calls ``fn`` eagerly
and says so once (``eager_reason``).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable

import torch

from dualflow.errors import DualFlowError

VelocityFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


class GraphedCall:
    """``fn(*inputs)`` replayed from a CUDA graph captured at the first call (module docstring).
    ``names``: the inputs' names for error messages."""

    def __init__(self, fn: Callable, warmup: int = 2, names: tuple[str, ...] | None = None):
        self.fn = fn
        self.warmup = int(warmup)
        self.names = names
        self.graph: torch.cuda.CUDAGraph | None = None
        self.eager_reason: str | None = None
        self._inputs: tuple[torch.Tensor, ...] = ()
        self._out = None

    def __call__(self, *inputs: torch.Tensor):
        if self.eager_reason is not None:
            return self.fn(*inputs)
        if self.graph is None:
            off = next((x.device for x in inputs if not x.is_cuda), None)
            if off is not None:
                self.eager_reason = f"inputs on {off}, not a CUDA device"
                return self.fn(*inputs)
            self._capture(inputs)
            if self.graph is None:
                return self.fn(*inputs)
        if len(inputs) != len(self._inputs):
            raise DualFlowError(f"{type(self).__name__}: {len(inputs)} inputs, captured with {len(self._inputs)}")
        for i, (given, static) in enumerate(zip(inputs, self._inputs)):
            if given.shape != static.shape or given.dtype != static.dtype or given.device != static.device:
                name = self.names[i] if self.names else f"input {i}"
                raise DualFlowError(
                    f"{type(self).__name__}: {name} {tuple(given.shape)} {given.dtype} on {given.device} differs from "
                    f"the captured {tuple(static.shape)} {static.dtype} on {static.device}; one graph serves one shape"
                )
        for given, static in zip(inputs, self._inputs):
            static.copy_(given)
        self.graph.replay()
        if isinstance(self._out, tuple):
            return tuple(o.clone() for o in self._out)
        return self._out.clone()

    def _capture(self, inputs: tuple[torch.Tensor, ...]) -> None:
        device = inputs[0].device
        with torch.inference_mode(False):  # copied into at every call, in inference mode or not
            self._inputs = tuple(x.detach().clone() for x in inputs)
        side = torch.cuda.Stream(device=device)
        side.wait_stream(torch.cuda.current_stream(device))
        with torch.cuda.stream(side):
            for _ in range(self.warmup):
                self.fn(*self._inputs)
        torch.cuda.current_stream(device).wait_stream(side)
        graph = torch.cuda.CUDAGraph()
        try:
            with torch.cuda.graph(graph):
                self._out = self.fn(*self._inputs)
        except RuntimeError as exc:  # something in the call cannot be captured: run eagerly
            self.eager_reason = f"CUDA graph capture failed ({str(exc).splitlines()[0]})"
            warnings.warn(f"dualflow: {self.eager_reason}; running eagerly", RuntimeWarning, stacklevel=3)
            return
        self.graph = graph


class GraphedVelocity(GraphedCall):
    """``velocity(x, t)`` replayed from a CUDA graph captured at the first call; x (B, T, D),
    t (B,). Make a new one per sampling run."""

    def __init__(self, velocity: VelocityFn, warmup: int = 2):
        super().__init__(velocity, warmup, names=("x", "t"))

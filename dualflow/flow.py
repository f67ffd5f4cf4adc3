"""Rectified flow for DualFlow (paper sec. 3.4): probability path, training target, ODE samplers.

Kept apart, as in facebookresearch/flow_matching:

* ``RectifiedPath``     the straight path x_t = (1 - t) eps + t x0 and its velocity v = x0 - eps.
* ``TimeSampler``       training times t: uniform on [0, 1] (default) or logit-normal.
* ``flow_loss``         L_flow = E || v_theta(x_t, t, c) - (x0 - eps) ||^2 (eq. 2), MSE.
* ``flow_training_step`` one noising + model call for a batch, returning everything the other
                         losses need (predicted velocities, x0_hat = x_t + (1 - t) v_hat).
* ``ode_solve``         Euler (default) or Heun integration of dx/dt = v(x, t) from t = 0 to 1.
* ``guided_velocity``   classifier-free guidance v = v_u + s (v_c - v_u).
* ``generate``          sample a motion with the model (interactive: both persons; reactive:
                         the reactor given the clean actor, which stays clean throughout);
                         ``SamplingSettings`` groups its sampler options, ``StepSettings``
                         those of ``flow_training_step``.

Convention (paper): t = 0 is noise, t = 1 is data; sampling integrates forward in t.
All tensors are (B, T, 262) normalised features per person unless stated otherwise.
Determinism: ``generate`` draws its noise from a ``torch.Generator`` seeded with ``sampling.seed``
on the CPU, so a given seed gives the same sample on any device.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from dataclasses import dataclass

import torch

from dualflow.errors import DualFlowError
from dualflow.model import Conditions, DualFlow

VelocityFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
ProjectFn = Callable[[torch.Tensor, float], torch.Tensor]

# ---------------------------------------------------------------------------------------------
# Probability path
# ---------------------------------------------------------------------------------------------


class RectifiedPath:
    """Straight-line path between noise (t = 0) and data (t = 1).

    x_t = (1 - t) eps + t x0,   v = d x_t / dt = x0 - eps,   x0 = x_t + (1 - t) v.
    t broadcasts from (B,) over the trailing dimensions of x.
    """

    @staticmethod
    def _bt(t: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        t = torch.as_tensor(t, dtype=x.dtype, device=x.device)
        return t.reshape(t.shape + (1,) * (x.ndim - t.ndim)) if t.ndim else t

    def interpolate(self, x0: torch.Tensor, noise: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """x_t = (1 - t) eps + t x0."""
        tb = self._bt(t, x0)
        return (1 - tb) * noise + tb * x0

    @staticmethod
    def target_velocity(x0: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """v = x0 - eps (constant along the path)."""
        return x0 - noise

    def x0_from_velocity(self, x_t: torch.Tensor, t: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """x0_hat = x_t + (1 - t) v_hat (one Euler step to t = 1)."""
        return x_t + (1 - self._bt(t, x_t)) * v


# ---------------------------------------------------------------------------------------------
# Training times and the flow loss
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class TimeSampler:
    """Training times t in [0, 1].

    kind="uniform": t ~ U(0, 1) (default). kind="logit_normal": t = sigmoid(n), n ~ N(mean, std)
    (Esser et al. 2024), which puts more samples at intermediate t.
    """

    kind: str = "uniform"
    mean: float = 0.0
    std: float = 1.0

    def __post_init__(self) -> None:
        if self.kind not in ("uniform", "logit_normal"):
            raise DualFlowError(f"TimeSampler.kind must be 'uniform' or 'logit_normal', got {self.kind!r}")
        if self.std <= 0:
            raise DualFlowError(f"TimeSampler.std must be > 0, got {self.std}")

    def sample(self, n: int, generator: torch.Generator | None = None, device="cpu") -> torch.Tensor:
        """(n,) times on ``device``, drawn on the generator's device (no copy when they agree)."""
        where = _draw_device(generator)
        if self.kind == "uniform":
            t = torch.rand(n, generator=generator, device=where)
        else:
            t = torch.sigmoid(self.mean + self.std * torch.randn(n, generator=generator, device=where))
        return t.to(device)


def _draw_device(generator: torch.Generator | None) -> torch.device:
    """Where random numbers of ``generator`` are drawn: its own device (CPU when None)."""
    return torch.device("cpu") if generator is None else generator.device


def flow_loss(v_pred: torch.Tensor, v_target: torch.Tensor, frame_mask: torch.Tensor | None = None) -> torch.Tensor:
    """L_flow = mean || v_pred - v_target ||^2 over batch, frames and features (eq. 2).

    v_pred, v_target (B, T, D); frame_mask (B, T) bool restricts the mean to real frames.
    """
    err = (v_pred - v_target) ** 2
    if frame_mask is None:
        return err.mean()
    m = frame_mask.to(err.dtype)[..., None]
    return (err * m).sum() / (m.sum() * err.shape[-1]).clamp_min(1.0)


@dataclass
class FlowStep:
    """Everything one training step produces (all (B, T, 262) unless noted).

    loss: scalar L_flow; t: (B,); v_a/v_b: predicted velocities; x0_hat_a/x0_hat_b:
    predicted clean motions x_t + (1 - t) v_hat (reactive: x0_hat_a is the clean actor);
    target_a/target_b: x0 - eps (reactive: zeros for the actor).
    """

    loss: torch.Tensor
    t: torch.Tensor
    v_a: torch.Tensor
    v_b: torch.Tensor
    x0_hat_a: torch.Tensor
    x0_hat_b: torch.Tensor
    target_a: torch.Tensor
    target_b: torch.Tensor


@dataclass(frozen=True)
class StepSettings:
    """How ``flow_training_step`` noises a batch and calls the model: training-time sampler,
    probability path, and the model's look-ahead in frames (None: the model's own)."""

    time_sampler: TimeSampler = TimeSampler()
    path: RectifiedPath = RectifiedPath()
    look_ahead: int | None = None


def flow_training_step(
    model: DualFlow,
    x0_a: torch.Tensor,
    x0_b: torch.Tensor,
    cond: Conditions | None = None,
    *,
    mode: str = "interactive",
    frame_mask: torch.Tensor | None = None,
    settings: StepSettings = StepSettings(),
    generator: torch.Generator | None = None,
) -> FlowStep:
    """Noise a clean batch along the path, call the model, return L_flow and x0_hat.

    interactive: both persons are noised with the same t and both velocities are learned,
    L_flow = MSE over [v_a; v_b] (eq. 17's 524-d output).
    reactive: the actor stays clean (x_a = x0_a), its velocity is 0 by construction, and
    L_flow = MSE over the reactor only.
    Noise and t come from ``generator`` so a seeded step is reproducible; they are drawn on the
    generator's device (a CUDA generator keeps them on the GPU: no host copy per step).
    settings: the time sampler, the path and the model's look-ahead (see ``StepSettings``).
    """
    path = settings.path
    look_ahead = settings.look_ahead
    b = x0_a.shape[0]
    device = x0_a.device
    where = _draw_device(generator)
    t = settings.time_sampler.sample(b, generator, device).to(x0_a.dtype)
    eps_b = torch.randn(x0_b.shape, generator=generator, device=where).to(device, x0_b.dtype)
    x_b = path.interpolate(x0_b, eps_b, t)
    target_b = path.target_velocity(x0_b, eps_b)
    if mode == "reactive":
        x_a = x0_a
        target_a = torch.zeros_like(x0_a)
    else:
        eps_a = torch.randn(x0_a.shape, generator=generator, device=where).to(device, x0_a.dtype)
        x_a = path.interpolate(x0_a, eps_a, t)
        target_a = path.target_velocity(x0_a, eps_a)
    v_a, v_b = model(x_a, x_b, t, cond, mode=mode, look_ahead=look_ahead, frame_mask=frame_mask)
    if mode == "reactive":
        loss = flow_loss(v_b, target_b, frame_mask)
        x0_hat_a = x0_a
    else:
        loss = flow_loss(torch.cat([v_a, v_b], -1), torch.cat([target_a, target_b], -1), frame_mask)
        x0_hat_a = path.x0_from_velocity(x_a, t, v_a)
    x0_hat_b = path.x0_from_velocity(x_b, t, v_b)
    return FlowStep(loss, t, v_a, v_b, x0_hat_a, x0_hat_b, target_a, target_b)


# ---------------------------------------------------------------------------------------------
# Samplers
# ---------------------------------------------------------------------------------------------


def time_grid(steps: int) -> list[float]:
    """Uniform grid t_k = k / steps, k = 0 .. steps (t = 0 noise -> t = 1 data)."""
    if steps < 1:
        raise DualFlowError(f"number of sampling steps must be >= 1, got {steps}")
    return [k / steps for k in range(steps + 1)]


def ode_solve(
    velocity: VelocityFn,
    x_init: torch.Tensor,
    steps: int = 20,
    method: str = "euler",
    project: ProjectFn | None = None,
) -> torch.Tensor:
    """Integrate dx/dt = velocity(x, t) from t = 0 to t = 1 on a uniform grid.

    euler: x_{k+1} = x_k + h v(x_k, t_k).
    heun:  x~ = x_k + h v(x_k, t_k);  x_{k+1} = x_k + h/2 [v(x_k, t_k) + v(x~, t_{k+1})]
           (2 model calls per step; the final step is Heun too).
    project(x, t) -> x, when given, is applied to the state at every grid time (and to Heun's
    predictor) to impose known values, e.g. inpainting already-emitted frames.
    velocity receives t as a (B,) tensor.
    """
    if method not in ("euler", "heun"):
        raise DualFlowError(f"sampler method must be 'euler' or 'heun', got {method!r}")
    grid = time_grid(steps)
    b = x_init.shape[0]
    x = x_init if project is None else project(x_init, 0.0)

    def tt(value: float) -> torch.Tensor:
        return torch.full((b,), value, dtype=x_init.dtype, device=x_init.device)

    for t0, t1 in zip(grid[:-1], grid[1:]):
        h = t1 - t0
        v0 = velocity(x, tt(t0))
        x_pred = x + h * v0
        if method == "heun":
            if project is not None:
                x_pred = project(x_pred, t1)
            x_pred = x + 0.5 * h * (v0 + velocity(x_pred, tt(t1)))
        x = x_pred if project is None else project(x_pred, t1)
    return x


def guided_velocity(
    model: DualFlow,
    cond: Conditions | None,
    *,
    mode: str,
    x_actor: torch.Tensor | None = None,
    cfg_scale: float = 1.0,
    look_ahead: int | None = None,
    frame_mask: torch.Tensor | None = None,
) -> VelocityFn:
    """Velocity function of the ODE state, with classifier-free guidance.

    v = v_u + s (v_c - v_u), v_c with ``cond``, v_u with text and music dropped; s = 1 is
    plain conditional sampling (one model call). State layout: interactive (B, T, 524) =
    [x_a; x_b]; reactive (B, T, 262) = x_b, with the clean actor ``x_actor`` fixed (its stream
    is computed once per conditioning variant and cached for all steps).
    """
    cond = cond or Conditions()
    uncond = cond.unconditional()
    d = model.config.motion_dim
    # Reactive: the actor stream is independent of t and of the reactor, so it is computed once
    # per conditioning variant and reused at every step (model.actor_context).
    contexts: dict[int, object] = {}

    def one(x: torch.Tensor, t: torch.Tensor, c: Conditions) -> torch.Tensor:
        if mode == "reactive":
            key = id(c)
            if key not in contexts:
                contexts[key] = model.actor_context(x_actor, c, frame_mask=frame_mask)
            return model(
                x_actor, x, t, c, mode=mode, look_ahead=look_ahead, frame_mask=frame_mask, actor_context=contexts[key]
            )[1]
        v_a, v_b = model(x[..., :d], x[..., d:], t, c, mode=mode, look_ahead=look_ahead, frame_mask=frame_mask)
        return torch.cat([v_a, v_b], -1)

    def velocity(x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        v_c = one(x, t, cond)
        if cfg_scale == 1.0:
            return v_c
        v_u = one(x, t, uncond)
        return v_u + cfg_scale * (v_c - v_u)

    return velocity


@dataclass(frozen=True)
class SamplingSettings:
    """How ``generate`` samples: ODE steps and method ("euler" | "heun"), classifier-free
    guidance scale (1: none), the model's look-ahead in frames (None: the model's own), the seed
    of the CPU generator that draws the initial noise, and an optional projection (see
    ``ode_solve``). cuda_graph: on a CUDA device, replay the velocity from a CUDA graph
    (``dualflow.cuda_graph``; the same kernels, launched once per step instead of one by one).
    precision: the network's matrix products on a CUDA device: "tf32" (default; float32
    products on the tensor cores, 10-bit mantissa inputs, float32 sums), "bf16" (autocast as
    training does there) or "float32" (exact float32, about 1.4x slower on an H100). The ODE
    state and each step's update stay in the model's dtype; off CUDA it does nothing. The output
    differs from float32 sampling by the products' rounding (bench/dualflow_gpu.py prints how
    much)."""

    steps: int = 20
    method: str = "euler"
    cfg_scale: float = 1.0
    look_ahead: int | None = None
    seed: int = 0
    project: ProjectFn | None = None
    cuda_graph: bool = True
    precision: str = "tf32"

    def __post_init__(self):
        if self.precision not in PRECISIONS:
            raise DualFlowError(f"SamplingSettings.precision must be one of {PRECISIONS}, got {self.precision!r}")


PRECISIONS = ("tf32", "bf16", "float32")


def bf16_velocity(velocity: VelocityFn, dtype: torch.dtype) -> VelocityFn:
    """``velocity`` with the network under CUDA bf16 autocast, its output back in ``dtype``.
    The autocast weight cache is off: a CUDA graph cannot capture a cache that outlives it, so
    each call casts the weights it uses (one read of them per call)."""

    def run(x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        with torch.autocast("cuda", dtype=torch.bfloat16, cache_enabled=False):
            v = velocity(x, t)
        return v.to(dtype)

    return run


@contextlib.contextmanager
def cuda_tf32(on: bool):
    """CUDA float32 matrix products and cuDNN convolutions on the tensor cores (TF32) inside the
    block, the settings before it restored after. (A process-wide switch of torch's: another
    thread's products in the meantime follow it too.)"""
    before = torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = on
    try:
        yield
    finally:
        torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = before


def precision_context(device: torch.device, precision: str):
    """Where a sampler at ``precision`` (``PRECISIONS``) runs its network: TF32 switched on or
    off on a CUDA device (``cuda_tf32``), nothing elsewhere."""
    return cuda_tf32(precision == "tf32") if device.type == "cuda" else contextlib.nullcontext()


@torch.no_grad()
def generate(
    model: DualFlow,
    n_frames: int,
    cond: Conditions | None = None,
    *,
    mode: str = "interactive",
    x_actor: torch.Tensor | None = None,
    batch: int | None = None,
    noise: torch.Tensor | None = None,
    sampling: SamplingSettings = SamplingSettings(),
) -> tuple[torch.Tensor, torch.Tensor]:
    """Sample motion; returns (x_a, x_b), each (B, T, 262) normalised features.

    interactive: both persons from noise; reactive: ``x_actor`` (B, T, 262) is required,
    stays clean (returned unchanged as x_a) and only the reactor is integrated.
    noise: optional initial state (B, T, 524 interactive | 262 reactive); otherwise drawn from
    a CPU generator seeded with ``sampling.seed``. sampling: see ``SamplingSettings``.
    """
    s = sampling
    d = model.config.motion_dim
    if mode == "reactive":
        if x_actor is None:
            raise DualFlowError("reactive generation needs x_actor (B, T, 262), the clean actor motion")
        if x_actor.ndim != 3 or x_actor.shape[1] != n_frames:
            raise DualFlowError(f"x_actor must be (B, {n_frames}, {d}), got {tuple(x_actor.shape)}")
        batch = x_actor.shape[0]
        width = d
    else:
        batch = batch or 1
        width = 2 * d
    param = next(model.parameters())
    device, dtype = param.device, param.dtype
    if noise is None:
        gen = torch.Generator().manual_seed(int(s.seed))
        noise = torch.randn((batch, n_frames, width), generator=gen)
    if tuple(noise.shape) != (batch, n_frames, width):
        raise DualFlowError(f"noise must be {(batch, n_frames, width)}, got {tuple(noise.shape)}")
    noise = noise.to(device, dtype)
    if x_actor is not None:
        x_actor = x_actor.to(device, dtype)
    velocity = guided_velocity(model, cond, mode=mode, x_actor=x_actor, cfg_scale=s.cfg_scale, look_ahead=s.look_ahead)
    if s.precision == "bf16" and device.type == "cuda":
        velocity = bf16_velocity(velocity, dtype)
    if s.cuda_graph and device.type == "cuda":
        from dualflow.cuda_graph import GraphedVelocity

        velocity = GraphedVelocity(velocity)
    was_training = model.training
    if was_training:  # Module.eval() walks every submodule: only when needed
        model.eval()
    try:
        with precision_context(device, s.precision):
            x = ode_solve(velocity, noise, steps=s.steps, method=s.method, project=s.project)
    finally:
        if was_training:
            model.train(True)
    if mode == "reactive":
        return x_actor, x
    return x[..., :d], x[..., d:]

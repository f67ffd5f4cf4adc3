"""The safety filter between whatever upstream produced and what a transport may send.

Every tick the control loop passes its desired joint targets (n,) in radians through
:meth:`SafetyFilter.step`. The command that comes out satisfies, whatever came in:

- it is finite (a target with NaN or inf is rejected whole and the last safe command is
  held, since a partially valid pose is not a pose);
- ``lower <= q <= upper`` (soft joint limits);
- ``|q_k - q_{k-1}| <= v_max · dt`` (velocity limit, per tick);
- ``|q_k - 2 q_{k-1} + q_{k-2}| <= a_max · dt²`` (acceleration limit), except where keeping
  inside the position limits forces a harder stop; to keep that rare, the velocity towards
  a limit is also capped at the braking speed ``sqrt(2 · a_max · distance)`` (in its
  discrete-time form).

Limits come from :class:`JointLimits`, which is built as the intersection of every
source (MJCF, hardware config, servo EEPROM): the bridge never enforces a limit wider
than any of them.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntFlag

import numpy as np

from ros_free_bridge.errors import BridgeError


class Intervention(IntFlag):
    """What the filter changed on a joint this tick (bit flags, stored in telemetry)."""

    NONE = 0
    NONFINITE = 1  #: upstream produced NaN/inf; the last safe command was held
    POSITION = 2  #: clamped to the soft joint limits
    VELOCITY = 4  #: slowed to the velocity limit (or the braking speed)
    ACCELERATION = 8  #: smoothed to the acceleration limit


@dataclass(frozen=True)
class JointLimits:
    """Per-joint limits, arrays of shape (n,) in the order of ``names``.

    lower, upper: rad. max_velocity: rad/s (> 0). max_acceleration: rad/s² (> 0).
    """

    names: tuple[str, ...]
    lower: np.ndarray
    upper: np.ndarray
    max_velocity: np.ndarray
    max_acceleration: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.names)
        for field in ("lower", "upper", "max_velocity", "max_acceleration"):
            arr = np.broadcast_to(np.asarray(getattr(self, field), dtype=np.float64), (n,)).copy()
            if not np.all(np.isfinite(arr)):
                raise BridgeError(f"joint limits: {field} must be finite for every joint, got {arr}")
            arr.setflags(write=False)
            object.__setattr__(self, field, arr)
        bad = np.flatnonzero(self.lower >= self.upper)
        if bad.size:
            j = self.names[bad[0]]
            raise BridgeError(
                f"joint limits: joint {j!r} has lower {self.lower[bad[0]]:.4f} >= upper {self.upper[bad[0]]:.4f}"
            )
        for field in ("max_velocity", "max_acceleration"):
            arr = getattr(self, field)
            if np.any(arr <= 0):
                j = self.names[int(np.argmin(arr))]
                raise BridgeError(f"joint limits: {field} of joint {j!r} must be > 0")

    @property
    def n(self) -> int:
        return len(self.names)

    def in_order(self, names) -> JointLimits:
        """These limits for the joints ``names``, in that order; BridgeError names any missing."""
        missing = [n for n in names if n not in self.names]
        if missing:
            raise BridgeError(f"joint limits: joints {missing} are missing from the limit set ({list(self.names)})")
        idx = np.array([self.names.index(n) for n in names], dtype=int)
        return JointLimits(
            tuple(names), self.lower[idx], self.upper[idx], self.max_velocity[idx], self.max_acceleration[idx]
        )

    def intersect(self, other: JointLimits) -> JointLimits:
        """The tighter of two limit sets for the same joints (by name)."""
        o = other.in_order(self.names)
        return JointLimits(
            self.names,
            np.maximum(self.lower, o.lower),
            np.minimum(self.upper, o.upper),
            np.minimum(self.max_velocity, o.max_velocity),
            np.minimum(self.max_acceleration, o.max_acceleration),
        )

    def contains(self, q: np.ndarray, tol: float = 1e-9) -> bool:
        q = np.asarray(q, dtype=np.float64)
        return bool(np.all(np.isfinite(q)) and np.all(q >= self.lower - tol) and np.all(q <= self.upper + tol))

    def clip(self, q: np.ndarray) -> np.ndarray:
        return np.clip(np.asarray(q, dtype=np.float64), self.lower, self.upper)


class SafetyFilter:
    """Clamp each tick's targets to position, velocity and acceleration limits.

    ``dt`` is the control period in seconds. Call :meth:`reset` with the measured
    present positions (clipped into the limits) before the first :meth:`step`.
    """

    def __init__(self, limits: JointLimits, dt: float):
        if not dt > 0:
            raise BridgeError(f"safety filter: control period must be > 0 s, got {dt}")
        self.limits = limits
        self.dt = float(dt)
        self._q: np.ndarray | None = None  # last command
        self._v = np.zeros(limits.n)  # last command's per-tick step (rad/tick)
        self._per_tick_for: JointLimits | None = None  # limits the per-tick bounds below were made from

    @property
    def last_command(self) -> np.ndarray:
        if self._q is None:
            raise BridgeError("safety filter: reset() with the present positions before stepping")
        return self._q.copy()

    def reset(self, present: np.ndarray) -> np.ndarray:
        """Start from the measured positions; returns the (clipped) starting command."""
        present = np.asarray(present, dtype=np.float64)
        if present.shape != (self.limits.n,) or not np.all(np.isfinite(present)):
            raise BridgeError(
                f"safety filter: present positions must be {self.limits.n} finite values, got {present}; "
                "check the servo readings"
            )
        self._q = self.limits.clip(present)
        self._v = np.zeros(self.limits.n)
        return self._q.copy()

    def _per_tick(self, lim: JointLimits) -> None:
        """Per-tick bounds of ``lim`` (recomputed when the limits object changes, e.g. degraded):
        a = a_max·dt², a², 8a and v = v_max·dt, all (n,) rad per tick."""
        dt = self.dt
        self._a_step = lim.max_acceleration * dt * dt
        self._a_sq = self._a_step * self._a_step
        self._a_8 = 8.0 * self._a_step
        self._v_step = lim.max_velocity * dt
        self._per_tick_for = lim

    def step(self, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Filter one tick's targets (n,) rad. Returns (command (n,), interventions (n,) uint8).

        Written as bare ufuncs (no ``np.clip``/boolean-index wrappers, bounds cached per
        limits): it runs every tick of a 250 Hz loop."""
        q_prev = self._q
        if q_prev is None:
            raise BridgeError("safety filter: reset() with the present positions before stepping")
        lim = self.limits
        if lim is not self._per_tick_for:
            self._per_tick(lim)
        a_step = self._a_step
        minimum, maximum = np.minimum, np.maximum
        target = np.asarray(target, dtype=np.float64)
        nonfinite = target.shape != (lim.n,) or not np.isfinite(target).all()
        if nonfinite:
            # Hold: decelerate to a stop as fast as the acceleration limit allows.
            target = q_prev + self._brake_step()
        step = target - q_prev
        in_pos = (target < lim.lower) | (target > lim.upper)
        # acceleration: the step may change by at most a_max·dt² from the previous step
        clipped = minimum(maximum(step, self._v - a_step), self._v + a_step)
        accel = clipped != step
        step = clipped
        # velocity, including the braking speed towards whichever limit we are heading to
        dist = np.where(step > 0, lim.upper - q_prev, q_prev - lim.lower)
        # largest step s from which steps s, s - a, s - 2a, ... stop within dist:
        # s (s + a) / (2 a) <= dist  (the discrete form of v <= sqrt(2 a d))
        brake = 0.5 * (-a_step + np.sqrt(self._a_sq + self._a_8 * maximum(dist, 0.0)))
        cap = minimum(self._v_step, maximum(brake, a_step))
        clipped = minimum(maximum(step, -cap), cap)
        vel = clipped != step
        q = q_prev + clipped
        q_clipped = minimum(maximum(q, lim.lower), lim.upper)
        pos = (q_clipped != q) | in_pos
        flags = (accel.view(np.uint8) * _ACCEL) | (vel.view(np.uint8) * _VEL) | (pos.view(np.uint8) * _POS)
        if nonfinite:
            flags |= _NONFINITE
        self._v = q_clipped - q_prev
        self._q = q_clipped
        return q_clipped.copy(), flags

    def _brake_step(self) -> np.ndarray:
        a_step = self.limits.max_acceleration * self.dt * self.dt
        return np.sign(self._v) * np.maximum(np.abs(self._v) - a_step, 0.0)


_NONFINITE, _ACCEL, _VEL, _POS = (
    np.uint8(f)
    for f in (Intervention.NONFINITE, Intervention.ACCELERATION, Intervention.VELOCITY, Intervention.POSITION)
)


def min_jerk(q0: np.ndarray, q1: np.ndarray, duration: float, dt: float) -> np.ndarray:
    """Minimum-jerk path from q0 to q1 (n,) over ``duration`` seconds sampled every dt.

    q(s) = q0 + (q1 - q0) · (10 s³ - 15 s⁴ + 6 s⁵), s = t / duration; zero velocity and
    acceleration at both ends. Returns (K, n) with K = ceil(duration / dt), ending at q1.
    """
    q0 = np.asarray(q0, dtype=np.float64)
    q1 = np.asarray(q1, dtype=np.float64)
    k = max(1, int(np.ceil(duration / dt - 1e-9)))
    s = np.arange(1, k + 1) / k
    blend = 10 * s**3 - 15 * s**4 + 6 * s**5
    return q0 + (q1 - q0) * blend[:, None]


def min_jerk_duration(q0: np.ndarray, q1: np.ndarray, limits: JointLimits, minimum: float = 0.5) -> float:
    """Shortest minimum-jerk duration that respects the velocity and acceleration limits.

    Peak speed of the profile is 1.875·Δ/T and peak acceleration 5.774·Δ/T².
    """
    delta = np.abs(np.asarray(q1, float) - np.asarray(q0, float))
    t_v = np.max(1.875 * delta / limits.max_velocity)
    t_a = np.max(np.sqrt(5.774 * delta / limits.max_acceleration))
    return float(max(minimum, t_v, t_a))

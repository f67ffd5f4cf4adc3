"""SYNTHETIC stepping leaders for the retargeter's stepping and turning figures and tests.

Made up by a program (the procedural dancer of :mod:`dualflow.synthetic`: rest-pose bones,
two-bone leg IK, feet flat and planted while down), not captured motion. Each leader steps
left and right alternately at ``bpm`` (one step per beat, the swing foot lifting 6 cm) and

- ``turning_leader``: turns in place at ``rate`` rad/s for ``turns`` full turns, by stepping
  (each landing turns the foot with the body);
- ``walking_leader``: walks forward at ``speed`` m/s (and, with ``turn_rate``, on a circle);
- ``sidestep_leader``: sways sideways ``amplitude`` m on the beat (steps in place);
- ``pivot_turn``: no steps at all: the rest pose turning rigidly on the spot (the feet pivot on
  the floor, so contact detection keeps them down), the case that made the offline solver
  report "infeasible ... velocity of root yaw".

Every leader carries its true contacts (T, 4) (left ankle, left foot, right ankle, right
foot); :func:`count_steps` counts its touch-downs. Units: m, rad, s; Z up; the person starts facing +X at the origin.
"""

from __future__ import annotations

import numpy as np

from dualflow.motion import REST_POSE, Motion
from dualflow.synthetic import _ARM_DOWN, _BodyPlan, _synthesise


def _leader(name: str, seconds: float, fps: float, bpm: float, heading, centre, arm_raise: float = 0.15) -> Motion:
    n = max(int(round(seconds * fps)), 2)
    period = 60.0 / bpm
    first_beat = 0.5 * period
    beats = first_beat - period + period * np.arange(int(np.ceil((seconds + 2 * period) / period)) + 2)
    arms = lambda t: np.full(np.shape(t), _ARM_DOWN + arm_raise)  # noqa: E731
    plan = _BodyPlan(centre=centre, heading=heading, arm_left=arms, arm_right=arms, beat_times=beats, first_foot=0)
    times = np.arange(n) / fps
    body = _synthesise(plan, times, period, 0.0)
    contacts = body.contacts
    return Motion(positions=body.positions, fps=fps, contacts=contacts, name=name)


def count_steps(contacts: np.ndarray) -> int:
    """Touch-downs after the first frame: rising edges of each side's contact (T, 2) or (T, 4)."""
    c = np.asarray(contacts, dtype=bool)
    if c.shape[1] == 4:
        c = np.stack([c[:, 0] | c[:, 1], c[:, 2] | c[:, 3]], axis=1)
    return int(np.sum(c[1:] & ~c[:-1]))


def turning_leader(
    turns: float = 2.5, rate: float = 0.6, fps: float = 30.0, bpm: float = 110.0, lead_in: float = 1.0
) -> Motion:
    """Turns in place, ``turns`` full turns at ``rate`` rad/s (positive: to the left), after
    ``lead_in`` s of stepping on the spot; ends with 1 s of stepping on the spot."""
    spin = 2 * np.pi * abs(turns) / abs(rate)
    seconds = lead_in + spin + 1.0
    sign = np.sign(rate) * np.sign(turns)

    def heading(t):
        return sign * np.abs(rate) * np.clip(np.asarray(t, dtype=np.float64) - lead_in, 0.0, spin)

    def centre(t):
        return np.zeros((np.size(t), 2))

    return _leader(f"synthetic_turn_{turns:g}x_{rate:g}rad_s", seconds, fps, bpm, heading, centre)


def walking_leader(
    seconds: float = 8.0,
    speed: float = 0.35,
    turn_rate: float = 0.0,
    fps: float = 30.0,
    bpm: float = 100.0,
    lead_in: float = 1.0,
    arm_raise: float = 0.15,
) -> Motion:
    """Walks forward at ``speed`` m/s after ``lead_in`` s of stepping on the spot (turning at
    ``turn_rate`` rad/s while walking: a circle). The arms hang ``arm_raise`` rad out from
    relaxed (negative: pressed against the thighs)."""

    def heading(t):
        return turn_rate * np.maximum(np.asarray(t, dtype=np.float64) - lead_in, 0.0)

    def centre(t):
        t = np.asarray(t, dtype=np.float64)
        # integrate the heading: dp/dt = speed (cos h, sin h), on a fine grid
        grid = np.linspace(0.0, max(float(np.max(t)), 1e-6), 2000)
        h = heading(grid)
        v = speed * (grid >= lead_in)
        dt = np.diff(grid, prepend=0.0)
        px, py = np.cumsum(v * np.cos(h) * dt), np.cumsum(v * np.sin(h) * dt)
        return np.stack([np.interp(t, grid, px), np.interp(t, grid, py)], axis=-1)

    name = f"synthetic_walk_{speed:g}m_s_{turn_rate:g}rad_s"
    return _leader(name, seconds, fps, bpm, heading, centre, arm_raise)


def sidestep_leader(seconds: float = 8.0, amplitude: float = 0.12, fps: float = 30.0, bpm: float = 90.0) -> Motion:
    """Steps on the spot, swaying ``amplitude`` m left and right over two beats."""
    period = 60.0 / bpm

    def heading(t):
        return np.zeros(np.shape(t))

    def centre(t):
        t = np.asarray(t, dtype=np.float64)
        return np.stack([np.zeros_like(t), amplitude * np.sin(np.pi * t / period)], axis=-1)

    return _leader(f"synthetic_sidestep_{amplitude:g}m", seconds, fps, bpm, heading, centre)


def leaders() -> list[Motion]:
    """The stepping leaders the figures use: two turning, two walking, one side-stepping."""
    return [
        turning_leader(2.5, 0.6),
        turning_leader(2.0, -0.9),
        walking_leader(8.0, 0.3),
        walking_leader(10.0, 0.3, 0.3),
        sidestep_leader(8.0),
    ]


def held_out_leaders() -> list[Motion]:
    """Stepping leaders with speeds, rates and rhythms the figures' set does not use (a check
    that the rules are not tuned to it): a slow and a fast turn, a faster walk, two circles,
    a wide quick and a narrow slow side-step, and a pivot on the spot."""
    return [
        turning_leader(1.5, 0.4),
        turning_leader(1.0, -1.2),
        walking_leader(8.0, 0.5),
        walking_leader(8.0, 0.2, -0.5),
        walking_leader(8.0, 0.4, 0.6, bpm=130.0),
        sidestep_leader(8.0, 0.2, bpm=120.0),
        sidestep_leader(8.0, 0.06, bpm=70.0),
        pivot_turn(0.8, 1.5),
    ]


def quick_leaders() -> list[Motion]:
    """Leaders stepping at a dance's pace, 2 to 2.7 steps a second (120, 140 and 160 bpm, one
    step per beat; the other leaders step 1.5-1.8 times a second): walking at 0.3 m/s, side-
    stepping 0.12 m, one turn at 0.8 rad/s and stepping in place, 6 s each."""
    out = []
    for bpm in (120.0, 140.0, 160.0):
        out += [
            walking_leader(6.0, 0.3, bpm=bpm).replace(name=f"quick_walk_{bpm:g}bpm"),
            sidestep_leader(6.0, 0.12, bpm=bpm).replace(name=f"quick_sidestep_{bpm:g}bpm"),
            turning_leader(1.0, 0.8, bpm=bpm).replace(name=f"quick_turn_{bpm:g}bpm"),
            walking_leader(6.0, 0.0, bpm=bpm).replace(name=f"quick_in_place_{bpm:g}bpm"),
        ]
    return out


def pivot_turn(rate: float = 0.8, turns: float = 2.5, fps: float = 30.0, lead_in: float = 0.5) -> Motion:
    """The rest pose turning ``turns`` full turns at ``rate`` rad/s on the spot, after ``lead_in``
    s still and before 0.5 s still; no contact labels (detected: both feet stay down)."""
    T = int(turns * 2 * np.pi / abs(rate) * fps + (lead_in + 0.5) * fps)
    yaw = np.sign(rate) * np.clip(abs(rate) * (np.arange(T) / fps - lead_in), 0.0, turns * 2 * np.pi)
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.zeros((T, 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
    pivot = REST_POSE[0] * np.array([1.0, 1.0, 0.0])
    return Motion(np.einsum("tij,kj->tki", R, REST_POSE - pivot) + pivot, fps, name=f"pivot_{turns:g}x_{rate:g}rad_s")

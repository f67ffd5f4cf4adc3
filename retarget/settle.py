"""The end of a live stream: the robot steps back to its own stance and comes to rest.

A stream can end with the robot in any stance the person left it in: feet apart or staggered,
turned from each other, the body twisted over them, a foot in the air. The bridge's stop ramp
then moves the joints to the rest pose (the stand pose) in joint space, a move that assumes
the feet in the stand stance under the hips: with the feet planted elsewhere it drags them,
and a body twisted 0.4-0.95 rad over its feet fell as the ramp unwound its hip yaws.

:class:`Settle` has the streaming retargeter follow a short motion of its own instead, in the
robot's frame (``BalancePlanner.rebase``: the person's frame and the body twist no longer
apply), so that the planner takes the steps (with their weight shift and ZMP plan) as it takes
the person's:

1. the body goes from where the robot is (its keypoints in the last frame, not the targets it
   was last given: a robot that could not keep up with them, the demo's partner ending
   mid-lunge 0.1 m and 76 deg from its targets, was swung round to them at the servos' speed
   limit) to the robot's stand pose over its planted feet, still facing where its hips face
   (``blend`` s, minimum jerk); the feet stay where they are, a foot in the air comes down.
   A body twisted over its feet is not turned back over them: the feet turn to it by
   stepping (unwinding 0.66 rad of twist on planted feet in 0.8-2 s, the demo's robot fell
   in 1-2 runs of 6);
2. once the body has come to rest (``pause``), while a planted foot is further than
   ``tolerance`` m (the planner's ``step_distance``) or ``turn_tolerance`` rad from where that
   stance puts it, it is lifted and put there (each foot in turn, at most ``max_steps`` steps;
   a foot whose step brought it no closer, its place clamped by the other foot's, is left where
   it is);
3. the pose held until the feet are down and the joints have moved slower than ``rest_speed``
   for ``hold`` s (at most ``max_hold`` s).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from retarget.lead_in import min_jerk_share


@dataclass(frozen=True)
class SettleConfig:
    blend: float = 0.5  #: s from the last pose to the stand pose, at least; ...
    turn_speed: float = 0.6  #: rad/s: ... longer where the body turns faster (the peak speed)
    hold: float = 0.5  #: s held at the end, the feet down and the joints slower than ...
    rest_speed: float = 0.3  #: ... this (rad/s)
    max_hold: float = 2.5  #: s: the hold ends after this long whatever the speed
    pause: float = 0.2  #: s of the same rest between the blend and the first step, ...
    max_pause: float = 1.0  #: ... waited for this long at most
    tolerance: float | None = None  #: m a planted foot may be from its place in the stance (None: step_distance)
    turn_tolerance: float = 0.12  #: rad it may be turned from it
    max_steps: int = 6
    land_wait: float = 0.25  #: s both feet down after a step, beyond min_stance / min_double


class Settle:
    """Iterate for the frames x (nx,) that take a balancing
    :class:`~retarget.streaming.StreamingRetargeter` from its last frame to its stand stance (the
    module docstring), one frame at a time so that a live bridge can play the first while the
    rest are made; :attr:`steps` counts the robot's own steps in them so far (its lift-offs: the
    planner also steps by itself to catch up with the targets' feet). No frames for a
    retargeter without balance or that has not started."""

    def __init__(self, streamer, config: SettleConfig = SettleConfig()):
        self.streamer, self.config, self.steps = streamer, config, 0
        self._last_x = None

    def _frames(self, seconds: float) -> int:
        return max(1, round(seconds * self.streamer.fps))

    def _add(self, targets: np.ndarray, contact=(True, True), still: bool = False) -> np.ndarray:
        """One frame: the planted feet's targets where the planner holds them, then stepped
        (``still``: a held pose, StreamingRetargeter.step)."""
        st = self.streamer
        st.planner.own_feet(targets)
        before = st.planted.copy()
        self._last_x = x = st.step(targets, contact, still)
        self.steps += int((before & ~st.planted).sum())
        return x

    def __iter__(self):
        st, config = self.streamer, self.config
        start = st.last_keypoints  # where the robot is, not the targets it was last given
        if not st.balance or start is None:
            return
        planner = st.planner
        planner.rebase()
        goal = planner.stand_over_feet(start)
        feet = planner.foot_keypoints
        body = np.setdiff1d(np.arange(len(start)), feet[0] + feet[1])
        now = start.copy()
        turn = abs(_turn(start, goal, st.robot.root_keypoint, feet))
        n = self._frames(max(config.blend, 1.875 * turn / config.turn_speed))  # min-jerk peak: 1.875 x mean speed
        for k in range(1, n + 1):  # 1: the body to the stand pose; a planted foot stays, one in the air comes down
            u = float(min_jerk_share(k / n))
            now[body] = start[body] + u * (goal[body] - start[body])
            for s in range(2):
                if not st.planted[s]:
                    now[feet[s], 2] = start[feet[s], 2] + u * (goal[feet[s], 2] - start[feet[s], 2])
            yield self._add(now)
        yield from self._hold(now, config.pause, config.max_pause)  # no step while the body still turns
        yield from self._to_stance(now, goal)
        yield from self._hold(now, config.hold, config.max_hold)

    def _hold(self, now: np.ndarray, hold: float, longest: float):
        """The pose ``now`` held until both feet have stood and the joints moved slower than
        ``rest_speed`` for ``hold`` s (the planner may still be finishing a step), at most
        ``longest`` s. Each frame's motion is damped (``still``): with the acceleration row
        alone the pelvis yaw over the planted feet rang at 1-2 rad/s for seconds after the
        body turned, and the holds ran to their longest (5.5 s settles on the demo partners,
        3.1 s damped)."""
        n_root = self.streamer.robot.n_root
        still, slow = 0, self.config.rest_speed / self.streamer.fps
        for _ in range(self._frames(longest)):
            before = self._last_x
            yield self._add(now, still=True)
            moving = np.abs(self._last_x - before)[n_root:].max() > slow
            still = 0 if moving or not self.streamer.planted.all() else still + 1
            if still >= self._frames(hold):
                return

    def _to_stance(self, now: np.ndarray, goal: np.ndarray):
        """2: each foot that is off its place in ``goal`` stepped there, in turn (``now``
        updated in place), until none is or ``max_steps``."""
        config, planner, cfg = self.config, self.streamer.planner, self.streamer.config
        tol = cfg.step_distance if config.tolerance is None else config.tolerance
        wait = max(cfg.min_stance, cfg.min_double) + config.land_wait
        stepped, foot, waited = 0, None, 0
        before, done = None, set()  # a foot whose last step brought it no closer (the other foot's place clamps it)
        while stepped < config.max_steps:
            offsets = planner.stance_offsets(goal)
            if offsets is None:  # a foot still up (the planner's own step, or ours landing)
                if waited > self._frames(cfg.max_swing + cfg.step_shift + cfg.min_double):
                    return
                yield self._add(now)
                waited += 1
                continue
            waited = 0
            if foot is not None and sum(offsets[foot]) > sum(before[foot]) - 0.005:
                done.add(foot)
            off = [s for s, (d, t) in enumerate(offsets) if s not in done and (d > tol or t > config.turn_tolerance)]
            if not off:
                return
            # feet in turn (a turn takes both); the first, the one further off
            s = 1 - foot if foot is not None and 1 - foot in off else max(off, key=lambda f: sum(offsets[f]))
            before = offsets
            yield from self._step(now, goal, s)
            for _ in range(self._frames(wait)):
                yield self._add(now)
            stepped, foot = stepped + 1, s

    def _step(self, now: np.ndarray, goal: np.ndarray, s: int):
        """Foot s lifted, carried to its place in ``goal`` and put down (``now`` updated in
        place), as a person's step: the planner shifts the weight, swings and lands it."""
        cfg = self.streamer.config
        idx = self.streamer.planner.foot_keypoints[s]
        start = now[idx].copy()
        dist = float(np.linalg.norm(goal[idx[0], 0:2] - start[0, 0:2]))
        shift, swing = self._frames(cfg.step_shift), self._frames(max(cfg.min_swing, dist / cfg.swing_speed))
        contact = (s == 1, s == 0)
        for k in range(1, shift + swing + 1):
            u = min(max(0.0, (k - shift) / swing), 1.0)
            now[idx] = start + math.sin(0.5 * math.pi * u) ** 2 * (goal[idx] - start)
            now[idx, 2] = goal[idx, 2] + cfg.swing_height * math.sin(math.pi * u)
            yield self._add(now, contact)
        now[idx] = goal[idx]


def _turn(a: np.ndarray, b: np.ndarray, root: int, feet) -> float:
    """How far (rad) the body of targets ``b`` is turned from that of ``a`` (K, 3) about the
    vertical: the mean bearing change of the targets above the feet, seen from the root."""
    above = [k for k in range(len(a)) if k != root and k not in feet[0] + feet[1]]
    da, db = a[above, 0:2] - a[root, 0:2], b[above, 0:2] - b[root, 0:2]
    cross, dot = da[:, 0] * db[:, 1] - da[:, 1] * db[:, 0], (da * db).sum(axis=1)
    return float(math.atan2(cross.sum(), dot.sum()))

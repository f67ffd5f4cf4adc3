"""Offline retargeting by the step planner: a whole clip through the streaming solver and its
balance planner (:mod:`retarget.balance`), which knows the clip's future.

Contract: :func:`planned_trajectory` takes a :class:`retarget.streaming.StreamingRetargeter`
with balance (a free-standing robot with feet) and a :class:`dualflow.motion.Motion` and returns
a :class:`retarget.trajectory.RobotTrajectory` whose ``meta`` has the window optimisation's keys
(mode ``offline``, ``engine`` ``planner``, the robot's own contact schedule, step counts, what
it changed, seconds). It never fails for a clip it can read: where the person does what the
robot cannot (steps faster than its pace, turns on the spot, slides, drifts), it does the
closest thing it can balance and the ``changes`` say which seconds and why (``own pace``,
``own place``, ``step skipped``, ``flight``, ``speed-limited``).

What the future buys offline: the planner sees the person's foot contacts ``lookahead`` s
early, so the robot's weight shift (``StreamingConfig.step_shift``) starts before the person's
foot lifts and the robot's foot leaves the floor with it, not after it. Measured on op3 with
steps (bench/stepping.py's 9 clips, physics): keypoint error 8.2 % of height streamed against
7.3 % with 0.1 s (3 frames) of look-ahead, all clips pass either way; 5 frames put the CMU
clip's jerk ratio over 1.
"""

from __future__ import annotations

import time

import numpy as np

from dualflow.motion import Motion
from retarget.schedule import Change, changes_over, count_steps, keep_feet_down_in_flight, speed_limited
from retarget.streaming import StreamingRetargeter, trajectory_from_x
from retarget.targets import bool_runs, make_targets
from retarget.trajectory import RobotTrajectory

#: a run of frames whose pose (pelvis-relative keypoints, mean) differs from the person's by more
#: than this share of the robot's height is reported
POSE_CHANGE = 0.12
#: ... and one whose pelvis stands further than this share of the robot's height from the person's
PLACE_CHANGE = 0.25


def planned_trajectory(
    stream: StreamingRetargeter,
    motion: Motion,
    contacts=None,
    scaler=None,
    lookahead: float = 0.1,
    velocity_safety: float = 1.0,
) -> RobotTrajectory:
    """The clip retargeted frame by frame by ``stream`` (reset first), its planner seeing the
    person's contacts ``lookahead`` s early. ``contacts`` (T, 2) bool overrides the motion's;
    ``scaler`` a :class:`retarget.targets.KeypointScaler` (default: fitted on this clip); runs at
    ``velocity_safety`` of a speed limit are reported too (:func:`retarget.schedule.speed_limited`)."""
    stream.check_clip(motion)
    rb, fps = stream.robot, motion.fps
    tg = make_targets(rb, motion, contacts, scaler)
    person = np.array(tg.contacts, dtype=bool)
    keep_feet_down_in_flight(person, fps, [])  # a jump: the feet down before it stay down
    ahead = max(0, int(round(lookahead * fps)))
    seen = np.concatenate([person[ahead:], np.repeat(person[-1:], min(ahead, len(person)), axis=0)])
    t0 = time.perf_counter()
    stream.reset()
    X, held = [], []
    for t in range(motion.n_frames):
        X.append(stream.step(tg.keypoints[t], seen[t]))
        held.append(stream.planted.copy())
    X, held = np.stack(X), np.array(held)
    meta = {
        "mode": "offline",
        "engine": "planner",
        "source": motion.name,
        "lookahead_s": ahead / fps,
        "seconds": time.perf_counter() - t0,
        "contacts": held.astype(int).tolist(),  # the robot's schedule, (T, 2) 0/1
        "steps": {"person": count_steps(tg.contacts), "robot": count_steps(held)},
        "changes": what_changed(rb, X, tg, held, stream.planner, ahead, velocity_safety),
    }
    return trajectory_from_x(rb, X, fps, meta)


def what_changed(rb, X: np.ndarray, tg, held, planner, ahead: int = 0, velocity_safety: float = 1.0) -> list[dict]:
    """The changes (as dicts, by start time) of a planner's trajectory X (T, nx) against the person's
    :class:`retarget.targets.Targets` ``tg`` (keypoints, foot contacts, fps), with the robot's own
    contacts ``held`` (T, 2), the :class:`retarget.balance.BalancePlanner` that made it and its
    look-ahead ``ahead`` (frames): flights, ``own pace``, ``own place``, speed-limited runs and
    skipped steps."""
    cfg = planner.config
    flights: list[Change] = []
    fps = tg.fps
    person = np.array(tg.contacts, dtype=bool)
    keep_feet_down_in_flight(person, fps, flights)
    changes = flights + _changes(rb, X, tg.keypoints, fps, planner) + speed_limited(rb, X, fps, velocity_safety)
    changes += skipped_steps(person, np.asarray(held, dtype=bool), fps, cfg, ahead)
    return [c.to_dict() for c in sorted(changes, key=lambda c: c.start_s)]


def _changes(rb, X: np.ndarray, keypoints: np.ndarray, fps: float, planner) -> list[Change]:
    """Where the robot's pose or place differs from the person's (module constants)."""
    ev = rb.evaluate(X)
    kp, r = ev["keypoints"], rb.root_keypoint
    height = float(np.ptp(rb.evaluate(rb.x_stand[None])["keypoints"][0][:, 2]))
    pose = np.linalg.norm((kp - kp[:, r : r + 1]) - (keypoints - keypoints[:, r : r + 1]), axis=-1).mean(axis=1)
    place = np.linalg.norm(kp[:, r, 0:2] - keypoints[:, r, 0:2], axis=-1)
    out, toe_in = planner.turn_limits
    pace = f"{_quickest(planner.config)}, a foot turned at most {out:g} rad out and {toe_in:g} rad in per step"
    return changes_over(
        pose / height,
        POSE_CHANGE,
        fps,
        "own pace",
        f"the robot steps and turns at its own pace ({pace}) and keeps its weight over its feet: its pose "
        f"differed from the person's by more than {100 * POSE_CHANGE:g} % of its height",
    ) + changes_over(
        place / height,
        PLACE_CHANGE,
        fps,
        "own place",
        "the robot's feet stay where it put them (it does not slide, drift or turn on a planted foot, "
        f"and steps no further than its stride): its pelvis stood over {100 * PLACE_CHANGE:g} % of its "
        "height from the person's",
    )


def _quickest(cfg) -> str:
    """The robot's quickest step in words (``StreamingConfig`` phases at ``pace_floor``)."""
    k = cfg.pace_floor
    return (
        f"at its quickest {k * cfg.min_stance:.2g} s on a foot, {k * cfg.min_double:.2g} s on both, "
        f"a {k * cfg.step_shift:.2g} s weight shift and {k * cfg.min_swing:.2g} s swings"
    )


def skipped_steps(person: np.ndarray, robot: np.ndarray, fps: float, cfg, ahead: int = 0) -> list[Change]:
    """One ``step skipped`` Change per swing of the person's foot (contacts ``person`` (T, 2)
    bool) that no lift of the robot's same foot (``robot`` (T, 2)) answers. A lift may answer a
    swing from ``ahead`` frames (the look-ahead) + ``step_shift`` before it begins to
    ``step_shift`` + ``min_swing`` after it ends (a late step); each lift answers one swing, the
    latest one begun by then that is not answered yet."""
    person, robot = np.asarray(person, dtype=bool), np.asarray(robot, dtype=bool)
    T = len(person)
    early, late = ahead + round(cfg.step_shift * fps), round((cfg.step_shift + cfg.min_swing) * fps)
    why = (
        f"the person stepped faster than the robot's pace ({_quickest(cfg)}): the robot kept this foot "
        "down and caught up where the person's went"
    )
    out = []
    for s in range(2):
        swings = [(a, b) for a, b, down in bool_runs(person[:, s]) if not down]
        answered = [False] * len(swings)
        for lift in [a for a, _, down in bool_runs(robot[:, s]) if not down]:
            open_ = [i for i, (a, b) in enumerate(swings) if a - early <= lift <= b + late and not answered[i]]
            if open_:
                answered[max(open_, key=lambda i: swings[i][0])] = True
        for (a, b), done in zip(swings, answered):
            if not done and a > 0 and b < T:  # up at the clip's start or end is not a step
                out.append(Change(round(a / fps, 3), round(b / fps, 3), "step skipped", why))
    return out

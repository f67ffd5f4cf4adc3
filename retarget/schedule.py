"""The robot's foot-contact schedule, made from the person's, and what it changed.

Contract: :func:`robot_contacts` turns the person's side contacts (T, 2) bool (left, right)
into the robot's (T, 2), which the offline solver holds as hard constraints, and returns the
changes it made as :class:`Change` (start and end s, what, why): turns and slides become
re-steps, frames with both feet up keep the feet down, swings too short are filled, a foot
lifts no earlier than one frame after the other lands, a swing that has not landed by the
clip's last frame is not made, and the opt-in rules of :class:`StepConfig` (standing start,
the robot's pace). Lengths m, angles rad, times s. The rules in full: docs/retargeting.md,
section 5.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from retarget.targets import bool_runs


@dataclass(frozen=True)
class StepConfig:
    """Rules of :func:`robot_contacts` (see the module docstring)."""

    step_turn: float = 0.3  # rad
    step_distance: float = 0.04  # m, at robot scale
    swing: float = 0.3  # s
    min_stance: float = 0.25  # s
    min_swing: float = 0.1  # s
    # The robot's pace, the standing start, the start from rest and the eased travel are off by
    # default (0 / False): on the op3 in MuJoCo (bench/stepping.py, /tmp figures in the retarget
    # note) they did not raise the physics pass rate: they fixed the fall at the entry of a clip
    # that starts mid-step (cmu18_01: 0.21 s -> 0.95 s) but made cmu19_01 fall, which passes
    # without them. Values that were measured: min_double 0.13, start_double 0.4, robot_swing 0.13,
    # standing_start True, start_ramp 0.3, travel_zmp_shift 0.015. The swing clearance (0.02, on
    # by default) with the lead-in (retarget.lead_in, on by default, see OfflineConfig) took the
    # bench from 6/9 to 7/9 physics passes (cmu18_01 passes; with the lead-in alone it falls 1.07 s
    # into the clip, its first swing foot not landing); alone it changed no verdict
    min_double: float = 0.0  # s, both feet down before a lift (the weight shift)
    start_double: float = 0.0  # s, both feet down at the clip's start
    robot_swing: float = 0.0  # s, the shortest swing the robot makes
    # the offline solver's swing (retarget.offline.swing_floor): the sole clears the floor by this
    # share of the robot's standing height in a swing's middle frames (0.02: 9 mm on the op3);
    # lift-off and touch-down are vertical; 0: the sole only stays above the floor
    swing_clearance: float = 0.02
    standing_start: bool = False
    # the offline solver starts the clip from rest over this long (s; 0: at the clip's speed):
    # the robot stands still when the clip begins (retarget.offline.OfflineRetargeter.solve)
    start_ramp: float = 0.0
    # the pelvis target's horizontal acceleration is bounded so that it moves the ZMP at most this
    # far (m; retarget.shaping.ease_travel, from rest at the start); 0: the person's as it is
    travel_zmp_shift: float = 0.0


@dataclass(frozen=True)
class Change:
    """A part of a clip the robot plays differently from the person: seconds [start_s, end_s),
    ``what`` (a short label: ``flight``, ``pivot``, ``restep``, ...) and ``why`` (one sentence)."""

    start_s: float
    end_s: float
    what: str
    why: str

    def to_dict(self) -> dict:
        return {"start_s": self.start_s, "end_s": self.end_s, "what": self.what, "why": self.why}


def changes_over(value: np.ndarray, level: float, fps: float, what: str, why: str) -> list[Change]:
    """One Change per run of frames with ``value`` (T,) above ``level``."""
    return [
        Change(round(start / fps, 3), round(stop / fps, 3), what, why)
        for start, stop, over in bool_runs(np.asarray(value) > level)
        if over
    ]


def foot_poses(robot, keypoints: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Per frame, each foot's ankle xy (T, 2, 2) and heading (T, 2) rad (ankle → toe; the hips'
    facing for a profile without toe keypoints), from robot keypoint targets (T, K, 3); None
    for a robot without ankle keypoints."""
    names = list(robot.keypoint_names)
    if not all(n in names for n in ("left_ankle", "right_ankle")):
        return None
    kp = np.asarray(keypoints, dtype=np.float64)
    ank = kp[:, [names.index("left_ankle"), names.index("right_ankle")], 0:2]
    if all(n in names for n in ("left_foot", "right_foot")):
        toe = kp[:, [names.index("left_foot"), names.index("right_foot")], 0:2]
        d = toe - ank
        head = np.arctan2(d[..., 1], d[..., 0])
    elif all(n in names for n in ("left_hip", "right_hip")):
        across = kp[:, names.index("left_hip"), 0:2] - kp[:, names.index("right_hip"), 0:2]
        h = np.arctan2(-across[:, 0], across[:, 1])
        head = np.stack([h, h], axis=1)
    else:
        return None
    return ank, head


def robot_contacts(
    robot, keypoints: np.ndarray, contacts: np.ndarray, fps: float, config: StepConfig = StepConfig()
) -> tuple[np.ndarray, list[Change]]:
    """The robot's contacts (T, 2) bool and the changes made (see the module docstring).

    keypoints (T, K, 3) m: the robot-scale targets; contacts (T, 2) bool: the person's."""
    cfg = config
    c = np.array(contacts, dtype=bool, copy=True)
    T = c.shape[0]
    changes: list[Change] = []
    if T == 0:
        return c, changes
    keep_feet_down_in_flight(c, fps, changes)  # 1. both feet up -> the feet down before stay down
    # 2. fill swings shorter than min_swing (only between two stances of the same foot)
    n_swing = max(1, int(round(cfg.min_swing * fps)))
    for s in range(2):
        for a, b, v in bool_runs(c[:, s]):
            if not v and b - a < n_swing and a > 0 and b < T and c[a:b, 1 - s].all():
                c[a:b, s] = True
    # 3. the robot's pace: double support before every lift, no swing shorter than robot_swing
    c = _pace(c, fps, cfg, changes)
    # 4. pivots and slides on a planted foot -> re-steps
    poses = foot_poses(robot, keypoints)
    out = c
    if poses is not None:  # a profile without ankle keypoints has no foot poses to re-step on
        out = _restep_pivots(robot, poses, c, fps, cfg, changes)
        out = _pace(out, fps, cfg, changes)
    _double_support_at_each_switch(out)
    _land_unfinished_swings(out, fps, changes)
    changes.sort(key=lambda ch: ch.start_s)
    return out, changes


def _double_support_at_each_switch(c: np.ndarray) -> None:
    """In place on contacts c (T, 2) bool: a foot that would lift in the frame the other foot
    lands lifts one frame later, so that the weight moves from one foot to the other over at
    least one frame on both feet, never between two frames (no rule makes one by default; the
    person's own steps, a flight's end and a lead-in's held foot can). The swing is one frame
    shorter; not reported (33 ms at 30 fps).

    A switch in zero frames asks the offline solver for the CoM (or ZMP) over one foot in one
    frame and over the other in the next, with both feet where they land and lift (the swing
    clearance's vertical lift-off and touch-down hold them there): CMU 19_01 with the lead-in,
    the clearance and OfflineConfig(balance=True) stopped at IPOPT's iteration limit with
    1e-5 violations all over the window (25 iterations with the frame of double support)."""
    for t in range(1, c.shape[0]):
        for s in range(2):
            o = 1 - s
            if not c[t - 1, s] and c[t, s] and c[t - 1, o] and not c[t, o]:
                c[t, o] = True


def _land_unfinished_swings(c: np.ndarray, fps: float, changes: list) -> None:
    """In place on contacts c (T, 2) bool: a foot still in the air in the last frame (a swing
    that lands after the clip) stays down from its lift on; one "unfinished step" change each.

    Such a swing would end the trajectory with the robot on one foot, which it then has to hold
    still (the lead-in's reason for never standing at rest on one foot, retarget.lead_in), and it
    leaves the offline solver's last window ill-posed: its padding past the clip repeats the last
    frame's schedule, a foot held above the floor (swing_floor) for a whole padding (~1 s) while
    the posture term pulls the legs back to standing (make_leader(4.0, seed=4) with the lead-in
    and a swing clearance of 0.02: IPOPT at its iteration limit with the stance foot sliding
    and sinking 17 mm in the padding)."""
    T = c.shape[0]
    for s in range(2):
        if T == 0 or c[-1, s]:
            continue
        down = np.flatnonzero(c[:, s])
        lift = int(down[-1]) + 1 if down.size else 0
        c[lift:, s] = True
        changes.append(
            Change(
                round(lift / fps, 3),
                round(T / fps, 3),
                "unfinished step",
                f"the person's {('left', 'right')[s]} foot was still in the air at the clip's end "
                f"({(T - lift) / fps:.2f} s after it lifted); the robot kept it down rather than end on one foot",
            )
        )


def keep_feet_down_in_flight(c: np.ndarray, fps: float, changes: list) -> None:
    """In place on contacts c (T, 2) bool: frames with both feet up keep the feet that were down
    before (both at the start); one "flight" change per such run."""
    why = "both of the person's feet were off the ground (a jump or a run): the robot kept its feet down"
    T = c.shape[0]
    prev = np.array([True, True])
    start = None
    for t in range(T):
        if not c[t].any():
            if start is None:
                start = t
            c[t] = prev
        else:
            if start is not None:
                changes.append(Change(round(start / fps, 3), round(t / fps, 3), "flight", why))
                start = None
            prev = c[t].copy()
    if start is not None:
        changes.append(Change(round(start / fps, 3), round(T / fps, 3), "flight", why))


def _restep_pivots(robot, poses: tuple, c: np.ndarray, fps: float, cfg: StepConfig, changes: list) -> np.ndarray:
    """Contacts (T, 2) bool in which a planted foot the person turns more than ``step_turn`` or
    slides more than ``step_distance`` on lifts for a ``swing`` and comes down at its new place,
    once it has stood ``min_stance``, the other foot stands for the whole swing and the swing
    lands before the clip's last frame (else a pivot beyond twice the turn is reported). poses:
    the feet's ankle xy (T, 2, 2) m and heading (T, 2) rad."""
    ank, head = poses
    T = c.shape[0]
    start_n = int(round(cfg.start_double * fps))
    swing_n = max(1, int(round(cfg.swing * fps)))
    stance_n = max(1, int(round(cfg.min_stance * fps)))
    ref_xy = ank[0].copy()
    ref_h = head[0].copy()
    if cfg.standing_start:
        ref_xy, ref_h = _standing_footprint(robot, ank[0], head[0])
    since = np.zeros(2, dtype=int)  # frames since touch-down (planted) or lift
    lifted_until = np.full(2, -1)  # a re-step's swing ends at this frame (exclusive)
    pivot_start = [None, None]
    out = c.copy()
    for t in range(T):
        for s in range(2):
            if t < lifted_until[s]:
                out[t, s] = False
                continue
            if t > 0 and out[t, s] and not out[t - 1, s]:  # touch-down: new reference
                ref_xy[s], ref_h[s], since[s] = ank[t, s], head[t, s], 0
            if not out[t, s]:
                continue
            since[s] += 1
            turn = abs((head[t, s] - ref_h[s] + math.pi) % (2 * math.pi) - math.pi)
            slide = float(np.hypot(*(ank[t, s] - ref_xy[s])))
            if turn <= cfg.step_turn and slide <= cfg.step_distance:
                _end_pivot(changes, pivot_start, s, t, fps)
                continue
            o = 1 - s
            other_ok = (
                out[t, o] and t >= lifted_until[o] and since[o] >= stance_n and c[t : min(T, t + swing_n), o].all()
            )
            # a re-step lands inside the clip (one that would land after it is not started:
            # it would end the clip on one foot, see _land_unfinished_swings)
            if since[s] >= stance_n and other_ok and t >= start_n and t + swing_n < T:
                end = t + swing_n
                out[t:end, s] = False
                lifted_until[s] = end
                since[s] = 0
                _end_pivot(changes, pivot_start, s, t, fps)
            elif turn > 2 * cfg.step_turn and not out[t, o] and pivot_start[s] is None:
                pivot_start[s] = t
    for s in range(2):
        _end_pivot(changes, pivot_start, s, T, fps)
    return out


def _pace(c: np.ndarray, fps: float, cfg: StepConfig, changes: list) -> np.ndarray:
    """Contacts (T, 2) bool at the robot's pace (module docstring): a lift waits until both feet
    have been down ``min_double`` (``start_double`` from the first frame) and is skipped when the
    swing left is shorter than ``robot_swing``; appends a ``step skipped`` Change per skipped swing."""
    T = c.shape[0]
    out = c.copy()
    n_start = int(round(cfg.start_double * fps))
    n_double = int(round(cfg.min_double * fps))
    n_swing = max(1, int(round(cfg.robot_swing * fps)))
    double = 0  # frames both feet have been down (the robot's), up to the last frame
    lifted = np.zeros(2, dtype=bool)  # the robot's foot is in the air
    early = np.zeros(2, dtype=bool)  # ... lifted before the person's, which has not lifted yet
    skip_until = np.zeros(2, dtype=int)  # a skipped swing keeps the foot down until this frame
    for t in range(T):
        for s in range(2):
            if lifted[s]:
                if not c[t, s]:
                    early[s] = False
                elif not early[s]:  # the person's foot is down again: land
                    lifted[s] = False
                continue
            if t < skip_until[s]:
                continue
            o = 1 - s
            need = n_start if double == t else n_double  # still on both feet since the first frame
            if c[t, s]:
                # a person's swing shorter than the robot's starts early enough, where the double
                # support before it is long enough: lift n_swing frames before its landing
                if not lifted[o] and double >= need and _early_swing_fits(c, t, s, n_swing):
                    lifted[s] = early[s] = True
                continue
            # the person's foot is up and the robot's down: lift now, wait, or skip this swing
            a, end = _person_swing(c, t, s)
            side = ("left", "right")[s]
            if lifted[o] or double < need:
                if end - (t + 1) < n_swing:  # waiting one more frame leaves too short a swing
                    skip_until[s] = end
                    changes.append(
                        _step_skipped(
                            a,
                            end,
                            fps,
                            f"the person's {side} foot stepped faster than the robot "
                            f"can (it needs {cfg.min_double:g} s on both feet before a step and "
                            f"{cfg.robot_swing:g} s in the air); the robot's foot stayed down",
                        )
                    )
                continue
            if end - t < n_swing and end < T:
                skip_until[s] = end
                changes.append(
                    _step_skipped(
                        a,
                        end,
                        fps,
                        f"the person's {side} foot was up {(end - a) / fps:.2f} s, less "
                        f"than the robot's shortest swing ({cfg.robot_swing:g} s); the robot's foot "
                        "stayed down",
                    )
                )
                continue
            lifted[s] = True
        for s in range(2):
            out[t, s] = not lifted[s]
        double = double + 1 if out[t].all() else 0
    return out


def _early_swing_fits(c: np.ndarray, t: int, s: int, n_swing: int) -> bool:
    """Whether the person's foot ``s``, down at frame ``t`` of contacts ``c`` (T, 2), lifts
    within ``n_swing`` frames and lands exactly ``n_swing`` frames after ``t`` with the other
    foot down all along: a swing the robot can do by lifting at ``t``."""
    T = c.shape[0]
    a = t + 1
    while a < T and a < t + n_swing and c[a, s]:
        a += 1
    e = a
    while e < T and not c[e, s]:
        e += 1
    return bool(a < T and not c[a, s] and e < T and e - t == n_swing and c[t:e, 1 - s].all())


def _person_swing(c: np.ndarray, t: int, s: int) -> tuple[int, int]:
    """(lift frame, landing frame) of the person's swing of foot ``s`` that frame ``t`` is in
    (``c[t, s]`` False); the landing is T when the foot never comes down."""
    T = c.shape[0]
    end = t
    while end < T and not c[end, s]:
        end += 1
    a = t
    while a > 0 and not c[a - 1, s]:
        a -= 1
    return a, end


def _step_skipped(lift: int, landing: int, fps: float, why: str) -> Change:
    """The ``step skipped`` change over the person's swing from frame ``lift`` to ``landing``."""
    return Change(round(lift / fps, 3), round(landing / fps, 3), "step skipped", why)


def _standing_footprint(robot, ank0: np.ndarray, head0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The robot's standing feet (ankle xy (2, 2), heading (2,)) moved to stand centred on the
    person's first-frame ankles ``ank0`` (2, 2) and turned to their mean heading ``head0`` (2,)."""
    st = foot_poses(robot, robot.evaluate(robot.x_stand[None])["keypoints"])
    ank_s, head_s = st[0][0], st[1][0]
    mean = lambda h: math.atan2(np.sin(h).sum(), np.cos(h).sum())  # noqa: E731
    d = mean(head0) - mean(head_s)
    R = np.array([[math.cos(d), -math.sin(d)], [math.sin(d), math.cos(d)]])
    return ank0.mean(axis=0) + (ank_s - ank_s.mean(axis=0)) @ R.T, head_s + d


def standing_soles(robot, keypoints: np.ndarray) -> np.ndarray | None:
    """Where the robot's soles stand in its standing footprint centred on the person's first
    frame (:func:`_standing_footprint`): per foot (2, 4) its sole corner 0 xy and the sole
    diagonal (corner 2 − corner 0) xy, m; None for a robot without ankle keypoints."""
    poses = foot_poses(robot, keypoints)
    if poses is None:
        return None
    ev = robot.evaluate(robot.x_stand[None])
    st = foot_poses(robot, ev["keypoints"])
    ank_s, head_s = st[0][0], st[1][0]
    new_xy, new_h = _standing_footprint(robot, poses[0][0], poses[1][0])
    d = float(new_h[0] - head_s[0])
    R = np.array([[math.cos(d), -math.sin(d)], [math.sin(d), math.cos(d)]])
    sole = ev["sole"][0][:, 0:2]  # (8, 2)
    placed = new_xy.mean(axis=0) + (sole - ank_s.mean(axis=0)) @ R.T
    return np.array([np.concatenate([placed[4 * f], placed[4 * f + 2] - placed[4 * f]]) for f in range(2)])


def standing_start(robot, keypoints: np.ndarray, planned: np.ndarray) -> tuple[np.ndarray, int, float, float]:
    """Keypoint targets (T, K, 3) with each foot standing in the robot's standing footprint
    (:func:`_standing_footprint`) until its first lift in the schedule ``planned`` (T, 2): the
    ankle and toe targets move rigidly with the foot (turned about the ankle), the knee by half
    the shift. Returns the targets, the last frame changed + 1 (0: none) and how far the first
    frame's feet moved: the largest ankle shift (m) and turn (rad)."""
    poses = foot_poses(robot, keypoints)
    if poses is None:
        return keypoints, 0, 0.0, 0.0
    ank, head = poses
    new_xy, new_h = _standing_footprint(robot, ank[0], head[0])
    moved = float(np.max(np.linalg.norm(new_xy - ank[0], axis=1)))
    turned = float(np.max(np.abs((new_h - head[0] + math.pi) % (2 * math.pi) - math.pi)))
    names = list(robot.keypoint_names)
    out = np.array(keypoints, dtype=np.float64, copy=True)
    last = 0
    for s, side in enumerate(("left", "right")):
        up = np.flatnonzero(~np.asarray(planned[:, s], dtype=bool))
        n = int(up[0]) if up.size else len(planned)
        last = max(last, n)
        for t in range(n):
            d = new_h[s] - head[t, s]
            R = np.array([[math.cos(d), -math.sin(d)], [math.sin(d), math.cos(d)]])
            shift = new_xy[s] - ank[t, s]
            for j, share in (("ankle", 1.0), ("foot", 1.0), ("knee", 0.5)):
                name = f"{side}_{j}"
                if name in names:
                    k = names.index(name)
                    rel = out[t, k, 0:2] - ank[t, s]
                    there = ank[t, s] + (rel @ R.T if j != "knee" else rel) + shift
                    out[t, k, 0:2] = (1 - share) * out[t, k, 0:2] + share * there
    return out, last, moved, turned


def _end_pivot(changes: list, pivot_start: list, s: int, t: int, fps: float) -> None:
    """Close foot s's pivot (started at pivot_start[s], if any) at frame t as a Change."""
    if pivot_start[s] is None:
        return
    a = pivot_start[s]
    pivot_start[s] = None
    changes.append(
        Change(
            round(a / fps, 3),
            round(t / fps, 3),
            "pivot",
            f"the person turned on the {('left', 'right')[s]} foot alone (a spin faster than the robot's "
            "feet allow); the robot's foot stayed planted and its turn waited for the next step",
        )
    )


def count_steps(contacts: np.ndarray) -> int:
    """Touch-downs after the first frame: rising edges of the side contacts (T, 2)."""
    c = np.asarray(contacts, dtype=bool)
    return int(np.sum(c[1:] & ~c[:-1]))


def speed_limited(
    robot, X: np.ndarray, fps: float, safety: float = 1.0, share: float = 0.98, min_frames: int = 2, gap: int = 2
) -> list:
    """Parts where the solution runs at a speed limit: runs of at least ``min_frames`` frames
    (gaps up to ``gap`` frames bridged) in which some joint or root DOF moves at ``share`` of
    its velocity bound or more; there the robot follows the person at reduced amplitude. One
    :class:`retarget.schedule.Change` ("speed-limited", naming the joints) per run. X (T, nx)."""
    v = np.concatenate([robot.root_velocity_limits, robot.velocity_limits]) * safety / fps
    if X.shape[0] < 2:
        return []
    hit = np.abs(np.diff(X, axis=0)) >= share * v[None]  # (T-1, nx): frame t → t+1
    any_hit = hit.any(axis=1)
    names = ("root x", "root y", "root z", "root yaw", "root pitch", "root roll")[: robot.n_root] + tuple(
        robot.joint_names
    )
    out, t, T1 = [], 0, len(any_hit)
    while t < T1:
        if not any_hit[t]:
            t += 1
            continue
        e = t + 1
        while e < T1 and (any_hit[e] or any_hit[e : e + gap + 1].any()):
            e += 1
        if e - t >= min_frames:
            joints = [names[j] for j in np.flatnonzero(hit[t:e].any(axis=0))]
            out.append(
                Change(
                    round(t / fps, 3),
                    round((e + 1) / fps, 3),
                    "speed-limited",
                    f"{', '.join(joints[:4])}{' ...' if len(joints) > 4 else ''} at the servo's speed limit: "
                    "the robot follows the person at reduced amplitude",
                )
            )
        t = e
    return out

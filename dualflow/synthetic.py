"""SYNTHETIC two-person duets: a procedural leader and a rule-driven follower.

Nothing here is captured motion: it lets the generator be trained and tested without a
dataset and gives the bridge an actor offline. Contract: ``make_duet(rule, seconds, fps, seed,
varied=False)`` returns a deterministic :class:`TwoPersonMotion` (DESIGN.md frames: metres,
Z up, ground z = 0) whose leader steps on the beat with planted feet and exact bone lengths and
whose follower is a causal function of the leader, one of :data:`RULES` (mirror, follow,
hand_hold, orbit); ``pair.text`` is a template sentence and ``pair.meta`` holds the rule, bpm,
seed, template slots, beat frames and the (T, 4) beat track. numpy only. Details: docs/model.md.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from dualflow.errors import DualFlowError
from dualflow.motion.container import Motion, TwoPersonMotion
from dualflow.motion.kinematics import forward_kinematics, rest_offsets
from dualflow.motion.skeleton import MIRROR_INDEX, N_JOINTS, REST_POSE

#: Follower rules, in a fixed order (index = rule id used by data loaders).
RULES: tuple[str, ...] = ("mirror", "follow", "hand_hold", "orbit")

#: Leader slot values (template vocabulary).
STEP_STYLES: tuple[str, ...] = ("in_place", "side_sway")
ARM_STYLES: tuple[str, ...] = ("both", "left", "right", "alternate", "none")
TURN_STYLES: tuple[str, ...] = ("none", "left", "right", "spin")
TRAVEL_STYLES: tuple[str, ...] = ("stay", "approach_retreat")

FOLLOW_LAG_S = 0.5  # "follow": delay of the follower, seconds
FOLLOW_SIDE_M = 1.0  # "follow": lateral offset, metres (leader's initial left)
MIRROR_GAP_M = 1.3  # "mirror": pelvis-to-pelvis distance at the start, metres
HOLD_GAP_M = 1.0  # "hand_hold": constant pelvis-to-pelvis distance, metres
ORBIT_RADIUS_M = 1.1  # "orbit": circle radius, metres
ORBIT_BEATS_PER_TURN = 16  # "orbit": beats per full circle

_LEFT, _RIGHT = 0, 1
_HIP = (1, 2)
_KNEE = (4, 5)
_ANKLE = (7, 8)
_FOOT = (10, 11)
_SHOULDER = (16, 17)
_ELBOW = (18, 19)
_SPINE = (3, 6, 9)
_NECK, _HEAD = 12, 15

#: Rest-pose bone offset of each joint from its parent, (22, 3) metres.
_OFFSETS = rest_offsets()
_ANKLE_REST_Z = REST_POSE[7, 2]  # ankle height with the foot flat on the ground, m
_LEG_REACH = 0.985 * (np.linalg.norm(_OFFSETS[4]) + np.linalg.norm(_OFFSETS[7]))
_PELVIS_Z = 0.91  # standing pelvis height (knees slightly bent), m
_STEP_LIFT = 0.06  # swing-foot lift, m


# ---------------------------------------------------------------------------
# rotations and leg inverse kinematics
# ---------------------------------------------------------------------------
def _rot(axis: int, angle) -> np.ndarray:
    """Rotation matrices (..., 3, 3) about body axis 0=x, 1=y, 2=z by ``angle`` rad."""
    a = np.asarray(angle, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    out = np.zeros(a.shape + (3, 3))
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    out[..., axis, axis] = 1.0
    out[..., i, i] = c
    out[..., j, j] = c
    out[..., i, j] = -s
    out[..., j, i] = s
    return out


def _smoothstep(s):
    s = np.clip(s, 0.0, 1.0)
    return s * s * (3.0 - 2.0 * s)


def _two_bone_ik(hip_to_ankle_local: np.ndarray, forward_local: np.ndarray, side: int):
    """Hip and knee local rotations that put the ankle at ``hip_to_ankle_local``.

    hip_to_ankle_local: (T, 3) target ankle minus hip, in the pelvis frame, m.
    forward_local: (T, 3) unit direction the knee should point to (pelvis frame).
    Knee flexion is a rotation about the body y axis, R_y(a) with a ≥ 0 moving
    the ankle backwards. With thigh u and shin v offsets,
    |u + R_y(a) v|² = |u|² + |v|² + 2 u·R_y(a) v and u·R_y(a) v = A cos a + B sin a + C,
    so a = atan2(B, A) + arccos((K − C) / √(A² + B²)), K = (d² − |u|² − |v|²) / 2.
    The hip rotation maps the bent leg's hip→ankle direction onto the target
    direction with the knee turned towards ``forward_local`` (two aligned frames).
    Returns (R_hip, R_knee), each (T, 3, 3). Targets out of reach are clamped.
    """
    u = _OFFSETS[_KNEE[side]]
    v = _OFFSETS[_ANKLE[side]]
    d = np.linalg.norm(hip_to_ankle_local, axis=-1)
    d = np.clip(d, 0.2, _LEG_REACH)
    a_coef = u[0] * v[0] + u[2] * v[2]
    b_coef = u[0] * v[2] - u[2] * v[0]
    c_coef = u[1] * v[1]
    k = 0.5 * (d**2 - u @ u - v @ v)
    phi = np.arctan2(b_coef, a_coef)
    cos_arg = np.clip((k - c_coef) / np.hypot(a_coef, b_coef), -1.0, 1.0)
    # pick the branch with the knee bending forwards (0 <= a < pi)
    cand = np.stack([phi + np.arccos(cos_arg), phi - np.arccos(cos_arg)], axis=-1)
    cand = np.mod(cand + np.pi, 2 * np.pi) - np.pi
    flex = np.where(cand[..., 0] >= 0, cand[..., 0], cand[..., 1])
    flex = np.clip(flex, 0.0, 2.5)
    r_knee = _rot(1, flex)
    leg = u + np.einsum("tij,j->ti", r_knee, v)  # hip→ankle, hip frame

    def frame(primary, hint):
        e1 = primary / np.linalg.norm(primary, axis=-1, keepdims=True)
        e2 = hint - np.sum(hint * e1, axis=-1, keepdims=True) * e1
        e2 /= np.linalg.norm(e2, axis=-1, keepdims=True)
        return np.stack([e1, e2, np.cross(e1, e2)], axis=-1)  # columns e1 e2 e3

    x_axis = np.broadcast_to(np.array([1.0, 0.0, 0.0]), leg.shape)
    src = frame(leg, x_axis)
    dst = frame(hip_to_ankle_local, forward_local)
    r_hip = dst @ np.swapaxes(src, -1, -2)
    return r_hip, r_knee


# ---------------------------------------------------------------------------
# the procedural body
# ---------------------------------------------------------------------------
@dataclass(frozen=True)
class _BodyPlan:
    """Time functions that define one procedural dancer (t in seconds, arrays)."""

    centre: Callable[[np.ndarray], np.ndarray]  # (n,) -> (n, 2) pelvis x, y, m
    heading: Callable[[np.ndarray], np.ndarray]  # (n,) -> (n,) yaw, rad (0 = facing +X)
    arm_left: Callable[[np.ndarray], np.ndarray]  # (n,) -> (n,) shoulder raise, rad
    arm_right: Callable[[np.ndarray], np.ndarray]
    beat_times: np.ndarray  # (K,) seconds, beats covering the clip
    first_foot: int  # foot stepping on beat 0 (0 left, 1 right)
    steps_per_beat: int = 1  # 2 = double time (a step on every half beat)
    reach_left: Callable[[np.ndarray], np.ndarray] | None = None  # (n,) -> (n,) in [0, 1]: hand held out forward
    reach_right: Callable[[np.ndarray], np.ndarray] | None = None


@dataclass(frozen=True)
class Body:
    """A synthesised dancer: positions, contacts and the rotations that made them.

    positions (T, 22, 3) m; contacts (T, 4) bool (left ankle, left foot, right
    ankle, right foot); root_pos (T, 3) m; local_rot (T, 22, 3, 3).
    """

    positions: np.ndarray
    contacts: np.ndarray
    root_pos: np.ndarray
    local_rot: np.ndarray


def _foot_track(plan: _BodyPlan, side: int, times: np.ndarray, period: float):
    """Ankle target (T, 3), foot yaw (T,) and planted flag (T,) for one foot.

    Steps fall on the beat (or on every half beat in double time), feet
    alternating; a foot swings during the half step before it lands and is then
    planted for 1.5 steps, placed where its hip will be at mid-stance.
    """
    step = period / plan.steps_per_beat
    beats = plan.beat_times[0] + step * np.arange(len(plan.beat_times) * plan.steps_per_beat)
    mine = beats[(np.arange(len(beats)) + plan.first_foot + side) % 2 == 0]
    lateral = _OFFSETS[_HIP[side], 1] + (_OFFSETS[_KNEE[side], 1] + _OFFSETS[_ANKLE[side], 1])
    back = _OFFSETS[_KNEE[side], 0] + _OFFSETS[_ANKLE[side], 0]

    def placement(t):
        c = plan.centre(t)
        h = plan.heading(t)
        off_x = back * np.cos(h) - lateral * np.sin(h)
        off_y = back * np.sin(h) + lateral * np.cos(h)
        return np.stack([c[:, 0] + off_x, c[:, 1] + off_y], axis=-1), h

    land_t = np.concatenate([[-np.inf], mine])
    # a foot is planted for 1.5 beats; it lands where its hip will be at mid-stance
    place_xy, place_yaw = placement(np.concatenate([[0.0], mine + 0.75 * step]))
    place_yaw = np.unwrap(place_yaw)
    swing = 0.5 * step
    k = np.searchsorted(mine, times, side="right")  # landings done by time t
    prev_xy, prev_yaw = place_xy[k], place_yaw[k]
    nxt = np.minimum(k + 1, len(land_t) - 1)
    next_t = np.where(k + 1 < len(land_t), land_t[nxt], np.inf)
    s = np.where(np.isfinite(next_t), (times - (next_t - swing)) / swing, -1.0)
    in_swing = (s > 0.0) & (s < 1.0)
    w = _smoothstep(np.where(in_swing, s, 0.0))[:, None]
    xy = (1 - w) * prev_xy + w * place_xy[nxt]
    yaw = (1 - w[:, 0]) * prev_yaw + w[:, 0] * place_yaw[nxt]
    z = _ANKLE_REST_Z + _STEP_LIFT * np.where(in_swing, np.sin(np.pi * s), 0.0)
    return np.column_stack([xy, z]), yaw, ~in_swing


def _synthesise(plan: _BodyPlan, times: np.ndarray, period: float, rng_phase: float) -> Body:
    """Joint rotations for a plan, then forward kinematics (see module docstring)."""
    n = len(times)
    heading = plan.heading(times)
    centre = plan.centre(times)
    r_pelvis = _rot(2, heading)

    feet = [_foot_track(plan, side, times, period) for side in (_LEFT, _RIGHT)]

    # pelvis height: a small dip on every beat, lowered further if a foot would be out of reach
    beat_phase = _beat_phase(times, plan.beat_times)
    pelvis_z = _PELVIS_Z - 0.02 * (0.5 + 0.5 * np.cos(2 * np.pi * beat_phase))
    for side, (ankle, _, _) in zip((_LEFT, _RIGHT), feet):
        hip_xy = centre + np.einsum("tij,j->ti", r_pelvis, _OFFSETS[_HIP[side]])[:, :2]
        horiz = np.linalg.norm(ankle[:, :2] - hip_xy, axis=-1)
        reach_z = np.sqrt(np.maximum(_LEG_REACH**2 - np.minimum(horiz, 0.95 * _LEG_REACH) ** 2, 0.0))
        pelvis_z = np.minimum(pelvis_z, ankle[:, 2] + reach_z - _OFFSETS[_HIP[side], 2] - 1e-3)
    root_pos = np.column_stack([centre, pelvis_z])

    local = np.broadcast_to(np.eye(3), (n, N_JOINTS, 3, 3)).copy()
    local[:, 0] = r_pelvis
    # legs: two-bone IK for the ankle, then the foot held flat along its own yaw
    for side, (ankle, yaw, _) in zip((_LEFT, _RIGHT), feet):
        hip_world = root_pos + np.einsum("tij,j->ti", r_pelvis, _OFFSETS[_HIP[side]])
        target = np.einsum("tji,tj->ti", r_pelvis, ankle - hip_world)
        fwd = np.column_stack([np.cos(yaw - heading), np.sin(yaw - heading), np.zeros(n)])
        r_hip, r_knee = _two_bone_ik(target, fwd, side)
        local[:, _HIP[side]] = r_hip
        local[:, _KNEE[side]] = r_knee
        parent_glob = r_pelvis @ r_hip @ r_knee
        local[:, _ANKLE[side]] = np.swapaxes(parent_glob, -1, -2) @ _rot(2, yaw)
    # upper body: a spine twist with the arms, a nod on the beat, arm waves
    arm_l = plan.arm_left(times)
    arm_r = plan.arm_right(times)
    twist = 0.08 * np.sin(2 * np.pi * (beat_phase / 2.0 + rng_phase)) / 3.0
    for j in _SPINE:
        local[:, j] = _rot(2, twist)
    local[:, _HEAD] = _rot(1, 0.06 * (0.5 + 0.5 * np.cos(2 * np.pi * beat_phase)))
    bend_l = 0.3 + 0.35 * (arm_l - _ARM_DOWN)
    bend_r = 0.3 + 0.35 * (arm_r - _ARM_DOWN)
    if plan.reach_left is None and plan.reach_right is None:
        local[:, _SHOULDER[_LEFT]] = _rot(0, arm_l)
        local[:, _SHOULDER[_RIGHT]] = _rot(0, -arm_r)
    else:  # a hand held out forward: blend the raise towards _REACH_RAISE and swing the arm to the front
        zero = np.zeros(n)
        w_l = zero if plan.reach_left is None else _smoothstep(plan.reach_left(times))
        w_r = zero if plan.reach_right is None else _smoothstep(plan.reach_right(times))
        arm_l = (1 - w_l) * arm_l + w_l * _REACH_RAISE
        arm_r = (1 - w_r) * arm_r + w_r * _REACH_RAISE
        local[:, _SHOULDER[_LEFT]] = _rot(2, -_REACH_SWING * w_l) @ _rot(0, arm_l)
        local[:, _SHOULDER[_RIGHT]] = _rot(2, _REACH_SWING * w_r) @ _rot(0, -arm_r)
        bend_l = (1 - w_l) * bend_l + w_l * 0.15
        bend_r = (1 - w_r) * bend_r + w_r * 0.15
    local[:, _ELBOW[_LEFT]] = _rot(2, -bend_l)
    local[:, _ELBOW[_RIGHT]] = _rot(2, bend_r)

    positions = forward_kinematics(root_pos, local)
    contacts = np.column_stack([feet[0][2], feet[0][2], feet[1][2], feet[1][2]])
    return Body(positions=positions, contacts=contacts, root_pos=root_pos, local_rot=local)


_ARM_DOWN = -1.25  # shoulder raise of a relaxed arm, rad (0 = T-pose, arm horizontal)
_REACH_RAISE = -0.35  # shoulder raise of a hand held out to the partner (slightly below horizontal), rad
_REACH_SWING = 1.3  # swing of that arm from the side to the front about the vertical, rad


def _beat_phase(times: np.ndarray, beat_times: np.ndarray) -> np.ndarray:
    """Fraction of the current beat elapsed, in [0, 1) (0 on a beat)."""
    period = beat_times[1] - beat_times[0]
    return np.mod((times - beat_times[0]) / period, 1.0)


# ---------------------------------------------------------------------------
# the leader
# ---------------------------------------------------------------------------
@dataclass(frozen=True)
class LeaderClip:
    """A synthetic leader with everything a follower rule needs.

    body: the synthesised :class:`Body`; plan: its time functions; times (T,) s;
    bpm; beat_times (K,) s; slots: template slot values; origin (2,) m and
    heading0 rad: where the leader starts and which way it faces.
    """

    body: Body
    plan: _BodyPlan
    times: np.ndarray
    fps: float
    bpm: float
    beat_times: np.ndarray
    slots: dict
    origin: np.ndarray
    heading0: float


def _check_clip_args(seconds: float, fps: float) -> int:
    try:
        seconds, fps = float(seconds), float(fps)
    except (TypeError, ValueError):
        raise DualFlowError(f"synthetic clip: seconds and fps must be numbers, got {seconds!r}, {fps!r}") from None
    if not np.isfinite(fps) or fps <= 0:
        raise DualFlowError(f"synthetic clip: fps must be > 0, got {fps!r}")
    if not np.isfinite(seconds) or seconds <= 0:
        raise DualFlowError(f"synthetic clip: seconds must be > 0, got {seconds!r}")
    return max(int(round(seconds * fps)), 2)


def _draw_slots(rng: np.random.Generator) -> dict[str, str]:
    """One style per slot (step, arms, turn, travel), drawn in that order from ``rng``."""
    return {
        "step": STEP_STYLES[rng.integers(len(STEP_STYLES))],
        "arms": ARM_STYLES[rng.integers(len(ARM_STYLES))],
        "turn": TURN_STYLES[rng.integers(len(TURN_STYLES))],
        "travel": TRAVEL_STYLES[rng.integers(len(TRAVEL_STYLES))],
    }


def _heading_curve(turn: str, heading0: float, turn_start: float, spin_len: float, period: float):
    """Facing yaw (rad) as a function of time (s, array): constant, one full spin over ``spin_len``,
    or a quarter turn left/right and back every 8 beats, starting at ``turn_start``."""

    def heading(t):
        t = np.asarray(t, dtype=np.float64)
        if turn == "none":
            return np.full(t.shape, heading0)
        if turn == "spin":
            return heading0 + 2 * np.pi * _smoothstep((t - turn_start) / spin_len)
        sign = 1.0 if turn == "left" else -1.0
        return heading0 + sign * 0.5 * np.pi * (
            0.5 - 0.5 * np.cos(2 * np.pi * np.maximum(t - turn_start, 0.0) / (8 * period))
        )

    return heading


def _centre_curve(
    heading, heading0: float, origin, travel_amp: float, sway_amp: float, first_beat: float, period: float
):
    """Ground position (m, (T, 2)) of the body centre over time (s, (T,)): ``origin`` plus a travel
    along the initial facing (8-beat period) and a sideways sway (one side per beat)."""

    def centre(t):
        t = np.asarray(t, dtype=np.float64)
        h0 = np.array([np.cos(heading0), np.sin(heading0)])
        fwd = travel_amp * np.sin(2 * np.pi * t / (8 * period))
        lat = sway_amp * np.sin(np.pi * (t - first_beat) / period)
        h = heading(t)
        left = np.stack([-np.sin(h), np.cos(h)], axis=-1)
        return origin + fwd[:, None] * h0 + lat[:, None] * left

    return centre


def _arm_curves(arms: str, wave_amp: float, first_beat: float, period: float):
    """(left, right) arm raise angle (rad) over time (s): a 2-beat wave, in phase for "both" and
    half a cycle apart for "alternate", or held just off the side for an arm that does not wave."""

    def wave(t, phase_beats):
        t = np.asarray(t, dtype=np.float64)
        return _ARM_DOWN + wave_amp * (
            0.5 - 0.5 * np.cos(2 * np.pi * (t - first_beat) / (2 * period) + np.pi * phase_beats)
        )

    still = lambda t: np.full(np.shape(t), _ARM_DOWN + 0.1)  # noqa: E731
    arm_left = (lambda t: wave(t, 0.0)) if arms in ("both", "left", "alternate") else still
    if arms in ("both", "right"):
        arm_right = lambda t: wave(t, 0.0)  # noqa: E731
    elif arms == "alternate":
        arm_right = lambda t: wave(t, 1.0)  # noqa: E731
    else:
        arm_right = still
    return arm_left, arm_right


def make_leader_clip(seconds: float = 4.0, fps: float = 30.0, seed: int = 0, bpm: float | None = None) -> LeaderClip:
    """Synthesise a leader clip (see the module docstring for what it does).

    seconds: clip length; fps: frame rate; seed: makes the clip reproducible;
    bpm: tempo in beats per minute (default: drawn from 90-130 by the seed).
    """
    n = _check_clip_args(seconds, fps)
    rng = np.random.default_rng([int(seed), 1])
    bpm_drawn = float(rng.uniform(90.0, 130.0))
    bpm = bpm_drawn if bpm is None else float(bpm)
    if not np.isfinite(bpm) or not 30.0 <= bpm <= 240.0:
        raise DualFlowError(f"synthetic leader: bpm must be within 30-240, got {bpm!r}")
    period = 60.0 / bpm
    slots = _draw_slots(rng)
    heading0 = float(rng.uniform(-np.pi, np.pi))
    origin = rng.uniform(-0.5, 0.5, size=2)
    first_beat = float(rng.uniform(0.0, period))
    first_foot = int(rng.integers(2))
    sway_amp = float(rng.uniform(0.06, 0.12)) if slots["step"] == "side_sway" else 0.0
    travel_amp = float(rng.uniform(0.2, 0.35)) if slots["travel"] == "approach_retreat" else 0.0
    wave_amp = float(rng.uniform(1.0, 1.8))
    twist_phase = float(rng.uniform(0.0, 1.0))
    duration = n / fps
    beat_times = first_beat - period + period * np.arange(int(np.ceil((duration + 2 * period) / period)) + 2)
    turn_start = first_beat + period
    spin_len = max(16 * period, duration - turn_start)
    heading = _heading_curve(slots["turn"], heading0, turn_start, spin_len, period)
    centre = _centre_curve(heading, heading0, origin, travel_amp, sway_amp, first_beat, period)
    arm_left, arm_right = _arm_curves(slots["arms"], wave_amp, first_beat, period)

    plan = _BodyPlan(
        centre=centre,
        heading=heading,
        arm_left=arm_left,
        arm_right=arm_right,
        beat_times=beat_times,
        first_foot=first_foot,
    )
    times = np.arange(n) / fps
    body = _synthesise(plan, times, period, twist_phase)
    return LeaderClip(
        body=body,
        plan=plan,
        times=times,
        fps=float(fps),
        bpm=bpm,
        beat_times=beat_times,
        slots=slots,
        origin=origin,
        heading0=heading0,
    )


def make_leader(seconds: float = 4.0, fps: float = 30.0, seed: int = 0, bpm: float | None = None) -> Motion:
    """A synthetic leader (actor) as a :class:`Motion`, e.g. for the bridge's
    offline actor source. Same arguments as :func:`make_leader_clip`."""
    clip = make_leader_clip(seconds, fps, seed, bpm)
    return Motion(
        positions=clip.body.positions,
        fps=clip.fps,
        contacts=clip.body.contacts,
        name=f"synthetic_leader_seed{int(seed)}",
    )


# ---------------------------------------------------------------------------
# follower rules
# ---------------------------------------------------------------------------
_CONTACT_MIRROR = [2, 3, 0, 1]  # (l_ankle, l_foot, r_ankle, r_foot) -> swapped sides


def _reflect(positions: np.ndarray, point: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Mirror image of (T, 22, 3) positions in the vertical plane through
    ``point`` (T, 2) with horizontal unit ``normal`` (T, 2), left/right joints
    relabelled so the result is a valid, right-handed-labelled skeleton:
    p' = p − 2((p − q)·n) n."""
    q = np.concatenate([point, np.zeros((len(point), 1))], axis=-1)[:, None, :]
    nrm = np.concatenate([normal, np.zeros((len(normal), 1))], axis=-1)[:, None, :]
    dist = np.sum((positions - q) * nrm, axis=-1, keepdims=True)
    return (positions - 2.0 * dist * nrm)[:, list(MIRROR_INDEX)]


def _follower(rule: str, clip: LeaderClip, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    body, n = clip.body, len(clip.times)
    h0 = np.array([np.cos(clip.heading0), np.sin(clip.heading0)])
    if rule == "mirror":
        point = np.broadcast_to(clip.origin + 0.5 * MIRROR_GAP_M * h0, (n, 2))
        pos = _reflect(body.positions, point, np.broadcast_to(h0, (n, 2)))
        return pos, body.contacts[:, _CONTACT_MIRROR]
    if rule == "hand_hold":
        gap = HOLD_GAP_M

        def centre(t):
            h = clip.plan.heading(t)
            return clip.plan.centre(t) + gap * np.stack([np.cos(h), np.sin(h)], axis=-1)

        plan = _BodyPlan(
            centre=centre,
            heading=lambda t: clip.plan.heading(t) + np.pi,
            arm_left=clip.plan.arm_right,
            arm_right=clip.plan.arm_left,
            beat_times=clip.beat_times,
            first_foot=1 - clip.plan.first_foot,
            steps_per_beat=2,
        )
        fbody = _synthesise(plan, clip.times, clip.beat_times[1] - clip.beat_times[0], float(rng.uniform()))
        return fbody.positions, fbody.contacts
    if rule == "follow":
        lag = int(round(FOLLOW_LAG_S * clip.fps))
        src = np.maximum(np.arange(n) - lag, 0)
        left0 = np.array([-h0[1], h0[0], 0.0])
        return body.positions[src] + FOLLOW_SIDE_M * left0, body.contacts[src]
    if rule == "orbit":
        period = clip.beat_times[1] - clip.beat_times[0]
        turn_s = ORBIT_BEATS_PER_TURN * period

        def angle(t):
            return clip.heading0 + 2 * np.pi * np.asarray(t, dtype=np.float64) / turn_s

        def centre(t):
            a = angle(t)
            return clip.plan.centre(t) + ORBIT_RADIUS_M * np.stack([np.cos(a), np.sin(a)], axis=-1)

        plan = _BodyPlan(
            centre=centre,
            heading=lambda t: angle(t) + np.pi,
            arm_left=clip.plan.arm_right,
            arm_right=clip.plan.arm_left,
            beat_times=clip.beat_times,
            first_foot=1 - clip.plan.first_foot,
            steps_per_beat=2,
        )
        fbody = _synthesise(plan, clip.times, period, float(rng.uniform()))
        return fbody.positions, fbody.contacts
    raise DualFlowError(f"synthetic duet: unknown rule {rule!r}; choose one of {', '.join(RULES)}")


# ---------------------------------------------------------------------------
# text and beats
# ---------------------------------------------------------------------------
_STEP_TEXT = {"in_place": "steps in place on the beat", "side_sway": "steps side to side on the beat"}
_ARM_TEXT = {
    "both": "waving both arms",
    "left": "waving the left arm",
    "right": "waving the right arm",
    "alternate": "waving the arms in turn",
    "none": "with the arms down",
}
_TURN_TEXT = {
    "none": "",
    "left": ", turns a quarter to the left and back",
    "right": ", turns a quarter to the right and back",
    "spin": ", spins once around",
}
_TRAVEL_TEXT = {"stay": "", "approach_retreat": ", moves towards the partner and back"}
_RULE_TEXT = {
    "mirror": "the partner mirrors the leader face to face.",
    "follow": "the partner copies the leader half a second later, standing beside them.",
    "hand_hold": "the partner keeps a hand-hold distance facing the leader and moves with them.",
    "orbit": "the partner circles around the leader, copying the arm waves.",
}


def _tempo_word(bpm: float) -> str:
    return "slow" if bpm < 103 else ("medium" if bpm < 117 else "fast")


def describe(slots: dict, rule: str, bpm: float) -> str:
    """Template text of a clip: leader's steps, arms, turn, travel, tempo; the rule."""
    return (
        f"The leader {_STEP_TEXT[slots['step']]} {_ARM_TEXT[slots['arms']]}"
        f"{_TURN_TEXT[slots['turn']]}{_TRAVEL_TEXT[slots['travel']]} "
        f"to {_tempo_word(bpm)} music; {_RULE_TEXT[rule]}"
    )


def beat_features(times: np.ndarray, beat_times: np.ndarray, fps: float) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame beat features (T, 4) float32 and the beat frame indices.

    Columns: [beat impulse (1 on the frame nearest a beat), sin(2π·phase),
    cos(2π·phase), downbeat impulse (first beat of each bar of 4)], phase ∈ [0, 1)
    the fraction of the current beat elapsed.
    """
    n = len(times)
    phase = _beat_phase(times, beat_times)
    inside = beat_times[(beat_times >= -0.5 / fps) & (beat_times < n / fps - 0.5 / fps)]
    frames = np.clip(np.rint(inside * fps).astype(np.int64), 0, n - 1)
    beat_index = np.rint((inside - beat_times[0]) / (beat_times[1] - beat_times[0])).astype(np.int64)
    feats = np.zeros((n, 4), dtype=np.float32)
    feats[frames, 0] = 1.0
    feats[:, 1] = np.sin(2 * np.pi * phase)
    feats[:, 2] = np.cos(2 * np.pi * phase)
    feats[frames[beat_index % 4 == 1], 3] = 1.0
    return feats, frames


# ---------------------------------------------------------------------------
# public entry point
# ---------------------------------------------------------------------------
def make_duet(
    rule: str = "mirror", seconds: float = 4.0, fps: float = 30.0, seed: int = 0, varied: bool = False
) -> TwoPersonMotion:
    """A SYNTHETIC two-person clip: procedural leader (actor) + rule-driven follower (reactor).

    rule: one of :data:`RULES`; seconds: length; fps: frame rate; seed: the clip
    is a deterministic function of (rule, seconds, fps, seed). Returns a
    :class:`TwoPersonMotion` in the Z-up world frame with ``text`` and ``meta``
    as described in the module docstring. varied: the wider repertoire of
    :mod:`dualflow.synthetic_varied` (walking up, turning to a side, reaching out a hand,
    followers that keep a personal distance, mirrored duets); False gives the classic clips.
    """
    if rule not in RULES:
        raise DualFlowError(f"synthetic duet: unknown rule {rule!r}; choose one of {', '.join(RULES)}")
    if varied:
        from dualflow.synthetic_varied import make_varied_duet

        return make_varied_duet(rule, seconds, fps, seed)
    clip = make_leader_clip(seconds, fps, seed)
    rng = np.random.default_rng([int(seed), 2, RULES.index(rule)])
    f_pos, f_contacts = _follower(rule, clip, rng)
    beats, beat_frames = beat_features(clip.times, clip.beat_times, clip.fps)
    actor = Motion(
        positions=clip.body.positions,
        fps=clip.fps,
        contacts=clip.body.contacts,
        name=f"synthetic_{rule}_seed{int(seed)}_leader",
    )
    reactor = Motion(
        positions=f_pos, fps=clip.fps, contacts=f_contacts, name=f"synthetic_{rule}_seed{int(seed)}_follower"
    )
    meta = {
        "synthetic": True,
        "rule": rule,
        "bpm": clip.bpm,
        "seed": int(seed),
        "slots": dict(clip.slots),
        "beats": beats,
        "beat_frames": beat_frames,
    }
    return TwoPersonMotion(actor=actor, reactor=reactor, text=describe(clip.slots, rule, clip.bpm), meta=meta)

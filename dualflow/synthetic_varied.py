"""A wider repertoire of SYNTHETIC duets: leaders that walk up, turn and reach out a hand,
followers that respond to them, and mirrored copies.

Made up by a program like :mod:`dualflow.synthetic` (same body synthesis, rules, layout and
``meta``; ``make_duet(..., varied=True)``), for training a partner that reacts to a real actor
rather than to one template: wider tempi, travel, turns and held-out hands; follower parameters
drawn per clip (one leader, many right answers); half the clips mirrored left-right. Every
follower is causal; clips are deterministic in (rule, seconds, fps, seed). numpy only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dualflow.motion.container import Motion, TwoPersonMotion
from dualflow.synthetic import (
    _ARM_DOWN,
    _ARM_TEXT,
    _CONTACT_MIRROR,
    _RULE_TEXT,
    _STEP_TEXT,
    _TRAVEL_TEXT,
    _TURN_TEXT,
    LeaderClip,
    _BodyPlan,
    _check_clip_args,
    _reflect,
    _smoothstep,
    _synthesise,
    _tempo_word,
    beat_features,
)

VARIED_ARMS = ("both", "left", "right", "alternate", "none", "reach_left", "reach_right")
VARIED_TURNS = ("none", "left", "right", "turn_to")
VARIED_TRAVEL = ("stay", "approach_retreat", "walk_up")

_ARM_WORDS = dict(_ARM_TEXT, reach_left="holding the left hand out", reach_right="holding the right hand out")
_TURN_WORDS = dict(_TURN_TEXT, turn_to=", turns to one side")
_TRAVEL_WORDS = dict(_TRAVEL_TEXT, walk_up=", walks up to the partner")


def _window(t: np.ndarray, start: float, hold: float, ramp: float = 0.4) -> np.ndarray:
    """Weight in [0, 1]: 0 before ``start``, ramps to 1 over ``ramp`` s, back to 0 after ``start + hold``."""
    up = np.clip((t - start) / ramp, 0.0, 1.0)
    down = np.clip((start + hold - t) / ramp, 0.0, 1.0)
    return np.minimum(up, down)


@dataclass(frozen=True)
class _VariedDraws:
    """The random choices of one varied leader (times in s, angles in rad, distances in m) and the
    body curves they define; ``draw`` takes them from the generator in a fixed order."""

    bpm: float
    slots: dict
    heading0: float
    origin: np.ndarray
    first_beat: float
    first_foot: int
    sway: float
    travel_amp: float
    walk_d: float
    walk_v: float
    walk_t0: float
    turn_ang: float
    turn_t0: float
    turn_len: float
    wave_amp: float
    reach_t0: float
    reach_hold: float
    twist_phase: float

    @property
    def period(self) -> float:
        return 60.0 / self.bpm

    @classmethod
    def draw(cls, rng: np.random.Generator, duration: float) -> _VariedDraws:
        bpm = float(rng.uniform(70.0, 150.0))
        period = 60.0 / bpm
        slots = {
            "step": ("in_place", "side_sway")[rng.integers(2)],
            "arms": VARIED_ARMS[rng.integers(len(VARIED_ARMS))],
            "turn": VARIED_TURNS[rng.integers(len(VARIED_TURNS))],
            "travel": VARIED_TRAVEL[rng.choice(3, p=[0.3, 0.2, 0.5])],
        }
        heading0 = float(rng.uniform(-np.pi, np.pi))
        origin = rng.uniform(-0.5, 0.5, size=2)
        first_beat = float(rng.uniform(0.0, period))
        first_foot = int(rng.integers(2))
        sway = float(rng.uniform(0.04, 0.1)) if slots["step"] == "side_sway" else 0.0
        travel_amp = float(rng.uniform(0.2, 0.35))
        walk_d, walk_v = float(rng.uniform(0.4, 1.0)), float(rng.uniform(0.6, 1.2))
        walk_t0 = float(rng.uniform(-0.5, 0.5 * duration))
        turn_ang = float(rng.choice([-1.0, 1.0]) * rng.uniform(0.5, 2.0))
        turn_t0, turn_len = float(rng.uniform(-0.3, 0.6 * duration)), float(rng.uniform(0.6, 1.5))
        wave_amp = float(rng.uniform(0.8, 1.8))
        reach_t0, reach_hold = float(rng.uniform(-0.5, 0.6 * duration)), float(rng.uniform(0.8, 2.5))
        twist_phase = float(rng.uniform(0.0, 1.0))
        return cls(
            bpm,
            slots,
            heading0,
            origin,
            first_beat,
            first_foot,
            sway,
            travel_amp,
            walk_d,
            walk_v,
            walk_t0,
            turn_ang,
            turn_t0,
            turn_len,
            wave_amp,
            reach_t0,
            reach_hold,
            twist_phase,
        )

    def heading(self, t):
        """Facing yaw (rad) at times ``t`` (s)."""
        t = np.asarray(t, dtype=np.float64)
        turn = self.slots["turn"]
        if turn == "none":
            return np.full(t.shape, self.heading0)
        if turn == "turn_to":
            return self.heading0 + self.turn_ang * _smoothstep((t - self.turn_t0) / self.turn_len)
        sign = 1.0 if turn == "left" else -1.0
        return self.heading0 + sign * 0.5 * np.pi * (
            0.5 - 0.5 * np.cos(2 * np.pi * np.maximum(t - self.first_beat, 0.0) / (8 * self.period))
        )

    def centre(self, t):
        """Ground position (m, (T, 2)) of the body centre at times ``t`` (s, (T,))."""
        t = np.asarray(t, dtype=np.float64)
        h0 = np.array([np.cos(self.heading0), np.sin(self.heading0)])
        if self.slots["travel"] == "walk_up":
            fwd = -self.walk_d * (1.0 - _smoothstep((t - self.walk_t0) * self.walk_v / (1.5 * self.walk_d)))
        elif self.slots["travel"] == "approach_retreat":
            fwd = self.travel_amp * np.sin(2 * np.pi * t / (8 * self.period))
        else:
            fwd = np.zeros(t.shape)
        lat = self.sway * np.sin(np.pi * (t - self.first_beat) / self.period)
        h = self.heading(t)
        left = np.stack([-np.sin(h), np.cos(h)], axis=-1)
        return self.origin + fwd[:, None] * h0 + lat[:, None] * left

    def arm_curves(self):
        """(left, right) arm raise angle (rad) over time (s): a 2-beat wave or held off the side."""
        period, first_beat, wave_amp = self.period, self.first_beat, self.wave_amp

        def wave(phase_beats):
            return lambda t: (
                _ARM_DOWN
                + wave_amp
                * (
                    0.5
                    - 0.5
                    * np.cos(
                        2 * np.pi * (np.asarray(t, dtype=np.float64) - first_beat) / (2 * period) + np.pi * phase_beats
                    )
                )
            )

        still = lambda t: np.full(np.shape(t), _ARM_DOWN + 0.1)  # noqa: E731
        arms = self.slots["arms"]
        arm_left = wave(0.0) if arms in ("both", "left", "alternate") else still
        arm_right = wave(0.0) if arms in ("both", "right") else (wave(1.0) if arms == "alternate" else still)
        return arm_left, arm_right

    def reach(self, t):
        """0-1 weight of the held-out hand at times ``t`` (s)."""
        return _window(np.asarray(t, dtype=np.float64), self.reach_t0, self.reach_hold)


def make_varied_leader(seconds: float, fps: float, seed: int) -> LeaderClip:
    """A leader of the wider repertoire (module docstring); deterministic in (seconds, fps, seed)."""
    n = _check_clip_args(seconds, fps)
    rng = np.random.default_rng([int(seed), 3])
    duration = n / fps
    d = _VariedDraws.draw(rng, duration)
    period = d.period
    beat_times = d.first_beat - period + period * np.arange(int(np.ceil((duration + 2 * period) / period)) + 2)
    arm_left, arm_right = d.arm_curves()
    arms = d.slots["arms"]
    plan = _BodyPlan(
        centre=d.centre,
        heading=d.heading,
        arm_left=arm_left,
        arm_right=arm_right,
        beat_times=beat_times,
        first_foot=d.first_foot,
        reach_left=d.reach if arms == "reach_left" else None,
        reach_right=d.reach if arms == "reach_right" else None,
    )
    times = np.arange(n) / fps
    body = _synthesise(plan, times, period, d.twist_phase)
    return LeaderClip(
        body=body,
        plan=plan,
        times=times,
        fps=float(fps),
        bpm=d.bpm,
        beat_times=beat_times,
        slots=d.slots,
        origin=d.origin,
        heading0=d.heading0,
    )


def _lagged(fn, lag: float):
    return None if fn is None else (lambda t: fn(np.asarray(t, dtype=np.float64) - lag))


def _personal_distance_plan(clip: LeaderClip, rng: np.random.Generator) -> _BodyPlan:
    """The varied ``hand_hold`` follower: keeps a comfortable distance, faces the leader (causal)."""
    lo, hi = float(rng.uniform(0.7, 0.9)), float(rng.uniform(1.0, 1.3))
    vmax = float(rng.uniform(0.8, 1.3))
    d0 = float(rng.uniform(0.9, 1.9))
    a0 = clip.heading0 + float(rng.uniform(-0.4, 0.4))
    dt = 1.0 / 60.0
    grid = np.arange(0.0, clip.times[-1] + 3.0, dt)  # before t = 0 the follower stands at its start
    lead = clip.plan.centre(grid)
    f = lead[0] + d0 * np.array([np.cos(a0), np.sin(a0)])
    track = np.empty_like(lead)
    for k, ell in enumerate(lead):  # causal: each step sees the leader's current position only
        v = f - ell
        d = max(float(np.linalg.norm(v)), 1e-6)
        want = ell + v / d * min(max(d, lo), hi)
        step = want - f
        size = float(np.linalg.norm(step))
        f = f + (step if size <= vmax * dt else step * (vmax * dt / size))
        track[k] = f
    to_leader = lead - track
    yaw = np.unwrap(np.arctan2(to_leader[:, 1], to_leader[:, 0]))

    def centre(t):
        t = np.asarray(t, dtype=np.float64)
        return np.stack([np.interp(t, grid, track[:, 0]), np.interp(t, grid, track[:, 1])], axis=-1)

    lag = 0.3
    p = clip.plan
    own = None
    if rng.uniform() < 0.4:  # offers its right hand by itself for a while
        t0, hold = float(rng.uniform(0.0, clip.times[-1])), float(rng.uniform(0.8, 2.0))
        own = lambda t: _window(np.asarray(t, dtype=np.float64), t0, hold)  # noqa: E731
    answer_left = _lagged(p.reach_right, lag)
    answer_right = _lagged(p.reach_left, lag)
    if own is not None:
        answer_right = own if answer_right is None else (lambda t, a=answer_right: np.maximum(a(t), own(t)))
    return _BodyPlan(
        centre=centre,
        heading=lambda t: np.interp(np.asarray(t, dtype=np.float64), grid, yaw),
        arm_left=_lagged(p.arm_right, lag),
        arm_right=_lagged(p.arm_left, lag),
        beat_times=clip.beat_times,
        first_foot=1 - p.first_foot,
        steps_per_beat=2,
        reach_left=answer_left,
        reach_right=answer_right,
    )


def _varied_follower(rule: str, clip: LeaderClip, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    body, n, p = clip.body, len(clip.times), clip.plan
    h0 = np.array([np.cos(clip.heading0), np.sin(clip.heading0)])
    period = clip.beat_times[1] - clip.beat_times[0]
    if rule == "mirror":
        gap = float(rng.uniform(1.0, 1.5))
        point = np.broadcast_to(clip.origin + 0.5 * gap * h0, (n, 2))
        return _reflect(body.positions, point, np.broadcast_to(h0, (n, 2))), body.contacts[:, _CONTACT_MIRROR]
    if rule == "follow":
        lag = int(round(float(rng.uniform(0.3, 0.8)) * clip.fps))
        side = float(rng.choice([-1.0, 1.0]) * rng.uniform(0.8, 1.2))
        src = np.maximum(np.arange(n) - lag, 0)
        return body.positions[src] + side * np.array([-h0[1], h0[0], 0.0]), body.contacts[src]
    if rule == "hand_hold":
        plan = _personal_distance_plan(clip, rng)
    else:  # orbit
        radius = float(rng.uniform(0.9, 1.3))
        turn_s = float(rng.choice([-1.0, 1.0])) * float(rng.uniform(12, 24)) * period

        def angle(t):
            return clip.heading0 + 2 * np.pi * np.asarray(t, dtype=np.float64) / turn_s

        plan = _BodyPlan(
            centre=lambda t: p.centre(t) + radius * np.stack([np.cos(angle(t)), np.sin(angle(t))], -1),
            heading=lambda t: angle(t) + np.pi,
            arm_left=p.arm_right,
            arm_right=p.arm_left,
            beat_times=clip.beat_times,
            first_foot=1 - p.first_foot,
            steps_per_beat=2,
            reach_left=p.reach_right,
            reach_right=p.reach_left,
        )
    fbody = _synthesise(plan, clip.times, period, float(rng.uniform()))
    return fbody.positions, fbody.contacts


def _swap_sides(text: str) -> str:
    return " ".join({"left": "right", "right": "left"}.get(w, w) for w in text.split(" "))


def make_varied_duet(rule: str, seconds: float, fps: float, seed: int) -> TwoPersonMotion:
    """A duet of the wider repertoire (module docstring); ``make_duet(rule, ..., varied=True)``."""
    clip = make_varied_leader(seconds, fps, seed)
    rng = np.random.default_rng([int(seed), 4, ("mirror", "follow", "hand_hold", "orbit").index(rule)])
    f_pos, f_contacts = _varied_follower(rule, clip, rng)
    a_pos, a_contacts = clip.body.positions, clip.body.contacts
    slots = clip.slots
    text = (
        f"The leader {_STEP_TEXT[slots['step']]} {_ARM_WORDS[slots['arms']]}{_TURN_WORDS[slots['turn']]}"
        f"{_TRAVEL_WORDS[slots['travel']]} to {_tempo_word(clip.bpm)} music; {_RULE_TEXT[rule]}"
    )
    mirrored = bool(rng.uniform() < 0.5)
    if mirrored:  # reflect both people in the vertical plane through the leader's start along its facing
        n = len(a_pos)
        point = np.broadcast_to(clip.origin, (n, 2))
        normal = np.broadcast_to(np.array([-np.sin(clip.heading0), np.cos(clip.heading0)]), (n, 2))
        a_pos, f_pos = _reflect(a_pos, point, normal), _reflect(f_pos, point, normal)
        a_contacts, f_contacts = a_contacts[:, _CONTACT_MIRROR], f_contacts[:, _CONTACT_MIRROR]
        text = _swap_sides(text)
    beats, beat_frames = beat_features(clip.times, clip.beat_times, clip.fps)
    name = f"synthetic_varied_{rule}_seed{int(seed)}"
    return TwoPersonMotion(
        actor=Motion(positions=a_pos, fps=clip.fps, contacts=a_contacts, name=name + "_leader"),
        reactor=Motion(positions=f_pos, fps=clip.fps, contacts=f_contacts, name=name + "_follower"),
        text=text,
        meta={
            "synthetic": True,
            "varied": True,
            "mirrored": mirrored,
            "rule": rule,
            "bpm": clip.bpm,
            "seed": int(seed),
            "slots": dict(slots),
            "beats": beats,
            "beat_frames": beat_frames,
        },
    )

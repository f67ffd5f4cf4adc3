"""A body that holds together: causal, per-frame cleanup of generated joint positions.

Contract: :class:`BodyCleaner` takes one generated frame (22, 3) (SMPL-22, metres, Z up, floor
at z = ``floor``) and returns a cleaned frame with less jitter (one-euro filters), travel over
the floor within a person's speed and acceleration, constant bone lengths and planted feet
(locked on touch-down, two-bone leg IK, pelvis lowered when a locked foot is out of reach).
Output frame i depends on input frames <= i only; :func:`clean_positions` runs the same filter
over a clip. numpy only. How it works: docs/model.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dualflow.errors import DualFlowError
from dualflow.motion.skeleton import MIRROR_INDEX, N_JOINTS, PARENTS, REST_POSE, bone_lengths

_PAR = np.asarray(PARENTS)
#: (hip, knee, ankle, toe) of the left and the right leg
_LEGS = ((1, 4, 7, 10), (2, 5, 8, 11))
_REST_LENGTHS = bone_lengths(REST_POSE[None])[0]  # (21,), bone ending at joint j is entry j - 1
_MIRROR_BONE = np.asarray(MIRROR_INDEX[1:]) - 1  # the same bone on the other side


@dataclass(frozen=True)
class CleanConfig:
    """Settings of :class:`BodyCleaner` (see the module docstring); lengths in metres."""

    smooth: bool = True
    order: int = 2
    # Hz and s/m: the one-euro cutoff at rest and its rise with speed. At 1.5 and 1.5 (with the
    # old landing) the streamed CMU partner's jerk was 175 m/s³ (now 154); the price is lag: the
    # pelvis trails a steady 0.5 m/s walk by 129 ms (96 ms). docs/model.md
    min_cutoff: float = 1.0
    beta: float = 1.0
    d_cutoff: float = 1.0
    feet: bool = True
    floor: float = 0.0
    lock_ankle_m: float = 0.11
    lock_toe_m: float = 0.06
    release_ankle_m: float = 0.13
    release_toe_m: float = 0.08
    max_drift_m: float = 0.15
    step_frames: int = 9
    step_lift_m: float = 0.08
    max_drop_m: float = 0.15
    foot_blend: float = 0.5
    # a foot leaves the floor only while the other one is planted, and a body with no foot
    # planted puts its lower foot down: the training duets never have both feet off the floor,
    # and a generated partner that bobs up hops (the streamed CMU partner: both feet up in 38 %
    # of its frames; with this 9 %, skate 0.047 -> 0.017, jerk 154 -> 154 with drop_gain 0.12).
    # The op3 steps more with such a partner: before its torso shell's edges had capsules and
    # its lifts waited for the weight it hit itself or fell on 3 of 8 demo-like partners
    # streamed and 5 of 8 planned; now 1 of 16 (bench/stepping.py --clips partners; 2 of 16
    # with the rule off). docs/model.md
    one_foot_down: bool = True
    # per frame: how fast the body comes down to a planted foot's reach (with one_foot_down,
    # 0.5 made the streamed CMU partner jerk 197 m/s³, 0.12 154)
    drop_gain: float = 0.12
    # the body's travel over the floor (pelvis xy): at most this fast (m/s) and this quick to
    # change speed (m/s²); 0 turns the limit off. The real CMU partners peak at 1.3 m/s (95th
    # percentile of acceleration 5-6 m/s²); generated partners chasing an actor reached 3.5 m/s.
    # Tighter limits (1.6 m/s, or 6 m/s²) made the streamed feet skate while the body caught up
    # (0.28-0.30 of contact frames on the CMU actor, against 0.18)
    max_speed: float = 2.0
    max_accel: float = 8.0

    def __post_init__(self) -> None:
        if not (self.min_cutoff > 0 and self.beta >= 0 and self.d_cutoff > 0):
            raise DualFlowError("clean config: min_cutoff and d_cutoff must be > 0 Hz and beta >= 0")
        if not 0.0 < self.foot_blend <= 1.0:
            raise DualFlowError("clean config: foot_blend must be in (0, 1] (1 = feet follow their targets at once)")
        if self.order < 1:
            raise DualFlowError("clean config: order (one-euro filters in a row) must be >= 1")
        if not 0.0 < self.drop_gain <= 1.0:
            raise DualFlowError("clean config: drop_gain must be in (0, 1] (1 = the body comes down at once)")
        if self.step_frames < 2 or self.max_drift_m <= 0:
            raise DualFlowError("clean config: step_frames must be >= 2 and max_drift_m > 0")
        if self.max_speed < 0 or self.max_accel < 0 or (self.max_speed > 0) != (self.max_accel > 0):
            raise DualFlowError("clean config: max_speed and max_accel must both be > 0 (or both 0: no travel limit)")


def _smoothstep(s: float) -> float:
    s = min(max(s, 0.0), 1.0)
    return s * s * (3.0 - 2.0 * s)


class _Foot:
    """Lock state of one foot: 'free' (follows the generated foot, minus a decaying offset),
    'locked' (held at ``anchor``) or 'step' (moving from ``anchor`` to the generated foot)."""

    def __init__(self) -> None:
        self.mode = "free"
        self.anchor = np.zeros(3)
        self.toe = np.zeros(3)  # toe - ankle held while locked
        self.offset = np.zeros(3)  # output - generated ankle while blending back after a release
        self.progress = 0.0


class BodyCleaner:
    """Causal per-frame cleanup (module docstring). fps: frame rate of the stream;
    lengths: (21,) bone lengths in metres, entry j - 1 for the bone ending at joint j (default:
    the first frame's, left and right averaged); config: :class:`CleanConfig`."""

    def __init__(self, fps: float = 30.0, lengths=None, config: CleanConfig | None = None):
        if not float(fps) > 0:
            raise DualFlowError(f"body cleanup: fps must be > 0, got {fps!r}")
        self.fps = float(fps)
        self.config = config or CleanConfig()
        self._given_lengths = None if lengths is None else self._check_lengths(lengths)
        self.reset()

    @staticmethod
    def _check_lengths(lengths) -> np.ndarray:
        arr = np.asarray(lengths, dtype=np.float64)
        if arr.shape != (N_JOINTS - 1,) or not np.isfinite(arr).all() or (arr <= 0).any():
            raise DualFlowError(
                f"body cleanup: lengths must be {N_JOINTS - 1} positive bone lengths in metres, got shape {arr.shape}"
            )
        return arr

    def reset(self) -> None:
        """Forget the stream (filter state, feet, skeleton size when not given)."""
        self.lengths = self._given_lengths
        self._x = self._dx = None
        self._drop = 0.0
        self._feet = (_Foot(), _Foot())
        self._foot_out = [None, None]
        self._root = self._root_v = None  # the limited pelvis xy (2,) and its velocity (2,)
        self._target = None  # the last generated pelvis xy (2,)

    # -- 1. smoothing ---------------------------------------------------------------------
    def _alpha(self, cutoff):
        tau = 1.0 / (2.0 * np.pi * cutoff)
        return 1.0 / (1.0 + tau * self.fps)

    def _smooth(self, p: np.ndarray) -> np.ndarray:
        """``order`` one-euro filters in a row (each state: value and filtered speed per joint)."""
        c = self.config
        if self._x is None:
            self._x = [p.copy() for _ in range(c.order)]
            self._dx = [np.zeros_like(p) for _ in range(c.order)]
            return p
        for x, dxf in zip(self._x, self._dx):
            dxf += self._alpha(c.d_cutoff) * ((p - x) * self.fps - dxf)
            speed = np.linalg.norm(dxf, axis=-1, keepdims=True)  # per joint, m/s
            x += self._alpha(c.min_cutoff + c.beta * speed) * (p - x)
            p = x.copy()
        return p

    def _limit_travel(self, p: np.ndarray) -> np.ndarray:
        """The frame moved horizontally so that the pelvis travels within ``max_speed`` and
        ``max_accel``: each frame it moves with the generated pelvis and closes the gap to it at
        the speed that still lets it stop there (about √(2·a·gap)), at once when that is within
        the limits."""
        c, dt = self.config, 1.0 / self.fps
        target = p[0, :2]
        if self._root is None:
            self._root, self._root_v, self._target = target.copy(), np.zeros(2), target.copy()
            return p
        moving = (target - self._target) / dt  # the generated pelvis's own velocity
        self._target = target.copy()
        err = target - (self._root + moving * dt)  # the gap left after moving with it
        dist = float(np.linalg.norm(err))
        # the closing speed it can still brake from within the gap, frame by frame: v²/2a + v·dt/2 = gap
        half = 0.5 * c.max_accel * dt
        close = min(dist / dt, float(np.sqrt(half * half + 2.0 * c.max_accel * dist)) - half)
        want = moving + (err * (close / dist) if dist > 1e-12 else 0.0)
        speed = float(np.linalg.norm(want))
        if speed > c.max_speed:
            want *= c.max_speed / speed
        dv = want - self._root_v
        step = float(np.linalg.norm(dv))
        if step > c.max_accel * dt:
            dv *= c.max_accel * dt / step
        self._root_v = self._root_v + dv
        self._root = self._root + self._root_v * dt
        out = p.copy()
        out[:, :2] += self._root - target
        return out

    # -- 2. bone lengths ------------------------------------------------------------------
    def _project(self, p: np.ndarray) -> np.ndarray:
        if self.lengths is None:  # the first frame's bones, left and right averaged
            first = bone_lengths(p[None])[0]
            self.lengths = 0.5 * (first + first[_MIRROR_BONE])
        bones = p[1:] - p[_PAR[1:]]
        norm = np.linalg.norm(bones, axis=-1, keepdims=True)
        rest_dir = REST_POSE[1:] - REST_POSE[_PAR[1:]]
        rest_dir /= np.linalg.norm(rest_dir, axis=-1, keepdims=True)
        dirs = np.where(norm > 1e-9, bones / np.maximum(norm, 1e-9), rest_dir)
        seg = dirs * self.lengths[:, None]
        q = np.empty_like(p)
        q[0] = p[0]
        for j in range(1, N_JOINTS):  # parents come before children in SMPL order
            q[j] = q[_PAR[j]] + seg[j - 1]
        return q

    # -- 3. feet --------------------------------------------------------------------------
    def _low(self, ankle: np.ndarray, toe: np.ndarray, on: bool) -> bool:
        c = self.config
        a_lim, t_lim = (c.lock_ankle_m, c.lock_toe_m) if on else (c.release_ankle_m, c.release_toe_m)
        return bool(ankle[2] - c.floor < a_lim or toe[2] - c.floor < t_lim)

    def _foot_target(
        self, foot: _Foot, ankle: np.ndarray, toe_vec: np.ndarray, at=None, other_down: bool = True
    ) -> tuple[np.ndarray, np.ndarray]:
        """(ankle, toe - ankle) wanted for one foot this frame; updates its lock state. ``at``: where
        the foot's ankle was put last frame (a foot that touches down is planted there, not
        where the generated foot is: it would slide the difference). ``other_down``: the other
        foot is planted (with ``one_foot_down``, a foot lifts only then, and a free foot is put
        down where it is when the other is not)."""
        c = self.config
        if foot.mode == "locked":
            if c.one_foot_down and not other_down:  # the other foot is up: this one stays
                return foot.anchor.copy(), foot.toe.copy()
            if not self._low(ankle, ankle + toe_vec, on=False):
                foot.mode, foot.offset = "free", foot.anchor - ankle
            elif np.linalg.norm((ankle - foot.anchor)[:2]) > c.max_drift_m:
                foot.mode, foot.progress = "step", 0.0
            else:
                return foot.anchor.copy(), foot.toe.copy()
        if foot.mode == "step":
            foot.progress += 1.0 / c.step_frames
            s = foot.progress
            w = _smoothstep((s - 0.2) / 0.45)  # moves only while lifted
            lift = c.step_lift_m * _smoothstep(s / 0.25) * _smoothstep((1.0 - s) / 0.25)
            out = (1 - w) * foot.anchor + w * ankle
            out[2] += lift
            tv = (1 - w) * foot.toe + w * toe_vec
            tv[2] = max(tv[2], foot.toe[2])  # the toe no lower than planted: a pointed toe drags
            tv *= np.linalg.norm(toe_vec) / max(np.linalg.norm(tv), 1e-9)
            if s >= 1.0 - 1e-9:
                foot.mode, foot.offset = "free", np.zeros(3)
                return self._foot_target(foot, ankle, toe_vec, at, other_down)  # lands (locks) if low, else swings on
            return out, tv
        # free: follow the generated foot, the offset of a release fading out: height first, the
        # horizontal part only once the foot is off the floor (no sliding while it touches)
        foot.offset[2] *= 0.5
        out = ankle + foot.offset
        if not self._low(out, out + toe_vec, on=False):
            foot.offset[:2] *= 0.7
            out = ankle + foot.offset
        grounded = c.one_foot_down and not other_down  # no foot planted: this one comes down
        if grounded or self._low(ankle, ankle + toe_vec, on=True):  # the generated foot touches down: plant it here
            foot.mode, foot.anchor, foot.toe = "locked", out.copy(), toe_vec.copy()
            if at is not None:
                foot.anchor[:2] = at[:2]
            # planted at a height the ankle and the toe can keep (the checks in step)
            floor = self.config.floor
            lowest = max(floor + self._ankle_floor(), floor - toe_vec[2])
            foot.anchor[2] = lowest if grounded else max(foot.anchor[2], lowest)
            return foot.anchor.copy(), foot.toe.copy()
        return out, toe_vec

    def _ankle_floor(self) -> float:
        """Lowest ankle height allowed: the rest pose's, scaled to this skeleton (m above the floor)."""
        return float(REST_POSE[7, 2] * self.lengths.sum() / _REST_LENGTHS.sum()) * 0.9

    def _leg_ik(self, q: np.ndarray, leg: tuple[int, int, int, int], ankle: np.ndarray, toe_vec: np.ndarray) -> None:
        """Place the leg's ankle at ``ankle`` (as near as reachable), its toe at ankle + toe_vec;
        thigh, shin and foot keep their lengths."""
        hip, knee, ank, toe = leg
        l1, l2 = self.lengths[knee - 1], self.lengths[ank - 1]
        v = ankle - q[hip]
        d = float(np.linalg.norm(v))
        u = v / max(d, 1e-9)
        d = min(max(d, abs(l1 - l2) + 1e-4), l1 + l2 - 1e-4)
        hint = q[knee] - q[hip]
        w = hint - np.dot(hint, u) * u
        wn = float(np.linalg.norm(w))
        if wn < 1e-6:  # a straight generated leg: bend the knee forwards (the toe's direction)
            w = toe_vec - np.dot(toe_vec, u) * u
            wn = max(float(np.linalg.norm(w)), 1e-9)
        w /= wn
        cos_a = np.clip((l1 * l1 + d * d - l2 * l2) / (2 * l1 * d), -1.0, 1.0)
        q[knee] = q[hip] + l1 * (cos_a * u + np.sqrt(1.0 - cos_a * cos_a) * w)
        q[ank] = q[hip] + d * u
        q[toe] = q[ank] + toe_vec

    def _pelvis_drop(self, q: np.ndarray, targets) -> float:
        """How far the body must come down so that every locked / stepping foot is reachable."""
        need = 0.0
        for (hip, knee, ank, _), (ankle, _), foot in zip(_LEGS, targets, self._feet):
            if foot.mode == "free":
                continue
            reach = 0.999 * (self.lengths[knee - 1] + self.lengths[ank - 1])
            r = float(np.linalg.norm((ankle - q[hip])[:2]))
            dz = q[hip, 2] - ankle[2]
            if r < reach:
                need = max(need, dz - np.sqrt(reach * reach - r * r))
        return min(max(need, 0.0), self.config.max_drop_m)

    def step(self, positions, contacts=None) -> tuple[np.ndarray, np.ndarray]:
        """One frame (22, 3) m in, ((22, 3) cleaned positions, (4,) bool foot contacts out:
        left ankle, left toe, right ankle, right toe). ``contacts`` (the model's, if any) is
        not needed: contact follows the foot heights (module docstring)."""
        p = np.asarray(positions, dtype=np.float64)
        if p.shape != (N_JOINTS, 3) or not np.isfinite(p).all():
            raise DualFlowError(f"body cleanup: a frame must be finite ({N_JOINTS}, 3) positions, got shape {p.shape}")
        c = self.config
        if c.smooth:
            p = self._smooth(p)
        if c.max_speed > 0:
            p = self._limit_travel(p)
        q = self._project(p)
        if not c.feet:
            return q, np.zeros(4, dtype=bool)
        targets = []
        for i, (foot, (_, _, ank, toe), last) in enumerate(zip(self._feet, _LEGS, self._foot_out)):
            other_down = self._feet[1 - i].mode == "locked"  # the left foot's update counts for the right
            at = None if last is None else last[0]
            targets.append(self._foot_target(foot, q[ank].copy(), q[toe] - q[ank], at, other_down))
        for i, (a, tv) in enumerate(targets):  # the ankle not below its standing height, the toe not below the floor
            lowest = max(c.floor + self._ankle_floor(), c.floor - tv[2])
            if a[2] < lowest:
                targets[i] = (np.array([a[0], a[1], lowest]), tv)
        if c.foot_blend < 1.0:  # a soft landing / take-off: the feet follow their targets through a low-pass
            for i, (a, tv) in enumerate(targets):
                prev = self._foot_out[i]
                if prev is not None:
                    # a planted or stepping foot is where its target says (its step is smooth
                    # already): low-passed across the floor, it slid after each landing
                    moving = self._feet[i].mode != "locked"
                    a = (
                        prev[0] + c.foot_blend * (a - prev[0])
                        if moving
                        else np.r_[a[:2], prev[0][2] + c.foot_blend * (a[2] - prev[0][2])]
                    )
                    mixed = prev[1] + c.foot_blend * (tv - prev[1])
                    tv = mixed * (np.linalg.norm(tv) / max(np.linalg.norm(mixed), 1e-9))
                targets[i] = self._foot_out[i] = (a, tv)
        need = self._pelvis_drop(q, targets)
        self._drop += c.drop_gain * (need - self._drop)
        if self._drop > 1e-6:
            q[:, 2] -= self._drop
        for leg, (a, tv) in zip(_LEGS, targets):
            self._leg_ik(q, leg, a, tv)
        flags = np.array([foot.mode == "locked" for foot in self._feet])
        return q, np.repeat(flags, 2)


def clean_positions(positions, fps: float = 30.0, lengths=None, config: CleanConfig | None = None):
    """A whole clip (T, 22, 3) m through :class:`BodyCleaner`: ((T, 22, 3), (T, 4) bool contacts)."""
    p = np.asarray(positions, dtype=np.float64)
    if p.ndim != 3 or p.shape[1:] != (N_JOINTS, 3):
        raise DualFlowError(f"body cleanup: positions must be (T, {N_JOINTS}, 3), got {p.shape}")
    cleaner = BodyCleaner(fps, lengths, config)
    out = np.empty_like(p)
    flags = np.empty((len(p), 4), dtype=bool)
    for t in range(len(p)):
        out[t], flags[t] = cleaner.step(p[t])
    return out, flags

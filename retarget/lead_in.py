"""A lead-in for a clip that starts mid-motion: from standing, at rest, into its first frame.

A clip cut out of a longer capture often starts mid-step: a foot in the air, the feet staggered
or turned against a standing stance, the body already moving. The physics check and the bridge
enter a clip from the robot's standing pose by moving the joints with both feet on the floor,
which can neither move a foot nor give the body the clip's speed; such a clip tips the robot
over at its start. :func:`lead_in` makes, at the level of the person's motion, what a person
would do to start that clip from rest:

1. *stand* ``hold_s`` in a standing pose (:func:`standing_pose`) at the first frame's place
   (pelvis xy) and heading (hip line): legs under the hips, arms down, both feet on the floor;
2. *step* each foot to its place in the first frame (farther than ``step_distance`` or turned
   more than ``step_turn`` from its standing place), one at a time: the pelvis first shifts
   ``shift_share`` of the way over the other foot (``shift_s``), the foot swings (``swing_s``,
   lifted ``lift`` m), lands and both feet stay down ``double_s`` while the pelvis comes back.
   A foot that is in the air in the first frame steps to the point on the floor below it (its
   ankle and toe xy, at floor height): it is *held* down there;
3. *move* (``move_s`` at least, longer for a large change at ``move_speed``) into the first
   frame's pose along a minimum-jerk path, s(u) = 10u³ − 15u⁴ + 6u⁵: pelvis and upper body,
   both feet on the floor, ending at rest in the first frame (a held foot on the floor below
   its place there);
4. *the clip* from that rest: a held foot stays on the floor and lifts ``swing_s`` before the
   person's foot lands (at least ``shift_s`` into the clip, landing that much later then, before
   the other foot lifts), swinging on a minimum-jerk blend to where the person puts it down; the
   body (pelvis, upper body; knees by half) shifts ``shift_share`` of the way over the stance foot
   over ``shift_s`` before the lift and back over ``double_s`` after the landing. The robot never
   stands on one foot at rest: a one-foot pose held still, 8-10 mm inside the sole's edge as the
   balance rows allow, tips the compliant servos over (cmu18_01 with the foot lifted in the
   lead-in: 1.3 s on one foot, the torso's tilt 1.6 -> 51 deg). With ``ease_s`` > 0 the clip's
   first ``ease_s`` seconds of trajectory time play it through a time warp τ(u) whose speed
   τ'(u) = 3x² − 2x³ (x = u / ease_s) rises from 0 to 1; τ(ease_s) = ease_s / 2, after which the
   clip plays as it is, ``ease_s / 2`` seconds later (off by default: see LeadInConfig).

Legs are placed by their feet: each knee comes from a two-bone IK (the hip, the ankle, the
thigh and shin lengths of the first frame, bent straight ahead), plus, during the move, the
first frame's knee's offset from that IK knee blended in, so a planted foot stays put while the
body moves and the last lead-in frame is the first frame. Contact labels (T, 4) come with the
frames: both feet down while standing and moving, a stepping foot up during its swing, a held
foot down until its swing in the ease-in; the clip's own labels (or detected ones) after that.

A clip whose first frame is already a standing double support at rest (both feet down, pelvis
slower than ``rest_speed``, every joint slower than ``rest_joint_speed`` over ``rest_window_s``,
no foot that would need a step) gets no lead-in (:func:`needs_lead_in`).

Times: the lead-in is ``LeadIn.frames`` frames before the clip's first frame. In the extended
motion (and the robot trajectory made from it) the clip's first frame is at ``t0_s`` =
frames / fps; *clip time* is the motion file's own time: negative in the lead-in, τ in the
ease-in, trajectory time − t0_s − ease_s / 2 after it (:meth:`LeadIn.clip_time`).
All lengths in metres (the person's scale), angles in radians, times in seconds.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from dualflow.motion import Motion
from dualflow.motion.skeleton import PARENTS, REST_POSE
from retarget.errors import RetargetError
from retarget.schedule import Change, count_steps
from retarget.targets import detect_contacts, side_contacts

PELVIS, L_HIP, R_HIP, L_KNEE, R_KNEE, L_ANKLE, R_ANKLE, L_FOOT, R_FOOT = 0, 1, 2, 4, 5, 7, 8, 10, 11
HIP, KNEE, ANKLE, TOE = (L_HIP, R_HIP), (L_KNEE, R_KNEE), (L_ANKLE, R_ANKLE), (L_FOOT, R_FOOT)
LEG_JOINTS = (L_KNEE, R_KNEE, L_ANKLE, R_ANKLE, L_FOOT, R_FOOT)


@dataclass(frozen=True)
class LeadInConfig:
    """Timing and thresholds of the lead-in (see the module docstring); s, m, rad."""

    hold_s: float = 0.3
    shift_s: float = 0.4
    swing_s: float = 0.4
    min_swing_s: float = 0.2  # a held foot's swing in the ease-in is at least this long
    double_s: float = 0.3
    move_s: float = 0.6
    move_speed: float = 0.3  # m/s: the move takes at least (largest joint displacement) / move_speed
    # 0: the clip plays at its own speed from the lead-in's rest (0.8 s made cmu19_01 fall 1.1 s into the
    # clip: its first steps at half speed hold each foot longer on the compliant servos)
    ease_s: float = 0.0
    lift: float = 0.05
    shift_share: float = 0.7
    step_distance: float = 0.03  # a foot farther than this from its standing place steps there
    step_turn: float = 0.15
    rest_speed: float = 0.05  # m/s, pelvis
    rest_joint_speed: float = 0.3  # m/s, any joint
    rest_window_s: float = 0.2
    knee_bend: float = 0.97  # standing hip-ankle distance as a share of thigh + shin


@dataclass(frozen=True)
class LeadIn:
    """What :func:`lead_in` added: ``frames`` lead-in frames before the clip's first frame
    (``t0_s`` = frames / fps), the ease-in (``ease_s`` of trajectory time playing the clip's first
    ``ease_s / 2``), the feet that stepped (``steps``: 'left'/'right'), the feet in the air in the
    first frame that the robot held on the floor (``held``) and the clip time (s) each of them
    swings from there (``swing_from_s``: None for a foot the person never puts down, which
    stays down), and why a lead-in was needed (``why``)."""

    frames: int
    fps: float
    ease_s: float
    steps: tuple
    held: tuple
    why: str
    swing_from_s: tuple = ()

    @property
    def t0_s(self) -> float:
        return self.frames / self.fps

    @property
    def delay_s(self) -> float:
        """How much later the clip plays after the ease-in than it would without the lead-in."""
        return self.ease_s / 2

    def clip_time(self, t) -> np.ndarray:
        """Clip time (s) of trajectory time(s) ``t`` (s): negative in the lead-in, the warp τ in the ease-in."""
        u = np.asarray(t, dtype=np.float64) - self.t0_s
        return np.where(u <= 0, u, _warp(np.maximum(u, 0.0), self.ease_s))

    def to_dict(self) -> dict:
        d = asdict(self)
        d.update(
            t0_s=round(self.t0_s, 6),
            delay_s=self.delay_s,
            steps=list(self.steps),
            held=list(self.held),
            swing_from_s=list(self.swing_from_s),
        )
        return d

    @classmethod
    def from_dict(cls, d: dict) -> LeadIn:
        return cls(
            int(d["frames"]),
            float(d["fps"]),
            float(d["ease_s"]),
            tuple(d.get("steps", ())),
            tuple(d.get("held", ())),
            str(d.get("why", "")),
            tuple(d.get("swing_from_s", ())),
        )


def _warp(u: np.ndarray, ease: float) -> np.ndarray:
    """τ(u): ∫ speed, speed = 3x² − 2x³ for x = u / ease < 1, then 1 (τ = u − ease / 2)."""
    if ease <= 0:
        return u
    x = np.clip(u / ease, 0.0, 1.0)
    return np.where(u < ease, ease * (x**3 - 0.5 * x**4), u - 0.5 * ease)


def min_jerk_share(u: np.ndarray) -> np.ndarray:
    """The share 10u³ − 15u⁴ + 6u⁵ of a minimum-jerk move done at u (clipped to [0, 1])."""
    u = np.clip(u, 0.0, 1.0)
    return 10 * u**3 - 15 * u**4 + 6 * u**5


def _rot_z(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _heading(p: np.ndarray) -> float:
    """Yaw (rad, +X at 0) of a pose (22, 3) from its hip line."""
    across = p[L_HIP] - p[R_HIP]
    return math.atan2(-across[0], across[1])


def _foot_yaw(p: np.ndarray, s: int) -> float:
    d = p[TOE[s]] - p[ANKLE[s]]
    return math.atan2(d[1], d[0])


def _contacts4(motion: Motion) -> np.ndarray:
    return np.asarray(motion.contacts if motion.contacts is not None else detect_contacts(motion), dtype=bool)


def _with_contacts(motion: Motion, contacts) -> Motion:
    """``motion`` labelled with ``contacts`` (T, 4) or (T, 2) (left, right: each side's ankle and toe)."""
    if contacts is None:
        return motion
    c = np.asarray(contacts, dtype=bool)
    if c.shape == (motion.n_frames, 2):
        c = np.repeat(c, 2, axis=1)
    if c.shape != (motion.n_frames, 4):
        raise RetargetError(f"contacts: expected shape ({motion.n_frames}, 4) or ({motion.n_frames}, 2), got {c.shape}")
    return motion.replace(contacts=c)


def knee_ik(hip: np.ndarray, ankle: np.ndarray, l1: float, l2: float, pole: np.ndarray) -> np.ndarray:
    """Knee position (3,) of a two-bone leg: |knee − hip| = l1, |ankle − knee| = l2 where the
    hip-ankle distance allows (clamped to a straight or folded leg), bent towards ``pole`` (3,)."""
    d = ankle - hip
    r = float(np.linalg.norm(d))
    axis = d / max(r, 1e-9)
    r = min(max(r, abs(l1 - l2) + 1e-6), l1 + l2 - 1e-9)
    a = (l1**2 - l2**2 + r**2) / (2 * r)  # along the hip-ankle line
    h = math.sqrt(max(l1**2 - a**2, 0.0))
    side = pole - (pole @ axis) * axis
    n = float(np.linalg.norm(side))
    side = side / n if n > 1e-9 else np.cross(axis, [0.0, 1.0, 0.0])
    return hip + a * axis + h * side


def standing_pose(first: np.ndarray, ground: np.ndarray, config: LeadInConfig = LeadInConfig()) -> np.ndarray:
    """The person standing (22, 3) at the first frame's place (pelvis xy) and heading (hip line),
    with its bone lengths: REST_POSE's bone directions, arms hanging, legs under the hips bent
    to ``knee_bend`` of their length, ankles and toes at ``ground`` (2,) heights (ankle, toe)."""
    first = np.asarray(first, dtype=np.float64)
    R = _rot_z(_heading(first))
    dirs = REST_POSE - REST_POSE[list(PARENTS)]
    dirs[0] = 0.0
    for j, sgn in ((18, 1), (19, -1), (20, 1), (21, -1)):  # elbows, wrists: arms hanging, slightly out
        dirs[j] = (0.0, 0.2 * sgn, -1.0)
    length = np.linalg.norm(first - first[list(PARENTS)], axis=1)
    local = np.zeros((22, 3))
    for j in range(1, 22):
        local[j] = local[PARENTS[j]] + length[j] * dirs[j] / np.linalg.norm(dirs[j])
    out = first[PELVIS] + local @ R.T
    legs = [length[KNEE[s]] + length[ANKLE[s]] for s in range(2)]
    hip_drop = max(out[PELVIS, 2] - out[HIP[s], 2] for s in range(2))
    # pelvis height: the longer-reaching leg bent to knee_bend with its ankle under its hip
    out[:, 2] += (ground[0] + config.knee_bend * min(legs) + hip_drop) - out[PELVIS, 2]
    fwd = R[:, 0]
    for s in range(2):
        ank = np.array([out[HIP[s], 0], out[HIP[s], 1], ground[0]])
        out[ANKLE[s]] = ank
        out[KNEE[s]] = knee_ik(out[HIP[s]], ank, length[KNEE[s]], length[ANKLE[s]], fwd)
        toe = R @ (dirs[TOE[s]] / np.linalg.norm(dirs[TOE[s]]))
        toe_xy = toe[0:2] / max(np.linalg.norm(toe[0:2]), 1e-9)
        dz = ground[1] - ground[0]
        horiz = math.sqrt(max(length[TOE[s]] ** 2 - dz**2, 0.0))
        out[TOE[s]] = ank + np.array([*(horiz * toe_xy), dz])
    return out


def _ground(motion: Motion, c4: np.ndarray) -> np.ndarray:
    """Ankle and toe height (2,) m of a foot on the floor: medians over the clip's contact frames."""
    p = motion.positions
    out = []
    for joints, cols in ((ANKLE, (0, 2)), (TOE, (1, 3))):
        z = np.concatenate([p[c4[:, col], j, 2] for j, col in zip(joints, cols)])
        out.append(float(np.median(z)) if z.size else float(min(p[0, joints[0], 2], p[0, joints[1], 2])))
    return np.array(out)


def _needs_step(stand: np.ndarray, first: np.ndarray, s: int, cfg: LeadInConfig) -> tuple[float, float]:
    moved = float(np.linalg.norm(first[ANKLE[s], 0:2] - stand[ANKLE[s], 0:2]))
    turned = abs((_foot_yaw(first, s) - _foot_yaw(stand, s) + math.pi) % (2 * math.pi) - math.pi)
    return moved, turned


def needs_lead_in(motion: Motion, config: LeadInConfig = LeadInConfig()) -> str:
    """Why the clip needs a lead-in ('' when its first frame is a standing double support at rest)."""
    cfg = config
    p = motion.positions
    c = side_contacts(_contacts4(motion))
    n = max(2, min(motion.n_frames, int(round(cfg.rest_window_s * motion.fps)) + 1))
    why = []
    up = [side for s, side in enumerate(("left", "right")) if not c[0, s]]
    if up:
        why.append(f"the {' and '.join(up)} foot is in the air")
    if n >= 2:
        v = np.linalg.norm(np.diff(p[:n], axis=0), axis=-1) * motion.fps  # (n-1, 22)
        if v[:, PELVIS].max() > cfg.rest_speed:
            why.append(f"the pelvis moves at {v[:, PELVIS].max():.2f} m/s")
        elif v.max() > cfg.rest_joint_speed:
            why.append(f"a joint moves at {v.max():.2f} m/s")
    stand = standing_pose(p[0], _ground(motion, _contacts4(motion)), cfg)
    for s, side in enumerate(("left", "right")):
        if c[0, s]:
            moved, turned = _needs_step(stand, p[0], s, cfg)
            if moved > cfg.step_distance or turned > cfg.step_turn:
                why.append(
                    f"the {side} foot stands {1000 * moved:.0f} mm and {math.degrees(turned):.0f} deg from "
                    "a standing stance"
                )
    return "; ".join(why)


def lead_in(
    motion: Motion, config: LeadInConfig = LeadInConfig(), contacts=None, force: bool = False
) -> tuple[Motion, LeadIn | None]:
    """The clip with a lead-in and an eased-in start (see the module docstring), and what was
    added; ``(motion, None)`` when its first frame is a standing double support at rest (unless
    ``force``). ``contacts`` (T, 4) or (T, 2) override the motion's labels; the result carries
    contact labels (T', 4)."""
    motion = _with_contacts(motion, contacts) if contacts is not None else motion
    why = needs_lead_in(motion, config)
    if not why and not force:
        return motion, None
    b = _LeadInBuilder(motion, config)
    b.hold()
    stepped = [("left", "right")[s] for s in range(2) if b.step_if_needed(s)]
    b.move_into_first_frame()
    lead = np.stack(b.frames[:-1])  # the last one is the first frame itself: the clip supplies it
    lead_c = np.array(b.labels[:-1], dtype=bool)
    ease = config.ease_s if motion.n_frames > 1 else 0.0
    clip, clip_c4, swing_from = b.eased_clip(ease)
    lead_c4 = np.repeat(lead_c, 2, axis=1)  # (left, right) -> (l_ankle, l_toe, r_ankle, r_toe)
    out = Motion(
        np.concatenate([lead, clip]).astype(motion.positions.dtype, copy=False),
        fps=motion.fps,
        contacts=np.concatenate([lead_c4, clip_c4]),
        name=motion.name,
    )
    held = tuple(("left", "right")[s] for s in b.held)
    return out, LeadIn(len(lead), motion.fps, ease, tuple(stepped), held, why, tuple(swing_from))


class _LeadInBuilder:
    """The lead-in's frames as they are built: the person's pelvis, upper body (every joint but
    the legs) relative to the pelvis and feet; the knees by two-bone IK. ``frames`` (22, 3) each
    and ``labels`` (left down, right down) each, in order. A foot in the air in the first frame
    is ``held`` on the floor below it (``first_feet``) through the lead-in."""

    def __init__(self, motion: Motion, cfg: LeadInConfig):
        self.cfg, self.fps, self.motion = cfg, motion.fps, motion
        self.p = np.asarray(motion.positions, dtype=np.float64)
        self.c4 = _contacts4(motion)
        self.c = side_contacts(self.c4)
        first = self.p[0]
        ground = _ground(motion, self.c4)
        self.stand = standing_pose(first, ground, cfg)
        self.length = np.linalg.norm(first - first[list(PARENTS)], axis=1)
        self.fwd = _rot_z(_heading(first))[:, 0]
        self.frames: list[np.ndarray] = []
        self.labels: list[tuple[bool, bool]] = []
        self.upper = [j for j in range(22) if j not in LEG_JOINTS and j != PELVIS]
        self.held = [s for s in range(2) if not self.c[0, s]]
        # where each foot stands when the lead-in ends: its first-frame place, a held foot on the
        # floor below it (ankle and toe at the floor's heights, the toe's direction and length kept)
        self.first_feet = {}
        for s in range(2):
            ank, toe = first[ANKLE[s]].copy(), first[TOE[s]].copy()
            if s in self.held:
                ank[2] = ground[0]
                d = toe[0:2] - first[ANKLE[s], 0:2]
                dz = ground[1] - ground[0]
                horiz = math.sqrt(max(self.length[TOE[s]] ** 2 - dz**2, 0.0))
                toe = ank + np.array([*(horiz * d / max(np.linalg.norm(d), 1e-9)), dz])
            self.first_feet[s] = (ank, toe)
        self.first = self._with_feet(first, self.first_feet)
        self.feet = {s: (self.stand[ANKLE[s]].copy(), self.stand[TOE[s]].copy()) for s in range(2)}
        # the first frame's knee against the straight-ahead IK knee: blended in during the move,
        # so the knee ends where it is in the first frame without flipping through the leg's axis
        f, L = self.first, self.length
        self.knee_fix = [
            f[KNEE[s]] - knee_ik(f[HIP[s]], f[ANKLE[s]], L[KNEE[s]], L[ANKLE[s]], self.fwd) for s in range(2)
        ]
        self.rel_stand = self.stand[self.upper] - self.stand[PELVIS]
        self.pel = self.stand[PELVIS].copy()

    def _with_feet(self, f: np.ndarray, feet: dict) -> np.ndarray:
        """Frame ``f`` (22, 3) with the feet of ``feet`` ({side: (ankle, toe)}) placed there, each
        knee moved by half its ankle's shift."""
        f = f.copy()
        for s in feet:
            shift = feet[s][0] - f[ANKLE[s]]
            f[ANKLE[s]], f[TOE[s]] = feet[s]
            f[KNEE[s]] += 0.5 * shift
        return f

    def n(self, seconds: float) -> int:
        return max(1, int(round(seconds * self.fps)))

    def emit(self, pelvis, rel, down, pole_share: float = 0.0) -> None:
        f = np.zeros((22, 3))
        f[PELVIS] = pelvis
        f[self.upper] = pelvis + rel
        for s in range(2):
            ank, toe = self.feet[s]
            f[ANKLE[s]], f[TOE[s]] = ank, toe
            knee = knee_ik(f[HIP[s]], ank, self.length[KNEE[s]], self.length[ANKLE[s]], self.fwd)
            f[KNEE[s]] = knee + pole_share * self.knee_fix[s]
        self.frames.append(f)
        self.labels.append(tuple(down))

    def hold(self) -> None:
        """1. standing still."""
        for _ in range(self.n(self.cfg.hold_s)):
            self.emit(self.pel, self.rel_stand, (True, True))

    def step_if_needed(self, s: int) -> bool:
        """2. a step of foot ``s`` to its place at the lead-in's end (``first_feet``) if that is
        elsewhere: weight shift, swing, double support. Whether it stepped."""
        cfg, stand, feet = self.cfg, self.stand, self.feet
        moved, turned = _needs_step(stand, self.first, s, cfg)
        if moved <= cfg.step_distance and turned <= cfg.step_turn:
            return False
        pel = self.pel
        over = pel.copy()
        over[0:2] += cfg.shift_share * (feet[1 - s][0][0:2] - pel[0:2])
        k = self.n(cfg.shift_s)
        for i in range(1, k + 1):
            self.emit(pel + (over - pel) * min_jerk_share(np.array(i / k)), self.rel_stand, (True, True))
        a0, t0 = feet[s]
        a1, t1 = self.first_feet[s]
        k = self.n(cfg.swing_s)
        for i in range(1, k + 1):
            w = float(min_jerk_share(np.array(i / k)))
            arc = cfg.lift * 4 * (i / k) * (1 - i / k)
            ank = a0 + (a1 - a0) * w + np.array([0, 0, arc])
            toe_rel = (t0 - a0) + ((t1 - a1) - (t0 - a0)) * w
            toe_rel *= np.linalg.norm(t1 - a1) / max(np.linalg.norm(toe_rel), 1e-9)
            feet[s] = (ank, ank + toe_rel)
            self.emit(over, self.rel_stand, (s == 1 or i == k, s == 0 or i == k))
        feet[s] = (a1.copy(), t1.copy())
        centre = pel.copy()
        centre[0:2] = 0.5 * (feet[0][0][0:2] + feet[1][0][0:2]) + (
            stand[PELVIS, 0:2] - 0.5 * (stand[L_ANKLE, 0:2] + stand[R_ANKLE, 0:2])
        )
        k = self.n(cfg.double_s)
        for i in range(1, k + 1):
            self.emit(over + (centre - over) * min_jerk_share(np.array(i / k)), self.rel_stand, (True, True))
        self.pel = centre
        return True

    def move_into_first_frame(self) -> None:
        """3. into the first frame's pose on both feet (a held foot on the floor below its place)."""
        cfg, first, pel, upper = self.cfg, self.first, self.pel, self.upper
        start_feet = dict(self.feet)
        rel0 = first[upper] - first[PELVIS]
        moves = [np.linalg.norm(first[PELVIS] - pel)]
        moves += [np.linalg.norm(self.first_feet[s][0] - start_feet[s][0]) for s in range(2)]
        moves.append(float(np.max(np.linalg.norm(rel0 - self.rel_stand, axis=1))))
        k = max(self.n(cfg.move_s), self.n(max(moves) / cfg.move_speed))
        for i in range(1, k + 1):
            w = float(min_jerk_share(np.array(i / k)))
            for s in range(2):
                (a0, t0), (a1, t1) = start_feet[s], self.first_feet[s]
                self.feet[s] = (a0 + (a1 - a0) * w, t0 + (t1 - t0) * w)
            self.emit(
                pel + (first[PELVIS] - pel) * w,
                self.rel_stand + (rel0 - self.rel_stand) * w,
                (True, True),
                pole_share=w,
            )

    def _held_swing(self, land: int, other_down: np.ndarray) -> tuple[int, int]:
        """(lift, landing) frames of a held foot's swing in the eased clip: ``swing_s`` long,
        landing with the person (``land``) or, when that leaves less than ``shift_s`` on both feet
        after the clip's first frame for the weight shift, that much later while the other foot
        (``other_down`` (T,) bool) is still down."""
        k_swing, k_shift, T = self.n(self.cfg.swing_s), self.n(self.cfg.shift_s), len(other_down)
        lift = min(max(land - k_swing, k_shift), T - 2)
        end = lift + k_swing
        while end > land and not other_down[min(end, T - 1)]:
            end -= 1  # the other foot lifts before: land in time for it
        return lift, min(max(end, lift + self.n(self.cfg.min_swing_s)), T - 1)

    def _shift_over(self, clip: np.ndarray, st: int, lift: int, land: int) -> None:
        """In place: the body (pelvis, upper body, knees by half) of ``clip`` (T, 22, 3) moved
        ``shift_share`` of the way over the stance foot ``st``'s ankle while the other foot swings
        (frames lift..land−1), ramping in over ``shift_s`` before the lift and out over
        ``double_s`` after the landing (minimum-jerk)."""
        cfg, T = self.cfg, len(clip)
        k_in, k_out = self.n(cfg.shift_s), self.n(cfg.double_s)
        body = [PELVIS] + self.upper
        for i in range(max(lift - k_in, 0), min(land + k_out, T)):
            if i < lift:
                w = float(min_jerk_share(np.array((i - (lift - k_in)) / k_in)))
            elif i < land:
                w = 1.0
            else:
                w = 1.0 - float(min_jerk_share(np.array((i - land + 1) / k_out)))
            d = np.zeros(3)
            d[0:2] = cfg.shift_share * w * (clip[i, ANKLE[st], 0:2] - clip[i, PELVIS, 0:2])
            clip[i, body] += d
            clip[i, [L_KNEE, R_KNEE]] += 0.5 * d

    @staticmethod
    def _leg_of(target: np.ndarray, s: int, frame: np.ndarray) -> np.ndarray:
        """``frame`` (22, 3) with foot ``s``'s ankle and toe from ``target`` (22, 3) and its knee
        moved by half the ankle's shift."""
        out = frame.copy()
        shift = target[ANKLE[s]] - frame[ANKLE[s]]
        out[ANKLE[s]], out[TOE[s]] = target[ANKLE[s]], target[TOE[s]]
        out[KNEE[s]] += 0.5 * shift
        return out

    def eased_clip(self, ease: float) -> tuple[np.ndarray, np.ndarray, list]:
        """4. the clip's frames on the trajectory's clock, its first ``ease`` s eased in from rest,
        each held foot on the floor until its swing to the person's landing; their contact labels
        (T, 4) and each held foot's swing start in clip time (s; None: it never lands)."""
        motion, p, fps = self.motion, self.p, self.fps
        t_clip = motion.times
        u_end = t_clip[-1] + 0.5 * ease  # the trajectory time of the clip's last frame
        u = np.arange(int(math.floor(u_end * fps + 1e-9)) + 1) / fps
        tau = np.minimum(_warp(u, ease), t_clip[-1])
        idx = np.clip(np.searchsorted(t_clip, tau, side="right") - 1, 0, motion.n_frames - 1)
        nxt = np.minimum(idx + 1, motion.n_frames - 1)
        span = np.maximum(t_clip[nxt] - t_clip[idx], 1e-12)
        a = np.where(nxt > idx, (tau - t_clip[idx]) / span, 0.0)[:, None, None]
        clip = (1 - a) * p[idx] + a * p[nxt]
        near = np.where(a[:, 0, 0] > 0.5, nxt, idx)
        c4 = self.c4[near].copy()
        swing_from = []
        for s in self.held:
            down = np.flatnonzero(c4[:, 2 * s] | c4[:, 2 * s + 1])
            land = int(down[0]) if down.size else len(u)
            if land >= len(u):  # the person never puts it down: it stays down
                c4[:, 2 * s : 2 * s + 2] = True
                for i in range(len(u)):
                    clip[i] = self._with_feet(clip[i], {s: self.first_feet[s]})
                swing_from.append(None)
                continue
            lift, land = self._held_swing(land, c4[:, 2 * (1 - s)] | c4[:, 2 * (1 - s) + 1])
            self._shift_over(clip, 1 - s, lift, land)
            on_floor = [self._with_feet(f, {s: self.first_feet[s]}) for f in clip[:land]]
            target = clip[min(land, len(clip) - 1)]
            for i in range(land):  # on the floor until the lift, then to where the person landed
                w = 0.0 if i < lift else float(min_jerk_share(np.array((i - lift + 1) / (land - lift))))
                clip[i] = on_floor[i] + w * (self._leg_of(target, s, on_floor[i]) - on_floor[i])
                c4[i, 2 * s : 2 * s + 2] = i < lift
            swing_from.append(round(float(tau[lift]), 3))
        return clip, c4, swing_from


def with_lead_in(traj, lead: LeadIn, contacts4=None):
    """The robot trajectory made from a lead-in motion, with the lead-in reported: ``meta``'s
    ``lead_in`` (:meth:`LeadIn.to_dict`) and ``t0_s`` (trajectory time of the clip's first
    frame), ``changes`` in clip time (negative before the clip) with a ``lead-in`` and an
    ``eased in`` change first, ``steps`` counted from the clip's first frame on (the lead-in's
    own steps in ``steps["lead_in"]``). A re-timed trajectory (``meta["retime"]`` f) keeps its
    times in the slowed clip's seconds like every other change (the lead-in scaled by f).
    ``contacts4`` (T', 4): the lead-in motion's person contacts, for the person's step count."""
    from dataclasses import replace

    meta = dict(traj.meta)
    f = float(meta.get("retime", 1.0))
    lead = replace(lead, fps=lead.fps / f, ease_s=lead.ease_s * f)
    t0 = lead.t0_s
    changes = []
    for c in meta.get("changes", []) or []:
        a, b = (float(lead.clip_time(x)) for x in (c["start_s"], c["end_s"]))
        changes.append({**c, "start_s": round(a, 3), "end_s": round(b, 3)})
    feet = lambda names: " and ".join(names) + (" foot" if len(names) == 1 else " feet")  # noqa: E731
    how = "stands at rest in its standing stance"
    if lead.steps:
        how += f", steps the {feet(lead.steps)} to the first frame's place"
    if lead.held:
        how += f", puts the {feet(lead.held)} down below the first frame's (in the air there)"
    head = [
        Change(
            round(-t0, 3),
            0.0,
            "lead-in",
            f"the clip starts mid-motion ({lead.why}): {t0:.2f} s before it the robot {how} and moves into "
            "its first pose, ending at rest",
        ),
    ]
    if lead.ease_s > 0:
        head.append(
            Change(
                0.0,
                round(lead.delay_s, 3),
                "eased in",
                f"the clip's first {lead.delay_s:.2f} s play from rest over {lead.ease_s:.2f} s (speed ramping "
                f"from 0 to 1); the rest plays {lead.delay_s:.2f} s later than the clip's own time",
            )
        )
    for side, start in zip(lead.held, lead.swing_from_s):
        if start is None:
            head.append(Change(0.0, 0.0, "held down", f"the {side} foot, in the air in the first frame, stays down"))
        else:
            head.append(
                Change(
                    0.0,
                    start,
                    "held down",
                    f"the {side} foot, in the air in the first frame, stays on the floor below it until "
                    f"{start:.2f} s and then swings to where the person puts it down",
                )
            )
    meta["changes"] = [c.to_dict() for c in head] + sorted(changes, key=lambda c: c["start_s"])
    meta["lead_in"] = lead.to_dict()
    meta["t0_s"] = round(t0, 6)
    steps = dict(meta.get("steps") or {})
    n = lead.frames
    if meta.get("contacts") is not None:
        planned = np.asarray(meta["contacts"], dtype=bool)
        steps["robot"], steps["lead_in"] = count_steps(planned[n:]), count_steps(planned[: n + 1])
    if contacts4 is not None:
        steps["person"] = count_steps(side_contacts(np.asarray(contacts4, dtype=bool))[n:])
    meta["steps"] = steps
    return replace(traj, meta=meta)


def lead_in_of(traj) -> LeadIn | None:
    """The lead-in a trajectory starts with (its ``meta["lead_in"]``, times in its own seconds), or None."""
    d = traj.meta.get("lead_in")
    return LeadIn.from_dict(d) if isinstance(d, dict) else None

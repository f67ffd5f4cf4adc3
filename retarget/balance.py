"""The streaming retargeter's balance planner: planted feet, steps, the support region, the targets' anchoring.

Contract: with ``StreamingConfig.balance`` the :class:`retarget.streaming.StreamingRetargeter`
asks a :class:`BalancePlanner` once per frame for the anchored targets (:meth:`BalancePlanner.anchor`),
the feet held down (:meth:`BalancePlanner.plan`), a swinging foot's path and height, and the
support region's half-planes and the CoM/DCM/ZMP row parameters (in a step, the CoM of a ZMP
preview plan: :mod:`retarget.preview`), which it writes into the compiled function's parameter
buffer (numpy views bound once, :meth:`BalancePlanner.bind`). Lengths m, times s. The rules
(footprints, the feet's region, when a foot lifts, how it swings and where it lands):
docs/retargeting.md, section 4.
"""

from __future__ import annotations

import math

import numpy as np

from retarget.errors import RetargetError
from retarget.preview import ZmpPreview
from retarget.step_turn import step_turn_limits
from retarget.support import (
    convex_hull,
    double_support_points,
    halfplanes,
    level_footprint,
)

#: half-planes of the balance region passed to the compiled function (the two-foot region has
#: 4 corners; unused rows are 0·c ≤ 1); kept at 6, the compiled function's parameter size
N_EDGES = 6


class BalancePlanner:
    """Planted feet, support region and target anchoring for one free-standing robot (see the
    module docstring). ``planted`` (2,) bool, ``offset`` (x, y) m and the heading
    turn ``psi`` rad of the anchoring are public state."""

    def __init__(self, robot, config, fps: float):
        rb, cfg = robot, config
        self.robot, self.config, self.fps = robot, config, float(fps)
        names = rb.keypoint_names
        index = {n: names.index(n) for n in names}
        self._ankles = [index[n] for n in ("left_ankle", "right_ankle") if n in index]
        self._toes = [index[n] for n in ("left_foot", "right_foot") if n in index]
        self._hips = [index[n] for n in ("left_hip", "right_hip") if n in index]
        if len(self._ankles) < 2 or (len(self._toes) < 2 and len(self._hips) < 2):
            raise RetargetError(
                f"{rb.profile.source or rb.name}: field keypoints: streaming balance needs left_ankle "
                "and right_ankle keypoints, and left/right_foot or left/right_hip ones (it follows the "
                "person's feet); add them or turn balance off"
            )
        self._toes = self._toes if len(self._toes) == 2 else None
        self._hips = self._hips if len(self._hips) == 2 else None
        self._foot_kps = [[self._ankles[s]] + ([self._toes[s]] if self._toes else []) for s in range(2)]
        self._foot_kp_h = [rb.standing_heights[k] for k in self._foot_kps]
        self._feet_idx = self._ankles + (self._toes if self._toes is not None else self._hips)
        # the body turned towards the person's heading ahead of the feet (``body_twist``):
        # everything above the knees (the hip yaw joints turn the pelvis over the legs)
        below = {index[n] for n in ("left_knee", "right_knee") if n in index}
        below |= set(self._ankles) | set(self._toes or ())
        self._twisted = [k for k in range(len(names)) if k not in below]
        stand = rb.evaluate(rb.x_stand[None])
        self._stand_kp = stand["keypoints"][0]
        h = float(stand["com"][0, 2] - stand["sole"][0, :, 2].min())
        self._zmp_k = h / 9.81 * self.fps**2  # ZMP = c − (h/g) c̈ = (1 − k) c + k (2c₋₁ − c₋₂)
        self._dcm_k = self.fps * np.sqrt(h / 9.81)  # DCM = c + ċ/ω = (1 + k) c − k c₋₁
        self._zmp_scale = np.sqrt(cfg.zmp_weight) * self._zmp_k
        self._w = np.sqrt([cfg.balance_weight, cfg.dcm_weight, cfg.zmp_limit_weight])
        self._w0 = np.sqrt([cfg.balance_weight, 0.0, 0.0])
        self._sole_local = [f.corners for f in rb.feet]
        self._anchor_alpha = 1.0 - math.exp(-1.0 / (self.fps * cfg.anchor_time))
        self._max_swing_frames = round(cfg.max_swing * self.fps)
        self._k = None  # the pace the step phases were last set for (_set_pace)
        # leg length (hip above ankle standing; the CoM height without hip keypoints): scales step lengths
        legs = [self._stand_kp[hip, 2] - self._stand_kp[ankle, 2] for hip, ankle in zip(self._hips or (), self._ankles)]
        self._leg = float(np.mean(legs)) if legs else h
        _check_step_timing(cfg, self.fps)
        frames = lambda t: max(0, round(t * self.fps))  # noqa: E731
        self._preview = ZmpPreview(h / 9.81 * self.fps**2, max(2, frames(cfg.step_preview)))
        self._set_pace(1.0)
        # the smoothing row's CoM prediction: the last velocity, decaying by this share a frame
        self._com_decay = math.exp(-1.0 / (self.fps * cfg.com_velocity_decay))
        #: how far a step may turn a foot from the other (toes out, toes in) rad: retarget.step_turn
        self.turn_limits = step_turn_limits(rb, cfg.max_step_turn, cfg.step_turn_clearance)
        if cfg.step_turn_clearance > 0 and cfg.max_step_turn > 0 and max(self.turn_limits) == 0:
            raise RetargetError(
                f"StreamingConfig: step_turn_clearance {cfg.step_turn_clearance:g} m leaves "
                f"{rb.profile.source or rb.name}'s legs no turn at all between steps (its capsule pairs off "
                "the feet stand closer than that); lower it"
            )
        self._plan_scale = math.sqrt(cfg.plan_weight)
        # each sole's centre from its ankle keypoint standing, in the foot's heading frame (the
        # stand pose faces +x): where a swinging foot's targets would put its footprint
        soles = stand["sole"][0]
        self._sole_from_ankle = [
            soles[4 * s : 4 * s + 4, 0:2].mean(axis=0) - self._stand_kp[self._ankles[s], 0:2] for s in range(2)
        ]
        # the stand pose about the midpoint of its soles' centres, and its heights above the
        # floor (the profile's standing_heights are its rest pose's): stand_over_feet
        mid = 0.5 * (soles[0:4, 0:2].mean(axis=0) + soles[4:8, 0:2].mean(axis=0))
        self._stand_about_mid = self._stand_kp[:, 0:2] - mid
        self._stand_sole_about_mid = [soles[4 * s : 4 * s + 4, 0:2].mean(axis=0) - mid for s in range(2)]
        self._stand_z = self._stand_kp[:, 2] - float(soles[:, 2].min())
        # each toe keypoint's distance from its ankle's, standing (own_feet, stand_over_feet)
        toes = self._toes or ()
        self._toe_reach = [
            float(np.linalg.norm(self._stand_kp[t, 0:2] - self._stand_kp[a, 0:2])) for a, t in zip(self._ankles, toes)
        ]

    def _set_pace(self, k: float) -> None:
        """The step's phases at ``k`` x their configured lengths: ``min_stance``, ``min_double``,
        ``step_shift`` and ``min_swing`` (at least 2 frames)."""
        if k == self._k:  # called every frame on both feet: the phases change only with k
            return
        self._k = k
        cfg = self.config
        frames = lambda t: max(0, round(t * k * self.fps))  # noqa: E731
        self._min_stance_frames = frames(cfg.min_stance)
        self._min_swing_frames = max(2, frames(cfg.min_swing))
        self._min_double_frames = frames(cfg.min_double)
        self._shift_frames = frames(cfg.step_shift)
        self._rise_frames, self._fall_frames = _halves(self._min_swing_frames)
        self._settle_frames = self._min_double_frames + max(0, round(cfg.step_settle * self.fps))

    def _person_pace(self) -> float:
        """How much shorter than configured the next step's phases are (``pace_floor`` .. 1): the
        person's step period (frames between its last two lift-offs, either foot, or since the
        last one if longer) against the robot's configured cycle (``min_double`` + ``step_shift``
        + ``min_swing``). A person stepping faster than the quickest pace is followed at it, and
        the steps the robot has no time for are skipped."""
        cfg = self.config
        lifts = self._person_lifts
        if cfg.pace_floor >= 1.0 or len(lifts) < 2:
            return 1.0
        cycle = (cfg.min_double + cfg.step_shift + cfg.min_swing) * self.fps
        period = max(lifts[-1] - lifts[-2], self._frame - lifts[-1])
        return min(1.0, max(cfg.pace_floor, period / cycle))

    def bind(self, anchor: np.ndarray, edges, points, point_w, cpred, zmp, lift) -> None:
        """Where to write: the contact rows' anchor (2, 8) and views into the parameter buffer
        for the region's half-planes (3·N_EDGES), the rows' (3, 3) points, their √weights (3),
        the CoM prediction (2), the ZMP-offset scale (1) and the swing rows' parameters: the
        soles' heights (2), then their on/off flags (2)."""
        self._anchor, self._edges, self._points, self._point_w, self._cpred, self._zmp, self._lift_h = (
            anchor,
            edges,
            points,
            point_w,
            cpred,
            zmp,
            lift,
        )

    def reset(self) -> None:
        """No feet planted, no history; no balance rows until :meth:`start` plants the feet."""
        self.planted = np.zeros(2, dtype=bool)
        self._prints: list = [None, None]  # level footprints (4, 2) of the planted feet
        self._lift_print: list = [None, None]  # ... and of each foot where it last lifted
        self._region_key = None
        self._c1 = self._c2 = None  # CoM xy of the last two emitted frames
        self._sole1 = None  # the last frame's sole corners (3, 8)
        #: the anchoring transform: offset (x, y) m and turn psi rad; the ankle targets and foot
        #: headings recorded when each foot touched down
        self.offset = (0.0, 0.0)
        self.psi = 0.0
        self._pelvis_xy = None  # the pelvis target's place under the anchoring, last frame
        self._ankle_ref = [(0.0, 0.0), (0.0, 0.0)]
        self._head_ref = [0.0, 0.0]
        self._since = np.zeros(2, dtype=int)  # frames since each foot last touched down or lifted
        self._descend_at = [None, None]  # a swinging foot's frame of its swing when it began to come down
        self._swing_heading = [None, None]  # a swinging foot's heading on its path (rad)
        self._frame = 0  # frames since start()
        self._shifting = None  # (foot, frame it lifts at) while the weight moves before a step
        self._lift_by = self._lifted_at = -1  # ... the latest frame it may lift at, and when it did
        self._zmp_keys = None  # the step's ZMP reference: (frames, points (n, 2)), linear in between
        self._plan_until = -1  # the last frame the CoM follows the preview plan
        self._person_down = np.ones(2, dtype=bool)  # the person's feet down last frame
        self._person_lifts: list[int] = []  # frames of the person's last lift-offs (either foot)
        self._person_up_at = [None, None]  # the frame each of the person's feet lifted, while it is up
        self._person_swing = None  # frames the person's last finished swing (either foot) lasted
        self._set_pace(1.0)
        self._edges[:] = np.tile([0.0, 0.0, 1.0], N_EDGES)
        self._points[:] = 0.0
        self._point_w[:] = 0.0
        self._cpred[:] = 0.0
        self._zmp[:] = 0.0
        self._lift_h[:] = 0.0  # heights (2,) and flags (2,) of the swing rows

    def start(self, sole: np.ndarray, com_xy: np.ndarray) -> tuple[bool, bool]:
        """First frame: both feet put down flat where the fit left them (``sole`` (3, 8), CoM
        xy (2,)); returns the feet to hold."""
        self._sole1 = sole.copy()
        self._c1 = self._c2 = com_xy.copy()
        for s in range(2):
            self.touch_down(s)
        self._stand_sep = float(np.linalg.norm(self._prints[0].mean(axis=0) - self._prints[1].mean(axis=0)))
        held = self.plan((True, True))
        self.set_points(True)
        return held

    def next(self, human_contact, targets: np.ndarray) -> tuple[bool, bool]:
        """Any later frame: plan the feet, put a lifted foot's targets on its swing path
        (``targets`` changed in place), set the row parameters; returns the feet to hold."""
        held = self.plan(human_contact)
        cfg = self.config
        for s in range(2):
            lift = self._lift_h[s] = self._swing_lift(s)
            self._lift_h[2 + s] = 0.0 if self.planted[s] else 1.0
            if not self.planted[s]:
                k = self._foot_kps[s]
                # clear the floor as the swing does: a foot the person barely lifts would drag
                low = self._foot_kp_h[s] + lift
                targets[k, 2] = np.clip(targets[k, 2], low, self._foot_kp_h[s] + max(cfg.swing_height, lift))
                aimed = self._sole_centre(targets, s)
                self._landing = self._clamp_step(aimed, s) if self.planted[1 - s] else aimed
                targets[k, 0:2] += self._swing_path(s) - aimed
        self.set_points(False)
        return held

    def _sole_centre(self, targets: np.ndarray, s: int) -> np.ndarray:
        """(2,) where foot s's ankle target and the person's foot heading put its sole's centre."""
        c, sn = math.cos(self._heads_now[s]), math.sin(self._heads_now[s])
        ox, oy = self._sole_from_ankle[s]
        return targets[self._ankles[s], 0:2] + (c * ox - sn * oy, sn * ox + c * oy)

    def _swing_frames(self, s: int) -> int:
        """How long foot s's swing takes (frames): its rise and fall (:meth:`_swing_time`),
        longer for a step longer than ``swing_speed`` covers in that time, at most ``max_swing``."""
        dist = float(np.linalg.norm(self._landing - self._lift_print[s].mean(axis=0)))
        n = math.ceil(dist / self.config.swing_speed * self.fps)
        return min(max(n, self._rise_frames + self._fall_frames), self._max_swing_frames)

    def _swing_path(self, s: int) -> np.ndarray:
        """Foot s's sole in this frame of its swing, written as the swing rows' anchor (its
        corners xy): the footprint it lifted from, moved towards the landing place and turned
        towards the person's foot heading (as far as :meth:`_landing_heading` allows) by the share
        sin²(π/2 · swing / its length) of the way (:meth:`_swing_frames`); the centre travels
        around the stance foot's centre (radius and bearing interpolated), so a foot crossing
        from behind to the front never passes through the other. Returns the sole's centre (2,)."""
        start = self._lift_print[s]
        c0 = start.mean(axis=0)
        u = min(1.0, int(self._since[s]) / self._swing_frames(s))
        share = math.sin(0.5 * math.pi * u) ** 2
        h0 = self._head_ref[s]  # the heading of the footprint it lifted from (touch_down)
        turn = share * _wrap(self._landing_heading(s) - h0)
        self._swing_heading[s] = h0 + turn  # where the foot points now: names its axis's direction at touch-down
        c, sn = math.cos(turn), math.sin(turn)
        if self.planted[1 - s]:  # around the stance foot's centre, not through it
            cs = self._prints[1 - s].mean(axis=0)
            a, b = c0 - cs, self._landing - cs
            r = (1 - share) * math.hypot(*a) + share * math.hypot(*b)
            th = math.atan2(a[1], a[0]) + share * _wrap(math.atan2(b[1], b[0]) - math.atan2(a[1], a[0]))
            centre = cs + r * np.array([math.cos(th), math.sin(th)])
        else:
            centre = c0 + share * (self._landing - c0)
        self._anchor[:, 4 * s : 4 * s + 4] = ((start - c0) @ np.array([[c, sn], [-sn, c]]) + centre).T
        return centre

    def _landing_heading(self, s: int) -> float:
        """The heading (rad) the lifted foot s lands with: the person's own foot heading (not the
        anchored one: a pivot on a planted foot that the anchoring absorbed is made up by
        stepping), toed out or in from the stance foot's at most as far as the robot's legs allow
        (:func:`retarget.step_turn.step_turn_limits` with ``step_turn_clearance``, at most
        ``max_step_turn``)."""
        want = self._heads_person[s]
        if not self.planted[1 - s]:
            return want
        hs = self._head_ref[1 - s]
        out, toe_in = self.turn_limits  # the left foot's heading minus the right's: + is toes out
        lo, hi = (-toe_in, out) if s == 0 else (-out, toe_in)
        return hs + min(max(_wrap(want - hs), lo), hi)

    def _swing_lift(self, s: int) -> float:
        """How high foot s's sole is held above the floor this frame (m): 0 planted; in a swing,
        ``swing_clearance`` x sin²(π/2 · rise) while it rises, held while the person's foot is up,
        x cos²(π/2 · fall) while it comes down (rise and fall: the share of each half of the
        step's swing time done, :meth:`_swing_time`). A servo robot's stance leg sags by about
        a centimetre under the whole weight: a foot aimed only just above the floor drags."""
        if self.planted[s]:
            return 0.0
        swing, down_at = int(self._since[s]), self._descend_at[s]
        up = min(swing if down_at is None else down_at, self._rise_frames) / self._rise_frames
        share = math.sin(0.5 * math.pi * up) ** 2
        if down_at is not None:
            share *= math.cos(0.5 * math.pi * min((swing - down_at) / self._fall_frames, 1.0)) ** 2
        return self.config.swing_clearance * share

    def _clamp_step(self, centre_s: np.ndarray, s: int) -> np.ndarray:
        """Where the robot can put the lifted foot s whose sole the person's foot would put at
        ``centre_s`` (2,): in the planted foot's frame (its footprint's centre and long axis,
        pointing along the foot's heading), at least ``min_separation`` x the standing feet's
        distance (sole centre to sole centre) to its own side (a person's narrower, crossed or
        closed feet would put the robot's into its other leg), and at most ``stride_limit`` x
        the leg length forwards, backwards and outwards from where it would stand beside the
        stance foot (at the standing distance). A foot landing
        turned by δ from the stance foot (toes in or out) sweeps its inner corners inwards by
        l·|sin δ| − w·(1 − cos δ) (half length l, half width w): it lands that much further out."""
        cfg = self.config
        fp = self._prints[1 - s]
        centre = fp.mean(axis=0)
        axis = np.array([math.cos(self._head_ref[1 - s]), math.sin(self._head_ref[1 - s])])  # its long axis
        side = np.array([-axis[1], axis[0]]) * (1.0 if s == 0 else -1.0)  # towards foot s's own side
        half_l, half_w = np.abs((fp - centre) @ axis).max(), np.abs((fp - centre) @ side).max()
        delta = _wrap(self._landing_heading(s) - self._head_ref[1 - s])
        turned = max(0.0, half_l * abs(math.sin(delta)) - half_w * (1.0 - math.cos(delta)))
        rel = np.asarray(centre_s) - centre
        along, across = float(rel @ axis), float(rel @ side)
        reach = cfg.stride_limit * self._leg
        want_along = min(max(along, -reach), reach)
        closest = cfg.min_separation * self._stand_sep + turned
        want_across = min(max(across, closest), max(closest, self._stand_sep + reach))
        return centre + want_along * axis + want_across * side

    def record(self, sole: np.ndarray, com_xy: np.ndarray) -> None:
        """The emitted frame's sole corners (3, 8) and CoM xy (2,)."""
        self._sole1 = sole.copy()
        self._c2 = self._c1
        self._c1 = com_xy.copy()

    def anchor(self, targets: np.ndarray, contact, first: bool) -> np.ndarray:
        """Move the targets by a horizontal rigid transform T(p) = R(ψ) p + o so that the
        person's feet that are down, where the robot's are planted too, stay where (and
        turned as) their targets were when the robot's foot touched down.

        With a_s, θ_s the person's ankle target (xy) and foot heading (ankle → toe; the hips'
        facing direction for a profile without toe keypoints) of each such foot and r_s, φ_s
        their values under T at touch-down, the raw transform is
        ψ* = mean_s (φ_s − θ_s), o* = mean_s r_s − R(ψ*) mean_s a_s; ψ and the image of the
        pivot p = mean_s a_s move towards it by α = 1 − exp(−1 / (fps τ)), τ = ``anchor_time``.
        The robot then follows the person's steps (and turns step by step), not the drift,
        turning on the spot or skating of the feet (generated motion often slides them),
        which it could not do standing. With ``body_twist`` the body above the knees is then
        turned back towards the person's heading about the pelvis target, by
        limit·tanh(−ψ / limit) (faded out as |ψ| goes from π/2 to π, where it would flip sides):
        the hips turn the trunk ahead of feet that lag the person's turn. While no foot is
        both down and planted (the person in the air, or on the foot the robot has lifted),
        the transform is not updated and the pelvis target is held where it was: the person's
        travel then is not followed."""
        feet = targets[self._feet_idx, 0:3].tolist()  # left/right ankle, then left/right toe or hip
        (lx, ly, lz), (rx, ry, rz) = feet[0], feet[1]
        if self._toes is not None:
            heads = [math.atan2(feet[2][1] - ly, feet[2][0] - lx), math.atan2(feet[3][1] - ry, feet[3][0] - rx)]
        else:
            h = math.atan2(-(feet[2][0] - feet[3][0]), feet[2][1] - feet[3][1])
            heads = [h, h]
        ankles = ((lx, ly), (rx, ry))
        if not first:
            # without steps both feet stay planted: the person's two feet (down or not) anchor
            # their midpoint, so a walking person's pelvis stays over the robot's feet
            ref = [s for s in range(2) if (contact[s] or not self.config.steps) and self.planted[s]]
            if ref:
                n = len(ref)
                sx = sum(math.cos(self._head_ref[s] - heads[s]) for s in ref)
                sy = sum(math.sin(self._head_ref[s] - heads[s]) for s in ref)
                psi_raw = math.atan2(sy, sx)
                px, py = sum(ankles[s][0] for s in ref) / n, sum(ankles[s][1] for s in ref) / n
                qx, qy = sum(self._ankle_ref[s][0] for s in ref) / n, sum(self._ankle_ref[s][1] for s in ref) / n
                c, sn = math.cos(self.psi), math.sin(self.psi)
                ox, oy = self.offset
                al = self._anchor_alpha
                # the pivot's image moves from T(p) towards T*(p) = mean r_s
                tx = (1 - al) * (c * px - sn * py + ox) + al * qx
                ty = (1 - al) * (sn * px + c * py + oy) + al * qy
                d = (psi_raw - self.psi + math.pi) % (2 * math.pi) - math.pi
                self.psi += al * d
                c, sn = math.cos(self.psi), math.sin(self.psi)
                self.offset = (tx - (c * px - sn * py), ty - (sn * px + c * py))
            elif self._pelvis_xy is not None:
                # no foot to anchor on: the person in the air (a jump, a run, a generated
                # partner's hop), or running on the foot the robot has lifted for a step of
                # its own. Its travel is not followed, the pelvis target held where it was:
                # the robot leaned after targets out of reach (bowed 43° and fell in the air;
                # on the demo's partner, dashing at 1.8 m/s on the foot the robot had lifted,
                # the pelvis target ran 0.11 m ahead of the robot's pelvis (7 mm held) and the
                # robot, pitched 13°, ended the stream tipped 20° in physics (11° held))
                c, sn = math.cos(self.psi), math.sin(self.psi)
                x, y = targets[self.robot.root_keypoint, 0:2]
                self.offset = (self._pelvis_xy[0] - (c * x - sn * y), self._pelvis_xy[1] - (sn * x + c * y))
        c, sn = math.cos(self.psi), math.sin(self.psi)
        ox, oy = self.offset
        x, y = targets[self.robot.root_keypoint, 0:2]
        self._pelvis_xy = (c * x - sn * y + ox, sn * x + c * y + oy)
        self._ankles_now = [(c * x - sn * y + ox, sn * x + c * y + oy) for x, y in ankles]
        self._heads_now = [heads[0] + self.psi, heads[1] + self.psi]
        self._heads_person = heads
        self._ankle_z = (lz, rz)
        return self.placed(targets, first)

    def placed(self, targets: np.ndarray, first: bool = False) -> np.ndarray:
        """``targets`` (K, 3) moved by the present anchoring transform, the body above the knees
        turned by ``body_twist`` (not on the first frame), as :meth:`anchor` returns them; no
        state changes."""
        c, sn = math.cos(self.psi), math.sin(self.psi)
        ox, oy = self.offset
        out = targets @ np.array([[c, sn, 0.0], [-sn, c, 0.0], [0.0, 0.0, 1.0]]) + np.array([ox, oy, 0.0])
        limit = self.config.body_twist
        if limit > 0 and not first:
            lag = _wrap(self.psi)
            # faded out from a lag of π/2 to π, where the wrap would flip it by 2·limit in one frame
            fade = math.cos(max(0.0, abs(lag) - 0.5 * math.pi)) ** 2
            self._twist(out, fade * limit * math.tanh(-lag / limit))
        return out

    def _twist(self, out: np.ndarray, angle: float) -> None:
        """Turn the body above the knees by ``angle`` rad about the pelvis target, in place: the
        anchoring turned the whole body with the planted feet."""
        root = out[self.robot.root_keypoint, 0:2].copy()
        c, sn = math.cos(angle), math.sin(angle)
        idx = self._twisted
        out[idx, 0:2] = root + (out[idx, 0:2] - root) @ np.array([[c, sn], [-sn, c]])

    def neutral_stance(self, targets: np.ndarray) -> np.ndarray:
        """``targets`` (K, 3) with the ankle and toe targets moved to where the robot's stand
        pose puts them relative to its pelvis, turned to the person's hip heading and placed
        under the pelvis target (a person caught mid-stride would otherwise plant the robot's
        feet in a stride it cannot balance on)."""
        if self._hips is None:
            return targets
        out = targets.copy()
        across = targets[self._hips[0], 0:2] - targets[self._hips[1], 0:2]
        yaw = math.atan2(-across[0], across[1])
        c, sn = math.cos(yaw), math.sin(yaw)
        root = self.robot.root_keypoint
        for k in self._foot_kps[0] + self._foot_kps[1]:
            dx, dy = self._stand_kp[k, 0:2] - self._stand_kp[root, 0:2]
            out[k, 0] = targets[root, 0] + c * dx - sn * dy
            out[k, 1] = targets[root, 1] + sn * dx + c * dy
            out[k, 2] = self.robot.standing_heights[k]
        return out

    # -- the end of a stream (retarget.settle): in the robot's own frame ----------------------
    def rebase(self) -> None:
        """From now on the targets are given in the robot's frame: the anchoring transform is
        the identity (and the body twist with it). The footprints, anchors and pelvis place are
        kept: they are in the robot's frame already."""
        self.psi, self.offset = 0.0, (0.0, 0.0)

    @property
    def foot_keypoints(self) -> list:
        """Per foot (left, right), the indices of its keypoints (ankle, and toe where there is one)."""
        return self._foot_kps

    def own_feet(self, targets: np.ndarray) -> None:
        """The ankle and toe targets of each planted foot put (in place) where the anchoring
        holds it, toe straight ahead along the foot's heading: after :meth:`rebase` such
        targets keep the anchoring the identity."""
        for s in range(2):
            if not self.planted[s]:
                continue
            ankle = np.asarray(self._ankle_ref[s])
            targets[self._ankles[s], 0:2] = ankle
            targets[self._ankles[s], 2] = self._stand_z[self._ankles[s]]
            if self._toes is not None:
                t, h = self._toes[s], self._head_ref[s]
                targets[t, 0:2] = ankle + self._toe_reach[s] * np.array([math.cos(h), math.sin(h)])
                targets[t, 2] = self._stand_z[t]

    def stand_over_feet(self, body: np.ndarray) -> np.ndarray:
        """(K, 3) the robot's stand pose over its planted feet (robot frame), facing where the
        hips of ``body`` (K, 3) face (the feet turn to it by stepping: the body is not turned
        over planted feet; without hip keypoints, the feet's mean heading): its soles' midpoint
        where theirs is (one foot planted: beside it; none: under the pelvis of ``body``), each
        toe target straight ahead of its ankle (a step lands the sole along ankle → toe; the
        stand pose's toe keypoints sit off the soles' axes, op3: 0.2 rad)."""
        down = [s for s in range(2) if self.planted[s]]
        if self._hips is not None:
            across = body[self._hips[0], 0:2] - body[self._hips[1], 0:2]
            yaw = math.atan2(-across[0], across[1])
        elif down:
            heads = [self._head_ref[s] for s in down]
            yaw = math.atan2(sum(map(math.sin, heads)), sum(map(math.cos, heads)))
        else:
            yaw = 0.0
        rot = np.array([[math.cos(yaw), math.sin(yaw)], [-math.sin(yaw), math.cos(yaw)]])
        if down:
            mid = np.mean([self._prints[s].mean(axis=0) - self._stand_sole_about_mid[s] @ rot for s in down], axis=0)
        else:
            mid = body[self.robot.root_keypoint, 0:2] - self._stand_about_mid[self.robot.root_keypoint] @ rot
        out = np.empty_like(body)
        out[:, 0:2] = self._stand_about_mid @ rot + mid
        out[:, 2] = self._stand_z
        if self._toes is not None:
            for ankle, toe, reach in zip(self._ankles, self._toes, self._toe_reach):
                out[toe, 0:2] = out[ankle, 0:2] + reach * np.array([math.cos(yaw), math.sin(yaw)])
        return out

    def stance_offsets(self, targets: np.ndarray) -> list | None:
        """How far each planted foot is from where ``targets`` (K, 3, robot frame: after
        :meth:`rebase`) put it: per foot (left, right) (distance of the sole centres m, turn
        from the foot heading of ankle → toe rad); None while a foot is up."""
        if not self.planted.all():
            return None
        feet = targets[self._feet_idx, 0:2]
        out = []
        for s in range(2):
            h = math.atan2(*(feet[2 + s] - feet[s])[::-1]) if self._toes is not None else self._head_ref[s]
            c, sn = math.cos(h), math.sin(h)
            ox, oy = self._sole_from_ankle[s]
            centre = feet[s] + (c * ox - sn * oy, sn * ox + c * oy)
            dist = float(np.linalg.norm(self._prints[s].mean(axis=0) - centre))
            out.append((dist, abs(_wrap(self._head_ref[s] - h))))
        return out

    def set_points(self, first: bool) -> None:
        """Parameters of the CoM, DCM and ZMP rows and the CoM prediction (module docstring)."""
        (c1x, c1y), (c2x, c2y) = self._c1, self._c2
        px, py = 2 * c1x - c2x, 2 * c1y - c2y
        kd, kz = self._dcm_k, self._zmp_k
        # (3, 3) column-major: columns com, dcm, zmp of rows α, β_x, β_y
        self._points[:] = (1.0, 0.0, 0.0, 1.0 + kd, -kd * c1x, -kd * c1y, 1.0 - kz, kz * px, kz * py)
        self._point_w[:] = self._w0 if first else self._w
        g = self._com_decay  # the CoM's velocity, decaying towards rest
        self._cpred[:] = (c1x + g * (c1x - c2x), c1y + g * (c1y - c2y))
        self._zmp[:] = 0.0 if first else self._zmp_scale
        if not first and self._frame <= self._plan_until:
            # during a step the CoM row follows the preview plan instead of the smooth prediction
            self._cpred[:] = self._preview.next_com(self._c1, self._c2, self._zmp_reference())
            self._zmp[:] = self._plan_scale

    def _zmp_reference(self) -> np.ndarray:
        """(N, 2): the step's ZMP reference for this frame and the preview's next N − 1."""
        frames, points = self._zmp_keys
        t = np.arange(self._frame, self._frame + self._preview.frames)
        return np.stack([np.interp(t, frames, points[:, 0]), np.interp(t, frames, points[:, 1])], axis=1)

    def plan(self, human_contact) -> tuple[bool, bool]:
        """Update :attr:`planted` from the person's contacts, and set the anchors and the balance
        region in the parameter buffer. Returns the contacts (left, right) the solver holds on the
        ground this frame. Without ``steps`` both feet stay planted; with them, see :meth:`_paced`."""
        contact = (bool(human_contact[0]), bool(human_contact[1]))
        if self.config.steps:
            self._paced(contact)
        key = (bool(self.planted[0]), bool(self.planted[1]))
        if self._region_key != key:
            self._region_key = key
            if key == (True, True):
                cfg = self.config
                self._double = double_support_points(self._prints, cfg.balance_margin, cfg.double_support_inset)
            self.set_region(self._double)  # on one foot too: the CoM stays between the feet
        return key

    def _paced(self, contact) -> None:
        """The feet with ``steps``: steps at the robot's own pace, each with a weight shift planned
        by a ZMP preview (:class:`retarget.preview.ZmpPreview`).

        The robot decides to step with foot s when the person's foot s is up, or when the robot's
        planted foot s has fallen behind the person's (``step_distance``, ``step_turn``), while
        the other foot is planted under the person's down foot, foot s has stood ``min_stance``
        and both have stood ``min_double`` since the last step. From then the ZMP reference
        moves under the stance foot, and the foot lifts ``step_shift`` later, once the plan has
        put the weight there (:meth:`_begin_step`). The lifted foot rises over half of its
        swing time (``min_swing``, longer for a slow stepper: :meth:`_swing_time`), follows the
        person's foot s, kept where the robot can put it (:meth:`_clamp_step`), begins to come
        down when the person's foot is down (or so as to land by ``max_swing``) and lands over
        the other half. So the robot steps as often as it can, skips the steps it has no time
        for, and catches up where the person's feet went.
        (Without the shift, a foot lifted with the CoM between the feet stays loaded: the soft
        servos bend the leg instead of lifting it, and the steps were shuffles; with a
        quasi-static shift and no preview the body rolled over the stance foot: docs/retargeting.md
        section 4.)"""
        self._since += 1
        self._frame += 1
        self._watch_person(np.asarray(contact, dtype=bool))
        for s in range(2):
            if self.planted[s]:
                continue
            swing = int(self._since[s])
            if (
                self._descend_at[s] is None
                and swing >= max(self._rise_frames, self._swing_frames(s) - self._fall_frames)
                and (contact[s] or swing >= self._max_swing_frames - self._fall_frames)
            ):
                self._descend_at[s] = swing
            if self._descend_at[s] is not None and swing >= self._descend_at[s] + self._fall_frames:
                self.touch_down(s)
                self._plan_landing()
            else:
                self._plan_swing(s)
        if self._shifting is not None:
            s, lift_at = self._shifting
            if self._frame >= lift_at:
                if self._frame < self._lift_by and not self._weight_shifted():
                    self._shifting = (s, self._frame + 1)  # the weight is not over there yet: wait
                    self._plan_swing(s)
                else:
                    self._shifting = None
                    self._lift(s)
            return
        if self.planted.all():
            self._set_pace(self._person_pace())
            for s in range(2):
                other = 1 - s
                ready = (
                    self._since[s] >= self._min_stance_frames
                    and self._since[other] >= self._min_double_frames
                    and contact[other]
                )
                if ready and (not contact[s] or self._behind(s)):
                    self._begin_step(s)
                    break

    def _watch_person(self, down: np.ndarray) -> None:
        """Record the person's feet (``down`` (2,) bool this frame): the frames of their last
        two lift-offs (either foot; :meth:`_person_pace`), when each foot that is up lifted and
        how long their last finished swing lasted (:meth:`_swing_time`, :meth:`_waited_landing`)."""
        lifted, landed = self._person_down & ~down, down & ~self._person_down
        if lifted.any():
            self._person_lifts = self._person_lifts[-1:] + [self._frame]
        for f in np.flatnonzero(lifted):
            self._person_up_at[f] = self._frame
        for f in np.flatnonzero(landed):
            if self._person_up_at[f] is not None:
                self._person_swing = self._frame - self._person_up_at[f]
                self._person_up_at[f] = None
        self._person_down = down.copy()

    def _begin_step(self, s: int) -> None:
        """Decide to step with foot s: the ZMP reference moves from the CoM to the stance point
        (``zmp_stance_inset`` inwards of the stance foot's centre) over ``step_shift``, and the
        foot lifts then."""
        stance, swing = self._prints[1 - s].mean(axis=0), self._prints[s].mean(axis=0)
        towards = (swing - stance) / max(float(np.linalg.norm(swing - stance)), 1e-9)
        self._stance_point = stance + self.config.zmp_stance_inset * towards
        self._stance_centre = stance
        self._step_start = (self._frame, np.array(self._c1, dtype=float))
        self._landing = swing  # until the swing's targets say where it lands
        self._rise_frames, self._fall_frames = _halves(self._swing_time())
        self._shifting = (s, self._frame + self._shift_frames)
        self._lift_by = self._frame + 2 * self._shift_frames
        self._plan_swing(s)
        if self._shift_frames == 0:
            self._shifting = None
            self._lift(s)

    def _swing_time(self) -> int:
        """Frames the next step's foot takes to rise and come down: ``min_swing`` at the pace,
        longer by half the time the person's step period leaves the robot after its
        ``min_double``, ``step_shift`` and ``min_swing``, up to the person's own last swing
        and ``slow_swing``. A person stepping slowly is followed by slow steps: a foot that
        rises over 4 frames jerks the whole body (CMU 18_01 slowed to 0.7x, streamed: jerk
        ratio 1.93 with every swing at min_swing, 1.46 with this; 0.79 with every swing twice
        as long, which cost the quick steppers a third of their steps)."""
        n = self._min_swing_frames
        lifts, swing = self._person_lifts, self._person_swing
        if len(lifts) < 2 or swing is None:
            return n
        period = max(lifts[-1] - lifts[-2], self._frame - lifts[-1])
        spare = period - self._min_double_frames - self._shift_frames - n  # the robot's time to spare per step
        return max(n, min(swing, n + spare // 2, round(self.config.slow_swing * self.fps), self._max_swing_frames))

    def _plan_swing(self, s: int) -> None:
        """The ZMP keys of foot s's step under way: from the CoM at the decision to the stance
        point by the lift, there until the landing (the rise and fall after the lift, or, while the
        foot is still up, a fall's length from now at the earliest, :meth:`_waited_landing`
        while it waits for the person's), then between the stance point and where the swing
        lands."""
        (n0, c0), stance_pt = self._step_start, self._stance_point
        mid = 0.5 * (self._stance_centre + self._landing)  # between the feet once landed, as _plan_landing
        lift = self._shifting[1] if self._shifting is not None else self._lifted_at
        if self._descend_at[s] is not None:
            land = lift + self._descend_at[s] + self._fall_frames
        elif self._shifting is not None:
            land = lift + self._rise_frames + self._fall_frames
        else:
            land = max(lift + self._swing_frames(s), self._frame + self._fall_frames, self._waited_landing(s, lift))
        settle = land + self._min_double_frames
        self._zmp_keys = _keys([n0, lift, land, settle + 1], [c0, stance_pt, stance_pt, mid])
        self._plan_until = settle + self._settle_frames

    def _waited_landing(self, s: int, lift: int) -> int:
        """While foot s waits up for the person's (still up): the frame it would land if the
        person's foot comes down when their last swing says, or by ``max_swing`` (once that has
        passed, or with no swing seen yet); 0 otherwise. A landing planned a fall's length from
        now, frame after frame, kept the planned CoM between the feet through a long swing, the
        ZMP outside the stance foot: CMU 19_01 planned with 2 or 5 mm of marker noise (3 seeds
        each) fell in all 6, 1.2-1.8 s in; all pass with this."""
        if self._person_down[s]:
            return 0
        up, swing, latest = self._person_up_at[s], self._person_swing, lift + self._max_swing_frames
        if up is None or swing is None or self._frame > up + swing:
            return latest
        return min(up + swing + self._fall_frames, latest)

    def _plan_landing(self) -> None:
        """A foot touched down: the ZMP reference moves from the stance point to between the
        planted feet over ``min_double``; the plan ends ``step_settle`` later."""
        if self._zmp_keys is None:
            return
        stance_pt = self._stance_point
        mid = 0.5 * (self._prints[0].mean(axis=0) + self._prints[1].mean(axis=0))
        n = self._frame
        self._zmp_keys = _keys([n, n + self._min_double_frames + 1], [stance_pt, mid])
        self._plan_until = n + self._settle_frames

    def _weight_shifted(self) -> bool:
        """The planned CoM has covered ``lift_shift`` of its way from the step's decision to the
        stance point (or that way is under 5 mm)."""
        if self.config.lift_shift <= 0:
            return True
        (_, c0), way = self._step_start, self._stance_point - self._step_start[1]
        length2 = float(way @ way)
        return length2 < 0.005**2 or float((np.asarray(self._c1) - c0) @ way) >= self.config.lift_shift * length2

    def _lift(self, s: int) -> None:
        self._lifted_at = self._frame
        self.planted[s] = False
        self._lift_print[s] = self._prints[s]
        self._prints[s] = None
        self._since[s] = 0
        self._descend_at[s] = None
        self._region_key = None

    def _behind(self, s: int) -> bool:
        """The robot's planted foot s is ``step_distance`` or ``step_turn`` from the person's (anchored)."""
        cfg = self.config
        (ax, ay), (rx, ry) = self._ankles_now[s], self._ankle_ref[s]
        # the person's foot heading against the robot's planted foot's (not the anchored one: the
        # anchoring absorbs a pivot on a planted foot, which the robot makes up by stepping)
        # (what a step could turn it: the person's feet turned further apart than a step may turn
        # would otherwise make it re-step for ever)
        turn = abs(_wrap(self._landing_heading(s) - self._head_ref[s]))
        return math.hypot(ax - rx, ay - ry) > cfg.step_distance or turn > cfg.step_turn

    def touch_down(self, s: int) -> None:
        """Plant foot s flat where it is now: its level footprint, the shrunk footprint's
        half-planes, the anchor of the contact rows and the ankle target it pins."""
        self.planted[s] = True
        fp = level_footprint(self._sole1[:, 4 * s : 4 * s + 4].T, self._sole_local[s])
        self._prints[s] = fp
        self._anchor[:, 4 * s : 4 * s + 4] = fp.T
        self._ankle_ref[s] = self._ankles_now[s]
        self._descend_at[s] = None  # the next step's shift plans its swing afresh (_plan_swing)
        # the foot's own heading; the axis's direction from where the swing pointed it (the
        # anchored person's heading can be more than π/2 off it after fast turns)
        hint = self._heads_now[s] if self._swing_heading[s] is None else self._swing_heading[s]
        axis = _long_axis(fp, hint)
        self._head_ref[s] = math.atan2(axis[1], axis[0])
        self._swing_heading[s] = None
        self._since[s] = 0
        self._region_key = None

    def set_region(self, points: np.ndarray) -> None:
        """The balance region: the convex hull of ``points`` (m, 2), as half-planes in the buffer."""
        hull = convex_hull(points)
        edges = np.tile([0.0, 0.0, 1.0], (N_EDGES, 1))
        if len(hull) >= 3:
            A, b = halfplanes(hull)
            edges[: len(b), 0:2], edges[: len(b), 2] = A, b
        self._edges[:] = edges.reshape(-1)  # (3, E) column-major = rows of (E, 3)


def _long_axis(footprint: np.ndarray, heading: float) -> np.ndarray:
    """The unit long axis (2,) of a footprint (4, 2), pointing along ``heading`` (rad) rather than against it."""
    d = footprint - footprint.mean(axis=0)
    axis = np.linalg.eigh(d.T @ d)[1][:, 1]
    return -axis if axis @ (math.cos(heading), math.sin(heading)) < 0 else axis


def _halves(frames: int) -> tuple[int, int]:
    """A swing of ``frames``: rises over the first half, comes down over the rest (1 frame each at least)."""
    rise = max(1, (frames + 1) // 2)
    return rise, max(1, frames - rise)


def _wrap(angle: float) -> float:
    """``angle`` (rad) in [-π, π)."""
    return (angle + math.pi) % (2 * math.pi) - math.pi


def _keys(frames: list, points: list) -> tuple[np.ndarray, np.ndarray]:
    """ZMP reference keys (frames (n,), points (n, 2)) with repeated frames dropped (the later
    point kept): np.interp does not say which of two points at one frame it returns."""
    out_f, out_p = [], []
    for f, p in zip(frames, points):
        if out_f and f <= out_f[-1]:
            out_p[-1] = p
            continue
        out_f.append(f)
        out_p.append(p)
    return np.array(out_f), np.array(out_p, dtype=float)


def _check_step_timing(cfg, fps: float) -> None:
    """One RetargetError naming the StreamingConfig field whose step timing cannot work."""
    problems = []
    if not cfg.swing_speed > 0:
        problems.append(f"swing_speed must be above 0 m/s (got {cfg.swing_speed})")
    if round(cfg.min_swing * fps) < 2:
        problems.append(f"min_swing must last at least 2 frames ({2 / fps:.3f} s at {fps:g} fps; got {cfg.min_swing})")
    if cfg.max_swing < cfg.min_swing:
        problems.append(f"max_swing ({cfg.max_swing}) must be at least min_swing ({cfg.min_swing})")
    if round(cfg.step_preview * fps) < 2:
        problems.append(f"step_preview must last at least 2 frames (got {cfg.step_preview})")
    if not 0 < cfg.pace_floor <= 1:
        problems.append(f"pace_floor must be above 0 and at most 1 (got {cfg.pace_floor})")
    if cfg.step_shift < 0:
        problems.append(f"step_shift must be 0 or more (got {cfg.step_shift})")
    if not 0 <= cfg.lift_shift <= 1:
        problems.append(f"lift_shift must be 0 to 1 (got {cfg.lift_shift})")
    if not (math.isfinite(cfg.body_twist) and cfg.body_twist >= 0):
        problems.append(f"body_twist must be 0 rad or more (got {cfg.body_twist})")
    for name, unit in (("max_step_turn", "rad"), ("step_turn_clearance", "m"), ("slow_swing", "s")):
        value = getattr(cfg, name)
        if not (math.isfinite(value) and value >= 0):
            problems.append(f"{name} must be 0 {unit} or more (got {value})")
    if not cfg.com_velocity_decay > 0:
        problems.append(
            f"com_velocity_decay must be above 0 s, math.inf to keep the velocity (got {cfg.com_velocity_decay})"
        )
    if problems:
        raise RetargetError("StreamingConfig: " + "; ".join(problems))

"""The streaming retargeter's balance planner: planted feet, the support region, the targets' anchoring.

Contract: with ``StreamingConfig.balance`` the :class:`retarget.streaming.StreamingRetargeter`
asks a :class:`BalancePlanner` once per frame for the anchored targets (:meth:`BalancePlanner.anchor`),
the feet held down (:meth:`BalancePlanner.plan`) and the support region's half-planes and the
CoM/DCM/ZMP row parameters, which it writes into the compiled function's parameter buffer
(numpy views bound once, :meth:`BalancePlanner.bind`). Lengths m, times s. The rules (footprints,
the feet's region, when a foot may lift and where it lands) and why steps are off by default:
docs/retargeting.md, section 4.
"""

from __future__ import annotations

import math

import numpy as np

from retarget.errors import RetargetError
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
        self._min_stance_frames = round(cfg.min_stance * self.fps)
        self._max_swing_frames = round(cfg.max_swing * self.fps)
        self._min_swing_frames = round(cfg.min_swing * self.fps)
        self._min_double_frames = round(cfg.min_double * self.fps)
        # leg length (hip above ankle standing; the CoM height without hip keypoints): scales step lengths
        legs = [self._stand_kp[hip, 2] - self._stand_kp[ankle, 2] for hip, ankle in zip(self._hips or (), self._ankles)]
        self._leg = float(np.mean(legs)) if legs else h

    def bind(self, anchor: np.ndarray, edges, points, point_w, cpred, zmp) -> None:
        """Where to write: the contact rows' anchor (2, 8) and views into the parameter buffer
        for the region's half-planes (3·N_EDGES), the rows' (3, 3) points, their √weights (3),
        the CoM prediction (2) and the ZMP-offset scale (1)."""
        self._anchor, self._edges, self._points, self._point_w, self._cpred, self._zmp = (
            anchor,
            edges,
            points,
            point_w,
            cpred,
            zmp,
        )

    def reset(self) -> None:
        """No feet planted, no history; no balance rows until :meth:`start` plants the feet."""
        self.planted = np.zeros(2, dtype=bool)
        self._prints: list = [None, None]  # level footprints (4, 2) of the planted feet
        self._region_key = None
        self._c1 = self._c2 = None  # CoM xy of the last two emitted frames
        self._sole1 = None  # the last frame's sole corners (3, 8)
        #: the anchoring transform: offset (x, y) m and turn psi rad; the ankle targets and foot
        #: headings recorded when each foot touched down
        self.offset = (0.0, 0.0)
        self.psi = 0.0
        self._ankle_ref = [(0.0, 0.0), (0.0, 0.0)]
        self._head_ref = [0.0, 0.0]
        self._since = np.zeros(2, dtype=int)  # frames since each foot last touched down or lifted
        self._edges[:] = np.tile([0.0, 0.0, 1.0], N_EDGES)
        self._points[:] = 0.0
        self._point_w[:] = 0.0
        self._cpred[:] = 0.0
        self._zmp[:] = 0.0

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
        """Any later frame: plan the feet, keep a lifted foot's targets low (``targets`` changed
        in place), set the row parameters; returns the feet to hold."""
        held = self.plan(human_contact)
        cfg = self.config
        for s in range(2):
            if not self.planted[s]:  # a foot in the air steps low: it lands soon and softly
                k = self._foot_kps[s]
                # clear the floor: a foot the person barely lifts would drag (ramped in over 3 frames)
                low = self._foot_kp_h[s] + cfg.swing_clearance * min(1.0, self._since[s] / 3.0)
                targets[k, 2] = np.clip(targets[k, 2], low, self._foot_kp_h[s] + cfg.swing_height)
                if self.planted[1 - s]:
                    self._clamp_step(targets, s)
        self.set_points(False)
        return held

    def _clamp_step(self, targets: np.ndarray, s: int) -> None:
        """Keep the lifted foot s's targets (changed in place) where the robot can put it: in the
        planted foot's frame (its footprint's centre and long axis, pointing along the foot's
        heading), at least ``min_separation`` x the standing feet's distance to its own side (a
        person's crossed or closed feet would put the robot's into its other leg), and at most
        ``stride_limit`` x the leg length from the standing place forwards, backwards and
        outwards. The foot's ankle and toe targets move together."""
        cfg = self.config
        fp = self._prints[1 - s]
        centre = fp.mean(axis=0)
        d = fp - centre
        axis = np.linalg.eigh(d.T @ d)[1][:, 1]  # the footprint's long axis
        heading = self._head_ref[1 - s]
        if axis @ (math.cos(heading), math.sin(heading)) < 0:
            axis = -axis
        side = np.array([-axis[1], axis[0]]) * (1.0 if s == 0 else -1.0)  # towards foot s's own side
        k = self._foot_kps[s]
        rel = targets[k[0], 0:2] - centre
        along, across = float(rel @ axis), float(rel @ side)
        reach = cfg.stride_limit * self._leg
        want_along = min(max(along, -reach), reach)
        want_across = min(max(across, cfg.min_separation * self._stand_sep), self._stand_sep + reach)
        shift = (want_along - along) * axis + (want_across - across) * side
        targets[k, 0:2] += shift

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
        which it could not do standing."""
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
        c, sn = math.cos(self.psi), math.sin(self.psi)
        ox, oy = self.offset
        self._ankles_now = [(c * x - sn * y + ox, sn * x + c * y + oy) for x, y in ankles]
        self._heads_now = [heads[0] + self.psi, heads[1] + self.psi]
        self._ankle_z = (lz, rz)
        return targets @ np.array([[c, sn, 0.0], [-sn, c, 0.0], [0.0, 0.0, 1.0]]) + np.array([ox, oy, 0.0])

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

    def set_points(self, first: bool) -> None:
        """Parameters of the CoM, DCM and ZMP rows and the CoM prediction (module docstring)."""
        (c1x, c1y), (c2x, c2y) = self._c1, self._c2
        px, py = 2 * c1x - c2x, 2 * c1y - c2y
        kd, kz = self._dcm_k, self._zmp_k
        # (3, 3) column-major: columns com, dcm, zmp of rows α, β_x, β_y
        self._points[:] = (1.0, 0.0, 0.0, 1.0 + kd, -kd * c1x, -kd * c1y, 1.0 - kz, kz * px, kz * py)
        self._point_w[:] = self._w0 if first else self._w
        self._cpred[:] = (px, py)
        self._zmp[:] = 0.0 if first else self._zmp_scale

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
        """The feet with ``steps``: quick steps at the robot's own pace, no weight shift, no preview.

        Foot s lifts when the person's foot s is up, or when the
        robot's planted foot s has fallen behind the person's (``step_distance``, ``step_turn``),
        while the other foot is planted under the person's down foot, foot s has stood
        ``min_stance`` and both have stood ``min_double`` since the last step. It lifts at once,
        and the CoM's region stays the two feet's region from before the lift: the robot steps
        the way its offline trajectories do, the CoM between the feet and a swing of about
        ``min_swing``, caught by the landing foot. (A quasi-static shift of the CoM over the
        stance foot first, the rule before this one, loads one soft servo leg for half a second or
        more: on the OP3 the body then rolls 6-10 degrees outwards over the stance foot and falls
        at the first or second step; and a person stepping three times a second is faster than
        that shift.) The lifted foot follows the person's foot s, kept where the robot can put
        it (:meth:`_clamp_step`), and lands when the person's foot is down and the swing has
        lasted ``min_swing``, or after ``max_swing``. So the robot steps as often as it can,
        skips the steps it has no time for, and catches up where the person's feet went."""
        self._since += 1
        for s in range(2):
            swing = int(self._since[s])
            landed = (contact[s] and swing >= self._min_swing_frames) or swing >= self._max_swing_frames
            if not self.planted[s] and landed:
                self.touch_down(s)
        if self.planted.all():
            for s in range(2):
                other = 1 - s
                ready = (
                    self._since[s] >= self._min_stance_frames
                    and self._since[other] >= self._min_double_frames
                    and contact[other]
                )
                if ready and (not contact[s] or self._behind(s)):
                    self._lift(s)
                    break

    def _lift(self, s: int) -> None:
        self.planted[s] = False
        self._prints[s] = None
        self._since[s] = 0
        self._region_key = None

    def _behind(self, s: int) -> bool:
        """The robot's planted foot s is ``step_distance`` or ``step_turn`` from the person's (anchored)."""
        cfg = self.config
        (ax, ay), (rx, ry) = self._ankles_now[s], self._ankle_ref[s]
        turn = abs((self._heads_now[s] - self._head_ref[s] + np.pi) % (2 * np.pi) - np.pi)
        return math.hypot(ax - rx, ay - ry) > cfg.step_distance or turn > cfg.step_turn

    def touch_down(self, s: int) -> None:
        """Plant foot s flat where it is now: its level footprint, the shrunk footprint's
        half-planes, the anchor of the contact rows and the ankle target it pins."""
        self.planted[s] = True
        fp = level_footprint(self._sole1[:, 4 * s : 4 * s + 4].T, self._sole_local[s])
        self._prints[s] = fp
        self._anchor[:, 4 * s : 4 * s + 4] = fp.T
        self._ankle_ref[s] = self._ankles_now[s]
        self._head_ref[s] = self._heads_now[s]
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

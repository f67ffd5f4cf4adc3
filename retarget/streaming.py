"""Streaming retargeting: one frame at a time, warm-started, limits as hard bounds.

Each frame solves a small bounded nonlinear least-squares problem in the configuration
x (nx,) (see :mod:`retarget.kinematics`):

    min_x ½‖r(x)‖²   s.t.   lb ≤ x ≤ ub

    r = [ √w_k (p_k(x) − target_k)                 keypoint tracking, m
          √w_a · fps² (x − 2 x₋₁ + x₋₂)             acceleration against the two frames already emitted
          √w_p (q − q_stand)                        posture
          √w_c · c_s · (z_sole, xy_sole − xy_sole₋₁) a foot in contact stays on the ground and put
          √w_g · min(z_sole, 0)                     no sole corner below the ground
          balance rows (optional, below) ]

    lb, ub = joint range ∩ [x₋₁ − v_max/fps, x₋₁ + v_max/fps]  (position and velocity limits,
                                                               the root's speed limits too)

solved by a few projected Gauss-Newton steps from the previous frame: each step solves
the box-constrained quadratic model (JᵀJ + μI) d = −Jᵀr with a primal active set (free
variables solved exactly, variables at a bound fixed there until their multiplier says
release), then accepts the step if the cost falls (else halves it). r and J come from one
CasADi function, compiled to C and cached (:mod:`retarget.codegen`). Every iterate stays
in the box, so no emitted frame can violate a position or velocity limit; a final clip
makes that exact in floating point.

Balance (``StreamingConfig.balance``; free-base robots with feet, a fixed base ignores it)
keeps a free-standing robot on its feet while it plays the frames open loop (weights w_* are
the config's; c(x) is the CoM, h its standing height, ω = √(g/h)):

    √w_b · max(0, A c_xy(x) − b)                          CoM inside the support region A c ≤ b
    √w_dcm · max(0, A ξ(x) − b),  ξ = c + (c − c₋₁) fps/ω   capture point (DCM) inside it: the
                                                          robot could still stop where it is
    √w_zl · max(0, A z(x) − b),   z = c − (h/g) c̈         ZMP inside it, c̈ = fps² (c − 2c₋₁ + c₋₂)
    √w_z · (h/g) fps² (c_xy − 2c₋₁ + c₋₂)                  ZMP offset: the CoM moves smoothly
    √w_pl · (z_sole, xy_sole − footprint)  (planted feet)  flat on their level footprint
    √w_lv · (z_corner − mean z_corner)  (each foot)        soles level, lifted ones too
    √w_up · (root pitch, root roll)                        trunk upright
    √w_col · min(0, (d² − r²) / 2r)  (profile pairs)       capsules apart (feet, arms and legs;
                                                          the feet by ``feet_clearance`` more)

- *Planted* feet are held on their level footprint: the sole's rectangle flat on the ground
  (z = 0), at the centre and heading the foot had when it touched down
  (:func:`retarget.support.level_footprint`). (Without balance the anchor is the previous
  frame's sole, re-taken every frame.) The ground row gets the planted weight too.
- The support region (:mod:`retarget.support`): on two feet, the hull of the feet's long centre
  lines, ``balance_margin`` in from toe and heel and ``double_support_inset`` towards each
  other (a compliant servo robot with its CoM over one foot unloads the other and sags over);
  on one foot, the inner half (towards the lifted foot) of its footprint shrunk by
  ``stance_margin``: a servo leg alone sags outwards, so the CoM stays on the inner side.
- Steps (``steps``, off by default): without them both feet stay planted whatever the person
  does. The bundled op3's position servos (kp 17.5 N m/rad) make one leg a soft spring: ankle
  roll and hip roll in series give ≈ 8.8 N m/rad against the m g h ≈ 8 N m/rad a 3.4 kg body
  at 0.24 m asks, so the robot survives standing on one leg but not the sway of getting there
  open loop (sim's check topples it), while on two feet it is stiff. With steps on, contacts
  come from the person (the motion's labels, or detected). A robot foot lifts only
  when the person's leaves (rises ``lift_height`` above the other, or moves ``step_distance`` /
  turns ``step_turn`` from where the robot's was put down) while the person's other foot is
  down, after ``min_stance``; and only once the CoM has been over the other foot's stance
  region for ``settle``. Until then the robot shifts its weight: the region becomes the
  stance footprint plus one point p = c₋₁ moved towards it (at most ``shift_speed``, speeding up
  by at most ``shift_accel``). A lifted foot's targets stay within ``swing_height`` of standing
  height; it touches down (flat, where it is) when the person's foot is down, or after
  ``max_swing``. The last planted foot never lifts: a jump or a glide is played on both feet.
- The person's translation and heading are anchored to the planted feet
  (:meth:`StreamingRetargeter._anchor_targets`): the robot follows steps, not sliding.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import casadi as ca
import numpy as np

from dualflow.motion import Motion
from retarget.codegen import compiled_function
from retarget.errors import RetargetError
from retarget.robot import segment_distance_sq
from retarget.support import (closest_point, convex_hull, double_support_points, halfplanes, level_footprint,
                              stance_points, support_polygon)
from retarget.targets import KeypointScaler, check_motion, make_targets
from retarget.trajectory import RobotTrajectory


@dataclass(frozen=True)
class StreamingConfig:
    """Weights (see the module docstring) and iteration counts."""

    accel_weight: float = 1e-6
    posture_weight: float | None = None  # None: the profile's
    contact_weight: float = 30.0
    ground_weight: float = 30.0
    iterations: int = 3
    first_iterations: int = 60
    damping: float = 1e-4  # Levenberg-Marquardt: H + λ(I + diag H), λ adapted per step
    compile: bool = True
    # balance (free-base robots with feet; see the module docstring). Weights are per m² of
    # the residual named; lengths m, times s.
    balance: bool = False
    steps: bool = False  # let a foot lift when the person steps (off: both feet stay planted)
    balance_margin: float = 0.02  # footprints shrunk by this; the CoM, DCM and ZMP stay inside
    balance_weight: float = 1e4  # CoM outside the support region
    dcm_weight: float = 1e3  # capture point outside it
    zmp_limit_weight: float = 300.0  # ZMP outside it
    zmp_weight: float = 30.0  # ZMP offset (h/g)·CoM acceleration (smooth CoM motion)
    balance_contact_weight: float = 1e3  # planted feet off their footprint (replaces contact_weight)
    level_weight: float = 30.0  # sole corner heights differing within a foot
    upright_weight: float = 0.3  # per rad² of root pitch and roll (a leaning servo robot sags further)
    collision_weight: float = 1e5  # the profile's capsule pairs penetrating
    stance_margin: float = 0.03  # on one foot the CoM stays in the inner half of its footprint shrunk by this
    feet_clearance: float = 0.015  # extra distance kept between the two feet's capsules
    double_support_inset: float = 0.01  # on two feet the CoM stays this far inside the feet's centre lines
    shift_speed: float = 0.15  # m/s, CoM travel towards the stance foot before the other lifts
    shift_accel: float = 1.0  # m/s², how fast that speed may grow
    release_tolerance: float = 0.002  # CoM this far outside the stance footprint still lets the other lift
    settle: float = 0.2  # ... once it has stayed there this long (the servos catch up with the shift)
    lift_height: float = 0.01  # a person's foot leaves when its ankle target rises this far above the other's,
    step_distance: float = 0.03  # ... or moves this far from where the robot's foot was put down,
    step_turn: float = 0.35  # rad, ... or turns this far
    min_stance: float = 0.2  # a foot stands this long before it may lift again
    max_swing: float = 0.6  # a lifted foot comes down after this long even if the person's does not
    swing_height: float = 0.02  # a lifted foot's ankle and toe targets stay this close above standing height
    anchor_time: float = 0.1  # time constant of anchoring the person's translation to the planted feet

def solve_box_qp(H: np.ndarray, g: np.ndarray, lo: np.ndarray, hi: np.ndarray, max_iter: int = 20) -> np.ndarray:
    """min_d ½ dᵀHd + gᵀd  s.t. lo ≤ d ≤ hi, H positive definite (n ≤ ~50), by a primal active set.

    Start from the unconstrained minimiser clipped to the box; repeat: variables at a bound
    whose gradient pushes outward stay fixed, the rest are solved exactly given them."""
    d = np.linalg.solve(H, -g)
    fixed = (d <= lo) | (d >= hi)
    if not fixed.any():
        return d
    d = np.clip(d, lo, hi)
    for _ in range(max_iter):
        free = ~fixed
        if free.any():
            rhs = -(g[free] + H[np.ix_(free, fixed)] @ d[fixed])
            d_free = np.linalg.solve(H[np.ix_(free, free)], rhs)
            lo_f, hi_f = lo[free], hi[free]
            bad = (d_free < lo_f) | (d_free > hi_f)
            d[free] = np.clip(d_free, lo_f, hi_f)
            if bad.any():
                idx = np.flatnonzero(free)[bad]
                fixed[idx] = True
                continue
        grad = H @ d + g
        release = fixed & (((d <= lo) & (grad < 0)) | ((d >= hi) & (grad > 0)) | ((d > lo) & (d < hi)))
        if not release.any():
            break
        fixed[release] = False
    return d


#: half-planes of the balance region passed to the compiled function: the two-foot region has
#: 4 corners, the stance region 4 plus the weight-shift point; unused rows are 0·c ≤ 1
_N_EDGES = 6


class StreamingRetargeter:
    """Call :meth:`step` once per frame with the frame's robot-scale keypoint targets (K, 3)
    and side contacts (2,); it returns the configuration x (nx,) to emit."""

    def __init__(self, robot, fps: float, config: StreamingConfig = StreamingConfig()):
        self.robot = robot
        self.fps = float(fps)
        self.config = config
        self._build()
        self.reset()
        #: scales human frames in :meth:`step_human`; REST_POSE proportions until replaced by
        #: one fitted on the person (``KeypointScaler(robot, first_second_of_positions)``)
        self.scaler = KeypointScaler(robot)

    def _build(self) -> None:
        rb, cfg = self.robot, self.config
        x = rb.kin.x_sym
        K, nx, nr = rb.n_keypoints, rb.nx, rb.n_root
        #: balance rows are built only where they mean something: a free base with feet
        self.balance = bool(cfg.balance and rb.floating and rb.has_feet)
        tgt = ca.SX.sym("tgt", 3, K)
        x1, x2 = ca.SX.sym("x1", nx), ca.SX.sym("x2", nx)
        acc_scale = ca.SX.sym("acc_scale")  # √w_a · fps² (0 without history)
        contact = ca.SX.sym("contact", 2)
        anchor = ca.SX.sym("anchor", 2, 8)
        wk = np.sqrt(rb.keypoint_weights)
        res = [ca.reshape((rb.keypoints_expr - tgt) @ ca.diag(ca.DM(wk)), -1, 1)]
        res.append(acc_scale * (x - 2 * x1 + x2))
        wp = rb.profile.posture_weight if cfg.posture_weight is None else cfg.posture_weight
        res.append(np.sqrt(wp) * (x[nr:] - ca.DM(rb.x_stand[nr:])))
        if rb.has_feet:
            sole = rb.sole_expr
            w_contact = cfg.balance_contact_weight if self.balance else cfg.contact_weight
            for s in range(2):
                cols = slice(4 * s, 4 * s + 4)
                wc = np.sqrt(w_contact) * contact[s]
                res.append(wc * ca.reshape(sole[2, cols], -1, 1))
                res.append(wc * ca.reshape(sole[0:2, cols] - anchor[:, cols], -1, 1))
            w_ground = max(cfg.ground_weight, cfg.balance_contact_weight) if self.balance else cfg.ground_weight
            res.append(np.sqrt(w_ground) * ca.reshape(ca.fmin(sole[2, :], 0), -1, 1))
            if self.balance and cfg.upright_weight > 0 and nr:  # trunk upright: root pitch and roll
                res.append(np.sqrt(cfg.upright_weight) * x[4:6])
            if self.balance and cfg.level_weight > 0:  # soles level, in the air too (a foot lands flat)
                for s in range(2):
                    z = sole[2, 4 * s:4 * s + 4]
                    res.append(np.sqrt(cfg.level_weight) * ca.reshape(z - ca.sum2(z) / 4, -1, 1))
        p_parts = [ca.reshape(tgt, -1, 1), x1, x2, acc_scale, contact, ca.reshape(anchor, -1, 1)]
        com = ca.SX.zeros(3, 1)
        if self.balance:
            edges = ca.SX.sym("edges", 3, _N_EDGES)  # rows a_x, a_y, b: inside ⇔ a·c ≤ b
            # the CoM, the DCM and the ZMP, each an affine map α c_xy + β of the CoM (columns α, β_x, β_y)
            points = ca.SX.sym("points", 3, 3)
            point_w = ca.SX.sym("point_w", 3)  # their √weights (0 turns one off)
            c_pred = ca.SX.sym("c_pred", 2)  # 2 c₋₁ − c₋₂
            zmp_scale = ca.SX.sym("zmp_scale")  # √w_z (h/g) fps² (0 without history)
            com = rb.com_expr
            for i in range(3):
                pt = points[0, i] * com[0:2] + points[1:3, i]
                outside = edges[0, :].T * pt[0] + edges[1, :].T * pt[1] - edges[2, :].T
                res.append(point_w[i] * ca.fmax(outside, 0))
            res.append(zmp_scale * (com[0:2] - c_pred))
            if rb.collision_pairs and cfg.collision_weight > 0:
                # (d² − r²) / 2r ≈ d − r (m) for the profile's capsule pairs, penalised below 0;
                # two feet keep feet_clearance more (a servo leg sags, a lifted foot swings in)
                feet = {f.body for f in rb.feet}
                for a, b in rb.collision_pairs:
                    cap_a, cap_b = rb.capsules[a], rb.capsules[b]
                    rr = cap_a.radius + cap_b.radius + rb.profile.collision_margin
                    if cap_a.body in feet and cap_b.body in feet:
                        rr += cfg.feet_clearance
                    d2 = segment_distance_sq(*rb.kin.capsule_segment(cap_a), *rb.kin.capsule_segment(cap_b))
                    res.append(np.sqrt(cfg.collision_weight) * ca.fmin((d2 - rr * rr) / (2 * rr), 0))
            p_parts += [ca.reshape(edges, -1, 1), ca.reshape(points, -1, 1), point_w, c_pred, zmp_scale]
        names = rb.keypoint_names
        self._ankles = ([names.index("left_ankle"), names.index("right_ankle")]
                        if "left_ankle" in names and "right_ankle" in names else None)
        self._toes = ([names.index("left_foot"), names.index("right_foot")]
                      if "left_foot" in names and "right_foot" in names else None)
        self._hips = ([names.index("left_hip"), names.index("right_hip")]
                      if "left_hip" in names and "right_hip" in names else None)
        if self._ankles is not None:
            self._foot_kps = [[k for k in (self._ankles[s], self._toes[s] if self._toes else None) if k is not None]
                              for s in range(2)]
            self._foot_kp_h = [rb.standing_heights[k] for k in self._foot_kps]
            self._feet_idx = list(self._ankles) + list(self._toes if self._toes is not None else (self._hips or []))
            self._stand_kp = rb.evaluate(rb.x_stand[None])["keypoints"][0]
        r = ca.vertcat(*res)
        J = ca.jacobian(r, x)
        p = ca.vertcat(*p_parts)
        sole = rb.sole_expr if rb.has_feet else ca.SX.zeros(3, 0)
        fn = ca.Function("stream_rj", [x, p], [ca.densify(r), ca.densify(J), ca.densify(sole), ca.densify(com)])
        # the cache key names only what shapes the expression graph (weights that enter as
        # parameters, iteration counts and the step rules do not), so configs share binaries
        shape = (wp, cfg.contact_weight, cfg.ground_weight, self.balance)
        if self.balance:
            shape += (cfg.balance_contact_weight, cfg.level_weight, cfg.collision_weight, cfg.feet_clearance,
                      cfg.upright_weight)
        key = f"{rb.fingerprint()}_{hash_config(shape)}"
        self._fn, self.compile_info = compiled_function(fn, key, enable=cfg.compile)
        # zero-copy evaluation: bind numpy buffers once (CasADi reads/writes column-major)
        self._xbuf = np.zeros(nx)
        self._pbuf = np.zeros(p.numel())
        self._rbuf = np.zeros(r.numel())
        self._Jbuf = np.zeros((r.numel(), nx), order="F")
        self._solebuf = np.zeros((3, sole.shape[1]), order="F")
        self._combuf = np.zeros(3)
        buf, self._eval = self._fn.buffer()
        buf.set_arg(0, memoryview(self._xbuf))
        buf.set_arg(1, memoryview(self._pbuf))
        buf.set_res(0, memoryview(self._rbuf))
        buf.set_res(1, memoryview(self._Jbuf.reshape(-1, order="F")))
        buf.set_res(2, memoryview(self._solebuf.reshape(-1, order="F")))
        buf.set_res(3, memoryview(self._combuf))
        self._buffer = buf  # keep alive
        n_t = 3 * K
        self._p_tgt = slice(0, n_t)
        self._p_x1 = slice(n_t, n_t + nx)
        self._p_x2 = slice(n_t + nx, n_t + 2 * nx)
        self._p_acc = n_t + 2 * nx
        self._p_contact = slice(n_t + 2 * nx + 1, n_t + 2 * nx + 3)
        self._p_anchor = slice(n_t + 2 * nx + 3, n_t + 2 * nx + 19)
        n_b = n_t + 2 * nx + 19
        self._p_edges = slice(n_b, n_b + 3 * _N_EDGES)
        n_b += 3 * _N_EDGES
        self._p_points = slice(n_b, n_b + 9)
        self._p_point_w = slice(n_b + 9, n_b + 12)
        self._p_cpred = slice(n_b + 12, n_b + 14)
        self._p_zmp = n_b + 14
        self._has_feet = rb.has_feet
        self._lo_pos, self._hi_pos = rb.x_lower.copy(), rb.x_upper.copy()
        self._vmax = np.concatenate([rb.root_velocity_limits, rb.velocity_limits]) / self.fps
        self._sqrt_wa_fps2 = np.sqrt(cfg.accel_weight) * self.fps ** 2
        self._min_stance_frames = round(cfg.min_stance * self.fps)
        self._settle_frames = round(cfg.settle * self.fps)
        self._max_swing_frames = round(cfg.max_swing * self.fps)
        if self.balance:
            h = float(rb.evaluate(rb.x_stand[None])["com"][0, 2] - rb.evaluate(rb.x_stand[None])["sole"][0, :, 2].min())
            self._zmp_k = h / 9.81 * self.fps ** 2  # ZMP = c − (h/g) c̈ = (1 + k) c − k (2c₋₁ − c₋₂)
            self._dcm_k = self.fps * np.sqrt(h / 9.81)  # DCM = c + ċ/ω = (1 + k) c − k c₋₁
            self._zmp_scale = np.sqrt(cfg.zmp_weight) * self._zmp_k
            self._point_w = np.sqrt([cfg.balance_weight, cfg.dcm_weight, cfg.zmp_limit_weight])
            self._point_w0 = np.sqrt([cfg.balance_weight, 0.0, 0.0])
            self._sole_local = [f.corners for f in rb.feet]
        self._anchor_alpha = 1.0 - math.exp(-1.0 / (self.fps * cfg.anchor_time))
        if self.balance and (self._ankles is None or (self._toes is None and self._hips is None)):
            raise RetargetError(f"{rb.profile.source or rb.name}: field keypoints: streaming balance needs left_ankle "
                                "and right_ankle keypoints, and left/right_foot or left/right_hip ones (it follows the person's "
                                "feet); add them or turn balance off")

    def _residual(self, x: np.ndarray) -> float:
        """Evaluate r, J (and the sole corners) at x into the bound buffers; returns ½‖r‖²."""
        self._xbuf[:] = x
        self._eval()
        return 0.5 * float(self._rbuf @ self._rbuf)

    def reset(self) -> None:
        """Forget the history (the next frame is solved from the stand pose)."""
        self._x1 = None
        self._x2 = None
        self._anchor = np.zeros((2, 8))
        #: balance state: feet planted (left, right), their level footprints (4, 2) m, the CoM
        #: xy of the last two emitted frames, and the last frame's sole corners (3, 8)
        self.planted = np.zeros(2, dtype=bool)
        self._prints: list = [None, None]
        self._settled = 0  # frames the CoM has been over the stance foot while the other waits to lift
        self._stance: list = [None, None]  # per planted foot: (hull, A, b) of its region when it stands alone
        self._region_key = None
        self._c1 = self._c2 = None
        self._sole1 = None
        self.shifting = False
        #: horizontal offset (x, y) m added to the targets (balance: the stance foot anchors the
        #: human's translation) and the ankle targets (2, 2) recorded when each foot touched down
        self.offset = (0.0, 0.0)
        self._psi = 0.0
        self._ankle_ref = [(0.0, 0.0), (0.0, 0.0)]
        self._head_ref = [0.0, 0.0]
        self._since = np.zeros(2, dtype=int)  # frames since each foot last touched down or lifted
        if self.balance:  # no balance rows until the first frame has planted the feet
            self._pbuf[self._p_edges] = np.tile([0.0, 0.0, 1.0], _N_EDGES)
            self._pbuf[self._p_points.start:] = 0.0

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Position ∩ velocity bounds for the next frame."""
        lo, hi = self._lo_pos.copy(), self._hi_pos.copy()
        if self._x1 is not None:
            lo = np.maximum(lo, self._x1 - self._vmax)
            hi = np.minimum(hi, self._x1 + self._vmax)
        return lo, hi

    def _initial_guess(self, targets: np.ndarray) -> np.ndarray:
        rb = self.robot
        x = rb.x_stand.copy()
        if rb.floating:
            names = rb.keypoint_names
            x[0:2] = targets[rb.root_keypoint, 0:2]
            if "left_hip" in names and "right_hip" in names:
                across = targets[names.index("left_hip")] - targets[names.index("right_hip")]
                x[3] = np.arctan2(-across[0], across[1])
        return x

    def _solve(self, x, x1, x2, acc, targets, contact, iters, lo, hi) -> np.ndarray:
        """Levenberg-Marquardt with box constraints from x (see the module docstring)."""
        cfg = self.config
        x = np.clip(x, lo, hi)
        pb = self._pbuf
        pb[self._p_tgt] = targets.reshape(-1)  # (K, 3) row-major = (3, K) column-major
        pb[self._p_x1] = x1
        pb[self._p_x2] = x2
        pb[self._p_acc] = acc
        pb[self._p_contact] = np.asarray(contact, dtype=np.float64)
        pb[self._p_anchor] = self._anchor.reshape(-1, order="F")
        cost = self._residual(x)
        damping = cfg.damping
        eye = np.eye(x.shape[0])
        for _ in range(iters):
            J, r = self._Jbuf, self._rbuf
            H = J.T @ J
            g = J.T @ r
            accepted = False
            for _ in range(8):
                d = solve_box_qp(H + damping * (eye + np.diag(np.diag(H))), g, lo - x, hi - x)
                xn = np.clip(x + d, lo, hi)
                cn = self._residual(xn)
                if cn <= cost:
                    x, cost, accepted = xn, cn, True
                    damping = max(damping * 0.3, cfg.damping)
                    break
                damping *= 10.0
            if not accepted:
                self._residual(x)
                break
            if np.max(np.abs(d)) < 1e-6:
                break
        return x

    def _best_start(self, x_stand: np.ndarray, targets: np.ndarray, contact) -> np.ndarray:
        rb = self.robot
        x_zero = x_stand.copy()
        x_zero[rb.n_root:] = np.clip([h.qpos0 for h in rb.kin.joints], rb.x_lower[rb.n_root:], rb.x_upper[rb.n_root:])
        best, best_cost = x_stand, np.inf
        for start in (x_stand, x_zero):
            self.reset()
            self._x1 = None
            x = self._solve(start, start, start, 0.0, targets, contact, self.config.first_iterations,
                            self._lo_pos, self._hi_pos)
            cost = self._residual(x)
            if cost < best_cost:
                best, best_cost = x, cost
        return best

    def step(self, targets: np.ndarray, contact=(False, False)) -> np.ndarray:
        """targets (K, 3) m, contact (2,) bool (the human's left, right foot) → configuration
        x (nx,) within all limits. With balance the robot's own foot contacts are in
        :attr:`planted` afterwards (see the module docstring)."""
        targets = np.asarray(targets, dtype=np.float64)
        if targets.shape != (self.robot.n_keypoints, 3) or not np.all(np.isfinite(targets)):
            raise RetargetError(f"streaming step: targets must be finite with shape ({self.robot.n_keypoints}, 3), got {targets.shape}")
        cfg = self.config
        first = self._x1 is None
        if self.balance:
            targets = self._anchor_targets(targets, contact, first)
            if first:  # start standing: feet at the robot's own stance under the person's pelvis
                targets = self._neutral_stance(targets)
        if first:
            x = self._initial_guess(targets)
            x1 = x2 = x
            acc = 0.0
            iters = cfg.first_iterations
            contact = (False, False)  # nothing to stay put against yet
            # two starts (the stand pose and the zero pose); keep the better fit
            x = self._best_start(x, targets, contact)
        else:
            x1 = self._x1
            x2 = self._x2 if self._x2 is not None else self._x1
            x = x1.copy()
            acc = self._sqrt_wa_fps2
            iters = cfg.iterations
        lo, hi = self.bounds()
        if self.balance:
            if first:
                # the stream starts standing: both feet put down flat where the fit left them
                self._residual(x)
                self._sole1 = self._solebuf.copy()
                self._c1 = self._c2 = self._combuf[0:2].copy()
                contact = self._plan_balance((True, True))
            else:
                contact = self._plan_balance(contact)
                for s in range(2):
                    if not self.planted[s]:  # a foot in the air steps low: it lands soon and softly
                        k = self._foot_kps[s]
                        targets[k, 2] = np.clip(targets[k, 2], self._foot_kp_h[s], self._foot_kp_h[s] + cfg.swing_height)
            self._pbuf[self._p_zmp] = 0.0 if first else self._zmp_scale
            self._set_points(first)
        x = self._solve(x, x1, x2, acc, targets, contact, iters, lo, hi)
        x = np.clip(x, lo, hi)  # a no-op (every iterate is in the box) but exact in floating point
        if self._has_feet:
            # the buffers hold r, J, the soles and the CoM at the returned x: _solve evaluates
            # each accepted iterate last (or re-evaluates x after a rejected step)
            if self.balance:
                self._sole1 = self._solebuf.copy()
                self._c2 = self._c1
                self._c1 = self._combuf[0:2].copy()
            else:
                self._anchor = self._solebuf[0:2, :].copy()
        self._x2 = self._x1 if not first else x
        self._x1 = x
        return x

    def _anchor_targets(self, targets: np.ndarray, contact, first: bool) -> np.ndarray:
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
                c, sn = math.cos(self._psi), math.sin(self._psi)
                ox, oy = self.offset
                al = self._anchor_alpha
                # the pivot's image moves from T(p) towards T*(p) = mean r_s
                tx = (1 - al) * (c * px - sn * py + ox) + al * qx
                ty = (1 - al) * (sn * px + c * py + oy) + al * qy
                d = (psi_raw - self._psi + math.pi) % (2 * math.pi) - math.pi
                self._psi += al * d
                c, sn = math.cos(self._psi), math.sin(self._psi)
                self.offset = (tx - (c * px - sn * py), ty - (sn * px + c * py))
        c, sn = math.cos(self._psi), math.sin(self._psi)
        ox, oy = self.offset
        self._ankles_now = [(c * x - sn * y + ox, sn * x + c * y + oy) for x, y in ankles]
        self._heads_now = [heads[0] + self._psi, heads[1] + self._psi]
        self._ankle_z = (lz, rz)
        return targets @ np.array([[c, sn, 0.0], [-sn, c, 0.0], [0.0, 0.0, 1.0]]) + np.array([ox, oy, 0.0])

    def _neutral_stance(self, targets: np.ndarray) -> np.ndarray:
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

    def _set_points(self, first: bool) -> None:
        """Parameters of the CoM, DCM and ZMP rows and the CoM prediction (module docstring)."""
        (c1x, c1y), (c2x, c2y) = self._c1, self._c2
        px, py = 2 * c1x - c2x, 2 * c1y - c2y
        kd, kz = self._dcm_k, self._zmp_k
        pb = self._pbuf
        # (3, 3) column-major: columns com, dcm, zmp of rows α, β_x, β_y
        pb[self._p_points] = (1.0, 0.0, 0.0, 1.0 + kd, -kd * c1x, -kd * c1y, 1.0 + kz, -kz * px, -kz * py)
        pb[self._p_point_w] = self._point_w0 if first else self._point_w
        pb[self._p_cpred] = (px, py)

    def _plan_balance(self, human_contact) -> tuple[bool, bool]:
        """Update :attr:`planted` from the human's contacts and the last frame's CoM, and set
        the anchors, the balance region and the CoM prediction in the parameter buffer.
        Returns the contacts (left, right) the solver holds on the ground this frame."""
        cfg = self.config
        contact = (bool(human_contact[0]), bool(human_contact[1]))
        # the person's feet: a lift counts only when the foot really leaves (rises lift_height above
        # the other, or its target moves step_distance or turns step_turn from where the robot put
        # it down) and the robot's foot has stood min_stance frames; a near-standing person's contact
        # flicker then never makes the robot stand on one leg. A step stands on the other foot: with
        # no foot down (a jump, a glide) both stay. A lifted foot comes down when the person's does,
        # or after max_swing seconds.
        self._since += 1
        want = [True, True]
        for s in range(2):
            planted, other = bool(self.planted[s]), 1 - s
            if not planted and (contact[s] or self._since[s] >= self._max_swing_frames):
                self._touch_down(s)
                continue
            if (not cfg.steps or contact[s] or not contact[other]
                    or (planted and self._since[s] < self._min_stance_frames)):
                continue
            dz = self._ankle_z[s] - self._ankle_z[other]
            (ax, ay), (rx, ry) = self._ankles_now[s], self._ankle_ref[s]
            turn = abs((self._heads_now[s] - self._head_ref[s] + np.pi) % (2 * np.pi) - np.pi)
            want[s] = not (dz > cfg.lift_height or math.hypot(ax - rx, ay - ry) > cfg.step_distance
                           or turn > cfg.step_turn)
        c1 = self._c1
        shift_point = None
        self.shifting = False
        for s in range(2):
            other = 1 - s
            if want[s] or not self.planted[s] or not self.planted[other]:
                continue
            if self._stance[other] is None:
                self._stance[other] = support_polygon([stance_points(self._prints[other], self._prints[s],
                                                                     cfg.stance_margin)])
            hull, A, b = self._stance[other]
            inside = float(np.min(b - A @ c1)) >= -cfg.release_tolerance
            self._settled = self._settled + 1 if inside else 0
            if self._settled > self._settle_frames:
                self.planted[s] = False  # the weight is on the other foot: lift
                self._prints[s] = None
                self._since[s] = 0
                self._region_key = None
            else:  # shift the weight first: the CoM's region is the stance foot and a point on the way
                self.shifting = True
                gap = closest_point(c1, hull) - c1
                dist = float(np.linalg.norm(gap))
                # at most shift_speed, reached with at most shift_accel from the CoM's speed towards it
                toward = max(0.0, float((self._c1 - self._c2) @ gap) / max(dist, 1e-12))
                step = min(cfg.shift_speed / self.fps, toward + cfg.shift_accel / self.fps ** 2, dist)
                shift_point = c1 + gap * (step / max(dist, 1e-12))
                self._region_key = None
                self._set_region(np.concatenate([hull, shift_point[None]]))
            break  # one foot at a time
        if not self.shifting:
            self._settled = 0
        key = (bool(self.planted[0]), bool(self.planted[1]))
        if shift_point is None and self._region_key != key:
            self._region_key = key
            if key == (True, True):
                self._set_region(double_support_points(self._prints, cfg.balance_margin, cfg.double_support_inset))
            else:
                self._set_region(np.concatenate([self._stance[f][0] for f in range(2) if self.planted[f]]))
        return key

    def _touch_down(self, s: int) -> None:
        """Plant foot s flat where it is now: its level footprint, the shrunk footprint's
        half-planes, the anchor of the contact rows and the ankle target it pins."""
        self.planted[s] = True
        fp = level_footprint(self._sole1[:, 4 * s:4 * s + 4].T, self._sole_local[s])
        self._prints[s] = fp
        self._stance = [None, None]
        self._anchor[:, 4 * s:4 * s + 4] = fp.T
        self._ankle_ref[s] = self._ankles_now[s]
        self._head_ref[s] = self._heads_now[s]
        self._since[s] = 0
        self._region_key = None

    def _set_region(self, points: np.ndarray) -> None:
        """The balance region: the convex hull of ``points`` (m, 2), as half-planes in the buffer."""
        hull = convex_hull(points)
        edges = np.tile([0.0, 0.0, 1.0], (_N_EDGES, 1))
        if len(hull) >= 3:
            A, b = halfplanes(hull)
            edges[:len(b), 0:2], edges[:len(b), 2] = A, b
        self._pbuf[self._p_edges] = edges.reshape(-1)  # (3, E) column-major = rows of (E, 3)

    def step_human(self, positions: np.ndarray, contact=(False, False)) -> np.ndarray:
        """One human frame (22, 3) m (SMPL-22, Z up) → configuration x (nx,), via ``self.scaler``."""
        positions = np.asarray(positions, dtype=np.float64)
        if positions.shape != (22, 3) or not np.all(np.isfinite(positions)):
            raise RetargetError(f"streaming step_human: positions must be finite with shape (22, 3), got {positions.shape}")
        return self.step(self.scaler.targets(positions[None])[0], contact)

    def split(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """x (nx,) → joint angles (n,) rad in the robot's joint order, root position (3,) m,
        root quaternion (4,) w, x, y, z."""
        pos, quat = self.robot.kin.root_pose(np.asarray(x)[None])
        return np.array(x[self.robot.n_root:]), pos[0], quat[0]

    def run(self, motion: Motion, contacts=None, scaler=None) -> RobotTrajectory:
        """Retarget a whole clip frame by frame (as the live bridge would). ``scaler``: a
        :class:`retarget.targets.KeypointScaler` (default: fitted on this clip)."""
        check_motion(motion, min_frames=2)
        if abs(motion.fps - self.fps) > 1e-9:
            raise RetargetError(f"{motion.name or 'motion'}: is {motion.fps:g} fps but this retargeter runs at {self.fps:g}; resample the motion")
        tg = make_targets(self.robot, motion, contacts, scaler)
        self.reset()
        X = np.stack([self.step(tg.keypoints[t], tg.contacts[t]) for t in range(motion.n_frames)])
        return trajectory_from_x(self.robot, X, motion.fps, {"mode": "streaming", "source": motion.name,
                                                                 "compiled": self.compile_info})


def hash_config(cfg) -> str:
    import hashlib

    return hashlib.sha256(repr(cfg).encode()).hexdigest()[:8]


def trajectory_from_x(robot, X: np.ndarray, fps: float, meta: dict) -> RobotTrajectory:
    """Configurations X (T, nx) → RobotTrajectory in the robot's joint order."""
    root_pos, root_quat = robot.kin.root_pose(X)
    return RobotTrajectory(robot.joint_names, X[:, robot.n_root:], root_pos, root_quat, fps, robot.name, dict(meta))

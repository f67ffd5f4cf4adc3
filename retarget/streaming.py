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

Which feet are planted (and where), the support region A c ≤ b and the anchoring of the
person's translation to the planted feet come from :class:`retarget.balance.BalancePlanner`.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from dualflow.motion import Motion
from retarget.codegen import compiled_function
from retarget.errors import RetargetError
from retarget.robot import segment_distance_sq
from retarget.balance import N_EDGES, BalancePlanner
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
    # frames of the person's contacts known ahead of the frame being solved (a stream delayed by
    # that many frames): the weight shift before a step starts that much earlier (BalancePlanner.plan)
    preview: int = 0

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
            edges = ca.SX.sym("edges", 3, N_EDGES)  # rows a_x, a_y, b: inside ⇔ a·c ≤ b
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
        self._p_edges = slice(n_b, n_b + 3 * N_EDGES)
        n_b += 3 * N_EDGES
        self._p_points = slice(n_b, n_b + 9)
        self._p_point_w = slice(n_b + 9, n_b + 12)
        self._p_cpred = slice(n_b + 12, n_b + 14)
        self._p_zmp = n_b + 14
        self._has_feet = rb.has_feet
        self._lo_pos, self._hi_pos = rb.x_lower.copy(), rb.x_upper.copy()
        self._vmax = np.concatenate([rb.root_velocity_limits, rb.velocity_limits]) / self.fps
        self._sqrt_wa_fps2 = np.sqrt(cfg.accel_weight) * self.fps ** 2
        self._anchor = np.zeros((2, 8))
        # the first frame's long solves stop once a step gains < 1e-6 of the cost (with balance:
        # its one-sided rows make the 1e-6 rad step test slow to trigger); else unchanged
        self._first_rtol = 1e-6 if self.balance else 0.0
        self.planner = None
        if self.balance:
            self.planner = BalancePlanner(rb, cfg, self.fps)
            pb = self._pbuf
            self.planner.bind(self._anchor, pb[self._p_edges], pb[self._p_points], pb[self._p_point_w],
                              pb[self._p_cpred], pb[self._p_zmp:self._p_zmp + 1])

    def _residual(self, x: np.ndarray) -> float:
        """Evaluate r, J (and the sole corners) at x into the bound buffers; returns ½‖r‖²."""
        self._xbuf[:] = x
        self._eval()
        return 0.5 * float(self._rbuf @ self._rbuf)

    def reset(self) -> None:
        """Forget the history (the next frame is solved from the stand pose)."""
        self._x1 = None
        self._x2 = None
        self._anchor[:] = 0.0
        self._contact = np.zeros(2, dtype=bool)
        if self.planner is not None:
            self.planner.reset()

    def resume(self, x1: np.ndarray, x2: np.ndarray) -> None:
        """Continue a stream from two frames emitted elsewhere (x1 the last, x2 the one before;
        (nx,) each), e.g. frames an offline solve settled: the next :meth:`step` is limited by
        their velocity bounds and its feet in contact stay where x1 put them. Plain streaming
        only (the balance planner's contact history cannot be rebuilt from two frames)."""
        if self.balance:
            raise RetargetError("streaming resume: not available with balance (StreamingConfig.balance); "
                                "reset() and stream from the start instead")
        self._x1, self._x2 = np.array(x1, dtype=np.float64), np.array(x2, dtype=np.float64)
        self._residual(self._x1)
        if self._has_feet:
            self._anchor[:] = self._solebuf[0:2, :]

    @property
    def planted(self) -> np.ndarray:
        """(2,) bool: the robot's feet held on the ground in the last frame (balance; else the
        contacts given)."""
        return self.planner.planted if self.planner is not None else self._contact

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

    def _solve(self, x, x1, x2, acc, targets, contact, iters, lo, hi, rtol: float = 0.0) -> np.ndarray:
        """Levenberg-Marquardt with box constraints from x (see the module docstring); stops early
        when a step moves no variable by 1e-6 or lowers the cost by no more than ``rtol`` of it."""
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
                    gain = cost - cn
                    x, cost, accepted = xn, cn, True
                    damping = max(damping * 0.3, cfg.damping)
                    break
                damping *= 10.0
            if not accepted:
                self._residual(x)
                break
            if np.max(np.abs(d)) < 1e-6 or gain <= rtol * cost:
                break
        return x

    def _best_start(self, x_stand: np.ndarray, targets: np.ndarray, contact) -> np.ndarray:
        rb = self.robot
        x_zero = x_stand.copy()
        x_zero[rb.n_root:] = np.clip([h.qpos0 for h in rb.kin.joints], rb.x_lower[rb.n_root:], rb.x_upper[rb.n_root:])
        best, best_cost = x_stand, np.inf
        # with balance the feet start at the robot's own stance, which the stand pose fits:
        # the zero-pose start (a T-pose, for odd first frames) would only cost time
        for start in (x_stand,) if self.balance else (x_stand, x_zero):
            self.reset()
            self._x1 = None
            x = self._solve(start, start, start, 0.0, targets, contact, self.config.first_iterations,
                            self._lo_pos, self._hi_pos, rtol=self._first_rtol)
            cost = self._residual(x)
            if cost < best_cost:
                best, best_cost = x, cost
        return best

    def step(self, targets: np.ndarray, contact=(False, False), ahead=None) -> np.ndarray:
        """targets (K, 3) m, contact (2,) bool (the human's left, right foot) → configuration
        x (nx,) within all limits. With balance the robot's own foot contacts are in
        :attr:`planted` afterwards (see the module docstring). ``ahead`` (2,) bool: the person's
        contacts ``config.preview`` frames later, where the caller has them (balance with steps
        uses them to shift the weight before a step; :meth:`run` passes them)."""
        targets = np.asarray(targets, dtype=np.float64)
        if targets.shape != (self.robot.n_keypoints, 3) or not np.all(np.isfinite(targets)):
            raise RetargetError(f"streaming step: targets must be finite with shape ({self.robot.n_keypoints}, 3), got {targets.shape}")
        cfg = self.config
        first = self._x1 is None
        if self.balance:
            targets = self.planner.anchor(targets, contact, first)
            if first:  # start standing: feet at the robot's own stance under the person's pelvis
                targets = self.planner.neutral_stance(targets)
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
            if first:  # the stream starts standing: both feet put down flat where the fit left them
                self._residual(x)
                contact = self.planner.start(self._solebuf, self._combuf[0:2])
            else:
                contact = self.planner.next(contact, targets, ahead)
        self._contact = np.array(contact, dtype=bool)
        x = self._solve(x, x1, x2, acc, targets, contact, iters, lo, hi, rtol=self._first_rtol if first else 0.0)
        x = np.clip(x, lo, hi)  # a no-op (every iterate is in the box) but exact in floating point
        if self._has_feet:
            # the buffers hold r, J, the soles and the CoM at the returned x: _solve evaluates
            # each accepted iterate last (or re-evaluates x after a rejected step)
            if self.balance:
                self.planner.record(self._solebuf, self._combuf[0:2])
            else:
                self._anchor[:] = self._solebuf[0:2, :]
        self._x2 = self._x1 if not first else x
        self._x1 = x
        return x

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
        T, P = motion.n_frames, self.config.preview
        ahead = (lambda t: tg.contacts[min(t + P, T - 1)]) if P > 0 and self.balance else (lambda t: None)
        X = np.stack([self.step(tg.keypoints[t], tg.contacts[t], ahead(t)) for t in range(T)])
        return trajectory_from_x(self.robot, X, motion.fps, {"mode": "streaming", "source": motion.name,
                                                                 "compiled": self.compile_info})


def hash_config(cfg) -> str:
    import hashlib

    return hashlib.sha256(repr(cfg).encode()).hexdigest()[:8]


def trajectory_from_x(robot, X: np.ndarray, fps: float, meta: dict) -> RobotTrajectory:
    """Configurations X (T, nx) → RobotTrajectory in the robot's joint order."""
    root_pos, root_quat = robot.kin.root_pose(X)
    return RobotTrajectory(robot.joint_names, X[:, robot.n_root:], root_pos, root_quat, fps, robot.ref, dict(meta))

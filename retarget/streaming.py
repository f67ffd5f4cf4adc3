"""Streaming retargeting: one frame at a time, a few bounded Gauss-Newton steps from the last frame.

Contract: :meth:`StreamingRetargeter.step` takes one frame's robot-scale keypoint targets (K, 3)
and the person's foot contacts (2,) and returns a configuration x (nx,) that is inside the joint
range and within one frame's speed limit of the previous frame (every iterate stays in the box).
With ``StreamingConfig.balance`` a :class:`retarget.balance.BalancePlanner` keeps the feet planted
and the CoM, capture point and ZMP over the support region. The residual rows and the balance
rules: docs/retargeting.md (sections 4 and 6).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import casadi as ca
import numpy as np

from dualflow.motion import Motion
from retarget.balance import N_EDGES, BalancePlanner
from retarget.codegen import compiled_function
from retarget.errors import RetargetError
from retarget.robot import segment_distance_sq
from retarget.step_turn import leg_bodies
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
    # the robot steps when the person does (False: both feet stay planted; None: the robot
    # profile's streaming_steps)
    steps: bool | None = None
    # the step phases (min_stance, min_double, min_swing, max_swing, slow_swing, step_shift, step_settle) at
    # this multiple of their lengths, swing_speed divided by it (None: the profile's step_pace)
    step_pace: float | None = None
    balance_margin: float = 0.02  # footprints shrunk by this; the CoM, DCM and ZMP stay inside
    balance_weight: float = 1e4  # CoM outside the support region
    dcm_weight: float = 1e3  # capture point outside it
    zmp_limit_weight: float = 300.0  # ZMP outside it
    zmp_weight: float = 30.0  # ZMP offset (h/g)·CoM acceleration (smooth CoM motion) ...
    # ... against a CoM velocity that decays with this time constant (s; math.inf: kept).
    # Kept, tracking alone pulled a moving CoM back, weakly: a generated partner standing still
    # drifted 5 cm to the edge of its feet in 0.5 s and fell. Measured on op3 (physics), 16
    # generated duets of other seeds than the bench's, planned and streamed: 26 of 32 pass kept,
    # 32 of 32 at 0.15 s
    com_velocity_decay: float = 0.15
    balance_contact_weight: float = 1e3  # planted feet off their footprint (replaces contact_weight)
    level_weight: float = 30.0  # sole corner heights differing within a foot
    upright_weight: float = 0.3  # per rad² of root pitch and roll (a leaning servo robot sags further)
    collision_weight: float = 1e5  # the profile's capsule pairs penetrating
    # m: beyond the hard distance, a capsule pair not both on the legs (an arm and the body or a
    # leg) is pushed apart softly within this (collision_buffer_weight per m²), so an arm makes
    # way for a leg swinging into it over several frames rather than being shoved within one
    # (the jerk that put CMU 18_01's streamed jerk ratio at 1.03: 0.89 with it). 0: hard only
    collision_buffer: float = 0.02
    collision_buffer_weight: float = 100.0
    feet_clearance: float = 0.015  # extra distance kept between the two feet's capsules
    double_support_inset: float = 0.01  # on two feet the CoM stays this far inside the feet's centre lines
    # steps (BalancePlanner._paced): steps at the robot's pace, the weight shifted over the stance
    # foot by a ZMP preview first (below)
    step_distance: float = 0.03  # a planted foot the person's has moved this far from re-steps,
    step_turn: float = 0.35  # rad, ... or turned this far
    min_stance: float = 0.2  # a foot stands this long before it may lift again
    min_double: float = 0.15  # both feet stand this long between two steps
    min_swing: float = 0.27  # a lifted foot rises over half of this (or more: slow_swing) and comes down over the rest
    max_swing: float = 0.6  # ... and comes down after this long even if the person's does not
    # s: a step's rise and fall take up to this long together where the person's tempo leaves
    # the time (BalancePlanner._swing_time); min_swing or less: always min_swing
    slow_swing: float = 0.53
    # its ankle and toe targets stay at least this above standing height (with the weight shift,
    # its sole is lifted this high mid-swing: BalancePlanner._swing_lift) ...
    swing_clearance: float = 0.03
    swing_height: float = 0.045  # ... and at most this
    min_separation: float = 1.0  # it lands at least this x the standing feet's distance from the other
    stride_limit: float = 0.35  # ... and at most this x the leg length from its place beside the stance foot
    max_step_turn: float = 0.6  # rad: a step turns the foot at most this far from the other ...
    # ... and no further than the legs' capsule pairs allow with this much room (m) to spare
    # (retarget.step_turn). Measured on op3 (bench/stepping.py, both clip sets, physics): at 3 mm
    # (0.39 rad toes out) the CMU clips' worst streamed jerk ratio is 0.93 and one fast orbiting
    # duet falls, streamed; at 0 (0.45 rad) all 51 clips pass in both modes and the keypoint error
    # is lower, but CMU 18_01 streamed reaches 1.05 (its body's turn over the feet runs into an
    # arm capsule and stops within a frame)
    step_turn_clearance: float = 0.0
    swing_speed: float = 0.4  # m/s: a step longer than this covers in min_swing takes longer
    anchor_time: float = 0.1  # time constant of anchoring the person's translation to the planted feet
    # rad: the body above the knees turns towards the person's own heading ahead of the planted
    # feet, this far at most (softly: limit·tanh(lag / limit), faded out for a lag beyond π/2);
    # the feet catch up by stepping (BalancePlanner.anchor). 0: the whole body turns with the
    # feet. Measured on op3 with steps (bench/stepping.py's 9 clips): keypoint error 9.1 -> 8.2 %
    # of height, all clips still pass
    body_twist: float = 0.8
    # the weight shift of a step (BalancePlanner._paced, retarget.preview): a receding-horizon ZMP
    # preview over step_preview s plans the CoM so that the ZMP moves under the stance foot
    # (zmp_stance_inset inwards of its centre) by the lift, step_shift s after the robot decides to
    # step, stays there through the swing, and returns between the feet over min_double after
    # touch-down; the CoM follows the plan with plan_weight (per m²) until step_settle after that
    step_preview: float = 1.0
    # the robot's pace follows the person's (BalancePlanner._person_pace): min_stance, min_double,
    # step_shift and min_swing shrink with the person's step period, to pace_floor x at most
    # (0.37 s a step: 2.7 steps a second against 1.7). Measured on op3, leaders stepping 2 to 2.7
    # times a second (physics, streamed and planned): 126-129 of 195 steps taken at 1.0, 182 at 0.63
    pace_floor: float = 0.63
    step_shift: float = 0.17
    # the foot lifts once the planned CoM has covered this share of its way from where it was at
    # the decision to the stance point (BalancePlanner._weight_shifted), waiting up to step_shift
    # longer for it; 0: it lifts on time. By the lift the stepping leaders' CoM covers 0.32-0.46,
    # the quick leaders' at 160 steps a minute 0.24 (a few lifts 0.06-0.07); generated partners,
    # planned, lifted at 0.04-0.09 from standing over the foot they stepped with, and the op3
    # fell off it. Measured on op3 (physics): 8 demo-like generated partners with two cleanups,
    # streamed and planned, 21 of 32 pass at 0, 24 at 0.15, 25 at 0.25; the 27 bench clips pass
    # at each, with 343 / 342 of the person's 395 steps at 0, 343 / 341 at 0.15, 334 / 336 at 0.25
    lift_shift: float = 0.15
    step_settle: float = 0.3
    zmp_stance_inset: float = 0.015
    plan_weight: float = 3e4


def paced(config: StreamingConfig, pace: float) -> StreamingConfig:
    """``config`` with its step phases at ``pace`` x their lengths and the swing speed divided by
    it (``step_pace`` set, so it is applied once)."""
    if not (math.isfinite(pace) and pace > 0):
        raise RetargetError(f"StreamingConfig: step_pace must be a number > 0, got {pace!r}")
    c = config
    return replace(
        c,
        step_pace=float(pace),
        min_stance=c.min_stance * pace,
        min_double=c.min_double * pace,
        min_swing=c.min_swing * pace,
        max_swing=c.max_swing * pace,
        slow_swing=c.slow_swing * pace,
        step_shift=c.step_shift * pace,
        step_settle=c.step_settle * pace,
        swing_speed=c.swing_speed / pace,
    )


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


@dataclass(frozen=True)
class _FrameSymbols:
    """The per-frame parameters of the streaming residual: targets (3, K), the two frames
    emitted before (nx,) each, √w_a·fps² (0 without history), contacts (2,), the planted
    feet's sole corners xy (2, 8) (a swinging foot's: where its swing path is this frame), and
    the height (2,) m each swinging foot's sole corners are held at, on for the feet whose
    ``swing`` (2,) is 1 (a foot in a step's swing is lifted clear of the floor, moved and put
    down on a planned path)."""

    tgt: ca.SX
    x1: ca.SX
    x2: ca.SX
    acc_scale: ca.SX
    contact: ca.SX
    anchor: ca.SX
    lift: ca.SX
    swing: ca.SX

    @classmethod
    def make(cls, rb) -> _FrameSymbols:
        return cls(
            ca.SX.sym("tgt", 3, rb.n_keypoints),
            ca.SX.sym("x1", rb.nx),
            ca.SX.sym("x2", rb.nx),
            ca.SX.sym("acc_scale"),
            ca.SX.sym("contact", 2),
            ca.SX.sym("anchor", 2, 8),
            ca.SX.sym("lift", 2),
            ca.SX.sym("swing", 2),
        )


@dataclass(frozen=True)
class _BalanceSymbols:
    """The balance rows' parameters: support edges (3, N_EDGES) (rows a_x, a_y, b: inside ⇔
    a·c ≤ b); the CoM, DCM and ZMP as affine maps α c_xy + β of the CoM (3, 3) (columns α, β_x,
    β_y) and their √weights (3,) (0 turns one off); 2 c₋₁ − c₋₂ (2,); √w_z (h/g) fps²."""

    edges: ca.SX
    points: ca.SX
    point_w: ca.SX
    c_pred: ca.SX
    zmp_scale: ca.SX

    @classmethod
    def make(cls) -> _BalanceSymbols:
        return cls(
            ca.SX.sym("edges", 3, N_EDGES),
            ca.SX.sym("points", 3, 3),
            ca.SX.sym("point_w", 3),
            ca.SX.sym("c_pred", 2),
            ca.SX.sym("zmp_scale"),
        )


class StreamingRetargeter:
    """Call :meth:`step` once per frame with the frame's robot-scale keypoint targets (K, 3)
    and side contacts (2,); it returns the configuration x (nx,) to emit."""

    def __init__(self, robot, fps: float, config: StreamingConfig = StreamingConfig()):
        self.robot = robot
        self.fps = float(fps)
        if config.steps is None:
            config = replace(config, steps=robot.profile.streaming_steps)
        if config.step_pace is None:
            config = paced(config, robot.profile.step_pace)
        self.config = config
        self._build()
        self.reset()
        #: scales human frames in :meth:`step_human`; REST_POSE proportions until replaced by
        #: one fitted on the person (``KeypointScaler(robot, first_second_of_positions)``)
        self.scaler = KeypointScaler(robot)

    def _build(self) -> None:
        """The per-frame residual r(x; p) and its Jacobian as one compiled function, with numpy
        buffers bound to its inputs and outputs (see the module docstring for the rows)."""
        rb, cfg = self.robot, self.config
        #: balance rows are built only where they mean something: a free base with feet
        self.balance = bool(cfg.balance and rb.floating and rb.has_feet)
        sym = _FrameSymbols.make(rb)
        res = self._tracking_rows(sym)
        p_parts = [
            ca.reshape(sym.tgt, -1, 1),
            sym.x1,
            sym.x2,
            sym.acc_scale,
            sym.contact,
            ca.reshape(sym.anchor, -1, 1),
            sym.lift,
            sym.swing,
        ]
        com = ca.SX.zeros(3, 1)
        if self.balance:
            bal = _BalanceSymbols.make()
            com = rb.com_expr
            res += self._balance_rows(bal, com)
            p_parts += [
                ca.reshape(bal.edges, -1, 1),
                ca.reshape(bal.points, -1, 1),
                bal.point_w,
                bal.c_pred,
                bal.zmp_scale,
            ]
        r = ca.vertcat(*res)
        p = ca.vertcat(*p_parts)
        sole = rb.sole_expr if rb.has_feet else ca.SX.zeros(3, 0)
        self._compile(r, p, sole, com)
        self._index_parameters(rb.n_keypoints, rb.nx)
        self._has_feet = rb.has_feet
        self._lo_pos, self._hi_pos = rb.x_lower.copy(), rb.x_upper.copy()
        self._vmax = np.concatenate([rb.root_velocity_limits, rb.velocity_limits]) / self.fps
        self._amax = rb.acceleration_limits / self.fps**2  # joints only: the root has no servo
        self._sqrt_wa_fps2 = np.sqrt(cfg.accel_weight) * self.fps**2
        self._anchor = np.zeros((2, 8))
        # the first frame's long solves stop once a step gains < 1e-6 of the cost (with balance:
        # its one-sided rows make the 1e-6 rad step test slow to trigger); else unchanged
        self._first_rtol = 1e-6 if self.balance else 0.0
        self.planner = None
        if self.balance:
            self.planner = BalancePlanner(rb, cfg, self.fps)
            pb = self._pbuf
            self.planner.bind(
                self._anchor,
                pb[self._p_edges],
                pb[self._p_points],
                pb[self._p_point_w],
                pb[self._p_cpred],
                pb[self._p_zmp : self._p_zmp + 1],
                pb[self._p_lift],
            )

    def _posture_weight(self) -> float:
        return self.robot.profile.posture_weight if self.config.posture_weight is None else self.config.posture_weight

    def _tracking_rows(self, sym: _FrameSymbols) -> list:
        """Keypoint, acceleration and posture rows, and the feet's rows (contact, ground; with
        balance also trunk upright and soles level)."""
        rb, cfg, x = self.robot, self.config, self.robot.kin.x_sym
        wk = np.sqrt(rb.keypoint_weights)
        res = [ca.reshape((rb.keypoints_expr - sym.tgt) @ ca.diag(ca.DM(wk)), -1, 1)]
        res.append(sym.acc_scale * (x - 2 * sym.x1 + sym.x2))
        res.append(np.sqrt(self._posture_weight()) * (x[rb.n_root :] - ca.DM(rb.x_stand[rb.n_root :])))
        if not rb.has_feet:
            return res
        sole = rb.sole_expr
        w_contact = cfg.balance_contact_weight if self.balance else cfg.contact_weight
        for s in range(2):
            cols = slice(4 * s, 4 * s + 4)
            wc = np.sqrt(w_contact) * sym.contact[s]
            res.append(wc * ca.reshape(sole[2, cols], -1, 1))
            res.append(wc * ca.reshape(sole[0:2, cols] - sym.anchor[:, cols], -1, 1))
        w_ground = max(cfg.ground_weight, cfg.balance_contact_weight) if self.balance else cfg.ground_weight
        res.append(np.sqrt(w_ground) * ca.reshape(ca.fmin(sole[2, :], 0), -1, 1))
        for s in range(2):  # a swinging sole on its path: corners xy at the anchor, at the profile's height
            cols = slice(4 * s, 4 * s + 4)
            ws = np.sqrt(w_contact) * sym.swing[s]
            res.append(ws * ca.reshape(sole[2, cols] - sym.lift[s], -1, 1))
            res.append(ws * ca.reshape(sole[0:2, cols] - sym.anchor[:, cols], -1, 1))
        if self.balance and cfg.upright_weight > 0 and rb.n_root:  # trunk upright: root pitch and roll
            res.append(np.sqrt(cfg.upright_weight) * x[4:6])
        if self.balance and cfg.level_weight > 0:  # soles level, in the air too (a foot lands flat)
            for s in range(2):
                z = sole[2, 4 * s : 4 * s + 4]
                res.append(np.sqrt(cfg.level_weight) * ca.reshape(z - ca.sum2(z) / 4, -1, 1))
        return res

    def _balance_rows(self, bal: _BalanceSymbols, com) -> list:
        """The CoM, DCM and ZMP outside the support region, the ZMP offset, and the capsule pairs."""
        rb, cfg = self.robot, self.config
        res = []
        for i in range(3):
            pt = bal.points[0, i] * com[0:2] + bal.points[1:3, i]
            outside = bal.edges[0, :].T * pt[0] + bal.edges[1, :].T * pt[1] - bal.edges[2, :].T
            res.append(bal.point_w[i] * ca.fmax(outside, 0))
        res.append(bal.zmp_scale * (com[0:2] - bal.c_pred))
        if rb.collision_pairs and cfg.collision_weight > 0:
            # (d² − r²) / 2r ≈ d − r (m) for the profile's capsule pairs, penalised below 0;
            # two feet keep feet_clearance more (a servo leg sags, a lifted foot swings in), the
            # pairs not both on the legs a soft collision_buffer beyond that
            feet, legs = {f.body for f in rb.feet}, leg_bodies(rb)
            buffer = cfg.collision_buffer > 0 and cfg.collision_buffer_weight > 0
            for a, b in rb.collision_pairs:
                cap_a, cap_b = rb.capsules[a], rb.capsules[b]
                rr = cap_a.radius + cap_b.radius + rb.profile.collision_margin
                if cap_a.body in feet and cap_b.body in feet:
                    rr += cfg.feet_clearance
                d2 = segment_distance_sq(*rb.kin.capsule_segment(cap_a), *rb.kin.capsule_segment(cap_b))
                res.append(np.sqrt(cfg.collision_weight) * ca.fmin((d2 - rr * rr) / (2 * rr), 0))
                if buffer and not (cap_a.body in legs and cap_b.body in legs):
                    rs = rr + cfg.collision_buffer
                    res.append(np.sqrt(cfg.collision_buffer_weight) * ca.fmin((d2 - rs * rs) / (2 * rs), 0))
        return res

    def _compile(self, r, p, sole, com) -> None:
        """Compile (x, p) → (r, J, sole, com) (cached) and bind numpy buffers to it once (zero-copy
        evaluation; CasADi reads and writes column-major)."""
        rb, cfg, x = self.robot, self.config, self.robot.kin.x_sym
        J = ca.jacobian(r, x)
        fn = ca.Function("stream_rj", [x, p], [ca.densify(r), ca.densify(J), ca.densify(sole), ca.densify(com)])
        # the cache key names only what shapes the expression graph (weights that enter as
        # parameters, iteration counts and the step rules do not), so configs share binaries
        shape = (self._posture_weight(), cfg.contact_weight, cfg.ground_weight, self.balance)
        if self.balance:
            shape += (
                cfg.balance_contact_weight,
                cfg.level_weight,
                cfg.collision_weight,
                cfg.collision_buffer,
                cfg.collision_buffer_weight,
                cfg.feet_clearance,
                cfg.upright_weight,
            )
        key = f"{rb.fingerprint()}_{hash_config(shape)}"
        self._fn, self.compile_info = compiled_function(fn, key, enable=cfg.compile)
        nx = rb.nx
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

    def _index_parameters(self, K: int, nx: int) -> None:
        """Slices of the parameter vector p, in the order _build stacks it."""
        n_t = 3 * K
        self._p_tgt = slice(0, n_t)
        self._p_x1 = slice(n_t, n_t + nx)
        self._p_x2 = slice(n_t + nx, n_t + 2 * nx)
        self._p_acc = n_t + 2 * nx
        self._p_contact = slice(n_t + 2 * nx + 1, n_t + 2 * nx + 3)
        self._p_anchor = slice(n_t + 2 * nx + 3, n_t + 2 * nx + 19)
        self._p_lift = slice(n_t + 2 * nx + 19, n_t + 2 * nx + 23)  # lift (2,), then swing (2,)
        n_b = n_t + 2 * nx + 23
        self._p_edges = slice(n_b, n_b + 3 * N_EDGES)
        n_b += 3 * N_EDGES
        self._p_points = slice(n_b, n_b + 9)
        self._p_point_w = slice(n_b + 9, n_b + 12)
        self._p_cpred = slice(n_b + 12, n_b + 14)
        self._p_zmp = n_b + 14

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
            raise RetargetError(
                "streaming resume: not available with balance (StreamingConfig.balance); "
                "reset() and stream from the start instead"
            )
        self._x1, self._x2 = np.array(x1, dtype=np.float64), np.array(x2, dtype=np.float64)
        self._residual(self._x1)
        if self._has_feet:
            self._anchor[:] = self._solebuf[0:2, :]

    @property
    def last_keypoints(self) -> np.ndarray | None:
        """Where the robot's keypoints are (K, 3) in the last frame, in the frame its
        configurations are given in (None before the first)."""
        if self._x1 is None:
            return None
        return np.array(self.robot.f_keypoints(self._x1)).T

    def settle(self):
        """After the last frame: an iterable of the frames x (nx,) that step the robot back to
        its own stance and bring it to rest, made as they are taken, with the robot's steps in
        ``.steps`` (:class:`retarget.settle.Settle`; no frames without balance)."""
        from retarget.settle import Settle

        return Settle(self)

    @property
    def planted(self) -> np.ndarray:
        """(2,) bool: the robot's feet held on the ground in the last frame (balance; else the
        contacts given)."""
        return self.planner.planted if self.planner is not None else self._contact

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Position ∩ velocity ∩ acceleration bounds for the next frame, as the bridge's safety
        filter bounds its commands (:class:`ros_free_bridge.control.safety.SafetyFilter`, with
        the same limits), so that it sends the plan nearly as planned: a joint's step differs from its
        last by at most its ``acceleration_limits`` x frame time², and it approaches either end
        of its range no faster than it can stop there (steps s, s − a, s − 2a, ... cover
        s (s + a) / 2a). A joint whose last step its range cannot continue takes the nearest
        step it can."""
        lo, hi = self._lo_pos.copy(), self._hi_pos.copy()
        x1 = self._x1
        if x1 is not None:
            lo = np.maximum(lo, x1 - self._vmax)
            hi = np.minimum(hi, x1 + self._vmax)
        if self._x2 is not None:
            n, a = self.robot.n_root, self._amax
            q1 = x1[n:]

            def brake(room):  # the largest step from which steps s, s - a, ... stop within room
                return np.maximum(0.5 * (-a + np.sqrt(a * a + 8.0 * a * np.maximum(room, 0.0))), a)

            hi[n:] = np.minimum(hi[n:], q1 + brake(self._hi_pos[n:] - q1))
            lo[n:] = np.maximum(lo[n:], q1 - brake(q1 - self._lo_pos[n:]))
            coast = 2.0 * q1 - self._x2[n:]
            # [coast - a, coast + a] ∩ [lo, hi], or the end of [lo, hi] nearest to it
            alo = np.minimum(np.maximum(lo[n:], coast - a), hi[n:])
            ahi = np.maximum(np.minimum(hi[n:], coast + a), lo[n:])
            lo[n:], hi[n:] = alo, ahi
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

    def _load_frame(self, x1, x2, acc: float, targets: np.ndarray, contact) -> None:
        """Write one frame's parameters into the bound buffer: the two frames before (nx,) each,
        √w_a·fps² (0 without history), targets (K, 3), contacts (2,) and the planted feet's anchor."""
        pb = self._pbuf
        pb[self._p_tgt] = targets.reshape(-1)  # (K, 3) row-major = (3, K) column-major
        pb[self._p_x1] = x1
        pb[self._p_x2] = x2
        pb[self._p_acc] = acc
        pb[self._p_contact] = np.asarray(contact, dtype=np.float64)
        pb[self._p_anchor] = self._anchor.reshape(-1, order="F")

    def _solve(self, x, iters: int, lo, hi, rtol: float = 0.0) -> np.ndarray:
        """Levenberg-Marquardt with box constraints lo ≤ x ≤ hi from x, for the frame
        :meth:`_load_frame` loaded (see the module docstring); stops early when a step moves no
        variable by 1e-6 or lowers the cost by no more than ``rtol`` of it."""
        cfg = self.config
        x = np.clip(x, lo, hi)
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
        x_zero[rb.n_root :] = np.clip(
            [h.qpos0 for h in rb.kin.joints], rb.x_lower[rb.n_root :], rb.x_upper[rb.n_root :]
        )
        best, best_cost = x_stand, np.inf
        # with balance the feet start at the robot's own stance, which the stand pose fits:
        # the zero-pose start (a T-pose, for odd first frames) would only cost time
        for start in (x_stand,) if self.balance else (x_stand, x_zero):
            self.reset()
            self._x1 = None
            self._load_frame(start, start, 0.0, targets, contact)
            x = self._solve(start, self.config.first_iterations, self._lo_pos, self._hi_pos, rtol=self._first_rtol)
            cost = self._residual(x)
            if cost < best_cost:
                best, best_cost = x, cost
        return best

    def step(self, targets: np.ndarray, contact=(False, False), still: bool = False) -> np.ndarray:
        """targets (K, 3) m, contact (2,) bool (the human's left, right foot) → configuration
        x (nx,) within all limits. With balance the robot's own foot contacts are in
        :attr:`planted` afterwards (see the module docstring). ``still``: the acceleration row
        taken against the last frame held still (x₋₂ = x₋₁), i.e. a velocity penalty: a held
        pose comes to rest instead of ringing (the acceleration row alone leaves a weakly held
        direction, the pelvis yaw over planted feet, an oscillator that decays over seconds)."""
        targets = np.asarray(targets, dtype=np.float64)
        if targets.shape != (self.robot.n_keypoints, 3) or not np.all(np.isfinite(targets)):
            raise RetargetError(
                f"streaming step: targets must be finite with shape ({self.robot.n_keypoints}, 3), got {targets.shape}"
            )
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
            x2 = self._x2 if self._x2 is not None and not still else self._x1
            x = x1.copy()
            acc = self._sqrt_wa_fps2
            iters = cfg.iterations
        lo, hi = self.bounds()
        if self.balance:
            if first:  # the stream starts standing: both feet put down flat where the fit left them
                self._residual(x)
                contact = self.planner.start(self._solebuf, self._combuf[0:2])
            else:
                contact = self.planner.next(contact, targets)
        self._contact = np.array(contact, dtype=bool)
        self._load_frame(x1, x2, acc, targets, contact)
        x = self._solve(x, iters, lo, hi, rtol=self._first_rtol if first else 0.0)
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
            raise RetargetError(
                f"streaming step_human: positions must be finite with shape (22, 3), got {positions.shape}"
            )
        return self.step(self.scaler.targets(positions[None])[0], contact)

    def split(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """x (nx,) → joint angles (n,) rad in the robot's joint order, root position (3,) m,
        root quaternion (4,) w, x, y, z."""
        pos, quat = self.robot.kin.root_pose(np.asarray(x)[None])
        return np.array(x[self.robot.n_root :]), pos[0], quat[0]

    def check_clip(self, motion: Motion) -> None:
        """One RetargetError for a clip this retargeter cannot run: too short, or at another
        frame rate than its own (its step timings and speed limits are per frame)."""
        check_motion(motion, min_frames=2)
        if abs(motion.fps - self.fps) > 1e-9:
            raise RetargetError(
                f"{motion.name or 'motion'}: is {motion.fps:g} fps "
                f"but this retargeter runs at {self.fps:g}; resample the motion"
            )

    def run(self, motion: Motion, contacts=None, scaler=None) -> RobotTrajectory:
        """Retarget a whole clip frame by frame (as the live bridge would). ``scaler``: a
        :class:`retarget.targets.KeypointScaler` (default: fitted on this clip)."""
        self.check_clip(motion)
        tg = make_targets(self.robot, motion, contacts, scaler)
        self.reset()
        X, held = [], []
        for t in range(motion.n_frames):
            X.append(self.step(tg.keypoints[t], tg.contacts[t]))
            held.append(self.planted.astype(int).tolist())
        meta = {"mode": "streaming", "source": motion.name, "compiled": self.compile_info}
        X = np.stack(X)
        if self.balance:  # the robot's own contacts (it steps at its own pace), as the offline schedule's
            from retarget.planned import what_changed  # (planned builds on this module)

            meta["contacts"] = held
            meta["changes"] = what_changed(self.robot, X, tg, held, self.planner)
        return trajectory_from_x(self.robot, X, motion.fps, meta)


def hash_config(cfg) -> str:
    import hashlib

    return hashlib.sha256(repr(cfg).encode()).hexdigest()[:8]


def trajectory_from_x(robot, X: np.ndarray, fps: float, meta: dict) -> RobotTrajectory:
    """Configurations X (T, nx) → RobotTrajectory in the robot's joint order."""
    root_pos, root_quat = robot.kin.root_pose(X)
    return RobotTrajectory(robot.joint_names, X[:, robot.n_root :], root_pos, root_quat, fps, robot.ref, dict(meta))

"""Streaming retargeting: one frame at a time, warm-started, limits as hard bounds.

Each frame solves a small bounded nonlinear least-squares problem in the configuration
x (nx,) (see :mod:`retarget.kinematics`):

    min_x ½‖r(x)‖²   s.t.   lb ≤ x ≤ ub

    r = [ √w_k (p_k(x) − target_k)                 keypoint tracking, m
          √w_a · fps² (x − 2 x₋₁ + x₋₂)             acceleration against the two frames already emitted
          √w_p (q − q_stand)                        posture
          √w_c · c_s · (z_sole, xy_sole − xy_sole₋₁) a foot in contact stays on the ground and put
          √w_g · min(z_sole, 0)                     no sole corner below the ground
          √w_b · max(0, A c_xy(x) − b)              balance (optional): CoM over the support polygon
          √w_z · (h/g) fps² (c_xy(x) − 2c₋₁ + c₋₂) ] balance: the CoM's acceleration as a ZMP offset

    lb, ub = joint range ∩ [x₋₁ − v_max/fps, x₋₁ + v_max/fps]  (position and velocity limits,
                                                               the root's speed limits too)

solved by a few projected Gauss-Newton steps from the previous frame: each step solves
the box-constrained quadratic model (JᵀJ + μI) d = −Jᵀr with a primal active set (free
variables solved exactly, variables at a bound fixed there until their multiplier says
release), then accepts the step if the cost falls (else halves it). r and J come from one
CasADi function, compiled to C and cached (:mod:`retarget.codegen`). Every iterate stays
in the box, so no emitted frame can violate a position or velocity limit; a final clip
makes that exact in floating point.

Balance (``StreamingConfig.balance``, free-base robots with feet; a fixed base ignores it).
The optional rows keep a free-standing robot on its feet while it plays the frames open loop:

- Feet the robot has *planted* are held, with the strong ``balance_contact_weight``, on their
  level footprint: the sole's own rectangle flat on the ground (z = 0) at the centre and
  heading the foot had when it touched down (:func:`retarget.support.level_footprint`), until
  the foot lifts. (Without balance the anchor is the previous frame's sole, re-taken each frame.)
- The CoM ground projection c_xy stays inside the convex hull of the planted footprints, each
  shrunk by ``balance_margin``: half-planes A c ≤ b (:mod:`retarget.support`), a one-sided
  penalty with weight ``balance_weight``. The ZMP row penalises the CoM's acceleration, with
  h the standing CoM height, so that the CoM moves quasi-statically.
- Contacts come from the human (the motion's labels or detected ones). A foot touches down
  when the human's does. A foot lifts only when the human's lifts *and* the CoM of the last
  emitted frame lies over the other planted foot's shrunk footprint; until then the robot
  shifts its weight: the CoM's region is the hull of the stance footprint and one point
  p = c₋₁ moved towards it by ``shift_speed`` / fps, so the CoM travels to the stance foot at
  that speed. The last planted foot never lifts (a jump is played with both feet down).
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from dualflow.motion import Motion
from retarget.codegen import compiled_function
from retarget.errors import RetargetError
from retarget.support import (closest_point, convex_hull, double_support_points, halfplanes, level_footprint, margin,
                              shrink_footprint, support_polygon)
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
    balance: bool = False  # free-base robots with feet only (see the module docstring)
    balance_margin: float = 0.015  # m, footprints shrunk by this before the CoM must lie inside
    balance_weight: float = 1e4  # per m² of CoM outside the shrunk support polygon
    balance_contact_weight: float = 1e3  # replaces contact_weight for planted feet with balance on
    zmp_weight: float = 0.3  # per m² of ZMP offset (h/g)·CoM acceleration
    dcm_weight: float = 1e3  # per m² of DCM (capture point) outside the shrunk support polygon
    zmp_limit_weight: float = 30.0  # per m² of ZMP outside the shrunk support polygon
    collision_weight: float = 1e3  # balance: per m² of capsule-pair penetration (the profile's pairs)
    shift_speed: float = 0.15  # m/s, CoM travel towards the stance foot before the other lifts
    shift_accel: float = 1.0  # m/s², how fast the CoM's speed towards the stance foot may grow
    release_tolerance: float = 0.002  # m, CoM this far outside the stance footprint still lets a foot lift
    lift_height: float = 0.01  # m, a human foot lifts when its ankle target rises this far above the other's
    step_distance: float = 0.03  # m, ... or its target moves this far from where the foot was put down
    double_support_inset: float = 0.01  # m, the CoM stays this far inside the feet's centre lines on two feet
    anchor_time: float = 0.1  # s, time constant of the stance-foot anchoring of the human's translation


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


#: half-planes of the balance region passed to the compiled function: the hull of two
#: footprints (8 corners) and the weight-shift point has at most 9 edges; unused rows are 0·c ≤ 1
_N_EDGES = 10


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
            res.append(np.sqrt(cfg.ground_weight) * ca.reshape(ca.fmin(sole[2, :], 0), -1, 1))
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
                # (d² − r²) / 2r ≈ d − r (m) for the profile's capsule pairs, penalised below 0
                r2 = np.array([2 * (rb.capsules[a].radius + rb.capsules[b].radius + rb.profile.collision_margin)
                               for a, b in rb.collision_pairs])
                res.append(np.sqrt(cfg.collision_weight) * ca.fmin(rb.collision_expr / ca.DM(r2), 0))
            p_parts += [ca.reshape(edges, -1, 1), ca.reshape(points, -1, 1), point_w, c_pred, zmp_scale]
        r = ca.vertcat(*res)
        J = ca.jacobian(r, x)
        p = ca.vertcat(*p_parts)
        sole = rb.sole_expr if rb.has_feet else ca.SX.zeros(3, 0)
        fn = ca.Function("stream_rj", [x, p], [ca.densify(r), ca.densify(J), ca.densify(sole), ca.densify(com)])
        key = f"{rb.fingerprint()}_{hash_config(cfg)}"
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
        if self.balance:
            h = float(rb.evaluate(rb.x_stand[None])["com"][0, 2] - rb.evaluate(rb.x_stand[None])["sole"][0, :, 2].min())
            self._zmp_k = h / 9.81 * self.fps ** 2  # ZMP = c − (h/g) c̈ = (1 + k) c − k (2c₋₁ − c₋₂)
            self._dcm_k = self.fps * np.sqrt(h / 9.81)  # DCM = c + ċ/ω = (1 + k) c − k c₋₁
            self._zmp_scale = np.sqrt(cfg.zmp_weight) * self._zmp_k
            self._sole_local = [f.corners for f in rb.feet]
        names = rb.keypoint_names
        self._ankles = ([names.index("left_ankle"), names.index("right_ankle")]
                        if "left_ankle" in names and "right_ankle" in names else None)
        if self.balance and self._ankles is None:
            raise RetargetError(f"{rb.profile.source or rb.name}: field keypoints: streaming balance needs left_ankle "
                                "and right_ankle keypoints (it follows the person's feet); add them or turn balance off")

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
        self._stance: list = [None, None]  # per planted foot: its shrunk footprint's (hull, A, b)
        self._region_key = None
        self._c1 = self._c2 = None
        self._sole1 = None
        self.shifting = False
        #: horizontal offset (2,) m added to the targets (balance: the stance foot anchors the
        #: human's translation) and the ankle targets (2, 2) recorded when each foot touched down
        self.offset = np.zeros(2)
        self._ankle_ref = np.zeros((2, 2))
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
            targets = self._anchor_targets(targets, contact, first)
            if first:
                # the stream starts standing: both feet put down flat where the fit left them
                self._residual(x)
                self._sole1 = self._solebuf.copy()
                self._c1 = self._c2 = self._combuf[0:2].copy()
                contact = self._plan_balance((True, True))
            else:
                contact = self._plan_balance(contact)
            self._pbuf[self._p_zmp] = 0.0 if first else self._zmp_scale
            self._set_points(first)
        x = self._solve(x, x1, x2, acc, targets, contact, iters, lo, hi)
        x = np.clip(x, lo, hi)
        if self._has_feet:
            self._residual(x)
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
        """Shift the targets horizontally so that the human's feet that are down, and that the
        robot also has planted, stay where their ankle targets were when the robot's foot
        touched down: o ← o + α (mean_s (ref_s − ankle_s) − o), α = 1 − exp(−1 / (fps τ)),
        τ = ``anchor_time``. The robot then follows the person's steps, not their drift or
        skating (generated motion often slides its feet), which it could not do standing."""
        ankles = targets[self._ankles, 0:2]  # (2, 2) human ankle targets, before the offset
        if not first:
            ref = [s for s in range(2) if contact[s] and self.planted[s]]
            if ref:
                raw = np.mean([self._ankle_ref[s] - ankles[s] for s in ref], axis=0)
                alpha = 1.0 - np.exp(-1.0 / (self.fps * self.config.anchor_time))
                self.offset = self.offset + alpha * (raw - self.offset)
        self._ankles_now = ankles + self.offset
        self._ankle_z = targets[self._ankles, 2]
        out = targets.copy()
        out[:, 0:2] += self.offset
        return out

    def _set_points(self, first: bool) -> None:
        """Parameters of the CoM, DCM and ZMP rows (see the module docstring)."""
        cfg = self.config
        pred = 2 * self._c1 - self._c2
        kd, kz = self._dcm_k, self._zmp_k
        pts = np.array([[1.0, 0.0, 0.0],
                        [1.0 + kd, *(-kd * self._c1)],
                        [1.0 + kz, *(-kz * pred)]])  # rows: com, dcm, zmp; columns α, β
        w = np.sqrt([cfg.balance_weight, 0.0 if first else cfg.dcm_weight, 0.0 if first else cfg.zmp_limit_weight])
        self._pbuf[self._p_points] = pts.reshape(-1)  # (3, 3) column-major = rows of pts
        self._pbuf[self._p_point_w] = w

    def _plan_balance(self, human_contact) -> tuple[bool, bool]:
        """Update :attr:`planted` from the human's contacts and the last frame's CoM, and set
        the anchors, the balance region and the CoM prediction in the parameter buffer.
        Returns the contacts (left, right) the solver holds on the ground this frame."""
        cfg = self.config
        contact = np.asarray(human_contact, dtype=bool)
        # the human's feet: a lift counts only when the foot really leaves (rises above the other
        # by lift_height, or moves step_distance from where it was put down); a near-standing
        # person's contact flicker then never makes the robot stand on one leg
        dz = self._ankle_z - self._ankle_z[::-1]
        moved = np.linalg.norm(self._ankles_now - self._ankle_ref, axis=1)
        lifted = ~contact & ((dz > cfg.lift_height) | (self.planted & (moved > cfg.step_distance)))
        down = contact | (dz < 0.5 * cfg.lift_height)
        for s in range(2):
            if down[s] and not lifted[s] and not self.planted[s]:  # touch down: flat, where the foot is now
                self._touch_down(s)
        want = ~lifted
        c1 = self._c1
        shift_point = None
        self.shifting = False
        for s in range(2):
            other = 1 - s
            if want[s] or not self.planted[s] or not self.planted[other]:
                continue
            hull, A, b = self._stance[other]
            if margin(c1, A, b) >= -cfg.release_tolerance:
                self.planted[s] = False  # the weight is on the other foot: lift
                self._prints[s] = None
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
        key = (bool(self.planted[0]), bool(self.planted[1]))
        if shift_point is None and self._region_key != key:
            self._region_key = key
            if key == (True, True):
                self._set_region(double_support_points(self._prints, cfg.balance_margin, cfg.double_support_inset))
            else:
                self._set_region(np.concatenate([self._stance[f][0] for f in range(2) if self.planted[f]]))
        self._pbuf[self._p_cpred] = 2 * self._c1 - self._c2
        return key

    def _touch_down(self, s: int) -> None:
        """Plant foot s flat where it is now: its level footprint, the shrunk footprint's
        half-planes, the anchor of the contact rows and the ankle target it pins."""
        self.planted[s] = True
        fp = level_footprint(self._sole1[:, 4 * s:4 * s + 4].T, self._sole_local[s])
        self._prints[s] = fp
        self._stance[s] = support_polygon([shrink_footprint(fp, self.config.balance_margin)])
        self._anchor[:, 4 * s:4 * s + 4] = fp.T
        self._ankle_ref[s] = self._ankles_now[s]
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

"""Streaming retargeting: one frame at a time, warm-started, limits as hard bounds.

Each frame solves a small bounded nonlinear least-squares problem in the configuration
x (nx,) (see :mod:`retarget.kinematics`):

    min_x ½‖r(x)‖²   s.t.   lb ≤ x ≤ ub

    r = [ √w_k (p_k(x) − target_k)                 keypoint tracking, m
          √w_a · fps² (x − 2 x₋₁ + x₋₂)             acceleration against the two frames already emitted
          √w_p (q − q_stand)                        posture
          √w_c · c_s · (z_sole, xy_sole − xy_sole₋₁) a foot in contact stays on the ground and put
          √w_g · min(z_sole, 0) ]                   no sole corner below the ground

    lb, ub = joint range ∩ [x₋₁ − v_max/fps, x₋₁ + v_max/fps]  (position and velocity limits,
                                                               the root's speed limits too)

solved by a few projected Gauss-Newton steps from the previous frame: each step solves
the box-constrained quadratic model (JᵀJ + μI) d = −Jᵀr with a primal active set (free
variables solved exactly, variables at a bound fixed there until their multiplier says
release), then accepts the step if the cost falls (else halves it). r and J come from one
CasADi function, compiled to C and cached (:mod:`retarget.codegen`). Every iterate stays
in the box, so no emitted frame can violate a position or velocity limit; a final clip
makes that exact in floating point.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from dualflow.motion import Motion
from retarget.codegen import compiled_function
from retarget.errors import RetargetError
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
            for s in range(2):
                cols = slice(4 * s, 4 * s + 4)
                wc = np.sqrt(cfg.contact_weight) * contact[s]
                res.append(wc * ca.reshape(sole[2, cols], -1, 1))
                res.append(wc * ca.reshape(sole[0:2, cols] - anchor[:, cols], -1, 1))
            res.append(np.sqrt(cfg.ground_weight) * ca.reshape(ca.fmin(sole[2, :], 0), -1, 1))
        r = ca.vertcat(*res)
        J = ca.jacobian(r, x)
        p = ca.vertcat(ca.reshape(tgt, -1, 1), x1, x2, acc_scale, contact, ca.reshape(anchor, -1, 1))
        sole = rb.sole_expr if rb.has_feet else ca.SX.zeros(3, 0)
        fn = ca.Function("stream_rj", [x, p], [ca.densify(r), ca.densify(J), ca.densify(sole)])
        key = f"{rb.fingerprint()}_{hash_config(cfg)}"
        self._fn, self.compile_info = compiled_function(fn, key, enable=cfg.compile)
        # zero-copy evaluation: bind numpy buffers once (CasADi reads/writes column-major)
        self._xbuf = np.zeros(nx)
        self._pbuf = np.zeros(p.numel())
        self._rbuf = np.zeros(r.numel())
        self._Jbuf = np.zeros((r.numel(), nx), order="F")
        self._solebuf = np.zeros((3, sole.shape[1]), order="F")
        buf, self._eval = self._fn.buffer()
        buf.set_arg(0, memoryview(self._xbuf))
        buf.set_arg(1, memoryview(self._pbuf))
        buf.set_res(0, memoryview(self._rbuf))
        buf.set_res(1, memoryview(self._Jbuf.reshape(-1, order="F")))
        buf.set_res(2, memoryview(self._solebuf.reshape(-1, order="F")))
        self._buffer = buf  # keep alive
        n_t = 3 * K
        self._p_tgt = slice(0, n_t)
        self._p_x1 = slice(n_t, n_t + nx)
        self._p_x2 = slice(n_t + nx, n_t + 2 * nx)
        self._p_acc = n_t + 2 * nx
        self._p_contact = slice(n_t + 2 * nx + 1, n_t + 2 * nx + 3)
        self._p_anchor = slice(n_t + 2 * nx + 3, n_t + 2 * nx + 19)
        self._has_feet = rb.has_feet
        self._lo_pos, self._hi_pos = rb.x_lower.copy(), rb.x_upper.copy()
        self._vmax = np.concatenate([rb.root_velocity_limits, rb.velocity_limits]) / self.fps
        self._sqrt_wa_fps2 = np.sqrt(cfg.accel_weight) * self.fps ** 2

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
        """targets (K, 3) m, contact (2,) bool → configuration x (nx,) within all limits."""
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
        x = self._solve(x, x1, x2, acc, targets, contact, iters, lo, hi)
        x = np.clip(x, lo, hi)
        if self._has_feet:
            self._residual(x)
            self._anchor = self._solebuf[0:2, :].copy()
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

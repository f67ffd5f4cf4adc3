"""Offline retargeting: the whole clip, or long overlapping windows, solved with IPOPT.

Per window of W frames, with X = [x_0 … x_{W−1}] (nx, W) and, with balance, convex weights
Λ = [λ_0 … λ_{W−1}] (8, W) over the shrunk sole corners:

    min  Σ_t f_t Σ_k w_k ‖p_k(x_t) − target_kt‖²                        keypoint tracking (m²)
       + w_a Σ_t ‖fps² (x_{t+1} − 2x_t + x_{t−1})‖²                     acceleration
       + w_j Σ_t ‖fps³ (x_{t+2} − 3x_{t+1} + 3x_t − x_{t−1})‖²          jerk
       + w_p Σ_t ‖q_t − q_stand‖²  + w_fix Σ_{t<n_fix} ‖x_t − x̄_t‖²     posture; continuity with the previous window
    s.t. lb ≤ x_t ≤ ub                                                    joint position limits (bounds)
         |x_{t+1} − x_t| ≤ v_max / fps                                    joint and root velocity limits (linear)
         z_c(x_t) ≥ 0, and = 0 for corners 0-2 while the foot is in contact  no sole corner below the ground; flat contact
         xy_0(x_{t+1}) = xy_0(x_t), (d_t × d_{t+1})_z / |d|² = 0          no sliding or turning while it stays in contact
              (d = xy_2 − xy_0, the sole diagonal). Exactly 6 equations fix a planted foot's 6 DOF:
              the redundant 8 + 8 of fixing all four corners break the constraint qualification
              (rank-deficient Jacobian), which slowed IPOPT (≈21 → ≈15 iterations per window on CMU)
         b_t = Σ_i λ_ti s̃_i(x_t), Σ_i λ_ti = 1, λ ≥ 0                     balance: the point b over the support polygon
              (λ_ti = 0 for corners of a foot in the air)                   shrunk by ``balance_margin``
              b_t = zmp_t = c_xy,t − (c_z,t / g) fps² (c_xy,t+1 − 2 c_xy,t + c_xy,t−1)   (``zmp=True``: the
              cart-table ZMP, one-sided at window ends), else (default) the static CoM b_t = c_xy,t
         ‖seg_a − seg_b‖² ≥ (r_a + r_b + margin)²                         self-collision between capsule pairs
         n·(a_i − b_j) ≥ r_a + r_b + margin                               the pairs between the two feet
              (``collision_model="sole-plane"``, default): every capsule end point a_i on the left
              foot and b_j on the right on their own sides of a plane along the feet, n their
              common lateral axis (retarget.robot.Separation). Smooth and conservative; the
              segment distance's closest-point case switches (the soles are near contact in most
              frames) cost IPOPT 34 instead of 22 iterations per window on the CMU pair

f_t is 1 for real frames and 0 for padding (also masking the acceleration and jerk terms
that reach into the padding, so a padded window ends like the clip; f_t and w_fix enter as
0/1 parameters), x̄ are the frames already fixed by the
previous window (w_fix = 0 in the first), so consecutive windows share n_fix frames and
the acceleration/jerk terms run across the seam: there is no seam to blend.

Per-frame quantities come from one CasADi function ``frame(x)`` mapped over the W frames
(``Function.map``), so the problem is a handful of matrix expressions whatever W is. Its
structure depends only on the robot, the profile and W (contacts enter as constraint
bounds, padding as f_t), so IPOPT's problem functions (objective, gradient, constraint
Jacobian, Lagrangian Hessian) are compiled to C once per robot and cached on disk
(:mod:`retarget.codegen`). The constraint Jacobian and the Gauss-Newton Hessian 2 J_Rᵀ J_R are
built by the chain rule, dg/dw = ∂g/∂Y · blockdiag_t(∂y_t/∂x_t) + ∂g/∂w with Y the per-frame
outputs, from one SX frame Jacobian mapped over the window (CasADi's AD of the mapped graph
took ~100 directional sweeps: 2-3x slower Jacobians). Each window is warm-started from the
streaming solver's output.

If IPOPT reports the window infeasible (limits and contacts cannot all hold at the clip's
speed), :class:`RetargetError` says which frames and offers re-timing (``retime``: play the
clip that many times slower); ``auto_retime`` tries 1.25×, 1.5×, 2× by itself. IPOPT's status
per window is kept in the trajectory's ``meta["ipopt_status"]``. Only a converged window
(``Solve_Succeeded``, ``Solved_To_Acceptable_Level``) is ever kept: an unfinished one
(``Maximum_Iterations_Exceeded``, ``Restoration_Failed``, ``Infeasible_Problem_Detected``, …) is a
failed retarget, a :class:`RetargetError` naming the window's frames and IPOPT's status, with
``time_s`` at the worst constraint violation or, when the constraints hold, at the window's first
frame (its point may satisfy every constraint and still be far from the tracking optimum, so it
is never passed on as a result; ``auto_retime`` retries it slower like an infeasible one). A solver
error (``Invalid_Option``, ``Error_In_Step_Computation``, …) always raises at once, even when the
point it returned (the untouched warm start) looks feasible.

Speed: IPOPT's own linear algebra (MUMPS on the KKT system, ~0.3 ms per frame and
iteration) dominates. The adaptive barrier parameter is chosen by IPOPT's quality-function
oracle (``mu_oracle``), not Mehrotra's probing: with the smooth sole rows that takes 17-19
iterations per CMU window instead of 22 (with the segment-distance rows it does not help).
MUMPS gets its workspace estimate + 100 % (``MUMPS_MEM_PERCENT``), not IPOPT's 1000 %, which made it
allocate and touch 11x the estimate at every factorisation (page faults ~11 % of the time).
See :func:`retarget.codegen.single_threaded_linear_algebra` for the thread setting. fatrop (the structure-exploiting solver shipped with CasADi) was tried on a
stage-wise version of this problem and was slower (see bench/retarget_speed.py's docstring).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import casadi as ca
import numpy as np

from dualflow.motion import Motion
from retarget.codegen import compiled_nlpsol, single_threaded_linear_algebra
from retarget.errors import RetargetError
from retarget.streaming import StreamingConfig, StreamingRetargeter, hash_config, trajectory_from_x
from retarget.targets import Targets, check_motion, make_targets
from retarget.trajectory import RobotTrajectory

_OK = {"Solve_Succeeded", "Solved_To_Acceptable_Level"}
#: IPOPT outcomes that say the solver (its options, its linear solver, the numbers it was
#: given) failed, not that the clip is infeasible: they always raise, whatever point came back
#: (with an unavailable linear solver IPOPT returns the untouched warm start, which may well
#: satisfy the constraints). Every other outcome outside _OK (Maximum_Iterations_Exceeded,
#: Restoration_Failed, ...) fails the window too: as infeasible when the returned point violates
#: the constraints, as not converged otherwise (both retried by ``auto_retime``).
_ERRORS = {"Invalid_Option", "Invalid_Problem_Definition", "Error_In_Step_Computation", "Unrecoverable_Exception",
           "NonIpopt_Exception_Thrown", "Insufficient_Memory", "Internal_Error", "Not_Enough_Degrees_Of_Freedom",
           "Invalid_Number_Detected"}
GRAVITY = 9.81  # m/s²
#: MUMPS working space beyond its estimate (%), IPOPT's ``mumps_mem_percent`` (see _solver)
MUMPS_MEM_PERCENT = 100


@dataclass(frozen=True)
class OfflineConfig:
    """Solver settings. ``window`` 0 means the whole clip in one problem."""

    window: int = 80
    overlap: int = 10
    n_fix: int = 3
    accel_weight: float = 1e-7
    jerk_weight: float = 1e-9
    posture_weight: float | None = None
    fix_weight: float = 1e4
    contacts: bool = True
    balance: bool = False
    balance_margin: float = 0.01
    zmp: bool = False  # True: balance keeps the ZMP (CoM with its acceleration term) over the polygon, not the CoM
    self_collision: bool = True
    # "sole-plane": the pairs between the two feet as a separating plane along the feet's
    # lateral axis (smooth, conservative; RetargetRobot.offline_collision_expr), the other
    # pairs as squared segment distances; "distance": every pair as its squared segment distance
    collision_model: str = "sole-plane"
    velocity_safety: float = 0.995
    compile: bool = True
    max_iter: int = 300
    tol: float = 1e-5
    retime: float = 1.0
    auto_retime: bool = False
    hessian: str = "gauss-newton"
    ipopt_options: tuple = ()  # extra (name, value) pairs passed to IPOPT, e.g. (("print_level", 5),)


class OfflineRetargeter:
    """Retarget whole clips for one robot; the IPOPT problem is built (and compiled) once per window length."""

    def __init__(self, robot, config: OfflineConfig = OfflineConfig(), streaming: StreamingConfig | None = None):
        self.robot = robot
        self.config = config
        self.streaming_config = streaming or StreamingConfig(accel_weight=1e-8)
        self._solvers: dict[tuple, tuple] = {}
        self._problems: dict[tuple, dict] = {}
        self._streams: dict[float, StreamingRetargeter] = {}  # warm-start solvers by fps, built once
        self._frame_fn = self._build_frame_function()

    # -- problem construction -----------------------------------------------------
    def _build_frame_function(self) -> ca.Function:
        """frame(x) → keypoints (3, K), sole (3, 8), shrunk sole xy (2, 8), com (3, 1), collision (P, 1)."""
        rb, cfg = self.robot, self.config
        x = rb.kin.x_sym
        shrunk = []
        for foot in rb.feet:
            c = foot.corners
            centre = c.mean(axis=0)
            off = c - centre
            # shrink each corner towards the centre by the margin along the two sole edge directions
            e1 = (c[0] - c[1]) / np.linalg.norm(c[0] - c[1])
            e2 = (c[1] - c[2]) / np.linalg.norm(c[1] - c[2])
            for o in off:
                a, b = o @ e1, o @ e2
                a = np.sign(a) * max(abs(a) - cfg.balance_margin, 0.0)
                b = np.sign(b) * max(abs(b) - cfg.balance_margin, 0.0)
                shrunk.append(rb.kin.point(foot.body, centre + a * e1 + b * e2)[0:2])
        shr = ca.horzcat(*shrunk) if shrunk else ca.SX.zeros(2, 0)
        if cfg.collision_model not in ("sole-plane", "distance"):
            raise RetargetError(f"offline config: collision_model must be 'sole-plane' or 'distance', got {cfg.collision_model!r}")
        if not cfg.self_collision:
            coll = ca.SX.zeros(0, 1)
        else:
            coll = rb.offline_collision_expr if cfg.collision_model == "sole-plane" else rb.collision_expr
        return ca.Function("frame", [x], [rb.keypoints_expr, rb.sole_expr, shr, rb.com_expr, coll])

    def _frame_jacobian(self, W: int) -> ca.Function:
        """X (nx, W) → (Y (ny, W): the frame function's outputs stacked per frame, ∂Y/∂X (ny, nx·W):
        frame t's Jacobian in columns t·nx … t·nx + nx − 1), one SX function mapped over W frames."""
        fr, x = self._frame_fn, self.robot.kin.x_sym
        y = ca.vertcat(*[ca.vec(o) for o in fr(x)])
        return ca.Function("frame_jac", [x], [y, ca.jacobian(y, x)]).map(W, "serial")

    def _solver(self, W: int, fps: float):
        key = (W, round(fps, 6))
        if key in self._solvers:
            return self._solvers[key]
        rb, cfg = self.robot, self.config
        nx, nr, K = rb.nx, rb.n_root, rb.n_keypoints
        feet = rb.has_feet and rb.floating and cfg.contacts
        balance = feet and cfg.balance
        X = ca.MX.sym("X", nx, W)
        L = ca.MX.sym("L", 8, W) if balance else ca.MX.sym("L", 0, W)
        TGT = ca.MX.sym("TGT", 3 * K, W)
        FW = ca.MX.sym("FW", 1, W)
        XF = ca.MX.sym("XF", nx, cfg.n_fix)
        WF = ca.MX.sym("WF", 1, 1)
        # the per-frame outputs as a symbol Y (ny, W) (column t = the frame's outputs, stacked):
        # R and g are written once in the mapped outputs (f, g and the gradient) and once in Y
        # (their Jacobians by the chain rule, below)
        fr = self._frame_fn
        shapes = [fr.sparsity_out(i).shape for i in range(fr.n_out())]
        ny = sum(r * c for r, c in shapes)
        Y = ca.MX.sym("Y", ny, W)
        parts, i0 = [], 0
        for r, c in shapes:  # (r*c, W) rows → (r, c*W), the layout Function.map gives
            parts.append(ca.reshape(Y[i0:i0 + r * c, :], r, c * W))
            i0 += r * c

        def terms(kp, sole, shr, com, coll):
            """R (residuals), J = ‖R‖², g and its row layout from the per-frame outputs (as Function.map lays them out)."""
            # objective J = ‖R‖² with R the stacked weighted residuals (module docstring)
            wk = np.sqrt(np.repeat(rb.keypoint_weights, 3))[:, None]
            wp = rb.profile.posture_weight if cfg.posture_weight is None else cfg.posture_weight
            acc = (X[:, 2:] - 2 * X[:, 1:-1] + X[:, :-2]) * fps ** 2
            jerk = (X[:, 3:] - 3 * X[:, 2:-1] + 3 * X[:, 1:-2] - X[:, :-3]) * fps ** 3
            R = ca.vertcat(
                ca.vec((ca.reshape(kp, 3 * K, W) - TGT) * ca.repmat(ca.DM(wk), 1, W) * ca.repmat(FW, 3 * K, 1)),
                np.sqrt(wp) * ca.vec(X[nr:, :] - ca.repmat(ca.DM(rb.x_stand[nr:]), 1, W)),
                np.sqrt(cfg.accel_weight) * ca.vec(acc * ca.repmat(FW[:, 2:], nx, 1)),
                np.sqrt(cfg.jerk_weight) * ca.vec(jerk * ca.repmat(FW[:, 3:], nx, 1)),
                WF * np.sqrt(cfg.fix_weight) * ca.vec(X[:, :cfg.n_fix] - XF),
            )
            J = ca.sumsqr(R)
            g = [ca.vec(X[:, 1:] - X[:, :-1])]
            layout = {"vel": nx * (W - 1)}
            if feet:
                g.append(ca.vec(ca.reshape(sole[2, :], 8, W)))
                layout["sole_z"] = 8 * W
                xy = ca.reshape(sole[0:2, :], 16, W)  # per frame: x0 y0 x1 y1 ... of the 8 corners
                slide = []
                for f, foot in enumerate(rb.feet):
                    c0, c2 = 8 * f, 8 * f + 4           # rows of corner 0 and corner 2 of this foot
                    d = xy[c2:c2 + 2, :] - xy[c0:c0 + 2, :]
                    diag2 = float(np.sum((foot.corners[2] - foot.corners[0]) ** 2))
                    slide += [xy[c0:c0 + 2, 1:] - xy[c0:c0 + 2, :-1],
                              (d[0, :-1] * d[1, 1:] - d[1, :-1] * d[0, 1:]) / diag2]
                g.append(ca.vec(ca.vertcat(*slide)))
                layout["slide"] = 6 * (W - 1)
            if balance:
                s = ca.reshape(shr, 16, W)
                sx, sy = s[0::2, :], s[1::2, :]
                c3 = ca.reshape(com, 3, W)
                comxy = c3[0:2, :]
                if cfg.zmp and W >= 3:
                    # ZMP of the cart-table model: p = c_xy − (c_z / g) · c̈_xy, with c̈ the central
                    # second difference (one-sided at the window's ends)
                    acc = (c3[0:2, 2:] - 2 * c3[0:2, 1:-1] + c3[0:2, :-2]) * fps ** 2
                    acc = ca.horzcat(acc[:, 0], acc, acc[:, -1])
                    comxy = comxy - ca.repmat(c3[2, :] / GRAVITY, 2, 1) * acc
                g.append(ca.vec(ca.vertcat(comxy[0, :] - ca.sum1(L * sx), comxy[1, :] - ca.sum1(L * sy), ca.sum1(L) - 1)))
                layout["balance"] = 3 * W
            P = coll.shape[0]
            if P:
                g.append(ca.vec(coll))
                layout["collision"] = P * W
            return R, J, ca.vertcat(*g), layout, P

        R_x, J_x, g_x, layout, P = terms(*fr.map(W, "serial")(X))
        R, _, g, _, _ = terms(*parts)
        w = ca.vertcat(ca.vec(X), ca.vec(L))
        par = ca.vertcat(ca.vec(TGT), ca.vec(FW), ca.vec(XF), WF)
        nlp = {"x": w, "p": par, "f": J_x, "g": g_x}
        dy_dx = self._frame_jacobian(W)
        # constraint Jacobian by the chain rule: dg/dw = ∂g/∂Y · blockdiag_t(∂y_t/∂x_t) + ∂g/∂w, with
        # each frame's Jacobian from one SX function mapped over the W frames. CasADi's own AD
        # of the mapped graph needs ~100 directional sweeps over all frames (~4-7 ms per call
        # against ~1 ms for the W frame Jacobians); the values are the same
        JYs = ca.MX.sym("JY", dy_dx.sparsity_out(1))
        BD = ca.horzcat(ca.diagcat(*ca.horzsplit(JYs, nx)), ca.MX(ny * W, w.shape[0] - nx * W))
        Jg = ca.mtimes(ca.jacobian(g, Y), BD) + ca.jacobian(g, w)
        Yv, JYv = dy_dx(X)
        g_v, Jg_v = ca.Function("jg", [Y, JYs, w, par], [g, Jg])(Yv, JYv, w, par)
        jac_g = ca.Function(f"rtw{W}_jac_g", [w, par], [g_v, Jg_v], ["x", "p"], ["g", "jac_g_x"])
        opts = {}
        hess = None
        if cfg.hessian == "gauss-newton":
            # H ≈ 2 λ_f J_Rᵀ J_R: first derivatives only (smaller code, faster compile); the
            # constraints' curvature is left out, as in generalised Gauss-Newton SQP
            # (J_R by the same chain rule as the constraint Jacobian)
            JR = ca.mtimes(ca.jacobian(R, Y), BD) + ca.jacobian(R, w)
            lam_f = ca.MX.sym("lam_f")
            lam_g = ca.MX.sym("lam_g", nlp["g"].shape[0])
            H = ca.triu(2 * lam_f * ca.mtimes(JR.T, JR))
            H_v = ca.Function("h", [Y, JYs, w, par, lam_f], [H])(Yv, JYv, w, par, lam_f)
            hess = ca.Function(f"rtw{W}_hess", [w, par, lam_f, lam_g], [H_v],
                               ["x", "p", "lam_f", "lam_g"], ["hess_gamma_x_x"])
        elif cfg.hessian != "exact":
            raise RetargetError(f"offline config: hessian must be 'gauss-newton' or 'exact', got {cfg.hessian!r}")
        opts |= {"ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes", "ipopt.max_iter": cfg.max_iter,
                "ipopt.tol": cfg.tol, "ipopt.constr_viol_tol": 1e-7, "ipopt.acceptable_tol": 1e-3,
                "ipopt.acceptable_iter": 3, "ipopt.acceptable_constr_viol_tol": 1e-6,
                "ipopt.mu_strategy": "adaptive", "ipopt.mu_oracle": "quality-function", "ipopt.bound_relax_factor": 1e-10,
                "ipopt.linear_solver": "mumps",
                # MUMPS's factorisation (with pivoting) solves the KKT system accurately enough: no
                # residual check and no iterative-refinement back-solve per step (same iterates on
                # the CMU pair to 3 digits, ~20 % less time)
                "ipopt.fast_step_computation": "yes", "ipopt.min_refinement_steps": 0,
                # MUMPS's working space: its own estimate + 100 % (IPOPT's default, 1000 %, makes it
                # allocate and touch ~11x the estimate at every factorisation: ~250k page faults
                # per CMU pair, the kernel's clear_page ~11 % of the time). Same iterates; when the
                # estimate is short, IPOPT doubles it and refactorises (0 % never recovers)
                "ipopt.mumps_mem_percent": MUMPS_MEM_PERCENT,
                # constraint multipliers start at 0: no least-squares estimate, which costs a
                # factorisation of its own system (with its own MUMPS analysis) per window, ~10 %
                # of IPOPT's time on the CMU pair, for a start it then threw away (same
                # iterations and solution to 1e-11 with or without it)
                "ipopt.constr_mult_init_max": 0.0}
        opts |= {f"ipopt.{k}": v for k, v in cfg.ipopt_options}
        name = f"rtw{W}"
        ckey = f"{rb.fingerprint()}_{hash_config(replace(cfg, max_iter=0, tol=0, retime=1.0, auto_retime=False, compile=True, ipopt_options=()))}_{int(round(fps * 1000))}"
        solver, info = compiled_nlpsol(name, nlp, opts, ckey, enable=cfg.compile, hess_lag=hess, jac_g=jac_g)
        # the problem and its hand-made derivatives, kept for checks against CasADi's own AD
        self._problems[key] = {"nlp": nlp, "R": R_x, "jac_g": jac_g, "hess": hess}
        entry = (solver, layout, P, balance, feet, info)
        self._solvers[key] = entry
        return entry

    # -- solving ---------------------------------------------------------------------
    def retarget(self, motion: Motion, contacts=None, scaler=None) -> RobotTrajectory:
        """Retarget a clip; raises RetargetError if it is infeasible at its speed (see ``retime``).
        ``contacts`` (T, 4) or (T, 2) bool overrides the motion's; ``scaler`` a KeypointScaler
        (default: fitted on this clip's own bone lengths)."""
        check_motion(motion, min_frames=2)
        cfg = self.config
        factors = [cfg.retime] + ([cfg.retime * f for f in (1.25, 1.5, 2.0)] if cfg.auto_retime else [])
        last = None
        for factor in factors:
            try:
                return self._retarget_at(motion, contacts, factor, scaler)
            except _Infeasible as exc:
                last, last_factor = exc, factor
        speed = "its speed" if factors[-1] == 1.0 else f"{factors[-1]:g}x slower"
        if last.feasible:  # constraints hold, IPOPT did not finish
            msg = (f"{motion.name or 'motion'}: retarget failed (not converged) at {speed}: {last}; give IPOPT more "
                   f"iterations (OfflineConfig.max_iter, now {cfg.max_iter}), or re-time the clip (retime=1.5 plays it "
                   "1.5x slower, CLI --retime 1.5; auto_retime=True, CLI --auto-retime)")
        else:
            msg = (f"{motion.name or 'motion'}: infeasible at {speed}: "
                   f"{last}; re-time the clip (retime=1.5 plays it 1.5x slower, CLI --retime 1.5) or let it try "
                   "(auto_retime=True, CLI --auto-retime)")
        raise RetargetError(msg, time_s=round(last.frame / motion.fps / last_factor, 3))

    def _retarget_at(self, motion: Motion, contacts, factor: float, scaler=None) -> RobotTrajectory:
        fps = motion.fps
        if factor != 1.0:
            if contacts is not None:
                contacts = None  # re-detected on the slowed clip
            slowed = Motion(motion.positions, fps=fps / factor, contacts=motion.contacts, name=motion.name)
            motion = slowed.resample(fps)
        tg = make_targets(self.robot, motion, contacts, scaler)
        t0 = time.perf_counter()
        stream = self._streams.get(fps)
        if stream is None:
            stream = self._streams[fps] = StreamingRetargeter(self.robot, fps, self.streaming_config)
        stream.reset()
        ws = feet_apart(self.robot, tg.keypoints, 0.02) if self.config.self_collision else tg.keypoints
        X0 = np.stack([stream.step(ws[t], tg.contacts[t]) for t in range(motion.n_frames)])
        X, stats = self.solve(tg, X0)
        stats["seconds"] = time.perf_counter() - t0
        stats["retime"] = factor
        return trajectory_from_x(self.robot, X, fps, {"mode": "offline", "source": motion.name, **stats})

    def solve(self, tg: Targets, X0: np.ndarray) -> tuple[np.ndarray, dict]:
        """Solve all windows; X0 (T, nx) is the initial guess. Returns X (T, nx) and solver stats."""
        cfg, rb = self.config, self.robot
        T = tg.keypoints.shape[0]
        # a clip shorter than the window is padded to it (padding is masked out), so one compiled
        # problem per robot serves every clip length; window 0 solves the clip as one problem of T frames
        W = T if cfg.window <= 0 else cfg.window
        if W < 4:
            W = 4
        hop = max(W - cfg.overlap, cfg.n_fix + 1)
        X = X0.copy()
        starts = [0]
        while starts[-1] + W < T:
            starts.append(starts[-1] + hop)
        iters, info, statuses = 0, "", []
        for wi, s in enumerate(starts):
            Xw, it, info, status = self._solve_window(tg, X, s, W, fixed=wi > 0)
            statuses.append(status)
            n_real = min(W, T - s)
            keep_from = 0 if wi == 0 else cfg.n_fix
            X[s + keep_from:s + n_real] = Xw[keep_from:n_real]
            iters += it
        X = np.clip(X, rb.x_lower, rb.x_upper)
        return X, {"windows": len(starts), "window": W, "ipopt_iterations": iters, "ipopt_status": statuses,
                   "collision_model": cfg.collision_model if cfg.self_collision else "off", "compiled": info}

    def _solve_window(self, tg: Targets, X: np.ndarray, s: int, W: int, fixed: bool):
        cfg, rb = self.config, self.robot
        solver, layout, P, balance, feet, info = self._solver(W, tg.fps)
        T, nx = X.shape[0], rb.nx
        idx = np.minimum(np.arange(s, s + W), T - 1)
        real = (np.arange(s, s + W) < T).astype(float)
        tgt = tg.keypoints[idx].reshape(W, -1).T  # (3K, W): column t = (k0x k0y k0z k1x …)
        x0 = X[idx].T
        xf = X[s:s + cfg.n_fix].T if fixed else np.tile(X[s], (cfg.n_fix, 1)).T
        p = np.concatenate([tgt.ravel(order="F"), real, xf.ravel(order="F"), [1.0 if fixed else 0.0]])
        contact = tg.contacts[idx]
        lbg, ubg = [], []
        v = np.concatenate([rb.root_velocity_limits, rb.velocity_limits])[:, None] * cfg.velocity_safety / tg.fps
        lbg.append(np.tile(-v, (1, W - 1)).ravel(order="F"))
        ubg.append(np.tile(v, (1, W - 1)).ravel(order="F"))
        lam0 = np.zeros((0, W))
        if feet:
            cz = np.repeat(contact, 4, axis=1).T  # (8, W)
            free = cz & np.tile([False, False, False, True], 2)[:, None]  # corner 3 of a foot in contact
            lbg.append(np.where(free, -np.inf, 0.0).ravel(order="F"))
            ubg.append(np.where(cz & ~free, 0.0, np.inf).ravel(order="F"))
            both = contact[1:] & contact[:-1]       # (W-1, 2)
            cs = np.repeat(both, 3, axis=1).T        # (6, W-1)
            lbg.append(np.where(cs, 0.0, -np.inf).ravel(order="F"))
            ubg.append(np.where(cs, 0.0, np.inf).ravel(order="F"))
        lbx = np.tile(rb.x_lower[:, None], (1, W))
        ubx = np.tile(rb.x_upper[:, None], (1, W))
        lbl = np.zeros((0, W))
        ubl = np.zeros((0, W))
        if balance:
            active = contact.any(axis=1)
            b = np.where(active, 0.0, np.inf)
            lbg.append(np.stack([-b, -b, -b]).ravel(order="F"))
            ubg.append(np.stack([b, b, b]).ravel(order="F"))
            cl = np.repeat(contact, 4, axis=1).T
            lbl = np.zeros((8, W))
            ubl = np.where(cl, 1.0, 0.0)
            n_on = np.maximum(cl.sum(axis=0, keepdims=True), 1)
            lam0 = cl / n_on
        if P:
            lbg.append(np.zeros(P * W))
            ubg.append(np.full(P * W, np.inf))
        args = dict(x0=np.concatenate([x0.ravel(order="F"), lam0.ravel(order="F")]), p=p,
                    lbx=np.concatenate([lbx.ravel(order="F"), lbl.ravel(order="F")]),
                    ubx=np.concatenate([ubx.ravel(order="F"), ubl.ravel(order="F")]),
                    lbg=np.concatenate(lbg), ubg=np.concatenate(ubg))
        # a warm start must lie inside the box
        args["x0"] = np.clip(args["x0"], args["lbx"], args["ubx"])
        sol = solver(**args)
        single_threaded_linear_algebra()  # MUMPS's BLAS is loaded by the first solve
        st = solver.stats()
        status = str(st.get("return_status", ""))
        xs = np.array(sol["x"]).ravel()
        g = np.array(sol["g"]).ravel()
        if status in _ERRORS or not np.all(np.isfinite(xs)):
            raise RetargetError(
                f"offline retarget: IPOPT failed on frames {s}..{min(s + W, T) - 1} with status {status or 'unknown'} "
                f"(a solver error, not a verdict on the clip); check OfflineConfig.ipopt_options "
                f"{dict(cfg.ipopt_options) or '(none set)'}, e.g. a linear_solver this IPOPT build lacks (mumps is "
                "always there)")
        viol = float(np.max(np.maximum(args["lbg"] - g, 0) + np.maximum(g - args["ubg"], 0))) if g.size else 0.0
        if status not in _OK and viol > 1e-5:
            worst, frame = self._describe_violation(layout, args["lbg"], args["ubg"], g, W, s, T - 1)
            raise _Infeasible(f"frames {s}..{min(s + W, T) - 1}: IPOPT says {status} (constraint violation {viol:.2g}, "
                              f"worst: {worst})", s if frame is None else frame)
        if status not in _OK:
            # feasible but unfinished: never a result (the module docstring); the window is the moment
            raise _Infeasible(f"frames {s}..{min(s + W, T) - 1}: IPOPT says {status or 'unknown status'} after "
                              f"{int(st.get('iter_count', 0))} iterations (the constraints hold, to {viol:.2g}, but "
                              "the optimum was not reached)", s, feasible=True)
        Xw = xs[:nx * W].reshape(W, nx)
        return Xw, int(st.get("iter_count", 0)), info, status


    def _describe_violation(self, layout: dict, lbg: np.ndarray, ubg: np.ndarray, g: np.ndarray, W: int,
                            s: int, last: int) -> tuple[str, int | None]:
        """Name the most violated constraint: its block (velocity, sole_z, slide, balance, collision
        pair) and the clip frame, e.g. ``collision l_sole_in/r_sole_in at frame 12``; and that frame
        (a window padded past the clip's ``last`` frame repeats it: a padding row names ``last``)."""
        v = np.maximum(lbg - g, 0) + np.maximum(g - ubg, 0)
        i = int(np.argmax(v))
        start = 0
        for name, size in layout.items():
            if i < start + size:
                rows = size // (W - 1) if name in ("vel", "slide") else size // W
                j, frame = (i - start) % rows, min(s + (i - start) // rows, last)
                what = name
                if name == "collision" and self.config.collision_model == "sole-plane":
                    what = f"collision {self.robot.offline_collision_labels[j]}"
                elif name == "collision":
                    a, b = self.robot.collision_pairs[j]
                    what = f"collision {a}/{b}"
                elif name == "vel":
                    what = f"velocity of {self._x_name(j)}"
                return f"{what} at frame {frame}", frame
            start += size
        return "unknown", None

    def _x_name(self, i: int) -> str:
        rb = self.robot
        root = ("root x", "root y", "root z", "root yaw", "root pitch", "root roll")
        return root[i] if i < rb.n_root else rb.joint_names[i - rb.n_root]


class _Infeasible(Exception):
    """A window IPOPT did not solve. ``feasible``: its point satisfies the hard
    constraints but IPOPT stopped short of the optimum (e.g. Maximum_Iterations_Exceeded)."""

    def __init__(self, message: str, frame: int, feasible: bool = False):
        super().__init__(message)
        self.frame = frame  #: the clip frame of the worst violation (of the clip as solved, maybe slowed), or the window's first
        self.feasible = feasible


#: keypoints moved with each foot by :func:`feet_apart` (share of the foot's shift)
_FOOT_CHAIN = {"ankle": 1.0, "foot": 1.0, "knee": 0.5}


def feet_apart(robot, keypoints: np.ndarray, extra: float = 0.0) -> np.ndarray:
    """Keypoint targets (T, K, 3) with the feet at least as far apart sideways as the robot's
    standing feet: the warm start for the offline solver, so that it starts with the feet on
    their own sides (a start with the soles crossed can leave IPOPT stuck on the wrong side of
    the foot-foot collision constraint). The streaming solver tracks these targets only
    approximately (planted feet stay where they landed), so this makes overlapping soles in
    the warm start rarer, not impossible; IPOPT's hard constraints do the rest.

    Per frame, with l = the horizontal unit vector from the right to the left hip target,
    s = min over (ankle, toe) of (p_left − p_right)·l and s₀ the same in the robot's stand
    pose plus ``extra`` (m): if s < s₀, the left foot's ankle and toe move by +(s₀ − s)/2 · l, the right's by
    −(s₀ − s)/2 · l, and the knees by half that. Other keypoints are unchanged."""
    names = robot.keypoint_names
    need = [f"{side}_{j}" for side in ("left", "right") for j in ("hip", "ankle", "foot")]
    if not all(n in names for n in need):
        return keypoints
    idx = {n: names.index(n) for n in names}
    stand = robot.evaluate(robot.x_stand[None])["keypoints"][0]

    def sep(kp):  # kp (T, K, 3) -> (T,) and the lateral axis (T, 3)
        across = kp[:, idx["left_hip"]] - kp[:, idx["right_hip"]]
        across[:, 2] = 0.0
        lat = across / np.maximum(np.linalg.norm(across, axis=-1, keepdims=True), 1e-9)
        d = [np.sum((kp[:, idx[f"left_{j}"]] - kp[:, idx[f"right_{j}"]]) * lat, axis=-1) for j in ("ankle", "foot")]
        return np.minimum(*d), lat

    s0 = float(sep(stand[None])[0][0]) + extra
    s, lat = sep(keypoints)
    push = np.maximum(s0 - s, 0.0)[:, None] / 2 * lat  # (T, 3)
    out = np.array(keypoints, dtype=np.float64, copy=True)
    for j, share in _FOOT_CHAIN.items():
        for side, sign in (("left", 1.0), ("right", -1.0)):
            name = f"{side}_{j}"
            if name in idx:
                out[:, idx[name]] += sign * share * push
    return out


def retarget_offline(robot, motion: Motion, config: OfflineConfig = OfflineConfig(), contacts=None,
                     scaler=None) -> RobotTrajectory:
    """One-call convenience: ``OfflineRetargeter(robot, config).retarget(motion)``."""
    return OfflineRetargeter(robot, config).retarget(motion, contacts, scaler)

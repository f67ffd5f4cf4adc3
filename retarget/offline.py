"""Offline retargeting: a whole clip solved as long overlapping windows of one IPOPT problem.

Contract: :meth:`OfflineRetargeter.retarget` takes a :class:`dualflow.motion.Motion` and returns a
:class:`retarget.trajectory.RobotTrajectory` that keeps every joint position and speed limit, the
feet flat and still while the robot's contact schedule holds them down, the capsule pairs apart
and (``balance``) the CoM or multibody ZMP over the support polygon; ``meta`` holds IPOPT's
status per window, the schedule, step counts and what the robot does differently. A clip it
cannot do at its speed raises :class:`retarget.errors.RetargetError` naming the frames and the
fix (``retime``). The formulation, warm start, balance rows and speed work:
docs/retargeting.md (sections 3, 4, 5 and 9).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace

import casadi as ca
import numpy as np

from dualflow.motion import Motion
from retarget.codegen import compiled_nlpsol, single_threaded_linear_algebra
from retarget.errors import RetargetError
from retarget.lead_in import LeadInConfig, lead_in, with_lead_in
from retarget.planned import planned_trajectory
from retarget.schedule import (
    Change,
    StepConfig,
    changes_over,
    count_steps,
    robot_contacts,
    speed_limited,
    standing_soles,
    standing_start,
)
from retarget.shaping import ease_travel
from retarget.streaming import StreamingConfig, StreamingRetargeter, hash_config, trajectory_from_x
from retarget.targets import KeypointScaler, Targets, check_motion, make_targets
from retarget.trajectory import RobotTrajectory

_OK = {"Solve_Succeeded", "Solved_To_Acceptable_Level"}
#: IPOPT outcomes that say the solver (its options, its linear solver, the numbers it was
#: given) failed, not that the clip is infeasible: they always raise, whatever point came back
#: (with an unavailable linear solver IPOPT returns the untouched warm start, which may well
#: satisfy the constraints). Every other outcome outside _OK (Maximum_Iterations_Exceeded,
#: Restoration_Failed, ...) fails the window too: as infeasible when the returned point violates
#: the constraints, as not converged otherwise (both retried by ``auto_retime``).
_ERRORS = {
    "Invalid_Option",
    "Invalid_Problem_Definition",
    "Error_In_Step_Computation",
    "Unrecoverable_Exception",
    "NonIpopt_Exception_Thrown",
    "Insufficient_Memory",
    "Internal_Error",
    "Not_Enough_Degrees_Of_Freedom",
    "Invalid_Number_Detected",
}
GRAVITY = 9.81  # m/s²
ENGINES = ("auto", "planner", "ipopt")
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
    # the ZMP's model: "multibody" (the robot's segments as point masses: their angular momentum
    # counts) or "cart-table" (one point mass at the CoM)
    zmp_model: str = "multibody"
    # with zmp: in single support the CoM too stays over the stance foot (shrunk by balance_margin):
    # the ZMP alone lets the CoM hang outside the foot while it accelerates, which the compliant
    # servos and the 30 fps reference do not reproduce precisely enough (the robot tips over the toe)
    # (off by default: it let cmu19_01 pass but made the synthetic turning leader fall, see the note)
    single_support_com: bool = False
    pre_lift_s: float = 0.0  # ... and already this long (s) before each lift-off, over the foot that stays
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
    # the robot's contact schedule from the person's (retarget.schedule: re-steps for pivots and
    # slides, no flight); None holds the person's contacts as they are
    steps: StepConfig | None = StepConfig()
    # LeadInConfig() (default): a clip whose first frame is not a standing double support at rest
    # is started from the robot's standing stance at rest (retarget.lead_in: stand, step into the
    # first frame's stance, a foot in the air there held on the floor below it, move into the
    # first pose); the trajectory then starts before the clip: meta["t0_s"] is the clip's first
    # frame, meta["lead_in"] what was added. None: the clip as it is, from its first frame. With
    # StepConfig's swing clearance (0.02) the op3 bench (bench/stepping.py --modes
    # offline,offline-no-lead-in --physics) passes 7/9 clips against 6/9 without both, and
    # cmu18_01 passes instead of falling 0.24 s into the clip. Its cost: the lead-in's frames are
    # solved too (3.07 s before each 2.5 s CMU clip: bench/retarget_speed.py's offline frames/s
    # per clip frame 126 -> 43)
    lead_in: LeadInConfig | None = LeadInConfig()
    # which method: "auto" retargets a free-standing robot with feet (with balance and contacts
    # on) by the step planner (retarget.planned: the streaming solver and its balance planner
    # over the whole clip, seeing the person's foot contacts ``lookahead`` s early), any other
    # robot by the window optimisation above; "planner" and "ipopt" choose one. Measured on op3
    # (bench/stepping.py --physics, 9 clips): the planner 9/9 clips without a fall, keypoint error
    # 7.3 % of height, ~2000 frames/s; the window optimisation 7/9, 3.7 %, ~90 frames/s. The
    # planner starts standing by construction (``lead_in`` and ``steps`` are the window
    # optimisation's) and never fails a clip: ``changes`` say where it did something else
    engine: str = "auto"
    lookahead: float = 0.1


@dataclass(frozen=True)
class _WindowSymbols:
    """The symbols of one window's problem: decision variables X (nx, W) and balance weights L
    (8 or 16, W); parameters TGT (3K, W) targets, FW (1, W) 1 for real frames, XF (nx, n_fix)
    frames fixed by the previous window, WF (1) 1 when they are, ANC (8) the feet's first-frame
    placement, REST (1) 1 when the window starts the clip from rest; and which row blocks exist."""

    X: ca.MX
    L: ca.MX
    TGT: ca.MX
    FW: ca.MX
    XF: ca.MX
    WF: ca.MX
    REST: ca.MX
    ANC: ca.MX
    feet: bool
    balance: bool
    static: bool

    @classmethod
    def make(cls, rb, cfg: OfflineConfig, W: int) -> _WindowSymbols:
        feet = bool(rb.has_feet and rb.floating and cfg.contacts)
        balance = feet and cfg.balance
        static = balance and cfg.zmp and cfg.single_support_com
        X = ca.MX.sym("X", rb.nx, W)
        L = ca.MX.sym("L", (16 if static else 8) if balance else 0, W)
        return cls(
            X,
            L,
            ca.MX.sym("TGT", 3 * rb.n_keypoints, W),
            ca.MX.sym("FW", 1, W),
            ca.MX.sym("XF", rb.nx, cfg.n_fix),
            ca.MX.sym("WF", 1, 1),
            ca.MX.sym("REST", 1, 1),
            ca.MX.sym("ANC", 8 if feet else 0, 1),
            feet,
            balance,
            static,
        )

    def decision(self) -> ca.MX:
        return ca.vertcat(ca.vec(self.X), ca.vec(self.L))

    def parameters(self) -> ca.MX:
        return ca.vertcat(ca.vec(self.TGT), ca.vec(self.FW), ca.vec(self.XF), self.WF, self.ANC, self.REST)


@dataclass(frozen=True)
class _Window:
    """One window of a clip of T frames: frames s … s+W−1 (``idx`` (W,) clamped to the clip),
    ``fixed`` (it continues a solved window), the robot's contacts there (W, 2) bool, ``pin``
    (the feet's first-frame placement is held) and ``from_rest`` (it starts the clip from rest)."""

    s: int
    W: int
    T: int
    fixed: bool
    idx: np.ndarray
    contact: np.ndarray
    pin: bool
    from_rest: bool


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
        self._com_height = float(robot.evaluate(robot.x_stand[None])["com"][0, 2]) if robot.n_keypoints else 0.0
        self._height = (
            float(np.ptp(robot.evaluate(robot.x_stand[None])["keypoints"][0][:, 2])) if robot.n_keypoints else 0.0
        )
        if config.engine not in ENGINES:
            raise RetargetError(f"OfflineConfig.engine: {config.engine!r} is not one of {', '.join(ENGINES)}")
        if not (math.isfinite(config.lookahead) and 0 <= config.lookahead <= 1.0):
            raise RetargetError(
                f"OfflineConfig.lookahead: {config.lookahead!r} s; give 0 to 1 s (the planner's view of the "
                "person's contacts ahead; default 0.1)"
            )
        free = robot.floating and robot.has_feet and config.balance and config.contacts
        if config.engine == "planner" and not free:
            raise RetargetError(
                f"OfflineConfig.engine: the planner retargets a free-standing robot with feet, balance and "
                f"contacts on ({robot.name}: floating {robot.floating}, feet {robot.has_feet}, balance "
                f"{config.balance}, contacts {config.contacts}); use engine='ipopt'"
            )
        self._planners: dict[float, StreamingRetargeter] = {}  # by fps, built once
        self.engine = "planner" if config.engine == "planner" or (config.engine == "auto" and free) else "ipopt"

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
            raise RetargetError(
                f"offline config: collision_model must be 'sole-plane' or 'distance', got {cfg.collision_model!r}"
            )
        if not cfg.self_collision:
            coll = ca.SX.zeros(0, 1)
        else:
            coll = rb.offline_collision_expr if cfg.collision_model == "sole-plane" else rb.collision_expr
        com = rb.com_expr
        if cfg.zmp_model not in ("multibody", "cart-table"):
            raise RetargetError(f"offline config: zmp_model must be 'multibody' or 'cart-table', got {cfg.zmp_model!r}")
        self._group_mass = np.array([1.0])
        if cfg.zmp and cfg.zmp_model == "multibody":  # the CoMs of the segments (3, G): the multibody ZMP
            m = rb.kin.model
            groups = mass_groups(m)
            self._group_mass = np.array([sum(float(m.body_mass[b]) for b in g) for g in groups])
            com = ca.horzcat(
                *[
                    sum((float(m.body_mass[b]) * rb.kin.point(b, m.body_ipos[b]) for b in g), ca.SX.zeros(3, 1))
                    / max(mg, 1e-12)
                    for g, mg in zip(groups, self._group_mass)
                ]
            )
        return ca.Function("frame", [x], [rb.keypoints_expr, rb.sole_expr, shr, com, coll])

    def _frame_jacobian(self, W: int) -> ca.Function:
        """X (nx, W) → (Y (ny, W): the frame function's outputs stacked per frame, ∂Y/∂X (ny, nx·W):
        frame t's Jacobian in columns t·nx … t·nx + nx − 1), one SX function mapped over W frames."""
        fr, x = self._frame_fn, self.robot.kin.x_sym
        y = ca.vertcat(*[ca.vec(o) for o in fr(x)])
        return ca.Function("frame_jac", [x], [y, ca.jacobian(y, x)]).map(W, "serial")

    def _solver(self, W: int, fps: float):
        """The IPOPT solver for windows of W frames at ``fps`` (built, compiled and cached once):
        (solver, row layout, collision pairs P, balance, feet, compile info)."""
        key = (W, round(fps, 6))
        if key in self._solvers:
            return self._solvers[key]
        rb, cfg = self.robot, self.config
        sym = _WindowSymbols.make(rb, cfg, W)
        Y, parts = self._output_symbol(W)
        R_x, J_x, g_x, layout, P = self._terms(sym, W, fps, self._frame_fn.map(W, "serial")(sym.X))
        R, _, g, _, _ = self._terms(sym, W, fps, parts)
        w, par = sym.decision(), sym.parameters()
        nlp = {"x": w, "p": par, "f": J_x, "g": g_x}
        jac_g, hess = self._chain_rule_derivatives(sym, W, Y, R, g)
        name = f"rtw{W}"
        key_cfg = replace(
            cfg,
            max_iter=0,
            tol=0,
            retime=1.0,
            auto_retime=False,
            compile=True,
            ipopt_options=(),
            steps=None,
            lead_in=None,
        )
        ckey = f"{rb.fingerprint()}_{hash_config(key_cfg)}_{int(round(fps * 1000))}"
        solver, info = compiled_nlpsol(
            name, nlp, self._ipopt_options(), ckey, enable=cfg.compile, hess_lag=hess, jac_g=jac_g
        )
        # the problem and its hand-made derivatives, kept for checks against CasADi's own AD
        self._problems[key] = {"nlp": nlp, "R": R_x, "jac_g": jac_g, "hess": hess}
        entry = (solver, layout, P, sym.balance, sym.feet, info)
        self._solvers[key] = entry
        return entry

    def _output_symbol(self, W: int) -> tuple:
        """The per-frame outputs as one symbol Y (ny, W) (column t = frame t's outputs stacked)
        and its parts in the layout ``Function.map`` gives ((r, c·W) each): R and g are written
        once in the mapped outputs (f, g and the gradient) and once in Y (their Jacobians by the
        chain rule, :meth:`_chain_rule_derivatives`)."""
        fr = self._frame_fn
        shapes = [fr.sparsity_out(i).shape for i in range(fr.n_out())]
        ny = sum(r * c for r, c in shapes)
        Y = ca.MX.sym("Y", ny, W)
        parts, i0 = [], 0
        for r, c in shapes:  # (r*c, W) rows → (r, c*W), the layout Function.map gives
            parts.append(ca.reshape(Y[i0 : i0 + r * c, :], r, c * W))
            i0 += r * c
        return Y, parts

    def _terms(self, sym: _WindowSymbols, W: int, fps: float, outs) -> tuple:
        """R (residuals), J = ‖R‖², g and its row layout, P, from the per-frame outputs ``outs``
        (keypoints, sole, shrunk sole, com, collision, as Function.map lays them out)."""
        kp, sole, shr, com, coll = outs
        R = self._residuals(sym, W, fps, kp)
        J = ca.sumsqr(R)
        X = sym.X
        g = [ca.vec(X[:, 1:] - X[:, :-1])]
        layout = {"vel": self.robot.nx * (W - 1)}
        if sym.feet:
            self._contact_rows(sym, W, sole, g, layout)
        if sym.balance:
            self._balance_rows(sym, W, fps, shr, com, g, layout)
        P = coll.shape[0]
        if P:
            g.append(ca.vec(coll))
            layout["collision"] = P * W
        return R, J, ca.vertcat(*g), layout, P

    def _residuals(self, sym: _WindowSymbols, W: int, fps: float, kp):
        """The stacked weighted residuals R of the objective J = ‖R‖² (module docstring)."""
        rb, cfg, X = self.robot, self.config, sym.X
        nx, nr, K = rb.nx, rb.n_root, rb.n_keypoints
        wk = np.sqrt(np.repeat(rb.keypoint_weights, 3))[:, None]
        wp = rb.profile.posture_weight if cfg.posture_weight is None else cfg.posture_weight
        acc = (X[:, 2:] - 2 * X[:, 1:-1] + X[:, :-2]) * fps**2
        jerk = (X[:, 3:] - 3 * X[:, 2:-1] + 3 * X[:, 1:-2] - X[:, :-3]) * fps**3
        return ca.vertcat(
            ca.vec((ca.reshape(kp, 3 * K, W) - sym.TGT) * ca.repmat(ca.DM(wk), 1, W) * ca.repmat(sym.FW, 3 * K, 1)),
            np.sqrt(wp) * ca.vec(X[nr:, :] - ca.repmat(ca.DM(rb.x_stand[nr:]), 1, W)),
            np.sqrt(cfg.accel_weight) * ca.vec(acc * ca.repmat(sym.FW[:, 2:], nx, 1)),
            np.sqrt(cfg.jerk_weight) * ca.vec(jerk * ca.repmat(sym.FW[:, 3:], nx, 1)),
            sym.WF * np.sqrt(cfg.fix_weight) * ca.vec(X[:, : cfg.n_fix] - sym.XF),
        )

    def _contact_rows(self, sym: _WindowSymbols, W: int, sole, g: list, layout: dict) -> None:
        """Append the feet's rows to g: sole corner heights (8 per frame), no slide or turn between
        frames (6 per frame pair) and the first frame's placement (6; bounds switch them on)."""
        g.append(ca.vec(ca.reshape(sole[2, :], 8, W)))
        layout["sole_z"] = 8 * W
        xy = ca.reshape(sole[0:2, :], 16, W)  # per frame: x0 y0 x1 y1 ... of the 8 corners
        slide = []
        for f, foot in enumerate(self.robot.feet):
            c0, c2 = 8 * f, 8 * f + 4  # rows of corner 0 and corner 2 of this foot
            d = xy[c2 : c2 + 2, :] - xy[c0 : c0 + 2, :]
            diag2 = float(np.sum((foot.corners[2] - foot.corners[0]) ** 2))
            slide += [xy[c0 : c0 + 2, 1:] - xy[c0 : c0 + 2, :-1], (d[0, :-1] * d[1, 1:] - d[1, :-1] * d[0, 1:]) / diag2]
        g.append(ca.vec(ca.vertcat(*slide)))
        layout["slide"] = 6 * (W - 1)
        # the feet's placement in the window's first frame (the standing start): corner 0
        # at ANC's point, the sole diagonal along ANC's direction (bounds switch it on)
        anchor = []
        for f, foot in enumerate(self.robot.feet):
            c0, c2 = 8 * f, 8 * f + 4
            d = xy[c2 : c2 + 2, 0] - xy[c0 : c0 + 2, 0]
            a = sym.ANC[4 * f + 2 : 4 * f + 4]
            diag2 = float(np.sum((foot.corners[2] - foot.corners[0]) ** 2))
            anchor += [xy[c0 : c0 + 2, 0] - sym.ANC[4 * f : 4 * f + 2], (d[0] * a[1] - d[1] * a[0]) / diag2]
        g.append(ca.vertcat(*anchor))
        layout["anchor"] = 6

    def _zmp_terms(self, sym: _WindowSymbols, W: int, fps: float, com) -> tuple:
        """(num (2, W), den (1, W) or None, scale): the balance point num / den, the multibody ZMP of
        the segments as point masses m_k at c_k, p = Σ_k m_k (c_k,xy (c̈_k,z + g) − c_k,z c̈_k,xy) /
        Σ_k m_k (c̈_k,z + g), c̈ the central second difference (one-sided at the window's ends);
        without ``zmp`` the static CoM (den None)."""
        if not (self.config.zmp and W >= 3):
            return ca.reshape(com, 3, W)[0:2, :], None, 1.0
        G = len(self._group_mass)
        cg = ca.reshape(com, 3 * G, W)  # rows 3k..3k+2: segment k's CoM
        acc = (cg[:, 2:] - 2 * cg[:, 1:-1] + cg[:, :-2]) * fps**2
        # frame 0: from rest (c_−1 = c_0) when REST, else one-sided
        acc0 = sym.REST * (cg[:, 1] - cg[:, 0]) * fps**2 + (1 - sym.REST) * acc[:, 0]
        acc = ca.horzcat(acc0, acc, acc[:, -1])
        num, den = 0, 0
        for k, mk in enumerate(self._group_mass):
            c, a = cg[3 * k : 3 * k + 3, :], acc[3 * k : 3 * k + 3, :]
            lift = mk * (a[2, :] + GRAVITY)
            num = num + ca.repmat(lift, 2, 1) * c[0:2, :] - mk * ca.repmat(c[2, :], 2, 1) * a[0:2, :]
            den = den + lift
        return num, den, 1.0 / (float(np.sum(self._group_mass)) * GRAVITY)

    def _balance_rows(self, sym: _WindowSymbols, W: int, fps: float, shr, com, g: list, layout: dict) -> None:
        """Append the balance rows to g: the balance point b = Σ_i λ_i s̃_i over the shrunk sole
        corners s̃ (3 per frame), and with ``single_support_com`` the CoM over the stance foot."""
        s = ca.reshape(shr, 16, W)
        sx, sy = s[0::2, :], s[1::2, :]
        num, den, scale = self._zmp_terms(sym, W, fps, com)
        L1 = sym.L[0:8, :]
        # zmp = num / den = b (b = Σ_i λ_i s̃_i) as num − b·den = 0, scaled by 1 / (M g) to stay
        # in metres: the same zeros while den = Σ_k m_k (c̈_k,z + g) > 0 (no free fall), but
        # polynomial, not rational: a walk off from frame 0 took IPOPT 89 iterations in the
        # first window with num / den − b, 15 with this (the solution within 3e-6 rad)
        b = ca.vertcat(ca.sum1(L1 * sx), ca.sum1(L1 * sy))
        zrow = num - b if den is None else (num - b * ca.repmat(den, 2, 1)) * scale
        g.append(ca.vec(ca.vertcat(zrow, ca.sum1(L1) - 1)))
        layout["balance"] = 3 * W
        if sym.static:  # the CoM over the stance foot in single support (bounds switch it on)
            G = len(self._group_mass)
            cg = ca.reshape(com, 3 * G, W)
            ctot = sum(float(mk) * cg[3 * k : 3 * k + 2, :] for k, mk in enumerate(self._group_mass)) / float(
                np.sum(self._group_mass)
            )
            L2 = sym.L[8:16, :]
            g.append(ca.vec(ca.vertcat(ctot[0, :] - ca.sum1(L2 * sx), ctot[1, :] - ca.sum1(L2 * sy), ca.sum1(L2) - 1)))
            layout["static"] = 3 * W

    def _chain_rule_derivatives(self, sym: _WindowSymbols, W: int, Y, R, g) -> tuple:
        """(jac_g, hess): the constraint Jacobian and the Gauss-Newton Hessian (None with
        ``hessian="exact"``) as functions of (w, p), from R and g written in Y (:meth:`_output_symbol`)."""
        nx, cfg = self.robot.nx, self.config
        w, par, X = sym.decision(), sym.parameters(), sym.X
        dy_dx = self._frame_jacobian(W)
        # constraint Jacobian by the chain rule: dg/dw = ∂g/∂Y · blockdiag_t(∂y_t/∂x_t) + ∂g/∂w, with
        # each frame's Jacobian from one SX function mapped over the W frames. CasADi's own AD
        # of the mapped graph needs ~100 directional sweeps over all frames (~4-7 ms per call
        # against ~1 ms for the W frame Jacobians); the values are the same
        JYs = ca.MX.sym("JY", dy_dx.sparsity_out(1))
        BD = ca.horzcat(ca.diagcat(*ca.horzsplit(JYs, nx)), ca.MX(Y.shape[0] * W, w.shape[0] - nx * W))
        Jg = ca.mtimes(ca.jacobian(g, Y), BD) + ca.jacobian(g, w)
        Yv, JYv = dy_dx(X)
        g_v, Jg_v = ca.Function("jg", [Y, JYs, w, par], [g, Jg])(Yv, JYv, w, par)
        jac_g = ca.Function(f"rtw{W}_jac_g", [w, par], [g_v, Jg_v], ["x", "p"], ["g", "jac_g_x"])
        if cfg.hessian == "exact":
            return jac_g, None
        if cfg.hessian != "gauss-newton":
            raise RetargetError(f"offline config: hessian must be 'gauss-newton' or 'exact', got {cfg.hessian!r}")
        # H ≈ 2 λ_f J_Rᵀ J_R: first derivatives only (smaller code, faster compile); the
        # constraints' curvature is left out, as in generalised Gauss-Newton SQP
        # (J_R by the same chain rule as the constraint Jacobian)
        JR = ca.mtimes(ca.jacobian(R, Y), BD) + ca.jacobian(R, w)
        lam_f = ca.MX.sym("lam_f")
        lam_g = ca.MX.sym("lam_g", g.shape[0])
        H = ca.triu(2 * lam_f * ca.mtimes(JR.T, JR))
        H_v = ca.Function("h", [Y, JYs, w, par, lam_f], [H])(Yv, JYv, w, par, lam_f)
        hess = ca.Function(
            f"rtw{W}_hess", [w, par, lam_f, lam_g], [H_v], ["x", "p", "lam_f", "lam_g"], ["hess_gamma_x_x"]
        )
        return jac_g, hess

    def _ipopt_options(self) -> dict:
        """IPOPT's options: the tuned defaults (reasons inline, figures in docs/retargeting.md) and
        ``OfflineConfig.ipopt_options`` on top."""
        cfg = self.config
        opts = {
            "ipopt.print_level": 0,
            "print_time": False,
            "ipopt.sb": "yes",
            "ipopt.max_iter": cfg.max_iter,
            "ipopt.tol": cfg.tol,
            "ipopt.constr_viol_tol": 1e-7,
            "ipopt.acceptable_tol": 1e-3,
            "ipopt.acceptable_iter": 3,
            "ipopt.acceptable_constr_viol_tol": 1e-6,
            "ipopt.mu_strategy": "adaptive",
            "ipopt.mu_oracle": "quality-function",
            "ipopt.bound_relax_factor": 1e-10,
            "ipopt.linear_solver": "mumps",
            # MUMPS's factorisation (with pivoting) solves the KKT system accurately enough: no
            # residual check and no iterative-refinement back-solve per step (same iterates on
            # the CMU pair to 3 digits, ~20 % less time)
            "ipopt.fast_step_computation": "yes",
            "ipopt.min_refinement_steps": 0,
            # MUMPS's working space: its own estimate + 100 % (IPOPT's default, 1000 %, makes it
            # allocate and touch ~11x the estimate at every factorisation: ~250k page faults
            # per CMU pair, the kernel's clear_page ~11 % of the time). Same iterates; when the
            # estimate is short, IPOPT doubles it and refactorises (0 % never recovers)
            "ipopt.mumps_mem_percent": MUMPS_MEM_PERCENT,
            # constraint multipliers start at 0: no least-squares estimate, which costs a
            # factorisation of its own system (with its own MUMPS analysis) per window, ~10 %
            # of IPOPT's time on the CMU pair, for a start it then threw away (same
            # iterations and solution to 1e-11 with or without it)
            "ipopt.constr_mult_init_max": 0.0,
        }
        return opts | {f"ipopt.{k}": v for k, v in cfg.ipopt_options}

    # -- solving ---------------------------------------------------------------------
    def retarget(self, motion: Motion, contacts=None, scaler=None) -> RobotTrajectory:
        """Retarget a clip; raises RetargetError if it is infeasible at its speed (see ``retime``).
        ``contacts`` (T, 4) or (T, 2) bool overrides the motion's; ``scaler`` a KeypointScaler
        (default: fitted on this clip's own bone lengths). With ``OfflineConfig.lead_in`` set, a clip
        that starts mid-motion gets a lead-in from standing at rest (:mod:`retarget.lead_in`); a
        lead-in that cannot be solved is dropped (the clip is retargeted as it is, and a
        "lead-in dropped" change says why)."""
        check_motion(motion, min_frames=2)
        cfg = self.config
        if self.engine == "planner":
            return self._retarget_planned(motion, contacts, scaler)
        if cfg.lead_in is not None and self.robot.floating and self.robot.has_feet:
            led, lead = lead_in(motion, cfg.lead_in, contacts)
            if lead is not None:  # the lead-in's motion carries its contacts; bones scaled as the clip's
                try:
                    traj = self._retarget_retimed(led, None, scaler or KeypointScaler(self.robot, motion.positions))
                    return with_lead_in(traj, lead, led.contacts)
                except RetargetError as exc:
                    dropped = exc
                traj = self._retarget_retimed(motion, contacts, scaler)
                why = f"the clip led in from standing could not be retargeted ({str(dropped)[:300]})"
                traj.meta["changes"] = [Change(0.0, 0.0, "lead-in dropped", why).to_dict(), *traj.meta["changes"]]
                return traj
        return self._retarget_retimed(motion, contacts, scaler)

    def _retarget_planned(self, motion: Motion, contacts, scaler) -> RobotTrajectory:
        """The step planner's trajectory (:mod:`retarget.planned`), at ``retime``."""
        cfg = self.config
        if cfg.retime != 1.0:
            motion, contacts = slowed(motion, cfg.retime), None  # contacts re-detected on the slowed clip
        stream = self._planners.get(motion.fps)
        if stream is None:
            planner = StreamingConfig(balance=True, compile=cfg.compile)
            stream = self._planners[motion.fps] = StreamingRetargeter(self.robot, motion.fps, planner)
        traj = planned_trajectory(stream, motion, contacts, scaler, cfg.lookahead, cfg.velocity_safety)
        traj.meta["retime"] = cfg.retime
        return traj

    def _retarget_retimed(self, motion: Motion, contacts, scaler) -> RobotTrajectory:
        """``_retarget_at`` at ``retime`` (and the slower factors with ``auto_retime``); RetargetError
        naming the first infeasible window of the last factor tried."""
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
            msg = (
                f"{motion.name or 'motion'}: retarget failed (not converged) at {speed}: {last}; give IPOPT more "
                f"iterations (OfflineConfig.max_iter, now {cfg.max_iter}), or re-time the clip (retime=1.5 plays it "
                "1.5x slower, CLI --retime 1.5; auto_retime=True, CLI --auto-retime)"
            )
        else:
            msg = (
                f"{motion.name or 'motion'}: infeasible at {speed}: "
                f"{last}; re-time the clip (retime=1.5 plays it 1.5x slower, CLI --retime 1.5) or let it try "
                "(auto_retime=True, CLI --auto-retime)"
            )
        raise RetargetError(msg, time_s=round(last.frame / motion.fps / last_factor, 3))

    def _retarget_at(self, motion: Motion, contacts, factor: float, scaler=None) -> RobotTrajectory:
        fps = motion.fps
        if factor != 1.0:
            motion, contacts = slowed(motion, factor), None  # contacts re-detected on the slowed clip
        tg = make_targets(self.robot, motion, contacts, scaler)
        t0 = time.perf_counter()
        person_steps = count_steps(tg.contacts)
        changes, anchor = [], None
        if self.config.steps is not None and self.config.contacts and self.robot.has_feet and self.robot.floating:
            planned, changes = robot_contacts(self.robot, tg.keypoints, tg.contacts, fps, self.config.steps)
            kp = tg.keypoints
            if self.config.steps.standing_start:
                anchor = standing_soles(self.robot, kp)
                kp, n, moved, turned = standing_start(self.robot, kp, planned)
                if n and (moved > self.config.steps.step_distance or turned > self.config.steps.step_turn):
                    changes.insert(
                        0,
                        Change(
                            0.0,
                            round(n / fps, 3),
                            "standing start",
                            "the robot starts in its standing stance (it is brought to the first "
                            f"frame from standing; the person's feet stood up to {1000 * moved:.0f} mm and "
                            f"{math.degrees(turned):.0f} deg away from that) and steps into the person's",
                        ),
                    )
            if self.config.steps.travel_zmp_shift > 0:
                a_max = GRAVITY * self.config.steps.travel_zmp_shift / max(self._com_height, 1e-3)
                kp, shift = ease_travel(kp, self.robot.root_keypoint, fps, a_max)
                changes += changes_over(
                    np.linalg.norm(shift, axis=1),
                    0.02,
                    fps,
                    "slower travel",
                    f"the person's travel accelerated faster than the robot's feet balance "
                    f"({a_max:.1f} m/s²; e.g. walking off from the first frame): the robot followed "
                    "more slowly, more than 2 cm behind",
                )
            tg = Targets(kp, planned, tg.fps)
        stream = self._streams.get(fps)
        if stream is None:
            stream = self._streams[fps] = StreamingRetargeter(self.robot, fps, self.streaming_config)
        stream.reset()
        ws = feet_apart(self.robot, tg.keypoints, 0.02) if self.config.self_collision else tg.keypoints

        def warm(X: np.ndarray, start: int, stop: int) -> None:
            """Frames start..stop−1 of X streamed on from the two solved frames before them."""
            if start == 0:
                stream.reset()
            else:
                stream.resume(X[start - 1], X[start - 2] if start >= 2 else X[start - 1])
            for t in range(start, stop):
                X[t] = stream.step(ws[t], tg.contacts[t])

        X0 = np.zeros((motion.n_frames, self.robot.nx))
        swing = None
        if (
            self.config.steps is not None
            and self.config.steps.swing_clearance > 0
            and self.config.contacts
            and self.robot.has_feet
            and self.robot.floating
        ):
            swing = swing_floor(tg.contacts, self.config.steps.swing_clearance * self._height)
        ramp = None
        if self.config.steps is not None and self.config.steps.start_ramp > 0:
            ramp = int(round(self.config.steps.start_ramp * fps))
        X, stats = self.solve(tg, X0, warm, swing, anchor, ramp)
        changes += _no_clearance_changes(stats.pop("no_clearance_frames"), fps, self.config.steps)
        stats["seconds"] = time.perf_counter() - t0
        stats["retime"] = factor
        stats["contacts"] = tg.contacts.astype(int).tolist()  # the robot's schedule, (T, 2) 0/1
        stats["steps"] = {"person": person_steps, "robot": count_steps(tg.contacts)}
        changes += speed_limited(self.robot, X, fps, self.config.velocity_safety)
        changes.sort(key=lambda c: c.start_s)
        stats["changes"] = [c.to_dict() for c in changes]
        return trajectory_from_x(self.robot, X, fps, {"mode": "offline", "source": motion.name, **stats})

    def solve(
        self, tg: Targets, X0: np.ndarray, warm=None, swing=None, anchor=None, ramp=None
    ) -> tuple[np.ndarray, dict]:
        """Solve all windows; X0 (T, nx) is the initial guess. Returns X (T, nx) and solver stats.

        ``warm(X, start, stop)``, if given, fills X[start:stop] (in place) with the warm start of
        the frames a window solves for the first time, continuing from the solved frames before
        ``start``. A warm start made once for the whole clip (X0 alone) drifts away from what the
        earlier windows solved: a streamed start turns and slides its contact feet with the
        person, the solved robot keeps them planted, so at the next window's first unsolved frame
        the start jumps by all the turn (or travel) the planted robot did not follow; IPOPT then
        has to close a root-yaw jump of that size inside one frame's velocity limit and stops
        infeasible ("velocity of root yaw", whatever the clip's speed).

        ``swing`` (T, 2) m, if given: the lowest a foot's sole corners may be in each frame it is
        off the ground (:func:`swing_floor`), and each lift-off and touch-down is vertical (the
        foot's position and heading in the first and last frame in the air are those of the frame
        on the ground next to it). ``anchor`` (2, 4), if given: each foot's sole corner 0 xy and
        sole-diagonal direction xy (corner 2 − corner 0) in the first frame (the standing start).
        ``ramp`` (frames), if given: the clip starts from rest, as the robot does after the move
        from standing: every DOF's speed limit opens linearly over the first ``ramp`` frames and
        the ZMP of frame 0 counts the acceleration from rest."""
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
        iters, info, statuses, unclear = 0, "", [], []
        done = 0  # frames 0..done−1 are solved
        for wi, s in enumerate(starts):
            if warm is not None:
                warm(X, done, min(s + W, T))
            n_real = min(W, T - s)
            try:
                Xw, it, info, status = self._solve_window(
                    tg, X, s, W, fixed=wi > 0, swing=swing, anchor=anchor, ramp=ramp
                )
            except _Infeasible:
                if swing is None:
                    raise
                # the floor clearance is a wish, not a limit: a window whose swings cannot clear
                # it (a big robot's short swings, a foot that has to travel far) keeps its feet
                # above the floor only, and says so (OfflineRetargeter._retarget_at's change)
                Xw, it, info, status = self._solve_window(tg, X, s, W, fixed=wi > 0, anchor=anchor, ramp=ramp)
                unclear.append((s, s + n_real))
            statuses.append(status)
            keep_from = 0 if wi == 0 else cfg.n_fix
            X[s + keep_from : s + n_real] = Xw[keep_from:n_real]
            done = s + n_real
            iters += it
        X = np.clip(X, rb.x_lower, rb.x_upper)
        return X, {
            "windows": len(starts),
            "window": W,
            "ipopt_iterations": iters,
            "ipopt_status": statuses,
            "collision_model": cfg.collision_model if cfg.self_collision else "off",
            "compiled": info,
            "no_clearance_frames": unclear,
        }

    def _solve_window(
        self, tg: Targets, X: np.ndarray, s: int, W: int, fixed: bool, swing=None, anchor=None, ramp=None
    ):
        """Solve frames s … s+W−1 (padded past the clip's end) from X's values there; returns
        (X_w (W, nx), IPOPT iterations, compile info, status). Raises _Infeasible or RetargetError."""
        cfg, rb = self.config, self.robot
        solver, layout, P, balance, feet, info = self._solver(W, tg.fps)
        T = X.shape[0]
        idx = np.minimum(np.arange(s, s + W), T - 1)
        win = _Window(
            s,
            W,
            T,
            fixed,
            idx,
            tg.contacts[idx],
            pin=anchor is not None and not fixed and feet,
            from_rest=ramp is not None and not fixed,
        )
        real = (np.arange(s, s + W) < T).astype(float)
        tgt = tg.keypoints[idx].reshape(W, -1).T  # (3K, W): column t = (k0x k0y k0z k1x …)
        xf = X[s : s + cfg.n_fix].T if fixed else np.tile(X[s], (cfg.n_fix, 1)).T
        anc = np.asarray(anchor, dtype=np.float64).ravel() if win.pin else np.zeros(8 if feet else 0)
        p = np.concatenate(
            [
                tgt.ravel(order="F"),
                real,
                xf.ravel(order="F"),
                [1.0 if fixed else 0.0],
                anc,
                [1.0 if win.from_rest else 0.0],
            ]
        )
        lbg, ubg = self._velocity_bounds(tg.fps, win, ramp)
        if feet:
            self._contact_bounds(win, swing, lbg, ubg)
        lam = (np.zeros((0, W)),) * 3  # balance weights: lower, upper bound, start
        if balance:
            lam = self._balance_bounds(tg, win, layout, lbg, ubg)
        if P:
            lbg.append(np.zeros(P * W))
            ubg.append(np.full(P * W, np.inf))
        lbx, ubx = np.tile(rb.x_lower[:, None], (1, W)), np.tile(rb.x_upper[:, None], (1, W))
        args = dict(
            x0=np.concatenate([X[idx].T.ravel(order="F"), lam[2].ravel(order="F")]),
            p=p,
            lbx=np.concatenate([lbx.ravel(order="F"), lam[0].ravel(order="F")]),
            ubx=np.concatenate([ubx.ravel(order="F"), lam[1].ravel(order="F")]),
            lbg=np.concatenate(lbg),
            ubg=np.concatenate(ubg),
        )
        # a warm start must lie inside the box
        args["x0"] = np.clip(args["x0"], args["lbx"], args["ubx"])
        sol = solver(**args)
        single_threaded_linear_algebra()  # MUMPS's BLAS is loaded by the first solve
        xs, iters, status = self._outcome(solver, sol, args, layout, win)
        return xs[: rb.nx * W].reshape(W, rb.nx), iters, info, status

    def _velocity_bounds(self, fps: float, win: _Window, ramp) -> tuple[list, list]:
        """Bounds of the velocity rows |x_{t+1} − x_t| ≤ v_max / fps, opening linearly over ``ramp``
        frames in a window that starts the clip from rest: ([lower], [upper])."""
        rb, cfg = self.robot, self.config
        v = np.concatenate([rb.root_velocity_limits, rb.velocity_limits])[:, None] * cfg.velocity_safety / fps
        vb = np.tile(v, (1, win.W - 1))
        if win.from_rest:  # from rest: the speed limits open over ``ramp`` frames
            vb = vb * np.minimum(1.0, (np.arange(win.W - 1) + 1) / max(ramp, 1))[None, :]
        return [(-vb).ravel(order="F")], [vb.ravel(order="F")]

    @staticmethod
    def _contact_bounds(win: _Window, swing, lbg: list, ubg: list) -> None:
        """Append the bounds of the feet's rows (sole heights, slide, first-frame placement)."""
        W, contact = win.W, win.contact
        cz = np.repeat(contact, 4, axis=1).T  # (8, W)
        free = cz & np.tile([False, False, False, True], 2)[:, None]  # corner 3 of a foot in contact
        low = np.zeros((8, W)) if swing is None else np.repeat(swing[win.idx], 4, axis=1).T
        lbg.append(np.where(free, -np.inf, np.where(cz, 0.0, low)).ravel(order="F"))
        ubg.append(np.where(cz & ~free, 0.0, np.inf).ravel(order="F"))
        # a foot in contact in both frames does not slide or turn; with ``swing`` also between
        # a contact frame and the air frame next to it (a vertical lift-off and touch-down)
        both = contact[1:] & contact[:-1] if swing is None else contact[1:] | contact[:-1]  # (W-1, 2)
        cs = np.repeat(both, 3, axis=1).T  # (6, W-1)
        lbg.append(np.where(cs, 0.0, -np.inf).ravel(order="F"))
        ubg.append(np.where(cs, 0.0, np.inf).ravel(order="F"))
        lbg.append(np.zeros(6) if win.pin else np.full(6, -np.inf))
        ubg.append(np.zeros(6) if win.pin else np.full(6, np.inf))

    def _balance_bounds(self, tg: Targets, win: _Window, layout: dict, lbg: list, ubg: list) -> tuple:
        """Append the balance rows' bounds (on while a foot is down); return the balance weights'
        (lower, upper, start) (8 or 16, W): weight only on corners of feet in contact, shared evenly."""
        W, contact = win.W, win.contact
        b = np.where(contact.any(axis=1), 0.0, np.inf)
        lbg.append(np.stack([-b, -b, -b]).ravel(order="F"))
        ubg.append(np.stack([b, b, b]).ravel(order="F"))
        cl = np.repeat(contact, 4, axis=1).T
        lbl, ubl = np.zeros((8, W)), np.where(cl, 1.0, 0.0)
        lam0 = cl / np.maximum(cl.sum(axis=0, keepdims=True), 1)
        if layout.get("static"):
            stance = _static_stance(tg.contacts, int(round(self.config.pre_lift_s * tg.fps)))[win.idx]  # (W, 2)
            on = stance.any(axis=1)
            b2 = np.where(on, 0.0, np.inf)
            lbg.append(np.stack([-b2, -b2, -b2]).ravel(order="F"))
            ubg.append(np.stack([b2, b2, b2]).ravel(order="F"))
            cl2 = np.repeat(np.where(on[:, None], stance, contact), 4, axis=1).T
            lbl, ubl = np.vstack([lbl, np.zeros((8, W))]), np.vstack([ubl, np.where(cl2, 1.0, 0.0)])
            lam0 = np.vstack([lam0, cl2 / np.maximum(cl2.sum(axis=0, keepdims=True), 1)])
        return lbl, ubl, lam0

    def _outcome(self, solver, sol, args: dict, layout: dict, win: _Window) -> tuple:
        """(x, iterations, status) of a converged window; a solver error raises RetargetError, an
        unconverged window _Infeasible (module docstring)."""
        s, W, T = win.s, win.W, win.T
        st = solver.stats()
        status = str(st.get("return_status", ""))
        xs = np.array(sol["x"]).ravel()
        g = np.array(sol["g"]).ravel()
        if status in _ERRORS or not np.all(np.isfinite(xs)):
            raise RetargetError(
                f"offline retarget: IPOPT failed on frames {s}..{min(s + W, T) - 1} with status {status or 'unknown'} "
                f"(a solver error, not a verdict on the clip); check OfflineConfig.ipopt_options "
                f"{dict(self.config.ipopt_options) or '(none set)'}, e.g. a linear_solver this IPOPT build lacks "
                "(mumps is always there)"
            )
        viol = float(np.max(np.maximum(args["lbg"] - g, 0) + np.maximum(g - args["ubg"], 0))) if g.size else 0.0
        if status not in _OK and viol > 1e-5:
            worst, frame = self._describe_violation(layout, args["lbg"], args["ubg"], g, W, s, T - 1)
            raise _Infeasible(
                f"frames {s}..{min(s + W, T) - 1}: IPOPT says {status} (constraint violation {viol:.2g}, "
                f"worst: {worst})",
                s if frame is None else frame,
            )
        if status not in _OK:
            # feasible but unfinished: never a result (the module docstring); the window is the moment
            raise _Infeasible(
                f"frames {s}..{min(s + W, T) - 1}: IPOPT says {status or 'unknown status'} after "
                f"{int(st.get('iter_count', 0))} iterations (the constraints hold, to {viol:.2g}, but "
                "the optimum was not reached)",
                s,
                feasible=True,
            )
        return xs, int(st.get("iter_count", 0)), status

    def _describe_violation(
        self, layout: dict, lbg: np.ndarray, ubg: np.ndarray, g: np.ndarray, W: int, s: int, last: int
    ) -> tuple[str, int | None]:
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


def _no_clearance_changes(spans, fps: float, steps) -> list[Change]:
    """One "no floor clearance" change per window (start, stop) frames solved without the swing
    clearance (OfflineRetargeter.solve)."""
    if not spans:
        return []
    why = (
        f"this window's swings could not clear the floor by the swing clearance ({steps.swing_clearance:g} x "
        "height) and converge; its feet only stay above the floor"
    )
    return [Change(round(a / fps, 3), round(b / fps, 3), "no floor clearance", why) for a, b in spans]


class _Infeasible(Exception):
    """A window IPOPT did not solve. ``feasible``: its point satisfies the hard
    constraints but IPOPT stopped short of the optimum (e.g. Maximum_Iterations_Exceeded)."""

    def __init__(self, message: str, frame: int, feasible: bool = False):
        super().__init__(message)
        self.frame = (
            frame  #: the clip frame of the worst violation (of the clip as solved, maybe slowed), or the window's first
        )
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


def _static_stance(contacts: np.ndarray, pre: int) -> np.ndarray:
    """(T, 2) bool: the foot the CoM must stand over in each frame (none: all False): the
    stance foot in single support, and the foot that stays in the ``pre`` frames of double
    support before the other lifts. contacts (T, 2) bool."""
    c = np.asarray(contacts, dtype=bool)
    out = c & ~c[:, ::-1]  # single support: the foot down
    for s in range(2):
        lifts = np.flatnonzero(c[:-1, s] & ~c[1:, s]) + 1  # first frame in the air
        for t in lifts:
            a = max(0, t - pre)
            both = c[a:t].all(axis=1)
            out[a:t, 1 - s] |= both
            out[a:t, s] &= ~both
    return out


def slowed(motion: Motion, factor: float) -> Motion:
    """``motion`` played ``factor`` times slower, at its own frame rate."""
    return Motion(motion.positions, fps=motion.fps / factor, contacts=motion.contacts, name=motion.name).resample(
        motion.fps
    )


def mass_groups(model, share: float = 0.35) -> list[list[int]]:
    """The robot's segments for the multibody ZMP: body ids (with mass) per segment. Each child
    subtree of the root body is a segment (a leg, an arm, the head), except that a subtree with
    more than ``share`` of the robot's mass (a torso carrying the arms) is split the same way,
    its top body joining the trunk; the trunk (the root body and those top bodies) is one."""
    parent = model.body_parentid
    children = {b: [c for c in range(1, model.nbody) if parent[c] == b and c != b] for b in range(model.nbody)}
    root = next(b for b in range(1, model.nbody) if parent[b] == 0)

    def subtree(b):
        out = [b]
        for c in children[b]:
            out += subtree(c)
        return out

    total = float(sum(model.body_mass[1:]))
    trunk, groups, todo = [root], [], list(children[root])
    while todo:
        b = todo.pop(0)
        sub = subtree(b)
        if sum(float(model.body_mass[i]) for i in sub) > share * total and children[b]:
            trunk.append(b)
            todo += children[b]
        else:
            groups.append(sub)
    groups = [trunk] + groups
    groups = [[b for b in g if model.body_mass[b] > 0] for g in groups]
    return [g for g in groups if g]


def swing_floor(contacts: np.ndarray, clearance: float) -> np.ndarray:
    """The lowest each foot's sole may be (T, 2) m: 0 in contact and in the air frame next to a
    contact frame, ``clearance`` / 2 two frames from one, ``clearance`` farther (a swing of 5+
    frames clears the floor in its middle instead of skimming it). contacts (T, 2) bool."""
    c = np.asarray(contacts, dtype=bool)
    T = c.shape[0]
    dist = np.full(c.shape, T, dtype=float)  # frames to the nearest contact frame of the same foot
    for s in range(2):
        on = np.flatnonzero(c[:, s])
        if on.size:
            t = np.arange(T)
            j = np.clip(np.searchsorted(on, t), 0, on.size - 1)
            dist[:, s] = np.minimum(np.abs(on[j] - t), np.abs(on[np.maximum(j - 1, 0)] - t))
    return clearance * np.clip((dist - 1) / 2, 0.0, 1.0)


def retarget_offline(
    robot, motion: Motion, config: OfflineConfig = OfflineConfig(), contacts=None, scaler=None
) -> RobotTrajectory:
    """One-call convenience: ``OfflineRetargeter(robot, config).retarget(motion)``."""
    return OfflineRetargeter(robot, config).retarget(motion, contacts, scaler)

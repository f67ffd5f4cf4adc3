"""Physical check of a robot trajectory: play it through the servos in MuJoCo and judge it.

The trajectory (:class:`retarget.RobotTrajectory`) is resampled to the control rate
(default 100 Hz, like the bridge) by linear or cubic (PCHIP, no overshoot)
interpolation; each control tick writes the goal angles to the position servos and
advances physics ``physics_hz / control_hz`` steps (default 500 Hz). Commands are
held between ticks (zero-order hold), as a servo bus does.

Modes: ``free`` (the robot stands on its own feet; only gravity, contacts and its
servos act on it; the root pose of the trajectory sets the start pose only) and
``fixed`` (the root body is bolted at the trajectory's first root pose).

Before playing, the robot is put in the first frame's pose with its lowest point
on the floor and the first frame is held for ``settle_s`` seconds (not judged).

Judged, each with the time of its first failure (s from the start of the clip):
``joint_limit`` (a command outside the MJCF range), ``speed_limit`` (a commanded
joint speed above the servo's no-load speed), ``fall`` (root height below
``fall_height_frac`` of its standing height, tilt above ``fall_tilt_deg``, or a
part other than a foot on the floor), ``self_collision``, ``human_penetration``,
``ground_penetration``, ``foot_slip`` (sliding distance of a foot while in
contact), ``balance`` (centre of mass outside the support polygon for
``balance_window_s``), ``torque_saturation`` (a servo at its stall torque for
``saturation_window_s``) and ``tracking_error`` (|q - q_cmd| above
``max_tracking_error`` for ``tracking_window_s``). The first in time is the reason.

The robot is read as published (:mod:`sim.robot_index`, :mod:`sim.scene`): feet are the
lowest contact bodies, limits of unranged joints come from the robot's profile or
hardware config, force limits from the actuators or the joints. A test that cannot run
for lack of data (a joint with no known limit, a servo with no known no-load speed or
force limit, a free-standing robot without feet) passes nothing silently: it is listed
in ``CheckResult.not_checked`` (reason -> why), in the JSON and the markdown report.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import mujoco
import numpy as np

from dualflow.motion import Motion
from retarget.errors import RetargetError
from retarget.trajectory import RobotTrajectory
from sim.contacts import ContactClassifier, min_distance
from sim.errors import SimError
from sim.human_figure import Placement
from sim.robot_index import geom_label
from sim.scene import Scene, SceneConfig

#: Robot-human distances are measured up to this many metres; farther reads as the cap.
HUMAN_DISTANCE_CAP = 0.1

REASONS = ("joint_limit", "speed_limit", "fall", "self_collision", "human_penetration", "ground_penetration",
           "foot_slip", "balance", "torque_saturation", "tracking_error")


@dataclass(frozen=True)
class CheckConfig:
    """Rates, mode and thresholds. Lengths in m are for the OP3's size unless scaled:
    ``foot_slip_frac`` and ``fall_height_frac`` scale with the robot."""

    control_hz: float = 100.0
    physics_hz: float = 500.0
    interpolation: str = "linear"  # "linear" | "cubic"
    mode: str = "free"  # "free" | "fixed"
    settle_s: float = 0.5
    fall_height_frac: float = 0.6  # of the standing root height
    fall_tilt_deg: float = 50.0
    speed_tolerance: float = 1.0  # x no-load speed
    self_collision_depth: float = 0.002  # m; two robot parts deeper into each other than this (published
    # models' collision hulls of neighbouring links often touch by a fraction of a millimetre at rest)
    human_penetration_depth: float = 0.005  # m
    ground_penetration_depth: float = 0.01  # m
    foot_slip_frac: float = 0.06  # of the robot's height, total sliding per foot
    balance_margin: float = 0.0  # m; fail below -balance_margin ...
    balance_window_s: float = 0.2  # ... sustained this long
    saturation_window_s: float = 0.5
    max_tracking_error: float = 0.35  # rad
    tracking_window_s: float = 0.25
    stop_after_fall_s: float = 0.5

    def validate(self) -> None:
        for name in ("control_hz", "physics_hz"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise SimError(f"check config: {name} must be > 0 Hz, got {v!r}")
        ratio = self.physics_hz / self.control_hz
        if ratio < 1 or abs(ratio - round(ratio)) > 1e-9:
            raise SimError(f"check config: physics_hz ({self.physics_hz:g}) must be a whole multiple of "
                           f"control_hz ({self.control_hz:g}), e.g. 500 and 100")
        if self.interpolation not in ("linear", "cubic"):
            raise SimError(f"check config: interpolation must be 'linear' or 'cubic', got {self.interpolation!r}")
        if self.mode not in ("free", "fixed"):
            raise SimError(f"check config: mode must be 'free' or 'fixed', got {self.mode!r}")
        if self.settle_s < 0:
            raise SimError(f"check config: settle_s must be >= 0, got {self.settle_s!r}")


@dataclass
class Failure:
    reason: str
    time: float  # s from the start of the clip
    detail: str


@dataclass
class CheckResult:
    """The verdict and everything measured. ``series`` holds (K,) or (K, n) arrays at
    the control rate for plots: t, q, q_cmd, torque, root_height, tilt_deg, com_margin.
    ``not_checked`` maps a reason that could not be judged (fully or for some joints) to
    why; ``notes`` are facts about how the robot was read (limits from the actuators'
    ctrlrange, a derived standing pose)."""

    robot: str
    mode: str
    passed: bool
    reason: str
    first_failure_time: float | None
    failures: list[Failure]
    metrics: dict
    joint_names: tuple[str, ...]
    lower: np.ndarray
    upper: np.ndarray
    series: dict = field(repr=False, default_factory=dict)
    config: CheckConfig = field(default_factory=CheckConfig)
    not_checked: dict = field(default_factory=dict)
    notes: list = field(default_factory=list)

    def summary(self) -> dict:
        """JSON-ready dict (no arrays)."""
        return {
            "robot": self.robot, "mode": self.mode, "passed": self.passed, "reason": self.reason,
            "first_failure_time_s": self.first_failure_time,
            "failures": [asdict(f) for f in self.failures],
            "not_checked": dict(self.not_checked), "notes": list(self.notes),
            "metrics": self.metrics, "joint_names": list(self.joint_names),
            "config": asdict(self.config),
        }


# -- input -----------------------------------------------------------------
def load_trajectory(path) -> RobotTrajectory:
    """Read a trajectory npz; any problem becomes a SimError naming the file."""
    path = Path(path)
    if not path.is_file():
        raise SimError(f"{path}: trajectory file not found; give an npz written by RobotTrajectory.save_npz")
    try:
        return RobotTrajectory.load_npz(path)
    except RetargetError as exc:
        raise SimError(str(exc)) from None


def _as_trajectory(traj) -> RobotTrajectory:
    if isinstance(traj, (str, Path)):
        return load_trajectory(traj)
    if not isinstance(traj, RobotTrajectory):
        raise SimError(f"check: expected a RobotTrajectory or an npz path, got {type(traj).__name__}")
    return traj


def _joint_columns(traj: RobotTrajectory, names: tuple[str, ...], robot: str) -> np.ndarray:
    """(T, n) joint angles reordered to the robot's joint order."""
    if traj.n_joints != len(names):
        raise SimError(f"trajectory: has {traj.n_joints} joints but robot {robot!r} has {len(names)} "
                       f"({', '.join(names)}); retarget for this robot")
    missing = [j for j in names if j not in traj.joint_names]
    if missing:
        raise SimError(f"trajectory: joints {missing} of robot {robot!r} are missing (it has "
                       f"{list(traj.joint_names)}); retarget for this robot")
    cols = [traj.joint_names.index(j) for j in names]
    q = traj.joint_pos[:, cols]
    if not np.all(np.isfinite(q)):
        raise SimError("trajectory: joint_pos has NaN or inf; fix the source motion")
    return q


def resample(times: np.ndarray, values: np.ndarray, t_new: np.ndarray, kind: str) -> np.ndarray:
    """Values (T, n) at ``times`` (T,) resampled at ``t_new`` (K,), clamped at the ends."""
    if len(times) == 1:
        return np.repeat(values[:1], len(t_new), axis=0)
    t_new = np.clip(t_new, times[0], times[-1])
    if kind == "cubic" and len(times) >= 3:
        from scipy.interpolate import PchipInterpolator

        return PchipInterpolator(times, values, axis=0)(t_new)
    idx = np.clip(np.searchsorted(times, t_new, side="right") - 1, 0, len(times) - 2)
    w = ((t_new - times[idx]) / (times[idx + 1] - times[idx]))[:, None]
    return (1.0 - w) * values[idx] + w * values[idx + 1]


# -- the check ---------------------------------------------------------------
def check_trajectory(traj, config: CheckConfig | None = None, robot: str | None = None, actor: Motion | None = None,
                     actor_placement: Placement | None = None, on_tick=None, joint_limits: dict | None = None,
                     no_load_speed=None) -> CheckResult:
    """Play ``traj`` (RobotTrajectory or npz path) and judge it. ``robot`` overrides
    ``traj.robot`` (default "op3"); ``actor`` adds the human figure (robot-human
    penetration is then measured); ``on_tick(t)`` as in :meth:`Checker.run` (e.g. progress);
    ``joint_limits`` / ``no_load_speed`` as in :class:`sim.scene.SceneConfig` (for what
    the MJCF does not say)."""
    config = config or CheckConfig()
    config.validate()
    traj = _as_trajectory(traj)
    scene = scene_for(traj, config, robot, actor, actor_placement, joint_limits=joint_limits,
                      no_load_speed=no_load_speed)
    return Checker(scene, config).run(traj, on_tick=on_tick)


def scene_for(traj: RobotTrajectory, config: CheckConfig, robot: str | None = None, actor: Motion | None = None,
              actor_placement: Placement | None = None, reactor: Motion | None = None,
              reactor_placement: Placement | None = None, joint_limits: dict | None = None,
              no_load_speed=None) -> Scene:
    """The scene a check of ``traj`` runs in (robot from ``robot``, ``traj.robot`` or op3)."""
    robot = robot or traj.robot or "op3"
    return Scene(SceneConfig(robot=robot, fixed_base=(config.mode == "fixed"),
                             base_pos=tuple(traj.root_pos[0]), base_quat=tuple(traj.root_quat[0]),
                             timestep=1.0 / config.physics_hz, actor=actor,
                             actor_placement=actor_placement or Placement(), reactor=reactor,
                             reactor_placement=reactor_placement or Placement(), joint_limits=joint_limits,
                             no_load_speed=no_load_speed))


class Checker:
    """Runs one trajectory through one scene and collects the measurements."""

    def __init__(self, scene: Scene, config: CheckConfig):
        self.scene, self.config = scene, config
        m, r = scene.model, scene.robot
        self.contacts = ContactClassifier(m, r.geom_ids, scene.floor_geom, r.foot_bodies)
        self.feet = r.feet
        self.robot_col_geoms = np.array([g for g in r.geom_ids if m.geom_contype[g] or m.geom_conaffinity[g]])

    def run(self, traj: RobotTrajectory, on_tick=None) -> CheckResult:
        """Play and judge ``traj``. ``on_tick(t)`` (optional) is called after each
        control tick with the clip time t in seconds (a renderer grabs frames there)."""
        sc, cfg, m, d, r = self.scene, self.config, self.scene.model, self.scene.data, self.scene.robot
        q_traj = _joint_columns(traj, r.joint_names, sc.config.robot)
        dt = 1.0 / cfg.control_hz
        n_sub = int(round(cfg.physics_hz / cfg.control_hz))
        n_ticks = int(math.floor(traj.duration * cfg.control_hz + 1e-9)) + 1
        t = np.arange(n_ticks) * dt
        q_cmd = resample(traj.times, q_traj, t, cfg.interpolation)
        free = not r.fixed_base

        # start: first frame, lowest point on the floor, settle
        sc.set_robot_pose(q_cmd[0], traj.root_pos[0], traj.root_quat[0], ground=free)
        sc.pose_humans(0.0)
        mujoco.mj_step(m, d, int(round(cfg.settle_s * cfg.physics_hz)))
        stand_h = sc.stand_root_height if free else np.nan

        K, n = n_ticks, r.n
        # -- record raw state per control tick into preallocated arrays (a few plain
        # copies from views bound once); everything is analysed afterwards, vectorised.
        qpos = np.full((K, m.nq), np.nan)
        qvel = np.full((K, m.nv), np.nan)
        force = np.full((K, m.nu), np.nan)
        com = np.full((K, 3), np.nan)  # robot centre of mass
        feet = np.array([f.body for f in self.feet], dtype=int)
        foot_x = np.full((K, len(feet), 3), np.nan)  # each foot's top body: position and rotation
        foot_R = np.full((K, len(feet), 9), np.nan)
        human_min = np.full(K, np.inf)
        con_count = np.zeros(K, int)
        con_geom, con_dist, con_pos = [], [], []
        actor = sc.actor
        stop_at = K
        fall_h = cfg.fall_height_frac * stand_h if free else -np.inf
        cos_tilt = math.cos(math.radians(cfg.fall_tilt_deg)) if free else -2.0
        root = r.root_body
        act = r.actuator_ids
        a0 = int(act[0])
        ctrl = d.ctrl[a0:a0 + len(act)] if np.array_equal(act, np.arange(a0, a0 + len(act))) else None
        root_xpos, root_xmat, root_com = d.xpos[root], d.xmat[root], d.subtree_com[root]
        d_qpos, d_qvel, d_force, d_xpos, d_xmat = d.qpos, d.qvel, d.actuator_force, d.xpos, d.xmat
        step = mujoco.mj_step

        for k in range(K):
            if ctrl is not None:
                ctrl[:] = q_cmd[k]
            else:
                d.ctrl[act] = q_cmd[k]
            if actor is not None:
                actor.pose_at(d, t[k])
            step(m, d, n_sub)
            qpos[k] = d_qpos
            qvel[k] = d_qvel
            force[k] = d_force
            com[k] = root_com
            if len(feet):
                foot_x[k] = d_xpos[feet]
                foot_R[k] = d_xmat[feet]
            nc = d.ncon
            if nc:
                c = d.contact
                con_count[k] = nc
                con_geom.append(c.geom.copy())
                con_dist.append(c.dist.copy())
                con_pos.append(c.pos.copy())
            if actor is not None:
                human_min[k] = min_distance(m, d, self.robot_col_geoms, actor.geom_ids, HUMAN_DISTANCE_CAP)
            if stop_at == K and (root_xpos[2] < fall_h or root_xmat[8] < cos_tilt):
                stop_at = min(K, k + 1 + int(cfg.stop_after_fall_s * cfg.control_hz))
            if on_tick is not None:
                on_tick(float(t[k]))
            if k + 1 >= stop_at:
                break
        K_run = min(stop_at, K)
        xpos, root_zz = _root_pose_series(qpos, r.free_qpos, root_xpos, root_xmat, K_run)

        q = qpos[:, r.qpos_adr]
        qd = qvel[:, r.dof_adr]
        tau = r.joint_torques(force)  # N m at the joints (gear, joint actuatorfrcrange)
        root_h = xpos[:, 2]
        com_xy = com[:, :2]
        # each foot's sole point (Foot.sole_point, in its top body's frame) in the world: x + R p
        sole = np.array([f.sole_point for f in self.feet]).reshape(-1, 3)
        foot_xy = (foot_x + np.einsum("kfij,fj->kfi", foot_R.reshape(K, -1, 3, 3), sole))[:, :, :2]
        tilt = np.degrees(np.arccos(np.clip(root_zz, -1.0, 1.0)))
        contacts = self.contacts.classify_many(K, con_count, con_geom, con_dist, con_pos)
        self_min, floor_min, non_foot = contacts.self_min, contacts.floor_min, contacts.non_foot
        self_pairs = {tuple(sorted((geom_label(m, a), geom_label(m, b)))) for a, b in contacts.self_pairs}
        fall_k = None
        if free:
            fell = (root_h[:K_run] < fall_h) | (root_zz[:K_run] < cos_tilt) | non_foot[:K_run]
            fall_k = _first(fell)
        slip = np.zeros((K, len(feet)))
        if len(feet):
            step = np.zeros((K, len(feet)))
            step[1:] = np.linalg.norm(np.diff(foot_xy, axis=0), axis=2)
            on = contacts.foot_on_floor([f.bodies for f in self.feet])  # (K, n_feet)
            both = on.copy()
            both[1:] &= on[:-1]
            both[0] = False
            slip = np.where(both, step, 0.0)

        margin = np.full(K, np.nan)
        if free:
            margin[:K_run] = contacts.support_margins(com_xy[:K_run])

        failures = self._judge(t, q_cmd, q, tau, root_h, tilt, non_foot, self_min, floor_min, human_min,
                               slip, margin, K_run, fall_k, stand_h, dt, free, actor is not None, self_pairs)
        failures.sort(key=lambda f: (f.time, REASONS.index(f.reason)))
        err = np.abs(q[:K_run] - q_cmd[:K_run])
        cmd_speed = np.abs(np.diff(q_cmd, axis=0)) / dt if K > 1 else np.zeros((1, n))
        sat = np.abs(tau[:K_run]) >= 0.99 * r.stall_torque
        metrics = {
            "duration_s": float(traj.duration),
            "simulated_s": float(K_run * dt),
            "control_hz": cfg.control_hz, "physics_hz": cfg.physics_hz,
            "tracking_rms_rad": _per_joint(r.joint_names, np.sqrt(np.nanmean(err ** 2, axis=0))),
            "tracking_max_rad": _per_joint(r.joint_names, np.nanmax(err, axis=0)),
            "torque_saturation_s": _per_joint(r.joint_names, sat.sum(axis=0) * dt),
            "max_abs_torque_nm": _per_joint(r.joint_names, np.nanmax(np.abs(tau[:K_run]), axis=0)),
            "stall_torque_nm": _per_joint(r.joint_names, r.stall_torque),
            "no_load_speed_rad_s": _per_joint(r.joint_names, r.no_load_speed),
            "speed_limit_hits": {j: int(v) for j, v in zip(r.joint_names, (cmd_speed > cfg.speed_tolerance * r.no_load_speed).sum(axis=0))},
            "max_command_speed_rad_s": _per_joint(r.joint_names, cmd_speed.max(axis=0)),
            "max_measured_speed_rad_s": _per_joint(r.joint_names, np.nanmax(np.abs(qd[:K_run]), axis=0)),
            "self_collision_ticks": int((self_min[:K_run] < -cfg.self_collision_depth).sum()),
            "self_collision_pairs": sorted(" / ".join(p) for p in self_pairs),
            "min_self_distance_m": _finite(self_min[:K_run].min()),
            "max_ground_penetration_m": _finite(max(0.0, -floor_min[:K_run].min())),
            "min_human_distance_m": _finite(human_min[:K_run].min()) if actor is not None else None,
            "foot_slip_m": [float(s) for s in slip[:K_run].sum(axis=0)],
            "min_com_margin_m": _finite(np.nanmin(margin)) if free and np.isfinite(margin).any() else None,
            "no_support_s": float(np.isnan(margin[:K_run]).sum() * dt) if free else None,
            "max_tilt_deg": _finite(np.nanmax(tilt[:K_run])) if free else None,
            "min_root_height_m": _finite(np.nanmin(root_h[:K_run])) if free else None,
            "standing_root_height_m": _finite(stand_h) if free else None,
        }
        metrics["joint_limit_source"] = {j: (s or None) for j, s in zip(r.joint_names, r.limit_source)}
        metrics["no_load_speed_source"] = {j: (s or None) for j, s in zip(r.joint_names, r.speed_source)}
        metrics["feet"] = {f.side: [m.body(b).name or f"body {b}" for b in f.bodies] for f in self.feet}
        first = failures[0] if failures else None
        series = {"t": t[:K_run], "q": q[:K_run], "q_cmd": q_cmd[:K_run], "torque": tau[:K_run],
                  "root_height": root_h[:K_run], "tilt_deg": tilt[:K_run], "com_margin": margin[:K_run]}
        return CheckResult(sc.config.robot, "fixed" if r.fixed_base else "free", first is None, first.reason if first else "ok",
                           first.time if first else None, failures, metrics, r.joint_names, r.lower, r.upper,
                           series, cfg, self.not_checked(), self.notes())

    def not_checked(self) -> dict[str, str]:
        """Reason -> why it could not be judged (for all joints or the ones named)."""
        r, sc, out = self.scene.robot, self.scene, {}
        joints = r.unchecked("joint_limit")
        if joints:
            out["joint_limit"] = (f"limits not checked for joints {', '.join(joints)}: the MJCF gives them no range and "
                                  "neither the retarget profile (joint_limits), the hardware config (limits), the "
                                  "actuator (ctrlrange) nor the caller (joint_limits) does")
        joints = r.unchecked("speed_limit")
        if joints:
            which = "any joint" if len(joints) == r.n else f"joints {', '.join(joints)}"
            out["speed_limit"] = (f"servo speed not checked for {which}: no no-load speed is known (give the MJCF a "
                                  "`<custom><numeric name=\"servo_no_load_speed\" data=\"RAD_S\"/></custom>`, name the "
                                  "servo model in the robot's hardware.yaml, or pass no_load_speed)")
        joints = r.unchecked("torque_saturation")
        if joints:
            which = "any joint" if len(joints) == r.n else f"joints {', '.join(joints)}"
            out["torque_saturation"] = (f"torque saturation not checked for {which}: no force limit (actuator "
                                        "forcerange or joint actuatorfrcrange) in the MJCF")
        if sc.floating and not r.fixed_base and len(r.feet) < 2:
            found = ", ".join(f.side for f in r.feet) or "none"
            out["foot_slip"] = (f"feet not found (found: {found}): the robot has no contact geoms on one side of its "
                                "root's y axis; foot slip is not measured and any floor contact counts as a fall")
        return out

    def notes(self) -> list[str]:
        r, sc, out = self.scene.robot, self.scene, []
        for src, what in (("ctrlrange", "the actuators' ctrlrange"), ("profile", "the retarget profile"),
                          ("hardware", "the hardware config"), ("given", "the caller")):
            joints = [j for j, s in zip(r.joint_names, r.limit_source) if s == src]
            if joints:
                out.append(f"joint limits from {what} (no range in the MJCF) for {', '.join(joints)}")
        out += list(sc.facts.notes)
        if sc.stand_source == "derived":
            out.append("no 'stand' keyframe: standing pose derived (joints at 0 clipped into their limits, lowest "
                       "contact geom on the floor)")
        return out

    def _judge(self, t, q_cmd, q, tau, root_h, tilt, non_foot, self_min, floor_min, human_min, slip, margin,
               K_run, fall_k, stand_h, dt, free, has_actor, self_pairs) -> list[Failure]:
        cfg, r = self.config, self.scene.robot
        names = r.joint_names
        out: list[Failure] = []
        below = q_cmd < r.lower - 1e-6
        above = q_cmd > r.upper + 1e-6
        if (below | above).any():
            k, j = np.argwhere(below | above)[0]
            out.append(Failure("joint_limit", float(t[k]), f"{names[j]} commanded {q_cmd[k, j]:.3f} rad outside "
                               f"[{r.lower[j]:.3f}, {r.upper[j]:.3f}]"))
        if len(t) > 1:
            speed = np.abs(np.diff(q_cmd, axis=0)) / dt
            hit = speed > cfg.speed_tolerance * r.no_load_speed
            if hit.any():
                k, j = np.argwhere(hit)[0]
                out.append(Failure("speed_limit", float(t[k]), f"{names[j]} commanded at {speed[k, j]:.2f} rad/s, "
                                   f"above the servo's no-load speed {r.no_load_speed[j]:.2f} rad/s"))
        if fall_k is not None:
            why = (f"root height {root_h[fall_k]:.3f} m (standing {stand_h:.3f} m)" if root_h[fall_k] < cfg.fall_height_frac * stand_h
                   else f"torso tilt {tilt[fall_k]:.0f} deg" if tilt[fall_k] > cfg.fall_tilt_deg
                   else "a part other than a foot touched the floor")
            out.append(Failure("fall", float(t[fall_k]), why))
        k = _first(self_min[:K_run] < -cfg.self_collision_depth)
        if k is not None:
            out.append(Failure("self_collision", float(t[k]), f"robot parts collide ({-self_min[k] * 1000:.1f} mm deep) "
                               f"({', '.join(sorted(' / '.join(p) for p in self_pairs)) or 'see report'})"))
        if has_actor:
            k = _first(human_min[:K_run] < -cfg.human_penetration_depth)
            if k is not None:
                out.append(Failure("human_penetration", float(t[k]), f"robot enters the human figure by {-human_min[k] * 1000:.1f} mm"))
        k = _first(floor_min[:K_run] < -cfg.ground_penetration_depth)
        if k is not None:
            out.append(Failure("ground_penetration", float(t[k]), f"robot is {-floor_min[k] * 1000:.1f} mm into the floor"))
        if slip.shape[1]:
            limit = cfg.foot_slip_frac * self.scene.robot_height
            cum = np.cumsum(slip[:K_run], axis=0)
            k = _first((cum > limit).any(axis=1))
            if k is not None:
                f = self.feet[int(np.argmax(cum[k]))]
                name = self.scene.model.body(f.body).name or f"body {f.body}"
                out.append(Failure("foot_slip", float(t[k]), f"the {f.side} foot ({name}) slid {cum[k].max() * 1000:.0f} mm while in contact "
                                   f"(limit {limit * 1000:.0f} mm)"))
        if free:
            k = _first_sustained(margin[:K_run] < -cfg.balance_margin, int(round(cfg.balance_window_s / dt)))
            if k is not None:
                worst = -np.nanmin(margin[k:k + int(round(cfg.balance_window_s / dt)) + 1])
                out.append(Failure("balance", float(t[k]), f"centre of mass up to {worst * 1000:.0f} mm outside the "
                                   f"support polygon for over {cfg.balance_window_s:g} s"))
        sat = np.abs(tau[:K_run]) >= 0.99 * r.stall_torque
        w = int(round(cfg.saturation_window_s / dt))
        firsts = [(_first_sustained(sat[:, j], w), j) for j in range(r.n)]
        firsts = [(k, j) for k, j in firsts if k is not None]
        if firsts:
            k, j = min(firsts)
            out.append(Failure("torque_saturation", float(t[k]), f"{names[j]} at its stall torque {r.stall_torque[j]:g} N m "
                               f"for over {cfg.saturation_window_s:g} s"))
        err = np.abs(q[:K_run] - q_cmd[:K_run])
        w = int(round(cfg.tracking_window_s / dt))
        firsts = [(_first_sustained(err[:, j] > cfg.max_tracking_error, w), j) for j in range(r.n)]
        firsts = [(k, j) for k, j in firsts if k is not None]
        if firsts:
            k, j = min(firsts)
            out.append(Failure("tracking_error", float(t[k]), f"{names[j]} lags its command by over "
                               f"{cfg.max_tracking_error:g} rad for {cfg.tracking_window_s:g} s"))
        return out


def _root_pose_series(qpos: np.ndarray, free_qpos: int, xpos_now: np.ndarray, xmat_now: np.ndarray,
                        k_run: int) -> tuple[np.ndarray, np.ndarray]:
    """Root body position (K, 3) and the z-z entry of its rotation matrix (K,) (the
    cosine of the torso tilt) per tick, NaN after ``k_run``.

    A free base reads them from its freejoint's qpos: position p = qpos[a:a+3] and,
    for the quaternion (w, x, y, z) normalised by s = w^2 + x^2 + y^2 + z^2,
    R_zz = (w^2 - x^2 - y^2 + z^2) / s. A fixed base never moves: its current pose
    ``xpos_now`` (3,) / ``xmat_now`` (9,) holds for every tick."""
    K = len(qpos)
    if free_qpos >= 0:
        pos = qpos[:, free_qpos:free_qpos + 3].copy()
        w, x, y, z = qpos[:, free_qpos + 3:free_qpos + 7].T
        zz = (w * w - x * x - y * y + z * z) / (w * w + x * x + y * y + z * z)
    else:
        pos = np.tile(xpos_now, (K, 1))
        zz = np.full(K, xmat_now[8])
    pos[k_run:] = np.nan
    zz[k_run:] = np.nan
    return pos, zz


def _first(mask: np.ndarray) -> int | None:
    idx = np.flatnonzero(mask)
    return int(idx[0]) if len(idx) else None


def _first_sustained(mask: np.ndarray, window: int) -> int | None:
    """Index where the first run of at least ``window`` consecutive True values starts.

    With c the running count of True values, a run of ``window`` ends at i when
    c[i] - c[i - window] == window."""
    window = max(1, window)
    mask = np.asarray(mask, dtype=bool)
    if len(mask) < window:
        return None
    c = np.concatenate([[0], np.cumsum(mask)])
    full = np.flatnonzero(c[window:] - c[:-window] == window)
    return int(full[0]) if len(full) else None


def _per_joint(names, values) -> dict:
    return {n: (float(v) if np.isfinite(v) else None) for n, v in zip(names, values)}


def _finite(v) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None

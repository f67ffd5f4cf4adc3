"""Physical check of a robot trajectory: play it through the servos in MuJoCo and judge it.

``check_trajectory(traj, CheckConfig())`` returns a :class:`CheckResult`: FAIL only for an
outcome (a fall, self-collision, a limit or servo-speed breach, sustained stall torque or
tracking error, penetrating the human), each at its first time in the clip (negative while
entering the clip's first pose from standing, and in a lead-in the retargeter put before the
clip: ``meta["lead_in"]``); slip and balance margins are warnings. A free robot plays through
the bridge's balance stabilizer. Reference: docs/simulation.md.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import mujoco
import numpy as np

from retarget.errors import RetargetError
from retarget.lead_in import lead_in_of
from retarget.trajectory import RobotTrajectory
from sim.contacts import ContactClassifier, min_distance
from sim.errors import SimError
from sim.human_figure import FaceToFace, People, Placement
from sim.robot_index import body_label, geom_label
from sim.scene import Scene, SceneConfig
from sim.stabilizer import Stabilizer, StabilizerGains, balance_model
from sim.virtual_robot import ImuProbe

#: Robot-human distances are measured up to this many metres; farther reads as the cap.
HUMAN_DISTANCE_CAP = 0.1

#: Failure reasons, in the order that breaks ties between failures at the same tick.
REASONS = (
    "joint_limit",
    "speed_limit",
    "fall",
    "self_collision",
    "human_penetration",
    "torque_saturation",
    "tracking_error",
)

#: Warning kinds (measured figures that do not fail a motion).
WARNINGS = ("foot_slip", "com_outside_support", "zmp_near_edge", "foot_in_floor")

#: Servo speed (rad/s) the entry transition assumes for a joint whose no-load speed is unknown.
UNKNOWN_ENTRY_SPEED = 2.0


@dataclass(frozen=True)
class CheckConfig:
    """Rates, mode, entry and thresholds. Lengths in m are for the OP3's size unless scaled:
    ``foot_slip_frac`` and ``fall_height_frac`` scale with the robot."""

    control_hz: float = 100.0
    physics_hz: float = 500.0
    interpolation: str = "linear"  # "linear" | "cubic"
    mode: str = "free"  # "free" | "fixed"
    entry: str = "stand"  # "stand" (min-jerk transition from the standing pose) | "first_frame"
    entry_speed_frac: float = 0.5  # the transition's peak joint speed, x the servo's no-load speed
    entry_min_s: float = 0.5  # shortest transition
    settle_s: float = 0.5  # standing still before the transition (or in the first frame): not judged
    fall_height_frac: float = 0.0  # of the standing root height; 0: off (a deep crouch is not a fall)
    fall_tilt_deg: float = 50.0
    speed_tolerance: float = 1.0  # x no-load speed
    self_collision_depth: float = 0.002  # m; two robot parts deeper into each other than this (published
    # models' collision hulls of neighbouring links often touch by a fraction of a millimetre at rest)
    human_penetration_depth: float = 0.005  # m
    saturation_window_s: float = 0.5
    max_tracking_error: float = 0.35  # rad
    tracking_window_s: float = 0.25
    stop_after_fall_s: float = 0.5
    # warnings
    ground_penetration_depth: float = 0.01  # m, a foot this deep in the floor
    foot_slip_frac: float = 0.02  # of the robot's height, a foot's slide within one stance
    stance_gap_s: float = 0.05  # a foot off the floor for less than this is still in the same stance
    balance_margin: float = 0.0  # m; centre of mass outside the support polygon by more than this ...
    balance_window_s: float = 0.2  # ... (or the ZMP near its edge) sustained this long
    zmp_edge_margin: float = 0.002  # m; the measured ZMP this close to the support polygon's edge
    # balance feedback, as in the bridge's loop (module docstring); gains None: scaled to the robot
    stabilizer: bool = True
    stabilizer_gains: StabilizerGains | None = None
    # control ticks between the readings the stabilizer gets and the command it makes: 1 as the
    # bridge's split-phase bus gives them, 0 as the virtual robot does (its readings are fresh)
    reading_age: int = 1
    # None: each stabilized command moves no faster than the reference or the servo. Else a
    # callable making, for one play, the bridge's safety filter: called as
    # command_filter(joint_names, start) with the check's joint order and the command (n,) rad
    # the clip starts from, it returns q (n,) -> q (n,), which each command of the clip goes
    # through as in the bridge's loop (stabilized or not); the stabilizer's correction is then
    # recorded before it, as the loop's telemetry records it.
    # ros_free_bridge.robots.check_command_filter makes the one the bridge drives a robot with.
    command_filter: object = None
    # with a command_filter: judge the joint and speed limits on what the trajectory asked (the
    # reference; the filter makes the sent commands keep them) rather than on the sent commands.
    # False where the reference is not a trajectory someone gave (a run's loop targets, replayed)
    judge_reference: bool = True

    def validate(self) -> None:
        for name in ("control_hz", "physics_hz"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise SimError(f"check config: {name} must be > 0 Hz, got {v!r}")
        ratio = self.physics_hz / self.control_hz
        if ratio < 1 or abs(ratio - round(ratio)) > 1e-9:
            raise SimError(
                f"check config: physics_hz ({self.physics_hz:g}) must be a whole multiple of "
                f"control_hz ({self.control_hz:g}), e.g. 500 and 100"
            )
        if self.interpolation not in ("linear", "cubic"):
            raise SimError(f"check config: interpolation must be 'linear' or 'cubic', got {self.interpolation!r}")
        if self.mode not in ("free", "fixed"):
            raise SimError(f"check config: mode must be 'free' or 'fixed', got {self.mode!r}")
        if self.entry not in ("stand", "first_frame"):
            raise SimError(f"check config: entry must be 'stand' or 'first_frame', got {self.entry!r}")
        if not (math.isfinite(self.entry_speed_frac) and 0 < self.entry_speed_frac <= 1):
            raise SimError(f"check config: entry_speed_frac must be in (0, 1], got {self.entry_speed_frac!r}")
        if self.stabilizer_gains is not None:
            try:
                self.stabilizer_gains.validate()
            except ValueError as exc:
                raise SimError(f"check config: {exc}") from None
        for name in ("settle_s", "entry_min_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise SimError(f"check config: {name} must be >= 0, got {v!r}")
        if not (isinstance(self.reading_age, int) and self.reading_age >= 0):
            raise SimError(f"check config: reading_age must be a whole number of ticks >= 0, got {self.reading_age!r}")
        if self.command_filter is not None and not callable(self.command_filter):
            raise SimError("check config: command_filter must be None or a callable that makes a filter")


@dataclass
class Failure:
    """One failed criterion: ``reason`` (one of :data:`REASONS`), ``time`` (s in the clip's time:
    negative during the entry transition and a lead-in), ``detail`` and ``phase`` ("entry": while
    moving from standing to the trajectory's first pose; "lead-in": in the lead-in the retargeter
    put before a clip that starts mid-motion (:mod:`retarget.lead_in`); "clip": while playing
    the clip)."""

    reason: str
    time: float  # s from the start of the clip
    detail: str
    phase: str = "clip"


@dataclass
class CheckWarning:
    """A measured figure beyond its warning level: ``kind`` (one of :data:`WARNINGS`), ``time``
    (s in the clip's time, where it first happened), ``detail``, ``phase`` as in :class:`Failure`."""

    kind: str
    time: float
    detail: str
    phase: str = "clip"


@dataclass
class CheckResult:
    """The verdict and everything measured. ``series`` holds (K,) or (K, n) arrays at
    the control rate for plots, the entry transition included (negative t): t, q, q_cmd,
    torque, root_height, tilt_deg, com_margin, zmp_margin.
    ``not_checked`` maps a reason that could not be judged (fully or for some joints) to
    why; ``notes`` are facts about how the robot was read (limits from the actuators'
    ctrlrange, a derived standing pose). ``warnings`` (:class:`CheckWarning`) never change
    ``passed``. ``entry_transition_s`` is the duration of the move from standing to the
    clip's first pose (0 with ``entry="first_frame"``)."""

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
    warnings: list = field(default_factory=list)
    entry_transition_s: float = 0.0

    def summary(self) -> dict:
        """JSON-ready dict (no arrays)."""
        return {
            "robot": self.robot,
            "mode": self.mode,
            "passed": self.passed,
            "reason": self.reason,
            "first_failure_time_s": self.first_failure_time,
            "failures": [asdict(f) for f in self.failures],
            "warnings": [asdict(w) for w in self.warnings],
            "entry_transition_s": self.entry_transition_s,
            "not_checked": dict(self.not_checked),
            "notes": list(self.notes),
            "metrics": self.metrics,
            "joint_names": list(self.joint_names),
            # the command filter is code, not a setting: named by whether there was one
            "config": {**asdict(self.config), "command_filter": self.config.command_filter is not None},
        }


# -- input -----------------------------------------------------------------
def lift_offs(metrics: dict) -> int:
    """How often a foot left the floor in a check (its ``metrics``): each foot's stances less one."""
    return sum(max(0, int(n) - 1) for n in metrics.get("stances") or [])


def steps_taken(metrics: dict) -> int:
    """The robot's steps in a check (its ``metrics``), counted as the person's are
    (:func:`steps_as_a_person`)."""
    return sum(int(n) for n in metrics.get("steps") or [])


def steps_as_a_person(sole: np.ndarray, dt: float, robot_height: float) -> list[int]:
    """Each foot's steps, counted by the rule that counts the person's
    (:func:`retarget.targets.detect_contacts`, :func:`retarget.schedule.count_steps`) scaled to
    the robot: a foot is down while its sole point ``sole`` (K, F, 3) m, world, one row a tick
    of ``dt`` s) is within 5 cm x s of where it stood at the first tick and moves slower than
    0.4 m/s x s (over a 30 fps frame), s = the robot's height over the person's rest height;
    ups and downs shorter than 0.1 s are smoothed away; a step is a touch-down after the first
    tick. A foot that leaves the floor by millimetres and comes back where it was (a rebound on
    landing, a rocking sole) is no step, as a person's shuffle below the rule is none; the raw
    count of lift-offs is :func:`lift_offs`."""
    from dualflow.motion.skeleton import REST_POSE
    from retarget.schedule import count_steps
    from retarget.targets import CONTACT_FPS, CONTACT_HEIGHT, CONTACT_MIN_FRAMES, CONTACT_SPEED, debounce

    sole = np.asarray(sole, dtype=np.float64)
    K, F = sole.shape[:2]
    if K < 2:
        return [0] * F
    scale = robot_height / float(REST_POSE[:, 2].max())
    w = max(1, int(round(1.0 / (CONTACT_FPS * dt))))  # ticks in one of the person's frames
    speed = np.zeros((K, F))
    if K > w:
        speed[w:] = np.linalg.norm(sole[w:] - sole[:-w], axis=-1) / (w * dt)
        speed[:w] = speed[w]
    rise = sole[..., 2] - sole[0, :, 2]
    down = (rise < CONTACT_HEIGHT * scale) & (speed < CONTACT_SPEED * scale)
    n = max(1, int(round(CONTACT_MIN_FRAMES / (CONTACT_FPS * dt))))
    return [count_steps(debounce(down[:, f], n)[:, None]) for f in range(F)]


def robot_of(traj: RobotTrajectory, robot=None):
    """The robot a check of ``traj`` plays: ``robot`` if given, else the trajectory's, else op3."""
    return robot or traj.robot or "op3"


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
        raise SimError(
            f"trajectory: has {traj.n_joints} joints but robot {robot!r} has {len(names)} "
            f"({', '.join(names)}); retarget for this robot"
        )
    missing = [j for j in names if j not in traj.joint_names]
    if missing:
        raise SimError(
            f"trajectory: joints {missing} of robot {robot!r} are missing (it has "
            f"{list(traj.joint_names)}); retarget for this robot"
        )
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
def check_trajectory(
    traj,
    config: CheckConfig | None = None,
    robot: str | None = None,
    people: People | None = None,
    on_tick=None,
    joint_limits: dict | None = None,
    no_load_speed=None,
) -> CheckResult:
    """Play ``traj`` (RobotTrajectory or npz path) and judge it. ``robot`` overrides
    ``traj.robot`` (default "op3"); ``people`` (:class:`sim.human_figure.People`) adds the human
    figures: with an actor, robot-human penetration is measured (its placement None: face to
    face at a partner's distance, :class:`sim.human_figure.FaceToFace`); ``on_tick(t)`` as in
    :meth:`Checker.run` (e.g. progress);
    ``joint_limits`` / ``no_load_speed`` as in :class:`sim.scene.SceneConfig` (for what
    the MJCF does not say)."""
    config = config or CheckConfig()
    config.validate()
    traj = _as_trajectory(traj)
    scene = scene_for(traj, config, robot, people, joint_limits=joint_limits, no_load_speed=no_load_speed)
    return Checker(scene, config).run(traj, on_tick=on_tick)


def scene_for(
    traj: RobotTrajectory,
    config: CheckConfig,
    robot: str | None = None,
    people: People | None = None,
    joint_limits: dict | None = None,
    no_load_speed=None,
) -> Scene:
    """The scene a check of ``traj`` runs in (robot from ``robot``, ``traj.robot`` or op3). The
    actor of ``people`` stands face to face with the robot's first frame unless its placement
    says otherwise; the reactor (the person the robot plays) is drawn where its placement puts
    it (None: as the file has it)."""
    robot = robot_of(traj, robot)
    people = people or People()
    return Scene(
        SceneConfig(
            robot=robot,
            fixed_base=(config.mode == "fixed"),
            base_pos=tuple(traj.root_pos[0]),
            base_quat=tuple(traj.root_quat[0]),
            timestep=1.0 / config.physics_hz,
            actor=people.actor,
            actor_placement=_actor_placement(traj, config, people.actor_placement),
            reactor=people.reactor,
            reactor_placement=people.reactor_placement or Placement(),
            joint_limits=joint_limits,
            no_load_speed=no_load_speed,
        )
    )


def _actor_placement(
    traj: RobotTrajectory, config: CheckConfig, placement: Placement | FaceToFace | None
) -> Placement | FaceToFace:
    """``placement`` (None: :class:`FaceToFace`); a free robot's face-to-face partner keeps its
    distance from the root's planned path, not just from its first frame. The path is in clip
    time, as the actor is posed (a lead-in's frames before the clip left out, an ease-in's warp
    undone), so that each of the actor's frames is matched with where the robot is then."""
    placement = placement or FaceToFace()
    if isinstance(placement, FaceToFace) and placement.path is None and config.mode == "free":
        xy = traj.root_pos[:, :2]
        lead = lead_in_of(traj)
        if lead is not None:  # the root at clip times 0, 1/fps, ... (clamped at the trajectory's end)
            tc = lead.clip_time(traj.times)
            t = np.arange(int(np.floor(max(float(tc[-1]), 0.0) * traj.fps + 1e-9)) + 1) / traj.fps
            xy = np.stack([np.interp(t, tc, xy[:, i]) for i in (0, 1)], axis=1)
        placement = replace(placement, path=tuple(map(tuple, np.round(xy, 6).tolist())), path_fps=float(traj.fps))
    return placement


@dataclass
class _Recording:
    """The raw state one play recorded per control tick (K ticks; rows from ``k_run`` on were
    not played): the reference ``q_ref`` and the commands ``q_cmd`` (K, n) with the
    stabilizer's ``correction``; MuJoCo's qpos, qvel, actuator force; the robot's centre of
    mass; each foot's top body position and rotation; the robot-human distance; the contacts
    of each tick with contacts (lists, as :meth:`ContactClassifier.classify_many` takes them)."""

    t: np.ndarray
    q_ref: np.ndarray
    q_cmd: np.ndarray
    correction: np.ndarray
    k0: int
    qpos: np.ndarray
    qvel: np.ndarray
    force: np.ndarray
    com: np.ndarray
    foot_x: np.ndarray
    foot_R: np.ndarray
    human_min: np.ndarray
    con_count: np.ndarray
    con_geom: list = field(default_factory=list)
    con_dist: list = field(default_factory=list)
    con_pos: list = field(default_factory=list)
    con_efc: list = field(default_factory=list)
    con_dim: list = field(default_factory=list)
    efc_force: list = field(default_factory=list)
    k_run: int = 0
    root_xpos: np.ndarray | None = None  # the root body's last pose (for _root_pose_series)
    root_xmat: np.ndarray | None = None

    @classmethod
    def empty(cls, t: np.ndarray, q_ref: np.ndarray, model, n_feet: int, k0: int) -> _Recording:
        K, n = q_ref.shape
        return cls(
            t,
            q_ref,
            q_ref.copy(),
            np.zeros((K, n)),
            k0,
            np.full((K, model.nq), np.nan),
            np.full((K, model.nv), np.nan),
            np.full((K, model.nu), np.nan),
            np.full((K, 3), np.nan),
            np.full((K, n_feet, 3), np.nan),
            np.full((K, n_feet, 9), np.nan),
            np.full(K, np.inf),
            np.zeros(K, int),
        )

    def record_contacts(self, k: int, data) -> None:
        nc = data.ncon
        if nc:
            c = data.contact
            self.con_count[k] = nc
            self.con_geom.append(c.geom.copy())
            self.con_dist.append(c.dist.copy())
            self.con_pos.append(c.pos.copy())
            self.con_efc.append(c.efc_address.copy())
            self.con_dim.append(c.dim.copy())
            self.efc_force.append(data.efc_force[: data.nefc].copy())


@dataclass
class Series:
    """What the judge reads, per control tick (K ticks, judged up to ``k_run``): clip time ``t``
    (s, negative during the entry), the commands ``q_cmd`` and the stabilizer's ``correction``,
    the commands the joint and speed limits are judged on ``q_judged`` (the reference when a
    safety filter made the sent ones keep them and ``judge_reference`` says so, else ``q_cmd``),
    measured ``q``, ``qd`` and joint torques ``tau`` (K, n); root height, torso tilt (deg), the
    classified contacts (:class:`sim.contacts.ContactSeries`) and self-collision pairs; the
    robot-human distance; the CoM and measured-ZMP margins to the support polygon (m, + inside);
    each foot's stances (:func:`_stance_slides`) and steps (:func:`steps_as_a_person`); the first
    fall tick ``fall_k``; the entry's
    ``k0`` ticks; the standing root height; ``dt``; whether the robot stands free and a human
    is in the scene."""

    t: np.ndarray
    q_cmd: np.ndarray
    q_judged: np.ndarray
    correction: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    tau: np.ndarray
    root_h: np.ndarray
    tilt: np.ndarray
    contacts: object
    self_pairs: set
    human_min: np.ndarray
    margin: np.ndarray
    zmp_margin: np.ndarray
    stances: list
    steps: list
    k_run: int
    fall_k: int | None
    k0: int
    stand_h: float
    dt: float
    free: bool
    has_actor: bool


class Checker:
    """Runs one trajectory through one scene and collects the measurements."""

    def __init__(self, scene: Scene, config: CheckConfig):
        self.scene, self.config = scene, config
        m, r = scene.model, scene.robot
        self.contacts = ContactClassifier(m, r.geom_ids, scene.floor_geom, r.foot_bodies)
        self.feet = r.feet
        self.robot_col_geoms = np.array([g for g in r.geom_ids if m.geom_contype[g] or m.geom_conaffinity[g]])
        self.balance = balance_model(scene=scene, gains=config.stabilizer_gains) if config.stabilizer else None
        self.stabilizer = Stabilizer(self.balance) if self.balance is not None else None
        self.imu = ImuProbe(m, r.root_body) if self.stabilizer is not None else None

    def run(self, traj: RobotTrajectory, on_tick=None) -> CheckResult:
        """Play and judge ``traj``. ``on_tick(t)`` (optional) is called after each control
        tick of the trajectory with its time t >= 0 in seconds from its first frame (a renderer
        grabs frames there; a lead-in included); the entry transition before it is not reported
        there. Failures, warnings and ``series["t"]`` are in clip time: the trajectory's time
        less a lead-in's (:meth:`retarget.lead_in.LeadIn.clip_time`), negative before the clip."""
        sc, cfg, r = self.scene, self.config, self.scene.robot
        q_traj = _joint_columns(traj, r.joint_names, sc.config.robot)
        dt = 1.0 / cfg.control_hz
        n_clip = int(math.floor(traj.duration * cfg.control_hz + 1e-9)) + 1
        q_clip = resample(traj.times, q_traj, np.arange(n_clip) * dt, cfg.interpolation)
        q_entry = self._start(traj, q_clip[0])  # robot placed and settled; (k0, n) transition commands
        k0 = len(q_entry)
        q_ref = np.concatenate([q_entry, q_clip]) if k0 else q_clip
        t_traj = (np.arange(k0 + n_clip) - k0) * dt  # trajectory time: the transition is negative
        lead = lead_in_of(traj)
        t = t_traj if lead is None else lead.clip_time(t_traj)  # clip time: also the lead-in is negative
        s = self._analyse(self._play(q_ref, t, k0, on_tick, t_traj))
        failures = sorted(self._judge(s), key=lambda f: (f.time, REASONS.index(f.reason)))
        warnings = sorted(self._warn(s), key=lambda w: (w.time, WARNINGS.index(w.kind)))
        self._mark_entry(s, failures, warnings)
        metrics = self._metrics(traj, s)
        first = failures[0] if failures else None
        K = s.k_run
        series = {
            "t": s.t[:K],
            "q": s.q[:K],
            "q_cmd": s.q_cmd[:K],
            "torque": s.tau[:K],
            "root_height": s.root_h[:K],
            "tilt_deg": s.tilt[:K],
            "com_margin": s.margin[:K],
            "zmp_margin": s.zmp_margin[:K],
            "correction": s.correction[:K],
        }
        return CheckResult(
            sc.config.robot,
            "fixed" if r.fixed_base else "free",
            first is None,
            first.reason if first else "ok",
            first.time if first else None,
            failures,
            metrics,
            r.joint_names,
            r.lower,
            r.upper,
            series,
            cfg,
            self.not_checked(),
            self.notes(),
            warnings,
            float(k0 * dt),
        )

    def _play(self, q_ref: np.ndarray, t: np.ndarray, k0: int, on_tick, t_tick: np.ndarray) -> _Recording:
        """Play the commands ``q_ref`` (K, n), through the stabilizer when it is on, and record
        the raw state at every control tick (clip times ``t`` (K,): the actor is posed there;
        ``on_tick`` gets ``t_tick`` (K,)); stop ``stop_after_fall_s`` after a fall."""
        sc, cfg, m, d, r = self.scene, self.config, self.scene.model, self.scene.data, self.scene.robot
        K, n_sub = len(t), int(round(cfg.physics_hz / cfg.control_hz))
        rec = _Recording.empty(t, q_ref, m, len(self.feet), k0)
        feet = np.array([f.body for f in self.feet], dtype=int)
        free = not r.fixed_base
        stand_h = sc.stand_root_height if free else np.nan
        fall_h = cfg.fall_height_frac * stand_h if free and cfg.fall_height_frac > 0 else -np.inf
        cos_tilt = math.cos(math.radians(cfg.fall_tilt_deg)) if free else -2.0
        act = r.actuator_ids
        a0 = int(act[0])
        ctrl = d.ctrl[a0 : a0 + len(act)] if np.array_equal(act, np.arange(a0, a0 + len(act))) else None
        root = r.root_body
        root_xpos, root_xmat, root_com = d.xpos[root], d.xmat[root], d.subtree_com[root]
        d_qpos, d_qvel, d_force, d_xpos, d_xmat = d.qpos, d.qvel, d.actuator_force, d.xpos, d.xmat
        actor, step, stop_at = sc.actor, mujoco.mj_step, K
        if self.stabilizer is not None:
            stabilized = self._stabilized_commands(rec)
        else:
            stabilized = None
            self._filter_open_loop(rec)
        for k in range(K):
            goal = rec.q_cmd[k] if stabilized is None else next(stabilized)
            if ctrl is not None:
                ctrl[:] = goal
            else:
                d.ctrl[act] = goal
            if actor is not None:
                actor.pose_at(d, t[k])
            step(m, d, n_sub)
            rec.qpos[k], rec.qvel[k], rec.force[k], rec.com[k] = d_qpos, d_qvel, d_force, root_com
            if len(feet):
                rec.foot_x[k], rec.foot_R[k] = d_xpos[feet], d_xmat[feet]
            rec.record_contacts(k, d)
            if actor is not None:
                rec.human_min[k] = min_distance(m, d, self.robot_col_geoms, actor.geom_ids, HUMAN_DISTANCE_CAP)
            if stop_at == K and (root_xpos[2] < fall_h or root_xmat[8] < cos_tilt):
                stop_at = min(K, k + 1 + int(cfg.stop_after_fall_s * cfg.control_hz))
            if on_tick is not None and k >= k0:
                on_tick(float(t_tick[k]))
            if k + 1 >= stop_at:
                break
        rec.k_run = min(stop_at, K)
        rec.root_xpos, rec.root_xmat = root_xpos.copy(), root_xmat.copy()
        return rec

    def _filter_start(self, rec: _Recording) -> np.ndarray:
        """The clip's first tick's filter, started from the command before it (the entry's last)."""
        k0 = rec.k0
        start = rec.q_cmd[k0 - 1] if k0 else rec.q_ref[0]
        return self.config.command_filter(tuple(self.scene.robot.joint_names), np.array(start, dtype=np.float64))

    def _filter_open_loop(self, rec: _Recording) -> None:
        """Without a stabilizer: the clip's commands through ``command_filter``'s filter (if given)."""
        if self.config.command_filter is None or rec.k0 >= len(rec.q_cmd):
            return
        filt = self._filter_start(rec)
        for k in range(rec.k0, len(rec.q_cmd)):
            rec.q_cmd[k] = filt(rec.q_cmd[k])

    def _stabilized_commands(self, rec: _Recording):
        """Yield each tick's command: the reference through the stabilizer, fed with the readings
        of ``reading_age`` ticks before (1: as the bridge's split-phase bus gives them), then
        through ``command_filter``'s filter from the clip's first tick on (the bridge's safety
        filter), else moving no faster than the reference or the servo, whichever is faster;
        fills ``rec.q_cmd`` and ``rec.correction``."""
        cfg, d, r, stab, imu = self.config, self.scene.data, self.scene.robot, self.stabilizer, self.imu
        dt = 1.0 / cfg.control_hz
        q_ref = rec.q_ref
        speed = np.where(np.isfinite(r.no_load_speed), cfg.speed_tolerance * r.no_load_speed, np.inf) * dt
        filt = None
        readings = deque(maxlen=cfg.reading_age + 1)
        for k in range(len(q_ref)):
            readings.append((d.qpos[r.qpos_adr].copy(), imu.read(d)))
            reading = readings[0]  # the oldest kept: reading_age ticks old once there are enough
            goal = stab.step(q_ref[k], reading[0], reading[1], dt)
            if cfg.command_filter is not None and k == rec.k0:
                filt = self._filter_start(rec)
            if filt is not None:
                rec.correction[k] = goal - q_ref[k]  # the stabilizer's own, before the filter
                goal = filt(goal)
            else:
                if k:
                    room = np.maximum(0.999 * speed, np.abs(q_ref[k] - q_ref[k - 1]))
                    goal = np.clip(goal, rec.q_cmd[k - 1] - room, rec.q_cmd[k - 1] + room)
                rec.correction[k] = goal - q_ref[k]
                stab.correction = rec.correction[k].copy()
            rec.q_cmd[k] = goal
            yield goal

    def _analyse(self, rec: _Recording) -> Series:
        """The recording turned into the judged time series (vectorised, after the play)."""
        sc, cfg, m, r = self.scene, self.config, self.scene.model, self.scene.robot
        K, dt, free = len(rec.t), 1.0 / cfg.control_hz, not r.fixed_base
        xpos, root_zz = _root_pose_series(rec.qpos, r.free_qpos, rec.root_xpos, rec.root_xmat, rec.k_run)
        # each foot's sole point (Foot.sole_point, in its top body's frame) in the world: x + R p
        sole = np.array([f.sole_point for f in self.feet]).reshape(-1, 3)
        sole_w = rec.foot_x + np.einsum("kfij,fj->kfi", rec.foot_R.reshape(K, -1, 3, 3), sole)
        foot_xy = sole_w[:, :, :2]
        contacts = self.contacts.classify_many(K, rec.con_count, rec.con_geom, rec.con_dist, rec.con_pos)
        s = Series(
            t=rec.t,
            q_cmd=rec.q_cmd,
            # with the bridge's safety filter the sent commands keep the limits by construction:
            # what the trajectory asked (before the clip, the entry's commands) is judged instead
            q_judged=_asked(rec) if cfg.command_filter is not None and cfg.judge_reference else rec.q_cmd,
            correction=rec.correction,
            q=rec.qpos[:, r.qpos_adr],
            qd=rec.qvel[:, r.dof_adr],
            tau=r.joint_torques(rec.force),
            root_h=xpos[:, 2],
            tilt=np.degrees(np.arccos(np.clip(root_zz, -1.0, 1.0))),
            contacts=contacts,
            self_pairs={tuple(sorted((geom_label(m, a), geom_label(m, b)))) for a, b in contacts.self_pairs},
            human_min=rec.human_min,
            margin=np.full(K, np.nan),
            zmp_margin=np.full(K, np.nan),
            stances=[],
            steps=[],
            k_run=rec.k_run,
            fall_k=None,
            k0=rec.k0,
            stand_h=sc.stand_root_height if free else np.nan,
            dt=dt,
            free=free,
            has_actor=sc.actor is not None,
        )
        if free:
            fall_h = cfg.fall_height_frac * s.stand_h if cfg.fall_height_frac > 0 else -np.inf
            cos_tilt = math.cos(math.radians(cfg.fall_tilt_deg))
            K_run = s.k_run
            fell = (s.root_h[:K_run] < fall_h) | (root_zz[:K_run] < cos_tilt) | contacts.non_foot[:K_run]
            s.fall_k = _first(fell)
            if s.fall_k is not None:  # what follows a fall (a touch without tilting on) is not judged
                s.k_run = min(K_run, s.fall_k + 1 + int(cfg.stop_after_fall_s * cfg.control_hz))
        if len(self.feet):
            on = contacts.foot_on_floor([f.bodies for f in self.feet])[: s.k_run]  # (k_run, n_feet)
            s.stances = [
                _stance_slides(on[:, i], foot_xy[: s.k_run, i], int(round(cfg.stance_gap_s / dt)))
                for i in range(len(self.feet))
            ]
            s.steps = steps_as_a_person(sole_w[: s.k_run], dt, sc.robot_height)
        if free:  # centre of mass, and the measured ZMP (centre of pressure), to the support polygon (+ inside)
            s.margin[: s.k_run] = contacts.support_margins(rec.com[: s.k_run, :2])
            fn = _normal_forces(rec.con_efc, rec.con_dim, rec.efc_force, m.opt.cone == mujoco.mjtCone.mjCONE_PYRAMIDAL)
            cop, _ = contacts.centre_of_pressure(fn)
            s.zmp_margin[: s.k_run] = contacts.support_margins(cop[: s.k_run])
        return s

    def _mark_entry(self, s: Series, failures: list, warnings: list) -> None:
        """Say which failures and warnings happened while entering the trajectory's first pose,
        and which in a lead-in before the clip."""
        entry_end = float(s.t[s.k0]) if s.k0 < len(s.t) else 0.0  # clip time of the trajectory's first frame
        for item in (*failures, *warnings):
            if item.time < entry_end - 1e-9:
                item.phase = "entry"
                item.detail = f"entering the clip's first pose from standing: {item.detail}"
            elif item.time < -1e-9:
                item.phase = "lead-in"
                item.detail = f"in the lead-in before the clip (moving into its first pose from rest): {item.detail}"
        if s.fall_k is not None and s.fall_k >= s.k0 and s.k0:
            onset = _tipping_since(s.fall_k, s.margin, s.zmp_margin, self.config)
            if onset < s.k0:  # it was already going over when the clip began: the first pose was not reached
                f = next(f for f in failures if f.reason == "fall")
                f.phase = "entry"
                f.detail += (
                    f"; tipping since {s.t[onset]:.2f} s, while entering the clip's first pose from "
                    "standing (a first pose the robot cannot hold still, e.g. mid-step)"
                )

    def _metrics(self, traj: RobotTrajectory, s: Series) -> dict:
        cfg, sc, m, r = self.config, self.scene, self.scene.model, self.scene.robot
        K_run, dt, names, free = s.k_run, s.dt, r.joint_names, s.free
        err = np.abs(s.q[:K_run] - s.q_cmd[:K_run])
        cmd_speed = np.abs(np.diff(s.q_cmd, axis=0)) / dt if len(s.t) > 1 else np.zeros((1, r.n))
        sat = np.abs(s.tau[:K_run]) >= 0.99 * r.stall_torque
        worst = max(((st[2], i, st) for i, fs in enumerate(s.stances) for st in fs), key=lambda w: w[0], default=None)
        margin, zmp = s.margin, s.zmp_margin
        metrics = {
            "duration_s": float(traj.duration),
            "simulated_s": float(K_run * dt),
            "entry_transition_s": float(s.k0 * dt),
            "entry": dict(self.entry),
            "lead_in_s": float(lead_in_of(traj).t0_s) if lead_in_of(traj) is not None else 0.0,
            "control_hz": cfg.control_hz,
            "physics_hz": cfg.physics_hz,
            "tracking_rms_rad": _per_joint(names, np.sqrt(np.nanmean(err**2, axis=0))),
            "tracking_max_rad": _per_joint(names, np.nanmax(err, axis=0)),
            "torque_saturation_s": _per_joint(names, sat.sum(axis=0) * dt),
            "max_abs_torque_nm": _per_joint(names, np.nanmax(np.abs(s.tau[:K_run]), axis=0)),
            "stall_torque_nm": _per_joint(names, r.stall_torque),
            "no_load_speed_rad_s": _per_joint(names, r.no_load_speed),
            "speed_limit_hits": {
                j: int(v) for j, v in zip(names, (cmd_speed > cfg.speed_tolerance * r.no_load_speed).sum(axis=0))
            },
            "max_command_speed_rad_s": _per_joint(names, cmd_speed.max(axis=0)),
            "max_measured_speed_rad_s": _per_joint(names, np.nanmax(np.abs(s.qd[:K_run]), axis=0)),
            "self_collision_ticks": int((s.contacts.self_min[:K_run] < -cfg.self_collision_depth).sum()),
            "self_collision_pairs": sorted(" / ".join(p) for p in s.self_pairs),
            "min_self_distance_m": _finite(s.contacts.self_min[:K_run].min()),
            "max_ground_penetration_m": _finite(max(0.0, -s.contacts.floor_min[:K_run].min())),
            "max_foot_penetration_m": _finite(max(0.0, -s.contacts.foot_floor_min[:K_run].min())),
            "min_human_distance_m": _finite(s.human_min[:K_run].min()) if s.has_actor else None,
            "foot_slip_m": [float(max((st[2] for st in fs), default=0.0)) for fs in s.stances],
            "stances": [len(fs) for fs in s.stances],
            "steps": [int(n) for n in s.steps],
            "worst_stance": None
            if worst is None
            else {
                "foot": self.feet[worst[1]].side,
                "start_s": float(s.t[worst[2][0]]),
                "end_s": float(s.t[worst[2][1] - 1]),
                "slide_m": float(worst[0]),
            },
            "min_com_margin_m": _finite(np.nanmin(margin)) if free and np.isfinite(margin).any() else None,
            "min_zmp_margin_m": _finite(np.nanmin(zmp)) if free and np.isfinite(zmp).any() else None,
            "no_support_s": float(np.isnan(margin[:K_run]).sum() * dt) if free else None,
            "max_tilt_deg": _finite(np.nanmax(s.tilt[:K_run])) if free else None,
            "min_root_height_m": _finite(np.nanmin(s.root_h[:K_run])) if free else None,
            "standing_root_height_m": _finite(s.stand_h) if free else None,
        }
        metrics["stabilizer"] = self._stabilizer_metrics(s.correction, K_run, s.t)
        metrics["joint_limit_source"] = {j: (src or None) for j, src in zip(names, r.limit_source)}
        metrics["no_load_speed_source"] = {j: (src or None) for j, src in zip(names, r.speed_source)}
        metrics["feet"] = {f.side: [m.body(b).name or f"body {b}" for b in f.bodies] for f in self.feet}
        p = sc.actor_placement
        metrics["actor_placement"] = (
            None
            if not s.has_actor
            else {
                "scale": float(p.resolve_scale(sc.actor.motion, sc.robot_height)),
                "offset_m": [float(v) for v in p.offset],
                "yaw_deg": float(p.yaw_deg),
            }
        )
        return metrics

    def _start(self, traj: RobotTrajectory, q0: np.ndarray) -> np.ndarray:
        """Put the robot where the run starts and let it settle; return the entry transition's
        commands (k0, n), one per control tick before the clip's first frame (k0 = 0 with
        ``entry="first_frame"``), and note what it did in ``self.entry``. See the module docstring."""
        sc, cfg, m, d, r = self.scene, self.config, self.scene.model, self.scene.data, self.scene.robot
        settle = int(round(cfg.settle_s * cfg.physics_hz))
        self.entry = {"duration_s": 0.0}
        if cfg.entry == "first_frame":
            sc.set_robot_pose(q0, traj.root_pos[0], traj.root_quat[0], ground=not r.fixed_base)
            sc.pose_humans(0.0)
            self._settle(q0, settle)
            return np.zeros((0, r.n))
        sc.reset()  # standing pose, humans at their first frame
        if not r.fixed_base:  # at the first frame's place and heading; the stand's height and lean kept
            a = r.free_qpos
            stand_quat = d.qpos[a + 3 : a + 7].copy()
            turn = _yaw(traj.root_quat[0]) - _yaw(stand_quat)
            quat = np.zeros(4)
            mujoco.mju_mulQuat(quat, np.array([math.cos(turn / 2), 0.0, 0.0, math.sin(turn / 2)]), stand_quat)
            d.qpos[a : a + 2] = traj.root_pos[0, :2]
            d.qpos[a + 3 : a + 7] = quat
            mujoco.mj_forward(m, d)
        start = sc.stand_ctrl.copy()
        self._settle(start, settle)
        duration = entry_duration(start, q0, r.no_load_speed, cfg.entry_speed_frac, cfg.entry_min_s)
        k0 = int(math.ceil(duration * cfg.control_hz - 1e-9))
        j = int(np.argmax(np.abs(q0 - start)))
        self.entry = {
            "duration_s": k0 / cfg.control_hz,
            "largest_move_rad": float(abs(q0[j] - start[j])),
            "largest_move_joint": r.joint_names[j],
        }
        s = np.arange(k0) / k0  # the tick at t = 0 plays q0 itself (s = 1): it is the clip's first
        return start + (q0 - start) * (10 * s**3 - 15 * s**4 + 6 * s**5)[:, None]

    def _settle(self, q: np.ndarray, steps: int) -> None:
        """Hold goals ``q`` (n,) for ``steps`` physics steps, through the stabilizer (when on) at
        the control rate, as the bridge holds a robot standing."""
        m, d, r, cfg = self.scene.model, self.scene.data, self.scene.robot, self.config
        if self.stabilizer is None:  # the goals the pose was set with
            mujoco.mj_step(m, d, steps)
            return
        self.stabilizer.reset()
        n_sub = int(round(cfg.physics_hz / cfg.control_hz))
        dt = 1.0 / cfg.control_hz
        reading = (d.qpos[r.qpos_adr].copy(), self.imu.read(d))
        for _ in range(max(0, steps) // n_sub):
            fresh = (d.qpos[r.qpos_adr].copy(), self.imu.read(d))
            d.ctrl[r.actuator_ids] = self.stabilizer.step(q, reading[0], reading[1], dt)
            reading = fresh  # one tick old next time, as in run()
            mujoco.mj_step(m, d, n_sub)

    def _stabilizer_metrics(self, correction, k_run: int, t: np.ndarray) -> dict:
        """Whether the stabilizer was on, why not, and its largest correction."""
        cfg, sc = self.config, self.scene
        if self.stabilizer is None:
            why = (
                "turned off (--no-stabilizer)"
                if not cfg.stabilizer
                else "fixed base"
                if sc.robot.fixed_base or not sc.floating
                else "no two legs with ankle joints found from the root to the feet"
            )
            return {"on": False, "why_off": why}
        c = np.abs(correction[:k_run]) if k_run else np.zeros((1, sc.robot.n))
        k, j = np.unravel_index(int(np.argmax(c)), c.shape) if c.size else (0, 0)
        g = self.balance.gains
        return {
            "on": True,
            "max_correction_rad": float(c.max()) if c.size else 0.0,
            "max_correction_joint": sc.robot.joint_names[j],
            "max_correction_time_s": float(t[k]) if k_run else None,
            "gains": {k_: float(v) for k_, v in asdict(g).items()},
            "notes": list(self.balance.notes),
        }

    def not_checked(self) -> dict[str, str]:
        """Reason -> why it could not be judged (for all joints or the ones named)."""
        r, sc, out = self.scene.robot, self.scene, {}
        joints = r.unchecked("joint_limit")
        if joints:
            out["joint_limit"] = (
                f"limits not checked for joints {', '.join(joints)}: the MJCF gives them no range and "
                "neither the retarget profile (joint_limits), the hardware config (limits), the "
                "actuator (ctrlrange) nor the caller (joint_limits) does"
            )
        joints = r.unchecked("speed_limit")
        if joints:
            which = "any joint" if len(joints) == r.n else f"joints {', '.join(joints)}"
            out["speed_limit"] = (
                f"servo speed not checked for {which}: no no-load speed is known (give the MJCF a "
                '`<custom><numeric name="servo_no_load_speed" data="RAD_S"/></custom>`, name the '
                "servo model in the robot's hardware.yaml, or pass no_load_speed)"
            )
        joints = r.unchecked("torque_saturation")
        if joints:
            which = "any joint" if len(joints) == r.n else f"joints {', '.join(joints)}"
            out["torque_saturation"] = (
                f"torque saturation not checked for {which}: no force limit (actuator "
                "forcerange or joint actuatorfrcrange) in the MJCF"
            )
        if sc.floating and not r.fixed_base and len(r.feet) < 2:
            found = ", ".join(f.side for f in r.feet) or "none"
            out["foot_slip"] = (
                f"feet not found (found: {found}): the robot has no contact geoms on one side of its "
                "root's y axis; foot slip is not measured and any floor contact counts as a fall"
            )
        return out

    def notes(self) -> list[str]:
        r, sc, out = self.scene.robot, self.scene, []
        for src, what in (
            ("ctrlrange", "the actuators' ctrlrange"),
            ("profile", "the retarget profile"),
            ("hardware", "the hardware config"),
            ("given", "the caller"),
        ):
            joints = [j for j, s in zip(r.joint_names, r.limit_source) if s == src]
            if joints:
                out.append(f"joint limits from {what} (no range in the MJCF) for {', '.join(joints)}")
        out += list(sc.facts.notes)
        if sc.stand_source == "profile":
            out.append(
                "no 'stand' keyframe: standing in the retarget profile's stand_pose (lowest contact geom on the floor)"
            )
        elif sc.stand_source == "derived":
            out.append(
                "no 'stand' keyframe: standing pose derived (joints at 0 clipped into their limits, lowest "
                "contact geom on the floor)"
            )
        return out

    def _judge(self, s: Series) -> list[Failure]:
        """The failed criteria (module docstring), each at its first tick."""
        return [
            *self._command_failures(s),
            *self._fall_failures(s),
            *self._contact_failures(s),
            *self._sustained_failures(s),
        ]

    def _command_failures(self, s: Series) -> list[Failure]:
        """Commands outside the joint limits or faster than the servos' no-load speed."""
        cfg, r = self.config, self.scene.robot
        t, q_cmd, names = s.t, s.q_judged, r.joint_names
        out: list[Failure] = []
        outside = (q_cmd < r.lower - 1e-6) | (q_cmd > r.upper + 1e-6)
        if outside.any():
            k, j = np.argwhere(outside)[0]
            out.append(
                Failure(
                    "joint_limit",
                    float(t[k]),
                    f"{names[j]} commanded {q_cmd[k, j]:.3f} rad outside [{r.lower[j]:.3f}, {r.upper[j]:.3f}]",
                )
            )
        played = q_cmd[: s.k_run]  # ticks after the check stopped (a fall + stop_after_fall_s) were never sent
        if len(played) > 1:
            speed = np.abs(np.diff(played, axis=0)) / s.dt
            hit = speed > cfg.speed_tolerance * r.no_load_speed
            if hit.any():
                k, j = np.argwhere(hit)[0]
                out.append(
                    Failure(
                        "speed_limit",
                        float(t[k]),
                        f"{names[j]} commanded at {speed[k, j]:.2f} rad/s, "
                        f"above the servo's no-load speed {r.no_load_speed[j]:.2f} rad/s",
                    )
                )
        return out

    def _fall_failures(self, s: Series) -> list[Failure]:
        """The fall (if any), with what made it one: a non-foot part down, tilt or root height."""
        k = s.fall_k
        if k is None:
            return []
        cfg, contacts = self.config, s.contacts
        if contacts.non_foot[k]:
            parts = ", ".join(body_label(self.scene.model, b) for b in contacts.non_foot_bodies(k))
            why = f"a part other than a foot touched the floor ({parts})"
        elif s.tilt[k] > cfg.fall_tilt_deg:
            why = f"torso tilt {s.tilt[k]:.0f} deg (limit {cfg.fall_tilt_deg:g} deg)"
        else:
            why = f"root height {s.root_h[k]:.3f} m (standing {s.stand_h:.3f} m)"
        return [Failure("fall", float(s.t[k]), why)]

    def _contact_failures(self, s: Series) -> list[Failure]:
        """Robot parts deep in each other, and the robot deep in the human figure."""
        cfg, t, K_run = self.config, s.t, s.k_run
        self_min = s.contacts.self_min
        out: list[Failure] = []
        k = _first(self_min[:K_run] < -cfg.self_collision_depth)
        if k is not None:
            out.append(
                Failure(
                    "self_collision",
                    float(t[k]),
                    f"robot parts collide ({-self_min[k] * 1000:.1f} mm deep) "
                    f"({', '.join(sorted(' / '.join(p) for p in s.self_pairs)) or 'see report'})",
                )
            )
        if s.has_actor:
            k = _first(s.human_min[:K_run] < -cfg.human_penetration_depth)
            if k is not None:
                out.append(
                    Failure(
                        "human_penetration",
                        float(t[k]),
                        f"robot enters the human figure by {-s.human_min[k] * 1000:.1f} mm",
                    )
                )
        return out

    def _sustained_failures(self, s: Series) -> list[Failure]:
        """Stall torque or tracking error held for their windows, at the earliest joint's first tick."""
        cfg, r, K_run, dt = self.config, self.scene.robot, s.k_run, s.dt
        out: list[Failure] = []
        sat = np.abs(s.tau[:K_run]) >= 0.99 * r.stall_torque
        hit = _first_sustained_joint(sat, int(round(cfg.saturation_window_s / dt)))
        if hit is not None:
            k, j = hit
            out.append(
                Failure(
                    "torque_saturation",
                    float(s.t[k]),
                    f"{r.joint_names[j]} at its stall torque {r.stall_torque[j]:g} N m "
                    f"for over {cfg.saturation_window_s:g} s",
                )
            )
        lagging = np.abs(s.q[:K_run] - s.q_cmd[:K_run]) > cfg.max_tracking_error
        hit = _first_sustained_joint(lagging, int(round(cfg.tracking_window_s / dt)))
        if hit is not None:
            k, j = hit
            out.append(
                Failure(
                    "tracking_error",
                    float(s.t[k]),
                    f"{r.joint_names[j]} lags its command by over "
                    f"{cfg.max_tracking_error:g} rad for {cfg.tracking_window_s:g} s",
                )
            )
        return out

    def _warn(self, s: Series) -> list[CheckWarning]:
        """The measured figures beyond their warning levels (module docstring)."""
        cfg, sc = self.config, self.scene
        t, contacts, stances, margin, zmp_margin, K_run, dt = (
            s.t,
            s.contacts,
            s.stances,
            s.margin,
            s.zmp_margin,
            s.k_run,
            s.dt,
        )
        out: list[CheckWarning] = []
        level = cfg.foot_slip_frac * sc.robot_height
        for foot, fs in zip(self.feet, stances):
            over = [s for s in fs if s[2] > level]
            if over:
                s0, s1, slide, _, _ = max(over, key=lambda s: s[2])
                rate = slide / max((s1 - s0) * dt, dt) * 1000
                first = _first_over(over[0], level)
                more = (
                    f"; {len(over)} of its {len(fs)} stances slid over that, the first from {t[first]:.2f} s"
                    if len(over) > 1
                    else ""
                )
                out.append(
                    CheckWarning(
                        "foot_slip",
                        float(t[first]),
                        f"the {foot.side} foot "
                        f"({body_label(sc.model, foot.body)}) slid {slide * 1000:.1f} mm within one "
                        f"stance (the stance from {t[s0]:.2f} s to {t[s1 - 1]:.2f} s, {rate:.1f} mm/s "
                        f"on average), over the warning level {level * 1000:.1f} mm "
                        f"({cfg.foot_slip_frac:g} x robot height){more}",
                    )
                )
        k = _first(contacts.foot_floor_min[:K_run] < -cfg.ground_penetration_depth)
        if k is not None:
            deepest = -contacts.foot_floor_min[:K_run].min()
            out.append(
                CheckWarning(
                    "foot_in_floor",
                    float(t[k]),
                    f"a foot is {deepest * 1000:.1f} mm into the floor "
                    f"(over {cfg.ground_penetration_depth * 1000:g} mm): the soft contact gives under "
                    "the load; the sole would press harder on a real floor",
                )
            )
        if s.free:
            w = int(round(cfg.balance_window_s / dt))
            k = _first_sustained(margin[:K_run] < -cfg.balance_margin, w)
            if k is not None:
                worst = -np.nanmin(margin[k : k + w + 1])
                out.append(
                    CheckWarning(
                        "com_outside_support",
                        float(t[k]),
                        f"centre of mass up to {worst * 1000:.0f} mm "
                        f"outside the support polygon for over {cfg.balance_window_s:g} s (held "
                        "still there, the robot would tip)",
                    )
                )
            k = _first_sustained(zmp_margin[:K_run] < cfg.zmp_edge_margin, w)
            if k is not None:
                out.append(
                    CheckWarning(
                        "zmp_near_edge",
                        float(t[k]),
                        f"the measured ZMP (the feet's centre of "
                        f"pressure) within {cfg.zmp_edge_margin * 1000:g} mm of the support polygon's "
                        f"edge for over {cfg.balance_window_s:g} s: a foot is rolling over an edge",
                    )
                )
        return out


def entry_duration(
    q_from: np.ndarray, q_to: np.ndarray, no_load_speed: np.ndarray, speed_frac: float = 0.5, minimum: float = 0.5
) -> float:
    """Duration (s) of the minimum-jerk move from ``q_from`` to ``q_to`` (n,) rad whose fastest
    joint peaks at ``speed_frac`` of its servo's no-load speed (n,) rad/s (unknown, +inf or NaN:
    :data:`UNKNOWN_ENTRY_SPEED`): T = max(minimum, max_j 1.875 |dq_j| / (speed_frac v_j)), 1.875
    being the peak of the profile's speed over the mean."""
    v = np.asarray(no_load_speed, np.float64)
    v = np.where(np.isfinite(v) & (v > 0), v, UNKNOWN_ENTRY_SPEED)
    dq = np.abs(np.asarray(q_to, np.float64) - np.asarray(q_from, np.float64))
    return float(max(minimum, np.max(1.875 * dq / (speed_frac * v), initial=0.0)))


def _tipping_since(k: int, margin: np.ndarray, zmp_margin: np.ndarray, cfg: CheckConfig) -> int:
    """First tick of the run of ticks up to ``k`` in which the robot was going over: its
    measured ZMP at the support polygon's edge, its centre of mass outside the polygon, or no
    support at all."""
    with np.errstate(invalid="ignore"):
        tipping = (zmp_margin[:k] < cfg.zmp_edge_margin) | (margin[:k] < -cfg.balance_margin) | np.isnan(margin[:k])
    calm = np.flatnonzero(~tipping)
    return int(calm[-1] + 1) if len(calm) else 0


def _asked(rec: _Recording) -> np.ndarray:
    """The commands a trajectory asked for: the entry's, then the clip's reference (K, n)."""
    return np.concatenate([rec.q_cmd[: rec.k0], rec.q_ref[rec.k0 :]])


def _yaw(quat) -> float:
    """Heading (rad about +Z) of the x axis of the frame with orientation ``quat`` (wxyz)."""
    w, x, y, z = (float(v) for v in quat)
    return math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def _stance_slides(on: np.ndarray, xy: np.ndarray, gap: int) -> list[tuple[int, int, float, int, np.ndarray]]:
    """One foot's stances: maximal runs of ticks on the floor (K,), off-floor gaps shorter than
    ``gap`` ticks bridged, each as (first tick, end tick (exclusive), slide m, tick of it, the
    distance (e - s,) m at every tick). The slide is the farthest the sole point ``xy`` (K, 2)
    got from where it stood at the stance's first tick: rocking and jitter within a stance do
    not add up, a steady creep does."""
    on = np.asarray(on, bool).copy()
    if gap > 1 and on.any():
        idx = np.flatnonzero(on)
        step = np.diff(idx)
        for i in np.flatnonzero((step > 1) & (step <= gap)):  # fewer than gap off-ticks between two on-ticks
            on[idx[i] : idx[i + 1]] = True
    edges = np.diff(np.concatenate([[0], on.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    out = []
    for s, e in zip(starts, ends):
        dist = np.linalg.norm(xy[s:e] - xy[s], axis=1)
        dist = np.where(np.isfinite(dist), dist, 0.0)
        j = int(np.argmax(dist))
        out.append((int(s), int(e), float(dist[j]), int(s + j), dist))
    return out


def _first_over(stance, level: float) -> int:
    """The tick at which ``stance`` (from :func:`_stance_slides`) first slid beyond ``level`` m."""
    return int(stance[0] + np.argmax(stance[4] > level))


def _normal_forces(adrs: list, dims: list, efcs: list, pyramidal: bool) -> np.ndarray:
    """Normal force (N,) N of every recorded contact, from each tick's contacts' ``efc_address``
    and ``dim`` and that tick's ``efc_force``, as :func:`mujoco.mj_contactForce` decodes it: a
    pyramidal cone's normal force is the sum of its 2 (dim - 1) edge forces, an elliptic cone's
    (or a frictionless contact's) the first row. A contact without constraint rows gets 0."""
    if not adrs:
        return np.zeros(0)
    counts = np.array([len(a) for a in adrs])
    base = np.concatenate([[0], np.cumsum([len(e) for e in efcs])[:-1]])
    adr = np.concatenate(adrs).astype(np.int64)
    dim = np.concatenate(dims).astype(np.int64)
    row0 = adr + np.repeat(base, counts)
    efc = np.concatenate(efcs)
    rows = np.where(dim > 1, 2 * (dim - 1), 1) if pyramidal else np.ones_like(dim)
    out = np.zeros(len(adr))
    active = adr >= 0
    for nr in np.unique(rows[active]):
        sel = active & (rows == nr)
        out[sel] = efc[row0[sel][:, None] + np.arange(nr)].sum(axis=1)
    return out


def _root_pose_series(
    qpos: np.ndarray, free_qpos: int, xpos_now: np.ndarray, xmat_now: np.ndarray, k_run: int
) -> tuple[np.ndarray, np.ndarray]:
    """Root body position (K, 3) and the z-z entry of its rotation matrix (K,) (the
    cosine of the torso tilt) per tick, NaN after ``k_run``.

    A free base reads them from its freejoint's qpos: position p = qpos[a:a+3] and,
    for the quaternion (w, x, y, z) normalised by s = w^2 + x^2 + y^2 + z^2,
    R_zz = (w^2 - x^2 - y^2 + z^2) / s. A fixed base never moves: its current pose
    ``xpos_now`` (3,) / ``xmat_now`` (9,) holds for every tick."""
    K = len(qpos)
    if free_qpos >= 0:
        pos = qpos[:, free_qpos : free_qpos + 3].copy()
        w, x, y, z = qpos[:, free_qpos + 3 : free_qpos + 7].T
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


def _first_sustained_joint(mask: np.ndarray, window: int) -> tuple[int, int] | None:
    """(tick, joint) of the earliest run of ``window`` True ticks in any column of ``mask``
    (K, n); ties go to the lower joint index."""
    firsts = [(_first_sustained(mask[:, j], window), j) for j in range(mask.shape[1])]
    firsts = [(k, j) for k, j in firsts if k is not None]
    return min(firsts) if firsts else None


def _per_joint(names, values) -> dict:
    return {n: (float(v) if np.isfinite(v) else None) for n, v in zip(names, values)}


def _finite(v) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None

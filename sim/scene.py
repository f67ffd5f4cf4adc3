"""The scene: floor, lights, the robot partner and the human figures, compiled once.

A :class:`Scene` owns one ``MjModel``/``MjData`` pair built from the robot's MJCF as published
(found through :mod:`firmware_cfg.registry`): a floor at z = 0 unless the model brings one,
the ``stand`` keyframe, else the profile's ``stand_pose`` or a derived standing pose,
optionally a bolted base, and kinematic figures of the people that exert no forces.
Reference: docs/simulation.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import mujoco
import numpy as np

from dualflow.motion import Motion
from sim.errors import SimError
from sim.human_figure import FaceToFace, HumanFigure, Placement
from sim.robot_facts import robot_facts
from sim.robot_index import RobotIndex, find_feet, geom_z_range, is_contact_geom


def robot_model_path(robot):
    """The MJCF of a robot reference (bundled name, robot folder, MJCF or hardware config)."""
    from firmware_cfg.errors import ConfigError
    from firmware_cfg.registry import resolve

    try:
        return resolve(robot).mjcf
    except ConfigError as exc:
        raise SimError(str(exc)) from None


ROBOT_GROUP = 1
ACTOR_GROUP = 3
REACTOR_GROUP = 4
ROBOT_COLLISION_GROUP = 5


@dataclass(frozen=True)
class SceneConfig:
    """What goes into the scene.

    ``robot``: a bundled robot name or an MJCF path. ``fixed_base``: None keeps the
    model's own choice (bundled fixed-base robots have no freejoint), True bolts the
    root body at ``base_pos`` (m) / ``base_quat`` (wxyz) (a free robot's first-frame pose otherwise:
    a :class:`sim.human_figure.FaceToFace` placement faces it). ``timestep`` s is the
    physics step (default 0.002 s = 500 Hz). ``joint_limits`` (joint -> (lower, upper)
    rad) and ``no_load_speed`` (joint -> rad/s, or one number for every servo) fill in
    what the MJCF does not give (unranged joints, servo speed), before the robot folder's
    profile and hardware config (:mod:`sim.robot_facts`); a joint the MJCF ranges keeps
    its MJCF range.
    """

    robot: str = "op3"
    fixed_base: bool | None = None
    base_pos: tuple[float, float, float] | None = None
    base_quat: tuple[float, float, float, float] | None = None
    timestep: float = 0.002
    actor: Motion | None = None
    actor_placement: Placement | FaceToFace = field(default_factory=Placement)
    reactor: Motion | None = None
    reactor_placement: Placement | FaceToFace = field(default_factory=Placement)
    floor_friction: float = 1.0
    floor_pairs: bool = True  # robot-floor contacts as explicit pairs (same contacts, cheaper: Scene._floor_as_pairs)
    joint_limits: dict | None = None
    no_load_speed: dict | float | None = None


class Scene:
    """The compiled scene. Attributes: ``model``, ``data``, ``robot`` (RobotIndex),
    ``actor`` / ``reactor`` (HumanFigure or None), ``floor_geom`` (id), ``floor_name``,
    ``stand_ctrl`` (n,) the standing pose's servo goals in joint order, ``stand_source``
    ("keyframe", "profile": its ``stand_pose``, or "derived", see the module docstring),
    ``stand_root_height`` (m, root body z when standing), ``robot_height`` (m, top of the robot when standing; exact for
    meshes and primitives), ``floating`` (the MJCF gives the robot a freejoint: it stands on
    its own feet, even where this scene bolts it down; only then are feet looked for, in
    ``robot.feet``), ``facts`` (:class:`sim.robot_facts.RobotFacts`) and ``actor_placement`` /
    ``reactor_placement`` (the :class:`sim.human_figure.Placement` each person got, None without
    that person)."""

    def __init__(self, config: SceneConfig | None = None):
        self.config = config = config or SceneConfig()
        if not (np.isfinite(config.timestep) and 0 < config.timestep <= 0.01):
            raise SimError(f"scene: timestep must be in (0, 0.01] s, got {config.timestep!r}")
        path = robot_model_path(config.robot)
        try:
            spec = mujoco.MjSpec.from_file(str(path))
        except ValueError as exc:
            raise SimError(f"robot model {path}: MuJoCo cannot load it ({exc})") from None
        root = spec.worldbody.first_body()
        if root is None:
            raise SimError(f"robot model {path}: worldbody has no body")
        if not root.name:
            root.name = "robot_root"
        self.root_name = root.name
        free = [j for j in spec.joints if j.type == mujoco.mjtJoint.mjJNT_FREE]
        self.floating = bool(free)
        if config.fixed_base and free:
            spec.delete(free[0])
            for key in spec.keys:
                if len(key.qpos) > 7:
                    key.qpos = list(key.qpos)[7:]
        if config.fixed_base or not free:
            if config.base_pos is not None:
                root.pos = list(config.base_pos)
            if config.base_quat is not None:
                root.quat = list(config.base_quat)
        spec.option.timestep = config.timestep
        # Island discovery pays off with several independent bodies; a scene holds one
        # robot (the human figures are mocap bodies without dofs), so it only costs time
        # (7 % of the instructions of an op3 mj_step). The constraint solution is the same.
        spec.option.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_ISLAND)
        self.floor_name = self._add_world(spec, config, path)

        # robot height and standing figures from a first compile (before the humans)
        try:
            probe = spec.compile()
        except ValueError as exc:
            raise SimError(f"robot model {path}: MuJoCo cannot compile it in the scene ({exc})") from None
        self._check_floor(probe, path)
        if config.floor_pairs:
            self._floor_as_pairs(spec, probe, self.floor_name)
        probe_data = mujoco.MjData(probe)
        self.facts = robot_facts(config.robot, config.joint_limits, config.no_load_speed)
        robot_probe = RobotIndex.from_model(probe, self.root_name, self.facts)
        self.stand_source = (
            "keyframe" if self._stand_key(probe) is not None else "profile" if self.facts.stand_pose else "derived"
        )
        self._stand_qpos, self.stand_ctrl = self._standing_pose(probe, probe_data, robot_probe)
        z = np.array([geom_z_range(probe, probe_data, int(g)) for g in robot_probe.geom_ids]).reshape(-1, 2)
        self.robot_height = float(np.max(z[:, 1]) - 0.0)
        self.stand_root_height = float(probe_data.xpos[robot_probe.root_body, 2])

        self.actor = self.reactor = None
        root_pos = config.base_pos if config.base_pos is not None else probe_data.xpos[robot_probe.root_body]
        root_quat = config.base_quat if config.base_quat is not None else probe_data.xquat[robot_probe.root_body]
        self.actor_placement = self.reactor_placement = None  # as resolved (a FaceToFace becomes a Placement)
        if config.actor is not None:
            self.actor_placement = p = self._placement(config.actor_placement, config.actor, root_pos, root_quat)
            s = p.resolve_scale(config.actor, self.robot_height)
            self.actor = HumanFigure(spec, "actor_", config.actor, s, p, group=ACTOR_GROUP)
        if config.reactor is not None:
            self.reactor_placement = p = self._placement(config.reactor_placement, config.reactor, root_pos, root_quat)
            s = p.resolve_scale(config.reactor, self.robot_height)
            self.reactor = HumanFigure(
                spec, "reactor_", config.reactor, s, p, rgba=(0.2, 0.45, 0.9, 1.0), radius=0.012, group=REACTOR_GROUP
            )
        self.model = spec.compile()
        self.data = mujoco.MjData(self.model)
        self.robot = RobotIndex.from_model(self.model, self.root_name, self.facts)
        self.floor_geom = self.model.geom(self.floor_name).id
        self._robot_groups()
        for fig in (self.actor, self.reactor):
            if fig is not None:
                fig.bind(self.model)
        self.reset()
        if self.floating:
            self.robot = replace(self.robot, feet=find_feet(self.model, self.data, self.robot))

    # -- building ----------------------------------------------------------
    def _placement(self, placement, motion: Motion, root_pos, root_quat) -> Placement:
        """A :class:`FaceToFace` resolved against the robot's first-frame root pose (``base_pos`` /
        ``base_quat``, else the standing pose's); a :class:`Placement` as it is."""
        if isinstance(placement, FaceToFace):
            return placement.resolve(motion, self.robot_height, root_pos, root_quat)
        return placement

    @staticmethod
    def _add_world(spec: mujoco.MjSpec, config: SceneConfig, path) -> str:
        """Add the floor (unless the file has one: see the module docstring) and lights;
        return the floor geom's name."""
        planes = [g for g in spec.worldbody.geoms if g.type == mujoco.mjtGeom.mjGEOM_PLANE]
        if len(planes) > 1:
            planes = [g for g in planes if g.name == "floor"] or planes[:1]
        if planes:
            own = planes[0]
            if not own.name:
                if any(g.name == "floor" for g in spec.geoms):
                    raise SimError(
                        f"robot model {path}: its world plane has no name and another geom is called "
                        "'floor'; name the plane"
                    )
                own.name = "floor"
            spec.visual.global_.offwidth = max(spec.visual.global_.offwidth, 1920)
            spec.visual.global_.offheight = max(spec.visual.global_.offheight, 1080)
            return own.name
        tex = spec.add_texture(
            name="grid",
            type=mujoco.mjtTexture.mjTEXTURE_2D,
            builtin=mujoco.mjtBuiltin.mjBUILTIN_CHECKER,
            rgb1=[0.82, 0.84, 0.86],
            rgb2=[0.72, 0.74, 0.77],
            width=256,
            height=256,
        )
        mat = spec.add_material(name="grid", texrepeat=[8, 8], reflectance=0.05)
        mat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = tex.name
        spec.worldbody.add_geom(
            name="floor",
            type=mujoco.mjtGeom.mjGEOM_PLANE,
            size=[10, 10, 0.05],
            material="grid",
            friction=[config.floor_friction, 0.02, 0.001],
            contype=1,
            conaffinity=1,
        )
        spec.worldbody.add_light(name="key", pos=[1.5, -1.5, 3.0], dir=[-0.45, 0.45, -0.77], diffuse=[0.7, 0.7, 0.7])
        spec.worldbody.add_light(name="fill", pos=[-1.5, 1.0, 2.5], dir=[0.5, -0.3, -0.8], diffuse=[0.35, 0.35, 0.35])
        spec.visual.headlight.ambient = [0.35, 0.35, 0.35]
        spec.visual.global_.offwidth = 1920
        spec.visual.global_.offheight = 1080
        return "floor"

    def _check_floor(self, probe: mujoco.MjModel, path) -> None:
        """The floor must be the z = 0 ground plane the checks assume (DESIGN: ground z = 0)."""
        f = probe.geom(self.floor_name).id
        d = mujoco.MjData(probe)
        mujoco.mj_kinematics(probe, d)
        normal, height = d.geom_xmat[f].reshape(3, 3)[:, 2], d.geom_xpos[f, 2]
        if normal[2] < 1 - 1e-6 or abs(height) > 1e-6:
            raise SimError(
                f"robot model {path}: its floor plane {self.floor_name!r} is not horizontal at z = 0 "
                f"(normal {np.round(normal, 3).tolist()}, z {height:.3f} m); the checks measure from a "
                "level ground at z = 0: move the plane, or load the robot's own MJCF without it"
            )

    def _robot_groups(self) -> None:
        """Robot geoms to group 1; a contact-only geom to group 5 (not drawn) when its body
        also has a geom that only shows, so a published model's collision hulls are not drawn
        over its visual meshes."""
        m, r = self.model, self.robot
        m.geom_group[r.geom_ids] = ROBOT_GROUP
        shows = {int(m.geom_bodyid[g]) for g in r.geom_ids if not is_contact_geom(m, int(g))}
        hide = [int(g) for g in r.geom_ids if is_contact_geom(m, int(g)) and int(m.geom_bodyid[g]) in shows]
        m.geom_group[hide] = ROBOT_COLLISION_GROUP

    @staticmethod
    def _floor_as_pairs(spec: mujoco.MjSpec, probe: mujoco.MjModel, floor: str = "floor") -> None:
        """Robot-floor contacts as explicit ``<pair>``s, the floor left out of the broad phase.

        The floor is an infinite plane, so every robot body overlaps it in MuJoCo's
        sweep-and-prune and every (floor, geom) pair reaches the narrow phase anyway;
        listing those pairs explicitly skips the floor's broad-phase work: 2.4 % fewer
        instructions per op3 mj_step (callgrind, 10 s bench clip), the same contacts.
        A pair gets the parameters MuJoCo's dynamic mixing would give (equal priority:
        condim and friction the maximum, margin and gap the maximum, solref / solimp
        averaged with weight solmix1 / (solmix1 + solmix2)); it is made only for geoms the
        dynamic filter would collide with the floor (contype/conaffinity bits, not welded
        to the world, not excluded). When a robot geom needs a rule not written here (a
        priority other than the floor's, direct solref, adhesion, surface velocity, a
        plugin) or has no name (a pair names its geoms), the floor stays dynamic."""
        m, f = probe, probe.geom(floor).id
        touches_world = {int(s_) & 0xFFFF for s_ in m.exclude_signature if int(s_) >> 16 == 0}
        touches_world |= {int(s_) >> 16 for s_ in m.exclude_signature if int(s_) & 0xFFFF == 0}
        g = np.flatnonzero(
            (np.arange(m.ngeom) != f)
            & (m.body_weldid[m.geom_bodyid] != 0)
            & ((m.geom_contype & m.geom_conaffinity[f]) | (m.geom_contype[f] & m.geom_conaffinity) != 0)
            & ~np.isin(m.geom_bodyid, list(touches_world))
        )
        both = np.append(g, f)
        names = [m.geom(int(i)).name for i in g]
        if (
            np.any(m.geom_priority[g] != m.geom_priority[f])
            or np.any(m.geom_solref[both, 0] <= 0)
            or np.any(m.geom_adhesion[both])
            or np.any(m.geom_surfacevel[both])
            or np.any(m.geom_plugin[both] != -1)
            or not all(names)
        ):
            return
        s1, s2 = m.geom_solmix[f], m.geom_solmix[g]
        mix = np.where(s1 + s2 < mujoco.mjMINVAL, 0.5, s1 / np.maximum(s1 + s2, mujoco.mjMINVAL))[:, None]
        fr = np.maximum(m.geom_friction[f], m.geom_friction[g])
        solref = mix * m.geom_solref[f] + (1 - mix) * m.geom_solref[g]
        solimp = mix * m.geom_solimp[f] + (1 - mix) * m.geom_solimp[g]
        condim = np.maximum(m.geom_condim[f], m.geom_condim[g])
        margin, gap = np.maximum(m.geom_margin[f], m.geom_margin[g]), np.maximum(m.geom_gap[f], m.geom_gap[g])
        for i, name in enumerate(names):
            spec.add_pair(
                geomname1=floor,
                geomname2=name,
                condim=int(condim[i]),
                friction=[fr[i, 0], fr[i, 0], fr[i, 1], fr[i, 2], fr[i, 2]],
                solref=solref[i].tolist(),
                solimp=solimp[i].tolist(),
                margin=float(margin[i]),
                gap=float(gap[i]),
            )
        floor_spec = spec.geom(floor)
        floor_spec.contype = floor_spec.conaffinity = 0

    @staticmethod
    def _stand_key(model: mujoco.MjModel) -> int | None:
        try:
            return model.key("stand").id
        except KeyError:
            return None

    def _standing_pose(self, model: mujoco.MjModel, data: mujoco.MjData, robot: RobotIndex):
        """(qpos (nq,), servo goals (n,)) of the standing pose (module docstring), and ``data``
        left in it."""
        mujoco.mj_resetData(model, data)
        key = self._stand_key(model)
        if key is not None:
            mujoco.mj_resetDataKeyframe(model, data, key)
            mujoco.mj_forward(model, data)
            return data.qpos.copy(), model.key_ctrl[key, robot.actuator_ids].copy()
        for name, angle in self.facts.stand_pose.items():  # the profile's standing pose (robot init)
            j = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
            if j >= 0:
                data.qpos[model.jnt_qposadr[j]] = angle
        q = np.clip(data.qpos[robot.qpos_adr], robot.lower, robot.upper)
        data.qpos[robot.qpos_adr] = q
        mujoco.mj_forward(model, data)
        low = self._lowest_point(model, data, robot)
        if not robot.fixed_base and np.isfinite(low):
            data.qpos[robot.free_qpos + 2] -= low
            mujoco.mj_forward(model, data)
        return data.qpos.copy(), q.copy()

    def _reset_to_stand(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        mujoco.mj_resetData(model, data)
        key = self._stand_key(model)
        if key is not None:
            mujoco.mj_resetDataKeyframe(model, data, key)
        else:
            data.qpos[:] = self._stand_qpos
            data.ctrl[self.robot.actuator_ids] = self.stand_ctrl
        mujoco.mj_forward(model, data)

    # -- state -------------------------------------------------------------
    def reset(self) -> None:
        """Robot in its standing pose (the "stand" keyframe or the derived one), humans at their first frame."""
        self._reset_to_stand(self.model, self.data)
        self.pose_humans(0.0)
        mujoco.mj_forward(self.model, self.data)

    def pose_humans(self, t: float) -> None:
        for fig in (self.actor, self.reactor):
            if fig is not None:
                fig.pose_at(self.data, t)

    def set_robot_pose(self, joint_pos, root_pos=None, root_quat=None, ground: bool = False) -> None:
        """Set joints (n,) rad in joint order and, for a free base, the root pose;
        ``ground`` shifts the root vertically so the lowest robot geom touches z = 0.
        Velocities are zeroed and the actuators' goals set to ``joint_pos``."""
        r = self.robot
        q = np.asarray(joint_pos, dtype=np.float64)
        self.data.qpos[r.qpos_adr] = q
        self.data.qvel[:] = 0.0
        self.data.ctrl[r.actuator_ids] = q
        if not r.fixed_base:
            if root_pos is not None:
                self.data.qpos[r.free_qpos : r.free_qpos + 3] = root_pos
            if root_quat is not None:
                self.data.qpos[r.free_qpos + 3 : r.free_qpos + 7] = root_quat
        mujoco.mj_forward(self.model, self.data)
        if ground and not r.fixed_base and np.isfinite(low := self.lowest_robot_point()):
            self.data.qpos[r.free_qpos + 2] -= low
            mujoco.mj_forward(self.model, self.data)

    def mujoco_forward(self) -> None:
        """Recompute positions after setting qpos or mocap poses by hand."""
        mujoco.mj_forward(self.model, self.data)

    def lowest_robot_point(self) -> float:
        """z (m) of the lowest point of any robot contact geom (exact for primitives and
        meshes: :func:`sim.robot_index.geom_z_range`)."""
        return self._lowest_point(self.model, self.data, self.robot)

    @staticmethod
    def _lowest_point(model: mujoco.MjModel, data: mujoco.MjData, robot: RobotIndex) -> float:
        z = [geom_z_range(model, data, int(g))[0] for g in robot.geom_ids if is_contact_geom(model, int(g))]
        return float(min(z)) if z else float("nan")

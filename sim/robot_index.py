"""Where a robot's joints, actuators, bodies and feet live inside a compiled MuJoCo model.

MuJoCo orders qpos by the body tree; a robot's joint order is its ACTUATOR order
(see :mod:`firmware_cfg.registry`). :class:`RobotIndex` maps between the two once, so the
rest of ``sim`` works with arrays of shape (n,) in joint order.

It reads a model as published, with no naming conventions of ours:

- joint limits: the MJCF ``range``; for an unranged joint (MuJoCo stores [0, 0] and does not
  limit it) the limits known from elsewhere (:mod:`sim.robot_facts`: given, the retarget
  profile, the hardware config), else the actuator's ``ctrlrange`` (the servo clips its goal
  there), else none: ±inf, and the joint is listed as unchecked;
- force limits: the actuator's ``forcerange`` and the joint's ``actuatorfrcrange`` (as the
  G1 declares them), the tighter of the two, in joint torque (N m; ``gear`` applied);
- servo no-load speed: the MJCF's ``<custom><numeric name="servo_no_load_speed">`` (one
  value, or one per actuator), else the hardware config's servo model, else none;
- feet: :func:`find_feet`, from the contact geoms of the lowest bodies in a standing pose.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import mujoco
import numpy as np

from sim.errors import SimError


@dataclass(frozen=True)
class Foot:
    """One foot. ``body`` is the top body of the foot (the leg's lowest body with contact
    geoms, or the nearest common ancestor of its lowest ones: an ankle above a toe);
    ``bodies`` are that body and the bodies below it that have contact geoms (all may touch
    the floor without it counting as a fall); ``sole_point`` (3,) m, in ``body``'s frame, is
    the middle of the foot's contact geoms at its lowest point in the standing pose (the
    point whose sliding is measured as foot slip)."""

    side: str  # "left" | "right"
    body: int
    bodies: tuple[int, ...]
    sole_point: np.ndarray


@dataclass(frozen=True)
class RobotIndex:
    """Indices and servo figures of one robot in a compiled model.

    Arrays are (n,) in actuator (= joint) order. ``free_qpos`` is the qpos address of the
    root freejoint, or -1 for a fixed base. ``lower``/``upper`` rad are the joint limits
    the check judges commands against (±inf where none is known), ``limit_source`` says
    where each came from ("mjcf", "given", "profile", "hardware", "ctrlrange" or "" for
    none). ``stall_torque`` (n,) N m is each joint's force limit (+inf where none),
    ``torque_lower``/``torque_upper`` (n,) the joint-side clamp MuJoCo applies
    (``actuatorfrcrange``, ±inf when none), ``gear`` (n,) the actuators' gear,
    ``joint_ids`` (n,) the MuJoCo joint ids.
    ``no_load_speed`` (n,) rad/s is +inf where unknown; ``speed_source`` as
    ``limit_source`` ("mjcf", "given", "hardware" or ""). ``feet`` is filled by the scene
    (:func:`find_feet`)."""

    joint_names: tuple[str, ...]
    qpos_adr: np.ndarray
    dof_adr: np.ndarray
    actuator_ids: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    stall_torque: np.ndarray
    no_load_speed: np.ndarray
    root_body: int
    free_qpos: int
    free_dof: int
    body_ids: np.ndarray
    geom_ids: np.ndarray
    limit_source: tuple[str, ...] = ()
    speed_source: tuple[str, ...] = ()
    gear: np.ndarray = field(default_factory=lambda: np.ones(0))
    torque_lower: np.ndarray = field(default_factory=lambda: np.zeros(0))
    torque_upper: np.ndarray = field(default_factory=lambda: np.zeros(0))
    joint_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    feet: tuple[Foot, ...] = ()

    @property
    def n(self) -> int:
        return len(self.joint_names)

    @property
    def fixed_base(self) -> bool:
        return self.free_qpos < 0

    @property
    def foot_bodies(self) -> tuple[int, ...]:
        """Every body of every foot."""
        return tuple(b for f in self.feet for b in f.bodies)

    def unchecked(self, what: str) -> tuple[str, ...]:
        """Joints for which ``what`` ("joint_limit", "speed_limit", "torque_saturation")
        cannot be judged for lack of data."""
        if what == "joint_limit":
            bad = ~(np.isfinite(self.lower) & np.isfinite(self.upper))
        elif what == "speed_limit":
            bad = ~np.isfinite(self.no_load_speed)
        elif what == "torque_saturation":
            bad = ~np.isfinite(self.stall_torque)
        else:
            raise ValueError(what)
        return tuple(j for j, b in zip(self.joint_names, bad) if b)

    @classmethod
    def from_model(cls, model: mujoco.MjModel, root_body: str, facts=None) -> RobotIndex:
        """Index the robot under body ``root_body``; ``facts`` (:class:`sim.robot_facts.RobotFacts`,
        optional) fills in limits and speeds the MJCF does not give."""
        try:
            root = model.body(root_body).id
        except KeyError:
            raise SimError(f"robot model: no body named {root_body!r}") from None
        names, qadr, dadr, acts, jids = [], [], [], [], []
        for a in range(model.nu):
            if model.actuator_trntype[a] != mujoco.mjtTrn.mjTRN_JOINT:
                continue
            j = int(model.actuator_trnid[a, 0])
            if model.jnt_type[j] != mujoco.mjtJoint.mjJNT_HINGE:
                raise SimError(f"robot model: actuator {model.actuator(a).name!r} drives a non-hinge joint")
            names.append(model.joint(j).name)
            qadr.append(model.jnt_qposadr[j])
            dadr.append(model.jnt_dofadr[j])
            acts.append(a)
            jids.append(j)
        if not names:
            raise SimError("robot model: no joint actuators; each joint needs a <position> actuator")
        acts_a, jids_a = np.array(acts), np.array(jids)
        lo, hi, lsrc = _joint_limits(model, names, acts_a, jids_a, facts)
        gear = model.actuator_gear[acts_a, 0].copy()
        stall, tlo, thi = _force_limits(model, acts_a, jids_a, gear)
        speed, ssrc = _speeds(model, names, facts)
        free_q = free_d = -1
        for j in range(model.njnt):
            if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE and model.jnt_bodyid[j] == root:
                free_q, free_d = int(model.jnt_qposadr[j]), int(model.jnt_dofadr[j])
        bodies = [b for b in range(model.nbody) if _in_subtree(model, b, root)]
        geoms = np.flatnonzero(np.isin(model.geom_bodyid, bodies))
        index = cls(
            tuple(names),
            np.array(qadr),
            np.array(dadr),
            acts_a,
            lo,
            hi,
            stall,
            speed,
            root,
            free_q,
            free_d,
            np.array(bodies),
            geoms,
            lsrc,
            ssrc,
            gear,
            tlo,
            thi,
            jids_a,
        )
        return index

    def joint_positions(self, data: mujoco.MjData) -> np.ndarray:
        return data.qpos[self.qpos_adr].copy()

    def joint_velocities(self, data: mujoco.MjData) -> np.ndarray:
        return data.qvel[self.dof_adr].copy()

    def joint_torques(self, actuator_force: np.ndarray) -> np.ndarray:
        """Torque (..., n) N m the joints get from actuator forces (..., nu): times the gear,
        clamped to the joints' ``actuatorfrcrange`` as MuJoCo does."""
        return np.clip(actuator_force[..., self.actuator_ids] * self.gear, self.torque_lower, self.torque_upper)


def _joint_limits(model, names, acts, jids, facts):
    lo = np.full(len(names), -np.inf)
    hi = np.full(len(names), np.inf)
    src = [""] * len(names)
    known = facts.joint_limits if facts is not None else {}
    known_src = facts.limit_source if facts is not None else {}
    for i, (name, a, j) in enumerate(zip(names, acts, jids)):
        if model.jnt_limited[j]:
            lo[i], hi[i], src[i] = model.jnt_range[j, 0], model.jnt_range[j, 1], "mjcf"
        elif name in known:
            (lo[i], hi[i]), src[i] = known[name], known_src.get(name, "given")
        elif model.actuator_ctrllimited[a]:
            lo[i], hi[i], src[i] = model.actuator_ctrlrange[a, 0], model.actuator_ctrlrange[a, 1], "ctrlrange"
    return lo, hi, tuple(src)


def _force_limits(model, acts, jids, gear):
    """Stall torque (n,) N m: the smaller of the actuator's |forcerange| x |gear| and the
    joint's |actuatorfrcrange| (each the smaller magnitude of its two bounds), +inf when
    neither is set; and the joint-side clamp (n,), (n,)."""
    stall = np.full(len(acts), np.inf)
    af = model.actuator_forcelimited[acts].astype(bool)
    a_mag = np.minimum(-model.actuator_forcerange[acts, 0], model.actuator_forcerange[acts, 1]) * np.abs(gear)
    stall[af] = a_mag[af]
    jf = model.jnt_actfrclimited[jids].astype(bool)
    j_mag = np.minimum(-model.jnt_actfrcrange[jids, 0], model.jnt_actfrcrange[jids, 1])
    stall[jf] = np.minimum(stall[jf], j_mag[jf])
    tlo = np.where(jf, model.jnt_actfrcrange[jids, 0], -np.inf)
    thi = np.where(jf, model.jnt_actfrcrange[jids, 1], np.inf)
    return stall, tlo, thi


def _speeds(model, names, facts):
    n = len(names)
    speed = _numeric(model, "servo_no_load_speed", n)
    src = ["mjcf" if np.isfinite(s) else "" for s in speed]
    if facts is not None:
        for i, name in enumerate(names):
            if src[i]:
                continue
            key = name if name in facts.no_load_speed else "*" if "*" in facts.no_load_speed else None
            if key is not None:
                speed[i], src[i] = facts.no_load_speed[key], facts.speed_source[key]
    return speed, tuple(src)


def _in_subtree(model: mujoco.MjModel, body: int, root: int) -> bool:
    while body > 0:
        if body == root:
            return True
        body = int(model.body_parentid[body])
    return False


def _numeric(model: mujoco.MjModel, name: str, n: int) -> np.ndarray:
    """(n,) values of a custom numeric holding 1 or n numbers; +inf when absent."""
    try:
        data = np.asarray(model.numeric(name).data, dtype=np.float64)
    except KeyError:
        return np.full(n, np.inf)
    if data.size == 1:
        return np.full(n, float(data[0]))
    if data.size != n:
        raise SimError(f"robot model: custom numeric {name!r} has {data.size} values; give 1 or {n} (one per actuator)")
    return data.copy()


# -- names ----------------------------------------------------------------------------
def body_label(model: mujoco.MjModel, body: int) -> str:
    """A body's name, or ``body <id>`` when it has none."""
    name = model.body(int(body)).name
    return name if name else f"body {int(body)}"


def geom_label(model: mujoco.MjModel, geom: int) -> str:
    """A geom's name, or, for an unnamed one, ``geom <k> of <body>`` (k counts the body's
    geoms from 0 in MJCF order), e.g. ``geom 1 of l_knee_link``."""
    g = int(geom)
    name = model.geom(g).name
    if name:
        return name
    b = int(model.geom_bodyid[g])
    return f"geom {g - int(model.body_geomadr[b])} of {body_label(model, b)}"


# -- geometry -------------------------------------------------------------------------
def is_contact_geom(model: mujoco.MjModel, g: int) -> bool:
    return bool(model.geom_contype[g] or model.geom_conaffinity[g])


def geom_z_range(model: mujoco.MjModel, data: mujoco.MjData, g: int) -> tuple[float, float]:
    """Lowest and highest world z (m) of geom ``g`` in ``data``'s pose: exact for boxes,
    spheres, capsules, cylinders, ellipsoids and meshes (their vertices, which bound the
    convex hull MuJoCo collides); the bounding sphere for anything else."""
    t, size = model.geom_type[g], model.geom_size[g]
    c, R = data.geom_xpos[g], data.geom_xmat[g].reshape(3, 3)
    rz = R[2]  # world z of the geom's local axes
    if t == mujoco.mjtGeom.mjGEOM_MESH and model.geom_dataid[g] >= 0:
        m = int(model.geom_dataid[g])
        adr, nv = int(model.mesh_vertadr[m]), int(model.mesh_vertnum[m])
        z = model.mesh_vert[adr : adr + nv] @ rz
        return float(c[2] + z.min()), float(c[2] + z.max())
    if t == mujoco.mjtGeom.mjGEOM_BOX:
        h = np.abs(rz) @ size
    elif t == mujoco.mjtGeom.mjGEOM_CAPSULE:
        h = abs(rz[2]) * size[1] + size[0]
    elif t == mujoco.mjtGeom.mjGEOM_SPHERE:
        h = size[0]
    elif t == mujoco.mjtGeom.mjGEOM_CYLINDER:
        h = abs(rz[2]) * size[1] + np.hypot(rz[0], rz[1]) * size[0]
    elif t == mujoco.mjtGeom.mjGEOM_ELLIPSOID:
        h = np.linalg.norm(rz * size)
    else:
        h = model.geom_rbound[g]
    return float(c[2] - h), float(c[2] + h)


# -- feet -----------------------------------------------------------------------------
def find_feet(model: mujoco.MjModel, data: mujoco.MjData, index: RobotIndex) -> tuple[Foot, ...]:
    """The robot's feet, from the contact geoms of its lowest bodies in ``data``'s pose
    (the standing pose): no site or body names are needed.

    Each robot body with contact geoms (contype or conaffinity set) goes to the left
    (y > 0) or the right (y < 0) side by its position in the root body's frame (x forward,
    y left, as humanoid models are written). On each side, the bodies whose lowest contact
    point lies within ``tol`` = max(2 mm, 0.4 % of the robot's height) of that side's lowest
    are the sole; the foot is their nearest common ancestor with everything below it that
    has contact geoms (so an ankle with a toe link is one foot). A side without contact
    geoms has no foot. Returns (left, right), either possibly missing."""
    col = [int(g) for g in index.geom_ids if is_contact_geom(model, int(g))]
    if not col:
        return ()
    low: dict[int, float] = {}
    for g in col:
        b = int(model.geom_bodyid[g])
        low[b] = min(low.get(b, np.inf), geom_z_range(model, data, g)[0])
    tops = [geom_z_range(model, data, int(g))[1] for g in index.geom_ids]
    height = max(tops) - min(low.values())
    tol = max(0.002, 0.004 * height)
    R0, p0 = data.xmat[index.root_body].reshape(3, 3), data.xpos[index.root_body]
    feet = []
    for side, sign in (("left", 1.0), ("right", -1.0)):
        mine = [b for b in low if b != index.root_body and sign * (R0.T @ (data.xpos[b] - p0))[1] > 1e-6]
        if not mine:
            continue
        z0 = min(low[b] for b in mine)
        sole = [b for b in mine if low[b] <= z0 + tol]
        top = _common_ancestor(model, sole)
        if top == index.root_body or top == 0:
            top = min(sole, key=lambda b: low[b])  # the soles share no leg: take the lowest body alone
        bodies = tuple(b for b in sorted(low) if _in_subtree(model, b, top))
        geoms = [g for g in col if int(model.geom_bodyid[g]) in bodies]
        xy = np.mean(data.geom_xpos[geoms, :2], axis=0)
        point = np.array([xy[0], xy[1], min(low[b] for b in bodies)])
        local = data.xmat[top].reshape(3, 3).T @ (point - data.xpos[top])
        feet.append(Foot(side, int(top), bodies, local))
    return tuple(feet)


def _common_ancestor(model: mujoco.MjModel, bodies) -> int:
    def chain(b):
        out = [int(b)]
        while out[-1] > 0:
            out.append(int(model.body_parentid[out[-1]]))
        return out

    chains = [chain(b) for b in bodies]
    common = set(chains[0]).intersection(*map(set, chains[1:]))
    return next(b for b in chains[0] if b in common)

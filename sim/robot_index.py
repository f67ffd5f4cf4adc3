"""Where a robot's joints, actuators and bodies live inside a compiled MuJoCo model.

MuJoCo orders qpos by the body tree; a robot's joint order is its ACTUATOR order
(see :mod:`sim.robots`). :class:`RobotIndex` maps between the two once, so the
rest of ``sim`` works with arrays of shape (n,) in joint order.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from sim.errors import SimError


@dataclass(frozen=True)
class RobotIndex:
    """Indices and servo figures of one robot in a compiled model.

    Arrays are (n,) in actuator (= joint) order. ``free_qpos`` is the qpos address
    of the root freejoint, or -1 for a fixed base. ``stall_torque`` (n,) N m is each
    actuator's force limit; ``no_load_speed`` (n,) rad/s comes from the MJCF's
    ``<custom>`` numeric ``servo_no_load_speed`` (one value for all joints, or one
    per actuator in actuator order).
    """

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
    foot_sites: tuple[int, ...]

    @property
    def n(self) -> int:
        return len(self.joint_names)

    @property
    def fixed_base(self) -> bool:
        return self.free_qpos < 0

    @classmethod
    def from_model(cls, model: mujoco.MjModel, root_body: str) -> "RobotIndex":
        try:
            root = model.body(root_body).id
        except KeyError:
            raise SimError(f"robot model: no body named {root_body!r}") from None
        names, qadr, dadr, acts, lo, hi = [], [], [], [], [], []
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
            lo.append(model.jnt_range[j, 0])
            hi.append(model.jnt_range[j, 1])
        if not names:
            raise SimError("robot model: no joint actuators; each joint needs a <position> actuator")
        free_q = free_d = -1
        for j in range(model.njnt):
            if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE and model.jnt_bodyid[j] == root:
                free_q, free_d = int(model.jnt_qposadr[j]), int(model.jnt_dofadr[j])
        bodies = [b for b in range(model.nbody) if _in_subtree(model, b, root)]
        geoms = np.flatnonzero(np.isin(model.geom_bodyid, bodies))
        feet = tuple(model.site(n).id for n in ("l_foot", "r_foot") if _has_site(model, n))
        stall = np.where(model.actuator_forcelimited[acts].astype(bool), model.actuator_forcerange[acts, 1], np.inf)
        speed = _numeric(model, "servo_no_load_speed", len(acts))
        return cls(tuple(names), np.array(qadr), np.array(dadr), np.array(acts), np.array(lo), np.array(hi),
                   stall, speed, root, free_q, free_d, np.array(bodies), geoms, feet)

    def joint_positions(self, data: mujoco.MjData) -> np.ndarray:
        return data.qpos[self.qpos_adr].copy()

    def joint_velocities(self, data: mujoco.MjData) -> np.ndarray:
        return data.qvel[self.dof_adr].copy()


def _in_subtree(model: mujoco.MjModel, body: int, root: int) -> bool:
    while body > 0:
        if body == root:
            return True
        body = int(model.body_parentid[body])
    return False


def _has_site(model: mujoco.MjModel, name: str) -> bool:
    try:
        model.site(name)
        return True
    except KeyError:
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

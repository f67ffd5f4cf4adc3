"""How fast each joint's servo can speed its links up: the acceleration limit that the
retargeter plans within and the bridge's safety filter enforces (one number for both).

A servo that gives at most torque tau_max to a joint whose links have inertia I about its axis
(the joint-space mass matrix's diagonal, the gear's reflected rotor inertia, MuJoCo's
``armature``, included) cannot speed them up faster than tau_max / I. The inertia is taken in
the model's zero pose (``qpos0``), where most robots stand with straight legs and straight
arms, about the most inertia each joint ever moves. A plan that asks for more is not tracked
by the servo, and a safety filter set below it sends commands that lag the plan: on the op3,
streamed steps with the filter at the old flat 80 rad/s² left a swing leg 0.26 rad behind at the
hip and the feet collided. The limit is never below :data:`DEFAULT_ACCELERATION`
(:func:`acceleration_limits`).
"""

from __future__ import annotations

import numpy as np

#: Acceleration limit (rad/s²) of a joint whose actuator's torque the model does not limit:
#: about what brisk human arm motion scaled to a 0.5 m robot asks for.
DEFAULT_ACCELERATION = 80.0


def stall_accelerations(model) -> dict[str, float]:
    """{joint name: tau_max / I (rad/s²)} for each hinge or slide joint that an actuator with a
    torque limit (its ``forcerange`` x its ``gear``, else the joint's ``actuatorfrcrange``)
    drives, with I the joint's diagonal of the mass matrix in the zero pose. ``model`` a
    ``mujoco.MjModel``."""
    import mujoco

    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    inertia = np.zeros((model.nv, model.nv))
    try:
        mujoco.mj_fullM(model, data, inertia)  # MuJoCo 4
    except TypeError:  # MuJoCo 3: (model, dst, qM)
        mujoco.mj_fullM(model, inertia, data.qM)
    out = {}
    for a in range(model.nu):
        if int(model.actuator_trntype[a]) != int(mujoco.mjtTrn.mjTRN_JOINT):
            continue
        j = int(model.actuator_trnid[a, 0])
        if int(model.jnt_type[j]) not in (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)):
            continue
        if model.actuator_forcelimited[a]:  # the actuator's force, times its gear at the joint
            tau = float(np.max(np.abs(model.actuator_forcerange[a]))) * abs(float(model.actuator_gear[a, 0]))
        elif model.jnt_actfrclimited[j]:  # the joint's own limit on the actuators' total torque
            tau = float(np.max(np.abs(model.jnt_actfrcrange[j])))
        else:
            continue
        dof = int(model.jnt_dofadr[j])
        if tau > 0 and inertia[dof, dof] > 0:
            name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j)
            out[name] = min(out.get(name, np.inf), tau / float(inertia[dof, dof]))
    return out


def acceleration_limits(model, joint_names) -> np.ndarray:
    """(n,) rad/s² for ``joint_names``: :func:`stall_accelerations`, never below
    :data:`DEFAULT_ACCELERATION` (a servo that cannot give its links that much at stall, such
    as the ub14's waist and shoulders at 16-41 rad/s², still follows a person's motion, late,
    as it did under the bridge's flat 80 rad/s²: a filter at its stall figure made CMU 19_01's
    arm lag into the ub14's body), the default where the model limits no torque."""
    stall = stall_accelerations(model)
    return np.array([max(stall.get(n, 0.0), DEFAULT_ACCELERATION) for n in joint_names], dtype=float)

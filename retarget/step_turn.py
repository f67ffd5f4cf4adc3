"""How far a step may turn one foot against the other: the robot's own legs decide.

Contract: :func:`step_turn_limits` returns (toe_out, toe_in) in rad, the largest heading of a
landing foot relative to the stance foot, turned away from it (toes out) and towards it (toes
in), that the robot's legs allow standing: each leg's yaw hinge (the hinge between the root and
the foot whose axis is nearest vertical in the stand pose, the hip yaw of a humanoid) turns its
leg by half the relative heading, and every profile capsule pair off the feet (the feet are
kept apart by the step's placement, :meth:`retarget.balance.BalancePlanner._clamp_step`) must
stay clear, with the profile's collision margin, or as clear as it stands. Both are capped at
``cap`` (the configured ``max_step_turn``) and by the yaw hinges' limits around the stand pose.

Why: a step planned to land further turned than the legs allow gives the solver a target it can
reach only by leaning the trunk. Measured on op3 when its hip-servo blocks were one bounding
capsule each (toes out to 0.19 rad; the boxes allow 0.57): a generated partner whose steps
landed toed out by up to 0.6 rad leaned its trunk 30° back for a second and fell (streamed,
3.45 s). With the profile's face rows for the blocks the limits are 0.45 rad out, 0.6 in.
"""

from __future__ import annotations

import numpy as np

#: a hinge whose axis is within this angle of vertical (stand pose) counts as a leg's yaw
_VERTICAL = np.cos(np.deg2rad(30.0))
#: the relative headings tried, in steps of this (rad)
_RESOLUTION = 0.01


def leg_yaw_joints(robot) -> list[tuple[int, float]] | None:
    """Per foot (left, right), (index into x, sign): the yaw hinge closest to the root on the
    chain from the root to the foot, and +1 or -1 so that +angle turns the foot counter-clockwise
    seen from above (stand pose). None without two feet or when a leg has no such hinge."""
    import mujoco

    kin = robot.kin
    if len(robot.feet) != 2 or not kin.floating:
        return None
    m = kin.model
    d = mujoco.MjData(m)
    d.qpos[:] = kin.qpos_from_x(np.asarray(robot.x_stand, float).ravel())
    mujoco.mj_kinematics(m, d)
    out = []
    for foot in robot.feet:
        found = None
        body = foot.body
        while body != kin.root_body and body > 0:
            for j in range(m.njnt):
                if m.jnt_bodyid[j] == body and m.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE:
                    z = float(d.xaxis[j][2])
                    if abs(z) >= _VERTICAL:
                        name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j)
                        found = (kin.n_root + kin.joint_names.index(name), 1.0 if z > 0 else -1.0)
            body = int(m.body_parentid[body])
        if found is None:
            return None
        out.append(found)
    return out


def step_turn_limits(robot, cap: float, reserve: float = 0.0) -> tuple[float, float]:
    """(toe_out, toe_in) rad, each in [0, cap]: see the module docstring; each pair keeps
    ``reserve`` m more than its margin (room for the rest of the body to move with the feet
    planted). ``cap`` for both when the robot has no leg yaw hinges or no capsule pairs off its feet."""
    joints = leg_yaw_joints(robot)
    foot_bodies = {f.body for f in robot.feet}
    rows = [
        k
        for k, (a, b) in enumerate(robot.collision_pairs)
        if robot.capsules[a].body not in foot_bodies and robot.capsules[b].body not in foot_bodies
    ]
    if joints is None:
        return cap, cap
    x0 = np.asarray(robot.x_stand, float).ravel()
    turns = np.arange(_RESOLUTION, cap + 0.5 * _RESOLUTION, _RESOLUTION)
    # a row is d² − r² (r: the radii and the margin); keeping d ≥ r + reserve is row ≥ 2·r·reserve + reserve²
    r = np.array([robot.capsules[a].radius + robot.capsules[b].radius for a, b in robot.collision_pairs])[rows]
    r = r + robot.profile.collision_margin
    need = 2 * r * reserve + reserve**2
    standing = robot.evaluate(x0[None])["collision"][0, rows]
    floor = np.minimum(standing, need)
    limits = []
    for toes_in in (False, True):
        # the left foot's heading minus the right's: positive is toes out
        rel = -turns if toes_in else turns
        X = np.repeat(x0[None], len(turns), axis=0)
        (jl, sl), (jr, sr) = joints
        X[:, jl] += sl * rel / 2
        X[:, jr] -= sr * rel / 2
        inside = np.all((X >= robot.x_lower) & (X <= robot.x_upper), axis=1)
        clear = np.all(robot.evaluate(X)["collision"][:, rows] >= floor, axis=1) if rows else np.ones(len(turns), bool)
        ok = inside & clear
        bad = np.flatnonzero(~ok)
        limits.append(float(turns[bad[0] - 1]) if len(bad) and bad[0] > 0 else (0.0 if len(bad) else cap))
    return limits[0], limits[1]

"""How far a step may turn one foot against the other: the robot's own legs decide.

Contract: :func:`step_turn_limits` returns (toe_out, toe_in) in rad, the largest heading of a
landing foot relative to the stance foot, turned away from it (toes out) and towards it (toes
in), that the robot's legs allow standing. Each leg's yaw hinge (:func:`leg_yaw_joints`; the
hip yaw of a humanoid) turns its leg by half the relative heading in the stand pose, and every
profile capsule pair off the feet must stay clear by the profile's collision margin plus the
given clearance, or stay at least as clear as it stands. (The feet themselves are kept apart by
the step's placement, :meth:`retarget.balance.BalancePlanner._clamp_step`.) Both limits are at
most ``cap`` (the configured ``max_step_turn``) and within the yaw hinges' joint limits.

Why: a step planned to land further turned than the legs allow gives the solver a target it can
reach only by leaning the trunk. Measured on op3 when its hip-servo blocks were one bounding
capsule each (toes out to 0.19 rad; the boxes allow 0.57): a generated partner whose steps
landed toed out by up to 0.6 rad leaned its trunk 30° back for a second and fell (streamed,
3.45 s). With the profile's face rows for the blocks the limits are 0.45 rad out, 0.6 in.
The limits assume the turn is shared evenly by the two hips; the body turned over the planted
feet (``body_twist``) shares it otherwise, and the solver's capsule rows hold what is left.
"""

from __future__ import annotations

import numpy as np

#: a hinge whose axis is within this angle of vertical (stand pose) counts as a leg's yaw
_VERTICAL = np.cos(np.deg2rad(30.0))
#: the relative headings tried, in steps of this (rad)
_RESOLUTION = 0.01


def _chain(m, body: int, root: int) -> list[int]:
    """Bodies from ``body`` up to (not including) ``root``."""
    out = []
    while body != root and body > 0:
        out.append(body)
        body = int(m.body_parentid[body])
    return out


def leg_bodies(robot) -> set[int]:
    """The bodies of the robot's legs: each foot's body and its parents below the root body."""
    return {b for foot in robot.feet for b in _chain(robot.kin.model, foot.body, robot.kin.root_body)}


def leg_yaw_joints(robot) -> list[tuple[int, float]] | None:
    """Per foot (left, right), (index into x, sign): the hinge closest to the root among those on
    the chain from the root to that foot, not on the other foot's chain (a waist turns both
    legs), whose axis is within 30° of vertical in the stand pose; the sign makes +angle turn the
    foot counter-clockwise seen from above. None for a fixed-base robot, without two feet, or
    when a leg has no such hinge."""
    import mujoco

    kin = robot.kin
    if len(robot.feet) != 2 or not kin.floating:
        return None
    m = kin.model
    d = mujoco.MjData(m)
    d.qpos[:] = kin.qpos_from_x(np.asarray(robot.x_stand, float).ravel())
    mujoco.mj_kinematics(m, d)
    chains = [_chain(m, foot.body, kin.root_body) for foot in robot.feet]
    shared = set(chains[0]) & set(chains[1])
    by_adr = {h.qpos_adr: h.index for h in kin.joints}
    out = []
    for chain in chains:
        found = None
        for body in chain:  # foot upwards: the last one found is the closest to the root
            if body in shared:
                break
            for j in range(m.njnt):
                if m.jnt_bodyid[j] == body and m.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE:
                    z = float(d.xaxis[j][2])
                    if abs(z) >= _VERTICAL:
                        found = (kin.n_root + by_adr[int(m.jnt_qposadr[j])], 1.0 if z > 0 else -1.0)
        if found is None:
            return None
        out.append(found)
    return out


def _pair_rows(robot) -> tuple[list[int], np.ndarray]:
    """Indices of the capsule pairs with neither capsule on a foot's body, and each one's
    radii plus the profile's collision margin (m)."""
    feet = {f.body for f in robot.feet}
    rows = [
        k
        for k, (a, b) in enumerate(robot.collision_pairs)
        if robot.capsules[a].body not in feet and robot.capsules[b].body not in feet
    ]
    r = np.array([robot.capsules[a].radius + robot.capsules[b].radius for a, b in robot.collision_pairs])
    return rows, r[rows] + robot.profile.collision_margin


def step_turn_limits(robot, cap: float, clearance: float = 0.0) -> tuple[float, float]:
    """(toe_out, toe_in) rad, each in [0, cap] on a grid of 0.01 rad: see the module docstring.
    Without leg yaw hinges, or with ``cap`` below the grid, ``cap`` for both."""
    joints = leg_yaw_joints(robot)
    turns = np.arange(_RESOLUTION, cap + 0.5 * _RESOLUTION, _RESOLUTION)
    if joints is None or len(turns) == 0:
        return cap, cap
    rows, r = _pair_rows(robot)
    x0 = np.asarray(robot.x_stand, float).ravel()
    # a row is d² − r²; keeping d ≥ r + clearance is row ≥ 2·r·clearance + clearance²
    floor = np.minimum(robot.evaluate(x0[None])["collision"][0, rows], 2 * r * clearance + clearance**2)
    (jl, sl), (jr, sr) = joints
    limits = []
    for toes_in in (False, True):
        rel = -turns if toes_in else turns  # the left foot's heading minus the right's: + is toes out
        X = np.repeat(x0[None], len(turns), axis=0)
        X[:, jl] += sl * rel / 2
        X[:, jr] -= sr * rel / 2
        ok = np.all((X >= robot.x_lower) & (X <= robot.x_upper), axis=1)
        if rows:
            ok &= np.all(robot.evaluate(X)["collision"][:, rows] >= floor, axis=1)
        bad = np.flatnonzero(~ok)
        limits.append(cap if len(bad) == 0 else float(turns[bad[0] - 1]) if bad[0] > 0 else 0.0)
    return limits[0], limits[1]

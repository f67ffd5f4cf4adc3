"""A standing pose for a free-standing robot whose MJCF has none (``robot init``).

A model's zero pose is often straight-legged, sometimes with the arms held out (the published
OP3: knees locked, a T-pose). A robot standing on locked knees cannot move its pelvis back
under a lean: the retargeter leans the whole body with the person, the CoM moves ahead of the
feet and the soft servos sag further. Measured on the published OP3 with the CMU pair
(physics, planned offline and streamed alike: robot init's profile keeps the feet planted):
from its zero pose both clips fell at 0.85 s; with the arms hanging and straight legs one of
two fell; with the pose below both were performed for hip drops of 8-12 % of the leg (one clip
fell at 4-6 % and one at 15 %: too little bend leaves no room to move the pelvis back, too much
loads the knees).

:func:`derive_stand_pose` bends the legs so that each hip drops :data:`KNEE_DROP` of its
hip-to-ankle distance, each foot level, unturned and under its hip as in the zero pose, and
lets each arm hang :data:`ARM_ABDUCTION` rad out from vertical (more where that touches the
body), by bounded least squares over the limbs' hinges (scipy); every other joint keeps its
zero-pose angle. The profile gets the angles as ``stand_pose``; the retargeter and the
physics check stand in it where the MJCF has no stand keyframe.
"""

from __future__ import annotations

import math

import numpy as np

#: the hip drops this share of its hip-to-ankle distance (knees 0.96 rad on the published OP3)
KNEE_DROP = 0.1
#: rad, the hanging arm's angle out from vertical; tried larger (to 0.9) while an arm touches
ARM_ABDUCTION = 0.3
_ABDUCTIONS = (ARM_ABDUCTION, 0.45, 0.6, 0.9)


def derive_stand_pose(m, an, limits: dict) -> tuple[dict, str] | None:
    """({joint name: rad} of the limbs' hinges, why) for model ``m`` with the
    :class:`retarget.profile_init.Anatomy` ``an`` (None unless it is floating with two legs).
    ``limits`` {joint: (lo, hi)} bounds the hinges the MJCF leaves unranged."""
    import mujoco

    if not an.floating or len(an.legs) != 2:
        return None
    limbs = list(an.legs.values()) + list(an.arms.values())
    ids = sorted({j.id for limb in limbs for j in limb.joints if m.jnt_type[j.id] == mujoco.mjtJoint.mjJNT_HINGE})
    names = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j) for j in ids]
    adr = np.array([m.jnt_qposadr[j] for j in ids])
    lo, hi = _bounds(m, ids, names, limits)
    q0 = np.clip(m.qpos0[adr], lo, hi)
    # the start: each knee bent into its range (straight, the hip's drop has no gradient, and a
    # knee at its bound gets no step from the bounded solver)
    inset = np.minimum(1e-3, 0.25 * (hi - lo))
    start = q0.copy()
    for leg in an.legs.values():
        if leg.mid is not None and leg.mid.id in ids:
            i = ids.index(leg.mid.id)
            start[i] += 0.5 if hi[i] - q0[i] >= q0[i] - lo[i] else -0.5
    start = np.clip(start, lo + inset, hi - inset)
    d = mujoco.MjData(m)
    d.qpos[:] = m.qpos0
    mujoco.mj_kinematics(m, d)
    legs = [_leg_rest(d, leg) for leg in an.legs.values()]
    arms = [_arm_rest(d, arm, an) for arm in an.arms.values()]
    from scipy.optimize import least_squares

    for alpha in _ABDUCTIONS:

        def residuals(x, alpha=alpha):
            d.qpos[adr] = x
            mujoco.mj_kinematics(m, d)
            r = [_leg_rows(d, leg) for leg in legs] + [_arm_rows(d, arm, alpha) for arm in arms]
            return np.concatenate(r + [0.01 * (x - q0)])

        x = least_squares(residuals, start, bounds=(lo, hi)).x
        touching = _arm_contacts(m, d, adr, x, an)
        if not touching:
            break
    pose = {n: round(float(v), 4) for n, v, a in zip(names, x, adr) if abs(v - m.qpos0[a]) > 1e-4}
    why = (
        f"derived: the model has no stand keyframe; knees bent so the hips drop {100 * KNEE_DROP:g} % of the "
        f"leg, feet level under the hips, arms hanging {alpha:g} rad out"
        + (f" (an arm still touches: {', '.join(touching)})" if touching else "")
    )
    return pose, why


def _bounds(m, ids, names, limits) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = np.full(len(ids), -math.pi), np.full(len(ids), math.pi)
    for i, (j, n) in enumerate(zip(ids, names)):
        if m.jnt_limited[j]:
            lo[i], hi[i] = m.jnt_range[j]
        elif n in limits:
            lo[i], hi[i] = limits[n]
    return lo, np.maximum(hi, lo + 1e-9)


def _leg_rest(d, leg) -> tuple:
    """(hip joint, ankle joint, foot body, foot rotation (3, 3), ankle-from-hip xy (2,), length)."""
    hip, ankle = leg.joints[0].id, leg.joints[-1].id
    foot = leg.foot_body if leg.foot_body is not None else leg.bodies[-1]
    v = d.xanchor[ankle] - d.xanchor[hip]
    return hip, ankle, foot, d.xmat[foot].reshape(3, 3).copy(), v[:2].copy(), float(np.linalg.norm(v))


def _leg_rows(d, leg) -> np.ndarray:
    hip, ankle, foot, R0, xy, length = leg
    v = d.xanchor[ankle] - d.xanchor[hip]
    return np.concatenate(
        [
            (v[:2] - xy) / length,  # under the hip as in the zero pose
            [(np.linalg.norm(v) - (1 - KNEE_DROP) * length) / length],  # the hip lowered
            d.xmat[foot] - R0.ravel(),  # the foot level and unturned
        ]
    )


def _arm_rest(d, arm, an) -> tuple:
    """(shoulder joint, hand body, hand point in it (3,), arm length, outward unit (3,))."""
    shoulder, body = arm.joints[0].id, arm.bodies[-1]
    R = d.xmat[body].reshape(3, 3)
    local = R.T @ (arm.end_point - d.xpos[body])
    out = np.asarray(an.left, dtype=float) * (1.0 if arm.side == "left" else -1.0)
    return shoulder, body, local, float(np.linalg.norm(arm.end_point - d.xanchor[shoulder])), out


def _arm_rows(d, arm, alpha: float) -> np.ndarray:
    shoulder, body, local, length, out = arm
    hand = d.xpos[body] + d.xmat[body].reshape(3, 3) @ local
    want = math.cos(alpha) * np.array([0.0, 0.0, -1.0]) + math.sin(alpha) * out
    return (hand - d.xanchor[shoulder]) / max(length, 1e-9) - want


def _arm_contacts(m, d, adr, x, an) -> list[str]:
    """Names of arm bodies whose geoms touch another body of the robot at pose x."""
    import mujoco

    d.qpos[adr] = x
    mujoco.mj_forward(m, d)
    arm_bodies = {b for arm in an.arms.values() for b in arm.bodies}
    out = set()
    for c in d.contact[: d.ncon]:
        b1, b2 = int(m.geom_bodyid[c.geom1]), int(m.geom_bodyid[c.geom2])
        if c.dist < -1e-3 and 0 not in (b1, b2) and (b1 in arm_bodies) != (b2 in arm_bodies):
            out.add(mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b1 if b1 in arm_bodies else b2) or str(b1))
    return sorted(out)

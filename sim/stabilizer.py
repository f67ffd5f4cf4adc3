"""Balance stabilizer: body IMU + joint readings -> bounded corrections on the legs' joints.

The same component in the bridge's control loop (after interpolation, before the safety
filter) and in the physics check. :func:`balance_model` reads a robot's legs and IMU frame
from its MJCF once (None for a fixed base); :meth:`Stabilizer.step` maps (reference (n,) rad,
measured (n,) rad, IMU reading, dt s) to corrected targets (n,) rad, every correction within
``max_correction`` rad, ``max_rate`` rad/s and the joint limits. Reference: docs/simulation.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np


@dataclass(frozen=True)
class StabilizerGains:
    """Feedback gains and bounds. ``None`` fields take the robot-scaled defaults
    (:func:`default_gains`). kp: rad of body rotation per rad of tilt error; ki: 1/s;
    kd, kd_hip: s (rad per rad/s); ki_sag: 1/s; max_correction rad; max_rate rad/s;
    gyro_cutoff_hz and reference_cutoff_hz Hz (low-pass of the gyro and of
    the reference attitude); stance_band m (a foot this much above the lowest has stance weight 0);
    two_feet_roll 0..1 (the share of the roll joints' feedback kept on two feet: 0 none, 1 all)."""

    kp: float | None = None
    ki: float | None = None
    kd: float | None = None
    kd_hip: float | None = None
    ki_sag: float | None = None
    kp_sag: float | None = None
    max_correction: float | None = None
    max_rate: float | None = None
    gyro_cutoff_hz: float | None = None
    reference_cutoff_hz: float | None = None
    stance_band: float | None = None
    two_feet_roll: float | None = None

    def resolved(self, defaults: StabilizerGains) -> StabilizerGains:
        return StabilizerGains(
            **{
                k: (getattr(self, k) if getattr(self, k) is not None else getattr(defaults, k))
                for k in self.__dataclass_fields__
            }
        )

    def validate(self) -> None:
        for k in self.__dataclass_fields__:
            v = getattr(self, k)
            if v is not None and not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"stabilizer gains: {k} must be a finite number >= 0, got {v!r}")
        if self.two_feet_roll is not None and self.two_feet_roll > 1:
            raise ValueError(f"stabilizer gains: two_feet_roll is a share, 0 to 1, got {self.two_feet_roll!r}")


@dataclass(frozen=True)
class ChainLink:
    """One body of a leg chain, root side first: ``pos`` (3,) and ``quat`` (4,) wxyz of the body
    in its parent at zero joint angles; its hinges as (joint index in the robot's joint order,
    or -1 for an unactuated one held at ``fixed_angle``; unit axis (3,) in the body frame;
    anchor (3,) in the body frame; fixed_angle)."""

    pos: tuple
    quat: tuple
    hinges: tuple


@dataclass(frozen=True)
class Leg:
    """A leg from the root's child to the foot: ``links``, the foot's ``sole`` point (3,) in the
    last link's frame, the joint indices by role (-1 if the leg has none) and ``sag_joints``
    (the pitch and roll joints: hips, knees, ankles)."""

    side: str
    links: tuple
    sole: tuple
    ankle_pitch: int
    ankle_roll: int
    hip_pitch: int
    hip_roll: int
    sag_joints: tuple


@dataclass(frozen=True)
class BalanceModel:
    """What the stabilizer knows of a robot: ``n`` joints, two ``legs``, ``imu_to_root`` (3, 3),
    joint ``lower``/``upper`` (n,) rad, ``mass`` kg, ``com_height`` m (centre of mass over the
    soles, standing), ``ankle_stiffness`` N m/rad (one ankle pitch servo), ``gains`` (resolved)."""

    robot: str
    n: int
    legs: tuple
    imu_to_root: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    mass: float
    com_height: float
    ankle_stiffness: float
    gains: StabilizerGains
    notes: tuple = ()

    def with_gains(self, gains: StabilizerGains | None) -> BalanceModel:
        """This model with ``gains``' given fields replacing the current ones."""
        if gains is None:
            return self
        gains.validate()
        return replace(self, gains=gains.resolved(self.gains))

    @property
    def ankle_joints(self) -> tuple:
        return tuple(j for leg in self.legs for j in (leg.ankle_pitch, leg.ankle_roll) if j >= 0)

    @property
    def hip_joints(self) -> tuple:
        return tuple(j for leg in self.legs for j in (leg.hip_pitch, leg.hip_roll) if j >= 0)


def default_gains(mass: float, com_height: float, ankle_stiffness: float, robot_height: float) -> StabilizerGains:
    """Gains scaled to the robot. Measured on the op3 in real MuJoCo with the readings one
    control tick old, as the bridge's split-phase bus gives them (bench/stabilizer.py):

    - attitude on the ankles, kp = 0.5, and rate, kd = 0.05 s: the standing robot then survives
      a 2.5 s push of 4 N forwards and backwards (3 N open loop) and a 0.2 s push of 7 N backwards
      (6 N open loop); larger kp, an integral (ki) or the rate on the hips (kd_hip) added nothing;
    - sag compensation off (ki_sag = kp_sag = 0): the PI on the joints' tracking error that
      removes the servos' sag passes one demo clip with fresh readings but fails it with readings
      one tick old, and in the real-time loop it oscillated at 5 Hz (+-0.15 rad on the hips);
    - the reference attitude low-passed at 3 Hz (a generated partner's jitter moves it by +-3 deg
      from tick to tick) and the gyro at 15 Hz;
    - bounds: corrections up to 0.3 rad, at most 3 rad/s;
    - the stance band (how far above the lower foot the reference may hold a foot before it
      shares no correction) is 10 % of the robot's height, 5 cm on the op3. At 2 % (1 cm, the
      value before) 6 of 76 recorded demo runs fell when replayed (the demo's check, in the
      loop's order) while the robot shuffled back to its stance at 2.8 steps a second, where
      the same targets without the stabilizer fell in none: a foot the reference lifts by less
      than the stance leg sags (about 1 cm on servos) still stands, yet got no share of the
      correction, so one ankle fought the other and a landing foot came down turned by the
      body's tilt. At 5 cm none fell, the peak tilt of that stretch 12 deg median (15 at 1 cm);
      at 3 cm 3 fell of 72; a 5 cm band on the reference attitude alone did not help, one on
      the corrections alone did. Push survival is unchanged;
    - no roll feedback on two feet (two_feet_roll = 0): the roll joints' share falls with the
      weaker foot's stance weight. On two feet apart the support holds the body's roll, and
      both ankles rolling alike lift one foot: with the share kept (two_feet_roll = 1) the
      landed foot lifted again 6-10 mm 0.1-0.3 s after touch-down, 1.16 lift-offs per planned
      step on 17 streamed stepping leaders against 1.01 without, all 17 up either way
      (bench/stabilizer.py); sideways pushes are survived as before (10 N for 0.2 s, 5 N for
      2.5 s, as without the stabilizer).

    The rate gain scales with the body's pendulum: kd = 0.75 sqrt(K I) / (2 k), with
    inertia I = m h^2 and the ankles' net stiffness K = 2 k - m g h (0.05 s on the op3)."""
    g = 9.81
    k2 = 2.0 * max(ankle_stiffness, 1e-6)
    k_net = max(k2 - mass * g * com_height, 0.1 * k2)
    damping = math.sqrt(k_net * mass * com_height**2) / k2  # s; 0.067 s on the op3
    return StabilizerGains(
        kp=0.5,
        ki=0.0,
        kd=0.75 * damping,
        kd_hip=0.0,
        ki_sag=0.0,
        kp_sag=0.0,
        max_correction=0.3,
        max_rate=3.0,
        gyro_cutoff_hz=15.0,
        reference_cutoff_hz=3.0,
        stance_band=0.1 * robot_height,
        two_feet_roll=0.0,
    )


# -- the per-tick stabilizer ---------------------------------------------------------------------


class Stabilizer:
    """One robot's balance feedback; call :meth:`reset` when the loop starts, then
    :meth:`step` every tick. ``correction`` (n,) rad is the last tick's correction, ``active``
    whether it had an attitude to work with, ``tilt_error`` (3,) rad the last attitude error
    (root frame), ``max_abs_correction`` rad the largest correction since the reset.

    Written with Python floats for the 3-vectors and the legs' kinematics (a numpy call on a
    3-vector costs more than the arithmetic): it runs every tick of the bridge's loop."""

    def __init__(self, model: BalanceModel):
        self.model = model
        self.n = model.n
        self._legs = model.legs
        self._sag = np.array(sorted({j for leg in model.legs for j in leg.sag_joints}), dtype=int)
        self._roles = [((leg.ankle_pitch, leg.ankle_roll), (leg.hip_pitch, leg.hip_roll)) for leg in model.legs]
        self._R = tuple(tuple(float(v) for v in row) for row in np.asarray(model.imu_to_root))
        self.reset()

    def reset(self) -> None:
        self.correction = np.zeros(self.n)
        self._att_i = [0.0, 0.0, 0.0]  # integral of the tilt error, rad s
        self._sag_i = np.zeros(len(self._sag))  # sag integrators, rad
        self._sag_err = np.zeros(len(self._sag))
        self._feedback = np.zeros(self.n)  # the attitude and rate feedback's share of the correction, rad
        self._gyro = None  # low-passed rate (root frame)
        self._u_ref_prev = None
        self.active = False
        self.max_abs_correction = 0.0
        self.tilt_error = np.zeros(3)

    def step(self, q_ref, position, imu, dt: float) -> np.ndarray:
        """Corrected targets (n,) rad for reference ``q_ref`` (n,) rad, measured ``position``
        (n,) rad (NaN: unknown; None: not read), ``imu`` (an object with ``gyro`` (3,) rad/s,
        ``accel`` (3,) m/s^2, ``quat`` (4,) wxyz; None: no IMU, then only the sag
        compensation acts) and the tick ``dt`` s."""
        q_ref = np.asarray(q_ref, dtype=np.float64)
        if q_ref.shape != (self.n,) or not np.isfinite(q_ref).all() or not dt > 0:
            return q_ref  # the safety filter deals with a bad target; nothing to add to it
        frames, weights, u_ref = self._reference_up(q_ref.tolist(), dt)
        target = np.zeros(self.n)
        self._attitude_feedback(target, frames, weights, u_ref, imu, dt)
        self._sag_compensation(target, q_ref, position, dt)
        return self._bounded(q_ref, target, dt)

    def _reference_up(self, ql: list, dt: float):
        """(each leg's frames, each leg's stance weight 0..1, the world's up axis in the root
        frame that the reference gives with the stance feet flat, low-passed)."""
        gains = self.model.gains
        frames = [_leg_frames(leg, ql) for leg in self._legs]
        heights = [u[0] * p[0] + u[1] * p[1] + u[2] * p[2] for u, p, _ in frames]
        low, band = min(heights), max(gains.stance_band, 1e-6)
        weights = [min(1.0, max(0.0, 1.0 - (h - low) / band)) for h in heights]
        u = [sum(w * f[0][i] for w, f in zip(weights, frames)) for i in range(3)]
        if self._u_ref_prev is not None:  # low-pass: a jittery reference must not shake the ankles
            a = dt / (dt + 1.0 / (2 * math.pi * max(gains.reference_cutoff_hz, 1e-3)))
            nu = math.sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2]) or 1.0
            p = self._u_ref_prev
            u = [p[i] + a * (u[i] / nu - p[i]) for i in range(3)]
        nu = math.sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2]) or 1.0
        return frames, weights, (u[0] / nu, u[1] / nu, u[2] / nu)

    def _attitude_feedback(self, target: np.ndarray, frames, weights, u_ref, imu, dt: float) -> None:
        """Add the attitude and rate feedback (module docstring, term 1) to ``target`` (n,)."""
        gains = self.model.gains
        u_meas, gyro = _imu_up_and_rate(imu, self._R)
        self.active = u_meas is not None
        if gyro is not None:
            a = dt / (dt + 1.0 / (2 * math.pi * max(gains.gyro_cutoff_hz, 1e-3)))
            g0 = self._gyro or gyro
            self._gyro = tuple(g0[i] + a * (gyro[i] - g0[i]) for i in range(3))
        prev = self._u_ref_prev
        w_ref = _cross(u_ref, prev, 1.0 / dt) if prev is not None else (0.0, 0.0, 0.0)
        self._u_ref_prev = u_ref
        if u_meas is None:
            return
        e = _tilt_only(_cross(u_ref, u_meas), u_meas)
        self.tilt_error = np.array(e)
        rate = (0.0, 0.0, 0.0)
        if self._gyro is not None:
            rate = _tilt_only(tuple(w_ref[i] - self._gyro[i] for i in range(3)), u_meas)
        ai = self._att_i
        w_ankle = tuple(gains.kp * e[i] + gains.ki * ai[i] + gains.kd * rate[i] for i in range(3))
        w_hip = tuple(gains.kd_hip * r for r in rate)
        # the roll joints' share: 1 on one foot, two_feet_roll on two (default_gains)
        roll_share = 1.0 - (1.0 - gains.two_feet_roll) * min(weights) if len(weights) == 2 else 1.0
        for (_, _, axes), wt, (ankles, hips) in zip(frames, weights, self._roles):
            if wt <= 0:
                continue
            for joints, w in ((ankles, w_ankle), (hips, w_hip)):
                for j, share in zip(joints, (1.0, roll_share)):  # (pitch, roll)
                    if j >= 0 and share > 0:
                        ax = axes[j]
                        target[j] -= wt * share * (ax[0] * w[0] + ax[1] * w[1] + ax[2] * w[2])
        lim = gains.max_correction
        if gains.ki > 0 and not any(abs(target[j]) >= lim for j in self.model.ankle_joints):  # anti-windup
            cap = lim / gains.ki
            for i in range(3):
                ai[i] = min(cap, max(-cap, ai[i] + e[i] * dt))

    def _sag_compensation(self, target: np.ndarray, q_ref: np.ndarray, position, dt: float) -> None:
        """Add the sag compensation (module docstring, term 2) to ``target`` (n,)."""
        gains, sag = self.model.gains, self._sag
        if len(sag):
            meas = None if position is None else np.asarray(position, dtype=np.float64)
            if meas is not None and meas.shape == (self.n,):
                # where the joint should be (reference + feedback) minus where it is: the sag
                err = q_ref[sag] + self._feedback[sag] - meas[sag]
                err[~np.isfinite(err)] = 0.0
                self._sag_err = err
                if gains.ki_sag > 0:
                    cur = self._sag_i
                    cand = cur + gains.ki_sag * dt * err
                    total = target[sag] + cand + gains.kp_sag * err
                    block = (np.abs(cand) > np.abs(cur)) & (np.abs(total) >= gains.max_correction)  # anti-windup
                    cand[block] = cur[block]
                    self._sag_i = np.minimum(np.maximum(cand, -gains.max_correction), gains.max_correction)
        self._feedback = np.minimum(np.maximum(target, -gains.max_correction), gains.max_correction)
        if len(sag):
            target[sag] += self._sag_i + gains.kp_sag * self._sag_err

    def _bounded(self, q_ref: np.ndarray, target: np.ndarray, dt: float) -> np.ndarray:
        """``q_ref`` plus the correction ``target``, bounded in size, rate and joint limits."""
        m, gains = self.model, self.model.gains
        step = gains.max_rate * dt
        c = np.minimum(np.maximum(target, -gains.max_correction), gains.max_correction)
        c = np.minimum(np.maximum(c, self.correction - step), self.correction + step)
        out = q_ref + c
        inside = (q_ref >= m.lower) & (q_ref <= m.upper)
        out = np.where(inside, np.minimum(np.maximum(out, m.lower), m.upper), q_ref)
        self.correction = out - q_ref
        peak = float(np.abs(self.correction).max()) if self.n else 0.0
        if peak > self.max_abs_correction:
            self.max_abs_correction = peak
        return out


def _cross(a, b, scale: float = 1.0):
    return (
        (a[1] * b[2] - a[2] * b[1]) * scale,
        (a[2] * b[0] - a[0] * b[2]) * scale,
        (a[0] * b[1] - a[1] * b[0]) * scale,
    )


def _tilt_only(v, up):
    """``v`` without its component along the unit vector ``up`` (a turn about the vertical is no tilt)."""
    k = v[0] * up[0] + v[1] * up[1] + v[2] * up[2]
    return (v[0] - k * up[0], v[1] - k * up[1], v[2] - k * up[2])


def _apply(R, v):
    return tuple(R[i][0] * v[0] + R[i][1] * v[1] + R[i][2] * v[2] for i in range(3))


def _imu_up_and_rate(imu, R):
    """(the world's up axis in the root frame, the body rate in the root frame), each a 3-tuple
    or None; ``R`` rotates IMU-frame vectors into the root frame."""
    if imu is None:
        return None, None
    up = None
    quat = [float(v) for v in np.ravel(imu.quat)] if imu.quat is not None else []
    nq = sum(v * v for v in quat) if len(quat) == 4 else float("nan")
    if nq > 0.5 and math.isfinite(nq):
        w, x, y, z = (v / math.sqrt(nq) for v in quat)
        up = (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y))  # R_world_imu^T e_z
    else:
        acc = [float(v) for v in np.ravel(imu.accel)] if imu.accel is not None else []
        na = math.sqrt(sum(v * v for v in acc)) if len(acc) == 3 else float("nan")
        if na > 1.0 and math.isfinite(na):
            up = tuple(v / na for v in acc)  # at rest the specific force points up
    if up is not None:
        up = _apply(R, up)
    gyro = [float(v) for v in np.ravel(imu.gyro)] if imu.gyro is not None else []
    rate = _apply(R, gyro) if len(gyro) == 3 and all(map(math.isfinite, gyro)) else None
    return up, rate


def _leg_frames(leg: Leg, q):
    """Forward kinematics of one leg at joint angles ``q`` (a list, rad): (the world's up axis
    in the root frame if this foot stands flat, the sole point in the root frame, {joint index:
    its axis in the root frame}), all 3-tuples."""
    qw, qx, qy, qz = 1.0, 0.0, 0.0, 0.0
    px = py = pz = 0.0
    axes = {}
    for link in leg.links:
        bx, by, bz = _rotate(qw, qx, qy, qz, *link.pos)
        px, py, pz = px + bx, py + by, pz + bz
        qw, qx, qy, qz = _mul(qw, qx, qy, qz, *link.quat)
        for j, axis, anchor, fixed in link.hinges:
            angle = q[j] if j >= 0 else fixed
            if j >= 0:
                axes[j] = _rotate(qw, qx, qy, qz, *axis)
            h = 0.5 * angle
            s = math.sin(h)
            rw, rx, ry, rz = math.cos(h), axis[0] * s, axis[1] * s, axis[2] * s
            if anchor != (0.0, 0.0, 0.0):  # a hinge off the body origin also moves it
                ax, ay, az = _rotate(rw, rx, ry, rz, *anchor)
                dx, dy, dz = _rotate(qw, qx, qy, qz, anchor[0] - ax, anchor[1] - ay, anchor[2] - az)
                px, py, pz = px + dx, py + dy, pz + dz
            qw, qx, qy, qz = _mul(qw, qx, qy, qz, rw, rx, ry, rz)
    sx, sy, sz = _rotate(qw, qx, qy, qz, *leg.sole)
    up = _rotate(qw, qx, qy, qz, 0.0, 0.0, 1.0)  # the flat foot's z axis is the world's up
    return up, (px + sx, py + sy, pz + sz), axes


def _mul(aw, ax, ay, az, bw, bx, by, bz):
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


def _rotate(w, x, y, z, vx, vy, vz):
    """Vector (vx, vy, vz) rotated by the unit quaternion (w, x, y, z)."""
    tx, ty, tz = 2 * (y * vz - z * vy), 2 * (z * vx - x * vz), 2 * (x * vy - y * vx)
    return (vx + w * tx + y * tz - z * ty, vy + w * ty + z * tx - x * tz, vz + w * tz + x * ty - y * tx)


# -- building the model from a robot (MuJoCo, once) ---------------------------------------------


def balance_model(
    robot=None, scene=None, gains: StabilizerGains | None = None, joint_names: tuple | None = None
) -> BalanceModel | None:
    """The :class:`BalanceModel` of a robot reference (as the registry resolves it) or of a
    built :class:`sim.scene.Scene`; None where a stabilizer does not apply: a fixed-base robot
    (no freejoint, or bolted down in the scene), or one whose two legs (root -> foot chains
    with ankle joints) are not found. ``joint_names``: the caller's joint order, which must be
    the robot's. ``gains``: overrides of the robot-scaled defaults."""
    import mujoco

    if scene is None:
        from sim.scene import Scene, SceneConfig

        scene = Scene(SceneConfig(robot=robot or "op3"))
    m, r = scene.model, scene.robot
    if r.fixed_base or not scene.floating or len(r.feet) < 2:
        return None
    if joint_names is not None and tuple(joint_names) != tuple(r.joint_names):
        from sim.errors import SimError

        raise SimError(
            f"stabilizer: joint order {tuple(joint_names)} differs from the robot model's {tuple(r.joint_names)}"
        )
    d = mujoco.MjData(m)
    d.qpos[:] = scene._stand_qpos if hasattr(scene, "_stand_qpos") else m.qpos0
    mujoco.mj_kinematics(m, d)
    mujoco.mj_comPos(m, d)
    root = r.root_body
    R_root = d.xmat[root].reshape(3, 3)
    jid_to_index = {int(j): i for i, j in enumerate(r.joint_ids)}
    legs = []
    for foot in r.feet:
        leg = _leg(m, d, root, foot, jid_to_index, R_root)
        if leg is None:
            return None
        legs.append(leg)
    mass = float(m.body_subtreemass[root])
    com = d.subtree_com[root]
    sole_z = min(float((d.xpos[f.body] + d.xmat[f.body].reshape(3, 3) @ f.sole_point)[2]) for f in r.feet)
    com_height = max(float(com[2] - sole_z), 1e-3)
    ank = [leg.ankle_pitch for leg in legs if leg.ankle_pitch >= 0]
    act = r.actuator_ids
    stiff = [float(m.actuator_gainprm[act[j], 0] * abs(m.actuator_gear[act[j], 0])) for j in ank]
    ankle_k = float(np.mean(stiff)) if stiff else 1.0
    imu_to_root, note = _imu_frame(m, d, root)
    defaults = default_gains(mass, com_height, ankle_k, scene.robot_height)
    model = BalanceModel(
        str(scene.config.robot),
        r.n,
        tuple(legs),
        imu_to_root,
        r.lower.copy(),
        r.upper.copy(),
        mass,
        com_height,
        ankle_k,
        defaults,
        (note,) if note else (),
    )
    return model.with_gains(gains)


def _leg(m, d, root: int, foot, jid_to_index: dict, R_root: np.ndarray) -> Leg | None:
    import mujoco

    chain = []
    b = int(foot.body)
    while b != root and b > 0:
        chain.append(b)
        b = int(m.body_parentid[b])
    if b != root:
        return None
    chain.reverse()
    links, roles = [], []  # roles: (joint index, kind, depth)
    for depth, body in enumerate(chain):
        hinges = []
        for jid in range(m.body_jntadr[body], m.body_jntadr[body] + m.body_jntnum[body]):
            if m.jnt_type[jid] != mujoco.mjtJoint.mjJNT_HINGE:
                return None  # a slide or ball joint in a leg: not a chain of hinges
            idx = jid_to_index.get(jid, -1)
            fixed = float(d.qpos[m.jnt_qposadr[jid]]) if idx < 0 else 0.0
            hinges.append(
                (idx, tuple(float(v) for v in m.jnt_axis[jid]), tuple(float(v) for v in m.jnt_pos[jid]), fixed)
            )
            if idx >= 0:
                axis_root = R_root.T @ d.xaxis[jid]
                kind = ("yaw", "pitch", "roll")[int(np.argmax(np.abs(axis_root[[2, 1, 0]])))]
                roles.append((idx, kind, depth))
        links.append(
            ChainLink(
                tuple(float(v) for v in m.body_pos[body]), tuple(float(v) for v in m.body_quat[body]), tuple(hinges)
            )
        )
    pitch = [i for i, k, _ in roles if k == "pitch"]
    roll = [i for i, k, _ in roles if k == "roll"]
    if len(pitch) < 2 or not roll:
        return None
    sole = tuple(float(v) for v in foot.sole_point)
    return Leg(
        foot.side,
        tuple(links),
        sole,
        ankle_pitch=pitch[-1],
        ankle_roll=roll[-1],
        hip_pitch=pitch[0],
        hip_roll=roll[0] if len(roll) > 1 else -1,
        sag_joints=tuple(pitch + roll),
    )


def imu_site(model, root: int) -> int:
    """The site the robot's IMU readings come from: the site of a gyro or framequat sensor on
    the root body, else a site on the root body named like "imu", else -1 (the root body's own
    frame)."""
    import mujoco

    for s in range(model.nsensor):
        if (
            model.sensor_type[s] in (mujoco.mjtSensor.mjSENS_GYRO, mujoco.mjtSensor.mjSENS_FRAMEQUAT)
            and model.sensor_objtype[s] == mujoco.mjtObj.mjOBJ_SITE
        ):
            site = int(model.sensor_objid[s])
            if model.site_bodyid[site] == root:
                return site
    for site in range(model.nsite):
        if model.site_bodyid[site] == root and "imu" in (model.site(site).name or "").lower():
            return site
    return -1


def _imu_frame(m, d, root: int) -> tuple[np.ndarray, str]:
    """Rotation (3, 3) from the IMU site's frame to the root body's, and a note."""
    site = imu_site(m, root)
    if site < 0:
        return np.eye(3), "no IMU site on the root body: IMU readings are taken in the root body's frame"
    R = d.xmat[root].reshape(3, 3).T @ d.site_xmat[site].reshape(3, 3)
    return R, ""


__all__ = ["StabilizerGains", "BalanceModel", "Stabilizer", "balance_model", "default_gains", "imu_site"]

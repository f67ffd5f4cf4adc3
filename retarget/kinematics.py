"""Symbolic forward kinematics in CasADi, built from any MuJoCo model.

Contract: :class:`RobotKinematics` reads the kinematic tree, body offsets, hinge axes and
anchors, reference angles, masses and geoms from an ``mujoco.MjModel`` and composes them as
MuJoCo's ``mj_kinematics`` does (no per-robot code), as CasADi expressions of one frame's
configuration vector

    x = [root position (3) m, root yaw, pitch, roll (3) rad, hinge angles (n) rad]   (free root)
    x = [hinge angles (n) rad]                                                         (fixed root)

with R_root = Rz(yaw) · Ry(pitch) · Rx(roll); pitch stays within ±80° (a bound the solvers
set). World frame Z up, metres. Hinge j of a body turns it about its axis through its anchor by
θ = q_j − qpos0_j (Rodrigues); a slide joint moves it along its axis; see docs/retargeting.md, section 2.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import numpy as np

from retarget.errors import RetargetError

_PITCH_LIMIT = np.deg2rad(80.0)


def quat_to_mat(q) -> np.ndarray:
    """(4,) unit quaternion w, x, y, z → (3, 3) rotation matrix (numeric)."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def mat_to_quat(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices → (..., 4) unit quaternions w, x, y, z with w ≥ 0 (MuJoCo's mju_mat2Quat)."""
    import mujoco

    R = np.asarray(R, dtype=np.float64)
    flat = R.reshape(-1, 9)
    out = np.zeros((flat.shape[0], 4))
    for i in range(flat.shape[0]):
        mujoco.mju_mat2Quat(out[i], flat[i])
    out *= np.where(out[:, :1] < 0, -1.0, 1.0)
    return out.reshape(R.shape[:-2] + (4,))


def euler_to_mat(e):
    """Yaw-pitch-roll (3,) → R = Rz(yaw)·Ry(pitch)·Rx(roll); works on numpy and CasADi types."""
    lib = ca if isinstance(e, (ca.SX, ca.MX, ca.DM)) else np
    yaw, pitch, roll = e[0], e[1], e[2]
    cy, sy, cp, sp, cr, sr = lib.cos(yaw), lib.sin(yaw), lib.cos(pitch), lib.sin(pitch), lib.cos(roll), lib.sin(roll)
    rows = [
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ]
    if lib is np:
        return np.array(rows, dtype=np.float64)
    return ca.vertcat(*[ca.horzcat(*r) for r in rows])


def mat_to_euler(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) → (..., 3) yaw, pitch, roll with R = Rz·Ry·Rx (numeric)."""
    R = np.asarray(R, dtype=np.float64)
    yaw = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    pitch = np.arcsin(np.clip(-R[..., 2, 0], -1.0, 1.0))
    roll = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    return np.stack([yaw, pitch, roll], axis=-1)


def _skew(a: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


def _axis_rotation(axis: np.ndarray, theta):
    """Rodrigues: Rot(a, θ) = I + sinθ·K + (1 − cosθ)·K², K = [a]× (symbolic θ)."""
    K = _skew(axis)
    return ca.DM(np.eye(3)) + ca.sin(theta) * ca.DM(K) + (1 - ca.cos(theta)) * ca.DM(K @ K)


@dataclass(frozen=True)
class HingeJoint:
    """One actuated hinge: name, its body, axis (body frame), anchor (body frame), reference
    angle qpos0 (rad), position limits (rad; ±inf if unlimited), and its index in ``x``'s joint part."""

    name: str
    body: int
    axis: np.ndarray
    anchor: np.ndarray
    qpos0: float
    lower: float
    upper: float
    index: int
    qpos_adr: int


@dataclass(frozen=True)
class Capsule:
    """A capsule between two points fixed in ``body`` (body frame, metres) with ``radius``."""

    name: str
    body: int
    p0: np.ndarray
    p1: np.ndarray
    radius: float


class RobotKinematics:
    """Symbolic forward kinematics of one MuJoCo model (hinge and slide joints, free or fixed root).

    ``fixed_base=True`` treats a free-floating model as bolted at its ``qpos0`` root pose
    (the upper-body-partner option).
    """

    def __init__(self, model, name: str = "", fixed_base: bool = False, source: str = ""):
        import mujoco

        self.model = model
        self.name = name
        self.source = source
        m = model
        free = [j for j in range(m.njnt) if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE]
        if len(free) > 1:
            raise RetargetError(
                f"{source or name}: the model has {len(free)} free joints; retargeting needs one robot with at most one"
            )
        for j in range(m.njnt):
            if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_BALL:
                jname = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j)
                raise RetargetError(
                    f"{source or name}: joint {jname!r} is a ball joint; "
                    "only hinge, slide and one free root joint are supported"
                )
        self._free_joint = free[0] if free else None
        if (
            self._free_joint is not None
            and m.jnt_bodyid[self._free_joint] != 1
            and m.body_parentid[m.jnt_bodyid[self._free_joint]] != 0
        ):
            raise RetargetError(f"{source or name}: the free joint must sit on a child of the world body")
        self.root_body = int(m.jnt_bodyid[self._free_joint]) if self._free_joint is not None else 1
        self.floating = self._free_joint is not None and not fixed_base
        self._fixed_root_pose = None
        if self._free_joint is not None and fixed_base:
            adr = m.jnt_qposadr[self._free_joint]
            self._fixed_root_pose = (np.array(m.qpos0[adr : adr + 3]), quat_to_mat(m.qpos0[adr + 3 : adr + 7]))

        hinges: list[HingeJoint] = []
        self._slides: dict[int, tuple[np.ndarray, float, int]] = {}
        for j in range(m.njnt):
            jt = m.jnt_type[j]
            if jt == mujoco.mjtJoint.mjJNT_HINGE:
                jname = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j) or f"joint{j}"
                limited = bool(m.jnt_limited[j])
                lo, hi = (float(m.jnt_range[j, 0]), float(m.jnt_range[j, 1])) if limited else (-np.inf, np.inf)
                hinges.append(
                    HingeJoint(
                        jname,
                        int(m.jnt_bodyid[j]),
                        np.array(m.jnt_axis[j]),
                        np.array(m.jnt_pos[j]),
                        float(m.qpos0[m.jnt_qposadr[j]]),
                        lo,
                        hi,
                        len(hinges),
                        int(m.jnt_qposadr[j]),
                    )
                )
            elif jt == mujoco.mjtJoint.mjJNT_SLIDE:
                jname = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j)
                raise RetargetError(
                    f"{source or name}: joint {jname!r} is a slide joint; "
                    "only hinge joints and one free root are supported"
                )
        hinges = self._actuator_order(hinges)
        self.joints: tuple[HingeJoint, ...] = tuple(hinges)
        self.joint_names: tuple[str, ...] = tuple(h.name for h in hinges)
        self.n_joints = len(hinges)
        self.n_root = 6 if self.floating else 0
        self.nx = self.n_root + self.n_joints
        self._body_joints: dict[int, list] = {}
        for j in range(m.njnt):
            self._body_joints.setdefault(int(m.jnt_bodyid[j]), []).append(j)
        by_adr = {h.qpos_adr: h for h in hinges}
        self._hinge_by_jid = {
            j: by_adr[int(m.jnt_qposadr[j])] for j in range(m.njnt) if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE
        }
        self.total_mass = float(sum(m.body_mass[b] for b in range(1, m.nbody)))
        self._x = ca.SX.sym("x", self.nx)
        self._frames = self._build_frames(self._x)

    def _actuator_order(self, hinges: list[HingeJoint]) -> list[HingeJoint]:
        """The robot's joint order: the actuator order when every hinge has exactly one joint
        actuator (servo-ID order for the bundled robots), else MuJoCo's qpos order."""
        import mujoco

        m = self.model
        by_adr = {h.qpos_adr: h for h in hinges}
        order = []
        for a in range(m.nu):
            if m.actuator_trntype[a] != mujoco.mjtTrn.mjTRN_JOINT:
                return hinges
            adr = int(m.jnt_qposadr[m.actuator_trnid[a, 0]])
            if adr not in by_adr or by_adr[adr] in order:
                return hinges
            order.append(by_adr[adr])
        if len(order) != len(hinges):
            return hinges
        from dataclasses import replace

        return [replace(h, index=i) for i, h in enumerate(order)]

    # -- construction -------------------------------------------------------
    @classmethod
    def from_xml(cls, path, name: str = "", fixed_base: bool = False) -> RobotKinematics:
        import mujoco

        path = Path(path)
        if not path.is_file():
            raise RetargetError(
                f"{path}: MJCF file not found; give a bundled robot name, a robot folder or an existing .xml path"
            )
        try:
            model = mujoco.MjModel.from_xml_path(str(path))
        except ValueError as exc:
            raise RetargetError(f"{path}: MuJoCo cannot load this MJCF ({str(exc).splitlines()[0]})") from None
        return cls(model, name or path.stem, fixed_base=fixed_base, source=str(path))

    def _split(self, x):
        if self.floating:
            return x[0:3], euler_to_mat(x[3:6]), x[6:]
        return None, None, x

    def _build_frames(self, x):
        """World (position (3,1), rotation (3,3)) of every body as SX expressions of ``x``."""
        import mujoco

        m = self.model
        p_root, R_root, q = self._split(x)
        pos = [ca.SX.zeros(3, 1)] * m.nbody
        rot = [ca.SX.eye(3)] * m.nbody
        for b in range(1, m.nbody):
            parent = int(m.body_parentid[b])
            xb = pos[parent] + rot[parent] @ ca.DM(m.body_pos[b])
            Rb = rot[parent] @ ca.DM(quat_to_mat(m.body_quat[b]))
            for j in self._body_joints.get(b, []):
                jt = m.jnt_type[j]
                if jt == mujoco.mjtJoint.mjJNT_FREE:
                    if self.floating:
                        xb, Rb = p_root, R_root
                    else:
                        xb, Rb = ca.DM(self._fixed_root_pose[0]), ca.DM(self._fixed_root_pose[1])
                elif jt == mujoco.mjtJoint.mjJNT_HINGE:
                    h = self._hinge_by_jid[j]
                    anchor = xb + Rb @ ca.DM(h.anchor)
                    Rb = Rb @ _axis_rotation(h.axis / np.linalg.norm(h.axis), q[h.index] - h.qpos0)
                    xb = anchor - Rb @ ca.DM(h.anchor)
            pos[b], rot[b] = xb, Rb
        return pos, rot

    # -- lookup -------------------------------------------------------------
    def body_id(self, name: str, field: str = "body") -> int:
        import mujoco

        bid = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, name)
        if bid < 0:
            names = [mujoco.mj_id2name(self.model, mujoco.mjtObj.mjOBJ_BODY, b) for b in range(1, self.model.nbody)]
            raise RetargetError(
                f"{field}: the MJCF {self.source or self.name} has no body {name!r}; "
                f"bodies are: {', '.join(n for n in names if n)}"
            )
        return int(bid)

    def site_id(self, name: str, field: str = "site") -> int:
        import mujoco

        sid = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_SITE, name)
        if sid < 0:
            names = [mujoco.mj_id2name(self.model, mujoco.mjtObj.mjOBJ_SITE, s) for s in range(self.model.nsite)]
            raise RetargetError(
                f"{field}: the MJCF {self.source or self.name} has no site {name!r}; "
                f"sites are: {', '.join(n for n in names if n) or '(none)'}"
            )
        return int(sid)

    def geom_id(self, name: str, field: str = "geom") -> int:
        import mujoco

        gid = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_GEOM, name)
        if gid < 0:
            raise RetargetError(
                f"{field}: the MJCF {self.source or self.name} has no geom {name!r}; "
                "name the geom in the MJCF or give body/from/to/radius"
            )
        return int(gid)

    def joint_index(self, name: str, field: str = "joint") -> int:
        if name not in self.joint_names:
            raise RetargetError(
                f"{field}: the MJCF {self.source or self.name} has no hinge joint {name!r}; "
                f"joints are: {', '.join(self.joint_names)}"
            )
        return self.joint_names.index(name)

    # -- symbolic quantities --------------------------------------------------
    @property
    def x_sym(self) -> ca.SX:
        """The configuration symbol (nx, 1) that every expression below depends on."""
        return self._x

    def body_frame(self, body: int):
        """(position (3,1), rotation (3,3)) SX of body ``body`` in the world."""
        return self._frames[0][body], self._frames[1][body]

    def point(self, body: int, local=(0.0, 0.0, 0.0)) -> ca.SX:
        """World position (3,1) of a point fixed at ``local`` (3,) in ``body``'s frame."""
        p, R = self.body_frame(body)
        return p + R @ ca.DM(np.asarray(local, dtype=np.float64))

    def site_point(self, site: int) -> ca.SX:
        return self.point(int(self.model.site_bodyid[site]), self.model.site_pos[site])

    def com(self) -> ca.SX:
        """Centre of mass (3,1): c = Σ_b m_b (x_b + R_b · ipos_b) / Σ_b m_b."""
        m = self.model
        acc = ca.SX.zeros(3, 1)
        for b in range(1, m.nbody):
            if m.body_mass[b] > 0:
                acc += float(m.body_mass[b]) * self.point(b, m.body_ipos[b])
        return acc / self.total_mass

    def capsule_from_geom(self, geom: int, name: str = "") -> Capsule:
        """The capsule of an MJCF capsule geom (or the axis of a cylinder / a box's long axis)."""
        import mujoco

        m = self.model
        gt = int(m.geom_type[geom])
        R = quat_to_mat(m.geom_quat[geom])
        size = m.geom_size[geom]
        if gt in (int(mujoco.mjtGeom.mjGEOM_CAPSULE), int(mujoco.mjtGeom.mjGEOM_CYLINDER)):
            half, radius, axis = size[1], size[0], R[:, 2]
        elif gt == int(mujoco.mjtGeom.mjGEOM_SPHERE):
            half, radius, axis = 0.0, size[0], R[:, 2]
        elif gt == int(mujoco.mjtGeom.mjGEOM_BOX):
            k = int(np.argmax(size))
            others = [size[i] for i in range(3) if i != k]
            half, radius, axis = size[k] - min(others), float(np.hypot(*others)), R[:, k]
        else:
            raise RetargetError(
                f"collision geom {name or geom}: type {int(gt)} is not a capsule, cylinder, sphere or box; "
                "give body/from/to/radius instead"
            )
        c = np.array(m.geom_pos[geom])
        return Capsule(name or f"geom{geom}", int(m.geom_bodyid[geom]), c - half * axis, c + half * axis, float(radius))

    def capsule_segment(self, cap: Capsule) -> tuple[ca.SX, ca.SX]:
        """World end points (3,1), (3,1) of the capsule's axis segment; for a sphere (p0 = p1)
        both are the same object, so distance functions can use the point formulas."""
        p0 = self.point(cap.body, cap.p0)
        return (p0, p0) if np.array_equal(cap.p0, cap.p1) else (p0, self.point(cap.body, cap.p1))

    # -- numeric helpers ------------------------------------------------------
    def function(self, name: str, outputs: list, labels: list[str] | None = None) -> ca.Function:
        """A CasADi Function of ``x`` returning ``outputs`` (SX expressions built from ``x_sym``)."""
        return ca.Function(name, [self._x], outputs, ["x"], labels or [f"o{i}" for i in range(len(outputs))])

    def x_from_qpos(self, qpos: np.ndarray) -> np.ndarray:
        """MuJoCo qpos (nq,) → configuration vector x (nx,)."""
        qpos = np.asarray(qpos, dtype=np.float64)
        joints = np.array([qpos[h.qpos_adr] for h in self.joints])
        if not self.floating:
            return joints
        adr = self.model.jnt_qposadr[self._free_joint]
        R = quat_to_mat(qpos[adr + 3 : adr + 7])
        return np.concatenate([qpos[adr : adr + 3], mat_to_euler(R), joints])

    def qpos_from_x(self, x: np.ndarray) -> np.ndarray:
        """Configuration vector x (nx,) → MuJoCo qpos (nq,) (other coordinates at qpos0)."""
        x = np.asarray(x, dtype=np.float64)
        qpos = np.array(self.model.qpos0, dtype=np.float64)
        for h in self.joints:
            qpos[h.qpos_adr] = x[self.n_root + h.index]
        if self.floating:
            adr = self.model.jnt_qposadr[self._free_joint]
            qpos[adr : adr + 3] = x[0:3]
            qpos[adr + 3 : adr + 7] = mat_to_quat(euler_to_mat(x[3:6]))
        return qpos

    def root_pose(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Root (T, 3) positions and (T, 4) wxyz quaternions of configurations X (T, nx).

        For a fixed base this is the (constant) pose of the root body."""
        X = np.atleast_2d(np.asarray(X, dtype=np.float64))
        T = X.shape[0]
        if self.floating:
            Rs = np.stack([euler_to_mat(e) for e in X[:, 3:6]])
            return X[:, 0:3].copy(), mat_to_quat(Rs)
        if self._fixed_root_pose is not None:
            p, R = self._fixed_root_pose
        else:
            m = self.model
            p, R = np.array(m.body_pos[self.root_body]), quat_to_mat(m.body_quat[self.root_body])
        return np.tile(p, (T, 1)), np.tile(mat_to_quat(R[None])[0], (T, 1))

    def x_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Box bounds (nx,), (nx,) on x from the MJCF: joint ranges; root pitch inside ±80°."""
        lo = np.full(self.nx, -np.inf)
        hi = np.full(self.nx, np.inf)
        if self.floating:
            lo[4], hi[4] = -_PITCH_LIMIT, _PITCH_LIMIT
        for h in self.joints:
            lo[self.n_root + h.index] = h.lower
            hi[self.n_root + h.index] = h.upper
        return lo, hi

    def fingerprint(self) -> str:
        """A hash of everything the kinematics depend on (for compiled-code caches)."""
        import hashlib

        m = self.model
        h = hashlib.sha256()
        for arr in (
            m.body_parentid,
            m.body_pos,
            m.body_quat,
            m.body_ipos,
            m.body_mass,
            m.jnt_type,
            m.jnt_bodyid,
            m.jnt_axis,
            m.jnt_pos,
            m.jnt_range,
            m.jnt_limited,
            m.qpos0,
            m.site_bodyid,
            m.site_pos,
            m.geom_bodyid,
            m.geom_pos,
            m.geom_quat,
            m.geom_size,
            m.geom_type,
        ):
            h.update(np.ascontiguousarray(arr).tobytes())
        h.update(repr((self.floating, self.joint_names)).encode())
        return h.hexdigest()

"""A robot ready for retargeting: its symbolic kinematics bound to its retarget profile.

``load_robot("op3")`` asks the robot registry (:mod:`firmware_cfg.registry`) for the
robot's folder: its MJCF and its ``profile.yaml``. A robot folder, an MJCF path or a
hardware config works too; a profile can be given explicitly. An MJCF outside a robot
folder has no profile of its own: give one, or make the folder with ``robot init``.

Everything the solvers need per frame is a CasADi expression of the configuration
vector ``x`` (see :mod:`retarget.kinematics`):

- ``keypoints(x)``: (3, K) world positions of the profile's robot points;
- ``sole(x)``: (3, 8) the four sole corners of the left then the right foot;
- ``com(x)``: (3, 1) the centre of mass;
- ``collision(x)``: (P, 1) squared distance between the axis segments of each capsule
  pair minus (r_a + r_b + margin)², ≥ 0 when the pair is apart (the real test: the report
  counts self-collisions with it);
- ``offline_collision(x)``: (P', 1) what the offline solver keeps ≥ 0 instead: the pairs
  between the two feet as rows of a separating plane along the feet's own lateral axis
  (:class:`Separation`, smooth and conservative), the other pairs as ``collision``.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import numpy as np

from dualflow.motion.skeleton import JOINT_NAMES, PARENTS
from retarget.actuation import acceleration_limits
from retarget.errors import RetargetError
from retarget.kinematics import Capsule, RobotKinematics, quat_to_mat
from retarget.profile import RetargetProfile


def segment_distance_sq(p0, p1, q0, q1, eps: float = 1e-12):
    """Squared distance between segments p0p1 and q0q1 ((3,1) CasADi or numpy).

    With u = p1 − p0, v = q1 − q0, w = p0 − q0, a = u·u, b = u·v, c = v·v, d = u·w, e = v·w:
    s = clamp((b e − c d) / (a c − b²)), t = clamp((b s + e) / c), s = clamp((b t − d) / a);
    the closest points are p0 + s u and q0 + t v (Ericson, Real-Time Collision Detection §5.1.9).
    A sphere is a segment whose end points are the same object (``p0 is p1``, as
    :meth:`RobotKinematics.capsule_segment` returns for a capsule with p0 = p1); a sphere's
    centre q against a segment uses s = clamp((q − p0)·u / u·u).
    """
    lib = ca if isinstance(p0, (ca.SX, ca.MX)) else np
    dot = (lambda x, y: ca.dot(x, y)) if lib is ca else (lambda x, y: float(np.dot(np.ravel(x), np.ravel(y))))
    if p0 is p1 and q0 is not q1:  # a sphere's centre against a segment
        p0, p1, q0, q1 = q0, q1, p0, p1
    if q0 is q1:
        # point q0 against segment p0p1: s = clamp((q0 − p0)·u / u·u), well conditioned whatever
        # the directions (the general formula below divides by a c − b², which vanishes for
        # parallel segments such as two feet side by side)
        u = p1 - p0
        clamp = (lambda x: ca.fmin(ca.fmax(x, 0), 1)) if lib is ca else (lambda x: min(max(x, 0.0), 1.0))
        s = clamp(dot(q0 - p0, u) / (dot(u, u) + eps)) if p0 is not p1 else 0.0
        diff = p0 + s * u - q0
        return dot(diff, diff)
    u, v, w = p1 - p0, q1 - q0, p0 - q0
    a, b, c, d, e = dot(u, u) + eps, dot(u, v), dot(v, v) + eps, dot(u, w), dot(v, w)
    den = a * c - b * b
    clamp = (lambda x: ca.fmin(ca.fmax(x, 0), 1)) if lib is ca else (lambda x: min(max(x, 0.0), 1.0))
    s = clamp((b * e - c * d) / (den + eps))
    t = clamp((b * s + e) / c)
    s = clamp((b * t - d) / a)
    diff = w + s * u - t * v
    return dot(diff, diff)


@dataclass(frozen=True)
class Separation:
    """Capsule pairs as rows of separating planes: a smooth, conservative stand-in for the
    segment distance, for the offline solver.

    The pairs are grouped by their two bodies (A, B); group g has one unit normal n_g (the
    caller supplies it; for the feet, the feet's own lateral axis). A capsule is the convex
    hull of the spheres at its axis' end points, so if every end point a_i of a capsule on A
    (radius r_a) and b_j of its partner on B (radius r_b) satisfies

        n_g·(a_i − b_j) ≥ r_a + r_b + margin                                      (one row each)

    then the plane n_g·p = min_i n_g·a_i − r_a − margin/2 separates the two capsules with
    ``margin`` to spare: the real segment-distance test of the pair holds. Unlike the squared
    segment distance, a row is smooth in x (no closest-point case switches, and its gradient
    does not vanish when the segments are parallel or cross), which is what IPOPT needs; the
    price is that a pair cannot pass to the other side of its plane.

    Rows are deduplicated: an end point shared by several capsules is one vertex, and a vertex
    on the segment between two others of the same body and radius (e.g. the middle of a sole
    edge) adds only rows implied by theirs, so it is dropped (linearly dependent active rows
    would break IPOPT's constraint qualification).

    groups (G, 2) body ids (a pair given as (B, A) joins group (A, B)); vertices: (body, local
    (3,), radius) each; rows (R, 3) int: group, vertex on A, vertex on B; clearance (R,) m.
    """

    groups: tuple
    vertices: tuple
    rows: np.ndarray
    clearance: np.ndarray

    @property
    def n_groups(self) -> int:
        return len(self.groups)

    @property
    def n_rows(self) -> int:
        return int(self.rows.shape[0])


def build_separation(capsules: dict, pairs, margin: float) -> Separation:
    """The :class:`Separation` of the capsule ``pairs`` (names into ``capsules``)."""
    verts, vindex, groups, rows = [], {}, [], {}

    def vid(body, p, r):
        key = (body, tuple(np.round(np.asarray(p, float), 12)), round(float(r), 12))
        if key not in vindex:
            vindex[key] = len(verts)
            verts.append((int(body), np.asarray(p, float), float(r)))
        return vindex[key]

    def ends(c):
        return [c.p0] if np.array_equal(c.p0, c.p1) else [c.p0, c.p1]

    for a, b in pairs:
        A, B = capsules[a], capsules[b]
        if (B.body, A.body) in groups and (A.body, B.body) not in groups:
            A, B = B, A  # the group's own order
        if (A.body, B.body) not in groups:
            groups.append((A.body, B.body))
        g = groups.index((A.body, B.body))
        for pa in ends(A):
            for pb in ends(B):
                rows[(g, vid(A.body, pa, A.radius), vid(B.body, pb, B.radius))] = A.radius + B.radius + margin

    def between(v):
        """Pairs (u, w) of other vertices of v's body and radius with v on the segment uw."""
        body, p, r = verts[v]
        out = []
        for u in range(len(verts)):
            for w in range(u + 1, len(verts)):
                if v in (u, w) or verts[u][0] != body or verts[w][0] != body or verts[u][2] != r or verts[w][2] != r:
                    continue
                d = verts[w][1] - verts[u][1]
                tau = float(np.dot(p - verts[u][1], d) / max(np.dot(d, d), 1e-30))
                if 0.0 <= tau <= 1.0 and np.linalg.norm(verts[u][1] + tau * d - p) < 1e-9:
                    out.append((u, w))
        return out

    keep = {}
    for (g, va, vb), c in rows.items():
        implied = any((g, u, vb) in rows and (g, w, vb) in rows for u, w in between(va)) or any(
            (g, va, u) in rows and (g, va, w) in rows for u, w in between(vb)
        )
        if not implied:
            keep[(g, va, vb)] = c
    return Separation(
        tuple(groups),
        tuple(verts),
        np.array(list(keep), dtype=int).reshape(-1, 3),
        np.array(list(keep.values()), dtype=float),
    )


@dataclass(frozen=True)
class Foot:
    """Sole corners (4, 3) and the same corners shrunk by the balance margin, body frame, m."""

    side: str
    body: int
    corners: np.ndarray
    normal_local: np.ndarray


class RetargetRobot:
    """Kinematics + profile, validated against each other, with the per-frame CasADi functions."""

    def __init__(self, kin: RobotKinematics, profile: RetargetProfile, mjcf_text: str = ""):
        self.kin = kin
        self.profile = profile
        self.name = profile.robot or kin.name
        #: How to find this robot again (registry reference): the bundled name, or the path it
        #: was loaded from; trajectories carry it so that ``check``/``render`` load the same model.
        self.ref = self.name
        src = profile.source or "profile"
        self._mjcf_hash = hashlib.sha256(mjcf_text.encode()).hexdigest() if mjcf_text else kin.fingerprint()
        self._bind_keypoints(src)
        self.x_lower, self.x_upper = self._position_limits(src)
        self.velocity_limits = self._velocity_limits(src)
        #: (n_joints,) rad/s²: what each joint's servo can give its links
        #: (:func:`retarget.actuation.acceleration_limits`); plans keep within it, and so does
        #: the bridge's safety filter
        self.acceleration_limits = acceleration_limits(kin.model, kin.joint_names)
        self.x_stand = self._stand_pose(src)
        self.feet: list[Foot] = [self._foot(side, src) for side in ("left", "right")] if profile.feet else []
        self.capsules: dict[str, Capsule] = self._bind_capsules(src)
        self.collision_pairs = tuple(profile.collision_pairs)
        self._build_functions()
        self._rest_scales()

    # -- construction helpers --------------------------------------------------
    def _bind_keypoints(self, src: str) -> None:
        """The profile's keypoints as (body id, point in the body frame (3,) m), their human joints and weights."""
        kin = self.kin
        pts, self.keypoint_names, self.human_index, weights = [], [], [], []
        for spec in self.profile.keypoints:
            if spec.site is not None:
                sid = kin.site_id(spec.site, f"{src}: field keypoints.{spec.human}.site")
                body, local = int(kin.model.site_bodyid[sid]), np.array(kin.model.site_pos[sid])
            else:
                body = kin.body_id(spec.body, f"{src}: field keypoints.{spec.human}.body")
                local = np.array(spec.offset)
            pts.append((body, local))
            self.keypoint_names.append(spec.human)
            self.human_index.append(JOINT_NAMES.index(spec.human))
            weights.append(spec.weight)
        self.keypoint_points = pts
        self.human_index = np.array(self.human_index)
        self.keypoint_weights = np.array(weights, dtype=float)
        self.n_keypoints = len(pts)
        self.root_keypoint = self.keypoint_names.index(self.profile.root_joint)

    def _position_limits(self, src: str) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper) (nx,) of x: the MJCF ranges narrowed by the profile's joint_limits."""
        kin = self.kin
        lo, hi = kin.x_bounds()
        for jname, (jlo, jhi) in self.profile.joint_limits.items():
            i = kin.n_root + kin.joint_index(jname, f"{src}: field joint_limits.{jname}")
            if jlo < lo[i] - 1e-9 or jhi > hi[i] + 1e-9:
                raise RetargetError(
                    f"{src}: field joint_limits.{jname}: [{jlo:.4f}, {jhi:.4f}] is wider than the MJCF range "
                    f"[{lo[i]:.4f}, {hi[i]:.4f}]; profile limits may only narrow the MJCF's"
                )
            lo[i], hi[i] = jlo, jhi
        unlimited = [
            h.name
            for h in kin.joints
            if not (np.isfinite(lo[kin.n_root + h.index]) and np.isfinite(hi[kin.n_root + h.index]))
        ]
        if unlimited:
            raise RetargetError(
                f"{kin.source or kin.name}: joints {unlimited} have no range; "
                f"give them range= in the MJCF or joint_limits in {src}"
            )
        return lo, hi

    def _velocity_limits(self, src: str) -> np.ndarray:
        """Joint speed limits (n_joints,) rad/s: the profile's, never above the MJCF's servo speed."""
        kin, profile = self.kin, self.profile
        ceiling = self._mjcf_speed_limits()
        vel = np.minimum(np.full(kin.n_joints, profile.velocity_default), ceiling)
        for jname, v in profile.velocity_limits.items():
            i = kin.joint_index(jname, f"{src}: field velocity_limits.{jname}")
            if v > ceiling[i] + 1e-9:
                raise RetargetError(
                    f"{src}: field velocity_limits.{jname}: {v} rad/s is above the MJCF's servo no-load "
                    f"speed {ceiling[i]} rad/s; profile limits may only narrow the MJCF's"
                )
            vel[i] = v
        return vel

    def _foot(self, side: str, src: str) -> Foot:
        """One foot from the profile: its body and sole corners (a box geom's lowest face, or given)."""
        kin, spec = self.kin, self.profile.feet[side]
        body = kin.body_id(spec.body, f"{src}: field feet.{side}.body")
        if spec.geom is not None:
            gid = kin.geom_id(spec.geom, f"{src}: field feet.{side}.geom")
            if int(kin.model.geom_bodyid[gid]) != body:
                raise RetargetError(f"{src}: field feet.{side}.geom: geom {spec.geom!r} is not on body {spec.body!r}")
            corners, normal = self._sole_from_box(gid, src, side)
        else:
            corners = np.array(spec.corners, dtype=float)
            n = np.cross(corners[1] - corners[0], corners[2] - corners[0])
            normal = -n / np.linalg.norm(n)
        return Foot(side, body, corners, normal)

    def _bind_capsules(self, src: str) -> dict:
        """name -> Capsule, from an MJCF geom or the profile's segment and radius."""
        kin, caps = self.kin, {}
        for name, spec in self.profile.capsules.items():
            if spec.geom is not None:
                gid = kin.geom_id(spec.geom, f"{src}: field capsules.{name}.geom")
                caps[name] = kin.capsule_from_geom(gid, name)
            else:
                body = kin.body_id(spec.body, f"{src}: field capsules.{name}.body")
                caps[name] = Capsule(name, body, np.array(spec.p0), np.array(spec.p1), float(spec.radius))
        return caps

    def _mjcf_speed_limits(self) -> np.ndarray:
        """Per-joint speed ceiling (rad/s) from the MJCF's ``<numeric name="servo_no_load_speed">``
        (one value for all joints, or one per actuator in actuator = joint order); +inf if absent."""
        import mujoco

        m, kin = self.kin.model, self.kin
        nid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_NUMERIC, "servo_no_load_speed")
        out = np.full(kin.n_joints, np.inf)
        if nid < 0:
            return out
        adr, size = int(m.numeric_adr[nid]), int(m.numeric_size[nid])
        data = np.array(m.numeric_data[adr : adr + size])
        if size == 1:
            return np.full(kin.n_joints, float(data[0]))
        if size == m.nu == kin.n_joints:
            for a in range(m.nu):
                jadr = int(m.jnt_qposadr[m.actuator_trnid[a, 0]])
                for h in kin.joints:
                    if h.qpos_adr == jadr:
                        out[h.index] = data[a]
        return out

    def _stand_pose(self, src: str) -> np.ndarray:
        import mujoco

        m = self.kin.model
        kid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, self.profile.stand_keyframe)
        qpos = np.array(m.key_qpos[kid]) if kid >= 0 else np.array(m.qpos0)
        for name, angle in self.profile.stand_pose:  # checked even where a keyframe takes its place
            j = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, name)
            if j < 0 or m.jnt_type[j] != mujoco.mjtJoint.mjJNT_HINGE:
                raise RetargetError(f"{src}: field stand_pose.{name}: the MJCF has no hinge joint {name!r}")
            if kid < 0:
                qpos[m.jnt_qposadr[j]] = angle
        x = self.kin.x_from_qpos(qpos)
        return np.clip(x, self.x_lower, self.x_upper)

    def _sole_from_box(self, gid: int, src: str, side: str):
        import mujoco

        m = self.kin.model
        if int(m.geom_type[gid]) != int(mujoco.mjtGeom.mjGEOM_BOX):
            raise RetargetError(f"{src}: field feet.{side}.geom: the sole geom must be a box; give corners: instead")
        Rg = quat_to_mat(m.geom_quat[gid])
        size = np.array(m.geom_size[gid])
        # the sole is the box face whose outward normal points most downward in the stand pose
        Rb = np.array(
            ca.Function("Rb", [self.kin.x_sym], [self.kin.body_frame(int(m.geom_bodyid[gid]))[1]])(self.x_stand)
        )
        best = None
        for axis in range(3):
            for sign in (-1.0, 1.0):
                n_local = sign * Rg[:, axis]
                nz = float((Rb @ n_local)[2])
                if best is None or nz < best[0]:
                    best = (nz, axis, sign, n_local)
        _, axis, sign, n_local = best
        others = [a for a in range(3) if a != axis]
        c = np.array(m.geom_pos[gid]) + sign * size[axis] * Rg[:, axis]
        corners = [
            c + s1 * size[others[0]] * Rg[:, others[0]] + s2 * size[others[1]] * Rg[:, others[1]]
            for s1, s2 in ((1, 1), (1, -1), (-1, -1), (-1, 1))
        ]
        return np.array(corners), n_local

    def _build_functions(self) -> None:
        kin, x = self.kin, self.kin.x_sym
        kp = ca.horzcat(*[kin.point(b, local) for b, local in self.keypoint_points])
        self.keypoints_expr = kp
        sole = [kin.point(f.body, c) for f in self.feet for c in f.corners]
        self.sole_expr = ca.horzcat(*sole) if sole else ca.SX.zeros(3, 0)
        self.com_expr = kin.com()
        coll = []
        for a, b in self.collision_pairs:
            ca_, cb = self.capsules[a], self.capsules[b]
            p0, p1 = kin.capsule_segment(ca_)
            q0, q1 = kin.capsule_segment(cb)
            r = ca_.radius + cb.radius + self.profile.collision_margin
            coll.append(segment_distance_sq(p0, p1, q0, q1) - r * r)
        self.collision_expr = ca.vertcat(*coll) if coll else ca.SX.zeros(0, 1)
        self._build_offline_collision()
        self.f_keypoints = ca.Function("keypoints", [x], [kp])
        self.f_all = ca.Function(
            "robot_points",
            [x],
            [kp, self.sole_expr, self.com_expr, self.collision_expr],
            ["x"],
            ["keypoints", "sole", "com", "collision"],
        )

    def _build_offline_collision(self) -> None:
        """``offline_collision_expr`` (P', 1) and its row labels ``offline_collision_labels``.

        Pairs with one capsule on each foot's body become :class:`Separation` rows with the
        normal n = the feet's common lateral axis: with f_L, f_R the horizontal parts of the two
        soles' long (heel → toe) axes, f = (f_L + f_R)/‖f_L + f_R‖ and n = (−f_y, f_x, 0), the
        left foot's side. The rows are smooth in x and turn with the feet, not with the pelvis
        (a twisted pelvis over planted feet would tip a pelvis-fixed plane). Conservative: the
        left foot's capsules stay on their side of a plane along the feet, so feet that pass
        each other fore and aft still may not cross sideways (the offline solver's warm start,
        :func:`retarget.offline.feet_apart`, keeps them on their own sides too). The soles are
        the pairs near contact in most frames, where the segment distance's closest-point case
        switches cost IPOPT most of its iterations (CMU pair: 34 → 22 per window). Other pairs
        keep the squared segment distance (``collision_expr``); rows are ≥ 0 when apart."""
        kin = self.kin
        pairs = list(self.collision_pairs)
        foot_bodies = {f.body for f in self.feet} if len(self.feet) == 2 else set()
        is_foot = [
            len(foot_bodies) == 2 and {self.capsules[a].body, self.capsules[b].body} == foot_bodies for a, b in pairs
        ]
        rows = [self.collision_expr[k] for k in range(len(pairs)) if not is_foot[k]]
        labels = [f"{a}/{b}" for k, (a, b) in enumerate(pairs) if not is_foot[k]]
        left = self.feet[0].body if self.feet else -1
        # the left foot's capsules first, so that the normal points from the right foot to the left
        foot_pairs = [
            (a, b) if self.capsules[a].body == left else (b, a) for k, (a, b) in enumerate(pairs) if is_foot[k]
        ]
        self.separation = build_separation(self.capsules, foot_pairs, self.profile.collision_margin)
        sep = self.separation
        if sep.n_rows:
            fwd = []
            for foot in self.feet:
                c = foot.corners
                edges = [c[1] - c[0], c[2] - c[1]]
                e = edges[int(np.argmax([np.linalg.norm(v) for v in edges]))]
                e = e / np.linalg.norm(e)
                R = kin.body_frame(foot.body)[1]
                if float((np.array(ca.Function("R", [kin.x_sym], [R])(self.x_stand)) @ e)[0]) < 0:
                    e = -e  # heel → toe: along the robot's forward (+x) in the stand pose
                fwd.append(R @ ca.DM(e))
            f = fwd[0][0:2] + fwd[1][0:2]
            f = f / ca.sqrt(ca.sumsqr(f))
            n = ca.vertcat(-f[1], f[0], 0)
            V = ca.horzcat(*[kin.point(body, p) for body, p, _ in sep.vertices])
            D = V[:, sep.rows[:, 1].tolist()] - V[:, sep.rows[:, 2].tolist()]
            plane = (ca.mtimes(n.T, D) - ca.DM(sep.clearance).T).T
            rows += [plane[i] for i in range(sep.n_rows)]
            vname = [f"{kin.model.body(body).name}@{np.round(p, 4).tolist()}" for body, p, _ in sep.vertices]
            labels += [f"sole plane {vname[va]}/{vname[vb]}" for _, va, vb in sep.rows]
        self.offline_collision_expr = ca.vertcat(*rows) if rows else ca.SX.zeros(0, 1)
        self.offline_collision_labels = tuple(labels)

    def _rest_scales(self) -> None:
        """Per-keypoint bone scale s_k = |r_k − r_parent(k)| / |h_k − h_parent(k)| from the robot at
        q = 0 (root at the origin, upright) and the SMPL REST_POSE; parent(k) is the nearest human
        ancestor that is also a keypoint. The root scale is the ratio of standing root heights."""
        src = self.profile.source or "profile"
        x0 = np.zeros(self.kin.nx)
        for h in self.kin.joints:
            x0[self.kin.n_root + h.index] = h.qpos0
        rest_kp, rest_sole, _, _ = (np.array(v) for v in self.f_all(x0))
        self.robot_rest_keypoints = rest_kp.T
        parent = []
        for k, j in enumerate(self.human_index):
            a = PARENTS[j]
            while a >= 0 and a not in self.human_index:
                a = PARENTS[a]
            if k == self.root_keypoint:
                parent.append(-1)
                continue
            if a < 0:
                raise RetargetError(
                    f"{src}: field root: keypoint {self.keypoint_names[k]!r} is not below the root joint "
                    f"{self.profile.root_joint!r} in the SMPL tree; use pelvis as the root"
                )
            parent.append(int(np.flatnonzero(self.human_index == a)[0]))
        self.keypoint_parent = np.array(parent)
        #: robot rest length of the bone ending at each keypoint (m; 0 for the root)
        self.bone_lengths = np.array(
            [np.linalg.norm(rest_kp[:, k] - rest_kp[:, p]) if p >= 0 else 0.0 for k, p in enumerate(parent)]
        )
        #: robot rest offset (3,) from the parent keypoint, world = root frame at q = 0 (m)
        self.rest_offsets = np.array(
            [rest_kp[:, k] - rest_kp[:, p] if p >= 0 else np.zeros(3) for k, p in enumerate(parent)]
        )
        ground = rest_sole[2].min() if rest_sole.size else rest_kp[2].min()
        #: height of the root keypoint above the lowest sole point at q = 0 (m)
        self.standing_root_height = float(rest_kp[2, self.root_keypoint] - ground)
        lin = self.profile.root_linear if self.profile.root_linear is not None else 2.0 * self.standing_root_height
        #: speed limits of the free root's (x, y, z) m/s and (yaw, pitch, roll) rad/s
        self.root_velocity_limits = np.array([lin] * 3 + [self.profile.root_angular] * 3)[: self.n_root]
        #: height of each keypoint above the lowest sole point at q = 0 (m)
        self.standing_heights = rest_kp[2] - ground

    def narrow_limits(self, names, max_velocity, max_acceleration) -> RetargetRobot:
        """Plan within other limits as well (the bridge's loop's for this robot: joint ``names``,
        rad/s and rad/s² per name): each named joint's speed and acceleration limit becomes the
        lower of its own and the given. Returns self."""
        src = self.profile.source or "profile"
        idx = [self.kin.joint_index(n, f"{src}: joint {n!r} of the limits to plan within") for n in names]
        self.velocity_limits[idx] = np.minimum(self.velocity_limits[idx], np.asarray(max_velocity, dtype=float))
        self.acceleration_limits[idx] = np.minimum(
            self.acceleration_limits[idx], np.asarray(max_acceleration, dtype=float)
        )
        return self

    # -- facts ------------------------------------------------------------------
    @property
    def joint_names(self) -> tuple[str, ...]:
        return self.kin.joint_names

    @property
    def nx(self) -> int:
        return self.kin.nx

    @property
    def n_root(self) -> int:
        return self.kin.n_root

    @property
    def floating(self) -> bool:
        return self.kin.floating

    @property
    def has_feet(self) -> bool:
        return bool(self.feet)

    def fingerprint(self) -> str:
        """Hash of model + profile + base mode, the key of compiled-code caches."""
        h = hashlib.sha256()
        h.update(self._mjcf_hash.encode())
        h.update(self.kin.fingerprint().encode())
        h.update(self.profile.fingerprint().encode())
        return h.hexdigest()[:16]

    def evaluate(self, X: np.ndarray) -> dict:
        """Numeric keypoints (T, K, 3), sole (T, 8, 3), com (T, 3), collision (T, P) for X (T, nx)."""
        X = np.atleast_2d(X)
        f = self.f_all.map(X.shape[0])
        kp, sole, com, coll = f(X.T)
        kp = np.array(kp).reshape(3, X.shape[0], -1).transpose(1, 2, 0)
        sole = np.array(sole).reshape(3, X.shape[0], -1).transpose(1, 2, 0)
        return {"keypoints": kp, "sole": sole, "com": np.array(com).T, "collision": np.array(coll).T}


def resolve_paths(robot: str | Path, profile: str | Path | None = None) -> tuple[Path, Path]:
    """(MJCF path, profile path) for a robot reference (a bundled name, a robot folder, an
    MJCF or a hardware config; see :func:`firmware_cfg.registry.resolve`)."""
    from firmware_cfg.errors import ConfigError
    from firmware_cfg.registry import resolve

    try:
        found = resolve(robot)
        if profile is not None:
            prof = Path(profile)
            if not prof.is_file():
                raise RetargetError(f"--profile {prof}: file not found")
            return found.mjcf, prof
        return found.mjcf, found.require_profile()
    except ConfigError as exc:
        raise RetargetError(str(exc)) from None


def model_path(robot: str | Path) -> Path:
    """The MJCF of a robot reference (no profile needed)."""
    from firmware_cfg.errors import ConfigError
    from firmware_cfg.registry import resolve

    try:
        return resolve(robot).mjcf
    except ConfigError as exc:
        raise RetargetError(str(exc)) from None


def load_robot(
    robot: str | Path, profile: str | Path | RetargetProfile | None = None, fixed_base: bool = False
) -> RetargetRobot:
    """A :class:`RetargetRobot` from a robot reference (a bundled name such as ``"op3"``, a
    robot folder, an MJCF or a hardware config) and its profile (the robot's own by default)."""
    if isinstance(profile, RetargetProfile):
        mjcf = model_path(robot)
        prof = profile
    else:
        mjcf, prof_path = resolve_paths(robot, profile)
        prof = RetargetProfile.load(prof_path)
    kin = RobotKinematics.from_xml(mjcf, name=prof.robot or Path(mjcf).stem, fixed_base=fixed_base)
    rb = RetargetRobot(kin, prof, mjcf_text=Path(mjcf).read_text())
    rb.ref = robot_ref(robot)
    return rb


def robot_ref(robot: str | Path) -> str:
    """The registry reference that finds ``robot`` again from any working directory: a bundled
    robot's name, else the absolute path given."""
    from firmware_cfg.errors import ConfigError
    from firmware_cfg.registry import reference

    try:
        return reference(robot)
    except ConfigError as exc:
        raise RetargetError(str(exc)) from None


def robot_from_xml_string(xml: str, profile: RetargetProfile, fixed_base: bool = False) -> RetargetRobot:
    """A :class:`RetargetRobot` from MJCF text (tests, generated models)."""
    import mujoco

    try:
        model = mujoco.MjModel.from_xml_string(xml)
    except ValueError as exc:
        raise RetargetError(f"MJCF text: MuJoCo cannot load it ({str(exc).splitlines()[0]})") from None
    kin = RobotKinematics(model, profile.robot or "robot", fixed_base=fixed_base, source="MJCF text")
    return RetargetRobot(kin, profile, mjcf_text=xml)

"""A first retarget profile (and a hardware-config skeleton) for any MJCF humanoid, from the model alone.

Contract: ``init_robot_folder(mjcf, out_dir)`` writes a robot folder (see
:mod:`firmware_cfg.registry`): ``profile.yaml`` that retargets without edits, ``hardware.yaml``
that :func:`firmware_cfg.config.load_config` parses as written, with every guessed value marked
``# FILL IN`` (listed by ``robot check``, failed by ``robot check --hardware``), and ``README.md``.
The model is not copied: ``mjcf:`` points to it, relative to the folder; a scene that only
includes the robot is replaced by the robot's file. No body or joint name is read for meaning:
how the legs, arms, joints, feet, capsules, limits and stand pose are found is in
docs/retargeting.md, section 8.
"""

from __future__ import annotations

import math
import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from retarget.errors import RetargetError
from retarget.stand_init import derive_stand_pose

#: The servo model hardware.yaml guesses until the user fills in theirs.
GUESSED_SERVO = "XM430-W350"
#: SMPL rest pose ratios (dualflow.motion.skeleton.REST_POSE): pelvis above the hips, over the
#: hips' height (0.08 / 0.87), and spine3 between pelvis and shoulders (0.30 / 0.45).
PELVIS_ABOVE_HIPS = 0.092
SPINE3_FRACTION = 0.667
TWIST_COS = 0.8
BEND_COS = 0.6
FILL = "# FILL IN"


# ------------------------------------------------------------------------------------- model


def robot_model_file(path: str | Path) -> tuple[Path, str | None]:
    """The robot's own MJCF for ``path``: a scene file whose worldbody has no bodies and which
    ``<include>``s one file with a robot in it gives that file. Returns (path, note or None)."""
    path = Path(path).resolve()
    if not path.is_file():
        raise RetargetError(f"{path}: MJCF file not found")
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise RetargetError(f"{path}: not valid XML ({exc})") from None
    if root.tag != "mujoco":
        raise RetargetError(f"{path}: not an MJCF file (its root element is <{root.tag}>, not <mujoco>)")
    own_bodies = [b for wb in root.iter("worldbody") for b in wb.iter("body")]
    if own_bodies:
        return path, None
    robots = []
    for inc in root.iter("include"):
        f = (path.parent / inc.get("file", "")).resolve()
        try:
            sub = ET.parse(f).getroot()
        except (ET.ParseError, OSError):
            continue
        if any(True for wb in sub.iter("worldbody") for _ in wb.iter("body")):
            robots.append(f)
    if len(robots) == 1:
        return robots[0], f"{path.name} is a scene around {robots[0].name}: the robot folder uses {robots[0].name}"
    return path, None


def load_model(path: str | Path):
    import mujoco

    try:
        return mujoco.MjModel.from_xml_path(str(path))
    except ValueError as exc:
        raise RetargetError(
            f"{path}: MuJoCo cannot load this MJCF ({str(exc).splitlines()[0]}); "
            "fix the model first (`python -m mujoco.viewer --mjcf FILE` shows the same error)"
        ) from None


# ---------------------------------------------------------------------------- geometry


def _fib_dirs(n: int = 48) -> np.ndarray:
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    th = np.pi * (1 + 5**0.5) * i
    return np.stack([np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)], axis=1)


_DIRS = _fib_dirs()


def geom_points_local(m, g: int) -> np.ndarray:
    """Points (N, 3) on or spanning geom ``g``'s surface, in the geom's frame (m)."""
    import mujoco

    t, s = int(m.geom_type[g]), np.array(m.geom_size[g])
    G = mujoco.mjtGeom
    if t == G.mjGEOM_BOX:
        return np.array([[a * s[0], b * s[1], c * s[2]] for a in (-1, 1) for b in (-1, 1) for c in (-1, 1)])
    if t == G.mjGEOM_SPHERE:
        return s[0] * _DIRS
    if t == G.mjGEOM_ELLIPSOID:
        return _DIRS * s[:3]
    if t == G.mjGEOM_CAPSULE:
        return np.vstack([s[0] * _DIRS + [0, 0, s[1]], s[0] * _DIRS - [0, 0, s[1]]])
    if t == G.mjGEOM_CYLINDER:
        a = np.linspace(0, 2 * np.pi, 16, endpoint=False)
        ring = np.stack([s[0] * np.cos(a), s[0] * np.sin(a), np.zeros_like(a)], axis=1)
        return np.vstack([ring + [0, 0, s[1]], ring - [0, 0, s[1]]])
    if t == G.mjGEOM_MESH:
        mid = int(m.geom_dataid[g])
        adr, n = int(m.mesh_vertadr[mid]), int(m.mesh_vertnum[mid])
        return np.array(m.mesh_vert[adr : adr + n], dtype=float)
    return np.zeros((0, 3))  # planes, height fields: not part of a robot's body


def _bottom_points_local(m, g: int, down_local: np.ndarray) -> np.ndarray:
    """The lowest points of a round geom exactly (sphere: its bottom; capsule: both ends'
    bottoms); others: their point cloud (the caller keeps the lowest)."""
    import mujoco

    t, s = int(m.geom_type[g]), np.array(m.geom_size[g])
    if t == mujoco.mjtGeom.mjGEOM_SPHERE:
        return s[0] * down_local[None]
    if t == mujoco.mjtGeom.mjGEOM_CAPSULE:
        return np.array([[0, 0, s[1]], [0, 0, -s[1]]]) + s[0] * down_local[None]
    return geom_points_local(m, g)


@dataclass
class FittedCapsule:
    """A capsule being fitted for the profile, in ``body``'s frame: segment ``p0``-``p1`` (m),
    ``radius`` (m), how far it may shrink to clear a pair that touches at rest (``min_radius``),
    and why it changed (``note``)."""

    name: str
    body: int
    p0: np.ndarray
    p1: np.ndarray
    radius: float
    min_radius: float = 0.0
    note: str = ""


def fit_capsule(points: np.ndarray, axis: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, float]:
    """The capsule (p0, p1, r) that holds every one of ``points`` (N, 3): axis = ``axis`` or the
    principal axis, through the centroid; r = the largest distance to the axis; each end as far
    in as its half-sphere still holds the points beyond it. The retargeter keeps capsules
    ``collision_margin`` apart, so a capsule that left points out let the real geometry touch:
    a 90th-percentile fit left the Unitree G1's thigh and hand points 8-17 mm outside, and its
    streamed hand went 13.5 mm into the hip's geometry while the capsules kept 10 mm apart."""
    c = points.mean(axis=0)
    d = points - c
    if axis is None:
        _, _, vt = np.linalg.svd(d, full_matrices=False)
        axis = vt[0]
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    t = d @ axis
    radial = np.linalg.norm(d - np.outer(t, axis), axis=1)
    r = max(float(radial.max()), 1e-3)
    reach = np.sqrt(np.maximum(r * r - radial * radial, 0.0))  # along the axis, within a half-sphere
    lo, hi = float(np.min(t + reach)), float(np.max(t - reach))
    if hi < lo:
        lo = hi = 0.5 * (lo + hi)
    return c + lo * axis, c + hi * axis, r


def segment_distance(p0, p1, q0, q1) -> float:
    """Distance between segments p0p1 and q0q1 (numpy (3,)), as retarget.robot computes it."""
    from retarget.robot import segment_distance_sq

    a = (p0, p0) if np.array_equal(p0, p1) else (p0, p1)
    b = (q0, q0) if np.array_equal(q0, q1) else (q0, q1)
    return math.sqrt(max(segment_distance_sq(a[0], a[1], b[0], b[1]), 0.0))


# ----------------------------------------------------------------------------- anatomy


@dataclass
class Joint:
    """A hinge of a limb at the rest pose: id, body, world anchor and unit axis."""

    id: int
    body: int
    anchor: np.ndarray
    axis: np.ndarray


@dataclass
class Limb:
    kind: str  # "leg" | "arm"
    side: str  # "left" | "right"
    bodies: list
    joints: list
    end_point: np.ndarray  # world, rest pose
    top: Joint | None = None
    mid: Joint | None = None
    bottom: Joint | None = None  # None: the end point is the ankle/wrist
    foot_body: int | None = None
    sole: dict | None = None  # rest-frame bbox: x0, x1, y0, y1, z; world corners
    points_ankle: np.ndarray | None = None  # ankle/wrist point, world


@dataclass
class Anatomy:
    """What :func:`infer_anatomy` found; body ids into the model, points in the world at rest."""

    root: int
    floating: bool
    height: float
    forward: np.ndarray
    left: np.ndarray
    legs: dict = field(default_factory=dict)
    arms: dict = field(default_factory=dict)
    pelvis_body: int = -1
    chest_body: int = -1
    head_body: int = -1
    points: dict = field(default_factory=dict)  # human joint -> (body, world point, why)
    notes: list = field(default_factory=list)


class _Rest:
    """The model at a pose (default qpos0) with world frames of every body and geom."""

    def __init__(self, m, qpos=None):
        import mujoco

        self.m = m
        self.d = mujoco.MjData(m)
        self.d.qpos[:] = m.qpos0 if qpos is None else qpos
        mujoco.mj_kinematics(m, self.d)
        self.children = [[] for _ in range(m.nbody)]
        for b in range(1, m.nbody):
            self.children[int(m.body_parentid[b])].append(b)
        self.hinges = [[] for _ in range(m.nbody)]
        for j in range(m.njnt):
            if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE:
                self.hinges[int(m.jnt_bodyid[j])].append(j)
        self._below = {}

    def R(self, b: int) -> np.ndarray:
        return self.d.xmat[b].reshape(3, 3)

    def to_local(self, b: int, pw) -> np.ndarray:
        return (np.asarray(pw) - self.d.xpos[b]) @ self.R(b)

    def to_world(self, b: int, pl) -> np.ndarray:
        return self.d.xpos[b] + np.asarray(pl) @ self.R(b).T

    def hinges_below(self, b: int) -> int:
        if b not in self._below:
            self._below[b] = len(self.hinges[b]) + sum(self.hinges_below(c) for c in self.children[b])
        return self._below[b]

    def rigid(self, b: int) -> list:
        """``b`` and the descendants welded to it (no joint on the way)."""
        out, stack = [], [b]
        while stack:
            x = stack.pop()
            out.append(x)
            stack += [c for c in self.children[x] if self.m.body_jntnum[c] == 0]
        return out

    def geoms(self, bodies, collision_only: bool = False) -> list:
        import mujoco

        m = self.m
        out = []
        for g in range(m.ngeom):
            if int(m.geom_bodyid[g]) not in bodies:
                continue
            if int(m.geom_type[g]) in (int(mujoco.mjtGeom.mjGEOM_PLANE), int(mujoco.mjtGeom.mjGEOM_HFIELD)):
                continue
            if collision_only and not (m.geom_contype[g] or m.geom_conaffinity[g]):
                continue
            out.append(g)
        return out

    def points(self, geoms) -> np.ndarray:
        pts = [self.d.geom_xpos[g] + geom_points_local(self.m, g) @ self.d.geom_xmat[g].reshape(3, 3).T for g in geoms]
        pts = [p for p in pts if len(p)]
        return np.vstack(pts) if pts else np.zeros((0, 3))

    def path(self, b: int, root: int) -> list:
        out = []
        while b != root and b > 0:
            out.append(b)
            b = int(self.m.body_parentid[b])
        return out[::-1]


def _dca(rest: _Rest, a: int, b: int) -> int:
    """Deepest common ancestor of bodies a and b."""
    anc = set()
    x = a
    while x >= 0:
        anc.add(x)
        if x == 0:
            break
        x = int(rest.m.body_parentid[x])
    x = b
    while x not in anc:
        x = int(rest.m.body_parentid[x])
    return x


def infer_anatomy(m) -> Anatomy:
    """Legs, arms, head, pelvis and chest of model ``m`` (see the module docstring)."""
    rest = _Rest(m)
    root, free = _pick_root(m, rest)
    Rr = rest.R(root)
    fwd = np.array([Rr[0, 0], Rr[1, 0], 0.0])
    fwd = fwd / np.linalg.norm(fwd) if np.linalg.norm(fwd) > 1e-6 else np.array([1.0, 0.0, 0.0])
    left = np.cross(np.array([0.0, 0.0, 1.0]), fwd)
    subtree = _subtree(rest, root)
    everything = rest.points(rest.geoms(subtree))
    if not len(everything):
        everything = np.array([rest.d.xpos[b] for b in subtree])
    zmin, zmax = float(everything[:, 2].min()), float(everything[:, 2].max())
    fr = _BodyFrame(np.array(rest.d.xpos[root]), fwd, left, max(zmax - zmin, 1e-3), zmin)
    an = Anatomy(root=root, floating=free, height=fr.height, forward=fwd, left=left)
    ends = [
        b for b in subtree if b != root and rest.hinges[b] and all(rest.hinges_below(c) == 0 for c in rest.children[b])
    ]
    info = {e: _end_info(m, rest, e, root) for e in ends}
    legs, in_legs = _find_legs(an, rest, ends, info, fr)
    in_arms = _find_arms(an, rest, ends, info, in_legs, fr)
    # legs: feet first (the leg's end point is the sole's centre), then the joints
    for _side, limb in an.legs.items():
        _find_foot(rest, limb, fwd, left, fr.height)
        _assign_joints(limb)
    for _side, limb in an.arms.items():
        _assign_joints(limb)
    _place_points(rest, an, ends, info, in_legs | in_arms)
    # the toes are farther in front of the ankle than the heel is behind it, on a robot facing +x
    if legs and any(
        limb.sole["x1"] + limb.sole["x0"] < 2 * float(limb.points_ankle @ fwd) - 1e-3 for limb in an.legs.values()
    ):
        an.notes.append(
            "the feet point backwards in the root's frame: the retargeter expects the robot to face its "
            "root body's +x (MuJoCo's convention); check the keypoints' left/right"
        )
    return an


@dataclass(frozen=True)
class _BodyFrame:
    """The robot's frame at rest for telling limbs apart: root body position (3,) m, forward and
    left (3,) horizontal unit vectors, height m (lowest to highest geometry point) and its lowest z m."""

    origin: np.ndarray
    forward: np.ndarray
    left: np.ndarray
    height: float
    zmin: float

    def lateral(self, p) -> float:
        """How far p (3,) m is to the root's left (m)."""
        return float((np.asarray(p) - self.origin) @ self.left)


def _pick_root(m, rest: _Rest) -> tuple[int, bool]:
    """(root body id, floating): the free joint's body, else the top body with most hinges below."""
    import mujoco

    free = [j for j in range(m.njnt) if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE]
    if free:
        root = int(m.jnt_bodyid[free[0]])
    else:
        tops = [b for b in rest.children[0]]
        if not tops:
            raise RetargetError("the model has no bodies")
        root = max(tops, key=rest.hinges_below)
    if rest.hinges_below(root) == 0:
        raise RetargetError("the model has no hinge joints: nothing to retarget")
    return root, bool(free)


def _end_info(m, rest: _Rest, e: int, root: int) -> dict:
    """A chain end e: its geometry's lowest and highest z, centre (3,), the chain's arc length from
    the root (m) and its path of bodies."""
    pts = rest.points(rest.geoms(rest.rigid(e)))
    if not len(pts):
        pts = np.array([rest.d.xpos[e]])
    path = rest.path(e, root)
    arc = sum(float(np.linalg.norm(m.body_pos[b])) for b in path)
    return dict(low=float(pts[:, 2].min()), top=float(pts[:, 2].max()), centre=pts.mean(axis=0), arc=arc, path=path)


def _find_legs(an: Anatomy, rest: _Rest, ends: list, info: dict, fr: _BodyFrame) -> tuple[dict, set]:
    """Legs: the lowest-reaching chain end on each side (both or none); sets an.pelvis_body and
    an.legs. Returns (side -> end body, the bodies in the legs)."""
    H, z_root = fr.height, float(fr.origin[2])
    legs = {}
    for side, sign in (("left", 1), ("right", -1)):
        cand = [
            e
            for e in ends
            if sign * fr.lateral(info[e]["centre"]) > 0.02 * H
            and info[e]["low"] < fr.zmin + 0.1 * H
            and info[e]["low"] < z_root - 0.2 * H
        ]
        if cand:
            legs[side] = min(cand, key=lambda e: (info[e]["low"], -info[e]["arc"]))
    if len(legs) == 1:
        an.notes.append(f"only one leg-like chain found (on the {next(iter(legs))}): treated as a robot without legs")
        legs = {}
    in_legs = set()
    if legs:
        an.pelvis_body = _dca(rest, legs["left"], legs["right"])
        for side, e in legs.items():
            chain = _truncate(rest, rest.path(e, an.pelvis_body))
            an.legs[side] = _limb(rest, "leg", side, chain, None)
            in_legs |= _subtree(rest, chain[0])
    return legs, in_legs


def _find_arms(an: Anatomy, rest: _Rest, ends: list, info: dict, in_legs: set, fr: _BodyFrame) -> set:
    """Arms: the longest chain on each side among the ends outside the legs (both or none); sets
    an.chest_body and an.arms. Returns the bodies in the arms."""
    arms = {}
    for side, sign in (("left", 1), ("right", -1)):
        cand = [e for e in ends if e not in in_legs and sign * fr.lateral(info[e]["centre"]) > 0.06 * fr.height]
        if cand:
            arms[side] = max(cand, key=lambda e: info[e]["arc"])
    if len(arms) == 2:
        an.chest_body = _dca(rest, arms["left"], arms["right"])
        for side, e in arms.items():
            chain = _truncate(rest, rest.path(e, an.chest_body))
            an.arms[side] = _limb(rest, "arm", side, chain, None)
    elif arms:
        an.notes.append("only one arm-like chain found: no arm keypoints")
    in_arms = set()
    for limb in an.arms.values():
        in_arms |= _subtree(rest, limb.bodies[0])
    return in_arms


def _subtree(rest: _Rest, b: int) -> set:
    out, stack = set(), [b]
    while stack:
        x = stack.pop()
        out.add(x)
        stack += rest.children[x]
    return out


def _truncate(rest: _Rest, chain: list) -> list:
    """The chain up to its first body that branches into several jointed children (a hand)."""
    for i, b in enumerate(chain):
        if sum(1 for c in rest.children[b] if rest.hinges_below(c)) >= 2:
            return chain[: i + 1]
    return chain


def _limb(rest: _Rest, kind: str, side: str, chain: list, end_point) -> Limb:
    joints = []
    for b in chain:
        for j in rest.hinges[b]:
            joints.append(
                Joint(j, b, np.array(rest.d.xanchor[j]), np.array(rest.d.xaxis[j]) / np.linalg.norm(rest.d.xaxis[j]))
            )
    if not joints:
        raise RetargetError(f"the {side} {kind} has no hinge joints")
    if end_point is None and kind == "arm":
        pts = rest.points(rest.geoms(set().union(*[rest.rigid(b) for b in chain[-1:]])))
        if len(pts):
            # along the direction to the farthest point, as far as the geometry goes, through the
            # middle of the last fifth of it (the tip's centre, not a point on its rim)
            a0 = joints[0].anchor
            u = pts[np.argmax(np.linalg.norm(pts - a0, axis=1))] - a0
            u = u / max(np.linalg.norm(u), 1e-9)
            t = (pts - a0) @ u
            tip = pts[t >= t.max() - 0.2 * (t.max() - t.min())]
            across = (tip - a0) - np.outer((tip - a0) @ u, u)
            end_point = a0 + t.max() * u + across.mean(axis=0)
        else:
            end_point = np.array(rest.d.xpos[chain[-1]])
    return Limb(kind, side, chain, joints, None if end_point is None else np.array(end_point))


def _find_foot(rest: _Rest, limb: Limb, fwd, left, H) -> None:
    m = rest.m
    bodies = set().union(*[rest.rigid(b) for b in limb.bodies])
    geoms = rest.geoms(bodies, collision_only=True) or rest.geoms(bodies)
    down = np.array([0.0, 0.0, -1.0])
    lows = {}
    for g in geoms:
        Rg = rest.d.geom_xmat[g].reshape(3, 3)
        pts = rest.d.geom_xpos[g] + _bottom_points_local(m, g, Rg.T @ down) @ Rg.T
        if len(pts):
            lows[g] = pts
    if not lows:
        raise RetargetError(f"the {limb.side} leg has no geometry to stand on")
    zlow = min(float(p[:, 2].min()) for p in lows.values())
    tol = max(0.002, 0.01 * H)
    sole = [g for g, p in lows.items() if float(p[:, 2].min()) < zlow + tol]
    owner = {g: next(b for b in limb.bodies if int(m.geom_bodyid[g]) in rest.rigid(b)) for g in sole}
    foot = min(owner.values(), key=limb.bodies.index)
    pts = np.vstack([lows[g][lows[g][:, 2] < zlow + tol] for g in sole if owner[g] == foot])
    x, y = pts @ fwd, pts @ left
    x0, x1, y0, y1 = float(x.min()), float(x.max()), float(y.min()), float(y.max())
    corners = [x1 * fwd + y0 * left, x1 * fwd + y1 * left, x0 * fwd + y1 * left, x0 * fwd + y0 * left]
    corners = np.array([c + [0, 0, zlow] for c in corners])  # counter-clockwise seen from above
    centre = corners.mean(axis=0)
    limb.foot_body = foot
    limb.sole = dict(x0=x0, x1=x1, y0=y0, y1=y1, z=zlow, corners=corners, centre=centre)
    limb.end_point = centre


def _assign_joints(limb: Limb) -> None:
    """knee/elbow, hip/shoulder and ankle/wrist of a limb (module docstring, step 5)."""
    J = limb.joints
    pts = [j.anchor for j in J] + [limb.end_point]
    s = np.concatenate([[0.0], np.cumsum([np.linalg.norm(pts[i + 1] - pts[i]) for i in range(len(pts) - 1)])])
    S = float(s[-1]) or 1.0

    def cos_to(j: Joint, target) -> float | None:
        v = np.asarray(target) - j.anchor
        n = np.linalg.norm(v)
        return None if n < 1e-4 else abs(float(j.axis @ v / n))

    cands = [i for i, j in enumerate(J) if 0.2 <= s[i] / S <= 0.8 and (cos_to(j, limb.end_point) or 0.0) < BEND_COS]
    if not cands:
        cands = list(range(len(J)))
    mi = min(cands, key=lambda i: abs(s[i] / S - 0.5))
    limb.mid = J[mi]
    top = None
    for i in range(mi - 1, -1, -1):
        c = cos_to(J[i], J[mi].anchor)
        if c is None or c < TWIST_COS:
            top = J[i]
            break
    limb.top = top or J[0]
    limb.bottom = None
    for i in range(mi + 1, len(J)):
        c = cos_to(J[i], J[mi].anchor)
        if (s[i] - s[mi]) >= 0.35 * (S - s[mi]) and (c is None or c < TWIST_COS):
            limb.bottom = J[i]
            break
    if limb.bottom is None:  # only twist joints beyond the middle: the last one far enough down (a wrist yaw)
        far = [i for i in range(mi + 1, len(J)) if (s[i] - s[mi]) >= 0.6 * (S - s[mi])]
        limb.bottom = J[far[-1]] if far else None
    if limb.kind == "leg" and limb.bottom is None:
        limb.bottom = J[-1] if mi < len(J) - 1 else None
    limb.points_ankle = limb.bottom.anchor if limb.bottom is not None else limb.end_point


def _place_points(rest: _Rest, an: Anatomy, ends, info, used: set) -> None:
    m = rest.m
    P = an.points

    def put(human, body, pw, why):
        P[human] = (int(body), np.array(pw, float), why)

    def jname(j: Joint) -> str:
        import mujoco

        return mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j.id) or f"joint {j.id}"

    for side, limb in an.legs.items():
        put(f"{side}_hip", limb.top.body, limb.top.anchor, f"hip: joint {jname(limb.top)}")
        put(f"{side}_knee", limb.mid.body, limb.mid.anchor, f"knee: joint {jname(limb.mid)}")
        if limb.bottom is not None:
            put(f"{side}_ankle", limb.bottom.body, limb.bottom.anchor, f"ankle: joint {jname(limb.bottom)}")
        else:
            put(f"{side}_ankle", limb.foot_body, rest.d.xpos[limb.foot_body], "ankle: the foot body's origin")
        so = limb.sole
        toe = so["x1"] * an.forward + 0.5 * (so["y0"] + so["y1"]) * an.left + [0, 0, so["z"]]
        put(f"{side}_foot", limb.foot_body, toe, "toe: middle of the sole's front edge")
    for side, limb in an.arms.items():
        put(f"{side}_shoulder", limb.top.body, limb.top.anchor, f"shoulder: joint {jname(limb.top)}")
        put(f"{side}_elbow", limb.mid.body, limb.mid.anchor, f"elbow: joint {jname(limb.mid)}")
        if limb.bottom is not None:
            put(f"{side}_wrist", limb.bottom.body, limb.bottom.anchor, f"wrist: joint {jname(limb.bottom)}")
        else:
            put(f"{side}_wrist", limb.bodies[-1], limb.end_point, "wrist: end of the forearm's geometry")

    if an.legs:
        hips = 0.5 * (P["left_hip"][1] + P["right_hip"][1])
        sole_z = min(limb.sole["z"] for limb in an.legs.values())
        pelvis = hips + [0, 0, PELVIS_ABOVE_HIPS * (hips[2] - sole_z)]
        put("pelvis", an.pelvis_body, pelvis, "between the hips, raised as on a person")
    else:
        target = an.chest_body if an.chest_body >= 0 else an.root
        path = [an.root] + rest.path(target, an.root)
        waist = next((j for b in path for j in rest.hinges[b]), None)
        if waist is not None:
            b = int(m.jnt_bodyid[waist])
            body = int(m.body_parentid[b]) if b != an.root else b
            an.pelvis_body = body
            put("pelvis", body, rest.d.xanchor[waist], "the first waist joint's anchor (no legs)")
        else:
            an.pelvis_body = an.root
            put("pelvis", an.root, rest.d.xpos[an.root], "the root body's origin (no legs)")

    if an.arms:
        sh = 0.5 * (P["left_shoulder"][1] + P["right_shoulder"][1])
        pz = P["pelvis"][1][2]
        chest = np.array([sh[0], sh[1], pz + SPINE3_FRACTION * (sh[2] - pz)])
        put("spine3", an.chest_body, chest, "chest: below the shoulders, two thirds up from the pelvis")
        # head: the highest other end above the shoulders, else the chest's geometry above them
        heads = [e for e in ends if e not in used and info[e]["top"] > sh[2]]
        if heads:
            e = max(heads, key=lambda e: info[e]["top"])
            pts = rest.points(rest.geoms(rest.rigid(e)))
            c = 0.5 * (pts.min(axis=0) + pts.max(axis=0)) if len(pts) else rest.d.xpos[e]
            an.head_body = e
            put("head", e, c, "head: centre of the highest chain's geometry")
        else:
            pts = rest.points(rest.geoms(rest.rigid(an.chest_body)))
            pts = pts[pts[:, 2] > sh[2] + 0.03 * an.height] if len(pts) else pts
            if len(pts) >= 4:
                an.head_body = an.chest_body
                put(
                    "head",
                    an.chest_body,
                    0.5 * (pts.min(axis=0) + pts.max(axis=0)),
                    "head: centre of the chest body's geometry above the shoulders (no head joint)",
                )


# ------------------------------------------------------------------------------ capsules


def _segment_bodies(limb: Limb, first: Joint | None, last: Joint | None) -> list:
    """Bodies of the limb from ``first``'s body up to (not including) ``last``'s body."""
    i0 = limb.bodies.index(first.body) if first is not None else 0
    i1 = limb.bodies.index(last.body) if last is not None else len(limb.bodies)
    return limb.bodies[i0:i1]


def build_capsules(rest: _Rest, an: Anatomy) -> dict:
    """The profile's capsules (module docstring, step 8), by name."""
    caps = {}

    def limb_capsule(name, bodies):
        if not bodies:
            return
        frame = bodies[-1]
        allb = set().union(*[rest.rigid(b) for b in bodies])
        pts = rest.points(rest.geoms(allb, collision_only=True))
        if len(pts) < 4:
            return
        p0, p1, r = fit_capsule(rest.to_local(frame, pts))
        caps[name] = FittedCapsule(name, frame, p0, p1, r, 0.5 * r)

    pre = {"left": "l_", "right": "r_"}
    for side, limb in an.legs.items():
        # the bodies between the pelvis and the thigh (a hip motor beside the pelvis: the G1's
        # hand hit its hip-pitch link, which no capsule held, 19 mm deep in a streamed duet)
        limb_capsule(pre[side] + "hip", _segment_bodies(limb, None, limb.top))
        limb_capsule(pre[side] + "thigh", _segment_bodies(limb, limb.top, limb.mid))
        limb_capsule(pre[side] + "shin", _segment_bodies(limb, limb.mid, limb.bottom))
    for side, limb in an.arms.items():
        limb_capsule(pre[side] + "upper_arm", _segment_bodies(limb, limb.top, limb.mid))
        limb_capsule(pre[side] + "forearm", _segment_bodies(limb, limb.mid, limb.bottom))
        if limb.bottom is not None:
            limb_capsule(pre[side] + "hand", _segment_bodies(limb, limb.bottom, None))
    if an.chest_body >= 0:
        pts = rest.points(rest.geoms(rest.rigid(an.chest_body), collision_only=True))
        if len(pts) >= 4:
            local = rest.to_local(an.chest_body, pts)
            Rc = rest.R(an.chest_body)
            up, fw, lf = Rc.T @ np.array([0.0, 0.0, 1.0]), Rc.T @ an.forward, Rc.T @ an.left
            a, b, t = local @ fw, local @ lf, local @ up
            ext = [(np.percentile(v, 5), np.percentile(v, 95)) for v in (a, b)]
            r = float(min(0.5 * (hi - lo) for lo, hi in ext))
            base = 0.5 * sum(ext[0]) * fw + 0.5 * sum(ext[1]) * lf
            lo, hi = float(t.min()) + r, float(t.max()) - r
            if hi < lo:
                lo = hi = 0.5 * (lo + hi)
            # it does not shrink (min_radius = r): up to six arm parts are kept off it, and a
            # cut for one arm that touches at rest left it under the chest for the others
            caps["torso"] = FittedCapsule("torso", an.chest_body, base + lo * up, base + hi * up, r, r)
    # feet: the sole edge facing the other foot, spheres on it, a sphere at the sole's centre
    if len(an.legs) == 2:
        edge_r = 0.003
        for side, limb in an.legs.items():
            so, b, p = limb.sole, limb.foot_body, pre[side]
            y_in = so["y0"] if side == "left" else so["y1"]
            z = so["z"] + edge_r

            def at(x, y, b=b, z=z):
                return rest.to_local(b, x * an.forward + y * an.left + [0, 0, z])

            heel, toe, xm = at(so["x0"], y_in), at(so["x1"], y_in), 0.5 * (so["x0"] + so["x1"])
            caps[p + "sole_in"] = FittedCapsule(p + "sole_in", b, heel, toe, edge_r, edge_r)
            for nm, x in (("heel_in", so["x0"]), ("mid_in", xm), ("toe_in", so["x1"])):
                q = at(x, y_in)
                caps[p + nm] = FittedCapsule(p + nm, b, q, q.copy(), edge_r, edge_r)
            half_w = 0.5 * (so["y1"] - so["y0"])
            q = at(xm, 0.5 * (so["y0"] + so["y1"]))
            caps[p + "sole_mid"] = FittedCapsule(p + "sole_mid", b, q, q.copy(), max(0.75 * half_w, edge_r), edge_r)
    return caps


def collision_pairs(caps: dict) -> list:
    pairs = []

    def add(a, b):
        if a in caps and b in caps:
            pairs.append([a, b])

    for s in ("l_", "r_"):
        add(s + "upper_arm", "torso")
        for part in ("forearm", "hand"):
            add(s + part, "torso")
            add(s + part, s + "hip")
            add(s + part, s + "thigh")
    add("l_forearm", "r_forearm")
    add("l_hand", "r_hand")
    add("l_thigh", "r_thigh")
    add("l_shin", "r_shin")
    for a, b in (("l_", "r_"), ("r_", "l_")):
        for nm in ("heel_in", "mid_in", "toe_in", "sole_mid"):
            add(a + nm, b + "sole_in")
    return pairs


def clear_rest_collisions(m, caps: dict, pairs: list, poses: list, margin: float) -> tuple[list, list]:
    """Shrink capsules (down to their ``min_radius``) until no pair touches in any of ``poses``
    (qpos vectors), then drop the pairs that still do. Returns (pairs kept, notes)."""
    rests = [_Rest(m, q) for q in poses]
    slack = 0.002
    notes = []
    for _ in range(8):
        changed = False
        for a, b in pairs:
            A, B = caps[a], caps[b]
            for rest in rests:
                d = segment_distance(
                    rest.to_world(A.body, A.p0),
                    rest.to_world(A.body, A.p1),
                    rest.to_world(B.body, B.p0),
                    rest.to_world(B.body, B.p1),
                )
                need = A.radius + B.radius + margin + slack - d
                if need > 1e-6:
                    room_a, room_b = A.radius - A.min_radius, B.radius - B.min_radius
                    room = room_a + room_b
                    if room <= 1e-6:
                        continue
                    cut = min(need, room)
                    A.radius -= cut * room_a / room
                    B.radius -= cut * room_b / room
                    changed = True
        if not changed:
            break
    kept = []
    for a, b in pairs:
        A, B = caps[a], caps[b]
        worst = min(
            segment_distance(
                r.to_world(A.body, A.p0), r.to_world(A.body, A.p1), r.to_world(B.body, B.p0), r.to_world(B.body, B.p1)
            )
            - A.radius
            - B.radius
            - margin
            for r in rests
        )
        if worst < 0:
            notes.append(f"[{a}, {b}] left out: they touch in the zero/stand pose ({1000 * worst:.0f} mm)")
        else:
            kept.append([a, b])
    return kept, notes


# ---------------------------------------------------------------------------------- limits


def joint_limits(m, an: Anatomy) -> tuple[dict, dict]:
    """Profile limits for unranged hinges: {joint: (lo, hi)} and {joint: why}."""
    import mujoco

    ctrl = {}
    for a in range(m.nu):
        if m.actuator_trntype[a] == mujoco.mjtTrn.mjTRN_JOINT and m.actuator_ctrllimited[a]:
            ctrl.setdefault(int(m.actuator_trnid[a, 0]), tuple(float(v) for v in m.actuator_ctrlrange[a]))
    knees = {limb.mid.id: limb for limb in an.legs.values()}
    out, why = {}, {}
    for j in range(m.njnt):
        if m.jnt_type[j] != mujoco.mjtJoint.mjJNT_HINGE or m.jnt_limited[j]:
            continue
        name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j)
        if j in ctrl:
            lo, hi = ctrl[j]
            src = "the actuator's ctrlrange"
        else:
            lo, hi = -math.pi, math.pi
            src = "no range or ctrlrange in the MJCF: +-pi, narrow it to the real joint's range"
        if j in knees:
            limb = knees[j]
            # +angle moves the foot by axis x (foot - knee); bending sends it backwards
            v = limb.end_point - limb.mid.anchor
            sign = 1.0 if float(np.cross(limb.mid.axis, v) @ an.forward) < 0 else -1.0
            q0 = float(m.qpos0[m.jnt_qposadr[j]])
            if sign > 0:
                lo = max(lo, q0)
            else:
                hi = min(hi, q0)
            src += "; kept to the knee's bending side"
        out[name], why[name] = (lo, hi), src
    return out, why


def speed_limits(m) -> tuple[float, dict, str]:
    """(default rad/s, {joint: rad/s} where lower, why): the MJCF's ``servo_no_load_speed`` less
    10 % (one value, or one per actuator), else the no-load speed of the servo model that
    hardware.yaml guesses (:data:`GUESSED_SERVO`) less 10 %. (A flat 5 rad/s guess let the
    retargeter command 5.0 rad/s where the physics check, going by the guessed servo, allows 4.82.)"""
    import mujoco

    from firmware_cfg import servo_models

    nid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_NUMERIC, "servo_no_load_speed")
    if nid < 0:
        guess = servo_models.load_servo_model(GUESSED_SERVO).no_load_speed_rad_s
        return (
            round(0.9 * guess, 3),
            {},
            (
                f"{FILL[2:]}: rad/s, the guessed servo's ({GUESSED_SERVO}) no-load speed less 10 %; "
                "use your actuators' no-load speed less 10 % (the retargeter never commands faster)"
            ),
        )
    adr, size = int(m.numeric_adr[nid]), int(m.numeric_size[nid])
    data = np.array(m.numeric_data[adr : adr + size], dtype=float)
    why = "rad/s: the MJCF's servo_no_load_speed less 10 % for load"
    if size != m.nu or size == 1:
        return round(0.9 * float(data.min()), 3), {}, why
    top = float(data.max())
    per = {}
    for a in range(m.nu):
        if data[a] < top and m.actuator_trntype[a] == mujoco.mjtTrn.mjTRN_JOINT:
            per[mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, int(m.actuator_trnid[a, 0]))] = round(
                0.9 * float(data[a]), 3
            )
    return round(0.9 * top, 3), per, why


def stand_keyframe(m) -> tuple[str, str]:
    import mujoco

    names = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_KEY, k) or "" for k in range(m.nkey)]
    for want in ("stand", "home", "standing", "default", "init"):
        for n in names:
            if n.lower() == want:
                return n, f"the model's keyframe {n!r}"
    named = [n for n in names if n]
    if len(named) == 1:
        return named[0], f"the model's only keyframe {named[0]!r}"
    return "stand", (
        "the model has no stand keyframe: the robot stands in stand_pose where that is given (robot init "
        'derives it for a free-standing robot), else in its zero pose; a <key name="stand" qpos=... ctrl=...> '
        "in the MJCF takes its place"
    )


# ----------------------------------------------------------------------------- writing


@dataclass
class InitResult:
    folder: Path
    mjcf: Path
    profile: Path
    hardware: Path
    readme: Path
    anatomy: Anatomy
    notes: list


def _relative(path: Path, folder: Path) -> str:
    """``path`` relative to ``folder`` (the robot folder travels with its model), or absolute
    when they share nothing below the file system's root."""
    common = Path(os.path.commonpath([path, folder]))
    if common == Path(common.anchor):
        return path.as_posix()
    return Path(os.path.relpath(path, folder)).as_posix()


def _inward(lo: float, hi: float, digits: int = 6) -> tuple[float, float]:
    """[lo, hi] rounded to ``digits`` decimals towards its inside (never wider than given)."""
    k = 10.0**digits
    return math.ceil(lo * k - 1e-9) / k, math.floor(hi * k + 1e-9) / k


def _f(x: float) -> str:
    v = round(float(x), 4)
    return "0.0" if v == 0 else repr(v)


def _vec(v) -> str:
    return "[" + ", ".join(_f(x) for x in v) + "]"


def _name(m, obj, i: int) -> str:
    import mujoco

    return mujoco.mj_id2name(m, obj, i) or ""


WEIGHTS = {"pelvis": 2.0, "left_ankle": 2.0, "right_ankle": 2.0, "left_wrist": 1.5, "right_wrist": 1.5, "head": 0.5}
ORDER = (
    "pelvis",
    "spine3",
    "head",
    "left_hip",
    "right_hip",
    "left_knee",
    "right_knee",
    "left_ankle",
    "right_ankle",
    "left_foot",
    "right_foot",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
)


def init_robot_folder(
    mjcf: str | Path,
    out_dir: str | Path,
    name: str | None = None,
    force: bool = False,
    probe_steps: bool = True,
    progress=None,
    check_config=None,
    planner=None,
) -> InitResult:
    """Write ``profile.yaml``, ``hardware.yaml`` and ``README.md`` for the MJCF into ``out_dir``.
    With ``probe_steps``, a free-standing robot with feet is probed for stepping in physics
    (:func:`sim.step_probe.choose_step_pace`; ``progress(clip name)`` before each clip, the check
    configured by ``check_config(folder)``, the robot that plans by ``planner(folder)``, when
    given) and the profile's ``streaming_steps`` and ``step_pace`` written from it; else its
    feet stay planted."""
    from firmware_cfg.registry import HARDWARE_FILE, PROFILE_FILE, README_FILE

    given = Path(mjcf)
    model_path, scene_note = robot_model_file(given)
    m = load_model(model_path)
    out = Path(out_dir)
    files = [out / PROFILE_FILE, out / HARDWARE_FILE, out / README_FILE]
    existing = [p.name for p in files if p.exists()]
    if existing and not force:
        raise RetargetError(
            f"{out}: already holds {', '.join(existing)}; choose another -o folder or pass --force to overwrite"
        )
    out.mkdir(parents=True, exist_ok=True)
    draft = _draft_profile(m, model_path, name or out.resolve().name, _relative(model_path, out.resolve()))
    notes = list(draft.an.notes) + ([scene_note] if scene_note else []) + draft.pair_notes
    files[0].write_text(_profile_text(draft))
    files[1].write_text(_hardware_text(m, draft.robot, draft.model_name, draft.rel, draft.limits))
    files[2].write_text(_readme_text(draft.model_name, model_path, given, draft.an, notes, draft.body_name))
    robot = _self_check(model_path, files[0])
    if probe_steps and robot.floating and robot.has_feet:
        from sim.step_probe import choose_step_pace

        steps = choose_step_pace(out.resolve(), progress=progress, check_config=check_config, planner=planner)
        files[0].write_text(_profile_text(draft, steps))
        notes.append(steps[1][-1].summary())
    return InitResult(out, model_path, files[0], files[1], files[2], draft.an, notes)


@dataclass
class _ProfileDraft:
    """What ``robot init`` found in the model for the profile it writes: the robot's and model's
    names, the model's path relative to the folder, the anatomy, keypoint frames, joint and speed
    limits with their reasons, capsules and pairs (with notes), the margin and the stand keyframe
    (name, why, and where the model has none the derived stand pose and why, else None, None)."""

    m: object
    robot: str
    model_name: str
    model_path: Path
    rel: str
    an: Anatomy
    rest: _Rest
    limits: dict
    limit_why: dict
    speed: float
    speeds: dict
    speed_why: str
    caps: dict
    pairs: list
    pair_notes: list
    margin: float
    stand: tuple

    def body_name(self, b: int) -> str:
        import mujoco

        return _name(self.m, mujoco.mjtObj.mjOBJ_BODY, b)


def _draft_profile(m, model_path: Path, robot: str, rel: str) -> _ProfileDraft:
    """Infer the anatomy, capsules and pairs clear in the rest poses, limits and the stand keyframe."""
    import mujoco

    model_name = ET.parse(model_path).getroot().get("model") or model_path.stem
    an = infer_anatomy(m)
    rest = _Rest(m)
    stand_name, stand_why = stand_keyframe(m)
    kid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, stand_name)
    limits, limit_why = joint_limits(m, an)
    poses = [np.array(m.qpos0)] + ([np.array(m.key_qpos[kid])] if kid >= 0 else [])
    try:
        derived = derive_stand_pose(m, an, limits) if kid < 0 else None
    except (ValueError, np.linalg.LinAlgError) as exc:  # the robot stands in its zero pose then
        derived = None
        an.notes.append(f"no standing pose derived ({exc}); add a stand keyframe to the MJCF")
    if derived is not None:
        stand_qpos = np.array(m.qpos0)
        for name, angle in derived[0].items():
            stand_qpos[m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, name)]] = angle
        poses.append(stand_qpos)
    margin = float(np.clip(round(0.008 * an.height, 3), 0.003, 0.01))
    caps = build_capsules(rest, an)
    pairs, pair_notes = clear_rest_collisions(m, caps, collision_pairs(caps), poses, margin)
    used = {c for p in pairs for c in p}
    caps = {k: v for k, v in caps.items() if k in used}
    speed, speeds, speed_why = speed_limits(m)
    draft = _ProfileDraft(
        m,
        robot,
        model_name,
        model_path,
        rel,
        an,
        rest,
        limits,
        limit_why,
        speed,
        speeds,
        speed_why,
        caps,
        pairs,
        pair_notes,
        margin,
        (stand_name, stand_why) + (derived or (None, None)),
    )
    _require_names(draft)
    return draft


def _require_names(d: _ProfileDraft) -> None:
    """Every hinge joint, and every body the profile names, has a name in the MJCF."""
    import mujoco

    m = d.m
    nameless = [
        j
        for j in range(m.njnt)
        if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE and not _name(m, mujoco.mjtObj.mjOBJ_JOINT, j)
    ]
    if nameless:
        raise RetargetError(
            f"{d.model_path}: hinge joints {nameless} (in file order) have no name; give every joint "
            "a name= in the MJCF (trajectories and the hardware config refer to joints by name)"
        )
    unnamed = [
        b
        for b in {p[0] for p in d.an.points.values()}
        | {c.body for c in d.caps.values()}
        | {limb.foot_body for limb in d.an.legs.values()}
        if not d.body_name(b)
    ]
    if unnamed:
        raise RetargetError(
            f"{d.model_path}: bodies {sorted(unnamed)} that the profile needs have no name; "
            "give every body a name= in the MJCF"
        )


def _profile_text(d: _ProfileDraft, steps=None) -> str:
    """The profile.yaml text, with a comment on where each value came from."""
    B, an, rest = d.body_name, d.an, d.rest
    L = [
        f"# Retarget profile of {d.model_name} ({d.model_path.name}), written by `dualflow-bridge robot init`",
        "# from the model alone: keypoints from the kinematic tree and the geometry, capsules fitted to the",
        "# collision geoms, feet from the lowest contact geoms (docs/retargeting.md says how). Check",
        "# it, edit freely (schema: retarget/profile.py), then run `dualflow-bridge robot check DIR`.",
        f"robot: {d.robot}",
        f"mjcf: {d.rel}",
        "root: pelvis",
        "# human joint (SMPL): robot body + point in that body's frame (m), tracking weight",
        "keypoints:",
    ]
    for h in ORDER:
        if h not in an.points:
            continue
        b, pw, why = an.points[h]
        off = rest.to_local(b, pw)
        L.append(f"  {h + ':':16s}{{body: {B(b)}, offset: {_vec(off)}, weight: {WEIGHTS.get(h, 1.0)}}}  # {why}")
    if d.limits:
        L.append("# Joints the MJCF leaves unranged (ranged ones keep the MJCF's range):")
        L.append("joint_limits:")
        for j, (lo, hi) in d.limits.items():
            lo, hi = _inward(lo, hi)
            L.append(f"  {j}: [{lo:.6f}, {hi:.6f}]  # {d.limit_why[j]}")
    L.append("velocity_limits:")
    L.append(f"  default: {d.speed}  # {d.speed_why}")
    for j, v in d.speeds.items():
        L.append(f"  {j}: {v}")
    L += _collision_lines(d)
    if len(an.legs) == 2:
        L.append("# Feet: the sole's four corners (m, foot body frame) from its lowest contact geoms.")
        L.append("feet:")
        for side in ("left", "right"):
            limb = an.legs[side]
            corners = [rest.to_local(limb.foot_body, c) for c in limb.sole["corners"]]
            L.append(
                f"  {side + ':':7s}{{body: {B(limb.foot_body)}, corners: [{', '.join(_vec(c) for c in corners)}]}}"
            )
    rigid = [h for h in ("left_hip", "right_hip", "left_shoulder", "right_shoulder") if h in an.points]
    L.append("# Hips and shoulders at the robot's own offsets, turned with the person's pelvis and chest.")
    L.append(f"rigid_offsets: [{', '.join(rigid)}]")
    L.append("posture_weight: 0.02")
    L.extend(_steps_lines(steps))
    L.append(f"stand_keyframe: {d.stand[0]}  # {d.stand[1]}")
    if d.stand[2]:
        L.append(f"# The standing pose without that keyframe (rad), {d.stand[3]}:")
        L.append("stand_pose: {" + ", ".join(f"{k}: {_f(v)}" for k, v in d.stand[2].items()) + "}")
    return "\n".join(L) + "\n"


def _steps_lines(steps) -> list[str]:
    """The profile's ``streaming_steps`` (and ``step_pace``) with why: ``steps`` is
    (pace or None, the probes run: sim.step_probe.choose_step_pace), or None (not probed)."""
    if steps is None:
        return [
            "# The live bridge keeps the feet planted (robot init did not probe stepping). Turn steps on",
            "# (true) once `dualflow-bridge retarget-check CLIPS --robot DIR --retargeter streaming`",
            "# passes with them.",
            "streaming_steps: false",
        ]
    pace, probes = steps
    L = ["# Steps of the live bridge, measured by robot init in physics (sim/step_probe.py):"]
    L += [f"#   {p.summary()}" for p in probes]
    if pace is None:
        L.append("# so the feet stay planted; turn steps on (true) only where your clips pass with them.")
        L.append("streaming_steps: false")
    else:
        L.append("streaming_steps: true")
        L.append(f"step_pace: {pace:g}  # x the step phases' default lengths (the op3's); larger is slower")
    return L


def _collision_lines(d: _ProfileDraft) -> list[str]:
    """The capsules, collision_pairs (with notes) and collision_margin lines."""
    L = ["# Self-collision: capsules in a body's frame (m), and the pairs kept apart.", "capsules:"]
    for c in d.caps.values():
        L.append(
            f"  {c.name + ':':13s}{{body: {d.body_name(c.body)}, from: {_vec(c.p0)}, to: {_vec(c.p1)}, "
            f"radius: {_f(c.radius)}}}"
        )
    L.append("collision_pairs:")
    for a, b in d.pairs:
        L.append(f"  - [{a}, {b}]")
    for n in d.pair_notes:
        L.append(f"  # {n}")
    if not d.pairs:
        L[-1] = "collision_pairs: []"
    L.append(f"collision_margin: {d.margin}")
    return L


def _self_check(model_path: Path, profile_path: Path):
    """The profile just written must load against its model (else it is a bug here); returns the robot."""
    from retarget.kinematics import RobotKinematics
    from retarget.profile import RetargetProfile
    from retarget.robot import RetargetRobot

    return RetargetRobot(RobotKinematics.from_xml(model_path), RetargetProfile.load(profile_path))


def _hardware_text(m, robot: str, model_name: str, rel: str, profile_limits: dict) -> str:
    import mujoco

    from firmware_cfg import servo_models
    from firmware_cfg.config import spec_angle_range

    spec = servo_models.load_servo_model(GUESSED_SERVO)
    smin, smax = spec_angle_range(spec)
    joints = []
    for a in range(m.nu):
        if m.actuator_trntype[a] == mujoco.mjtTrn.mjTRN_JOINT:
            j = int(m.actuator_trnid[a, 0])
            if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE and j not in [x[0] for x in joints]:
                joints.append((j, mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j)))
    L = [
        f"# Hardware config skeleton of {model_name}, written by `dualflow-bridge robot init`.",
        "# The MJCF cannot say how the robot is wired: every line marked FILL IN is a placeholder to",
        "# replace with the real robot's value, then delete the marker. Schema and units: firmware_cfg/config.py",
        "# (angles in rad; servo = direction * joint + zero_offset, from the servo's centre tick).",
        "# - id, direction, zero_offset: per servo; `dualflow-bridge servo scan` finds the IDs, and",
        "#   `dualflow-bridge servo calibrate` records zero offsets with the robot held in its zero pose;",
        "# - limits: the MJCF's range (or the profile's, for unranged joints) clipped to the servo's range;",
        "#   narrow them to the real robot's safe range (never wider than the MJCF).",
        "# `dualflow-bridge robot check DIR --hardware` fails while a FILL IN marker is left.",
        f"robot: {robot}",
        f"mjcf: {rel}",
        "stop_policy: hold",
        "servo_defaults:",
        f"  model: {GUESSED_SERVO}  {FILL}: your servo model ({', '.join(servo_models.servo_model_names())})",
        "  direction: 1",
        "  zero_offset: 0.0",
        "buses:",
        "  - name: body",
        f"    port: /dev/ttyUSB0  {FILL}: the bus's serial device",
        f"    baud: 2000000  {FILL}: the servos' baud rate",
        f'    protocol: "2.0"  {FILL}: "1.0", "2.0" (Dynamixel) or serial-link (a microcontroller)',
        "    servos:",
    ]
    if not joints:
        L.append(f"      []  {FILL}: the model has no joint actuators; list one servo per driven joint")
    for i, (j, jn) in enumerate(joints):
        if m.jnt_limited[j]:
            lo, hi = (float(v) for v in m.jnt_range[j])
        else:
            lo, hi = profile_limits.get(jn, (-math.pi, math.pi))
        lo, hi = _inward(max(lo, smin), min(hi, smax))
        L.append(
            f"      - {{id: {i + 1}, joint: {jn}, direction: 1, zero_offset: 0.0, limits: [{lo:.6f}, {hi:.6f}]}}"
            f"  {FILL}: id, direction, zero_offset"
        )
    return "\n".join(L) + "\n"


def _readme_text(model_name, model_path, given, an: Anatomy, notes, B) -> str:
    L = [
        f"# {model_name} ({model_path.name}): robot folder set up by robot init",
        "",
        f"Model: `{model_path}`" + (f" (given as `{given}`)" if Path(given).resolve() != model_path else "") + ".",
        "",
        "Inferred by `dualflow-bridge robot init` from the model alone (retarget/profile_init.py):",
        "",
    ]
    for h in ORDER:
        if h in an.points:
            b, _, why = an.points[h]
            L.append(f"- `{h}` on body `{B(b)}` ({why})")
    if notes:
        L += ["", "Notes:", ""] + [f"- {n}" for n in notes]
    L += [
        "",
        "Next:",
        "",
        "1. Look at the keypoints above; edit `profile.yaml` where a guess is wrong.",
        "2. Fill in `hardware.yaml` (every `# FILL IN`): servo IDs, directions, zero offsets, port.",
        "3. `dualflow-bridge robot check DIR` (add `--hardware` before the first power-on).",
        "",
    ]
    return "\n".join(L)


__all__ = ["init_robot_folder", "infer_anatomy", "robot_model_file", "fit_capsule", "InitResult", "Anatomy"]

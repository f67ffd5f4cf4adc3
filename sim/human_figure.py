"""A person as a kinematic figure: one capsule per SMPL-22 bone on a mocap body.

The capsules are posed each frame from joint positions (T, 22, 3) in metres; they
take part in no contact (contype = conaffinity = 0) so they never push the robot.
Distances and penetrations between the robot and the figure are measured
explicitly (:mod:`sim.contacts`).

Placement: world = R_z(yaw) @ (scale * p) + offset, applied to every joint position
p of the source motion. :class:`FaceToFace` works one out for a partner: in front of the
robot, facing it, at a partner's distance.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import mujoco
import numpy as np

from dualflow.motion import PARENTS, REST_POSE, Motion
from sim.errors import SimError

#: Height of the adult whose joint span (head joint to foot joints) the rest pose has.
_REST_HEIGHT_M = 1.72
_REST_JOINT_SPAN_M = float(REST_POSE[15, 2] - REST_POSE[[10, 11], 2].min())


@dataclass(frozen=True)
class Placement:
    """How a human motion is placed in the scene.

    ``scale``: a float, "human" (1.0) or "robot" (the robot's standing height over
    the person's estimated height). ``offset`` (3,) metres and ``yaw_deg`` about +Z
    are applied after scaling.
    """

    scale: float | str = "robot"
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    yaw_deg: float = 0.0

    def resolve_scale(self, motion: Motion, robot_height: float) -> float:
        if self.scale == "human":
            return 1.0
        if self.scale == "robot":
            return robot_height / estimate_height(motion)
        try:
            s = float(self.scale)
        except (TypeError, ValueError):
            raise SimError(f"human placement: scale must be 'robot', 'human' or a number, got {self.scale!r}") from None
        if not np.isfinite(s) or s <= 0:
            raise SimError(f"human placement: scale must be > 0, got {self.scale!r}")
        return s


#: Root-to-pelvis distance of a person facing the robot, as a share of the mean standing height
#: of the two (the robot and the person as scaled). Two adults of about 1.7 m who talk or shake
#: hands stand about 1 m apart, pelvis to pelvis (the far phase of Hall's personal distance,
#: 0.75-1.2 m): close enough to reach each other with bent elbows, far enough that torsos and
#: hanging arms never touch. 1.0 / 1.7 is about 0.6.
PARTNER_DISTANCE_FRAC = 0.6


@dataclass(frozen=True)
class FaceToFace:
    """A person placed as a partner: in front of the robot, facing it, at a partner's distance.

    Resolved (:meth:`resolve`) from the first frames of both: the person's motion is scaled
    (``scale`` as in :class:`Placement`) and turned about +Z so that their first-frame heading
    (the hips' left vector turned by -90 deg) points back at the robot; their first-frame
    pelvis goes on the line ahead of the robot's first-frame root along the robot's heading
    (its root's x axis on the floor), as near as keeps the pelvis at least ``distance`` m from
    the robot's root (horizontally) in every frame: ``distance`` at the first frame, farther
    where the two walk towards each other (``path``: the robot's root xy per frame at
    ``path_fps``, e.g. a trajectory's; None: the robot stays at its first-frame root).
    ``distance`` None is :data:`PARTNER_DISTANCE_FRAC` x the mean of the robot's height and
    the scaled person's. Heights stay as they are: the motion's floor (z = 0) is the scene's."""

    scale: float | str = "robot"
    distance: float | None = None
    path: tuple | None = field(default=None, repr=False)  # ((x, y), ...) m, the robot's root per frame
    path_fps: float | None = None

    def resolve(self, motion: Motion, robot_height: float, root_pos, root_quat) -> Placement:
        """The :class:`Placement` for ``motion`` beside a robot of ``robot_height`` m whose root
        is at ``root_pos`` (3,) m with orientation ``root_quat`` (wxyz) at the first frame."""
        s = Placement(self.scale).resolve_scale(motion, robot_height)
        d = self.distance
        if d is None:
            d = PARTNER_DISTANCE_FRAC * 0.5 * (robot_height + s * estimate_height(motion))
        elif not (np.isfinite(d) and d >= 0):
            raise SimError(f"human placement: distance must be >= 0 m, got {self.distance!r}")
        w, x, y, z = (float(v) for v in root_quat)
        heading = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))  # yaw of the root's x axis
        ahead = np.array([np.cos(heading), np.sin(heading)])
        p0 = motion.positions[0]
        left = p0[1] - p0[2]  # right hip -> left hip
        facing = np.arctan2(left[1], left[0]) - 0.5 * np.pi
        yaw = heading + np.pi - facing  # turn the person to face back along the robot's heading
        yaw_deg = float((np.degrees(yaw) + 180.0) % 360.0 - 180.0)
        root0 = np.asarray(root_pos, dtype=np.float64)[:2]
        turned = Placement(s, (0.0, 0.0, 0.0), yaw_deg)
        pelvis = place(motion.positions[:, :1], s, turned)[:, 0, :2]  # (T, 2), before moving
        offset = root0 + d * ahead - pelvis[0]
        robot = self._robot_xy(motion, root0)
        for _ in range(8):  # each pass closes the closest frame's shortfall (exact when it is along `ahead`)
            gap = np.linalg.norm(pelvis + offset - robot, axis=1)
            shortfall = d - float(gap.min())
            if shortfall <= 1e-4:
                break
            offset = offset + shortfall * ahead
        return Placement(s, (float(offset[0]), float(offset[1]), 0.0), yaw_deg)

    def _robot_xy(self, motion: Motion, root0: np.ndarray) -> np.ndarray:
        """(T, 2) the robot's root at the person's frame times: ``path`` resampled (clamped at
        its ends), or the first-frame root throughout."""
        if not self.path or not self.path_fps:
            return root0[None]
        path = np.asarray(self.path, dtype=np.float64).reshape(-1, 2)
        t = np.arange(motion.n_frames) / motion.fps
        tp = np.arange(len(path)) / self.path_fps
        return np.stack([np.interp(t, tp, path[:, i]) for i in (0, 1)], axis=1)


@dataclass(frozen=True)
class People:
    """The people drawn beside the robot. ``actor``: the partner the robot answers, placed by
    ``actor_placement`` (None: :class:`FaceToFace`); ``reactor``: the person the robot plays,
    drawn for comparison where ``reactor_placement`` puts it (None: as its file has it). Either
    motion None: that person is not in the scene."""

    actor: Motion | None = None
    actor_placement: Placement | FaceToFace | None = None
    reactor: Motion | None = None
    reactor_placement: Placement | FaceToFace | None = None


def estimate_height(motion: Motion) -> float:
    """A person's standing height (m) from the first frame's head-to-foot span."""
    p = motion.positions[0]
    span = float(p[15, 2] - min(p[10, 2], p[11, 2], p[7, 2], p[8, 2]))
    if span <= 0.1:
        raise SimError(f"human motion {motion.name or ''}: first frame is not upright (head-to-foot span {span:.3f} m)")
    return span * _REST_HEIGHT_M / _REST_JOINT_SPAN_M


def place(positions: np.ndarray, scale: float, placement: Placement) -> np.ndarray:
    """(T, 22, 3) joint positions in scene coordinates."""
    c, s = np.cos(np.radians(placement.yaw_deg)), np.sin(np.radians(placement.yaw_deg))
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return (scale * positions) @ rot.T + np.asarray(placement.offset, dtype=np.float64)


class HumanFigure:
    """Capsules on mocap bodies for one person, added to an ``MjSpec`` before compiling.

    ``radius`` (m, before scaling) sets the limb thickness; ``group`` the geom group
    (renderers toggle groups to show or hide a figure).
    """

    def __init__(
        self,
        spec: mujoco.MjSpec,
        prefix: str,
        motion: Motion,
        scale: float,
        placement: Placement,
        rgba=(0.85, 0.55, 0.35, 0.8),
        radius: float = 0.05,
        group: int = 3,
    ):
        self.prefix = prefix
        self.motion = motion
        self.positions = place(motion.positions, scale, placement)  # (T, 22, 3)
        lengths = np.linalg.norm(self.positions[:, 1:] - self.positions[:, np.array(PARENTS[1:])], axis=-1)
        self.lengths = np.maximum(np.median(lengths, axis=0), 1e-3)  # (21,)
        r = radius * scale
        for k, joint in enumerate(range(1, len(PARENTS))):
            body = spec.worldbody.add_body(name=f"{prefix}bone{joint}", mocap=True)
            half = max(self.lengths[k] / 2.0 - r * 0.5, 1e-4)
            body.add_geom(
                name=f"{prefix}bone{joint}",
                type=mujoco.mjtGeom.mjGEOM_CAPSULE,
                size=[r, half, 0],
                rgba=list(rgba),
                contype=0,
                conaffinity=0,
                group=group,
            )
        head = spec.worldbody.add_body(name=f"{prefix}head", mocap=True)
        head.add_geom(
            name=f"{prefix}head",
            type=mujoco.mjtGeom.mjGEOM_SPHERE,
            size=[1.8 * r, 0, 0],
            rgba=list(rgba),
            contype=0,
            conaffinity=0,
            group=group,
        )
        self._mocap: np.ndarray | None = None
        self.geom_ids: np.ndarray | None = None

    def bind(self, model: mujoco.MjModel) -> None:
        """Look up mocap and geom ids in the compiled model."""
        names = [f"{self.prefix}bone{j}" for j in range(1, len(PARENTS))] + [f"{self.prefix}head"]
        self._mocap = np.array([model.body_mocapid[model.body(n).id] for n in names])
        self.geom_ids = np.array([model.geom(n).id for n in names])

    @property
    def n_frames(self) -> int:
        return self.positions.shape[0]

    def pose_at(self, data: mujoco.MjData, t: float) -> None:
        """Pose the figure at time ``t`` seconds (linear interpolation, clamped at the ends)."""
        f = np.clip(t * self.motion.fps, 0.0, self.n_frames - 1)
        i0 = int(np.floor(f))
        i1 = min(i0 + 1, self.n_frames - 1)
        w = f - i0
        p = (1.0 - w) * self.positions[i0] + w * self.positions[i1]
        parents = np.array(PARENTS[1:])
        a, b = p[parents], p[1:]
        data.mocap_pos[self._mocap[:-1]] = 0.5 * (a + b)
        data.mocap_quat[self._mocap[:-1]] = _z_to(b - a)
        head_dir = p[15] - p[12]
        data.mocap_pos[self._mocap[-1]] = p[15] + 0.3 * head_dir
        data.mocap_quat[self._mocap[-1]] = (1.0, 0.0, 0.0, 0.0)


def _z_to(v: np.ndarray) -> np.ndarray:
    """Unit quaternions wxyz (k, 4) rotating +Z onto each direction v (k, 3).

    q = normalise(1 + z.u, z x u) (half-way quaternion); the antiparallel case maps to
    a half turn about +X.
    """
    n = np.linalg.norm(v, axis=1, keepdims=True)
    u = np.where(n > 1e-9, v / np.maximum(n, 1e-12), np.array([0.0, 0.0, 1.0]))
    w = 1.0 + u[:, 2]
    q = np.stack([w, -u[:, 1], u[:, 0], np.zeros(len(u))], axis=1)
    flip = w < 1e-9
    q[flip] = (0.0, 1.0, 0.0, 0.0)
    return q / np.linalg.norm(q, axis=1, keepdims=True)

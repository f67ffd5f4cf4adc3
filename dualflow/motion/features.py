"""The InterGen 262-d per-person motion feature, to and from :class:`Motion`.

Contract: the one place where the project's Z-up world meets InterGen's Y-up feature frame
(``yup = zup[..., [1, 2, 0]]``). A row is positions 0:66, velocities 66:132 (metres per frame),
6D local rotations 132:258, foot contacts 258:262 (:data:`FEATURE_SLICES`), in the person's
canonical frame (:func:`canonical_frame`: floored, first pelvis at the origin, facing +Z); a
pair uses person A's frame for both. T frames give T - 1 rows (``append_last_frame`` rebuilds
the last on decoding). Conventions, rotations and measured accuracy: docs/model.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dualflow.errors import DualFlowError
from dualflow.motion.container import DEFAULT_FPS, Motion, TwoPersonMotion
from dualflow.motion.kinematics import (
    fit_offsets,
    forward_kinematics,
    inverse_kinematics,
    root_orientation,
)
from dualflow.motion.rotations import axis_angle_matrix, matrix_to_6d, sixd_to_matrix
from dualflow.motion.skeleton import FACE_JOINTS, FOOT_JOINTS, N_JOINTS, REST_POSE

#: Width of one person's feature row.
FEATURE_DIM = 262
#: Named column ranges of a feature row (see the module docstring).
FEATURE_SLICES: dict[str, slice] = {
    "positions": slice(0, 66),
    "velocities": slice(66, 132),
    "rotations": slice(132, 258),
    "contacts": slice(258, 262),
}
#: Joints whose local rotation is stored, in this order (all but the root).
ROTATION_JOINTS: tuple[int, ...] = tuple(range(1, N_JOINTS))

#: A foot joint is in contact at frame t when |p[t+1] - p[t]|^2 (metres^2 per
#: frame, all three axes) is below this ...
CONTACT_SQ_DISPLACEMENT = 0.001
#: ... and its canonical height p[t].y above the floor (metres) is below this,
#: per column of FOOT_JOINTS: left ankle, left foot, right ankle, right foot.
CONTACT_HEIGHTS: tuple[float, float, float, float] = (0.12, 0.05, 0.12, 0.05)


def zup_to_yup(x) -> np.ndarray:
    """(..., 3) project Z-up -> InterGen Y-up: ``yup = zup[..., [1, 2, 0]]``."""
    return np.asarray(x)[..., [1, 2, 0]]


def yup_to_zup(x) -> np.ndarray:
    """(..., 3) InterGen Y-up -> project Z-up: ``zup = yup[..., [2, 0, 1]]``."""
    return np.asarray(x)[..., [2, 0, 1]]


#: The rest pose in the Y-up feature frame (faces +Z, left towards +X).
REST_POSE_YUP: np.ndarray = np.ascontiguousarray(zup_to_yup(REST_POSE))
REST_POSE_YUP.setflags(write=False)


@dataclass(frozen=True)
class CanonicalFrame:
    """The rigid transform from a Z-up world to the canonical Y-up feature frame.

    ``origin`` (3,) is a Y-up world point in metres: (first-frame root x, floor
    height, first-frame root z); ``yaw`` (rad) is the turn about +Y applied after
    moving ``origin`` to 0::

        canonical = R_y(yaw) (zup_to_yup(world) - origin)
        world     = yup_to_zup(R_y(yaw)^T canonical + origin)
    """

    yaw: float = 0.0
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        try:
            yaw = float(self.yaw)
        except (TypeError, ValueError):
            raise DualFlowError(f"canonical frame: yaw must be a number (radians), got {self.yaw!r}") from None
        origin = np.array(self.origin, dtype=np.float64)
        if origin.shape != (3,) or not np.isfinite(origin).all() or not np.isfinite(yaw):
            raise DualFlowError(
                f"canonical frame: origin must be 3 finite numbers and yaw finite, got origin "
                f"{origin.tolist()} yaw {yaw!r}"
            )
        origin.setflags(write=False)
        object.__setattr__(self, "yaw", yaw)
        object.__setattr__(self, "origin", origin)

    @property
    def rotation(self) -> np.ndarray:
        """R_y(yaw) (3, 3), acting on Y-up column vectors."""
        return axis_angle_matrix([0.0, 1.0, 0.0], self.yaw)

    def to_canonical(self, points_zup) -> np.ndarray:
        """(..., 3) Z-up world points -> (..., 3) canonical Y-up points."""
        return (zup_to_yup(points_zup) - self.origin) @ self.rotation.T

    def to_world(self, points_yup) -> np.ndarray:
        """(..., 3) canonical Y-up points -> (..., 3) Z-up world points."""
        return yup_to_zup(np.asarray(points_yup, dtype=np.float64) @ self.rotation + self.origin)

    def to_dict(self) -> dict:
        """JSON-friendly form (yaw in radians, origin in Y-up metres)."""
        return {"yaw": self.yaw, "origin": [float(v) for v in self.origin]}

    @classmethod
    def from_dict(cls, data: dict) -> CanonicalFrame:
        if not isinstance(data, dict) or "yaw" not in data or "origin" not in data:
            raise DualFlowError(f"canonical frame: expected a mapping with keys 'yaw' and 'origin', got {data!r}")
        return cls(yaw=data["yaw"], origin=data["origin"])


def canonical_frame(motion: Motion) -> CanonicalFrame:
    """The canonical frame of one person (steps 1-3 of the module docstring)."""
    yup = zup_to_yup(_motion(motion, "motion").positions)
    root0 = yup[0, 0]
    origin = np.array([root0[0], yup[..., 1].min(), root0[2]])
    p0 = yup[0]
    r_hip, l_hip, r_sho, l_sho = FACE_JOINTS
    across = (p0[r_hip] - p0[l_hip]) + (p0[r_sho] - p0[l_sho])
    forward = np.cross([0.0, 1.0, 0.0], across)  # horizontal by construction
    if np.linalg.norm(forward) < 1e-9:
        return CanonicalFrame(0.0, origin)
    # R_y(yaw) (fx, 0, fz) = (0, 0, |f|)  <=>  yaw = -atan2(fx, fz)
    return CanonicalFrame(float(-np.arctan2(forward[0], forward[2])), origin)


def foot_contacts(positions_yup) -> np.ndarray:
    """Foot contact labels (T-1, 4) float32 from canonical Y-up positions (T, 22, 3).

    Column k (joint FOOT_JOINTS[k]) at frame t is 1 when both
    ``|p[t+1] - p[t]|^2 < CONTACT_SQ_DISPLACEMENT`` (squared 3-D displacement over
    one frame, m^2; 0.001 is about 0.95 m/s at 30 fps) and
    ``p[t].y < CONTACT_HEIGHTS[k]`` (height of frame t above the floor, m).
    """
    feet = np.asarray(positions_yup, dtype=np.float64)[:, list(FOOT_JOINTS)]
    sq_disp = np.sum((feet[1:] - feet[:-1]) ** 2, axis=-1)
    low = feet[:-1, :, 1] < np.asarray(CONTACT_HEIGHTS)
    return ((sq_disp < CONTACT_SQ_DISPLACEMENT) & low).astype(np.float32)


def encode_person(motion: Motion, canonical: CanonicalFrame | None = None) -> np.ndarray:
    """One person's motion (T frames, T >= 2) -> features (T-1, 262) float32.

    ``canonical``: the frame to express the motion in; default
    :func:`canonical_frame` of this motion. Pass another person's frame to place
    this person relative to them (what :func:`encode_pair` does).
    ``motion.contacts`` is not used: contacts are recomputed by
    :func:`foot_contacts` in the canonical frame, as InterGen does. The contact
    thresholds are per frame, so give motion at the model's rate (30 fps).
    """
    motion = _motion(motion, "motion")
    if motion.n_frames < 2:
        raise DualFlowError(
            f"{motion.name or 'motion'}: positions has {motion.n_frames} frame; features need at "
            "least 2 (velocity is p[t+1] - p[t])"
        )
    frame = canonical_frame(motion) if canonical is None else canonical
    if not isinstance(frame, CanonicalFrame):
        raise DualFlowError(f"canonical: expected a CanonicalFrame, got {type(frame).__name__}")
    pos = frame.to_canonical(motion.positions)  # (T, 22, 3) Y-up
    T = pos.shape[0]
    _, local = inverse_kinematics(pos[:-1], REST_POSE_YUP)  # per frame; the last row is dropped
    rot6 = matrix_to_6d(local[:, list(ROTATION_JOINTS)])  # (T-1, 21, 6)
    out = np.concatenate(
        [
            pos[:-1].reshape(T - 1, -1),
            (pos[1:] - pos[:-1]).reshape(T - 1, -1),
            rot6.reshape(T - 1, -1),
            foot_contacts(pos),
        ],
        axis=-1,
    )
    return out.astype(np.float32)


def encode_pair(pair: TwoPersonMotion) -> tuple[np.ndarray, CanonicalFrame]:
    """Actor and reactor -> (features (T-1, 2, 262) float32, actor's CanonicalFrame).

    ``[:, 0]`` is the actor (person A), ``[:, 1]`` the reactor (person B), both in
    A's canonical frame. Give the returned frame to :func:`decode_pair` to get
    back to the original world.
    """
    if not isinstance(pair, TwoPersonMotion):
        raise DualFlowError(f"pair: expected a TwoPersonMotion, got {type(pair).__name__}")
    frame = canonical_frame(pair.actor)
    feats = np.stack([encode_person(pair.actor, frame), encode_person(pair.reactor, frame)], axis=1)
    return feats, frame


def _check_features(features, shape_tail: tuple[int, ...], what: str) -> np.ndarray:
    arr = np.asarray(features, dtype=np.float64)
    if arr.ndim != 1 + len(shape_tail) or arr.shape[1:] != shape_tail or arr.shape[0] < 1:
        want = ", ".join(["T"] + [str(n) for n in shape_tail])
        raise DualFlowError(f"{what}: expected shape ({want}) with T >= 1, got {tuple(arr.shape)}")
    if not np.isfinite(arr).all():
        row = int(np.argwhere(~np.isfinite(arr))[0][0])
        raise DualFlowError(f"{what}: contain NaN or inf (first at row {row}); check the generator output")
    return arr


def decode_person(
    features,
    fps: float = DEFAULT_FPS,
    canonical: CanonicalFrame | None = None,
    *,
    use_rotations: bool = False,
    offsets=None,
    append_last_frame: bool = False,
    name: str = "",
) -> Motion:
    """Features (T', 262) -> Motion of T' frames (T'+1 with ``append_last_frame``).

    canonical: ``None`` keeps the canonical frame (converted to Z-up: first-frame
        root above the origin, floor at z = 0, facing +X); a CanonicalFrame maps
        back to the original world it came from.
    use_rotations: take positions from forward kinematics of the rotation part
        instead of the position part: root position and root orientation (not
        stored in the feature) from the position part, local rotations of joints
        1..21 from the 6D part, bone offsets ``offsets`` (22, 3) in the Y-up
        frame, by default the rest pose's directions scaled to the median bone
        lengths of the position part.
    append_last_frame: add the frame dropped by encoding, ``p[T'-1] + v[T'-1]``
        (with the last row's contacts).
    Contacts are ``contacts column > 0.5``.
    """
    x = _check_features(features, (FEATURE_DIM,), "features")
    T = x.shape[0]
    pos = x[:, FEATURE_SLICES["positions"]].reshape(T, N_JOINTS, 3)
    if use_rotations:
        rot6 = x[:, FEATURE_SLICES["rotations"]].reshape(T, len(ROTATION_JOINTS), 6)
        local = np.empty((T, N_JOINTS, 3, 3))
        local[:, 0] = root_orientation(pos, REST_POSE_YUP)
        local[:, list(ROTATION_JOINTS)] = sixd_to_matrix(rot6)
        if offsets is None:
            offsets = fit_offsets(pos, local)
        pos = forward_kinematics(pos[:, 0], local, offsets)
    contacts = x[:, FEATURE_SLICES["contacts"]] > 0.5
    if append_last_frame:
        last = pos[-1] + x[-1, FEATURE_SLICES["velocities"]].reshape(N_JOINTS, 3)
        pos = np.concatenate([pos, last[None]], axis=0)
        contacts = np.concatenate([contacts, contacts[-1:]], axis=0)
    world = yup_to_zup(pos) if canonical is None else _frame(canonical).to_world(pos)
    return Motion(positions=world, fps=fps, contacts=contacts, name=name)


def decode_pair(
    features,
    fps: float = DEFAULT_FPS,
    canonical: CanonicalFrame | None = None,
    *,
    text: str = "",
    **options,
) -> TwoPersonMotion:
    """Features (T', 2, 262) -> TwoPersonMotion (actor = [:, 0], reactor = [:, 1]).

    World frame: person A's canonical frame in Z-up when ``canonical`` is None,
    else the original world. ``options`` are those of :func:`decode_person`.
    """
    x = _check_features(features, (2, FEATURE_DIM), "pair features")
    actor = decode_person(x[:, 0], fps, canonical, name="actor", **options)
    reactor = decode_person(x[:, 1], fps, canonical, name="reactor", **options)
    return TwoPersonMotion(actor, reactor, text)


def _motion(motion, what: str) -> Motion:
    if not isinstance(motion, Motion):
        raise DualFlowError(f"{what}: expected a Motion, got {type(motion).__name__}")
    return motion


def _frame(canonical) -> CanonicalFrame:
    if not isinstance(canonical, CanonicalFrame):
        raise DualFlowError(f"canonical: expected a CanonicalFrame or None, got {type(canonical).__name__}")
    return canonical

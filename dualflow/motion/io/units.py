"""Length units, up axes and a stature estimate for imported motion.

Imported files come in many units (metres, centimetres, inches, CMU's own unit of
2.54/0.45 cm) and with Y or Z up. We decide the unit by the person's size: a
candidate unit is right when the estimated standing height lands in
``HEIGHT_RANGE`` (1.4 to 2.1 m); the candidates differ by factors of 2.2 or more,
so at most one fits.

Stature estimate (pose independent, from bone lengths of SMPL-22 positions):

    H = K * (leg + trunk),  leg = mean over sides of |hip-knee| + |knee-ankle|,
                            trunk = |pelvis-spine1| + |spine1-spine2| + |spine2-spine3|
                                    + |spine3-neck| + |neck-head|

with K chosen so that :data:`dualflow.motion.REST_POSE` (a 1.72 m adult) gives
1.72 m. Bone lengths are medians over frames, so any pose works.
"""

from __future__ import annotations

import numpy as np

from dualflow.errors import DualFlowError
from dualflow.motion.skeleton import REST_POSE

#: Plausible adult standing height in metres.
HEIGHT_RANGE: tuple[float, float] = (1.4, 2.1)

#: Frame rates a motion file may declare (frames/s): below 1 fps a clip is a slide show (and
#: resampling it to 30 fps multiplies its size); no capture system records above 1000 fps.
FPS_RANGE: tuple[float, float] = (1.0, 1000.0)

#: Fewest frames a motion file must hold: one frame has no motion (and no frame rate to speak of).
MIN_FRAMES = 2

#: Largest joint coordinate accepted, metres from the capture origin (after the unit scale):
#: values beyond it are damaged or in another unit, and would overflow later arithmetic.
MAX_COORDINATE_M = 1e4

#: Length units a file may use, metres per unit.
KNOWN_UNITS: dict[str, float] = {
    "m": 1.0,
    "cm": 0.01,
    "mm": 0.001,
    "inch": 0.0254,
    "cmu": 0.0254 / 0.45,  # CMU mocap skeleton unit: 2.54/0.45 cm ~ 0.05644 m
}

_LEGS = ((1, 4, 7), (2, 5, 8))  # hip, knee, ankle
_TRUNK = (0, 3, 6, 9, 12, 15)  # pelvis .. head
_REST_STATURE = 1.72


def _chain_sum(pos: np.ndarray, chain) -> np.ndarray:
    seg = pos[..., list(chain[1:]), :] - pos[..., list(chain[:-1]), :]
    return np.linalg.norm(seg, axis=-1).sum(axis=-1)


def _raw_size(positions: np.ndarray) -> float:
    pos = np.asarray(positions, dtype=np.float64)
    if pos.ndim == 2:
        pos = pos[None]
    leg = 0.5 * (_chain_sum(pos, _LEGS[0]) + _chain_sum(pos, _LEGS[1]))
    return float(np.median(leg + _chain_sum(pos, _TRUNK)))


_K = _REST_STATURE / _raw_size(REST_POSE)


def estimate_height(positions: np.ndarray) -> float:
    """Standing height (in the units of ``positions``) of a person given as SMPL-22
    joint positions (T, 22, 3) or (22, 3); see the module docstring."""
    return _K * _raw_size(positions)


def unit_name(scale: float) -> str:
    for name, value in KNOWN_UNITS.items():
        if abs(value - scale) <= 1e-9 * value:
            return name
    return f"{scale:g} m/unit"


def detect_scale(size_in_units: float, source: str) -> float:
    """Metres per file unit, from the estimated height in file units."""
    lo, hi = HEIGHT_RANGE
    fits = [s for s in KNOWN_UNITS.values() if lo <= size_in_units * s <= hi]
    if len(fits) == 1:
        return fits[0]
    raise DualFlowError(
        f"{source}: cannot tell the length unit: the person is {size_in_units:.4g} units tall, which is "
        f"not {lo}-{hi} m in any of {', '.join(KNOWN_UNITS)}; pass --scale (metres per unit, "
        f"e.g. --scale 0.01 for centimetres)"
    )


def check_height(height_m: float, scale: float, source: str, height_range=HEIGHT_RANGE) -> None:
    """Raise when ``height_m`` is outside ``height_range``, suggesting the unit that fits."""
    if height_range is None:
        return
    lo, hi = height_range
    if lo <= height_m <= hi:
        return
    size = height_m / scale
    fits = [f"--scale {s:g} ({n})" for n, s in KNOWN_UNITS.items() if lo <= size * s <= hi]
    fix = (
        f"the file is probably in other units: use {fits[0]}"
        if fits
        else ("check --scale (metres per file unit) and the joint map")
    )
    raise DualFlowError(
        f"{source}: with {unit_name(scale)} the person is {height_m:.2f} m tall, outside {lo}-{hi} m; {fix}"
    )


# ---------------------------------------------------------------------------
# Axes
# ---------------------------------------------------------------------------
#: File -> world rotation for a Y-up file whose person faces +Z with the left
#: towards +X (BVH, InterGen, HumanML3D): world = (z, x, y), i.e. zup = yup[..., [2, 0, 1]].
Y_UP = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
#: Z-up files facing +X (our own frame).
Z_UP = np.eye(3)


def _signed_axis(v: np.ndarray, what: str, source: str) -> np.ndarray:
    k = int(np.argmax(np.abs(v)))
    if np.abs(v[k]) < 0.7 * np.linalg.norm(v):
        raise DualFlowError(
            f"{source}: cannot tell the {what} axis from the rest pose (direction {np.round(v, 3).tolist()}); "
            "pass --up y or --up z"
        )
    out = np.zeros(3)
    out[k] = np.sign(v[k])
    return out


def axes_from_rest(up_vec: np.ndarray, left_vec: np.ndarray, source: str) -> np.ndarray:
    """The proper rotation A (3, 3), world = A @ file, that maps the rest pose's up
    direction to +Z and its left direction to +Y (so it faces +X = left x up)."""
    up = _signed_axis(np.asarray(up_vec, float), "up", source)
    left = _signed_axis(np.asarray(left_vec, float), "left-right", source)
    if abs(up @ left) > 0.5:
        raise DualFlowError(f"{source}: the rest pose's up and left axes coincide; pass --up y or --up z")
    forward = np.cross(left, up)
    return np.stack([forward, left, up])


def axes_matrix(up: str) -> np.ndarray:
    """File -> world rotation for an explicit ``up`` of 'y' or 'z' (see Y_UP, Z_UP)."""
    key = str(up).lower()
    if key == "y":
        return Y_UP.copy()
    if key == "z":
        return Z_UP.copy()
    raise DualFlowError(f"up axis must be 'y', 'z' or 'auto', got {up!r}")


def frames_message(n: int, source: str) -> str:
    """What to say about a motion file of ``n`` < MIN_FRAMES frames."""
    if n == 0:
        return f"{source}: the file has zero frames; a motion needs at least {MIN_FRAMES}"
    return f"{source}: the file has only {n} frame; a motion needs at least {MIN_FRAMES} (re-export the whole clip)"


def check_fps(fps: float, where: str) -> float:
    """``fps`` if it lies in :data:`FPS_RANGE`, else DualFlowError naming ``where``."""
    lo, hi = FPS_RANGE
    if not lo <= fps <= hi:  # NaN fails too
        raise DualFlowError(
            f"{where}: fps must be > 0, within {lo:g}-{hi:g} frames/s, got {fps!r}; the field is damaged, "
            "or give the file's real rate (--source-fps)"
        )
    return float(fps)


def check_positions(pos: np.ndarray, source: str) -> None:
    """Joint positions (T, J, 3) in metres as a motion file must give them: at least
    :data:`MIN_FRAMES` frames, finite, within :data:`MAX_COORDINATE_M`; else DualFlowError."""
    if pos.shape[0] < MIN_FRAMES:
        raise DualFlowError(frames_message(pos.shape[0], source))
    bad = ~np.isfinite(pos)
    if bad.any():
        frame, joint = np.argwhere(bad)[0][:2]
        raise DualFlowError(
            f"{source}: positions contain NaN or inf (first at frame {frame}, joint {joint}); clean the file"
        )
    far = np.abs(pos) > MAX_COORDINATE_M
    if far.any():
        frame, joint = np.argwhere(far)[0][:2]
        raise DualFlowError(
            f"{source}: a joint is {np.abs(pos).max():.3g} m from the origin (first at frame {frame}, "
            f"joint {joint}), beyond {MAX_COORDINATE_M:g} m; the values are damaged or in another unit "
            "(give --scale)"
        )

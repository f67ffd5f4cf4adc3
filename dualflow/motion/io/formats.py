"""One entry point for motion files: :func:`load_motion`, :func:`load_pair`, :func:`load_any`,
:func:`save_motion`.

Contract: the format is chosen by extension, then content: ``.bvh`` (with a joint map), our
``.npz`` (``dualflow-motion-1`` / ``dualflow-duet-1``), AMASS-style ``.npz`` joints, and
``.npy`` HumanML3D joints, InterGen raw (T, 492), InterGen features (T, 262) or a pair
(T, 2, 262). Readers never move the data (:func:`put_on_ground` does); npz is read without
pickle; writes are atomic. The table of layouts: docs/model.md.
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np

from dualflow.errors import DualFlowError
from dualflow.motion.container import Motion, TwoPersonMotion
from dualflow.motion.io.bvh import atomic_write_bytes
from dualflow.motion.io.bvh_motion import BvhImportOptions, read_bvh_motion, write_bvh_motion
from dualflow.motion.io.npfile import open_npz, read_npy, scalar, text
from dualflow.motion.io.units import (
    HEIGHT_RANGE,
    MIN_FRAMES,
    Y_UP,
    axes_matrix,
    check_fps,
    check_height,
    check_positions,
    estimate_height,
    frames_message,
)
from dualflow.motion.skeleton import FOOT_JOINTS, JOINT_NAMES, N_JOINTS

MOTION_FORMAT = "dualflow-motion-1"
DUET_FORMAT = "dualflow-duet-1"
HUMANML3D_FPS = 20.0
INTERGEN_FPS = 30.0
_JOINT_KEYS = ("joints", "positions", "joint_positions", "Jtr", "jtr")
_FPS_KEYS = ("fps", "mocap_framerate", "mocap_frame_rate", "frame_rate", "framerate")
#: InterGen raw (Z up) -> InterGen Y up: (x, y, z) -> (x, z, -y).
_INTERGEN_RAW_TO_YUP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def _finish(pos: np.ndarray, fps: float, name: str, source: str, opts: dict, contacts=None) -> Motion:
    """Scale, height check and resampling shared by the array readers."""
    scale = opts.get("scale") or 1.0
    pos = np.asarray(pos, dtype=np.float64) * scale
    check_positions(pos, source)
    check_height(estimate_height(pos), scale, source, opts.get("height_range", HEIGHT_RANGE))
    motion = Motion(pos, fps=fps, contacts=contacts, name=name)
    if opts.get("fps") is not None:
        motion = motion.resample(opts["fps"])
    return motion


def _fps_value(value, source: str, field: str) -> float:
    where = f"{source}, field {field!r}"
    return check_fps(scalar(value, where, what="fps"), where)


def _axes(opts: dict, default: str) -> np.ndarray:
    return axes_matrix(opts.get("up") or default)


# ---------------------------------------------------------------------------
# npz
# ---------------------------------------------------------------------------
def _magic(path: Path, prefix: bytes, what: str) -> None:
    with open(path, "rb") as f:
        head = f.read(len(prefix))
    if head != prefix:
        raise DualFlowError(f"{path}: not a readable {what} file (wrong header); is it really {what}?")


def _get(data, key: str, source: str) -> np.ndarray:
    """Field ``key`` of an open :class:`~dualflow.motion.io.npfile.NpzFile` (errors name it)."""
    return data.get(key, fix="re-export the file with this field (formats: dualflow.motion.io.formats)")


def _text_field(data, key: str, source: str) -> str:
    return text(_get(data, key, source), f"{source}, field {key!r}")


def _positions_field(arr: np.ndarray, source: str, field: str) -> np.ndarray:
    arr = np.asarray(arr)
    if arr.dtype.kind != "f":
        raise DualFlowError(
            f"{source}, field {field!r}: expected joint positions as floating-point numbers (metres), "
            f"got dtype {arr.dtype}; save them as float32 or float64"
        )
    if arr.ndim == 2 and arr.shape[1] % 3 == 0 and arr.shape[1] >= 3 * N_JOINTS:
        arr = arr.reshape(arr.shape[0], -1, 3)
    if arr.ndim != 3 or arr.shape[2] != 3 or arr.shape[1] < N_JOINTS:
        raise DualFlowError(
            f"{source}, field {field!r}: expected joint positions (T, J >= 22, 3), got shape {tuple(arr.shape)}"
        )
    return arr[:, :N_JOINTS].astype(np.float64)


def _contacts_field(data, key: str, n: int, source: str):
    if key not in data.files:
        return None
    c = _get(data, key, source)
    if c.dtype.kind not in "biuf":
        raise DualFlowError(f"{source}, field {key!r}: expected foot contacts as booleans, got dtype {c.dtype}")
    if c.shape != (n, 4):
        raise DualFlowError(f"{source}, field {key!r}: expected shape ({n}, 4), got {tuple(c.shape)}")
    return c.astype(bool)


def _read_npz(path: Path, opts: dict):
    source = str(path)
    with open_npz(path) as data:
        files = set(data.files)
        fmt = _text_field(data, "format", source) if "format" in files else ""
        if fmt == MOTION_FORMAT or (not fmt and {"positions", "fps"} <= files and "joint_names" in files):
            pos = _positions_field(_get(data, "positions", source), source, "positions")
            fps = opts.get("source_fps") or _fps_value(_get(data, "fps", source), source, "fps")
            name = _text_field(data, "name", source) if "name" in files else path.stem
            contacts = _contacts_field(data, "contacts", pos.shape[0], source)
            return _finish(pos, fps, name, source, opts, contacts)
        if fmt == DUET_FORMAT:
            fps = opts.get("source_fps") or _fps_value(_get(data, "fps", source), source, "fps")
            people = []
            for role in ("actor", "reactor"):
                key = f"{role}_positions"
                if key not in files:
                    raise DualFlowError(f"{source}: duet file has no field {key!r}; it is incomplete")
                pos = _positions_field(_get(data, key, source), source, key)
                contacts = _contacts_field(data, f"{role}_contacts", pos.shape[0], source)
                name = _text_field(data, f"{role}_name", source) if f"{role}_name" in files else role
                people.append(_finish(pos, fps, name, source, opts, contacts))
            cue = _text_field(data, "text", source) if "text" in files else ""
            meta = {}
            if "meta" in files:
                try:
                    meta = json.loads(_text_field(data, "meta", source))
                except (json.JSONDecodeError, RecursionError) as exc:
                    raise DualFlowError(f"{source}, field 'meta': not valid JSON ({str(exc)[:100]})") from None
                if not isinstance(meta, dict):
                    raise DualFlowError(f"{source}, field 'meta': must be a JSON object, got {type(meta).__name__}")
            try:
                return TwoPersonMotion(people[0], people[1], cue, meta)
            except DualFlowError as exc:
                raise DualFlowError(f"{source}: {exc}") from None
        if fmt:
            raise DualFlowError(
                f"{source}, field 'format': unknown format {fmt!r}; expected {MOTION_FORMAT} or {DUET_FORMAT}"
            )
        key = next((k for k in _JOINT_KEYS if k in files), None)
        if key is None:
            if {"poses", "trans"} & files:
                raise DualFlowError(
                    f"{source}: an AMASS/SMPL parameter file (poses, trans, betas) without joint positions; "
                    "joint positions need the SMPL body model: export them (e.g. a 'joints' array (T, 22+, 3)) first"
                )
            raise DualFlowError(
                f"{source}: no joint positions found; expected one of the fields {', '.join(_JOINT_KEYS)} "
                f"(the file has: {', '.join(sorted(files)) or 'nothing'})"
            )
        pos = _positions_field(_get(data, key, source), source, key)
        fps_key = next((k for k in _FPS_KEYS if k in files), None)
        if opts.get("source_fps"):
            fps = check_fps(float(opts["source_fps"]), "option source_fps")
        elif fps_key is None:
            raise DualFlowError(
                f"{source}: no frame rate field ({', '.join(_FPS_KEYS)}); give the file's fps (--source-fps)"
            )
        else:
            fps = _fps_value(_get(data, fps_key, source), source, fps_key)
        pos = np.einsum("ab,tjb->tja", _axes(opts, "z"), pos)
        return _finish(pos, fps, path.stem, source, opts)


# ---------------------------------------------------------------------------
# npy
# ---------------------------------------------------------------------------
def _features():
    try:
        from dualflow.motion import features
    except ImportError as exc:  # the 262-d codec is part of dualflow.motion
        raise DualFlowError(f"reading InterGen 262-d features needs dualflow.motion.features ({exc})") from None
    return features


def _read_npy(path: Path, opts: dict):
    source = str(path)
    _magic(path, b"\x93NUMPY", ".npy")
    arr = read_npy(path)
    if arr.dtype.kind != "f":
        raise DualFlowError(
            f"{source}: expected a numeric array of floating-point numbers, got dtype {arr.dtype}; "
            "save it as float32 or float64"
        )
    if arr.ndim >= 1 and arr.shape[0] < MIN_FRAMES:
        raise DualFlowError(frames_message(arr.shape[0], source))
    if not np.isfinite(arr).all():
        row = int(np.argwhere(~np.isfinite(arr))[0][0])
        raise DualFlowError(f"{source}: contains NaN or inf (first at frame {row}); clean the file")
    shape = arr.shape
    if arr.ndim == 3 and shape[1:] == (N_JOINTS, 3):  # HumanML3D new_joints, Y up
        pos = np.einsum("ab,tjb->tja", _axes(opts, "y"), arr.astype(np.float64))
        return _finish(pos, opts.get("source_fps") or HUMANML3D_FPS, path.stem, source, opts)
    if arr.ndim == 2 and shape[1] == 492:  # InterGen raw
        raw = arr[:, : 3 * N_JOINTS].reshape(-1, N_JOINTS, 3).astype(np.float64)
        to_world = (Y_UP @ _INTERGEN_RAW_TO_YUP) if not opts.get("up") else axes_matrix(opts["up"])
        pos = np.einsum("ab,tjb->tja", to_world, raw)
        return _finish(pos, opts.get("source_fps") or INTERGEN_FPS, path.stem, source, opts)
    fps = opts.get("source_fps") or INTERGEN_FPS
    if arr.ndim == 2 and shape[1] == 262:
        m = _features().decode_person(arr.astype(np.float64), fps=fps, name=path.stem)
        return _finish(m.positions, fps, path.stem, source, opts, m.contacts)
    if (arr.ndim == 3 and shape[1:] == (2, 262)) or (arr.ndim == 2 and shape[1] == 524):
        pair = _features().decode_pair(arr.reshape(-1, 2, 262).astype(np.float64), fps=fps)
        people = [
            _finish(m.positions, fps, f"{path.stem}_{role}", source, opts, m.contacts)
            for m, role in ((pair.actor, "actor"), (pair.reactor, "reactor"))
        ]
        return TwoPersonMotion(people[0], people[1])
    raise DualFlowError(
        f"{source}: unrecognised array shape {shape}; expected HumanML3D joints (T, 22, 3), "
        "InterGen raw (T, 492), InterGen features (T, 262) or a feature pair (T, 2, 262)"
    )


# ---------------------------------------------------------------------------
# entry points
# ---------------------------------------------------------------------------
_OPTION_NAMES = {"fps", "source_fps", "scale", "up", "joint_map", "drop_first", "height_range", "axes"}


def _check_options(opts: dict) -> dict:
    unknown = set(opts) - _OPTION_NAMES
    if unknown:
        raise TypeError(f"unknown option(s): {', '.join(sorted(unknown))}")
    for key in ("fps", "source_fps", "scale"):
        value = opts.get(key)
        if value is not None and (not isinstance(value, (int, float)) or not np.isfinite(value) or value <= 0):
            raise DualFlowError(f"option {key!r} must be a positive number, got {value!r}")
        if value is not None and key != "scale":
            check_fps(float(value), f"option {key!r}")
    return opts


def _bvh_options(opts: dict) -> BvhImportOptions:
    return BvhImportOptions(
        scale=opts.get("scale"),
        up=opts.get("up") or "auto",
        joint_map=opts.get("joint_map"),
        drop_first=opts.get("drop_first", "auto"),
        height_range=opts.get("height_range", HEIGHT_RANGE),
        axes=opts.get("axes"),
    )


def _path(path) -> Path:
    p = Path(path)
    if not p.exists():
        raise DualFlowError(f"{p}: no such file")
    if p.is_dir():
        raise DualFlowError(f"{p}: is a folder, expected a motion file")
    return p


def load_any(path, **opts) -> Motion | TwoPersonMotion:
    """Load one motion file (format in the module docstring); a duet file gives a
    TwoPersonMotion, anything else a Motion.

    Options: ``fps`` (resample to), ``source_fps`` (the file's own rate where the
    file does not say or says wrong), ``scale`` (metres per file unit), ``up``
    ('y' / 'z'; BVH also 'auto'), ``joint_map`` and ``drop_first`` (BVH),
    ``height_range`` (m, or None to skip the check), ``axes`` (BVH, a 3x3 file->world).
    """
    opts = _check_options(dict(opts))
    p = _path(path)
    ext = p.suffix.lower()
    if ext == ".bvh":
        result = read_bvh_motion(p, _bvh_options(opts), opts.get("fps"))
        return result.motion
    if ext == ".npz":
        return _read_npz(p, opts)
    if ext == ".npy":
        return _read_npy(p, opts)
    raise DualFlowError(f"{p}: unknown motion file type {ext or '(none)'!r}; use .bvh, .npz or .npy")


def load_motion(path, **opts) -> Motion:
    """Load one person's motion (see :func:`load_any` for formats and options)."""
    m = load_any(path, **opts)
    if isinstance(m, TwoPersonMotion):
        raise DualFlowError(
            f"{path}: holds two people; use load_any / load_pair (CLI: pass it alone to motion info/preview)"
        )
    return m


def load_pair(actor_path, reactor_path, text: str = "", **opts) -> TwoPersonMotion:
    """Two files captured in one world frame -> TwoPersonMotion (actor, reactor).

    BVH: the reactor gets the actor's length unit and axes (unless ``scale`` / ``up``
    are given), so both stay in the capture's shared frame; nothing is re-centred.
    The reactor is resampled to the actor's fps and both are trimmed to the
    shorter length (:meth:`TwoPersonMotion.from_pair`).
    """
    opts = _check_options(dict(opts))
    a, b = _path(actor_path), _path(reactor_path)
    meta: dict = {"actor_file": str(a), "reactor_file": str(b)}
    if a.suffix.lower() == ".bvh" and b.suffix.lower() == ".bvh":
        ra = read_bvh_motion(a, _bvh_options(opts), opts.get("fps"))
        shared = dict(opts, scale=ra.scale, axes=ra.axes)
        rb = read_bvh_motion(b, _bvh_options(shared), opts.get("fps"))
        actor, reactor = ra.motion, rb.motion
        meta.update(
            scale=ra.scale,
            joint_map=[ra.joint_map, rb.joint_map],
            dropped_first_frame=[ra.dropped_first_frame, rb.dropped_first_frame],
        )
    else:
        actor, reactor = load_motion(a, **opts), load_motion(b, **opts)
    pair = TwoPersonMotion.from_pair(actor, reactor, text)
    return TwoPersonMotion(pair.actor, pair.reactor, text, meta)


def put_on_ground(motion: Motion | TwoPersonMotion) -> Motion | TwoPersonMotion:
    """Shift vertically so the lowest foot joint (ankles and toes, over all frames) is
    at z = 0. A pair gets one shared shift (the lower of the two), keeping its
    common frame. Readers never do this; it is for data whose floor is elsewhere."""
    if isinstance(motion, TwoPersonMotion):
        low = min(
            motion.actor.positions[:, list(FOOT_JOINTS), 2].min(),
            motion.reactor.positions[:, list(FOOT_JOINTS), 2].min(),
        )
        shift = np.array([0.0, 0.0, -low])
        return TwoPersonMotion(
            motion.actor.translated(shift), motion.reactor.translated(shift), motion.text, dict(motion.meta)
        )
    low = motion.positions[:, list(FOOT_JOINTS), 2].min()
    return motion.translated([0.0, 0.0, -low])


def _npz_bytes(arrays: dict) -> bytes:
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return buf.getvalue()


def motion_npz_arrays(motion: Motion) -> dict:
    arrays = {
        "format": np.array(MOTION_FORMAT),
        "positions": np.asarray(motion.positions, dtype=np.float64),
        "fps": np.array(motion.fps),
        "name": np.array(motion.name),
        "joint_names": np.array(JOINT_NAMES),
    }
    if motion.contacts is not None:
        arrays["contacts"] = motion.contacts.astype(bool)
    return arrays


def duet_npz_arrays(pair: TwoPersonMotion) -> dict:
    try:
        meta = json.dumps(pair.meta, default=lambda o: o.tolist() if isinstance(o, np.ndarray) else str(o))
    except (TypeError, ValueError) as exc:
        raise DualFlowError(f"duet meta cannot be stored as JSON ({exc})") from None
    arrays = {
        "format": np.array(DUET_FORMAT),
        "actor_positions": np.asarray(pair.actor.positions, dtype=np.float64),
        "reactor_positions": np.asarray(pair.reactor.positions, dtype=np.float64),
        "actor_name": np.array(pair.actor.name),
        "reactor_name": np.array(pair.reactor.name),
        "fps": np.array(pair.fps),
        "text": np.array(pair.text),
        "meta": np.array(meta),
        "joint_names": np.array(JOINT_NAMES),
    }
    for role, m in (("actor", pair.actor), ("reactor", pair.reactor)):
        if m.contacts is not None:
            arrays[f"{role}_contacts"] = m.contacts.astype(bool)
    return arrays


def save_motion(motion: Motion | TwoPersonMotion, path, *, translations: str = "root") -> None:
    """Write ``.npz`` (ours, both kinds) or ``.bvh`` (one person, SMPL-22 skeleton),
    atomically. ``translations`` is the BVH writer's option."""
    p = Path(path)
    ext = p.suffix.lower()
    if ext == ".npz":
        if isinstance(motion, TwoPersonMotion):
            atomic_write_bytes(p, _npz_bytes(duet_npz_arrays(motion)))
        elif isinstance(motion, Motion):
            atomic_write_bytes(p, _npz_bytes(motion_npz_arrays(motion)))
        else:
            raise DualFlowError(f"{p}: can only save a Motion or TwoPersonMotion, got {type(motion).__name__}")
        return
    if ext == ".bvh":
        if isinstance(motion, TwoPersonMotion):
            raise DualFlowError(
                f"{p}: a BVH file holds one person; save the actor and the reactor to two .bvh files "
                "(save_motion(pair.actor, ...), save_motion(pair.reactor, ...)) or use .npz"
            )
        write_bvh_motion(motion, p, translations=translations)
        return
    raise DualFlowError(f"{p}: cannot write {ext or '(no extension)'!r}; use .npz or .bvh")

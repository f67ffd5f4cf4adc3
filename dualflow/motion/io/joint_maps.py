"""Joint-name maps from BVH skeletons to the SMPL-22 joints, kept as data.

Contract: a map gives each SMPL joint a source in the BVH hierarchy: one joint name (End Sites
are ``<parent>_end``) or a point ``{"between": [A, B], "t": 0.4}`` = (1 - t) p_A + t p_B.
Built in: ``cmu``, ``mixamo`` (namespace prefixes ignored), ``mixamo_spine3``, ``smpl``. A user
YAML/JSON file may start from a built-in map (``base: mixamo``) and override ``joints``;
without ``base`` it must name all 22 joints.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from dualflow.errors import DualFlowError
from dualflow.motion.skeleton import JOINT_NAMES


@dataclass(frozen=True)
class JointSource:
    """Where one SMPL joint comes from: ``(1 - t) * p[a] + t * p[b]`` (``b`` None: ``p[a]``)."""

    a: str
    b: str | None = None
    t: float = 0.0

    @property
    def names(self) -> tuple[str, ...]:
        return (self.a,) if self.b is None else (self.a, self.b)


def _between(a: str, b: str, t: float = 0.5) -> dict:
    return {"between": [a, b], "t": t}


def _sided(left: dict) -> dict:
    """Complete a map given for the midline and the left side by mirroring names."""
    out = dict(left)
    for smpl, src in left.items():
        if not smpl.startswith("left_"):
            continue

        def swap(n):
            return n.replace("Left", "Right").replace("LHip", "RHip").replace("LThumb", "RThumb")

        if isinstance(src, str):
            out["right_" + smpl[5:]] = swap(src)
        else:
            out["right_" + smpl[5:]] = {"between": [swap(n) for n in src["between"]], "t": src["t"]}
    return out


#: CMU cgspeed 31-joint skeleton. Choices where SMPL has no direct counterpart:
#: LowerBack sits exactly on Hips (zero offset), so spine1 takes Spine (about
#: 0.13 m above the pelvis, SMPL's is about 0.11 m); spine2 is halfway between
#: Spine and Spine1; spine3 is Spine1 (the chest joint the arms hang from); Neck
#: coincides with Spine1, so neck takes Neck1 (the base of the neck, just above the
#: shoulders) and head takes Head; LeftShoulder also coincides with Spine1, so the
#: collar is halfway along the clavicle from LeftShoulder to LeftArm, and
#: left_shoulder is LeftArm (the gleno-humeral joint).
CMU_CGSPEED: dict = _sided(
    {
        "pelvis": "Hips",
        "left_hip": "LeftUpLeg",
        "left_knee": "LeftLeg",
        "left_ankle": "LeftFoot",
        "left_foot": "LeftToeBase",
        "spine1": "Spine",
        "spine2": _between("Spine", "Spine1"),
        "spine3": "Spine1",
        "neck": "Neck1",
        "head": "Head",
        "left_collar": _between("LeftShoulder", "LeftArm"),
        "left_shoulder": "LeftArm",
        "left_elbow": "LeftForeArm",
        "left_wrist": "LeftHand",
    }
)

#: Mixamo-style skeleton with three spine joints: one to one.
MIXAMO: dict = _sided(
    {
        "pelvis": "Hips",
        "left_hip": "LeftUpLeg",
        "left_knee": "LeftLeg",
        "left_ankle": "LeftFoot",
        "left_foot": "LeftToeBase",
        "spine1": "Spine",
        "spine2": "Spine1",
        "spine3": "Spine2",
        "neck": "Neck",
        "head": "Head",
        "left_collar": "LeftShoulder",
        "left_shoulder": "LeftArm",
        "left_elbow": "LeftForeArm",
        "left_wrist": "LeftHand",
    }
)

#: Four spine joints (Spine just above the hips, then Spine1-3): SMPL's three
#: spine joints take Spine1, Spine2 and Spine3, the upper three.
MIXAMO_SPINE3: dict = {**MIXAMO, "spine1": "Spine1", "spine2": "Spine2", "spine3": "Spine3"}

#: Our own SMPL-22 names (the BVH files this package writes).
SMPL: dict = {name: name for name in JOINT_NAMES}

BUILTIN_MAPS: dict[str, dict] = {
    "cmu": CMU_CGSPEED,
    "mixamo": MIXAMO,
    "mixamo_spine3": MIXAMO_SPINE3,
    "smpl": SMPL,
}

#: Detection tries the built-in maps in this order, most specific first.
DETECTION_ORDER: tuple[str, ...] = ("cmu", "mixamo_spine3", "mixamo", "smpl")


@dataclass(frozen=True)
class JointMap:
    """A validated map: one :class:`JointSource` per SMPL joint, in SMPL order."""

    name: str
    sources: tuple[JointSource, ...]

    def source_names(self) -> set[str]:
        return {n for s in self.sources for n in s.names}

    def apply(self, positions: np.ndarray, names: Sequence[str], source: str = "<bvh>") -> np.ndarray:
        """SMPL-22 positions (T, 22, 3) from BVH joint positions (T, J, 3) named ``names``."""
        lookup = {n: i for i, n in enumerate(names)}
        missing = sorted(self.source_names() - set(lookup))
        if missing:
            raise DualFlowError(
                f"{source}: joint map {self.name!r} needs joints the file lacks: {', '.join(missing)}; "
                f"the file has: {', '.join(names)}. Pass a joint map file (--joint-map) that names existing joints"
            )
        a = np.array([lookup[s.a] for s in self.sources])
        b = np.array([lookup[s.b if s.b is not None else s.a] for s in self.sources])
        t = np.array([s.t if s.b is not None else 0.0 for s in self.sources])[:, None]
        return (1.0 - t) * positions[:, a] + t * positions[:, b]


def strip_namespace(name: str) -> str:
    """``"mixamorig:LeftArm"`` -> ``"LeftArm"``; names without a namespace are unchanged."""
    return name.rsplit(":", 1)[-1]


def _parse_source(value, where: str) -> JointSource:
    if isinstance(value, str) and value:
        return JointSource(value)
    if isinstance(value, Mapping) and set(value) <= {"between", "t"} and "between" in value:
        pair = value["between"]
        t = value.get("t", 0.5)
        if (
            isinstance(pair, Sequence)
            and not isinstance(pair, str)
            and len(pair) == 2
            and all(isinstance(n, str) and n for n in pair)
            and isinstance(t, (int, float))
            and 0.0 <= float(t) <= 1.0
        ):
            return JointSource(pair[0], pair[1], float(t))
    raise DualFlowError(f"{where}: a source must be a joint name or {{between: [A, B], t: 0..1}}, got {value!r}")


def make_joint_map(spec: Mapping, name: str = "custom", where: str = "joint map") -> JointMap:
    """Validate a ``{smpl_name: source}`` mapping covering all 22 SMPL joints."""
    unknown = sorted(set(spec) - set(JOINT_NAMES))
    if unknown:
        raise DualFlowError(
            f"{where}: unknown SMPL joint name(s) {', '.join(map(repr, unknown))}; "
            f"valid names: {', '.join(JOINT_NAMES)}"
        )
    missing = [n for n in JOINT_NAMES if n not in spec]
    if missing:
        raise DualFlowError(
            f"{where}: no source for SMPL joint(s) {', '.join(missing)}; give all 22 or set 'base:' to a built-in map"
        )
    return JointMap(name, tuple(_parse_source(spec[n], f"{where}, joint {n!r}") for n in JOINT_NAMES))


def builtin_map(name: str) -> JointMap:
    if name not in BUILTIN_MAPS:
        raise DualFlowError(f"unknown built-in joint map {name!r}; choose one of: {', '.join(BUILTIN_MAPS)}")
    return make_joint_map(BUILTIN_MAPS[name], name)


def load_joint_map(path: str | os.PathLike) -> JointMap:
    """Read a user joint-map file (.yaml/.yml/.json; format in the module docstring)."""
    path = Path(path)
    kind = "JSON" if path.suffix.lower() == ".json" else "YAML"
    try:
        text = path.read_bytes().decode("utf-8")
    except OSError as exc:
        raise DualFlowError(f"{path}: cannot read joint map ({exc.strerror})") from None
    except UnicodeDecodeError as exc:
        raise DualFlowError(f"{path}: not UTF-8 text (byte {exc.start}); a joint map is a {kind} file") from None
    try:
        data = json.loads(text) if kind == "JSON" else yaml.safe_load(text)
    except (json.JSONDecodeError, yaml.YAMLError) as exc:
        raise DualFlowError(f"{path}: not valid {kind}: {str(exc)[:200]}") from None
    except RecursionError:
        raise DualFlowError(f"{path}: nested too deeply to be a joint map; fix the syntax") from None
    if not isinstance(data, Mapping) or "joints" not in data or not isinstance(data["joints"], Mapping):
        raise DualFlowError(
            f"{path}: a joint map needs a 'joints:' mapping of SMPL joint -> source (and optionally 'base:')"
        )
    extra = sorted(set(data) - {"base", "joints"})
    if extra:
        raise DualFlowError(f"{path}: unknown key(s) {', '.join(extra)}; only 'base' and 'joints' are allowed")
    spec: dict = {}
    if data.get("base") is not None:
        if data["base"] not in BUILTIN_MAPS:
            raise DualFlowError(
                f"{path}, field 'base': unknown map {data['base']!r}; choose one of: {', '.join(BUILTIN_MAPS)}"
            )
        spec.update(BUILTIN_MAPS[data["base"]])
    spec.update(data["joints"])
    return make_joint_map(spec, name=str(path), where=str(path))


def detect_joint_map(names: Sequence[str], source: str = "<bvh>") -> JointMap:
    """The built-in map that fits a hierarchy's joint names.

    The first map in :data:`DETECTION_ORDER` whose source joints all exist wins;
    the order puts the more specific skeletons first (a four-joint spine also
    has the joints of the three-joint one). When none fits, the error lists what
    the closest map misses and how to fix it.
    """
    present = set(names)
    closest = None
    for key in DETECTION_ORDER:
        jm = builtin_map(key)
        missing = jm.source_names() - present
        if not missing:
            return jm
        if closest is None or len(missing) < len(closest[1]):
            closest = (key, missing)
    key, missing = closest
    raise DualFlowError(
        f"{source}: unknown skeleton; no built-in joint map fits (closest {key!r} misses "
        f"{', '.join(sorted(missing))}). Write a joint map file (YAML: base: {key}, joints: "
        "{smpl_joint: YourJoint}) and pass it with --joint-map"
    )


def resolve_joint_map(names: Sequence[str], joint_map=None, source: str = "<bvh>") -> JointMap:
    """``joint_map`` may be None (detect), a built-in name, a file path, a mapping or a JointMap."""
    if joint_map is None:
        return detect_joint_map(names, source)
    if isinstance(joint_map, JointMap):
        return joint_map
    if isinstance(joint_map, Mapping):
        return make_joint_map(joint_map)
    if isinstance(joint_map, str) and joint_map in BUILTIN_MAPS:
        return builtin_map(joint_map)
    path = Path(joint_map)
    if path.suffix.lower() in (".yaml", ".yml", ".json") or path.exists():
        return load_joint_map(path)
    raise DualFlowError(
        f"joint map {joint_map!r} is neither a built-in map ({', '.join(BUILTIN_MAPS)}) nor a .yaml/.json file"
    )

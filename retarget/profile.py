"""The retarget profile of one robot (YAML): what drives what, how hard, within which limits.

A profile says, in robot-independent terms:

- ``keypoints``: which SMPL-22 human joint drives which robot point (a ``site``, or a
  ``body`` with an optional ``offset`` (3,) m in the body frame), with a tracking ``weight``;
- ``scale``: per-bone overrides of the automatic scale (keyed by the child human joint),
  and ``root`` for the root translation scale. By default every scale is computed from the
  human's and the robot's rest-pose bone lengths (see :mod:`retarget.targets`);
- ``joint_limits``: narrower position limits (rad) per joint, never wider than the MJCF;
- ``velocity_limits``: ``default`` and per-joint speed limits (rad/s), and for a free root
  ``root_linear`` (m/s, default 2 standing root heights per second) and ``root_angular``
  (rad/s of each root angle, default 2π): the root moves only as fast as a body could;
- ``capsules`` and ``collision_pairs``: capsules (an MJCF ``geom``, or ``body`` +
  ``from``/``to`` (3,) m + ``radius`` m) and the pairs that must stay apart;
- ``feet``: ``left``/``right`` foot ``body`` and either its sole ``geom`` (a box: the
  face lowest in the stand pose is the sole) or four sole ``corners`` (body frame, m);
- ``rigid_offsets``: keypoints (default: hips and shoulders) placed at the robot's own rest
  offset from their parent, turned by the human's pelvis or chest frame, instead of along the
  scaled human bone (these short bones point differently on a person and on most robots);
- ``posture_weight``: pull towards the ``stand_keyframe`` pose, which also seeds the solvers;
- ``mjcf``: the robot's model, relative to the profile's folder (a robot folder's profile names
  its model this way, see :mod:`firmware_cfg.registry`); the solver ignores it.

Only positions are tracked, so no rotation offsets between human and robot frames
are ever needed. Validation against the MJCF happens in :class:`retarget.robot.RetargetRobot`;
every error names the profile file and the field.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from dualflow.motion.skeleton import JOINT_NAMES
from retarget.errors import RetargetError


@dataclass(frozen=True)
class KeypointSpec:
    """Human joint ``human`` drives the robot point ``site`` or ``body`` + ``offset`` (3,) m."""

    human: str
    site: str | None = None
    body: str | None = None
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    weight: float = 1.0


@dataclass(frozen=True)
class CapsuleSpec:
    """A capsule: an MJCF ``geom``, or ``body`` + segment ``p0``/``p1`` (3,) m + ``radius`` m."""

    name: str
    geom: str | None = None
    body: str | None = None
    p0: tuple[float, float, float] | None = None
    p1: tuple[float, float, float] | None = None
    radius: float | None = None


@dataclass(frozen=True)
class FootSpec:
    """One foot: the ``body`` it moves with and its sole (a box ``geom`` or 4 ``corners`` (4, 3) m)."""

    side: str
    body: str
    geom: str | None = None
    corners: tuple | None = None


@dataclass(frozen=True)
class RetargetProfile:
    robot: str
    keypoints: tuple[KeypointSpec, ...]
    root_joint: str = "pelvis"
    scale_overrides: dict = field(default_factory=dict)
    root_scale: float | None = None
    joint_limits: dict = field(default_factory=dict)
    velocity_default: float = 5.0
    velocity_limits: dict = field(default_factory=dict)
    root_linear: float | None = None
    root_angular: float = 2 * np.pi
    capsules: dict = field(default_factory=dict)
    collision_pairs: tuple = ()
    collision_margin: float = 0.005
    feet: dict = field(default_factory=dict)
    posture_weight: float = 0.02
    stand_keyframe: str = "stand"
    rigid_offsets: tuple = ("left_hip", "right_hip", "left_shoulder", "right_shoulder")
    source: str = ""

    # -- loading ----------------------------------------------------------------
    @classmethod
    def load(cls, path) -> "RetargetProfile":
        path = Path(path)
        if not path.is_file():
            raise RetargetError(f"{path}: retarget profile not found; write one (see firmware_cfg/robots/op3/profile.yaml, or run `dualflow-bridge robot init MODEL.xml -o DIR`)")
        try:
            data = yaml.safe_load(path.read_bytes().decode("utf-8"))
        except yaml.YAMLError as exc:
            raise RetargetError(f"{path}: not valid YAML ({str(exc).splitlines()[0]})") from None
        except UnicodeDecodeError as exc:
            raise RetargetError(f"{path}: not UTF-8 text (byte {exc.start}); is it really a profile.yaml?") from None
        except RecursionError:
            raise RetargetError(f"{path}: nested too deeply to be a retarget profile; fix the syntax") from None
        return cls.from_dict(data, source=str(path))

    @classmethod
    def from_dict(cls, data, source: str = "profile") -> "RetargetProfile":
        if not isinstance(data, dict):
            raise RetargetError(f"{source}: the profile must be a YAML mapping with keys robot, keypoints, feet, ...")
        # mjcf: the robot folder's model (relative to the profile), read by firmware_cfg.registry;
        # the solver gets its model from the caller and ignores the key
        known = {"robot", "mjcf", "root", "keypoints", "scale", "joint_limits", "velocity_limits", "capsules",
                 "collision_pairs", "collision_margin", "feet", "posture_weight", "stand_keyframe", "rigid_offsets"}
        unknown = sorted(set(data) - known)
        if unknown:
            raise RetargetError(f"{source}: unknown field(s) {unknown}; known fields are {sorted(known)}")

        def where(f):
            return f"{source}: field {f}"

        kps = data.get("keypoints")
        if not isinstance(kps, dict) or not kps:
            raise RetargetError(f"{where('keypoints')}: give a mapping human joint -> {{site: ...}} or {{body: ..., offset: [x, y, z]}}")
        keypoints = []
        for human, spec in kps.items():
            f = f"keypoints.{human}"
            if human not in JOINT_NAMES:
                raise RetargetError(f"{where(f)}: {human!r} is not an SMPL-22 joint; use one of {', '.join(JOINT_NAMES)}")
            if not isinstance(spec, dict) or (("site" in spec) == ("body" in spec)):
                raise RetargetError(f"{where(f)}: give exactly one of site: NAME or body: NAME")
            keypoints.append(KeypointSpec(
                human=human, site=spec.get("site"), body=spec.get("body"),
                offset=_vec3(spec.get("offset", (0, 0, 0)), where(f + ".offset")),
                weight=_positive(spec.get("weight", 1.0), where(f + ".weight"), allow_zero=True)))
        root = data.get("root", "pelvis")
        if root not in kps:
            raise RetargetError(f"{where('root')}: the root human joint {root!r} must also be one of the keypoints")

        scale = data.get("scale") or {}
        if not isinstance(scale, dict):
            raise RetargetError(f"{where('scale')}: give a mapping human joint -> bone scale (and optionally root: s)")
        root_scale = None
        overrides = {}
        for k, v in scale.items():
            if k == "root":
                root_scale = _positive(v, where("scale.root"))
            elif k not in kps:
                raise RetargetError(f"{where('scale.' + str(k))}: {k!r} is not one of the keypoints; scales are keyed by the child keypoint's human joint")
            else:
                overrides[k] = _positive(v, where("scale." + k))

        jl = data.get("joint_limits") or {}
        if not isinstance(jl, dict):
            raise RetargetError(f"{where('joint_limits')}: give a mapping joint -> [lower, upper] in rad")
        joint_limits = {}
        for k, v in jl.items():
            try:
                lo, hi = (float(x) for x in v)
            except (TypeError, ValueError):
                raise RetargetError(f"{where('joint_limits.' + str(k))}: give [lower, upper] in rad, got {v!r}") from None
            if not lo < hi:
                raise RetargetError(f"{where('joint_limits.' + str(k))}: lower {lo} must be below upper {hi}")
            joint_limits[str(k)] = (lo, hi)

        vl = data.get("velocity_limits") or {}
        if not isinstance(vl, dict):
            raise RetargetError(f"{where('velocity_limits')}: give a mapping with default: rad/s and joint: rad/s")
        vdefault = _positive(vl.get("default", 5.0), where("velocity_limits.default"))
        vlimits = {str(k): _positive(v, where(f"velocity_limits.{k}")) for k, v in vl.items()
                   if k not in ("default", "root_linear", "root_angular")}
        root_linear = _positive(vl["root_linear"], where("velocity_limits.root_linear")) if "root_linear" in vl else None
        root_angular = _positive(vl.get("root_angular", 2 * np.pi), where("velocity_limits.root_angular"))

        caps = {}
        for name, spec in (data.get("capsules") or {}).items():
            f = f"capsules.{name}"
            if not isinstance(spec, dict):
                raise RetargetError(f"{where(f)}: give {{geom: NAME}} or {{body: NAME, from: [x,y,z], to: [x,y,z], radius: r}}")
            if "geom" in spec:
                caps[name] = CapsuleSpec(name, geom=str(spec["geom"]))
            elif {"body", "from", "to", "radius"} <= set(spec):
                caps[name] = CapsuleSpec(name, body=str(spec["body"]), p0=_vec3(spec["from"], where(f + ".from")),
                                         p1=_vec3(spec["to"], where(f + ".to")), radius=_positive(spec["radius"], where(f + ".radius")))
            else:
                raise RetargetError(f"{where(f)}: give geom: NAME, or all of body, from, to, radius")
        pairs = []
        for i, pair in enumerate(data.get("collision_pairs") or []):
            f = f"collision_pairs[{i}]"
            if not isinstance(pair, (list, tuple)) or len(pair) != 2:
                raise RetargetError(f"{where(f)}: give a pair [capsule_a, capsule_b]")
            for c in pair:
                if c not in caps:
                    raise RetargetError(f"{where(f)}: {c!r} is not a capsule defined under capsules: ({', '.join(caps) or 'none'})")
            pairs.append((str(pair[0]), str(pair[1])))

        feet = {}
        fdata = data.get("feet")
        if fdata is not None:
            if not isinstance(fdata, dict) or set(fdata) != {"left", "right"}:
                raise RetargetError(f"{where('feet')}: give both left: and right: feet (or leave feet out for a robot without legs)")
            for side, spec in fdata.items():
                f = f"feet.{side}"
                if not isinstance(spec, dict) or "body" not in spec or (("geom" in spec) == ("corners" in spec)):
                    raise RetargetError(f"{where(f)}: give body: NAME and exactly one of geom: NAME (a box) or corners: 4 x [x, y, z]")
                corners = None
                if "corners" in spec:
                    c = np.asarray(spec["corners"], dtype=float)
                    if c.shape != (4, 3) or not np.all(np.isfinite(c)):
                        raise RetargetError(f"{where(f + '.corners')}: give 4 corners [x, y, z] in the foot body frame (m)")
                    corners = tuple(map(tuple, c))
                feet[side] = FootSpec(side, str(spec["body"]), spec.get("geom"), corners)

        rigid = data.get("rigid_offsets", ["left_hip", "right_hip", "left_shoulder", "right_shoulder"]) or []
        allowed = ("left_hip", "right_hip", "left_shoulder", "right_shoulder")
        for name in rigid:
            if name not in allowed:
                raise RetargetError(f"{where('rigid_offsets')}: {name!r} is not one of {', '.join(allowed)}")
        rigid = tuple(n for n in rigid if n in kps)

        return cls(
            robot=str(data.get("robot", "")), rigid_offsets=rigid, keypoints=tuple(keypoints), root_joint=root,
            scale_overrides=overrides, root_scale=root_scale, joint_limits=joint_limits,
            velocity_default=vdefault, velocity_limits=vlimits, root_linear=root_linear, root_angular=root_angular, capsules=caps, collision_pairs=tuple(pairs),
            collision_margin=float(data.get("collision_margin", 0.005)), feet=feet,
            posture_weight=_positive(data.get("posture_weight", 0.02), where("posture_weight"), allow_zero=True),
            stand_keyframe=str(data.get("stand_keyframe", "stand")), source=source,
        )

    def fingerprint(self) -> str:
        import hashlib

        return hashlib.sha256(repr(self.__dict__ | {"source": ""}).encode()).hexdigest()


def _vec3(v, where: str) -> tuple[float, float, float]:
    try:
        a = np.asarray(v, dtype=float)
    except (TypeError, ValueError):
        a = np.zeros(0)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise RetargetError(f"{where}: give three numbers [x, y, z] in metres, got {v!r}")
    return tuple(float(x) for x in a)


def _positive(v, where: str, allow_zero: bool = False) -> float:
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise RetargetError(f"{where}: give a number, got {v!r}") from None
    if not np.isfinite(x) or x < 0 or (x == 0 and not allow_zero):
        raise RetargetError(f"{where}: must be {'>= 0' if allow_zero else '> 0'}, got {v!r}")
    return x

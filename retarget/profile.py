"""The retarget profile of one robot (YAML): what drives what, how hard, within which limits.

Contract: :meth:`RetargetProfile.load` reads ``profile.yaml`` (fields: ``robot``, ``mjcf``,
``root``, ``keypoints``, ``scale``, ``joint_limits``, ``velocity_limits``, ``capsules``,
``collision_pairs``, ``collision_margin``, ``feet``, ``rigid_offsets``, ``posture_weight``,
``stand_keyframe``, ``streaming_steps``) into a frozen :class:`RetargetProfile`; every error is a
:class:`retarget.errors.RetargetError` naming the file and the field. Lengths m, angles rad,
speeds rad/s. Validation against the MJCF happens in :class:`retarget.robot.RetargetRobot`.
What each field means: docs/retargeting.md, section 8.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from dualflow.motion.skeleton import JOINT_NAMES
from retarget.errors import RetargetError

#: the range of a profile's ``step_pace`` (x the streaming step phases' default lengths)
MIN_STEP_PACE, MAX_STEP_PACE = 0.5, 4.0


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
    #: ((joint, rad), ...): the standing pose where the MJCF has no keyframe ``stand_keyframe``
    #: (robot init derives one: retarget.stand_init); joints not named keep their qpos0
    stand_pose: tuple = ()
    #: whether the streaming retargeter (the live bridge) steps with this free-standing robot
    #: when the person steps (True), or keeps its feet planted (StreamingConfig.steps None)
    streaming_steps: bool = True
    #: the streaming retargeter's step phases at this multiple of their lengths (StreamingConfig
    #: step_pace None): a robot whose servos answer slowly steps at a slower pace (robot init
    #: measures it: sim.step_probe)
    step_pace: float = 1.0
    rigid_offsets: tuple = ("left_hip", "right_hip", "left_shoulder", "right_shoulder")
    source: str = ""

    # -- loading ----------------------------------------------------------------
    @classmethod
    def load(cls, path) -> RetargetProfile:
        path = Path(path)
        if not path.is_file():
            raise RetargetError(
                f"{path}: retarget profile not found; write one (see firmware_cfg/robots/op3/profile.yaml, "
                "or run `dualflow-bridge robot init MODEL.xml -o DIR`)"
            )
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
    def from_dict(cls, data, source: str = "profile") -> RetargetProfile:
        """A profile from its parsed YAML ``data``; every error names ``source`` and the field."""
        if not isinstance(data, dict):
            raise RetargetError(f"{source}: the profile must be a YAML mapping with keys robot, keypoints, feet, ...")
        # mjcf: the robot folder's model (relative to the profile), read by firmware_cfg.registry;
        # the solver gets its model from the caller and ignores the key
        known = {
            "robot",
            "mjcf",
            "root",
            "keypoints",
            "scale",
            "joint_limits",
            "velocity_limits",
            "capsules",
            "collision_pairs",
            "collision_margin",
            "feet",
            "posture_weight",
            "stand_keyframe",
            "stand_pose",
            "rigid_offsets",
            "streaming_steps",
            "step_pace",
        }
        unknown = sorted(set(data) - known)
        if unknown:
            raise RetargetError(f"{source}: unknown field(s) {unknown}; known fields are {sorted(known)}")
        kps, keypoints = _parse_keypoints(data, source)
        root = data.get("root", "pelvis")
        if root not in kps:
            raise RetargetError(
                f"{_where(source, 'root')}: the root human joint {root!r} must also be one of the keypoints"
            )
        # checked in this order: the first error a profile has is the one reported
        root_scale, overrides = _parse_scale(data, kps, source)
        joint_limits = _parse_joint_limits(data, source)
        vdefault, vlimits, root_linear, root_angular = _parse_velocity_limits(data, source)
        caps = _parse_capsules(data, source)
        pairs = _parse_pairs(data, caps, source)
        feet = _parse_feet(data, source)
        rigid = _parse_rigid_offsets(data, kps, source)
        return cls(
            robot=str(data.get("robot", "")),
            rigid_offsets=rigid,
            keypoints=tuple(keypoints),
            root_joint=root,
            scale_overrides=overrides,
            root_scale=root_scale,
            joint_limits=joint_limits,
            velocity_default=vdefault,
            velocity_limits=vlimits,
            root_linear=root_linear,
            root_angular=root_angular,
            capsules=caps,
            collision_pairs=pairs,
            collision_margin=float(data.get("collision_margin", 0.005)),
            feet=feet,
            posture_weight=_positive(
                data.get("posture_weight", 0.02), _where(source, "posture_weight"), allow_zero=True
            ),
            stand_keyframe=str(data.get("stand_keyframe", "stand")),
            stand_pose=_parse_stand_pose(data, source),
            streaming_steps=_flag(data.get("streaming_steps", True), _where(source, "streaming_steps")),
            step_pace=_step_pace(data.get("step_pace", 1.0), _where(source, "step_pace")),
            source=source,
        )

    def fingerprint(self) -> str:
        import hashlib

        return hashlib.sha256(repr(self.__dict__ | {"source": ""}).encode()).hexdigest()


def _where(source: str, f: str) -> str:
    return f"{source}: field {f}"


def _parse_keypoints(data: dict, source: str) -> tuple[dict, list]:
    """(the ``keypoints`` mapping, its KeypointSpecs)."""
    kps = data.get("keypoints")
    if not isinstance(kps, dict) or not kps:
        raise RetargetError(
            f"{_where(source, 'keypoints')}: give a mapping human joint -> {{site: ...}} "
            "or {body: ..., offset: [x, y, z]}"
        )
    keypoints = []
    for human, spec in kps.items():
        f = _where(source, f"keypoints.{human}")
        if human not in JOINT_NAMES:
            raise RetargetError(f"{f}: {human!r} is not an SMPL-22 joint; use one of {', '.join(JOINT_NAMES)}")
        if not isinstance(spec, dict) or (("site" in spec) == ("body" in spec)):
            raise RetargetError(f"{f}: give exactly one of site: NAME or body: NAME")
        keypoints.append(
            KeypointSpec(
                human=human,
                site=spec.get("site"),
                body=spec.get("body"),
                offset=_vec3(spec.get("offset", (0, 0, 0)), f + ".offset"),
                weight=_positive(spec.get("weight", 1.0), f + ".weight", allow_zero=True),
            )
        )
    return kps, keypoints


def _parse_scale(data: dict, kps: dict, source: str) -> tuple[float | None, dict]:
    """(root scale or None, per-bone scale overrides keyed by the child keypoint's human joint)."""
    scale = data.get("scale") or {}
    if not isinstance(scale, dict):
        raise RetargetError(
            f"{_where(source, 'scale')}: give a mapping human joint -> bone scale (and optionally root: s)"
        )
    root_scale = None
    overrides = {}
    for k, v in scale.items():
        if k == "root":
            root_scale = _positive(v, _where(source, "scale.root"))
        elif k not in kps:
            raise RetargetError(
                f"{_where(source, 'scale.' + str(k))}: {k!r} is not one of the keypoints; "
                "scales are keyed by the child keypoint's human joint"
            )
        else:
            overrides[k] = _positive(v, _where(source, "scale." + k))
    return root_scale, overrides


def _parse_joint_limits(data: dict, source: str) -> dict:
    """joint -> (lower, upper) rad."""
    jl = data.get("joint_limits") or {}
    if not isinstance(jl, dict):
        raise RetargetError(f"{_where(source, 'joint_limits')}: give a mapping joint -> [lower, upper] in rad")
    joint_limits = {}
    for k, v in jl.items():
        f = _where(source, "joint_limits." + str(k))
        try:
            lo, hi = (float(x) for x in v)
        except (TypeError, ValueError):
            raise RetargetError(f"{f}: give [lower, upper] in rad, got {v!r}") from None
        if not lo < hi:
            raise RetargetError(f"{f}: lower {lo} must be below upper {hi}")
        joint_limits[str(k)] = (lo, hi)
    return joint_limits


def _parse_velocity_limits(data: dict, source: str) -> tuple:
    """(default rad/s, per-joint rad/s, root_linear m/s or None, root_angular rad/s)."""
    vl = data.get("velocity_limits") or {}
    if not isinstance(vl, dict):
        raise RetargetError(f"{_where(source, 'velocity_limits')}: give a mapping with default: rad/s and joint: rad/s")
    vdefault = _positive(vl.get("default", 5.0), _where(source, "velocity_limits.default"))
    vlimits = {
        str(k): _positive(v, _where(source, f"velocity_limits.{k}"))
        for k, v in vl.items()
        if k not in ("default", "root_linear", "root_angular")
    }
    root_linear = (
        _positive(vl["root_linear"], _where(source, "velocity_limits.root_linear")) if "root_linear" in vl else None
    )
    root_angular = _positive(vl.get("root_angular", 2 * np.pi), _where(source, "velocity_limits.root_angular"))
    return vdefault, vlimits, root_linear, root_angular


def _parse_capsules(data: dict, source: str) -> dict:
    """name -> CapsuleSpec."""
    caps = {}
    for name, spec in (data.get("capsules") or {}).items():
        f = _where(source, f"capsules.{name}")
        if not isinstance(spec, dict):
            raise RetargetError(f"{f}: give {{geom: NAME}} or {{body: NAME, from: [x,y,z], to: [x,y,z], radius: r}}")
        if "geom" in spec:
            caps[name] = CapsuleSpec(name, geom=str(spec["geom"]))
        elif {"body", "from", "to", "radius"} <= set(spec):
            caps[name] = CapsuleSpec(
                name,
                body=str(spec["body"]),
                p0=_vec3(spec["from"], f + ".from"),
                p1=_vec3(spec["to"], f + ".to"),
                radius=_positive(spec["radius"], f + ".radius"),
            )
        else:
            raise RetargetError(f"{f}: give geom: NAME, or all of body, from, to, radius")
    return caps


def _parse_pairs(data: dict, caps: dict, source: str) -> tuple:
    """The collision pairs ((capsule_a, capsule_b), ...), each naming capsules of ``caps``."""
    pairs = []
    for i, pair in enumerate(data.get("collision_pairs") or []):
        f = _where(source, f"collision_pairs[{i}]")
        if not isinstance(pair, (list, tuple)) or len(pair) != 2:
            raise RetargetError(f"{f}: give a pair [capsule_a, capsule_b]")
        for c in pair:
            if c not in caps:
                raise RetargetError(
                    f"{f}: {c!r} is not a capsule defined under capsules: ({', '.join(caps) or 'none'})"
                )
        pairs.append((str(pair[0]), str(pair[1])))
    return tuple(pairs)


def _parse_feet(data: dict, source: str) -> dict:
    """side -> FootSpec (empty for a robot without legs)."""
    feet = {}
    fdata = data.get("feet")
    if fdata is None:
        return feet
    if not isinstance(fdata, dict) or set(fdata) != {"left", "right"}:
        raise RetargetError(
            f"{_where(source, 'feet')}: give both left: and right: feet (or leave feet out for a robot without legs)"
        )
    for side, spec in fdata.items():
        f = _where(source, f"feet.{side}")
        if not isinstance(spec, dict) or "body" not in spec or (("geom" in spec) == ("corners" in spec)):
            raise RetargetError(f"{f}: give body: NAME and exactly one of geom: NAME (a box) or corners: 4 x [x, y, z]")
        corners = None
        if "corners" in spec:
            c = np.asarray(spec["corners"], dtype=float)
            if c.shape != (4, 3) or not np.all(np.isfinite(c)):
                raise RetargetError(f"{f}.corners: give 4 corners [x, y, z] in the foot body frame (m)")
            corners = tuple(map(tuple, c))
        feet[side] = FootSpec(side, str(spec["body"]), spec.get("geom"), corners)
    return feet


def _parse_rigid_offsets(data: dict, kps: dict, source: str) -> tuple:
    """The keypoints placed at the robot's own rest offset (those of them that are keypoints)."""
    rigid = data.get("rigid_offsets", ["left_hip", "right_hip", "left_shoulder", "right_shoulder"]) or []
    allowed = ("left_hip", "right_hip", "left_shoulder", "right_shoulder")
    for name in rigid:
        if name not in allowed:
            raise RetargetError(f"{_where(source, 'rigid_offsets')}: {name!r} is not one of {', '.join(allowed)}")
    return tuple(n for n in rigid if n in kps)


def _vec3(v, where: str) -> tuple[float, float, float]:
    try:
        a = np.asarray(v, dtype=float)
    except (TypeError, ValueError):
        a = np.zeros(0)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise RetargetError(f"{where}: give three numbers [x, y, z] in metres, got {v!r}")
    return tuple(float(x) for x in a)


def _parse_stand_pose(data: dict, source: str) -> tuple:
    raw = data.get("stand_pose") or {}
    where = _where(source, "stand_pose")
    if not isinstance(raw, dict):
        raise RetargetError(f"{where}: must map joint names to angles in rad, e.g. {{l_knee: 0.6}}; got {raw!r}")
    out = []
    for name, v in raw.items():
        try:
            x = float(v)
        except (TypeError, ValueError):
            raise RetargetError(f"{where}.{name}: give an angle in rad, got {v!r}") from None
        if not np.isfinite(x):
            raise RetargetError(f"{where}.{name}: give a finite angle in rad, got {v!r}")
        out.append((str(name), x))
    return tuple(out)


def _flag(v, where: str) -> bool:
    if not isinstance(v, bool):
        raise RetargetError(f"{where}: must be true or false, got {v!r}")
    return v


def _step_pace(v, where: str) -> float:
    x = _positive(v, where)
    if not MIN_STEP_PACE <= x <= MAX_STEP_PACE:
        raise RetargetError(
            f"{where}: must be within {MIN_STEP_PACE:g}-{MAX_STEP_PACE:g} (x the step phases' default lengths), "
            f"got {v!r}"
        )
    return x


def _positive(v, where: str, allow_zero: bool = False) -> float:
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise RetargetError(f"{where}: give a number, got {v!r}") from None
    if not np.isfinite(x) or x < 0 or (x == 0 and not allow_zero):
        raise RetargetError(f"{where}: must be {'>= 0' if allow_zero else '> 0'}, got {v!r}")
    return x

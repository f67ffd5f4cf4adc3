"""The robot registry: one place that turns ``--robot NAME|DIR|FILE`` into a robot's files.

A robot is one folder (its MJCF, ``profile.yaml``, ``hardware.yaml``, an optional README);
bundled ones live under ``firmware_cfg/robots/``. :func:`resolve` gives a :class:`Robot`;
a path never picks up a bundled robot's files. Standard library only (the MJCF is read as
XML, following ``<include>``). How a reference resolves: docs/robots.md.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import yaml

from firmware_cfg.errors import ConfigError

BUNDLED_DIR = Path(__file__).resolve().parent / "robots"
PROFILE_FILE = "profile.yaml"
HARDWARE_FILE = "hardware.yaml"
README_FILE = "README.md"

#: What ``robot init`` writes and ``robot check`` validates (the error messages point at them).
INIT_HINT = "dualflow-bridge robot init MODEL.xml -o DIR"


@dataclass(frozen=True)
class Robot:
    """A resolved robot. Paths are absolute; ``profile``/``hardware`` are None when absent."""

    name: str
    folder: Path
    mjcf: Path
    profile: Path | None
    hardware: Path | None
    bundled: bool

    @property
    def description(self) -> str:
        readme = self.folder / README_FILE
        if readme.is_file():
            for line in readme.read_text(errors="replace").splitlines():
                if line.startswith("#"):
                    return line.lstrip("#").strip()
        return f"robot model {self.mjcf.name}"

    @property
    def fixed_base(self) -> bool:
        """True when the model has no free joint (bolted to the world, e.g. a pedestal)."""
        return not mjcf_has_freejoint(self.mjcf)

    @property
    def joint_names(self) -> tuple[str, ...]:
        return joint_names(self)

    def require_profile(self) -> Path:
        if self.profile is None:
            raise ConfigError(
                f"robot {self.name} ({self.folder}): no retarget profile ({PROFILE_FILE}); write one with `{INIT_HINT}`"
            )
        return self.profile

    def require_hardware(self) -> Path:
        if self.hardware is None:
            raise ConfigError(
                f"robot {self.name} ({self.folder}): no hardware config ({HARDWARE_FILE}); "
                f"`{INIT_HINT}` writes a skeleton to fill in (servo IDs, directions, offsets)"
            )
        return self.hardware

    def __str__(self) -> str:  # what messages and telemetry headers call the robot
        if self.bundled:
            return self.name
        return str(self.folder if self.profile is not None else self.mjcf)


def bundled_names() -> tuple[str, ...]:
    """Names of the bundled robots (folders under ``firmware_cfg/robots/``)."""
    return tuple(sorted(p.name for p in BUNDLED_DIR.iterdir() if p.is_dir() and _folder_mjcf(p, quiet=True)))


def resolve(ref: str | Path | Robot) -> Robot:
    """The :class:`Robot` that ``ref`` (a bundled name, a folder, an MJCF or a hardware
    config) names. Raises ConfigError naming the reference and the fix."""
    if isinstance(ref, Robot):
        return ref
    text = str(ref).strip()
    if not text:
        raise ConfigError(
            f"--robot: empty; give a bundled robot name ({', '.join(bundled_names())}), a robot folder or an MJCF file"
        )
    path = Path(text).expanduser()
    looks_like_path = path.suffix != "" or "/" in text or "\\" in text or text.startswith(".")
    if not looks_like_path and (BUNDLED_DIR / text).is_dir():
        return _from_folder(BUNDLED_DIR / text, bundled=True)
    if path.is_dir():
        return _from_folder(path.resolve(), bundled=path.resolve().parent == BUNDLED_DIR)
    if path.is_file() and path.suffix.lower() == ".xml":
        return _from_mjcf(path.resolve())
    if path.is_file() and path.suffix.lower() in (".yaml", ".yml"):
        return _from_hardware(path.resolve())
    if path.exists():
        raise ConfigError(f"--robot {text}: not a robot folder, an MJCF (.xml) or a hardware config (.yaml)")
    if looks_like_path:
        raise ConfigError(f"--robot {text}: no such file or folder")
    raise ConfigError(
        f"--robot {text}: unknown robot; bundled robots are {', '.join(bundled_names())}, "
        f"or give a robot folder (`{INIT_HINT}` makes one from an MJCF)"
    )


def reference(robot: str | Path | Robot) -> str:
    """How to name ``robot`` again from any working directory (what trajectories, telemetry and
    the generator process carry): a bundled robot's name, else the absolute path given."""
    found = resolve(robot)
    if found.bundled:
        return found.name
    if isinstance(robot, Robot):
        return str(robot.folder if robot.profile is not None else robot.mjcf)
    return str(Path(str(robot)).expanduser().resolve())


def _folder_mjcf(folder: Path, quiet: bool = False) -> Path | None:
    own = folder / f"{folder.name}.xml"
    if own.is_file():
        return own
    prof = folder / PROFILE_FILE
    if prof.is_file():
        key = _yaml_key(prof, "mjcf")
        if key:
            p = (folder / str(key)).resolve()
            if not p.is_file():
                raise ConfigError(f"{prof}: field mjcf: {key} does not exist (relative to {folder})")
            return p
    xmls = sorted(p for p in folder.glob("*.xml") if _is_robot_mjcf(p))
    if len(xmls) == 1:
        return xmls[0]
    if quiet:
        return None
    if not xmls:
        raise ConfigError(
            f"robot folder {folder}: no MJCF (.xml) in it; put the model there or name it with "
            f"'mjcf: PATH' in {PROFILE_FILE} (`{INIT_HINT}` does both)"
        )
    raise ConfigError(
        f"robot folder {folder}: several MJCF files ({', '.join(p.name for p in xmls)}); "
        f"name the robot's model with 'mjcf: FILE' in {PROFILE_FILE}, or call it {folder.name}.xml"
    )


def _from_folder(folder: Path, bundled: bool) -> Robot:
    mjcf = _folder_mjcf(folder)
    assert mjcf is not None
    profile = folder / PROFILE_FILE
    hardware = folder / HARDWARE_FILE
    if profile.is_file() and hardware.is_file():  # both name the robot: they must name the same one
        p_name, h_name = _yaml_key(profile, "robot"), _yaml_key(hardware, "robot")
        if p_name and h_name and str(p_name) != str(h_name):
            raise ConfigError(
                f"{profile}: field robot: {p_name!r}, but {hardware.name} beside it is for robot "
                f"{h_name!r}; the profile belongs to another robot, put this robot's profile here"
            )
    return Robot(
        folder.name,
        folder,
        mjcf,
        profile if profile.is_file() else None,
        hardware if hardware.is_file() else None,
        bundled,
    )


def _from_mjcf(mjcf: Path) -> Robot:
    folder = mjcf.parent
    try:
        own = _folder_mjcf(folder, quiet=True)
    except ConfigError:
        own = None
    if own is not None and own.resolve() == mjcf and (folder / PROFILE_FILE).is_file():
        robot = _from_folder(folder, bundled=folder == BUNDLED_DIR / folder.name)
        return robot
    # A model on its own: no profile or hardware config is guessed for it.
    return Robot(mjcf.stem, folder, mjcf, None, None, bundled=False)


def _from_hardware(path: Path) -> Robot:
    mjcf_key = _yaml_key(path, "mjcf")
    if not mjcf_key:
        raise ConfigError(
            f"{path}: the hardware config needs an 'mjcf' key naming the robot model "
            f"(or put it in a robot folder: `{INIT_HINT}`)"
        )
    mjcf = (path.parent / str(mjcf_key)).resolve()
    if not mjcf.is_file():
        raise ConfigError(f"{path}: field mjcf: {mjcf_key} does not exist (relative to {path.parent})")
    name = str(_yaml_key(path, "robot") or mjcf.stem)
    profile = None
    for candidate in (path.parent / PROFILE_FILE, path.with_name(f"{name}.profile.yaml")):
        if candidate.is_file():
            profile = candidate
            break
    bundled = path.parent.parent == BUNDLED_DIR
    return Robot(name, path.parent, mjcf, profile, path, bundled)


def _yaml_key(path: Path, key: str):
    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise ConfigError(f"{path}: not readable YAML ({str(exc).splitlines()[0]})") from None
    except RecursionError:
        raise ConfigError(f"{path}: not readable YAML (nested too deeply)") from None
    return data.get(key) if isinstance(data, dict) else None


def _is_robot_mjcf(path: Path) -> bool:
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError):
        return False
    return root.tag == "mujoco"


# -- reading the MJCF without mujoco ------------------------------------------------------


@lru_cache(maxsize=64)
def _load_xml(path: Path, mtime: float) -> ET.Element:
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise ConfigError(f"robot model {path}: not valid XML ({exc})") from None
    except OSError as exc:
        raise ConfigError(f"robot model {path}: cannot read it ({exc.strerror})") from None
    _expand_includes(root, path.parent, depth=0)
    return root


def _expand_includes(node: ET.Element, base: Path, depth: int) -> None:
    if depth > 16:
        raise ConfigError(f"robot model in {base}: <include> nested more than 16 deep")
    for i, child in enumerate(list(node)):
        if child.tag == "include" and child.get("file"):
            inc = (base / child.get("file")).resolve()
            included = parse_mjcf(inc)
            node.remove(child)
            for k, sub in enumerate(list(included)):
                node.insert(i + k, sub)
        else:
            _expand_includes(child, base, depth + 1)


def parse_mjcf(path: str | Path) -> ET.Element:
    """The MJCF's root element with ``<include>`` files spliced in (cached per file version)."""
    path = Path(path).resolve()
    if not path.is_file():
        raise ConfigError(f"robot model {path}: file not found")
    return _load_xml(path, path.stat().st_mtime)


def mjcf_has_freejoint(path: str | Path) -> bool:
    root = parse_mjcf(path)
    return any(el.tag == "freejoint" or (el.tag == "joint" and el.get("type") == "free") for el in root.iter())


def joint_names(robot: str | Path | Robot) -> tuple[str, ...]:
    """The joint names of a robot reference (name, folder, MJCF, hardware config) in actuator
    order: the servo order of the bundled robots, and the order of trajectories."""
    path = resolve(robot).mjcf
    root = parse_mjcf(path)
    names = tuple(
        el.get("joint")
        for act in root.iter("actuator")
        for el in act
        if el.tag in ("position", "general", "motor", "velocity") and el.get("joint")
    )
    if not names:
        raise ConfigError(
            f"robot model {path}: no joint actuators found; each driven joint needs an actuator "
            "(<position joint=...>) in <actuator>"
        )
    return names


def joint_limits(robot: str | Path | Robot) -> dict[str, tuple[float, float] | None]:
    """(lower, upper) rad of each joint in actuator order from the MJCF's ranges; None for a
    joint the MJCF leaves unranged (its limits must come from the profile or hardware config)."""
    from firmware_cfg.config import mjcf_joint_ranges

    found = resolve(robot)
    ranges = mjcf_joint_ranges(found.mjcf)
    return {j: ranges.get(j) for j in joint_names(found)}


__all__ = [
    "BUNDLED_DIR",
    "Robot",
    "bundled_names",
    "resolve",
    "reference",
    "parse_mjcf",
    "joint_names",
    "joint_limits",
    "mjcf_has_freejoint",
    "PROFILE_FILE",
    "HARDWARE_FILE",
    "INIT_HINT",
]

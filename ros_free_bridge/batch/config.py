"""The settings of a ``retarget-check`` batch and where its clips' outputs go.

:class:`BatchConfig` decides every clip's row; :meth:`BatchConfig.settings` is what a resumed batch must match.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class BatchConfig:
    robot: str = "op3"
    out: Path = Path("out/retarget_check")
    fps: float = 30.0
    balance: bool = True
    auto_retime: bool = False
    #: offline: a clip that starts mid-motion is led in from the robot's standing stance
    #: (retarget.lead_in; the trajectory starts before the clip)
    lead_in: bool = True
    fixed_base: bool | None = None  #: None: the robot's own (fixed for upper-body robots)
    compile: bool = True
    #: "offline": the whole clip at once (retarget.offline); "streaming": frame by frame as the
    #: live bridge runs it (steps at the robot's pace, CoM, capture point and ZMP over its feet)
    retargeter: str = "offline"
    #: offline: "auto" (the step planner for a free-standing robot, the window optimisation for
    #: any other), "planner" or "ipopt" (retarget.offline.OfflineConfig.engine)
    offline_engine: str = "auto"
    #: film each clip (person and robot side by side, physics playback) into ``video.mp4``
    video: bool = True
    video_size: tuple[int, int] = (256, 192)  #: pixels per panel (width, height; multiples of 16 for the encoder)
    video_fps: float = 15.0

    def settings(self) -> dict:
        """What decides a clip's row (the robot by the content of its files): a batch resumes
        only with the same settings."""
        return {
            "robot": str(self.robot),
            "robot_files": robot_fingerprint(self.robot),
            "fps": self.fps,
            "balance": self.balance,
            "auto_retime": self.auto_retime,
            "lead_in": self.lead_in,
            "fixed_base": self.fixed_base,
            "retargeter": self.retargeter,
            "offline_engine": self.offline_engine if self.retargeter == "offline" else None,
        }


def robot_fingerprint(robot) -> str:
    """sha256 over the robot folder's files (names and contents): a changed model, profile or
    hardware config changes it. A reference the registry cannot resolve hashes to its text."""
    from firmware_cfg.errors import ConfigError
    from firmware_cfg.registry import resolve

    try:
        folder = resolve(robot).folder
    except ConfigError:
        return hashlib.sha256(str(robot).encode()).hexdigest()
    h = hashlib.sha256()
    for f in sorted(p for p in folder.rglob("*") if p.is_file() and "__pycache__" not in p.parts):
        h.update(f.relative_to(folder).as_posix().encode() + b"\0")
        h.update(hashlib.sha256(f.read_bytes()).digest())
    return h.hexdigest()


def clip_dir(cfg: BatchConfig, name: str) -> Path:
    """Where a clip's outputs live: ``OUT/clips/<name>/`` (a folder of its own, which a re-run
    of the clip empties: so the name must stay below ``clips/``)."""
    parts = Path(name).parts
    if not parts or Path(name).is_absolute() or any(p in ("..", ".") for p in parts):
        from ros_free_bridge.errors import BridgeError

        raise BridgeError(f"clip name {name!r}: must be a relative path inside the folder (no '..')")
    return Path(cfg.out) / "clips" / name

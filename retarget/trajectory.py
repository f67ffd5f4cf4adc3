"""The robot trajectory: what retargeting produces and simulation and the bridge consume.

Shapes and units:
- ``root_pos`` (T, 3) metres, world frame (Z up, ground z = 0);
- ``root_quat`` (T, 4) unit quaternion w, x, y, z (MuJoCo's order), world frame;
- ``joint_pos`` (T, n) radians, columns in the order of ``joint_names`` (the
  robot's MJCF hinge joints);
- ``fps`` frames per second.

For a fixed-base robot the root pose is still stored (it is the base's pose).
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from retarget.errors import RetargetError

#: Frame rates a trajectory file may have (frames/s): a motion clip at 1 fps to a control loop's
#: telemetry at 1 kHz.
FPS_RANGE = (1.0, 1000.0)
#: Fewest frames a trajectory file must hold (one frame is a pose, not a motion to judge or play).
MIN_FRAMES = 2
#: Largest joint angle (rad) and root coordinate (m) a trajectory file may hold.
MAX_JOINT_RAD = 1e3
MAX_ROOT_M = 1e4


@dataclass(frozen=True)
class RobotTrajectory:
    joint_names: tuple[str, ...]
    joint_pos: np.ndarray
    root_pos: np.ndarray
    root_quat: np.ndarray
    fps: float
    robot: str = ""
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        names = tuple(str(n) for n in self.joint_names)
        if len(set(names)) != len(names):
            raise RetargetError(f"trajectory: joint_names has duplicates: {names}")
        q = np.asarray(self.joint_pos, dtype=np.float64)
        if q.ndim == 1 and len(names) > 0:
            q = q[:, None] if len(names) == 1 else q
        if q.ndim != 2 or q.shape[1] != len(names):
            raise RetargetError(
                f"trajectory: joint_pos must have shape (T, {len(names)}) to match joint_names, got {tuple(q.shape)}"
            )
        t = q.shape[0]
        if t < 1:
            raise RetargetError("trajectory: it has zero frames; give at least one")
        pos = np.asarray(self.root_pos, dtype=np.float64)
        quat = np.asarray(self.root_quat, dtype=np.float64)
        if pos.shape != (t, 3):
            raise RetargetError(f"trajectory: root_pos must have shape ({t}, 3), got {tuple(pos.shape)}")
        if quat.shape != (t, 4):
            raise RetargetError(f"trajectory: root_quat must have shape ({t}, 4) (w, x, y, z), got {tuple(quat.shape)}")
        for label, arr in (("joint_pos", q), ("root_pos", pos), ("root_quat", quat)):
            if not np.all(np.isfinite(arr)):
                frame = int(np.argwhere(~np.isfinite(arr))[0][0])
                raise RetargetError(f"trajectory: {label} has NaN or inf at frame {frame}; fix the source motion")
        norms = np.linalg.norm(quat, axis=1)
        if np.any(np.abs(norms - 1.0) > 1e-3):
            frame = int(np.argmax(np.abs(norms - 1.0)))
            raise RetargetError(
                f"trajectory: root_quat is not a unit quaternion at frame {frame} (norm {norms[frame]:.4f})"
            )
        try:
            fps = float(self.fps)
        except (TypeError, ValueError):
            raise RetargetError(f"trajectory: fps must be a number, got {self.fps!r}") from None
        if not np.isfinite(fps) or fps <= 0:
            raise RetargetError(f"trajectory: fps must be > 0, got {self.fps!r}")
        quat = quat / norms[:, None]
        for arr in (q, pos, quat):
            arr.setflags(write=False)
        object.__setattr__(self, "joint_names", names)
        object.__setattr__(self, "joint_pos", q)
        object.__setattr__(self, "root_pos", pos)
        object.__setattr__(self, "root_quat", quat)
        object.__setattr__(self, "fps", fps)

    @property
    def n_frames(self) -> int:
        return int(self.joint_pos.shape[0])

    def __len__(self) -> int:
        return self.n_frames

    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    @property
    def duration(self) -> float:
        return (self.n_frames - 1) / self.fps

    @property
    def times(self) -> np.ndarray:
        return np.arange(self.n_frames) / self.fps

    @classmethod
    def standing(
        cls, joint_names, pose, n_frames: int, fps: float, root_pos=(0.0, 0.0, 0.0), robot: str = ""
    ) -> RobotTrajectory:
        """A constant trajectory holding ``pose`` (n,) for ``n_frames`` frames."""
        q = np.tile(np.asarray(pose, dtype=np.float64), (n_frames, 1))
        return cls(
            tuple(joint_names),
            q,
            np.tile(np.asarray(root_pos, float), (n_frames, 1)),
            np.tile([1.0, 0.0, 0.0, 0.0], (n_frames, 1)),
            fps,
            robot,
        )

    # -- files ------------------------------------------------------------
    def save_npz(self, path) -> Path:
        """Write an npz (no pickle: names and meta are stored as JSON text)."""
        path = Path(path)
        tmp = path.with_name(path.name + ".partial.npz")
        np.savez(
            tmp,
            joint_pos=self.joint_pos,
            root_pos=self.root_pos,
            root_quat=self.root_quat,
            fps=np.float64(self.fps),
            header=np.array(
                json.dumps({"joint_names": list(self.joint_names), "robot": self.robot, "meta": self.meta})
            ),
        )
        tmp.replace(path)
        return path

    @classmethod
    def load_npz(cls, path) -> RobotTrajectory:
        """Read a file written by :meth:`save_npz`. Anything that cannot be a robot trajectory
        raises RetargetError naming the file and the field: a damaged archive, a missing
        field, array headers declaring absurd sizes (checked before allocating), non-float
        joint or root arrays, fewer than :data:`MIN_FRAMES` frames, an fps outside
        :data:`FPS_RANGE`, values beyond :data:`MAX_JOINT_RAD` / :data:`MAX_ROOT_M`."""
        from dualflow.motion.io.npfile import open_npz, scalar, text

        path = Path(path)
        fix = "expected arrays joint_pos, root_pos, root_quat, fps and header (RobotTrajectory.save_npz)"
        with open_npz(path, error=RetargetError) as data:
            where = f"{path}, field 'header'"
            try:
                header = json.loads(text(data.get("header", fix), where, RetargetError))
            except (ValueError, RecursionError) as exc:
                if isinstance(exc, RetargetError):
                    raise
                raise RetargetError(f"{where}: not valid JSON ({str(exc)[:100]}); re-save the trajectory") from None
            if not isinstance(header, dict):
                raise RetargetError(f"{where}: must be a JSON object with joint_names, got {type(header).__name__}")
            names = header.get("joint_names")
            if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
                raise RetargetError(f"{where}: joint_names must be a list of joint names (text), got {names!r:.80}")
            meta = header.get("meta", {})
            if not isinstance(meta, dict):
                raise RetargetError(f"{where}: meta must be a JSON object, got {type(meta).__name__}")
            arrays = {}
            for key in ("joint_pos", "root_pos", "root_quat"):
                arr = data.get(key, fix)
                if arr.dtype.kind != "f":
                    raise RetargetError(
                        f"{path}, field {key!r}: expected floating-point numbers, got dtype {arr.dtype}; "
                        "re-save the trajectory"
                    )
                arrays[key] = arr
            fps = scalar(data.get("fps", fix), f"{path}, field 'fps'", RetargetError)
        lo, hi = FPS_RANGE
        if not lo <= fps <= hi:
            raise RetargetError(
                f"{path}, field 'fps': fps must be > 0, within {lo:g}-{hi:g} frames/s, got {fps!r}; the file is damaged"
            )
        q = arrays["joint_pos"]
        if q.ndim != 2 or q.shape[0] < MIN_FRAMES:
            raise RetargetError(
                f"{path}, field 'joint_pos': a trajectory needs at least {MIN_FRAMES} frames as (T, n) "
                f"joint angles, got shape {q.shape}"
            )
        for key, bound, unit in (("joint_pos", MAX_JOINT_RAD, "rad"), ("root_pos", MAX_ROOT_M, "m")):
            arr = arrays[key]
            with np.errstate(invalid="ignore"):
                big = np.abs(arr) > bound
            if big.any():
                frame = int(np.argwhere(big)[0][0])
                raise RetargetError(
                    f"{path}, field {key!r}: {np.nanmax(np.abs(arr)):.3g} {unit} at frame {frame}, beyond "
                    f"±{bound:g} {unit}; the file is damaged"
                )
        robot = header.get("robot", "")
        try:
            return cls(
                tuple(names),
                q,
                arrays["root_pos"],
                arrays["root_quat"],
                fps,
                robot if isinstance(robot, str) else "",
                meta,
            )
        except RetargetError as exc:
            raise RetargetError(f"{path}: {exc}") from None

    def save_csv(self, path) -> Path:
        """One row per frame: time, root x y z, root qw qx qy qz, then each joint in radians."""
        path = Path(path)
        tmp = path.with_name(path.name + ".partial")
        with open(tmp, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(
                ["time_s", "root_x", "root_y", "root_z", "root_qw", "root_qx", "root_qy", "root_qz", *self.joint_names]
            )
            for i in range(self.n_frames):
                w.writerow(
                    [
                        f"{i / self.fps:.6f}",
                        *(f"{v:.6f}" for v in self.root_pos[i]),
                        *(f"{v:.6f}" for v in self.root_quat[i]),
                        *(f"{v:.6f}" for v in self.joint_pos[i]),
                    ]
                )
        tmp.replace(path)
        return path

"""The retarget report of one clip: how well, how smooth, how safe. JSON, markdown and a figure.

Definitions (all at robot scale, i.e. against the scaled targets of :mod:`retarget.targets`):

- keypoint error (mm): ‖p_k(x_t) − target_kt‖ over frames and keypoints (mean, max);
- foot skate: over frames t where a foot is in contact at t − 1 and t (the robot's contact
  schedule, ``meta["contacts"]``, when the retargeter planned one; else the person's), the horizontal
  displacement of its sole centre; ``skate_share`` is the share of those frames sliding more
  than 5 mm in one frame, ``worst_slide_mm`` the largest slide;
- ground penetration (mm): the deepest sole corner below z = 0 over the clip (0 if none);
- limit violations: (frame, joint) pairs outside the joint range (profile ∩ MJCF) by more
  than 1e-9 rad; velocity violations: frame steps with |Δq|·fps above the profile's speed
  limit by more than 1e-6 relative. Both must be 0;
- jerk: mean absolute third difference of position, |Δ³p|·fps³ (m/s³), over every keypoint
  coordinate. The robot's is taken on its forward-kinematics keypoints, the source's on the
  scaled targets, so both are the same quantity at the same scale and ``jerk_ratio`` =
  robot / source (≤ 1 means the robot moves no less smoothly than the person). For a
  motionless source (jerk 0) the ratio is undefined: ``None`` (JSON null, 'n/a' in the
  markdown), never NaN. The mean absolute joint jerk |Δ³q|·fps³ (rad/s³) is reported too;
- self-collisions: (frame, capsule pair) with the capsules overlapping (distance of their
  axes below the sum of radii, no margin);
- first failure (s): for a clip that fails (see ``passed``), the earliest moment of a failing
  criterion: a joint or velocity limit exceeded, a sole more than 5 mm below the ground, a
  foot sliding more than 5 mm in a frame (when skate fails); ``None`` when the clip passes.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from retarget.kinematics import mat_to_euler, quat_to_mat
from retarget.targets import Targets
from retarget.trajectory import RobotTrajectory

SKATE_MM_PER_FRAME = 5.0
#: A clip passes with skate in under this share of its contact frames ...
SKATE_SHARE = 0.02
#: ... and no sole deeper than this below the ground (mm).
PENETRATION_MM = 5.0


@dataclass(frozen=True)
class RetargetReport:
    clip: str
    robot: str
    mode: str
    frames: int
    fps: float
    keypoint_error_mean_mm: float
    keypoint_error_max_mm: float
    contact_frames: int
    skate_share: float
    worst_slide_mm: float
    penetration_mm: float
    limit_violations: int
    velocity_violations: int
    jerk_robot: float
    jerk_source: float
    jerk_ratio: float | None  # None when the source does not move (0/0)
    joint_jerk_mean: float
    self_collisions: int
    solver: dict
    first_failure_s: float | None = None
    #: parts the robot plays differently from the person (the contact schedule's changes,
    #: retarget.schedule): dicts start_s, end_s, what, why, keypoint_error_mm (mean over them)
    changes: tuple = ()
    #: touch-downs of the person's feet and of the robot's planned contacts (None: no schedule)
    steps: dict | None = None

    @property
    def passed(self) -> bool:
        """0 limit and velocity violations, skate in < 2 % of contact frames, penetration ≤ 5 mm."""
        return (self.limit_violations == 0 and self.velocity_violations == 0 and self.skate_share < SKATE_SHARE
                and self.penetration_mm <= PENETRATION_MM)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["passed"] = self.passed
        return d

    def to_markdown(self) -> str:
        rows = [
            ("keypoint error mean / max", f"{self.keypoint_error_mean_mm:.1f} / {self.keypoint_error_max_mm:.1f} mm"),
            ("foot skate (> 5 mm/frame)", f"{100 * self.skate_share:.2f} % of {self.contact_frames} contact frames"),
            ("worst slide", f"{self.worst_slide_mm:.2f} mm/frame"),
            ("ground penetration", f"{self.penetration_mm:.2f} mm"),
            ("joint-limit violations", str(self.limit_violations)),
            ("velocity-limit violations", str(self.velocity_violations)),
            ("keypoint jerk robot / source", f"{self.jerk_robot:.2f} / {self.jerk_source:.2f} m/s³ (ratio {_ratio_text(self.jerk_ratio)})"),
            ("mean abs joint jerk", f"{self.joint_jerk_mean:.1f} rad/s³"),
            ("self-collisions", str(self.self_collisions)),
        ]
        lines = [f"# Retarget report: {self.clip} → {self.robot}", "",
                 f"{self.frames} frames at {self.fps:g} fps, mode {self.mode}; "
                 f"{'PASS' if self.passed else 'FAIL'}"
                 + ("" if self.first_failure_s is None else f", first failure at {self.first_failure_s:g} s"),
                 "", "| figure | value |", "|---|---|"]
        if self.steps is not None:
            lines += [f"| steps robot / person | {self.steps.get('robot')} / {self.steps.get('person')} |"]
        lines += [f"| {a} | {b} |" for a, b in rows]
        if self.changes:
            lines += ["", "## What the robot does differently", "", "| seconds | what | why | keypoint error there |",
                      "|---|---|---|---|"]
            lines += [f"| {c['start_s']:.2f}-{c['end_s']:.2f} | {c['what']} | {c['why']} | "
                      f"{c.get('keypoint_error_mm', float('nan')):.1f} mm |" for c in self.changes]
        return "\n".join(lines) + "\n"

    def changes_text(self) -> str:
        """One line for a table: each change as 'what start-end s (error mm)', or ''."""
        return "; ".join(f"{c['what']} {c['start_s']:.2f}-{c['end_s']:.2f} s ({c.get('keypoint_error_mm', 0):.0f} mm)"
                         for c in self.changes)

    def save(self, out_dir, stem: str) -> dict[str, Path]:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        paths = {"json": out / f"{stem}.report.json", "md": out / f"{stem}.report.md"}
        _atomic_text(paths["json"], json.dumps(self.to_dict(), indent=2, default=_jsonable))
        _atomic_text(paths["md"], self.to_markdown())
        return paths


def _ratio_text(r: float | None) -> str:
    return "n/a" if r is None else f"{r:.2f}"


def jerk_ratio(robot_jerk: float, source_jerk: float) -> float | None:
    """robot / source jerk, or None when the source's is 0 (a motionless clip: 0/0 is undefined)."""
    return float(robot_jerk / source_jerk) if source_jerk > 0 else None


def _jsonable(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def _atomic_text(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".partial")
    tmp.write_text(text)
    os.replace(tmp, path)


def configurations(robot, traj: RobotTrajectory) -> np.ndarray:
    """RobotTrajectory → configuration vectors X (T, nx) of ``robot``."""
    if list(traj.joint_names) != list(robot.joint_names):
        from retarget.errors import RetargetError

        raise RetargetError(f"trajectory joints {traj.joint_names} do not match robot {robot.name}'s {robot.joint_names}")
    if not robot.floating:
        return np.array(traj.joint_pos)
    Rs = np.stack([quat_to_mat(q) for q in traj.root_quat])
    return np.hstack([traj.root_pos, mat_to_euler(Rs), traj.joint_pos])


def robot_schedule(traj: RobotTrajectory, person: np.ndarray) -> np.ndarray:
    """The robot's side contacts (T, 2) bool: the schedule the retargeter planned
    (``traj.meta["contacts"]``, :mod:`retarget.schedule`) when it has one of the right shape,
    else the person's ``person`` (T, 2)."""
    planned = traj.meta.get("contacts")
    if planned is not None:
        planned = np.asarray(planned, dtype=bool)
        if planned.shape == np.shape(person):
            return planned
    return np.asarray(person, dtype=bool)


def _jerk(p: np.ndarray, fps: float) -> float:
    if p.shape[0] < 4:
        return 0.0
    return float(np.mean(np.abs(np.diff(p, n=3, axis=0))) * fps ** 3)


def evaluate(robot, traj: RobotTrajectory, targets: Targets, clip: str = "") -> RetargetReport:
    """Measure a trajectory against its targets (see the module docstring)."""
    X = configurations(robot, traj)
    ev = robot.evaluate(X)
    T, fps = X.shape[0], traj.fps
    err = 1000 * np.linalg.norm(ev["keypoints"] - targets.keypoints, axis=-1)
    contact_frames, slides, slide_frames = 0, [], []
    on = robot_schedule(traj, targets.contacts)
    if robot.has_feet and robot.floating:
        for side in range(2):
            centre = ev["sole"][:, 4 * side:4 * side + 4, 0:2].mean(axis=1)
            both = on[1:, side] & on[:-1, side]
            step = 1000 * np.linalg.norm(np.diff(centre, axis=0), axis=-1)
            slides.append(step[both])
            slide_frames.append(1 + np.flatnonzero(both))
            contact_frames += int(both.sum())
    slides = np.concatenate(slides) if slides else np.zeros(0)
    slide_frames = np.concatenate(slide_frames) if slide_frames else np.zeros(0, int)
    skate_share = float(np.mean(slides > SKATE_MM_PER_FRAME)) if slides.size else 0.0
    sole_z = ev["sole"][..., 2]
    penetration = float(max(0.0, -sole_z.min()) * 1000) if sole_z.size else 0.0
    q = traj.joint_pos
    lo, hi = robot.x_lower[robot.n_root:], robot.x_upper[robot.n_root:]
    beyond = (q < lo - 1e-9) | (q > hi + 1e-9)
    limit_v = int(np.sum(beyond))
    too_fast = np.abs(np.diff(q, axis=0)) * fps > robot.velocity_limits * (1 + 1e-6)
    vel_v = int(np.sum(too_fast))
    failing = [np.flatnonzero(beyond.any(axis=1)), 1 + np.flatnonzero(too_fast.any(axis=1))]
    if penetration > PENETRATION_MM:
        failing.append(np.flatnonzero((sole_z < -PENETRATION_MM / 1000).reshape(T, -1).any(axis=1)))
    if skate_share >= SKATE_SHARE:
        failing.append(slide_frames[slides > SKATE_MM_PER_FRAME])
    failing = np.concatenate(failing)
    first_failure = round(float(failing.min()) / fps, 3) if failing.size else None
    coll = 0
    if robot.collision_pairs:
        # overlap without the profile's margin: d² − (r_a + r_b + m)² < (r_a + r_b)² − (r_a + r_b + m)²
        m = robot.profile.collision_margin
        radii = np.array([robot.capsules[a].radius + robot.capsules[b].radius for a, b in robot.collision_pairs])
        thresh = radii ** 2 - (radii + m) ** 2
        coll = int(np.sum(ev["collision"] < thresh[None] - 1e-9))
    jr, js = _jerk(ev["keypoints"], fps), _jerk(targets.keypoints, fps)
    meta = dict(traj.meta)
    changes = []
    for c in meta.get("changes", []) or []:
        a, b = int(round(c["start_s"] * fps)), int(round(c["end_s"] * fps))
        a, b = min(max(a, 0), T - 1), min(max(b, a + 1), T)
        changes.append({**c, "keypoint_error_mm": float(err[a:b].mean())})
    return RetargetReport(
        clip=clip or str(meta.get("source", "")), robot=robot.name, mode=str(meta.get("mode", "")), frames=T, fps=fps,
        keypoint_error_mean_mm=float(err.mean()), keypoint_error_max_mm=float(err.max()),
        contact_frames=contact_frames, skate_share=skate_share,
        worst_slide_mm=float(slides.max()) if slides.size else 0.0, penetration_mm=penetration,
        limit_violations=limit_v, velocity_violations=vel_v, jerk_robot=jr, jerk_source=js,
        jerk_ratio=jerk_ratio(jr, js), joint_jerk_mean=_jerk(q, fps),
        self_collisions=coll, solver={k: v for k, v in meta.items() if k not in ("source", "contacts", "changes", "steps")},
        first_failure_s=first_failure, changes=tuple(changes), steps=meta.get("steps"),
    )


def plot_joints(robot, traj: RobotTrajectory, path) -> Path:
    """One panel per joint: its angle over time (rad) against its lower and upper limit."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = traj.n_joints
    cols = 4
    rows = int(np.ceil(n / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 1.9 * rows), sharex=True, squeeze=False)
    t = traj.times
    lo, hi = robot.x_lower[robot.n_root:], robot.x_upper[robot.n_root:]
    for j in range(rows * cols):
        ax = axes[j // cols][j % cols]
        if j >= n:
            ax.axis("off")
            continue
        ax.plot(t, traj.joint_pos[:, j], lw=1.0, color="tab:blue")
        ax.axhline(lo[j], color="tab:red", lw=0.8, ls="--")
        ax.axhline(hi[j], color="tab:red", lw=0.8, ls="--")
        ax.set_title(traj.joint_names[j], fontsize=8)
        ax.tick_params(labelsize=6)
    fig.suptitle(f"{traj.robot}: joint angles (rad) and limits (dashed)", fontsize=9)
    fig.supxlabel("time (s)", fontsize=8)
    fig.tight_layout()
    path = Path(path)
    tmp = path.with_name(path.stem + ".partial" + path.suffix)
    fig.savefig(tmp, dpi=90)
    plt.close(fig)
    os.replace(tmp, path)
    return path

"""The retarget report of one clip: how well, how smooth, how safe. JSON, markdown and a figure.

Contract: :func:`evaluate` measures a :class:`retarget.trajectory.RobotTrajectory` against the
robot-scale :class:`retarget.targets.Targets` it was made from and returns a
:class:`RetargetReport` (keypoint error mm, foot skate, ground penetration mm, limit and speed
violations, jerk ratio, self-collisions, the first failing moment, what the robot does
differently); ``passed`` is the verdict. The definitions and thresholds of each figure:
docs/retargeting.md, section 7.
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
    #: the lead-in before the clip (retarget.lead_in.LeadIn.to_dict: frames, t0_s, ease_s, ...), None: none
    lead_in: dict | None = None
    #: mean keypoint error (mm) over the clip's frames outside every change: how closely the robot
    #: follows the person where it means to (None: no such frame)
    keypoint_error_followed_mm: float | None = None

    @property
    def passed(self) -> bool:
        """0 limit and velocity violations, skate in < 2 % of contact frames, penetration ≤ 5 mm."""
        return (
            self.limit_violations == 0
            and self.velocity_violations == 0
            and self.skate_share < SKATE_SHARE
            and self.penetration_mm <= PENETRATION_MM
        )

    def to_dict(self) -> dict:
        d = asdict(self)
        d["passed"] = self.passed
        return d

    def to_markdown(self) -> str:
        rows = [
            ("keypoint error mean / max", f"{self.keypoint_error_mean_mm:.1f} / {self.keypoint_error_max_mm:.1f} mm"),
            (
                "keypoint error where it follows the person (outside the changes)",
                "n/a" if self.keypoint_error_followed_mm is None else f"{self.keypoint_error_followed_mm:.1f} mm",
            ),
            ("foot skate (> 5 mm/frame)", f"{100 * self.skate_share:.2f} % of {self.contact_frames} contact frames"),
            ("worst slide", f"{self.worst_slide_mm:.2f} mm/frame"),
            ("ground penetration", f"{self.penetration_mm:.2f} mm"),
            ("joint-limit violations", str(self.limit_violations)),
            ("velocity-limit violations", str(self.velocity_violations)),
            (
                "keypoint jerk robot / source",
                f"{self.jerk_robot:.2f} / {self.jerk_source:.2f} m/s³ (ratio {_ratio_text(self.jerk_ratio)})",
            ),
            ("mean abs joint jerk", f"{self.joint_jerk_mean:.1f} rad/s³"),
            ("self-collisions", str(self.self_collisions)),
        ]
        lines = [
            f"# Retarget report: {self.clip} → {self.robot}",
            "",
            f"{self.frames} frames at {self.fps:g} fps, mode {self.mode}; "
            f"{'PASS' if self.passed else 'FAIL'}"
            + ("" if self.first_failure_s is None else f", first failure at {self.first_failure_s:g} s"),
            "",
            "| figure | value |",
            "|---|---|",
        ]
        if self.lead_in is not None:
            li = self.lead_in
            lines += [
                f"| lead-in before the clip | {li['t0_s']:.2f} s ({li['frames']} frames), eased in over "
                f"{li['ease_s']:.2f} s |"
            ]
        if self.steps is not None:
            lines += [f"| steps robot / person | {self.steps.get('robot')} / {self.steps.get('person')} |"]
        lines += [f"| {a} | {b} |" for a, b in rows]
        if self.changes:
            lines += [
                "",
                "## What the robot does differently",
                "",
                "| seconds | what | why | keypoint error there |",
                "|---|---|---|---|",
            ]
            lines += [
                f"| {c['start_s']:.2f}-{c['end_s']:.2f} | {c['what']} | {c['why']} | "
                + (f"{c['keypoint_error_mm']:.1f} mm |" if c.get("keypoint_error_mm") is not None else "n/a |")
                for c in self.changes
            ]
        return "\n".join(lines) + "\n"

    def changes_text(self) -> str:
        """One line for a table: each change as 'what start-end s (error mm)', or ''."""
        return "; ".join(
            f"{c['what']} {c['start_s']:.2f}-{c['end_s']:.2f} s ({c.get('keypoint_error_mm', 0):.0f} mm)"
            for c in self.changes
        )

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

        raise RetargetError(
            f"trajectory joints {traj.joint_names} do not match robot {robot.name}'s {robot.joint_names}"
        )
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
    return float(np.mean(np.abs(np.diff(p, n=3, axis=0))) * fps**3)


def evaluate(robot, traj: RobotTrajectory, targets: Targets, clip: str = "") -> RetargetReport:
    """Measure a trajectory against its targets (see the module docstring). A trajectory that
    starts with a lead-in (``meta["lead_in"]``, :mod:`retarget.lead_in`) is measured against
    the clip's ``targets`` from the clip's first frame on (tracking, jerk) and as a whole
    (limits, skate, penetration, collisions: the robot does the lead-in too); times are clip
    times (negative in the lead-in)."""
    clip_name = clip
    X = configurations(robot, traj)
    ev = robot.evaluate(X)
    T, fps = X.shape[0], traj.fps
    tk, person, clip_t = clip_targets(traj, targets)
    clip = clip_t >= -1e-9  # frames of the clip (after a lead-in)
    err = 1000 * np.linalg.norm(ev["keypoints"] - tk, axis=-1)  # NaN in a lead-in: no person there
    slides, slide_frames, contact_frames = _foot_slides(robot, ev, robot_schedule(traj, person))
    skate_share = float(np.mean(slides > SKATE_MM_PER_FRAME)) if slides.size else 0.0
    sole_z = ev["sole"][..., 2]
    penetration = float(max(0.0, -sole_z.min()) * 1000) if sole_z.size else 0.0
    q = traj.joint_pos
    lo, hi = robot.x_lower[robot.n_root :], robot.x_upper[robot.n_root :]
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
    first_failure = round(float(clip_t[int(failing.min())]), 3) if failing.size else None
    coll = _self_collisions(robot, ev)
    jr, js = _jerk(ev["keypoints"][clip], fps), _jerk(targets.keypoints, fps)
    meta = dict(traj.meta)
    changes = _change_errors(meta.get("changes", []) or [], clip_t, clip, err)
    followed = clip & ~_inside_changes(changes, clip_t)
    return RetargetReport(
        clip=clip_name or str(meta.get("source", "")),
        robot=robot.name,
        mode=str(meta.get("mode", "")),
        frames=T,
        fps=fps,
        keypoint_error_mean_mm=float(err[clip].mean()),
        keypoint_error_max_mm=float(err[clip].max()),
        contact_frames=contact_frames,
        skate_share=skate_share,
        worst_slide_mm=float(slides.max()) if slides.size else 0.0,
        penetration_mm=penetration,
        limit_violations=limit_v,
        velocity_violations=vel_v,
        jerk_robot=jr,
        jerk_source=js,
        jerk_ratio=jerk_ratio(jr, js),
        joint_jerk_mean=_jerk(q, fps),
        self_collisions=coll,
        solver={
            k: v for k, v in meta.items() if k not in ("source", "contacts", "changes", "steps", "lead_in", "t0_s")
        },
        first_failure_s=first_failure,
        changes=tuple(changes),
        steps=meta.get("steps"),
        lead_in=meta.get("lead_in"),
        keypoint_error_followed_mm=float(err[followed].mean()) if followed.any() else None,
    )


def _foot_slides(robot, ev: dict, on: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """(slides (N,) mm, their frames (N,), contact frames): how far each foot's sole centre
    moved between two frames both in contact (``on`` (T, 2)); empty for a robot without feet
    or a fixed base."""
    contact_frames, slides, slide_frames = 0, [], []
    if robot.has_feet and robot.floating:
        for side in range(2):
            centre = ev["sole"][:, 4 * side : 4 * side + 4, 0:2].mean(axis=1)
            both = on[1:, side] & on[:-1, side]
            step = 1000 * np.linalg.norm(np.diff(centre, axis=0), axis=-1)
            slides.append(step[both])
            slide_frames.append(1 + np.flatnonzero(both))
            contact_frames += int(both.sum())
    slides = np.concatenate(slides) if slides else np.zeros(0)
    slide_frames = np.concatenate(slide_frames) if slide_frames else np.zeros(0, int)
    return slides, slide_frames, contact_frames


def _self_collisions(robot, ev: dict) -> int:
    """Frame-pair count of the robot's capsules overlapping (the profile's margin not counted)."""
    if not robot.collision_pairs:
        return 0
    # overlap without the profile's margin: d² − (r_a + r_b + m)² < (r_a + r_b)² − (r_a + r_b + m)²
    m = robot.profile.collision_margin
    radii = np.array([robot.capsules[a].radius + robot.capsules[b].radius for a, b in robot.collision_pairs])
    thresh = radii**2 - (radii + m) ** 2
    return int(np.sum(ev["collision"] < thresh[None] - 1e-9))


def _inside_changes(changes: list, clip_t: np.ndarray) -> np.ndarray:
    """(T,) bool: frames inside any change (start_s <= t < end_s, clip times)."""
    inside = np.zeros(len(clip_t), dtype=bool)
    for c in changes:
        inside |= (clip_t >= c["start_s"] - 1e-9) & (clip_t < c["end_s"] - 1e-9)
    return inside


def _change_errors(changes: list, clip_t: np.ndarray, clip: np.ndarray, err: np.ndarray) -> list[dict]:
    """Each change (a part the robot plays differently, :meth:`retarget.schedule.Change.to_dict`)
    with the mean keypoint error (mm) over its clip frames (shorter than a frame: the nearest)."""
    out = []
    for c in changes:
        there = (clip_t >= c["start_s"] - 1e-9) & (clip_t < c["end_s"] - 1e-9) & clip
        if not there.any() and c["start_s"] >= 0:  # shorter than a frame: the nearest one
            there[int(np.argmin(np.abs(clip_t - c["start_s"])))] = True
        out.append({**c, "keypoint_error_mm": float(err[there].mean())} if there.any() else dict(c))
    return out


def clip_targets(traj: RobotTrajectory, targets: Targets) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per trajectory frame: the targets (T, K, 3), the person's side contacts (T, 2) and the clip
    time (T,) s. Without a lead-in these are the clip's own. After a lead-in
    (:func:`retarget.lead_in.lead_in_of`) each frame's clip time is the lead-in's (negative
    before the clip, warped in the ease-in); targets are the clip's interpolated there, NaN in
    the lead-in, and the person's feet are down in the lead-in."""
    from retarget.lead_in import lead_in_of

    T, fps = traj.n_frames, traj.fps
    lead = lead_in_of(traj)
    if lead is None:
        return targets.keypoints, targets.contacts, np.arange(T) / fps
    t = lead.clip_time(traj.times)
    n = targets.keypoints.shape[0]
    f = np.clip(t * targets.fps, 0.0, n - 1)
    i = np.minimum(np.floor(f).astype(int), n - 1)
    j = np.minimum(i + 1, n - 1)
    a = (f - i)[:, None, None]
    tk = (1 - a) * targets.keypoints[i] + a * targets.keypoints[j]
    tk[t < -1e-9] = np.nan
    person = np.asarray(targets.contacts, dtype=bool)[np.where(a[:, 0, 0] > 0.5, j, i)]
    person[t < -1e-9] = True
    return tk, person, t


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
    lo, hi = robot.x_lower[robot.n_root :], robot.x_upper[robot.n_root :]
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

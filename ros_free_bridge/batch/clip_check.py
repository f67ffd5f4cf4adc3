"""One clip of a ``retarget-check`` batch: load, retarget, physics check and film it.

:func:`check_clip` never raises: a failure is a ``fail`` row, anything unexpected an ``error`` row
with its traceback beside the clip's outputs. The engines look it up here at call time.
"""

from __future__ import annotations

import shutil
import traceback
from dataclasses import dataclass
from pathlib import Path

from ros_free_bridge.batch.config import BatchConfig, clip_dir
from ros_free_bridge.batch.results import ClipResult

VIDEO = "video.mp4"

_ROBOT = {}
_CHECK: dict = {}  #: (robot, fixed) -> sim.check.CheckConfig, per worker process


@dataclass(frozen=True)
class _Scene:
    """What the physics check and the video of one clip share."""

    robot: object  #: retarget.robot.RetargetRobot
    fixed: bool  #: the robot's root is bolted at its first pose
    traj: object  #: retarget.RobotTrajectory, as retargeted (re-timed, if it was)
    src: object  #: dualflow Motion: the person the robot plays, as it played them (slowed alike)
    partner: object = None  #: a pair's actor (slowed alike), or None
    placement: object = None  #: sim.human_figure.Placement of the capture's people (a pair only)
    check_config: object = None  #: sim.check.CheckConfig both play the trajectory with (_check_config)


def _check_config(robot: str, fixed: bool):
    """The physics check's config: the bridge's safety filter for ``robot`` (its hardware config
    read once per worker process and robot)."""
    key = (robot, fixed)
    if key not in _CHECK:
        from ros_free_bridge.robots import bridge_check_config

        _CHECK[key] = bridge_check_config(robot, mode="fixed" if fixed else "free")
    return _CHECK[key]


def _robot(cfg: BatchConfig):
    """The retarget robot and the retargeter, built once per worker process."""
    key = (
        cfg.robot,
        cfg.fixed_base,
        cfg.balance,
        cfg.auto_retime,
        cfg.lead_in,
        cfg.compile,
        cfg.retargeter,
        cfg.offline_engine,
        cfg.fps,
    )
    if key not in _ROBOT:
        from retarget.lead_in import LeadInConfig
        from retarget.offline import OfflineConfig, OfflineRetargeter
        from retarget.streaming import StreamingConfig, StreamingRetargeter
        from ros_free_bridge.robots import planning_robot, resolve_robot

        fixed = cfg.fixed_base if cfg.fixed_base is not None else resolve_robot(cfg.robot).fixed_base
        robot = planning_robot(cfg.robot, fixed_base=fixed)
        balance = cfg.balance and not fixed
        if cfg.retargeter == "streaming":
            retarget = StreamingRetargeter(robot, cfg.fps, StreamingConfig(compile=cfg.compile, balance=balance)).run
        else:
            retarget = OfflineRetargeter(
                robot,
                OfflineConfig(
                    balance=balance,
                    zmp=True,
                    auto_retime=cfg.auto_retime,
                    compile=cfg.compile,
                    lead_in=LeadInConfig() if cfg.lead_in else None,
                    engine=cfg.offline_engine,
                ),
            ).retarget
        _ROBOT[key] = (robot, retarget, fixed)
    return _ROBOT[key]


def check_clip(path, cfg: BatchConfig, name: str | None = None, actor=None, workdir=None) -> ClipResult:
    """Retarget and check one clip; never raises (an unexpected error becomes an 'error' row
    with its traceback written beside the clip's outputs).

    ``path``: the motion file the robot takes; ``actor``: for a pair, the other person's file
    (both in one world frame). ``name``: the row name (default the file's name). Outputs go to
    ``workdir`` (default ``OUT/clips/<name>/``, emptied first); messages name them where they
    end up, under ``OUT/clips/<name>/``."""
    import time

    from dualflow.errors import DualFlowError
    from retarget.errors import RetargetError
    from sim.errors import SimError

    path = Path(path)
    res = ClipResult(name or path.name)
    final = clip_dir(cfg, res.clip)
    out = Path(workdir) if workdir is not None else final
    shutil.rmtree(out, ignore_errors=True)  # a previous run's outputs of this clip (e.g. its video)
    t0 = time.monotonic()
    try:
        res.stage = "load"
        motion, partner = _load(path, cfg.fps, actor)
        res.frames, res.duration_s = motion.n_frames, round(motion.duration, 3)
        res.stage = "retarget"
        robot, retarget, fixed = _robot(cfg)
        traj = retarget(motion)
        res.retime = float(traj.meta.get("retime", 1.0))
        src = _retarget_report(robot, traj, motion, res, out)
        if partner is not None and res.retime != 1.0:
            partner = _slowed(partner, res.retime)
        placement = None if partner is None else _scene_placement(robot, traj, src, fixed)
        scene = _Scene(robot, fixed, traj, src, partner, placement, _check_config(cfg.robot, fixed))
        res.stage = "check"
        _physics_check(scene, cfg, res, out)
        if cfg.video:
            _film(scene, cfg, res, out)
    except (DualFlowError, RetargetError, SimError) as exc:
        res.status, res.reason = ("error" if res.stage == "load" else "fail"), str(exc)
        res.first_failure_s = getattr(exc, "time_s", None)
    except Exception as exc:  # noqa: BLE001 - one broken clip must not stop the batch
        out.mkdir(parents=True, exist_ok=True)
        (out / "traceback.txt").write_text(traceback.format_exc())
        res.files["traceback"] = "traceback.txt"
        res.status = "error"
        res.reason = f"unexpected {type(exc).__name__}: {exc} (traceback in {final / 'traceback.txt'})"
    res.seconds = round(time.monotonic() - t0, 2)
    return res


def _load(path: Path, fps: float, actor_path=None):
    """(the robot's person, the other person or None), resampled to ``fps``. A pair of files
    or a two-person file: the reactor is the robot's part."""
    from dualflow.motion import TwoPersonMotion
    from dualflow.motion.io import load_any, load_pair

    motion = load_pair(actor_path, path) if actor_path is not None else load_any(path)
    partner = None
    if isinstance(motion, TwoPersonMotion):
        motion, partner = motion.reactor, motion.actor.resample(fps)
    motion = motion.resample(fps)
    return motion.replace(name=path.stem), partner


def _slowed(motion, factor: float):
    """``motion`` played ``factor`` times slower, at its own frame rate."""
    from dualflow.motion import Motion

    return Motion(motion.positions, motion.fps / factor, name=motion.name).resample(motion.fps)


def _retarget_report(robot, traj, motion, res: ClipResult, out: Path):
    """Write the trajectory and the retarget report; the source motion as the robot played it
    (slowed by the re-timing, if any)."""
    from retarget.report import evaluate
    from retarget.targets import make_targets

    src = motion if res.retime == 1.0 else _slowed(motion, res.retime)
    report = evaluate(robot, traj, make_targets(robot, src), clip=motion.name)
    out.mkdir(parents=True, exist_ok=True)
    traj.save_npz(out / "trajectory.npz")
    report.save(out, "retarget")
    res.keypoint_error_mm = round(report.keypoint_error_mean_mm, 1)
    res.skate_share = round(report.skate_share, 4)
    res.jerk_ratio = None if report.jerk_ratio is None else round(report.jerk_ratio, 3)
    res.limit_violations = report.limit_violations + report.velocity_violations
    res.changed = changes_summary(report.changes, res.retime)
    res.files.update(trajectory="trajectory.npz", retarget_report="retarget.report.md")
    if not report.passed:
        res.status, res.stage, res.first_failure_s = "fail", "retarget", _clip_time(report.first_failure_s, res)
        res.reason = (
            f"retarget report: {report.limit_violations} limit / {report.velocity_violations} velocity "
            f"violations, skate {100 * report.skate_share:.1f}% of contact frames, "
            f"penetration {report.penetration_mm:.1f} mm"
        )
    return src


def _scene_placement(robot, traj, reactor, fixed: bool):
    """The placement (:class:`sim.human_figure.Placement`) that puts the capture's people into the
    robot's scene: ``reactor`` (the person the robot plays) onto the robot, and so a pair's actor
    where they stood relative to that person.

    A free-standing robot's root follows the reactor's pelvis scaled about the world origin
    (``root_scale``) and lifted to put its feet on the floor (:mod:`retarget.targets`): the same
    scale and lift keep the capture's shared world frame. A fixed-base robot only mirrors the
    reactor's posture at its own pedestal: the people are scaled to the robot's head height and
    moved so that the reactor's pelvis and heading at the first frame are the robot's; the actor
    keeps their place relative to the reactor at that frame (the robot does not follow a walk)."""
    import math

    from retarget.targets import KeypointScaler, make_targets
    from sim.human_figure import Placement

    r = robot.root_keypoint
    if robot.floating and not fixed:
        scaler = KeypointScaler(robot, reactor.positions)
        lift = (
            make_targets(robot, reactor, scaler=scaler).keypoints[0, r, 2]
            - scaler.targets(reactor.positions[:1])[0, r, 2]
        )
        return Placement(scale=float(scaler.root_scale), offset=(0.0, 0.0, float(lift)), yaw_deg=0.0)
    stand = robot.evaluate(robot.x_stand[None])["keypoints"][0]  # (K, 3) m, the robot standing
    top = robot.keypoint_names.index("head") if "head" in robot.keypoint_names else int(stand[:, 2].argmax())
    p0 = reactor.positions[0]
    floor = float(min(p0[j, 2] for j in (7, 8, 10, 11)))  # ankles and feet
    scale = float(stand[top, 2]) / max(float(p0[15, 2]) - floor, 1e-3)  # head over the floor
    left = p0[1] - p0[2]  # right hip -> left hip; a person faces along it turned by -90 deg
    qw, qx, qy, qz = (float(v) for v in traj.root_quat[0])
    yaw = math.atan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy * qy + qz * qz)) - math.atan2(-left[0], left[1])
    c, s_ = math.cos(yaw), math.sin(yaw)
    px, py = scale * (c * p0[0, 0] - s_ * p0[0, 1]), scale * (s_ * p0[0, 0] + c * p0[0, 1])
    return Placement(
        scale=scale,
        offset=(float(stand[r, 0]) - px, float(stand[r, 1]) - py, -scale * floor),
        yaw_deg=math.degrees(yaw),
    )


def _physics_check(scene: _Scene, cfg: BatchConfig, res: ClipResult, out: Path) -> None:
    """``check.md`` and its plots in ``out``; the row's verdict (a retarget failure stays the reason)."""
    from sim.check import check_trajectory
    from sim.human_figure import People
    from sim.report import write_report

    check = check_trajectory(
        scene.traj,
        scene.check_config,
        robot=cfg.robot,
        people=People(scene.partner, scene.placement),
    )
    write_report(check, out, "check")
    res.files["check_report"] = "check.md"
    res.check_reason = "" if check.passed else check.reason
    if res.status == "fail":  # the retarget report already failed: keep that as the reason
        return
    if check.passed:
        res.status, res.stage = "pass", ""
    else:
        res.status, res.reason = "fail", check.reason
        res.first_failure_s = _clip_time(check.first_failure_time, res)


def _film(scene: _Scene, cfg: BatchConfig, res: ClipResult, out: Path) -> None:
    """``video.mp4``: a pair as three panels (the actor | the person the robot plays | the robot
    with the actor), one person as one panel with that person moving beside the robot. The
    servos play the trajectory as in the check, so the video shows what the check judged. A
    video that cannot be made (no OpenGL) is noted in ``video_error.txt``; it never changes the row."""
    import math

    from sim.errors import SimError
    from sim.human_figure import People, Placement
    from sim.render import RenderConfig, render_trajectory

    traj, robot, src, partner, placement = scene.traj, scene.robot, scene.src, scene.partner, scene.placement
    fixed = scene.fixed
    w, h = cfg.video_size
    check_cfg = scene.check_config  # as _physics_check
    on_robot = placement or _scene_placement(robot, traj, src, fixed)  # the robot's person drawn on the robot
    try:
        if partner is not None:
            render_trajectory(
                traj,
                out / VIDEO,
                RenderConfig(width=w, height=h, fps=cfg.video_fps, side_by_side=True),
                check_cfg,
                robot=cfg.robot,
                people=People(partner, placement, src, on_robot),
            )
        else:
            # the person one robot height to the robot's left (as the robot faces at the first frame)
            qw, qx, qy, qz = (float(v) for v in traj.root_quat[0])
            yaw = math.atan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy * qy + qz * qz))
            step = float(robot.evaluate(robot.x_stand[None])["keypoints"][0][:, 2].max())
            x, y, z = on_robot.offset
            beside = Placement(
                on_robot.scale, (x - step * math.sin(yaw), y + step * math.cos(yaw), z), on_robot.yaw_deg
            )
            render_trajectory(
                traj,
                out / VIDEO,
                RenderConfig(width=2 * w, height=h, fps=cfg.video_fps),
                check_cfg,
                robot=cfg.robot,
                people=People(src, beside),
            )
        res.files["video"] = VIDEO
    except SimError as exc:  # e.g. no OpenGL context on this machine
        (out / "video_error.txt").write_text(f"no video: {exc}\n")
    except Exception as exc:  # noqa: BLE001 - the video is an extra: a bug in making it must not change the verdict
        (out / "video_error.txt").write_text(
            f"no video: unexpected {type(exc).__name__}: {exc}\n\n{traceback.format_exc()}"
        )


def _clip_time(t: float | None, res: ClipResult) -> float | None:
    """A time on the robot's trajectory -> seconds into the motion file (a re-timed trajectory
    plays the clip ``retime`` times slower)."""
    return None if t is None else round(float(t) / res.retime, 3)


def changes_summary(changes, retime: float = 1.0) -> str:
    """One cell for the ``changed`` column: per kind of change (retarget.schedule / offline: step
    skipped, speed-limited, slower travel, flight, pivot, standing start), in order of first
    appearance, "what: N× T s from a s (up to E mm)", times in seconds into the motion file
    (a re-timed clip's divided by ``retime``), E the worst mean keypoint error over one part
    (left out where no part has one: a lead-in before the clip has no person to measure against)."""
    kinds: dict[str, list] = {}
    for c in changes:
        kinds.setdefault(c["what"], []).append(c)
    cells = []
    for what, cs in kinds.items():
        total = sum(c["end_s"] - c["start_s"] for c in cs) / retime
        errors = [c["keypoint_error_mm"] for c in cs if c.get("keypoint_error_mm") is not None]
        worst = f" (up to {max(errors):.0f} mm)" if errors else ""
        cells.append(f"{what}: {len(cs)}x {total:.2f} s from {cs[0]['start_s'] / retime:.2f} s{worst}")
    return "; ".join(cells)

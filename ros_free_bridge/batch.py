"""Offline retarget-and-check over a folder: can the robot do each clip, and if not, why.

Each clip (one motion file, or two files of one capture joined with ``pairs``) goes through:

1. load, resample to 30 fps;
2. offline retargeting (CasADi/IPOPT: limits, foot contacts, self-collision, balance), which
   may find the clip infeasible at its speed and say how much slower it would have to be; or,
   with ``retargeter="streaming"``, the live bridge's frame-by-frame retargeter (limits as
   hard bounds, feet planted, CoM, capture point and ZMP kept over them);
3. the physics check in MuJoCo (falls, torque saturation, speed limits, collisions, balance,
   and, where the clip has a second person, penetrating that person);
4. optionally a short video: the person and the robot side by side (``BatchConfig.video``).

Which files: the motion files directly in the folder (or, with ``recursive``, in its whole
tree), named by their path relative to it. A folder in InterGen's layout (``person1/`` and
``person2/`` side by side, or under ``motions_processed/``) gives one clip per pair, the
reactor's file: person2's, unless InterHuman-AS's ``actor_reactor.json`` in the dataset root
says person2 acts. With a pair pattern (:class:`PairPattern`, e.g. ``{name}_S1.bvh,{name}_S2.bvh``)
the two files of one capture in one folder form one clip, named by the reactor's (second)
file: the robot takes the reactor's part and the actor stands beside it in the capture's
shared world frame. Files that match neither half of the pattern stay single clips; a file
whose partner is missing gets an ``error`` row naming the missing file.

One row per clip: ``status`` is ``pass``, ``fail`` (with the stage, the reason and the time of
the first failure) or ``error`` (a file that could not be read, with the message). A clip that
fails or crashes never stops the batch, not even one that kills its worker process (a crash in
a native library, or out of memory).

Engines (``run_batch(engine=...)``): ``local`` (the default) runs the clips in a pool of worker
processes on this machine (forked; with videos, forked from a clean fork server, so a script
calling :func:`run_batch` needs the usual ``if __name__ == "__main__":`` guard); a worker that
dies takes the clips in flight with it: those are
re-run one per process, the others in a new pool, and a clip that kills its process again gets
an ``error`` row. ``ray`` runs each clip as a Ray task (:mod:`ros_free_bridge.batch_ray`), on
a cluster or a local Ray instance; only that engine imports Ray. Both run the same per-clip
function (:func:`check_clip`) and write the same files.

Results on disk, written as each clip ends (:class:`ResultLog`): the clip's outputs under
``OUT/clips/<clip>/``, then its marker ``OUT/clips/<clip>/result.json`` (the row and the input
files' sizes and times, written atomically after every other output), then one line of
``results.jsonl`` and one of ``results.csv`` (each line written whole and synced). A clip is
*complete* when its marker exists, ``results.jsonl`` holds a line for it equal to the marker's
row, and its input files are unchanged; ``resume=True`` skips complete clips and re-runs the
rest, so a batch killed at any moment and resumed ends with the same table as one that ran
through. When the batch ends (or is interrupted) ``results.csv`` is rewritten in clip
order, ``results.md`` and the browsable ``index.html`` (:mod:`ros_free_bridge.report_html`)
are written from the rows.
"""

from __future__ import annotations

import csv
import hashlib
import json
import os
import re
import shutil
import sys
import traceback
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path

MOTION_SUFFIXES = (".bvh", ".npz", ".npy")
COLUMNS = ("clip", "actor", "status", "stage", "reason", "first_failure_s", "frames", "duration_s", "retime",
           "keypoint_error_mm", "skate_share", "jerk_ratio", "limit_violations", "check_reason", "changed", "seconds")
#: Columns that depend on the machine and its load, not on the clip (left out when two tables are compared).
TIMING_COLUMNS = ("seconds",)
#: The marker a clip's output folder gets last: its row, once every other output is written.
MARKER = "result.json"
VIDEO = "video.mp4"
RESULTS_JSONL, RESULTS_CSV, RESULTS_MD, SETTINGS = "results.jsonl", "results.csv", "results.md", "batch.json"


@dataclass
class ClipResult:
    clip: str
    status: str = "error"  #: pass | fail | error
    stage: str = ""  #: load | retarget | check
    reason: str = ""
    first_failure_s: float | None = None  #: seconds into the motion file (not the re-timed trajectory)
    frames: int = 0
    duration_s: float = 0.0
    retime: float = 1.0
    keypoint_error_mm: float | None = None
    skate_share: float | None = None
    jerk_ratio: float | None = None
    limit_violations: int | None = None
    check_reason: str = ""
    #: what the robot plays differently from the person (retarget.schedule's changes: a jump kept on
    #: the ground, a spin on one foot, ...): "what start-end s (keypoint error there)", seconds
    #: into the motion file; "" when nothing was changed
    changed: str = ""
    seconds: float = 0.0
    actor: str = ""  #: a pair's actor file (relative to the folder, like ``clip``); "" for one person
    files: dict = field(default_factory=dict)  #: output name -> file name in the clip's folder (not a column)

    def row(self) -> dict:
        d = asdict(self)
        return {k: d[k] for k in COLUMNS}

    @classmethod
    def from_row(cls, row: dict) -> "ClipResult":
        known = {f.name for f in fields(cls)} - {"files"}
        return cls(**{k: v for k, v in row.items() if k in known})


@dataclass(frozen=True)
class BatchConfig:
    robot: str = "op3"
    out: Path = Path("out/retarget_check")
    fps: float = 30.0
    balance: bool = True
    auto_retime: bool = False
    fixed_base: bool | None = None  #: None: the robot's own (fixed for upper-body robots)
    compile: bool = True
    #: "offline": the whole clip in windows (CasADi/IPOPT, ZMP balance); "streaming": frame by
    #: frame as the live bridge runs it (feet planted, CoM, capture point and ZMP over them)
    retargeter: str = "offline"
    #: film each clip (person and robot side by side, physics playback) into ``video.mp4``
    video: bool = True
    video_size: tuple[int, int] = (256, 192)  #: pixels per panel (width, height; multiples of 16 for the encoder)
    video_fps: float = 15.0

    def settings(self) -> dict:
        """What decides a clip's row (the robot by the content of its files): a batch resumes
        only with the same settings."""
        return {"robot": str(self.robot), "robot_files": robot_fingerprint(self.robot), "fps": self.fps,
                "balance": self.balance, "auto_retime": self.auto_retime, "fixed_base": self.fixed_base,
                "retargeter": self.retargeter}


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


# -- which clips -------------------------------------------------------------
@dataclass(frozen=True)
class Clip:
    """One row of the batch: ``path`` is the file the robot takes (for a pair: the reactor's),
    ``actor`` the other person's file of a pair, ``name`` the row name; ``problem`` (a pair
    with a missing file) makes it an ``error`` row without running anything."""

    name: str
    path: Path
    actor: Path | None = None
    actor_name: str = ""
    problem: str = ""


@dataclass(frozen=True)
class PairPattern:
    """Two file-name patterns, actor first, reactor second, each with one ``{name}``:
    ``{name}_S1.bvh,{name}_S2.bvh`` joins ``take7_S1.bvh`` (actor) and ``take7_S2.bvh``
    (reactor, the robot's part) in the same folder. Names match whole and case-sensitively."""

    actor: str
    reactor: str

    @classmethod
    def parse(cls, text: str) -> "PairPattern":
        from ros_free_bridge.errors import BridgeError

        parts = [p.strip() for p in str(text).split(",")]
        fix = "give two file-name patterns, actor first, e.g. --pairs '{name}_S1.bvh,{name}_S2.bvh'"
        if len(parts) != 2 or not all(parts):
            raise BridgeError(f"--pairs {text!r}: {fix}")
        for p in parts:
            if p.count("{name}") != 1 or re.search(r"\{(?!name\})", p):
                raise BridgeError(f"--pairs {text!r}: each pattern needs exactly one {{name}} and no other braces; {fix}")
            if "/" in p or "\\" in p:
                raise BridgeError(f"--pairs {text!r}: patterns are file names, not paths (both files lie in one folder); {fix}")
            if Path(p.replace("{name}", "x")).suffix.lower() not in MOTION_SUFFIXES:
                raise BridgeError(f"--pairs {text!r}: {p!r} must end in a motion file type ({', '.join(MOTION_SUFFIXES)})")
        if parts[0] == parts[1]:
            raise BridgeError(f"--pairs {text!r}: the actor's and the reactor's patterns are the same; {fix}")
        return cls(*parts)

    def _regex(self, pattern: str) -> re.Pattern:
        head, tail = pattern.split("{name}")
        return re.compile(re.escape(head) + "(?P<name>.+)" + re.escape(tail))

    def match(self, filename: str) -> tuple[str | None, str | None]:
        """(name if ``filename`` is an actor's file, name if it is a reactor's file)."""
        a, r = self._regex(self.actor).fullmatch(filename), self._regex(self.reactor).fullmatch(filename)
        return (a["name"] if a else None), (r["name"] if r else None)

    def __str__(self) -> str:
        return f"{self.actor},{self.reactor}"


def find_motion_files(folder, recursive: bool = False, exclude=None) -> list[Path]:
    """The clips in ``folder`` (module docstring), sorted; ``exclude``: a folder to leave out
    (the batch's own output folder, when it lies inside the input)."""
    folder = Path(folder)
    if not folder.is_dir():
        from ros_free_bridge.errors import BridgeError

        raise BridgeError(f"{folder}: not a folder; give a folder of motion files (BVH, npz, npy)")
    skip = Path(exclude).resolve() if exclude is not None else None
    candidates = [p for p in (folder.rglob("*") if recursive else folder.iterdir())
                  if p.is_file() and p.suffix.lower() in MOTION_SUFFIXES
                  and not (skip is not None and p.resolve().is_relative_to(skip))]
    # InterGen's layout: FOLDER/ or FOLDER/motions_processed/ (with --recursive: any folder) holding
    # person1/ and person2/; their files are listed as pairs, by the reactor's file
    bases = {folder, folder / "motions_processed"}
    if recursive:
        bases |= {p.parent.parent for p in candidates}
    bases = sorted(b for b in bases if (b / "person1").is_dir() and (b / "person2").is_dir())
    people = {b / person for b in bases for person in ("person1", "person2")}
    found = [p for p in candidates if p.parent not in people]
    for base in bases:
        found += _intergen_reactors(base)
    return sorted(found)


def find_clips(folder, recursive: bool = False, exclude=None, pairs: PairPattern | str | None = None) -> list[Clip]:
    """The batch's clips, sorted by name: :func:`find_motion_files`, with the files that
    ``pairs`` joins turned into one clip per capture (module docstring)."""
    files = find_motion_files(folder, recursive, exclude)
    if pairs is None:
        return [Clip(clip_name(f, folder), f) for f in files]
    pattern = pairs if isinstance(pairs, PairPattern) else PairPattern.parse(pairs)
    present = set(files)
    used: set[Path] = set()
    clips = []
    for f in files:  # pairs first, found from the reactor's side
        _, as_reactor = pattern.match(f.name)
        if as_reactor is not None:
            actor = f.parent / pattern.actor.replace("{name}", as_reactor)
            if actor in present and actor != f:
                clips.append(Clip(clip_name(f, folder), f, actor, clip_name(actor, folder)))
                used |= {f, actor}
    for f in files:
        if f in used:
            continue
        as_actor, as_reactor = pattern.match(f.name)
        name = clip_name(f, folder)
        if as_reactor is not None:
            missing = pattern.actor.replace("{name}", as_reactor)
            clips.append(Clip(name, f, problem=f"pair {pattern}: {name} has no actor file {missing} beside it; "
                                                f"add it, or move {f.name} out of the folder"))
        elif as_actor is not None:
            missing = pattern.reactor.replace("{name}", as_actor)
            clips.append(Clip(name, f, problem=f"pair {pattern}: {name} is an actor's file without its reactor "
                                                f"{missing} beside it; add it, or move {f.name} out of the folder"))
        else:
            clips.append(Clip(name, f))
    return sorted(clips, key=lambda c: c.name)


def _intergen_reactors(base: Path) -> list[Path]:
    """The reactor's file of each clip under ``base``/person1|person2 (a clip with one person only:
    that person's file); InterHuman-AS's actor_reactor.json in the dataset root says who acts."""
    from dualflow.datasets.interhuman import LABEL_FILE, PEOPLE, read_actor_labels

    files = {person: {f.name: f for f in (base / person).iterdir() if f.is_file() and f.suffix.lower() in MOTION_SUFFIXES}
             for person in PEOPLE}
    root = base.resolve()
    root = root.parent if root.name == "motions_processed" else root
    labels = read_actor_labels(root / LABEL_FILE) if (root / LABEL_FILE).is_file() else {}
    reactors = []
    for name in sorted(set(files["person1"]) | set(files["person2"])):
        order = ("person1", "person2") if labels.get(Path(name).stem) == "person2" else ("person2", "person1")
        reactors.append(next(files[p][name] for p in order if name in files[p]))
    return reactors


def clip_name(path, folder) -> str:
    """A clip's row name: its path relative to the batch's folder (``/``-separated)."""
    return Path(path).relative_to(folder).as_posix()


def as_clips(files, folder=None) -> list[Clip]:
    """Clips from a list of :class:`Clip` or of files (named relative to ``folder``, default by file name)."""
    out = []
    for f in files:
        if isinstance(f, Clip):
            out.append(f)
        else:
            f = Path(f)
            out.append(Clip(clip_name(f, folder) if folder is not None else f.name, f))
    return out


# -- one clip ----------------------------------------------------------------
_ROBOT = {}


def _robot(cfg: BatchConfig):
    """The retarget robot and the retargeter, built once per worker process."""
    key = (cfg.robot, cfg.fixed_base, cfg.balance, cfg.auto_retime, cfg.compile, cfg.retargeter, cfg.fps)
    if key not in _ROBOT:
        from retarget.offline import OfflineConfig, OfflineRetargeter
        from retarget.robot import load_robot
        from retarget.streaming import StreamingConfig, StreamingRetargeter
        from ros_free_bridge.robots import resolve_robot

        fixed = cfg.fixed_base if cfg.fixed_base is not None else resolve_robot(cfg.robot).fixed_base
        robot = load_robot(cfg.robot, fixed_base=fixed)
        balance = cfg.balance and not fixed
        if cfg.retargeter == "streaming":
            retarget = StreamingRetargeter(robot, cfg.fps, StreamingConfig(compile=cfg.compile, balance=balance)).run
        else:
            retarget = OfflineRetargeter(robot, OfflineConfig(balance=balance, zmp=True, auto_retime=cfg.auto_retime,
                                                              compile=cfg.compile)).retarget
        _ROBOT[key] = (robot, retarget, fixed)
    return _ROBOT[key]


def clip_dir(cfg: BatchConfig, name: str) -> Path:
    """Where a clip's outputs live: ``OUT/clips/<name>/`` (a folder of its own, which a re-run
    of the clip empties: so the name must stay below ``clips/``)."""
    parts = Path(name).parts
    if not parts or Path(name).is_absolute() or any(p in ("..", ".") for p in parts):
        from ros_free_bridge.errors import BridgeError

        raise BridgeError(f"clip name {name!r}: must be a relative path inside the folder (no '..')")
    return Path(cfg.out) / "clips" / name


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
        res.stage = "check"
        _physics_check(traj, cfg, fixed, res, out, partner, placement)
        if cfg.video:
            _film(traj, cfg, fixed, robot, src, partner, placement, res, out)
    except (DualFlowError, RetargetError, SimError) as exc:
        res.status, res.reason = ("error" if res.stage == "load" else "fail"), str(exc)
        res.first_failure_s = getattr(exc, "time_s", None)
    except Exception as exc:  # noqa: BLE001 - one broken clip must not stop the batch
        out.mkdir(parents=True, exist_ok=True)
        (out / "traceback.txt").write_text(traceback.format_exc())
        res.files["traceback"] = "traceback.txt"
        res.status, res.reason = "error", f"unexpected {type(exc).__name__}: {exc} (traceback in {final / 'traceback.txt'})"
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
        res.reason = (f"retarget report: {report.limit_violations} limit / {report.velocity_violations} velocity "
                      f"violations, skate {100 * report.skate_share:.1f}% of contact frames, "
                      f"penetration {report.penetration_mm:.1f} mm")
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
        lift = make_targets(robot, reactor, scaler=scaler).keypoints[0, r, 2] - scaler.targets(reactor.positions[:1])[0, r, 2]
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
    return Placement(scale=scale, offset=(float(stand[r, 0]) - px, float(stand[r, 1]) - py, -scale * floor),
                     yaw_deg=math.degrees(yaw))


def _physics_check(traj, cfg: BatchConfig, fixed: bool, res: ClipResult, out: Path, actor=None, placement=None) -> None:
    from sim.check import CheckConfig, check_trajectory
    from sim.report import write_report

    check = check_trajectory(traj, CheckConfig(mode="fixed" if fixed else "free"), robot=cfg.robot, actor=actor,
                             actor_placement=placement)
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


def _film(traj, cfg: BatchConfig, fixed: bool, robot, src, partner, placement, res: ClipResult, out: Path) -> None:
    """``video.mp4``: a pair as three panels (the actor | the person the robot plays | the robot
    with the actor), one person as one panel with that person moving beside the robot. The
    servos play the trajectory as in the check, so the video shows what the check judged. A
    video that cannot be made (no OpenGL) is noted in ``video_error.txt``; it never changes the row."""
    import math

    from sim.check import CheckConfig
    from sim.errors import SimError
    from sim.human_figure import Placement
    from sim.render import RenderConfig, render_trajectory

    w, h = cfg.video_size
    check_cfg = CheckConfig(mode="fixed" if fixed else "free")
    on_robot = placement or _scene_placement(robot, traj, src, fixed)  # the robot's person drawn on the robot
    try:
        if partner is not None:
            render_trajectory(traj, out / VIDEO, RenderConfig(width=w, height=h, fps=cfg.video_fps, side_by_side=True),
                              check_cfg, robot=cfg.robot, actor=partner, actor_placement=placement,
                              reactor=src, reactor_placement=on_robot)
        else:
            # the person one robot height to the robot's left (as the robot faces at the first frame)
            qw, qx, qy, qz = (float(v) for v in traj.root_quat[0])
            yaw = math.atan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy * qy + qz * qz))
            step = float(robot.evaluate(robot.x_stand[None])["keypoints"][0][:, 2].max())
            x, y, z = on_robot.offset
            beside = Placement(on_robot.scale, (x - step * math.sin(yaw), y + step * math.cos(yaw), z), on_robot.yaw_deg)
            render_trajectory(traj, out / VIDEO, RenderConfig(width=2 * w, height=h, fps=cfg.video_fps), check_cfg,
                              robot=cfg.robot, actor=src, actor_placement=beside)
        res.files["video"] = VIDEO
    except SimError as exc:  # e.g. no OpenGL context on this machine
        (out / "video_error.txt").write_text(f"no video: {exc}\n")
    except Exception as exc:  # noqa: BLE001 - the video is an extra: a bug in making it must not change the verdict
        (out / "video_error.txt").write_text(f"no video: unexpected {type(exc).__name__}: {exc}\n\n"
                                             f"{traceback.format_exc()}")


def _clip_time(t: float | None, res: ClipResult) -> float | None:
    """A time on the robot's trajectory -> seconds into the motion file (a re-timed trajectory
    plays the clip ``retime`` times slower)."""
    return None if t is None else round(float(t) / res.retime, 3)


# -- results on disk ---------------------------------------------------------
def _append_line(path: Path, text: str) -> None:
    """Append one line with a single write, then flush and fsync: after a kill the file ends
    with this whole line or without it (at worst a torn tail that :func:`_complete_lines` drops)."""
    data = (text.rstrip("\n") + "\n").encode()
    with open(path, "ab") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())


def _atomic_write(path: Path, text: str, sync: bool = True) -> None:
    """Write under a temporary name and rename: the file is whole or absent. ``sync``: on
    disk before the rename (records); pages that can be made again skip it."""
    tmp = path.with_name(path.name + ".partial")
    with open(tmp, "w", newline="") as fh:
        fh.write(text)
        if sync:
            fh.flush()
            os.fsync(fh.fileno())
    tmp.replace(path)


def _complete_lines(path: Path) -> list[str]:
    """The whole lines of ``path`` (a torn last line, from a kill in mid-write, is left out)."""
    if not path.is_file():
        return []
    data = path.read_bytes()
    end = data.rfind(b"\n") + 1
    return data[:end].decode(errors="replace").splitlines()


def _csv_text(rows: list[dict], header: bool = True) -> str:
    import io

    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=COLUMNS, lineterminator="\n")
    if header:
        w.writeheader()
    for r in rows:
        w.writerow(r)
    return buf.getvalue()


def _row_json(row: dict) -> str:
    return json.dumps(row, allow_nan=False, separators=(",", ":"))


def input_stamp(clip: Clip) -> list:
    """What a clip was made from: [file name, size in bytes, modification time in ns] of its
    motion file (and of a pair's actor file). A changed file changes it."""
    stamp = []
    for path in (clip.path, clip.actor):
        if path is not None:
            try:
                st = Path(path).stat()
                stamp.append([Path(path).name, st.st_size, st.st_mtime_ns])
            except OSError:
                stamp.append([Path(path).name, None, None])
    return stamp


class ResultLog:
    """``OUT/results.jsonl`` and ``OUT/results.csv``, one line per clip as it ends, and each
    clip's marker ``OUT/clips/<clip>/result.json``: ``{"row": the row, "inputs": input_stamp}``.

    A clip is *complete* when its marker exists, ``results.jsonl`` holds a line for it equal to
    the marker's row, and its input files (the same ones: a pair's actor too) have the size and
    modification time the marker recorded. The marker is written after every other output of
    the clip and before its lines, each write whole (a temporary file renamed, or one synced
    append), so a kill at any moment leaves a clip either complete or to be run again.

    ``resume=False`` starts both files afresh; ``resume=True`` keeps the rows of the complete
    clips among ``clips`` (both files are rewritten with just those, atomically, which also
    drops a torn last line) and refuses an output folder made with other settings
    (``OUT/batch.json``)."""

    def __init__(self, cfg: BatchConfig, clips: list[Clip] = (), resume: bool = False):
        from ros_free_bridge.errors import BridgeError

        self.cfg, self.out = cfg, Path(cfg.out)
        self.out.mkdir(parents=True, exist_ok=True)
        self.jsonl, self.csv = self.out / RESULTS_JSONL, self.out / RESULTS_CSV
        settings = cfg.settings()
        self.rows: dict[str, dict] = {}
        saved = self.out / SETTINGS
        if resume and saved.is_file():
            try:
                before = json.loads(saved.read_text())
            except ValueError:
                before = None
            if before != settings:
                diff = sorted(k for k in settings if not isinstance(before, dict) or before.get(k) != settings[k])
                raise BridgeError(f"--resume: {self.out} was made with other settings ({', '.join(diff) or SETTINGS}: "
                                  f"{SETTINGS} there says {before!r}); resume with the same options and robot files, "
                                  "or write to another -o folder (or drop --resume to start afresh)")
            self.rows = self._complete_rows(clips)
        _atomic_write(saved, json.dumps(settings, indent=1) + "\n")
        rows = list(self.rows.values())
        _atomic_write(self.jsonl, "".join(_row_json(r) + "\n" for r in rows))
        _atomic_write(self.csv, _csv_text(rows))

    def _complete_rows(self, clips: list[Clip]) -> dict[str, dict]:
        lines = {}
        for line in _complete_lines(self.jsonl):
            try:
                row = json.loads(line)
            except ValueError:
                continue
            if isinstance(row, dict) and isinstance(row.get("clip"), str):
                lines[row["clip"]] = row  # the last line of a clip wins
        rows = {}
        for clip in clips:
            row = lines.get(clip.name)
            if row is not None and self._marker(clip.name) == {"row": row, "inputs": input_stamp(clip)}:
                rows[clip.name] = row
        return rows

    def _marker(self, name: str) -> dict | None:
        try:
            return json.loads((clip_dir(self.cfg, name) / MARKER).read_text())
        except (OSError, ValueError):
            return None

    def complete(self) -> dict[str, ClipResult]:
        """The clips already complete (by name)."""
        return {name: ClipResult.from_row(row) for name, row in self.rows.items()}

    def add(self, clip: Clip, res: ClipResult) -> None:
        """Record a clip whose outputs are all written: its marker, then its lines."""
        row = res.row()
        folder = clip_dir(self.cfg, res.clip)
        folder.mkdir(parents=True, exist_ok=True)
        marker = {"row": row, "inputs": input_stamp(clip)}
        _atomic_write(folder / MARKER, json.dumps(marker, allow_nan=False, separators=(",", ":")) + "\n")
        _append_line(self.jsonl, _row_json(row))
        _append_line(self.csv, _csv_text([row], header=False))
        self.rows[res.clip] = row


def read_results(out) -> list[dict]:
    """The rows of ``OUT/results.jsonl`` in clip order (the last line per clip, whole lines
    only): what the tables and the HTML report are made from."""
    rows = {}
    for line in _complete_lines(Path(out) / RESULTS_JSONL):
        try:
            row = json.loads(line)
        except ValueError:
            continue
        if isinstance(row, dict) and isinstance(row.get("clip"), str):
            rows[row["clip"]] = row
    return [rows[name] for name in sorted(rows)]


# -- the batch ---------------------------------------------------------------
def run_batch(files, cfg: BatchConfig, jobs: int | None = None, progress: bool = True, folder=None,
              engine: str = "local", address: str | None = None, resume: bool = False) -> list[ClipResult]:
    """Check every clip; rows in clip order. Each row is written to disk as its clip ends
    (:class:`ResultLog`); at the end (or on Ctrl-C) the tables and the HTML report are written.

    files:   :class:`Clip` objects or motion files (named relative to ``folder``, default by file name).
    jobs:    local engine: worker processes (default: every core this process may use); ray: the
             CPUs of the Ray instance it starts, or at most this many clips at once on a cluster.
    engine:  "local" or "ray" (``address``: a Ray cluster to join; None starts a local instance).
    resume:  skip the clips a previous run in ``cfg.out`` completed with the same settings.
    """
    from tqdm import tqdm

    from ros_free_bridge.errors import BridgeError

    if engine not in ("local", "ray"):
        raise BridgeError(f"engine {engine!r}: use 'local' or 'ray'")
    clips = as_clips(files, folder)
    names = [c.name for c in clips]
    if len(set(names)) != len(names):
        raise BridgeError(f"two clips share a name ({sorted(n for n in names if names.count(n) > 1)[0]}); "
                          "give files from one folder")
    for n in names:
        clip_dir(cfg, n)  # each name stays inside OUT/clips (raises otherwise)
    if engine == "ray":
        try:
            from ros_free_bridge.batch_ray import run_ray
        except ImportError as exc:
            raise BridgeError(f"--engine ray needs Ray ({exc}); install it with `pip install -e \".[cluster]\"` "
                              "(or `pip install 'ray>=2.40,<3'`), or use the local engine") from None
    log = ResultLog(cfg, clips, resume=resume)
    wanted = set(names)
    results: dict[str, ClipResult] = {n: r for n, r in log.complete().items() if n in wanted}
    todo = [c for c in clips if c.name not in results]
    if resume and progress and results:
        print(f"resuming: {len(results)} of {len(clips)} clips already complete in {cfg.out}")
    try:
        with tqdm(total=len(todo), desc="retarget-check", unit="clip", disable=not progress) as bar:
            def done(clip: Clip, res: ClipResult) -> None:
                res.actor = clip.actor_name
                log.add(clip, res)
                results[clip.name] = res
                bar.update()
                bar.set_postfix_str(f"{res.clip}: {res.status}", refresh=True)

            runnable = []
            for c in todo:
                if c.problem:
                    done(c, ClipResult(c.name, status="error", stage="load", reason=c.problem))
                else:
                    runnable.append(c)
            if engine == "ray":
                run_ray(runnable, cfg, done, jobs=jobs, address=address)
            else:
                _run_local(runnable, cfg, jobs, done)
    finally:
        finish(cfg, clips, [results[c.name] for c in clips if c.name in results])
    return [results[n] for n in names]


def finish(cfg: BatchConfig, clips: list[Clip], results: list[ClipResult]) -> dict[str, Path]:
    """The tables (``results.csv`` in clip order, ``results.md``) and the HTML report, from the rows."""
    from ros_free_bridge.report_html import write_html_report

    paths = write_results(results, cfg.out)
    paths["html"] = write_html_report(cfg.out, results, total=len(clips))
    return paths


def _run_local(clips: list[Clip], cfg: BatchConfig, jobs: int | None, done) -> None:
    """The local engine: ``jobs`` forked worker processes (module docstring)."""
    if not clips:
        return
    jobs = max(1, min(jobs or _usable_cores(), len(clips)))
    pending = list(range(len(clips)))
    while pending:
        lost = _pool_pass(pending, clips, cfg, jobs, done)
        # the clips a dead worker took down: those that were in flight (the first submitted:
        # jobs, plus the one the pool had queued) run one per process, to find each one that
        # kills its process; the rest run again in a pool
        suspects, pending = lost[:jobs + 1], lost[jobs + 1:]
        for i in suspects:
            if _pool_pass([i], clips, cfg, 1, done):
                done(clips[i], ClipResult(clips[i].name, status="error",
                                          reason="the worker process died while checking this clip (a crash in a native "
                                                 "library, or out of memory); retarget it alone with `dualflow-bridge "
                                                 f"retarget {clips[i].path}` to see the crash"))


def _pool_pass(indices, clips: list[Clip], cfg: BatchConfig, jobs: int, done) -> list[int]:
    """Run ``indices`` in a pool of ``jobs`` processes, calling ``done(clip, result)`` as each ends;
    the indices whose result was lost because a worker process died."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor, as_completed
    from concurrent.futures.process import BrokenProcessPool

    lost = []
    with ProcessPoolExecutor(jobs, mp_context=_pool_context(cfg)) as pool:
        try:
            futures = {pool.submit(check_clip, clips[i].path, cfg, clips[i].name, actor=clips[i].actor): i
                       for i in indices}
            for fut in as_completed(futures):
                i = futures[fut]
                try:
                    res = fut.result()
                except BrokenProcessPool:
                    lost.append(i)
                    continue
                except Exception as exc:  # noqa: BLE001 - e.g. a result that cannot be sent back
                    res = ClipResult(clips[i].name, status="error", reason=f"unexpected {type(exc).__name__}: {exc}")
                done(clips[i], res)
        except BaseException:  # Ctrl-C: no clip is started any more, and the running ones stop
            workers = list((getattr(pool, "_processes", None) or {}).values())
            pool.shutdown(wait=False, cancel_futures=True)
            for proc in workers:
                proc.terminate()
            raise
    return sorted(lost)


def _pool_context(cfg: BatchConfig):
    """How the local engine's workers are made.

    ``fork`` starts them at once with everything this process imported (and, in tests,
    patched). It is not safe after this process used OpenGL (EGL: a forked worker that films a
    clip hangs creating its context) or loaded Ray (its gRPC threads and locks do not survive a
    fork): with videos, or with Ray loaded, a fork server started clean (this package and its
    solvers imported, no OpenGL context) makes the workers instead."""
    import multiprocessing as mp

    if not cfg.video and sys.modules.get("ray") is None:
        return mp.get_context("fork")
    ctx = mp.get_context("forkserver")
    ctx.set_forkserver_preload(["ros_free_bridge.batch", "retarget.offline", "sim.check"])
    return ctx


def _usable_cores() -> int:
    """Cores this process may run on (its affinity, where the OS has one), at least 1."""
    try:
        return len(os.sched_getaffinity(0)) or 1
    except AttributeError:
        return os.cpu_count() or 1


def changes_summary(changes, retime: float = 1.0) -> str:
    """One cell for the ``changed`` column: per kind of change (retarget.schedule / offline: step
    skipped, speed-limited, slower travel, flight, pivot, standing start), in order of first
    appearance, "what: N× T s from a s (up to E mm)", times in seconds into the motion file
    (a re-timed clip's divided by ``retime``), E the worst mean keypoint error over one part."""
    kinds: dict[str, list] = {}
    for c in changes:
        kinds.setdefault(c["what"], []).append(c)
    cells = []
    for what, cs in kinds.items():
        total = sum(c["end_s"] - c["start_s"] for c in cs) / retime
        worst = max(c.get("keypoint_error_mm", 0.0) for c in cs)
        cells.append(f"{what}: {len(cs)}x {total:.2f} s from {cs[0]['start_s'] / retime:.2f} s (up to {worst:.0f} mm)")
    return "; ".join(cells)


def write_results(results: list[ClipResult], out: Path) -> dict[str, Path]:
    """results.csv and results.md in the order given (complete or absent: written under a
    temporary name and renamed)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    csv_path, md_path = out / RESULTS_CSV, out / RESULTS_MD
    _atomic_write(csv_path, _csv_text([r.row() for r in results]))
    _atomic_write(md_path, markdown_table(results))
    return {"csv": csv_path, "markdown": md_path}


def markdown_table(results: list[ClipResult]) -> str:
    n_pass = sum(r.status == "pass" for r in results)
    lines = [f"# Retarget-and-check: {n_pass} of {len(results)} clips pass", "",
             "| clip | status | stage | first failure (s) | frames | retime | kp err (mm) | skate | jerk ratio | reason "
             "| changed from the person |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        cells = [r.clip, r.status.upper(), r.stage or "-", _fmt(r.first_failure_s), str(r.frames), _fmt(r.retime),
                 _fmt(r.keypoint_error_mm), _fmt(r.skate_share), _fmt(r.jerk_ratio), (r.reason or "-").replace("|", "/"),
                 (r.changed or "-").replace("|", "/")]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _fmt(v) -> str:
    return "-" if v is None else f"{v:g}" if isinstance(v, float) else str(v)

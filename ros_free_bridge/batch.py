"""Offline retarget-and-check over a folder: can the robot do each clip, and if not, why.

Each motion file (BVH, our npz, InterGen / HumanML3D npy; for two-person files the reactor,
the robot's role) goes through:

1. load, resample to 30 fps;
2. offline retargeting (CasADi/IPOPT: limits, foot contacts, self-collision, balance), which
   may find the clip infeasible at its speed and say how much slower it would have to be; or,
   with ``retargeter="streaming"``, the live bridge's frame-by-frame retargeter (limits as
   hard bounds, feet planted, CoM, capture point and ZMP kept over them);
3. the physics check in MuJoCo (falls, torque saturation, speed limits, collisions, balance).

Which files: the motion files directly in the folder (or, with ``recursive``, in its whole
tree), named by their path relative to it. A folder in InterGen's layout (``person1/`` and
``person2/`` side by side, or under ``motions_processed/``) gives one clip per pair, the
reactor's file: person2's, unless InterHuman-AS's ``actor_reactor.json`` in the dataset root
says person2 acts.

One row per clip: ``status`` is ``pass``, ``fail`` (with the stage, the reason and the time of
the first failure) or ``error`` (a file that could not be read, with the message). A clip that
fails or crashes never stops the batch, not even one that kills its worker process (a crash in
a native library, or out of memory): the clips that were in flight are re-run one per process,
the others in a new pool, and a clip that kills its process again gets an ``error`` row. Clips run in parallel
processes, each loading the robot (and its compiled CasADi functions) once.
"""

from __future__ import annotations

import csv
import os
import traceback
from dataclasses import asdict, dataclass, field
from pathlib import Path

MOTION_SUFFIXES = (".bvh", ".npz", ".npy")
COLUMNS = ("clip", "status", "stage", "reason", "first_failure_s", "frames", "duration_s", "retime",
           "keypoint_error_mm", "skate_share", "jerk_ratio", "limit_violations", "check_reason", "seconds")


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
    seconds: float = 0.0
    files: dict = field(default_factory=dict)

    def row(self) -> dict:
        d = asdict(self)
        return {k: d[k] for k in COLUMNS}


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


def clip_name(path, folder) -> str:
    """A clip's row name: its path relative to the batch's folder (``/``-separated)."""
    return Path(path).relative_to(folder).as_posix()


def check_clip(path, cfg: BatchConfig, name: str | None = None) -> ClipResult:
    """Retarget and check one file; never raises (an unexpected error becomes an 'error' row
    with its traceback written beside the clip's outputs). Outputs go to ``OUT/clips/<name>/``
    (``name``: the row name, default the file's name)."""
    import time

    from dualflow.errors import DualFlowError
    from retarget.errors import RetargetError
    from sim.errors import SimError

    path = Path(path)
    res = ClipResult(name or path.name)
    out = Path(cfg.out) / "clips" / res.clip
    t0 = time.monotonic()
    try:
        res.stage = "load"
        motion = _load(path, cfg.fps)
        res.frames, res.duration_s = motion.n_frames, round(motion.duration, 3)
        res.stage = "retarget"
        robot, retarget, fixed = _robot(cfg)
        traj = retarget(motion)
        res.retime = float(traj.meta.get("retime", 1.0))
        _retarget_report(robot, traj, motion, res, out)
        res.stage = "check"
        _physics_check(traj, cfg, fixed, res, out)
    except (DualFlowError, RetargetError, SimError) as exc:
        res.status, res.reason = ("error" if res.stage == "load" else "fail"), str(exc)
        res.first_failure_s = getattr(exc, "time_s", None)
    except Exception as exc:  # noqa: BLE001 - one broken clip must not stop the batch
        out.mkdir(parents=True, exist_ok=True)
        (out / "traceback.txt").write_text(traceback.format_exc())
        res.status, res.reason = "error", f"unexpected {type(exc).__name__}: {exc} (traceback in {out / 'traceback.txt'})"
    res.seconds = round(time.monotonic() - t0, 2)
    return res


def _load(path: Path, fps: float):
    from dualflow.motion import TwoPersonMotion
    from dualflow.motion.io import load_any

    motion = load_any(path)
    if isinstance(motion, TwoPersonMotion):
        motion = motion.reactor
    motion = motion.resample(fps)
    return motion.replace(name=path.stem)


def _retarget_report(robot, traj, motion, res: ClipResult, out: Path) -> None:
    from retarget.report import evaluate
    from retarget.targets import make_targets

    src = motion
    if res.retime != 1.0:
        from dualflow.motion import Motion

        src = Motion(motion.positions, motion.fps / res.retime, name=motion.name).resample(motion.fps)
    report = evaluate(robot, traj, make_targets(robot, src), clip=motion.name)
    out.mkdir(parents=True, exist_ok=True)
    traj.save_npz(out / "trajectory.npz")
    report.save(out, "retarget")
    res.keypoint_error_mm = round(report.keypoint_error_mean_mm, 1)
    res.skate_share = round(report.skate_share, 4)
    res.jerk_ratio = None if report.jerk_ratio is None else round(report.jerk_ratio, 3)
    res.limit_violations = report.limit_violations + report.velocity_violations
    res.files["trajectory"] = str(out / "trajectory.npz")
    if not report.passed:
        res.status, res.stage, res.first_failure_s = "fail", "retarget", _clip_time(report.first_failure_s, res)
        res.reason = (f"retarget report: {report.limit_violations} limit / {report.velocity_violations} velocity "
                      f"violations, skate {100 * report.skate_share:.1f}% of contact frames, "
                      f"penetration {report.penetration_mm:.1f} mm")


def _physics_check(traj, cfg: BatchConfig, fixed: bool, res: ClipResult, out: Path) -> None:
    from sim.check import CheckConfig, check_trajectory
    from sim.report import write_report

    check = check_trajectory(traj, CheckConfig(mode="fixed" if fixed else "free"), robot=cfg.robot)
    write_report(check, out, "check")
    res.check_reason = "" if check.passed else check.reason
    if res.status == "fail":  # the retarget report already failed: keep that as the reason
        return
    if check.passed:
        res.status, res.stage = "pass", ""
    else:
        res.status, res.reason = "fail", check.reason
        res.first_failure_s = _clip_time(check.first_failure_time, res)


def _clip_time(t: float | None, res: ClipResult) -> float | None:
    """A time on the robot's trajectory -> seconds into the motion file (a re-timed trajectory
    plays the clip ``retime`` times slower)."""
    return None if t is None else round(float(t) / res.retime, 3)


def run_batch(files, cfg: BatchConfig, jobs: int | None = None, progress: bool = True,
              folder=None) -> list[ClipResult]:
    """Check every file in ``jobs`` worker processes (default: every core this process may use);
    rows in file order, named relative to ``folder`` (default: by file name)."""
    from tqdm import tqdm

    files = [Path(f) for f in files]
    names = [clip_name(f, folder) if folder is not None else f.name for f in files]
    jobs = max(1, min(jobs or _usable_cores(), len(files) or 1))
    results: dict[int, ClipResult] = {}
    with tqdm(total=len(files), desc="retarget-check", unit="clip", disable=not progress) as bar:
        def done(i: int, res: ClipResult) -> None:
            results[i] = res
            bar.update()
            bar.set_postfix_str(f"{res.clip}: {res.status}", refresh=True)

        pending = list(range(len(files)))
        while pending:
            lost = _pool_pass(pending, files, names, cfg, jobs, done)
            # the clips a dead worker took down: those that were in flight (the first submitted:
            # jobs, plus the one the pool had queued) run one per process, to find each one that
            # kills its process; the rest run again in a pool
            suspects, pending = lost[:jobs + 1], lost[jobs + 1:]
            for i in suspects:
                if _pool_pass([i], files, names, cfg, 1, done):
                    done(i, ClipResult(names[i], status="error",
                                       reason="the worker process died while checking this clip (a crash in a native "
                                              "library, or out of memory); retarget it alone with `dualflow-bridge "
                                              f"retarget {files[i]}` to see the crash"))
    return [results[i] for i in range(len(files))]


def _pool_pass(indices, files, names, cfg: BatchConfig, jobs: int, done) -> list[int]:
    """Run ``indices`` in a pool of ``jobs`` processes, calling ``done(i, result)`` as each ends;
    the indices whose result was lost because a worker process died."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor, as_completed
    from concurrent.futures.process import BrokenProcessPool

    lost = []
    with ProcessPoolExecutor(jobs, mp_context=mp.get_context("fork")) as pool:
        try:
            futures = {pool.submit(check_clip, files[i], cfg, names[i]): i for i in indices}
            for fut in as_completed(futures):
                i = futures[fut]
                try:
                    done(i, fut.result())
                except BrokenProcessPool:
                    lost.append(i)
                except Exception as exc:  # noqa: BLE001 - e.g. a result that cannot be sent back
                    done(i, ClipResult(names[i], status="error", reason=f"unexpected {type(exc).__name__}: {exc}"))
        except BaseException:  # Ctrl-C: no clip is started any more, and the running ones stop
            workers = list((getattr(pool, "_processes", None) or {}).values())
            pool.shutdown(wait=False, cancel_futures=True)
            for proc in workers:
                proc.terminate()
            raise
    return sorted(lost)


def _usable_cores() -> int:
    """Cores this process may run on (its affinity, where the OS has one), at least 1."""
    try:
        return len(os.sched_getaffinity(0)) or 1
    except AttributeError:
        return os.cpu_count() or 1


def write_results(results: list[ClipResult], out: Path) -> dict[str, Path]:
    """results.csv and results.md (complete or absent: written under a temporary name)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    csv_path, md_path = out / "results.csv", out / "results.md"
    tmp = csv_path.with_name(csv_path.name + ".partial")
    with open(tmp, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=COLUMNS)
        w.writeheader()
        for r in results:
            w.writerow(r.row())
    tmp.replace(csv_path)
    tmp = md_path.with_name(md_path.name + ".partial")
    tmp.write_text(markdown_table(results))
    tmp.replace(md_path)
    return {"csv": csv_path, "markdown": md_path}


def markdown_table(results: list[ClipResult]) -> str:
    n_pass = sum(r.status == "pass" for r in results)
    lines = [f"# Retarget-and-check: {n_pass} of {len(results)} clips pass", "",
             "| clip | status | stage | first failure (s) | frames | retime | kp err (mm) | skate | jerk ratio | reason |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        cells = [r.clip, r.status.upper(), r.stage or "-", _fmt(r.first_failure_s), str(r.frames), _fmt(r.retime),
                 _fmt(r.keypoint_error_mm), _fmt(r.skate_share), _fmt(r.jerk_ratio), (r.reason or "-").replace("|", "/")]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _fmt(v) -> str:
    return "-" if v is None else f"{v:g}" if isinstance(v, float) else str(v)

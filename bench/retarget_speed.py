"""Retarget speed and quality on one core, next to a GMR-style per-frame differential-IK baseline.

    python bench/retarget_speed.py [--robot op3] [--clip cmu|synthetic] [--seconds 20] [--quick]

The clip is the CMU two-person capture (../shared/data/mocap/cmu, both people, 30 fps) when
present, else a synthetic duet (dualflow.synthetic.make_duet). Each figure is printed next to
the baseline's on the SAME clip in the SAME run, the issue's target and the ratio.

Baseline ("GMR style"): per frame, mink differential IK solved with daqp, two stages as GMR
configures them (stage 1: root, feet and hands; stage 2: every keypoint), each stage iterated
until the task error stops falling by 1 mm (at most 10 steps), damping 0.5, configuration
limits, warm-started from the previous frame. It tracks the same scaled keypoint targets as
ours (positions only: SMPL-22 positions carry no segment orientations).

Timing: the process is pinned to one core (sched_setaffinity) with single-threaded BLAS;
frames/s are reported on process CPU time (robust to other load on a shared machine) and on
wall time. Compilation (cached on disk) is excluded and reported on its own line, and every
method makes one untimed pass over the first clip before anything is timed (imports, model
loading, first solves), so neither side pays one-off costs. The offline lines are the window
optimisation (OfflineConfig(engine="ipopt"), with and without the ZMP), and the configuration
retarget-check runs (OfflineConfig(balance=True, zmp=True), engine "auto": the step planner,
retarget.planned, on a free-standing robot); the latter's ratio to the baseline has the issue's
0.9 target. Where the window optimisation's time goes and what was tried: docs/retargeting.md,
section 9.

Quality (see retarget/report.py): jerk ratio = mean |Δ³p|·fps³ over the robot's keypoints /
the same over the source's scaled keypoints; with 1 cm noise the ratio is given both against
the noisy source (the issue's definition) and against the clean source (stricter).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from dataclasses import replace  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.table import NA, Row, parse_args, script_main, verdict  # noqa: E402
from dualflow.motion import Motion  # noqa: E402
from retarget.offline import OfflineConfig, OfflineRetargeter  # noqa: E402
from retarget.report import evaluate  # noqa: E402
from retarget.robot import load_robot, resolve_paths  # noqa: E402
from retarget.streaming import StreamingRetargeter, trajectory_from_x  # noqa: E402
from retarget.targets import KeypointScaler, make_targets  # noqa: E402

CMU = ROOT.parent / "shared" / "data" / "mocap" / "cmu"
# The CMU pair is 152 frames at 30 fps: short enough for a smoke run as it is. (A 3 s synthetic
# clip is no shortcut: the offline solver calls its first window infeasible at that speed.)
QUICK: list[str] = []


def load_clips(kind: str, seconds: float) -> list[Motion]:
    if kind == "cmu" and (CMU / "18_01.bvh").is_file():
        from dualflow.motion.io import load_pair, put_on_ground

        pair = put_on_ground(load_pair(CMU / "18_01.bvh", CMU / "19_01.bvh", fps=30.0))
        return [pair.actor.replace(name="cmu18_01"), pair.reactor.replace(name="cmu19_01")]
    from dualflow.synthetic import make_duet

    duet = make_duet("hand_hold", seconds=seconds, fps=30.0, seed=0)
    return [duet.actor, duet.reactor]


def _loadavg() -> str:
    """The 1, 5 and 15 minute load averages (a shared machine's timings depend on them)."""
    try:
        return " ".join(f"{x:.2f}" for x in os.getloadavg())
    except OSError:
        return "unknown"


class Clock:
    """CPU and wall seconds of a block."""

    def __enter__(self):
        self.c, self.w = time.process_time(), time.perf_counter()
        return self

    def __exit__(self, *exc):
        self.cpu, self.wall = time.process_time() - self.c, time.perf_counter() - self.w


def gmr_style(rb, xml: Path, tg) -> np.ndarray:
    """Per-frame two-stage mink/daqp IK on the targets tg.keypoints (T, K, 3) → X (T, nx)."""
    import mink
    import mujoco

    model = mujoco.MjModel.from_xml_path(str(xml))
    conf = mink.Configuration(model)
    kid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, "stand")
    conf.update(model.key_qpos[kid] if kid >= 0 else model.qpos0)
    sites = [s.site for s in rb.profile.keypoints]
    tasks = [
        mink.FrameTask(site, "site", position_cost=float(w), orientation_cost=0.0, lm_damping=1.0)
        for site, w in zip(sites, rb.keypoint_weights)
    ]
    stage1_names = {"pelvis", "left_ankle", "right_ankle", "left_foot", "right_foot", "left_wrist", "right_wrist"}
    stage1 = [t for t, n in zip(tasks, rb.keypoint_names) if n in stage1_names]
    limits = [mink.ConfigurationLimit(model)]
    dt = model.opt.timestep
    X = np.zeros((tg.keypoints.shape[0], rb.nx))

    def error(stage):
        return sum(np.linalg.norm(t.compute_error(conf)[:3]) for t in stage)

    for t in range(tg.keypoints.shape[0]):
        for task, p in zip(tasks, tg.keypoints[t]):
            task.set_target(mink.SE3.from_translation(p))
        for stage in (stage1, tasks):
            err = error(stage)
            for _ in range(10):
                vel = mink.solve_ik(conf, stage, dt, "daqp", damping=0.5, limits=limits)
                conf.integrate_inplace(vel, dt)
                new = error(stage)
                if err - new < 1e-3:
                    break
                err = new
        X[t] = rb.kin.x_from_qpos(conf.q)
    return X


def warm_up(rb, xml: Path, clip: Motion, offline: tuple) -> None:
    """One untimed pass of each method over ``clip`` before anything is timed: the one-off costs
    (imports, model loading, the first IPOPT solve, the warm-start solver's set-up) are left out on
    both sides. Without it the baseline's first clip paid for ``import mink`` (~0.3 s CPU, a
    quarter of its time on the CMU pair) while ours had its compilation excluded: a ratio of
    ~1.0 that was ~0.65 warm."""
    tg = make_targets(rb, clip)
    gmr_style(rb, xml, tg)
    for off in offline:
        if off is not None:
            off.retarget(clip, scaler=KeypointScaler(rb, clip.positions))


def rows(quick: bool = False, argv: list[str] = ()) -> list[Row]:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--robot", default="op3")
    ap.add_argument("--clip", choices=("cmu", "synthetic"), default="cmu")
    ap.add_argument("--seconds", type=float, default=20.0, help="synthetic clip length")
    ap.add_argument("--no-balance", action="store_true")
    args = parse_args(ap, argv, quick, QUICK)
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})

    rb = load_robot(args.robot)
    xml, _ = resolve_paths(args.robot)
    clips = load_clips(args.clip, args.seconds)
    n_frames = sum(c.n_frames for c in clips)
    print(f"robot {rb.name} ({rb.kin.n_joints} joints), clips {[c.name for c in clips]}, {n_frames} frames at 30 fps")
    print(f"load average at start: {_loadavg()}")

    # the window optimisation (engine "ipopt"), whatever the robot
    offline_cfg = OfflineConfig(balance=not args.no_balance, engine="ipopt")
    off = OfflineRetargeter(rb, offline_cfg)
    # the configuration retarget-check runs (engine "auto": the step planner on a free-standing robot)
    off_check = OfflineRetargeter(rb, OfflineConfig(balance=not args.no_balance, zmp=True))
    # the dynamic variant: the ZMP (CoM with its acceleration term) over the support polygon
    off_zmp = None if args.no_balance else OfflineRetargeter(rb, replace(offline_cfg, zmp=True))
    # the same problem with every collision pair as a segment distance (the sole pairs too):
    # what the sole-plane rows replaced, timed in the same run
    off_dist = OfflineRetargeter(rb, replace(offline_cfg, collision_model="distance"))
    with Clock() as c_build:
        off._solver(offline_cfg.window, 30.0)
        off_dist._solver(offline_cfg.window, 30.0)
        if off_zmp is not None:
            off_zmp._solver(offline_cfg.window, 30.0)
        stream = StreamingRetargeter(rb, 30.0)
    print(
        f"compile/load: {c_build.wall:.1f} s wall ({off._solver(offline_cfg.window, 30.0)[-1]}; "
        f"streaming {stream.compile_info})"
    )
    warm_up(rb, xml, clips[0], (off, off_dist, off_zmp, off_check))

    noise_rng = np.random.default_rng(0)
    results = {"ours_stream": [], "ours_off": [], "base": [], "ours_zmp": [], "ours_dist": [], "ours_check": []}
    times = {k: [0.0, 0.0] for k in results}
    reports = {
        k: []
        for k in (
            "ours_off",
            "ours_stream",
            "base",
            "off_noisy",
            "base_noisy",
            "stream_noisy",
            "ours_zmp",
            "ours_dist",
            "ours_check",
        )
    }
    jerk_clean, ipopt, ipopt_dist = {}, {}, {}
    for clip in clips:
        tg = make_targets(rb, clip)
        scaler = KeypointScaler(rb, clip.positions)
        # streaming
        with Clock() as ck:
            stream.reset()
            Xs = np.stack([stream.step(tg.keypoints[t], tg.contacts[t]) for t in range(clip.n_frames)])
        times["ours_stream"][0] += ck.cpu
        times["ours_stream"][1] += ck.wall
        tr_s = trajectory_from_x(rb, Xs, clip.fps, {"mode": "streaming"})
        reports["ours_stream"].append(evaluate(rb, tr_s, tg, clip.name))
        # offline
        with Clock() as ck:
            tr_o = off.retarget(clip, scaler=scaler)
        times["ours_off"][0] += ck.cpu
        times["ours_off"][1] += ck.wall
        reports["ours_off"].append(evaluate(rb, tr_o, tg, clip.name))
        ipopt[clip.name] = (tr_o.meta["ipopt_iterations"], tr_o.meta["ipopt_status"])
        with Clock() as ck:
            tr_d = off_dist.retarget(clip, scaler=scaler)
        times["ours_dist"][0] += ck.cpu
        times["ours_dist"][1] += ck.wall
        reports["ours_dist"].append(evaluate(rb, tr_d, tg, clip.name))
        ipopt_dist[clip.name] = tr_d.meta["ipopt_iterations"]
        with Clock() as ck:
            tr_c = off_check.retarget(clip, scaler=scaler)
        times["ours_check"][0] += ck.cpu
        times["ours_check"][1] += ck.wall
        reports["ours_check"].append(evaluate(rb, tr_c, tg, clip.name))
        if off_zmp is not None:
            with Clock() as ck:
                tr_z = off_zmp.retarget(clip, scaler=scaler)
            times["ours_zmp"][0] += ck.cpu
            times["ours_zmp"][1] += ck.wall
            reports["ours_zmp"].append(evaluate(rb, tr_z, tg, clip.name))
        # baseline
        with Clock() as ck:
            Xb = gmr_style(rb, xml, tg)
        times["base"][0] += ck.cpu
        times["base"][1] += ck.wall
        reports["base"].append(evaluate(rb, trajectory_from_x(rb, Xb, clip.fps, {"mode": "gmr-style"}), tg, clip.name))
        jerk_clean[clip.name] = reports["base"][-1].jerk_source
        # the same clip with 1 cm of noise on every joint
        noisy = clip.replace(
            positions=clip.positions + noise_rng.normal(scale=0.01, size=clip.positions.shape), name=clip.name + "+1cm"
        )
        tgn = make_targets(rb, noisy, contacts=tg.contacts, scaler=scaler)
        reports["off_noisy"].append(
            evaluate(rb, off.retarget(noisy, contacts=tg.contacts, scaler=scaler), tgn, noisy.name)
        )
        stream.reset()
        Xsn = np.stack([stream.step(tgn.keypoints[t], tgn.contacts[t]) for t in range(clip.n_frames)])
        reports["stream_noisy"].append(evaluate(rb, trajectory_from_x(rb, Xsn, clip.fps, {}), tgn, noisy.name))
        reports["base_noisy"].append(
            evaluate(rb, trajectory_from_x(rb, gmr_style(rb, xml, tgn), clip.fps, {}), tgn, noisy.name)
        )

    print(
        "offline IPOPT per clip (iterations, status per window): "
        + "; ".join(f"{name} {it} {st}" for name, (it, st) in ipopt.items())
    )
    print(f"load average at end: {_loadavg()}")

    def agg(key, field, how=np.mean):
        return float(how([getattr(r, field) for r in reports[key]]))

    def fps(key, i):
        return n_frames / times[key][i]

    def vs_clean(key):
        return float(np.mean([r.jerk_robot / jerk_clean[r.clip.replace("+1cm", "")] for r in reports[key]]))

    def r(name, ours, base, target="", ok=None):
        return Row(name, ours, base, target, verdict(ok) if target else NA)

    stream_fps, base_fps = fps("ours_stream", 0), fps("base", 0)
    off_fps = fps("ours_off", 0)
    jerk = {k: agg(k, "jerk_ratio") for k in ("ours_off", "ours_stream", "base", "off_noisy", "base_noisy")}
    out = [
        r(
            "retarget streaming frames/s (CPU time, 1 core)",
            stream_fps,
            base_fps,
            ">= 1000 and >= 4x baseline",
            stream_fps >= 1000 and stream_fps >= 4 * base_fps,
        ),
        r("retarget streaming frames/s (wall)", fps("ours_stream", 1), fps("base", 1)),
        r(
            f"retarget offline frames/s (CPU time; contacts{'' if args.no_balance else '+balance'})",
            off_fps,
            base_fps,
            ">= 250",
            off_fps >= 250,
        ),
        r("retarget offline frames/s (wall)", fps("ours_off", 1), fps("base", 1)),
        r("offline IPOPT iterations per clip (mean)", float(np.mean([it for it, _ in ipopt.values()])), None),
        r("retarget offline frames/s (CPU time), all pairs as segment distances", fps("ours_dist", 0), base_fps),
        r(
            "offline IPOPT iterations per clip, all pairs as segment distances",
            float(np.mean(list(ipopt_dist.values()))),
            None,
        ),
        r(
            "keypoint error mean mm (offline, all pairs as segment distances)",
            agg("ours_dist", "keypoint_error_mean_mm"),
            agg("base", "keypoint_error_mean_mm"),
        ),
        r(
            "jerk ratio, clean capture: offline, all pairs as segment distances",
            agg("ours_dist", "jerk_ratio"),
            agg("base", "jerk_ratio"),
        ),
    ]
    if off_zmp is not None:
        zj = agg("ours_zmp", "jerk_ratio")
        zr = fps("ours_zmp", 0) / base_fps
        out += [
            r("retarget offline frames/s (CPU time; window optimisation, ZMP balance)", fps("ours_zmp", 0), base_fps),
            r("offline window optimisation (ZMP balance) frames/s / baseline's, same run", zr, 1.0),
            r("jerk ratio, clean capture: offline window optimisation, ZMP balance", zj, jerk["base"]),
        ]
    cr, cj = fps("ours_check", 0) / base_fps, agg("ours_check", "jerk_ratio")
    out += [
        r(
            f"retarget offline frames/s (CPU time; as retarget-check runs it: engine {off_check.engine})",
            fps("ours_check", 0),
            base_fps,
        ),
        r(f"offline ({off_check.engine}) frames/s / baseline's, same run", cr, 1.0, ">= 0.9", cr >= 0.9),
        r(f"jerk ratio, clean capture: offline ({off_check.engine})", cj, jerk["base"], "<= 1.0", cj <= 1.0),
        r(
            f"keypoint error mean mm (offline, {off_check.engine})",
            agg("ours_check", "keypoint_error_mean_mm"),
            agg("base", "keypoint_error_mean_mm"),
        ),
    ]
    out += [
        r("jerk ratio, clean capture: offline", jerk["ours_off"], jerk["base"], "<= 1.0", jerk["ours_off"] <= 1.0),
        r("jerk ratio, clean capture: streaming", jerk["ours_stream"], jerk["base"]),
        r(
            "jerk ratio, 1 cm noise (vs noisy source): offline",
            jerk["off_noisy"],
            jerk["base_noisy"],
            "<= 1.0",
            jerk["off_noisy"] <= 1.0,
        ),
        r("jerk ratio, 1 cm noise (vs clean source): offline", vs_clean("off_noisy"), vs_clean("base_noisy")),
        r("jerk ratio, 1 cm noise (vs clean source): streaming", vs_clean("stream_noisy"), vs_clean("base_noisy")),
    ]
    for key, label in (("ours_off", "offline"), ("ours_stream", "streaming")):
        for field, what in (("limit_violations", "joint-limit"), ("velocity_violations", "velocity-limit")):
            n = int(agg(key, field, np.sum))
            out.append(r(f"{what} violations ({label})", n, int(agg("base", field, np.sum)), "0", n == 0))
    skate, pen = agg("ours_off", "skate_share"), agg("ours_off", "penetration_mm", np.max)
    n_self = int(agg("ours_off", "self_collisions", np.sum))
    out += [
        r("foot skate share of contact frames (offline)", skate, agg("base", "skate_share"), "< 0.02", skate < 0.02),
        r(
            "worst slide mm/frame (offline)",
            agg("ours_off", "worst_slide_mm", np.max),
            agg("base", "worst_slide_mm", np.max),
        ),
        r("worst ground penetration mm (offline)", pen, agg("base", "penetration_mm", np.max), "<= 5", pen <= 5),
        r("self-collisions (offline)", n_self, int(agg("base", "self_collisions", np.sum)), "0", n_self == 0),
        r(
            "keypoint error mean mm (offline)",
            agg("ours_off", "keypoint_error_mean_mm"),
            agg("base", "keypoint_error_mean_mm"),
        ),
        r(
            "keypoint error mean mm (streaming)",
            agg("ours_stream", "keypoint_error_mean_mm"),
            agg("base", "keypoint_error_mean_mm"),
        ),
    ]
    return out


def main(argv: list[str] | None = None) -> int:
    return script_main(rows, argv)


if __name__ == "__main__":
    raise SystemExit(main())

"""Speed of the MuJoCo check and of offscreen rendering, on one CPU core.

Prints, for a 10 s op3 clip (a slow two-arm dance) with physics at 500 Hz and
control at 100 Hz:
  - validation speed (sim.check, all metrics) as a multiple of real time;
  - the baseline measured in the same run: raw mj_step with the same control
    updates and no metrics (the ceiling the check can reach);
  - the issue's target (>= 50x real time);
and offscreen rendering frames per second at 640x480 ("fast" and "full" quality)
next to a baseline of mj_forward + scene update alone.

Times are CPU seconds of this process (time.process_time), so that other
programs competing for the core do not count; wall-clock figures are printed too.

Usage: python bench/sim_speed.py [--seconds 10] [--repeats 5] [--no-render] [--quick]
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.table import NA, Row, parse_args, script_main, verdict  # noqa: E402

TARGET_X_REALTIME = 50.0
QUICK = ["--seconds", "3", "--repeats", "1", "--frames", "5"]


def pin_one_core() -> str:
    try:
        cpu = min(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {cpu})
        return f"pinned to CPU {cpu}"
    except (AttributeError, OSError):
        return "not pinned (sched_setaffinity unavailable)"


def dance(seconds: float):
    import numpy as np

    from firmware_cfg.registry import joint_names
    from retarget import RobotTrajectory
    from sim.scene import Scene

    names = joint_names("op3")
    stand = Scene().stand_ctrl
    fps = 30.0
    t = np.arange(int(seconds * fps) + 1) / fps
    q = np.tile(stand, (len(t), 1))
    q[:, names.index("r_sho_pitch")] -= 0.6 * np.sin(0.8 * t) ** 2
    q[:, names.index("l_sho_pitch")] -= 0.6 * np.sin(0.8 * t + 1.0) ** 2
    q[:, names.index("head_pan")] = 0.5 * np.sin(0.5 * t)
    n = len(t)
    return RobotTrajectory(names, q, np.tile([0, 0, 0.27], (n, 1)), np.tile([1.0, 0, 0, 0], (n, 1)), fps, "op3")


def bench_check(seconds: float, repeats: int) -> list[Row]:
    import mujoco
    import numpy as np

    from sim.check import CheckConfig, Checker, resample, scene_for

    traj = dance(seconds)
    cfg = CheckConfig()
    best_check = best_raw = best_build = float("inf")
    wall_check = wall_raw = float("inf")
    for _ in range(repeats):
        t0 = time.process_time()
        scene = scene_for(traj, cfg)
        best_build = min(best_build, time.process_time() - t0)
        t0, w0 = time.process_time(), time.perf_counter()
        result = Checker(scene, cfg).run(traj)
        best_check = min(best_check, time.process_time() - t0)
        wall_check = min(wall_check, time.perf_counter() - w0)
        assert result.passed, result.failures

        # baseline: the same physics and control updates from the same start (standing,
        # feet on the floor; the entry transition's ticks hold the first frame), nothing measured
        m, d, r = scene.model, scene.data, scene.robot
        ticks = int(traj.duration * cfg.control_hz) + 1
        entry = int(round(result.entry_transition_s * cfg.control_hz))
        q_cmd = resample(traj.times, traj.joint_pos, np.arange(ticks) / cfg.control_hz, "linear")
        q_cmd = np.concatenate([np.repeat(q_cmd[:1], entry, axis=0), q_cmd])
        ticks += entry
        scene.reset()
        n_sub = int(cfg.physics_hz / cfg.control_hz)
        settle = int(cfg.settle_s * cfg.physics_hz)
        t0, w0 = time.process_time(), time.perf_counter()
        mujoco.mj_step(m, d, settle)
        for k in range(ticks):
            d.ctrl[r.actuator_ids] = q_cmd[k]
            mujoco.mj_step(m, d, n_sub)
        best_raw = min(best_raw, time.process_time() - t0)
        wall_raw = min(wall_raw, time.perf_counter() - w0)
    sim_s = traj.duration + cfg.settle_s + result.entry_transition_s
    print(
        f"check: {traj.duration:.0f} s clip (+{cfg.settle_s} s settle, +{result.entry_transition_s:g} s entry from "
        f"standing), physics {cfg.physics_hz:g} Hz, "
        f"control {cfg.control_hz:g} Hz, best of {repeats}"
    )
    print(
        f"  validation (all metrics):      {best_check:6.3f} CPU s = {sim_s / best_check:7.1f} x real time"
        f"   target >= {TARGET_X_REALTIME:g} x   (wall {wall_check:.3f} s = {sim_s / wall_check:.1f} x)"
    )
    print(
        f"  baseline raw mj_step:          {best_raw:6.3f} CPU s = {sim_s / best_raw:7.1f} x real time"
        f"                   (wall {wall_raw:.3f} s = {sim_s / wall_raw:.1f} x)"
    )
    print(f"  metrics overhead:              {best_check / best_raw - 1:6.1%} over the baseline")
    print(f"  scene build (compile, once):   {best_build:6.3f} CPU s")
    with_build = best_check + best_build
    print(f"  validation incl. scene build:  {with_build:6.3f} CPU s = {sim_s / with_build:7.1f} x real time")
    clip = f"{traj.duration:.0f} s clip, physics {cfg.physics_hz:g} Hz"
    target = f">= {TARGET_X_REALTIME:g}"
    return [
        Row(
            f"check speed, {clip} (x real time, CPU; baseline raw mj_step)",
            sim_s / best_check,
            sim_s / best_raw,
            target,
            verdict(sim_s / best_check >= TARGET_X_REALTIME),
        ),
        Row(
            f"check speed incl. scene build, {clip} (x real time, CPU)",
            sim_s / with_build,
            sim_s / best_raw,
            target,
            verdict(sim_s / with_build >= TARGET_X_REALTIME),
        ),
        Row(f"check speed, {clip} (x real time, wall)", sim_s / wall_check, sim_s / wall_raw, "", NA),
    ]


def bench_render(frames: int) -> list[Row]:
    import mujoco

    from sim.render import Filmer, RenderConfig
    from sim.scene import Scene

    scene = Scene()
    print(f"render: 640x480, {frames} frames, MUJOCO_GL={os.environ.get('MUJOCO_GL', '(default)')}")
    t0 = time.process_time()
    cam = mujoco.MjvCamera()
    cam.distance = 1.2
    opt = mujoco.MjvOption()
    vscene = mujoco.MjvScene(scene.model, maxgeom=1000)
    pert = mujoco.MjvPerturb()
    for _ in range(frames):
        mujoco.mj_forward(scene.model, scene.data)
        mujoco.mjv_updateScene(scene.model, scene.data, opt, pert, cam, mujoco.mjtCatBit.mjCAT_ALL, vscene)
    base = (time.process_time() - t0) / frames
    print(f"  baseline forward + scene update: {1.0 / base:8.1f} frames/s")
    rows = []
    for quality in ("fast", "full"):
        filmer = Filmer(scene, RenderConfig(quality=quality))
        filmer.grab()  # warm up the GL context
        t0, w0 = time.process_time(), time.perf_counter()
        for _ in range(frames):
            mujoco.mj_forward(scene.model, scene.data)
            filmer.grab()
        dt = (time.process_time() - t0) / frames
        wall = (time.perf_counter() - w0) / frames
        filmer.close()
        print(
            f"  offscreen render ({quality:4s}):         {1.0 / dt:8.1f} frames/s per CPU s   "
            f"(wall {1.0 / wall:.1f} frames/s)"
        )
        rows.append(
            Row(
                f"offscreen render 640x480, {quality} quality (frames/s per CPU s; baseline forward + scene update)",
                1.0 / dt,
                1.0 / base,
                "",
                NA,
            )
        )
    return rows


def rows(quick: bool = False, argv: list[str] = ()) -> list[Row]:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--no-render", action="store_true")
    args = parse_args(ap, argv, quick, QUICK)
    print(pin_one_core(), f"| load average {os.getloadavg()[0]:.1f}" if hasattr(os, "getloadavg") else "")
    importlib.import_module("sim")  # sets MUJOCO_GL=egl on a headless machine before mujoco loads

    out = bench_check(args.seconds, args.repeats)
    if not args.no_render:
        out += bench_render(args.frames)
    return out


def main(argv: list[str] | None = None) -> int:
    return script_main(rows, argv)


if __name__ == "__main__":
    raise SystemExit(main())

"""The balance stabilizer (sim/stabilizer.py): push recovery and its cost per control tick.

Prints, for the bundled op3 standing in its "stand" pose on the MuJoCo floor (servos at the
model's kp, control at 100 Hz, physics at 500 Hz):
  - the largest push it survives (torso tilt stays under 50 deg until 1.5 s after the push),
    a force on the torso body's centre of mass for 0.2 s (a shove) and for 2.5 s (a lean),
    1 s after standing, sideways (+y / -y) and forward / backward (+x / -x), searched in 1 N
    steps; with the stabilizer (readings one tick old, as the bridge's split-phase bus gives
    them) and, as the baseline in the same run, without it (the servos alone);
  - the stabilizer's cost per tick (Stabilizer.step, CPU microseconds) next to the bridge's
    safety filter step measured in the same run (the issue's budget: <= 100 us per tick);
  - on stepping clips (the synthetic leaders of bench/stepping_leaders.py, streamed as the
    bridge retargets them, checked as `check` does: the bridge's safety filter, readings one
    tick old): clips performed without a fall and the feet's lift-offs per planned step, with
    the default gains and, as the baseline in the same run, with the roll joints' feedback
    kept on two feet (StabilizerGains(two_feet_roll=1), the rule before).

Usage: python bench/stabilizer.py [--quick] [--max-force 60] [--stepping-clips leaders,quick]
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.table import Row, parse_args, script_main, verdict  # noqa: E402

COST_BUDGET_US = 100.0
QUICK = ["--max-force", "15", "--ticks", "2000", "--stepping-clips", "quick"]


def survives(
    scene,
    force: float,
    axis: int,
    stabilizer: bool,
    duration: float = 0.2,
    push_at: float = 1.0,
    control_hz: float = 100.0,
    gains=None,
) -> bool:
    """Whether the standing robot of ``scene`` stays up (tilt < 50 deg) until 1.5 s after a push
    of ``force`` N along world axis ``axis`` (0 x, 1 y) on its root body's centre of mass for
    ``duration`` s. The stabilizer gets the readings of the tick before, as in the bridge."""
    import mujoco
    import numpy as np

    from sim.stabilizer import Stabilizer, balance_model
    from sim.virtual_robot import ImuProbe

    scene.reset()
    m, d, r = scene.model, scene.data, scene.robot
    model = balance_model(scene=scene, gains=gains) if stabilizer else None
    stab = Stabilizer(model) if model is not None else None
    probe = ImuProbe(m, r.root_body)
    q_ref = scene.stand_ctrl.copy()
    dt = 1.0 / control_hz
    n_sub = int(round(m.opt.timestep**-1 / control_hz))
    cos_fall = math.cos(math.radians(50.0))
    reading = (d.qpos[r.qpos_adr].copy(), probe.read(d))
    for k in range(int((push_at + duration + 1.5) * control_hz)):
        t = k * dt
        fresh = (d.qpos[r.qpos_adr].copy(), probe.read(d))
        d.ctrl[r.actuator_ids] = q_ref if stab is None else stab.step(q_ref, reading[0], reading[1], dt)
        reading = fresh
        d.xfrc_applied[r.root_body] = 0.0
        if push_at <= t < push_at + duration:
            d.xfrc_applied[r.root_body, axis] = force
        mujoco.mj_step(m, d, n_sub)
        if d.xmat[r.root_body][8] < cos_fall:
            return False
    return bool(np.isfinite(d.qpos).all())


def largest_push(
    scene, axis: int, sign: float, stabilizer: bool, max_force: float, gains=None, duration: float = 0.2
) -> float:
    """The largest whole-newton push (up to ``max_force``) survived, every smaller one survived too."""
    best = 0.0
    for f in range(1, int(max_force) + 1):
        if not survives(scene, sign * f, axis, stabilizer, duration=duration, gains=gains):
            break
        best = float(f)
    return best


def tick_cost_us(ticks: int) -> tuple[float, float]:
    """(Stabilizer.step, SafetyFilter.step) CPU microseconds per call on the op3, standing with
    IMU readings from the simulation and a reference that moves every tick."""
    import numpy as np

    from ros_free_bridge.control.safety import JointLimits, SafetyFilter
    from sim.scene import Scene
    from sim.stabilizer import Stabilizer, balance_model
    from sim.virtual_robot import ImuProbe

    scene = Scene()
    m, d, r = scene.model, scene.data, scene.robot
    stab = Stabilizer(balance_model(scene=scene))
    imu = ImuProbe(m, r.root_body).read(d)
    q0 = scene.stand_ctrl.copy()
    refs = q0 + 0.02 * np.sin(np.arange(ticks)[:, None] * 0.05 + np.arange(r.n)[None, :])
    pos = d.qpos[r.qpos_adr].copy()
    t0 = time.process_time()
    for q in refs:
        stab.step(q, pos, imu, 0.01)
    stab_us = (time.process_time() - t0) / ticks * 1e6
    lim = JointLimits(r.joint_names, r.lower, r.upper, np.full(r.n, 4.0), np.full(r.n, 100.0))
    safety = SafetyFilter(lim, 0.01)
    safety.reset(q0)
    t0 = time.process_time()
    for q in refs:
        safety.step(q)
    safety_us = (time.process_time() - t0) / ticks * 1e6
    return stab_us, safety_us


def stepping(kinds: list[str], gains) -> tuple[int, int, int, int]:
    """(clips, clips without a fall, the feet's lift-offs, planned steps) of the op3 on the
    stepping leaders ``kinds`` ("leaders", "quick"), streamed and checked as ``check`` does with
    stabilizer ``gains``."""
    import numpy as np

    from bench.stepping_leaders import leaders, quick_leaders
    from retarget.schedule import count_steps
    from retarget.streaming import StreamingConfig, StreamingRetargeter
    from ros_free_bridge.robots import bridge_check_config, planning_robot
    from sim.check import check_trajectory, lift_offs

    clips = (leaders() if "leaders" in kinds else []) + (quick_leaders() if "quick" in kinds else [])
    rb = planning_robot("op3")
    config = bridge_check_config("op3", mode="free", stabilizer_gains=gains)
    streamer = StreamingRetargeter(rb, 30.0, StreamingConfig(balance=True, steps=True))  # run() resets it
    up = lifts = planned = 0
    for motion in clips:
        traj = streamer.run(motion)
        res = check_trajectory(traj, config, robot="op3")
        up += bool(res.passed or res.reason != "fall")
        lifts += lift_offs(res.metrics)
        planned += count_steps(np.asarray(traj.meta["contacts"], bool))
    return len(clips), up, lifts, planned


def _stepping_rows(kinds: list[str]) -> list[Row]:
    from sim.stabilizer import StabilizerGains

    n, up, lifts, planned = stepping(kinds, None)
    n0, up0, lifts0, planned0 = stepping(kinds, StabilizerGains(two_feet_roll=1.0))
    per, per0 = lifts / max(planned, 1), lifts0 / max(planned0, 1)
    clips = ",".join(kinds)
    print(f"  stepping clips ({clips}): {up}/{n} without a fall, {lifts} lift-offs for {planned} planned steps")
    print(f"    baseline, the roll feedback kept on two feet: {up0}/{n0}, {lifts0} lift-offs for {planned0}")
    what = f"op3, {n} streamed stepping leaders ({clips}), as check plays them; baseline: two_feet_roll=1"
    return [
        Row(f"clips without a fall, {what}", up, up0, ">= baseline", verdict(up >= up0)),
        Row(
            f"feet's lift-offs per planned step, {what}",
            round(per, 3),
            round(per0, 3),
            "<= baseline",
            verdict(per <= per0),
        ),
    ]


def rows(quick: bool = False, argv: list[str] = ()) -> list[Row]:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--max-force", type=float, default=60.0, help="largest push tried, N (default 60)")
    ap.add_argument("--ticks", type=int, default=20000, help="ticks timed for the per-tick cost (default 20000)")
    ap.add_argument(
        "--stepping-clips", default="leaders,quick", help="stepping leaders checked: leaders, quick, both or none"
    )
    args = parse_args(ap, argv, quick, QUICK)
    import sim  # noqa: F401  (MUJOCO_GL before mujoco loads)
    from sim.scene import Scene

    scene = Scene()
    out = []
    for duration in (0.2, 2.5):
        for name, axis, sign in (
            ("sideways, to the left (+y)", 1, 1.0),
            ("sideways, to the right (-y)", 1, -1.0),
            ("forward (+x)", 0, 1.0),
            ("backward (-x)", 0, -1.0),
        ):
            on = largest_push(scene, axis, sign, True, args.max_force, duration=duration)
            off = largest_push(scene, axis, sign, False, args.max_force, duration=duration)
            print(
                f"  push {duration:g} s {name:28s} survived up to {on:5.1f} N with the stabilizer, {off:5.1f} N without"
            )
            out.append(
                Row(
                    f"largest push survived, {duration:g} s at the torso CoM, {name}, standing op3 (N; "
                    "baseline: no stabilizer)",
                    on,
                    off,
                    ">= baseline",
                    verdict(on >= off),
                )
            )
    kinds = [k for k in args.stepping_clips.split(",") if k in ("leaders", "quick")]
    if kinds:
        out += _stepping_rows(kinds)
    stab_us, safety_us = tick_cost_us(args.ticks)
    print(f"  Stabilizer.step {stab_us:.1f} us per tick (safety filter step {safety_us:.1f} us)")
    out.append(
        Row(
            "stabilizer cost per control tick, op3 (CPU us; baseline: the safety filter's step)",
            stab_us,
            safety_us,
            f"<= {COST_BUDGET_US:g}",
            verdict(stab_us <= COST_BUDGET_US),
        )
    )
    return out


def main(argv: list[str] | None = None) -> int:
    return script_main(rows, argv)


if __name__ == "__main__":
    raise SystemExit(main())

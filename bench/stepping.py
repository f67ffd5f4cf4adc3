"""Stepping, tracking and balance of the retargeted robot, next to the behaviour before stepping.

    python bench/stepping.py [--robot op3] [--clips leaders,quick,gestures,cmu,duets] [--physics] [--quick]

Clips: ``leaders``: the SYNTHETIC stepping leaders of bench/stepping_leaders.py (turning in place
2-2.5 turns, walking straight and on a circle, side-stepping); ``pivot``: the rest pose turning
2.5 turns on the spot at 0.8 and 0.5 rad/s without stepping (the root-yaw verdict's case);
``quick``: leaders stepping at a dance's pace, 2 to 2.7 steps a second
(bench/stepping_leaders.quick_leaders); ``gestures``: everyday gestures standing still (bow, hand
over, high fives, handshake, side lean, wave; bench/gestures.py); ``heldout``: other stepping leaders
(bench/stepping_leaders.held_out_leaders) and eight other generated duets (mirror, follow,
hand_hold, orbit; seeds 2 and 3), to check the rules on clips they were not tuned on; ``cmu``: the CMU two-person pair
(../shared/data/mocap/cmu, both people, when present); ``duets``: the rule followers of
dualflow.synthetic.make_duet (generated partners, hand_hold and orbit); ``partners``: the bundled
DualFlow model's partners to four synthetic leaders, two seeds each, streamed and cleaned as the
demo does (bench/partner_clips.py; opt-in: the run with --physics took 41 s on 2 cores). Each clip goes through four
retargeters in the same run, on one core (sched_setaffinity, single-threaded BLAS), CPU time:

- offline (OfflineConfig(balance=True, zmp=True), as retarget-check runs it; engine "auto": on a
  free-standing robot the step planner of retarget.planned, the streaming solver over the whole
  clip seeing the person's contacts 0.1 s early). Its baseline, *offline ipopt*
  (``engine="ipopt"``, the default before): the window optimisation with the robot's own contact
  schedule (retarget.schedule), per-window warm starts, the lead-in (``OfflineConfig.lead_in``:
  a clip that starts mid-motion is started from the robot's standing stance at rest by
  retarget.lead_in) and the swing clearance (``StepConfig(swing_clearance=0.02)``); its figures
  are over the clip's frames (after the lead-in), physics failure times in clip time. *offline
  before* (``--modes offline-before``): the window optimisation with the person's contacts held as
  they are and one streamed warm start for the whole clip, without a lead-in (the code before the
  stepping work);
- *offline without the lead-in* (``--modes offline,offline-no-lead-in``, then *offline*'s
  baseline): the window optimisation with ``lead_in=None`` and ``StepConfig(swing_clearance=0.0)`` (the defaults
  before both were switched on);
- *offline previous* (``--modes offline-prev``): the same with every change of the physics
  root-cause work off (the lead-in too): the cart-table ZMP (one point mass at the CoM), no
  CoM-over-the-stance-foot rows in single support, and a schedule without the robot's pace,
  standing start, swing clearance, start from rest and eased travel (StepConfig(min_double=0,
  start_double=0, robot_swing=0, swing_clearance=0, standing_start=False, start_ramp=0,
  travel_zmp_shift=0));
- streaming with steps (StreamingConfig(balance=True, steps=True), the default: steps at the
  robot's pace, quickened to the person's, with a planned weight shift, retarget.balance); its
  baseline, *streaming before*: StreamingConfig(balance=True, steps=False) (feet always planted);
- *offline fixed pace* and *streaming fixed pace* (``--modes``; each, when run, is its mode's
  baseline): the planner and the streamer at the robot's configured pace only
  (``StreamingConfig(pace_floor=1.0)``, the default before the pace followed the person's).

Figures per retargeter, over the clips (a failed retarget counts as not performed):

- steps: touch-downs of the robot's feet (a sole's highest corner below 2 mm after being above
  it for 2+ frames) against the person's (rising edges of their foot contacts); target within 20 %;
- pelvis-relative keypoint error: mean ‖(p_k − p_root) − (t_k − t_root)‖ as a share of the
  robot's standing height (target ≤ 8 %);
- jerk ratio (retarget.report), target ≤ 1.0 on clean capture (the CMU pair);
- kinematic ZMP: share of frames whose cart-table ZMP of the robot's multibody CoM,
  z = c_xy − (c_z / g) c̈_xy, lies inside the support polygon of the feet on the ground (the
  level footprints), and inside it with 1 cm to spare;
- frames/s (CPU, one core);
- with ``--physics``: sim's free-standing check as ``dualflow-bridge check`` runs it (with
  sim's balance stabilizer where sim has it on by default, and each command through the
  bridge's safety filter for the robot): clips passed, first failure of each,
  and the lift-offs: how often a foot really left the floor in physics (sim's stances per foot,
  less one), next to the person's steps (a reference step can be a shuffle on the servos).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.retarget_speed import Clock, load_clips  # noqa: E402
from bench.stepping_leaders import leaders  # noqa: E402
from bench.table import Row, parse_args, script_main, verdict  # noqa: E402
from retarget.errors import RetargetError  # noqa: E402
from retarget.offline import OfflineConfig, OfflineRetargeter, _Infeasible, feet_apart  # noqa: E402
from retarget.planned import planned_trajectory  # noqa: E402
from retarget.report import clip_targets, evaluate  # noqa: E402
from retarget.robot import robot_ref  # noqa: E402
from retarget.schedule import StepConfig, count_steps  # noqa: E402
from retarget.streaming import StreamingConfig, StreamingRetargeter, trajectory_from_x  # noqa: E402
from retarget.support import com_margins  # noqa: E402
from retarget.targets import make_targets  # noqa: E402
from ros_free_bridge.robots import planning_robot  # noqa: E402

QUICK = ["--clips", "leaders", "--max-clips", "2"]
GRAVITY = 9.81


def steps_match(robot: int, person: int) -> bool:
    """The robot's step count within 20 % of the person's. A person who stands still is
    matched by a robot that does too (0 against 0), where a ratio would read 0 % of them."""
    return abs(robot - person) <= 0.2 * person


def robot_steps(rb, X: np.ndarray, fps: float) -> tuple[int, np.ndarray]:
    """Touch-downs of the robot's feet in configurations X (T, nx) and the feet on the ground (T, 2)."""
    sole = rb.evaluate(X)["sole"][..., 2]  # (T, 8)
    down = np.stack([sole[:, 0:4].max(axis=1) < 0.002, sole[:, 4:8].max(axis=1) < 0.002], axis=1)
    # debounce: an up phase shorter than 2 frames is still the same stance
    for s in range(2):
        c = down[:, s]
        t = 1
        while t < len(c):
            if not c[t] and c[t - 1]:
                e = t
                while e < len(c) and not c[e]:
                    e += 1
                if e - t < 2 and e < len(c):
                    c[t:e] = True
                t = e
            else:
                t += 1
    return count_steps(down), down


#: the offline mode's baseline: the first of these that ran (the streaming mode's likewise)
OFFLINE_BASELINES = ("offline-fixed-pace", "offline-ipopt", "offline-no-lead-in", "offline-prev", "offline-before")
STREAMING_BASELINES = ("streaming-fixed-pace", "streaming-before")


def zmp_shares(rb, X: np.ndarray, down: np.ndarray, fps: float) -> tuple[float, float]:
    """Shares of frames (with a foot down) whose cart-table ZMP is inside the support polygon, and with
    1 cm to spare."""
    ev = rb.evaluate(X)
    c = ev["com"]
    acc = np.zeros_like(c[:, 0:2])
    acc[1:-1] = (c[2:, 0:2] - 2 * c[1:-1, 0:2] + c[:-2, 0:2]) * fps**2
    z = c[:, 0:2] - (c[:, 2:3] / GRAVITY) * acc
    m = com_margins(z, ev["sole"], [f.corners for f in rb.feet], down)
    ok = np.isfinite(m)
    return float(np.mean(m[ok] >= 0)), float(np.mean(m[ok] >= 0.01))


def pelvis_relative_error(rb, X: np.ndarray, keypoints: np.ndarray) -> float:
    """Mean ‖(p_k − p_root) − (t_k − t_root)‖ (m) over frames and keypoints."""
    kp = rb.evaluate(X)["keypoints"]
    r = rb.root_keypoint
    return float(np.mean(np.linalg.norm((kp - kp[:, r : r + 1]) - (keypoints - keypoints[:, r : r + 1]), axis=-1)))


def offline_before(off: OfflineRetargeter, rb, motion, tg):
    """The offline retargeter as it was: the person's contacts, one streamed warm start for the clip."""
    stream = StreamingRetargeter(rb, motion.fps, off.streaming_config)
    ws = feet_apart(rb, tg.keypoints, 0.02)
    X0 = np.stack([stream.step(ws[t], tg.contacts[t]) for t in range(motion.n_frames)])
    X, _ = off.solve(tg, X0)
    return X


def rows(quick: bool = False, argv: list[str] = ()) -> list[Row]:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--robot", default="op3")
    ap.add_argument("--clips", default="leaders,quick,gestures,cmu,duets")
    ap.add_argument("--max-clips", type=int, default=0, help="at most this many clips (0: all)")
    ap.add_argument("--physics", action="store_true", help="also run sim's free-standing check")
    ap.add_argument("--modes", default="offline,offline-ipopt,streaming,streaming-before")
    args = parse_args(ap, argv, quick, QUICK)
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
    rb = planning_robot(args.robot)  # within the loop's limits, as retarget-check plans
    ref = robot_ref(args.robot)  # the check finds a robot folder again by it, a bundled robot by name
    clips, clean = [], set()
    kinds = args.clips.split(",")
    if "leaders" in kinds:
        clips += leaders()
    if "gestures" in kinds:
        from bench.gestures import gestures

        clips += gestures()
    if "quick" in kinds:
        from bench.stepping_leaders import quick_leaders

        clips += quick_leaders()
    if "pivot" in kinds:
        from bench.stepping_leaders import pivot_turn

        clips += [pivot_turn(0.8, 2.5), pivot_turn(0.5, 2.5)]
    if "cmu" in kinds:
        cmu = load_clips("cmu", 20.0)
        if cmu[0].name.startswith("cmu"):
            clips += cmu
            clean |= {c.name for c in cmu}
    if "heldout" in kinds:  # other leaders and duet seeds than the figures' (see held_out_leaders)
        from bench.stepping_leaders import held_out_leaders
        from dualflow.synthetic import make_duet

        clips += held_out_leaders()
        clips += [
            make_duet(r, seconds=10.0, fps=30.0, seed=seed).reactor.replace(name=f"duet_{r}_{seed}")
            for r in ("mirror", "follow", "hand_hold", "orbit")
            for seed in (2, 3)
        ]
    if "partners" in kinds:  # generated by the bundled model as the demo makes them
        from bench.partner_clips import demo_partners

        clips += demo_partners()
    if "duets" in kinds:
        from dualflow.synthetic import make_duet

        clips += [
            make_duet(r, seconds=10.0, fps=30.0, seed=1).reactor.replace(name=f"duet_{r}")
            for r in ("hand_hold", "orbit")
        ]
    if args.max_clips:
        clips = clips[: args.max_clips]
    height = float(rb.evaluate(rb.x_stand[None])["keypoints"][0][:, 2].max())
    print(f"robot {rb.name} (height {height:.3f} m), {len(clips)} clips, load {os.getloadavg()[0]:.2f}")
    off = OfflineRetargeter(rb, OfflineConfig(balance=True, zmp=True))
    off_ipopt = OfflineRetargeter(rb, OfflineConfig(balance=True, zmp=True, engine="ipopt"))
    off_plain = OfflineRetargeter(
        rb, OfflineConfig(balance=True, zmp=True, lead_in=None, steps=StepConfig(swing_clearance=0.0), engine="ipopt")
    )
    prev = StepConfig(
        min_double=0.0,
        start_double=0.0,
        robot_swing=0.0,
        swing_clearance=0.0,
        standing_start=False,
        start_ramp=0.0,
        travel_zmp_shift=0.0,
    )
    off_prev = OfflineRetargeter(
        rb,
        OfflineConfig(
            balance=True,
            zmp=True,
            zmp_model="cart-table",
            single_support_com=False,
            steps=prev,
            lead_in=None,
            engine="ipopt",
        ),
    )
    st_new = StreamingRetargeter(rb, 30.0, StreamingConfig(balance=True, steps=True))
    st_old = StreamingRetargeter(rb, 30.0, StreamingConfig(balance=True, steps=False))
    st_fixed = StreamingRetargeter(rb, 30.0, StreamingConfig(balance=True, steps=True, pace_floor=1.0))
    modes = args.modes.split(",")
    stats = {
        m: {
            "frames": 0,
            "cpu": 0.0,
            "steps": 0,
            "person": 0,
            "err": [],
            "jerk": [],
            "zmp": [],
            "zmp1": [],
            "done": 0,
            "phys": [],
            "lift_offs": 0,
            "phys_counts": [],  # (robot steps in physics by the person's rule, person steps) per clip checked
            "step_counts": [],  # (robot, person) per clip
        }
        for m in modes
    }
    for motion in clips:
        tg = make_targets(rb, motion)
        person = count_steps(tg.contacts)
        for mode in modes:
            s = stats[mode]
            X, note = None, ""
            try:
                with Clock() as ck:
                    if mode == "offline":
                        traj = off.retarget(motion)
                    elif mode == "offline-ipopt":
                        traj = off_ipopt.retarget(motion)
                    elif mode == "offline-no-lead-in":
                        traj = off_plain.retarget(motion)
                    elif mode == "offline-prev":
                        traj = off_prev.retarget(motion)
                    elif mode == "offline-before":
                        traj = trajectory_from_x(
                            rb, offline_before(off, rb, motion, tg), motion.fps, {"mode": "offline"}
                        )
                    elif mode == "offline-fixed-pace":
                        traj = planned_trajectory(st_fixed, motion)
                    else:
                        traj = {"streaming": st_new, "streaming-fixed-pace": st_fixed}.get(mode, st_old).run(motion)
            except (RetargetError, _Infeasible) as exc:  # _Infeasible: the old solve() raises it bare
                note = f"retarget failed: {str(exc)[:110]}"
                traj = None
            if traj is not None:
                from retarget.report import configurations

                X = configurations(rb, traj)
                tk, _, clip_t = clip_targets(traj, tg)  # the clip's frames (after a lead-in) and targets there
                X, tk = X[clip_t >= -1e-9], tk[clip_t >= -1e-9]
                s["frames"] += traj.n_frames
                s["cpu"] += ck.cpu
                s["done"] += 1
                n, down = robot_steps(rb, X, motion.fps)
                s["steps"] += n
                s["person"] += person
                s["step_counts"].append((n, person))
                s["err"].append(pelvis_relative_error(rb, X, tk) / height)
                rep = evaluate(rb, traj, tg)
                if motion.name in clean and rep.jerk_ratio is not None:
                    s["jerk"].append(rep.jerk_ratio)
                z0, z1 = zmp_shares(rb, X, down, motion.fps)
                s["zmp"].append(z0)
                s["zmp1"].append(z1)
                note = (
                    f"steps {n}/{person}, err {100 * s['err'][-1]:.1f} %, jerk {rep.jerk_ratio or 0:.2f}, "
                    f"zmp in {100 * z0:.0f} %"
                )
                if args.physics:
                    from ros_free_bridge.robots import bridge_check_config
                    from sim.check import check_trajectory, lift_offs, steps_taken

                    res = check_trajectory(traj, bridge_check_config(ref, mode="free"), robot=ref)
                    s["phys"].append(res.passed)
                    lifts, taken = lift_offs(res.metrics), steps_taken(res.metrics)
                    s["lift_offs"] += lifts
                    s["phys_counts"].append((taken, person))
                    t0 = float(traj.meta.get("t0_s", 0.0))  # the lead-in's length (the check's times are clip times)
                    after = f"{res.first_failure_time:.2f} s after the clip's start" if not res.passed else ""
                    note += ", physics " + ("pass" if res.passed else f"{res.reason} at {after}")
                    note += f", {taken} steps ({lifts} lift-offs)"
                    if t0:
                        note += f" (lead-in {t0:.2f} s)"
            elif args.physics:
                s["phys"].append(False)
            print(f"  {motion.name:34s} {mode:17s} {note}", flush=True)
    out = []
    for mode in modes:
        s = stats[mode]
        base = {
            "offline": next((m for m in OFFLINE_BASELINES if m in stats), None),
            "streaming": next((m for m in STREAMING_BASELINES if m in stats), None),
        }.get(mode)
        b = stats.get(base) if base else None

        def fig(key, fn, mode=mode, b=b):
            v = fn(stats[mode][key]) if stats[mode][key] else float("nan")
            return v, (fn(b[key]) if b and b[key] else "")

        mean = lambda a: float(np.mean(a))  # noqa: E731
        label = f"{mode}"
        out.append(
            Row(
                f"{label}: clips retargeted / all",
                f"{s['done']}/{len(clips)}",
                f"{b['done']}/{len(clips)}" if b else "",
            )
        )
        v, bv = fig("step_counts", lambda a: float(np.mean([steps_match(n, p) for n, p in a])))
        out.append(
            Row(
                f"{label}: share of clips with robot steps within 20 % of the person's",
                v,
                bv,
                "1.0",
                verdict(v >= 1.0) if mode in ("offline", "streaming") else "n/a",
            )
        )
        out.append(
            Row(
                f"{label}: robot steps / person steps (all clips)",
                f"{s['steps']}/{s['person']}",
                f"{b['steps']}/{b['person']}" if b else "",
            )
        )
        v, bv = fig("err", mean)
        out.append(
            Row(
                f"{label}: pelvis-relative keypoint error (% of robot height)",
                100 * v,
                100 * bv if bv != "" else "",
                "<= 8",
                verdict(v <= 0.08),
            )
        )
        if stats[mode]["jerk"]:
            v, bv = fig("jerk", max)
            out.append(Row(f"{label}: jerk ratio, clean capture (worst clip)", v, bv, "<= 1.0", verdict(v <= 1.0)))
        v, bv = fig("zmp", mean)
        out.append(
            Row(
                f"{label}: kinematic ZMP inside the support polygon (% of frames)",
                100 * v,
                100 * bv if bv != "" else "",
            )
        )
        v, bv = fig("zmp1", mean)
        out.append(Row(f"{label}: ... with 1 cm to spare (% of frames)", 100 * v, 100 * bv if bv != "" else ""))
        fps = s["frames"] / s["cpu"] if s["cpu"] else float("nan")
        bfps = b["frames"] / b["cpu"] if b and b["cpu"] else ""
        tgt = ">= 1000" if mode == "streaming" else ""
        out.append(
            Row(
                f"{label}: frames/s (CPU, 1 core)",
                fps,
                bfps,
                tgt,
                verdict(fps >= 1000) if mode == "streaming" else "n/a",
            )
        )
        if args.physics:
            v, bv = fig("phys", lambda a: float(np.mean(a)))
            out.append(Row(f"{label}: share of clips passing sim's free check (as `check` runs it)", v, bv))
            out.append(
                Row(
                    f"{label}: feet lifted off the floor in physics / person steps (sim's stances; a step "
                    "the reference takes may be a shuffle)",
                    f"{s['lift_offs']}/{s['person']}",
                    f"{b['lift_offs']}/{b['person']}" if b else "",
                )
            )
            within = [steps_match(r, p) for r, p in s["phys_counts"]]
            b_within = [steps_match(r, p) for r, p in b["phys_counts"]] if b else []
            out.append(
                Row(
                    f"{label}: robot steps in physics (counted by the person's rule, scaled: "
                    "sim.check.steps_as_a_person) / person steps; clips within 20 %",
                    f"{sum(r for r, _ in s['phys_counts'])}/{s['person']}; {sum(within)} of {len(within)}",
                    f"{sum(r for r, _ in b['phys_counts'])}/{b['person']}; {sum(b_within)} of {len(b_within)}"
                    if b
                    else "",
                )
            )
    return out


def main(argv: list[str] | None = None) -> int:
    return script_main(rows, argv)


if __name__ == "__main__":
    raise SystemExit(main())

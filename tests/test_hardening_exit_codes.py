"""The exit-code contract, through the command line: 0 a normal end (and a passed check),
1 a fault, e-stop, watchdog stop or failed verdict, 2 bad usage or bad input (one line).
Faults are injected into the real processes a run starts: the bus emulator is killed (the
port vanishes), the generator process is killed (it crashes)."""

from __future__ import annotations

import multiprocessing
import os
import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from ros_free_bridge.cli import EXIT_CODES, build_parser, main
from ros_free_bridge.control.loop import ControlLoop, Fault, LoopConfig
from ros_free_bridge.control.safety import JointLimits
from ros_free_bridge.control.targets import TargetBuffer, TargetFrame
from ros_free_bridge.telemetry.log import read_telemetry
from ros_free_bridge.transports.record import RecordTransport

os.environ.setdefault("MUJOCO_GL", "egl")


def _when_streaming(out: Path, action) -> threading.Thread:
    """Run ``action()`` in a thread once the run in ``out`` streams (bounded wait)."""

    def wait():
        events = out / "telemetry.dftl.events.jsonl"
        end = time.monotonic() + 120
        while time.monotonic() < end:
            if events.exists() and '"kind": "streaming"' in events.read_text():
                time.sleep(0.3)
                action()
                return
            time.sleep(0.05)

    t = threading.Thread(target=wait, daemon=True)
    t.start()
    return t


def _end(out: Path) -> dict:
    (end,) = [e for e in read_telemetry(out / "telemetry.dftl").events if e["kind"] == "end"]
    return end


def test_a_normal_end_exits_0_and_a_vanished_bus_exits_1(tmp_path, capsys):
    out = tmp_path / "normal"
    assert (
        main(
            [
                "run",
                "--partner",
                "imitate",
                "--transport",
                "record",
                "--robot",
                "ub14",
                "--seconds",
                "1",
                "--quiet",
                "-o",
                str(out),
            ]
        )
        == 0
    )
    assert _end(out)["reason"] == "the motion ended"

    out = tmp_path / "vanish"

    def kill_the_bus():  # the emulator is a child process of this one: the port disappears
        for child in multiprocessing.active_children():
            os.kill(child.pid, signal.SIGKILL)

    _when_streaming(out, kill_the_bus)
    code = main(
        [
            "run",
            "--partner",
            "imitate",
            "--transport",
            "dynamixel",
            "--emulate",
            "--seconds",
            "20",
            "--quiet",
            "-o",
            str(out),
        ]
    )
    assert code == 1, capsys.readouterr().err[-2000:]
    end = _end(out)
    assert end["state"] == "ESTOP" and end["reason"].startswith("bus error")
    assert end["summary"]["faults"] & Fault.BUS_ERROR


def test_a_crashed_generator_exits_1(tmp_path, tiny_checkpoint, capsys):
    out = tmp_path / "crash"

    def kill_the_generator():
        for stat in Path("/proc").glob("[0-9]*/cmdline"):
            try:
                cmd = stat.read_bytes()
                if b"ros_free_bridge.partner.child" in cmd and f"--parent\0{os.getpid()}\0".encode() in cmd:
                    os.kill(int(stat.parent.name), signal.SIGKILL)
            except OSError:
                pass

    _when_streaming(out, kill_the_generator)
    code = main(
        [
            "run",
            "--generator",
            "process",
            "--model",
            str(tiny_checkpoint),
            "--transport",
            "record",
            "--robot",
            "ub14",
            "--seconds",
            "30",
            "--quiet",
            "-o",
            str(out),
        ]
    )
    assert code == 1, capsys.readouterr().err[-2000:]
    end = _end(out)
    assert "generator" in end["reason"] and end["summary"]["fault_stop"]


def test_a_watchdog_stop_is_not_a_normal_end(tmp_path):
    names = ("a", "b")
    limits = JointLimits(names, [-1.0] * 2, [1.0] * 2, [4.0] * 2, [50.0] * 2)
    buf = TargetBuffer(30.0)
    for k in range(10):  # then the generator goes quiet, the stream still open
        buf.push(TargetFrame(k, np.zeros(2), time.monotonic()))
    loop = ControlLoop(
        RecordTransport(names),
        limits,
        buf,
        LoopConfig(rate_hz=100.0, min_ramp=0.1, rest_after=0.3, handle_signals=False),
    )
    s = loop.run()
    assert s.end_state == "STOPPED" and "no new frames" in s.reason and s.fault_stop and not s.ok


def test_a_failed_physics_check_exits_1_and_bad_input_exits_2(tmp_path, capsys):
    from retarget.robot import load_robot
    from retarget.trajectory import RobotTrajectory
    from ros_free_bridge.robots import resolve_robot

    files = resolve_robot("ub14")
    robot = load_robot(files.mjcf, files.profile)
    pose = np.asarray(robot.x_stand)[robot.n_root :].copy()
    traj = RobotTrajectory.standing(robot.joint_names, pose, 30, 30.0, np.asarray(robot.x_stand)[:3], "ub14")
    q = np.array(traj.joint_pos)
    q[10:, 0] = robot.x_upper[robot.n_root] + 1.0  # beyond its joint limit: a verdict, not bad input
    bad = RobotTrajectory(traj.joint_names, q, traj.root_pos, traj.root_quat, traj.fps, "ub14")
    path = bad.save_npz(tmp_path / "beyond.npz")
    assert main(["check", str(path), "--robot", "ub14", "--no-plots", "-o", str(tmp_path / "c")]) == 1
    assert "FAIL" in capsys.readouterr().out

    assert (
        main(
            [
                "run",
                "--transport",
                "dynamixel",
                "--port",
                str(tmp_path / "no-such-port"),
                "--partner",
                "imitate",
                "--quiet",
                "-o",
                str(tmp_path / "r"),
            ]
        )
        == 2
    )
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("error")]
    assert len(err) == 1 and "no-such-port" in err[0]
    with pytest.raises(SystemExit) as exc:
        main(["run", "--transport", "teleport"])
    assert exc.value.code == 2


def test_every_command_states_the_exit_codes_in_its_help():
    def leaves(parser):
        subs = [a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction"]
        if not subs:
            yield parser
        for action in subs:
            for sub in action.choices.values():
                yield from leaves(sub)

    parsers = list(leaves(build_parser()))
    assert len(parsers) > 20
    for p in parsers:
        text = "".join(p.format_help().split())  # wrapped anyhow: compare without whitespace
        assert "".join(EXIT_CODES.split()) in text, p.prog

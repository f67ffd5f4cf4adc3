"""``replay`` plays every command of a good telemetry file, whatever the machine's load: the
recorded stream is complete from the start, so the loop's "no new frames" watchdog (meant
for live streams) never fires, and it advances one command per executed tick, so a late or
skipped tick delays the rest instead of dropping commands."""

from __future__ import annotations

import threading
import time

import numpy as np

from ros_free_bridge.cli import main
from ros_free_bridge.control.loop import ControlLoop, LoopConfig
from ros_free_bridge.control.safety import JointLimits
from ros_free_bridge.control.targets import TargetBuffer, TargetFrame
from ros_free_bridge.telemetry.log import TelemetryWriter
from ros_free_bridge.transports.record import RecordTransport


def _commands(n: int, joints: int) -> np.ndarray:
    t = np.arange(n)[:, None] / n
    return 0.3 * np.sin(2 * np.pi * t * (1 + np.arange(joints)[None] / joints))


class Load:
    """Python threads that keep the GIL busy, as a busy bridge process does."""

    def __init__(self, n: int = 3):
        self.stop = threading.Event()
        self.threads = [threading.Thread(target=self._spin, daemon=True) for _ in range(n)]

    def _spin(self):
        x = 0
        while not self.stop.is_set():
            for k in range(20000):
                x += k * k

    def __enter__(self):
        for t in self.threads:
            t.start()
        return self

    def __exit__(self, *exc):
        self.stop.set()
        for t in self.threads:
            t.join()


def test_every_command_is_played_in_order_under_load():
    names = ("a", "b", "c")
    limits = JointLimits(names, [-1.0] * 3, [1.0] * 3, [20.0] * 3, [400.0] * 3)
    q = _commands(1034, 3)
    buf = TargetBuffer(200.0, capacity=len(q) + 1)
    now = time.monotonic()
    for k, row in enumerate(q):
        buf.push(TargetFrame(k, row, now))
    buf.close()
    tr = RecordTransport(names)
    loop = ControlLoop(
        tr, limits, buf, LoopConfig(rate_hz=200.0, rest_pose=q[0], pace="ticks", min_ramp=0.2, handle_signals=False)
    )
    with Load():
        summary = loop.run()
    assert summary.ok and summary.reason == "the motion ended"
    assert summary.frames_played == len(q)
    sent = np.asarray(tr.commands)
    # the streamed part of what was sent is the recording itself, command for command
    start = int(np.argmin(np.abs(sent - q[1]).max(axis=1)))
    np.testing.assert_allclose(sent[start - 1 : start - 1 + len(q)], q, atol=1e-6)


def test_replay_plays_a_long_recording_through_the_cli_under_load(tmp_path, capsys):
    from retarget.robot import load_robot
    from ros_free_bridge.robots import resolve_robot

    files = resolve_robot("ub14")
    robot = load_robot(files.mjcf, files.profile)
    names = list(robot.joint_names)
    stand = np.asarray(robot.x_stand)[robot.n_root :]
    q = stand + 0.1 * _commands(1034, len(names))
    path = tmp_path / "telemetry.dftl"
    with TelemetryWriter(path, names, 250.0, meta={"robot": "ub14"}) as w:
        for k, row in enumerate(q):
            w.record(t=k / 250, tick=k, target=row, command=row, measured=row, state=3)
    with Load():
        code = main(["replay", str(path), "--transport", "record"])
    err = capsys.readouterr().err
    assert code == 0, err
    assert "replayed 1034 of 1034 commands: STOPPED (the motion ended)" in err

"""Processes and signals: the generator and bus-emulator children end with the bridge however
it ends (SIGKILL included), and SIGINT / SIGTERM end a run in the safe state with the signal
as the recorded reason (exit code 1), never a bus error from a read the signal raced."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from ros_free_bridge.control.loop import ControlLoop, Fault, LoopConfig
from ros_free_bridge.control.safety import JointLimits
from ros_free_bridge.control.targets import TargetBuffer, TargetFrame
from ros_free_bridge.errors import BridgeError
from ros_free_bridge.telemetry.log import TelemetryWriter, read_telemetry
from ros_free_bridge.transports.record import RecordTransport

ROOT = Path(__file__).resolve().parents[1]
NAMES = ("a", "b", "c")


class SignalledBus(RecordTransport):
    """A bus whose read, at tick 40, is hit by SIGTERM and then fails (as a bus emulator or
    adapter killed by the same signal makes it fail)."""

    def read_state(self):
        if len(self.commands) == 40:
            os.kill(os.getpid(), signal.SIGTERM)
            raise BridgeError("servo 2: no status packet")
        return super().read_state()


def test_a_signal_that_races_a_failing_bus_read_is_the_recorded_reason(tmp_path):
    limits = JointLimits(NAMES, [-1.0] * 3, [1.0] * 3, [4.0] * 3, [50.0] * 3)
    buf = TargetBuffer(30.0)
    for k in range(300):
        buf.push(TargetFrame(k, np.full(3, 0.2 * np.sin(k / 10)), time.monotonic()))
    tel = TelemetryWriter(tmp_path / "t.dftl", NAMES, 100.0)
    tr = SignalledBus(NAMES)
    loop = ControlLoop(tr, limits, buf, LoopConfig(rate_hz=100.0, min_ramp=0.1, handle_signals=True), tel)
    summary = loop.run()  # the test runs in the main thread: the loop's handlers are installed
    assert summary.end_state == "ESTOP" and summary.reason == "signal SIGTERM" and not summary.ok
    assert tr.stopped_with == "limp"
    events = read_telemetry(tmp_path / "t.dftl").events
    (bus,) = [e for e in events if e["kind"] == "bus_error"]
    assert bus["after_estop"] is True
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL  # restored


def _children(pid: int) -> list[int]:
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            out.append(int(stat.parent.name))
    return out


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"  # a zombie has ended; reaping it is its new parent's business


def _wait(predicate, timeout: float) -> bool:
    """Wait for ``predicate`` up to ``timeout`` s (a bound on waiting, not a timing check)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(0.05)
    return predicate()


def _start_run(out: Path, *extra: str) -> subprocess.Popen:
    env = dict(os.environ, MUJOCO_GL="egl", PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "ros_free_bridge",
            "run",
            "--actor",
            "synthetic",
            "--seconds",
            "60",
            "--quiet",
            "-o",
            str(out),
            *extra,
        ],
        cwd=ROOT,
        env=env,
        start_new_session=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def _wait_streaming(proc: subprocess.Popen, out: Path) -> None:
    events = out / "telemetry.dftl.events.jsonl"
    ok = _wait(
        lambda: proc.poll() is not None or (events.exists() and '"kind": "streaming"' in events.read_text()), 120
    )
    if proc.poll() is not None or not ok:
        proc.kill()
        pytest.fail("the run did not start streaming: " + proc.communicate()[1][-2000:])


@pytest.mark.parametrize("sig, group", [(signal.SIGTERM, False), (signal.SIGINT, True)])
def test_sigterm_and_a_ctrl_c_to_the_group_end_in_the_safe_state_with_the_signal_as_reason(
    tmp_path, tiny_checkpoint, sig, group
):
    out = tmp_path / "run"
    # the generator in its process and the bus emulator in its own: a Ctrl-C reaches all three
    proc = _start_run(
        out, "--transport", "dynamixel", "--emulate", "--generator", "process", "--model", str(tiny_checkpoint)
    )
    _wait_streaming(proc, out)
    children = _children(proc.pid)
    assert len(children) >= 2  # generator and emulator
    if group:
        os.killpg(proc.pid, sig)  # what a terminal's Ctrl-C does
    else:
        os.kill(proc.pid, sig)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 1, err[-2000:]
    (end,) = [e for e in read_telemetry(out / "telemetry.dftl").events if e["kind"] == "end"]
    assert end["state"] == "ESTOP" and end["reason"] == f"signal {sig.name}"
    assert not end["summary"]["faults"] & Fault.BUS_ERROR
    assert _wait(lambda: not any(_alive(c) for c in children), 30)


def test_the_children_die_with_a_killed_parent(tmp_path, tiny_checkpoint):
    out = tmp_path / "run"
    proc = _start_run(
        out, "--transport", "dynamixel", "--emulate", "--generator", "process", "--model", str(tiny_checkpoint)
    )
    _wait_streaming(proc, out)
    children = _children(proc.pid)
    assert len(children) >= 2
    os.kill(proc.pid, signal.SIGKILL)  # runs no code of ours: no finally, no atexit
    proc.communicate(timeout=60)
    assert _wait(lambda: not any(_alive(c) for c in children), 30), [
        Path(f"/proc/{c}/cmdline").read_bytes()[:120] for c in children if _alive(c)
    ]

"""``run --realtime-priority``: the loop asks for SCHED_FIFO and says in telemetry what it got."""

import os

import pytest

from dualflow.motion.io import save_motion
from dualflow.synthetic import make_leader
from ros_free_bridge.cli import main
from ros_free_bridge.telemetry.log import read_telemetry


def test_run_passes_the_priority_to_the_loop_and_logs_the_outcome(tmp_path):
    clip = tmp_path / "actor.npz"
    save_motion(make_leader(1.0, 30.0, seed=2), clip)
    out = tmp_path / "run"
    rc = main(
        [
            "run",
            "--actor",
            str(clip),
            "--partner",
            "imitate",
            "--transport",
            "record",
            "--quiet",
            "--realtime-priority",
            "7",
            "--out",
            str(out),
        ]
    )
    assert rc == 0
    (event,) = [e for e in read_telemetry(out / "telemetry.dftl").events if e["kind"] == "realtime"]
    note = event["scheduling"]
    granted = _can_fifo()
    # either the loop ran at the asked priority, or it says why not and how to fix it
    assert note == "SCHED_FIFO priority 7" if granted else ("not granted" in note or "not available" in note)
    assert os.sched_getscheduler(0) != getattr(os, "SCHED_FIFO", -1)  # restored after the run


def _can_fifo() -> bool:
    try:
        old = os.sched_getscheduler(0), os.sched_getparam(0)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
    except (OSError, AttributeError):
        return False
    os.sched_setscheduler(0, *old)
    return True


@pytest.mark.parametrize("priority", ["-1", "100"])
def test_an_impossible_priority_is_one_clear_error(tmp_path, capsys, priority):
    rc = main(
        [
            "run",
            "--partner",
            "imitate",
            "--transport",
            "record",
            "--quiet",
            "--seconds",
            "1",
            "--realtime-priority",
            priority,
            "--out",
            str(tmp_path / "run"),
        ]
    )
    err = capsys.readouterr().err
    assert rc == 2
    assert "realtime_priority" in err and "1-99" in err

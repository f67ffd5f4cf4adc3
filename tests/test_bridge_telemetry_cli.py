"""plot and replay: figures and a second run from a telemetry file."""

import numpy as np
import pytest

from ros_free_bridge.cli import main
from ros_free_bridge.robots import bridge_limits, resolve_robot
from ros_free_bridge.telemetry.log import TelemetryWriter


@pytest.fixture
def op3_telemetry(tmp_path):
    limits = bridge_limits(resolve_robot("op3").hardware_config())
    path = tmp_path / "run" / "telemetry.dftl"
    with TelemetryWriter(path, limits.names, 100.0, meta={"robot": "op3"}) as w:
        for k in range(60):
            q = 0.3 * np.sin(2 * np.pi * k / 60) * np.ones(limits.n)
            w.record(t=k / 100, tick=k, target=q, command=q, measured=q, state=3)
    return path


def test_plot_writes_three_figures(op3_telemetry, tmp_path, capsys):
    assert main(["plot", str(op3_telemetry), "-o", str(tmp_path / "plots")]) == 0
    pngs = sorted((tmp_path / "plots").glob("*.png"))
    assert [p.name for p in pngs] == ["joints.png", "safety.png", "timing.png"]
    assert all(p.stat().st_size > 10_000 for p in pngs)


def test_replay_drives_a_transport_through_the_loop(op3_telemetry, capsys):
    assert main(["replay", str(op3_telemetry), "--transport", "record"]) == 0
    assert "STOPPED (the motion ended)" in capsys.readouterr().err


def test_replay_needs_something_to_do_and_a_matching_robot(op3_telemetry, tmp_path, capsys):
    assert main(["replay", str(op3_telemetry)]) == 2
    assert "--video" in capsys.readouterr().err
    other = tmp_path / "other.dftl"
    with TelemetryWriter(other, ("a", "b"), 100.0, meta={"robot": "op3"}) as w:
        for k in range(3):
            w.record(t=k / 100, tick=k)
    assert main(["replay", str(other), "--transport", "record"]) == 2
    assert "joints" in capsys.readouterr().err

"""The telemetry file pair (ticks + events) describes one run, even when a folder is reused."""

import numpy as np

from ros_free_bridge.telemetry.log import TelemetryWriter, read_telemetry


def _run(path, n_ticks, stop_reason):
    with TelemetryWriter(path, ["a", "b"], rate_hz=100.0) as tel:
        for k in range(n_ticks):
            tel.record(t=k / 100.0, tick=k, command=np.array([0.1 * k, -0.1 * k]))
        tel.event("stopped", reason=stop_reason)


def test_a_second_run_in_the_same_folder_replaces_both_files(tmp_path):
    path = tmp_path / "telemetry.dftl"
    _run(path, 5, "first run")
    _run(path, 3, "second run")
    tel = read_telemetry(path)
    assert len(tel.records) == 3
    assert [e["reason"] for e in tel.events] == ["second run"]
    np.testing.assert_allclose(tel.records["command"][-1], [0.2, -0.2], atol=1e-6)

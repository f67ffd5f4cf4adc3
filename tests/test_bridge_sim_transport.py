"""The control loop driving the MuJoCo virtual robot through the sim transport."""

import threading
import time

import numpy as np
import pytest

from ros_free_bridge.control.loop import ControlLoop, LoopConfig
from ros_free_bridge.control.targets import TargetBuffer, TargetFrame
from ros_free_bridge.robots import bridge_limits, resolve_robot
from ros_free_bridge.transports.base import Transport
from ros_free_bridge.transports.sim import SimTransport

pytestmark = pytest.mark.slow


def test_loop_moves_the_simulated_robot_and_records_what_it_did():
    limits = bridge_limits(resolve_robot("op3").hardware_config())
    tr = SimTransport("op3", clock="lockstep")
    assert isinstance(tr, Transport)
    buf = TargetBuffer(30.0)
    loop = ControlLoop(tr, limits, buf, LoopConfig(handle_signals=False, min_ramp=0.3))
    # both elbows bend 0.8 rad in towards the body over a second, then hold (upper body only: the
    # robot keeps standing); ROBOTIS's axes: the right elbow bends in with +, the left with -
    el = [limits.names.index("r_el"), limits.names.index("l_el")]
    goal = np.array([0.8, -0.8])

    def produce():
        loop.ready.wait(10)
        base = loop.safety.last_command
        for k in range(45):
            q = base.copy()
            q[el] = base[el] + (goal - base[el]) * min(1.0, k / 30)
            buf.push(TargetFrame(k, q, time.monotonic()))
            time.sleep(1 / 30)
        buf.close()

    threading.Thread(target=produce, daemon=True).start()
    summary = loop.run()
    assert summary.end_state == "STOPPED"
    traj = tr.recorded_trajectory()
    assert traj.joint_names == limits.names and traj.n_frames == summary.ticks + 1
    peak = np.abs(traj.joint_pos[:, el]).max(axis=0)
    np.testing.assert_allclose(peak, 0.8, atol=0.05)  # the servos tracked the command
    assert traj.root_pos[:, 2].min() > 0.2  # still standing: torso well above the floor

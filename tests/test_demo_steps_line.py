"""The demo's steps line: the partner's touch-downs that end a jump are named, because the robot
keeps its feet down through a jump and has no step there to match."""

import numpy as np

from dualflow.motion import Motion
from dualflow.motion.io import save_motion
from ros_free_bridge.commands.demo import jump_landings, steps_line


class _Check:
    metrics = {"stances": [2, 1], "steps": [1, 0]}  # the robot lifted its left foot once, a step


def test_jump_landings_counts_the_touch_downs_that_end_a_jump():
    c = np.array([[1, 1], [1, 0], [0, 0], [0, 0], [1, 1], [1, 1], [0, 1], [1, 1], [0, 0]], bool)
    jumps, landings, airborne = jump_landings(c, 10.0)
    assert (jumps, landings) == (1, 2)  # both feet came down after frames 2-3; the last run never lands
    assert abs(airborne - 0.2) < 1e-9
    assert jump_landings(c[:2], 10.0) == (0, 0, 0)  # no frame with both feet up


def test_the_steps_line_names_the_partners_jump(tmp_path):
    from dualflow.synthetic import make_leader

    leader = make_leader(4.0, 30.0, seed=0)
    still = np.repeat(leader.positions[:1], 60, axis=0)  # standing, both feet down
    hop = still.copy()
    hop[25:35, :, 2] += 0.25  # the whole body 25 cm up for a third of a second, then down
    path = tmp_path / "partner.npz"
    save_motion(Motion(hop, 30.0, name="partner"), path)
    line = steps_line(path, _Check())
    assert "landing from 1 jump" in line and "the robot 1 " in line, line
    save_motion(Motion(still, 30.0, name="partner"), path)
    assert "jump" not in steps_line(path, _Check())


def test_the_steps_line_counts_the_return_to_stance_apart(tmp_path):
    """The robot's steps back to its stance after the stream are not steps matched to the
    partner's: counted apart (the physics check saw 3 lift-offs, 2 of them after the stream)."""
    from dualflow.synthetic import make_leader

    class Three:
        metrics = {"stances": [3, 2], "steps": [2, 1]}

    still = np.repeat(make_leader(1.0, 30.0, seed=0).positions[:1], 30, axis=0)
    path = tmp_path / "partner.npz"
    save_motion(Motion(still, 30.0, name="partner"), path)
    line = steps_line(path, Three(), settle_steps=2)
    assert "the robot 1 " in line and "and 2 returning to its stance after the stream" in line, line
    assert "they left the floor 1 time)" in line, line
    assert "returning" not in steps_line(path, Three())


def test_the_live_robot_line_names_a_fall_the_replayed_check_may_not_see():
    """The demo's video shows the virtual robot that ran live; the check replays the commands in
    its own simulation. A live robot whose torso tips past the check's fall tilt is reported
    (and fails the demo) with the time it happened."""
    from retarget.trajectory import RobotTrajectory
    from ros_free_bridge.commands.demo import live_robot_line

    T, fps = 300, 100.0
    tip = np.radians(np.clip((np.arange(T) - 200) * 1.5, 0.0, 80.0))  # upright, then tipping 1.5 deg a tick
    quat = np.stack([np.cos(tip / 2), np.sin(tip / 2), np.zeros(T), np.zeros(T)], axis=1)  # about x
    fallen = RobotTrajectory(("j",), np.zeros((T, 1)), np.zeros((T, 3)), quat, fps, "op3", {})
    fell, line = live_robot_line(fallen, 50.0)
    assert fell and "FELL at 2.34 s" in line, line  # 51 deg there, 49.5 a tick before
    upright = RobotTrajectory(("j",), np.zeros((231, 1)), np.zeros((231, 3)), quat[:231], fps, "op3", {})
    fell, line = live_robot_line(upright, 50.0)
    assert not fell and "stayed up (largest torso tilt 45 deg)" in line, line


def test_the_steps_line_says_why_a_robot_keeps_its_feet_planted(tmp_path):
    """A robot folder whose profile says streaming_steps: false (robot init, after its robot fell
    with steps in the probe) takes no steps in the demo: the line names the file that says so.
    The bundled op3 steps, and gets no such note."""
    import shutil

    from firmware_cfg.registry import BUNDLED_DIR
    from ros_free_bridge.commands.demo import planted_note

    assert planted_note("op3") == ""
    folder = tmp_path / "flatfoot"
    shutil.copytree(BUNDLED_DIR / "op3", folder)
    prof = folder / "profile.yaml"
    prof.write_text(prof.read_text() + "streaming_steps: false\n")
    note = planted_note(folder)
    assert "keeps its feet planted" in note and str(prof) in note, note
    from dualflow.synthetic import make_leader

    still = np.repeat(make_leader(1.0, 30.0, seed=0).positions[:1], 30, axis=0)
    path = tmp_path / "partner.npz"
    save_motion(Motion(still, 30.0, name="partner"), path)
    assert steps_line(path, _Check(), planted=note).endswith(note)

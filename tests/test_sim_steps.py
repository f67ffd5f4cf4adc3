"""The robot's steps in the physics check, counted by the person's rule scaled to the robot
(sim.check.steps_as_a_person): a rebound of a few millimetres is no step, a foot lifted and put
down elsewhere is one, as for the person."""

import numpy as np

from sim.check import steps_as_a_person

DT = 0.01
HEIGHT = 0.5  # m, an op3-sized robot: the rule's 5 cm and 0.4 m/s scale to about 16 mm and 0.13 m/s


def _foot(z_mm: np.ndarray, x_m: np.ndarray | None = None) -> np.ndarray:
    """One foot's sole point (K, 1, 3): height ``z_mm`` above the floor, moved along x by ``x_m``."""
    K = len(z_mm)
    p = np.zeros((K, 1, 3))
    p[:, 0, 2] = 0.001 * np.asarray(z_mm, dtype=float)
    if x_m is not None:
        p[:, 0, 0] = x_m
    return p


def _bump(K: int, start: int, ticks: int, peak: float) -> np.ndarray:
    """A smooth rise to ``peak`` and back over ``ticks`` ticks from ``start``."""
    z = np.zeros(K)
    z[start : start + ticks] = peak * np.sin(np.linspace(0.0, np.pi, ticks))
    return z


def test_a_rebound_of_a_few_millimetres_is_no_step():
    # landed, then up 5 mm for 0.15 s where it stood (the op3's rebound after touch-down)
    z = _bump(200, 80, 15, 5.0)
    assert steps_as_a_person(_foot(z), DT, HEIGHT) == [0]


def test_a_foot_lifted_and_put_down_elsewhere_is_one_step():
    K = 200
    z = _bump(K, 60, 25, 20.0)  # 20 mm clearance for 0.25 s
    x = np.clip((np.arange(K) - 60) / 25.0, 0.0, 1.0) * 0.06  # 6 cm forward during it
    assert steps_as_a_person(_foot(z, x), DT, HEIGHT) == [1]
    # the same lift in place is a step too: the foot moves faster than a person's standing foot
    assert steps_as_a_person(_foot(z), DT, HEIGHT) == [1]
    # and two of them two
    z2 = z + _bump(K, 140, 25, 20.0)
    assert steps_as_a_person(_foot(z2), DT, HEIGHT) == [2]


def test_the_rule_scales_with_the_robot():
    """A slow 12 mm lift in place (0.4 s) is a step for a robot a fifth of a person's size (the
    rule's height 9.5 mm) and none for one of a person's size (for whom 12 mm is a shuffle)."""
    z = _bump(200, 60, 40, 12.0)
    assert steps_as_a_person(_foot(z), DT, 0.3) == [1]
    assert steps_as_a_person(_foot(z), DT, 1.6) == [0]


def test_a_streamed_stepping_leader_takes_its_planned_steps_in_physics():
    """In real MuJoCo: the op3 streamed with steps takes the steps its plan has (give or take
    one, a step the physics merges or splits), and no more than its feet's lift-offs."""
    from dualflow.synthetic import make_leader
    from retarget.robot import load_robot
    from retarget.schedule import count_steps
    from retarget.streaming import StreamingConfig, StreamingRetargeter
    from sim.check import CheckConfig, check_trajectory, lift_offs, steps_taken

    traj = StreamingRetargeter(load_robot("op3"), 30.0, StreamingConfig(balance=True, steps=True)).run(
        make_leader(4.0, 30.0, 0)
    )
    plan = count_steps(np.asarray(traj.meta["contacts"], bool))
    res = check_trajectory(traj, CheckConfig(mode="free"), robot="op3")
    assert res.passed, res.failures
    assert plan >= 4
    assert abs(steps_taken(res.metrics) - plan) <= 1, (res.metrics["steps"], plan)
    assert steps_taken(res.metrics) <= lift_offs(res.metrics)

"""The robot trajectory type: validation and lossless npz / CSV files."""

import csv

import numpy as np
import pytest

from retarget import RetargetError, RobotTrajectory


def _traj(n=10):
    rng = np.random.default_rng(0)
    quat = rng.normal(size=(n, 4))
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    return RobotTrajectory(
        ("a", "b", "c"),
        rng.normal(size=(n, 3)),
        rng.normal(size=(n, 3)),
        quat,
        30.0,
        robot="toy",
        meta={"source": "unit test"},
    )


def test_npz_round_trip_is_exact(tmp_path):
    t = _traj()
    back = RobotTrajectory.load_npz(t.save_npz(tmp_path / "t.npz"))
    assert back.joint_names == t.joint_names and back.robot == "toy" and back.meta == t.meta
    np.testing.assert_array_equal(back.joint_pos, t.joint_pos)
    np.testing.assert_array_equal(back.root_quat, t.root_quat)
    assert not (tmp_path / "t.npz.partial.npz").exists()


def test_csv_has_a_header_and_one_row_per_frame(tmp_path):
    t = _traj(7)
    rows = list(csv.reader(open(t.save_csv(tmp_path / "t.csv"))))
    assert rows[0][:2] == ["time_s", "root_x"] and rows[0][-3:] == ["a", "b", "c"]
    assert len(rows) == 8
    assert float(rows[-1][-1]) == pytest.approx(t.joint_pos[-1, -1], abs=1e-6)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"joint_pos": np.zeros((10, 2))}, r"\(T, 3\)"),
        ({"root_quat": np.zeros((10, 4))}, "unit quaternion"),
        ({"fps": 0}, "fps"),
        ({"joint_pos": np.full((10, 3), np.nan)}, "NaN"),
        ({"joint_names": ("a", "a", "c")}, "duplicates"),
    ],
)
def test_bad_trajectories_are_rejected(kwargs, match):
    t = _traj()
    fields = dict(
        joint_names=t.joint_names, joint_pos=t.joint_pos, root_pos=t.root_pos, root_quat=t.root_quat, fps=t.fps
    )
    fields.update(kwargs)
    with pytest.raises(RetargetError, match=match):
        RobotTrajectory(**fields)


def test_loading_a_non_trajectory_names_the_file(tmp_path):
    p = tmp_path / "x.npz"
    np.savez(p, foo=np.zeros(3))
    with pytest.raises(RetargetError, match="x.npz"):
        RobotTrajectory.load_npz(p)

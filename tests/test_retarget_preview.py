"""retarget.preview.ZmpPreview: the receding-horizon cart-table plan the streaming steps follow."""

import numpy as np
import pytest

from retarget.preview import ZmpPreview

KZ = 23.4  # (h/g) fps² of the op3: CoM 0.255 m above its soles, 30 fps
N = 30


def _run(preview: ZmpPreview, ref: np.ndarray, frames: int) -> tuple[np.ndarray, np.ndarray]:
    """Follow the plan's first frame every frame (receding horizon) from rest at ref[0]; the
    CoM (frames + 2, d) and the ZMP of each planned frame (frames, d)."""
    c = [ref[0], ref[0]]
    for k in range(frames):
        c.append(preview.next_com(c[-1], c[-2], ref[k : k + preview.frames]))
    c = np.array(c)
    z = (1 - KZ) * c[2:] + KZ * (2 * c[1:-1] - c[:-2])
    return c, z


def test_a_robot_at_rest_over_its_reference_stays_there():
    p = ZmpPreview(KZ, N)
    here = np.array([0.12, -0.03])
    c, z = _run(p, np.tile(here, (60, 1)), 20)
    assert np.abs(c - here).max() < 1e-12
    # the gains of the known frames and the reference add up to one: moving everything moves the plan
    assert p.plan_gains.sum(axis=1) == pytest.approx(np.ones(N), abs=1e-9)


def test_a_weight_shift_puts_the_zmp_under_the_stance_foot_before_the_lift_and_the_com_comes_back():
    """The ZMP reference of a step: from between the feet to 3.3 cm to the side over 5 frames,
    held for a 0.27 s swing, back over 5 frames. The plan starts moving before the reference
    does (the preview), its ZMP reaches the stance point by the lift and stays within 5 mm of
    it through the swing, the CoM never passes the stance point, and all ends at rest."""
    frames = np.arange(90 + N)
    ref = np.interp(frames, [0, 3, 8, 16, 21], [0.0, 0.0, 0.033, 0.033, 0.0])[:, None]
    c, z = _run(ZmpPreview(KZ, N), ref, 90)
    assert z[0, 0] < -0.005  # it pushes off the other way first: the CoM is accelerated towards the stance foot
    assert np.abs(z[8:16, 0] - 0.033).max() < 0.005, z[8:16, 0]
    assert c[:, 0].max() < 0.033
    assert c[2 + 12, 0] > 0.015  # the CoM moved well towards the stance foot mid-swing
    assert abs(c[-1, 0]) < 1e-3 and abs(z[-1, 0]) < 1e-3


def test_the_plan_is_the_first_frame_of_the_whole_plan_and_rejects_a_too_short_horizon():
    p = ZmpPreview(KZ, N)
    rng = np.random.default_rng(0)
    c0, cm1, ref = rng.normal(size=2), rng.normal(size=2), rng.normal(size=(N, 2))
    assert p.next_com(c0, cm1, ref) == pytest.approx(p.plan(c0, cm1, ref)[0])
    with pytest.raises(ValueError, match="frames"):
        ZmpPreview(KZ, 1)

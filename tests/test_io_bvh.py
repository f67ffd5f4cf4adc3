"""The BVH format layer: parsing robustness, forward kinematics, writing, bad input."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from dualflow import DualFlowError
from dualflow.motion.io.bvh import BvhClip, BvhJoint, bvh_text, parse_bvh_text, read_bvh, write_bvh

SMALL = """HIERARCHY
ROOT Hips
{
\tOFFSET 0 0 0
\tCHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
\tJOINT Chest
\t{
\t\tOFFSET 0 10 0
\t\tCHANNELS 3 Xrotation Zrotation Yrotation
\t\tEnd Site
\t\t{
\t\t\tOFFSET 0 5 0
\t\t}
\t}
\tJOINT Leg
\t{
\t\tOFFSET 2 -10 0
\t\tCHANNELS 3 Yrotation Xrotation Zrotation
\t\tEnd Site
\t\t{
\t\t\tOFFSET 0 -9 1
\t\t}
\t}
}
MOTION
Frames: 2
Frame Time: 0.04
1 90 2 0 0 0 90 0 0 0 0 0
1 90 2 90 0 0 0 0 0 0 0 90
"""


def reference_fk(clip: BvhClip) -> np.ndarray:
    """Per-frame, per-joint FK with scipy's intrinsic Euler convention (an independent
    implementation of the BVH semantics in bvh.py's docstring)."""
    out = np.zeros((clip.n_frames, len(clip.joints), 3))
    starts = clip.channel_offsets()
    for t in range(clip.n_frames):
        glob = [None] * len(clip.joints)
        for j, joint in enumerate(clip.joints):
            vals = clip.motion[t, starts[j] : starts[j] + len(joint.channels)]
            trans = np.array(joint.offset, float)
            axes, angles = "", []
            for ch, v in zip(joint.channels, vals):
                if ch.endswith("position"):
                    trans["XYZ".index(ch[0])] = v
                else:
                    axes += ch[0]
                    angles.append(v)
            local = Rotation.from_euler(axes, angles, degrees=True) if axes else Rotation.identity()
            if joint.parent < 0:
                out[t, j], glob[j] = trans, local
            else:
                out[t, j] = out[t, joint.parent] + glob[joint.parent].apply(trans)
                glob[j] = glob[joint.parent] * local
    return out


def test_parses_structure_channels_and_end_sites():
    clip = parse_bvh_text(SMALL, "small.bvh")
    assert clip.names == ("Hips", "Chest", "Chest_end", "Leg", "Leg_end")
    assert clip.parents == (-1, 0, 1, 0, 3)
    assert clip.joints[1].rotation_axes == "XZY" and clip.joints[3].rotation_axes == "YXZ"
    assert clip.joints[2].is_end_site and clip.joints[2].channels == ()
    assert clip.n_channels == 12 and clip.n_frames == 2 and clip.fps == pytest.approx(25.0)
    assert clip.first_motion_line == 28


def test_fk_matches_hand_computed_values():
    pos = parse_bvh_text(SMALL, "small.bvh").global_positions()
    # frame 0: root at (1, 90, 2) unrotated; the chest's Xrotation 90 turns its end
    # site's offset (0,5,0) into (0,0,5)
    np.testing.assert_allclose(pos[0, 0], [1, 90, 2])
    np.testing.assert_allclose(pos[0, 1], [1, 100, 2], atol=1e-12)
    np.testing.assert_allclose(pos[0, 2], [1, 100, 7], atol=1e-12)
    # frame 1: root rotated 90 deg about Z: chest (0,10,0) -> (-10,0,0); leg offset (2,-10,0) -> (10,2,0)
    np.testing.assert_allclose(pos[1, 1], [-9, 90, 2], atol=1e-12)
    np.testing.assert_allclose(pos[1, 3], [11, 92, 2], atol=1e-12)
    # the leg's own Zrotation 90 turns its end site (0,-9,1) -> (9,0,1), then the root's Z turn -> (0,9,1)
    np.testing.assert_allclose(pos[1, 4], [11, 101, 3], atol=1e-12)
    np.testing.assert_allclose(pos, reference_fk(parse_bvh_text(SMALL)), atol=1e-12)


@pytest.mark.parametrize("newline", ["\n", "\r\n", "\r", "mixed"])
def test_line_endings_do_not_matter(newline):
    lines = SMALL.splitlines()
    if newline == "mixed":  # like the CMU files: CRLF with a few LF-only lines
        text = "".join(line + ("\n" if i % 3 == 0 else "\r\n") for i, line in enumerate(lines))
    else:
        text = newline.join(lines) + newline
    clip = parse_bvh_text(text, "x.bvh")
    np.testing.assert_allclose(clip.motion, parse_bvh_text(SMALL).motion)
    assert clip.first_motion_line == 28


def test_tolerates_spacing_case_and_braces_on_one_line():
    text = SMALL.replace("\t", "   ").replace("End Site", "End site").replace("{\n", "{ ")
    text = text.replace("Xposition", "XPOSITION")
    clip = parse_bvh_text(text)
    np.testing.assert_allclose(clip.global_positions(), parse_bvh_text(SMALL).global_positions())


# -- random hierarchies: write -> read -> the same FK as an independent implementation ----
@st.composite
def random_clips(draw):
    n = draw(st.integers(1, 7))
    rng = np.random.default_rng(draw(st.integers(0, 2**31)))
    joints = []
    for j in range(n):
        parent = -1 if j == 0 else int(rng.integers(0, j))
        rot = list(rng.permutation(["Xrotation", "Yrotation", "Zrotation"]))
        pos = ["Xposition", "Yposition", "Zposition"] if (j == 0 or rng.random() < 0.2) else []
        channels = pos + rot if rng.random() < 0.5 else rot + pos
        if rng.random() < 0.15:  # a joint with fewer rotation channels
            channels = [c for c in channels if c != "Yrotation"]
        joints.append(BvhJoint(f"j{j}", parent, tuple(rng.normal(0, 5, 3)), tuple(channels)))
    ends = [BvhJoint(f"j{j}_end", j, tuple(rng.normal(0, 3, 3)), (), True) for j in range(n) if rng.random() < 0.5]
    joints = joints + ends
    T = draw(st.integers(1, 6))
    C = sum(len(j.channels) for j in joints)
    motion = rng.uniform(-180, 180, (T, C))
    return BvhClip(tuple(joints), 1 / 30, motion, "random.bvh")


@settings(max_examples=40, deadline=None)
@given(clip=random_clips())
def test_any_hierarchy_and_channel_order_roundtrips_and_matches_reference_fk(clip, tmp_path_factory):
    path = tmp_path_factory.mktemp("bvh") / "r.bvh"
    write_bvh(clip, path, precision=9)
    back = read_bvh(path)
    # End Sites are re-ordered after their joint's children on writing; compare by name
    order = [back.names.index(n) for n in clip.names]
    np.testing.assert_allclose(back.global_positions()[:, order], reference_fk(clip), atol=1e-6)
    np.testing.assert_allclose(clip.global_positions(), reference_fk(clip), atol=1e-9)


def test_write_is_atomic_and_needs_the_folder(tmp_path):
    clip = parse_bvh_text(SMALL)
    with pytest.raises(DualFlowError, match="does not exist"):
        write_bvh(clip, tmp_path / "missing" / "x.bvh")
    write_bvh(clip, tmp_path / "x.bvh")
    assert [p.name for p in tmp_path.iterdir()] == ["x.bvh"]  # no temp file left behind
    assert bvh_text(clip).count("\n") == (tmp_path / "x.bvh").read_text().count("\n")


# -- bad input: one clear error with the file name and the line ----------------------
def _lines(text=SMALL):
    return text.splitlines()


def _without(text, line_no):
    lines = _lines(text)
    del lines[line_no - 1]
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: "\n".join(_lines()[:12]) + "\n", r"bad\.bvh, line 12: file ends inside the HIERARCHY.*truncated"),
        (lambda: "\n".join(_lines()[:28]) + "\n", r"bad\.bvh, line 28: 'Frames: 2' but only 1 motion lines.*truncated"),
        (
            lambda: SMALL[: SMALL.rindex("90")],
            r"bad\.bvh, line 29: expected 12 values .* found 11 \(truncated file\?\)",
        ),
        (
            lambda: SMALL.replace("1 90 2 0 0 0 90 0 0 0 0 0", "1 90 2 0 0 0 90 0 0 0 0"),
            r"bad\.bvh, line 28: expected 12 values.*found 11",
        ),
        (lambda: SMALL.replace("1 90 2 90 0 0", "1 90 2 nan 0 0"), r"bad\.bvh, line 29: channel 4 is nan"),
        (lambda: SMALL.replace("1 90 2 90 0 0", "1 90 2 9O 0 0"), r"bad\.bvh, line 29: '9O' is not a number"),
        (lambda: SMALL.replace("Frames: 2", "Frames: 0").split("1 90 2 0 0")[0], r"line 26: .*zero frames"),
        (lambda: SMALL.replace("Frames: 2", "Frames: 3"), r"'Frames: 3' but only 2 motion lines"),
        (lambda: SMALL.replace("Frames: 2", "Frames: 1"), r"line 29: 'Frames: 1' but 2 motion lines"),
        (lambda: SMALL.replace("Frame Time: 0.04", "Frame Time: 0"), r"line 27: 'Frame Time:' must be > 0"),
        (lambda: _without(SMALL, 27), r"line 27: expected 'Frames: N' and 'Frame Time: dt' after MOTION"),
        (
            lambda: SMALL.replace("Yrotation Xrotation Zrotation", "Yrotation Xrotation Wrotation"),
            r"line 18: unknown channel 'Wrotation' for joint 'Leg'",
        ),
        (lambda: SMALL.replace("JOINT Leg", "JOINT Chest"), r"line 15: joint name 'Chest' is used twice"),
        (
            lambda: SMALL.replace("OFFSET 0 10 0", "OFFSET 0 ten 0"),
            r"line 8: expected a number for the OFFSET of 'Chest'",
        ),
        (lambda: SMALL.replace("OFFSET 0 10 0", "OFFSET 0 nan 0"), r"line 8: the OFFSET of 'Chest' is 'nan'"),
        (lambda: SMALL.split("MOTION")[0], r"no MOTION section"),
        (lambda: SMALL.split("Frame Time")[0], r"line 26: the MOTION section has no 'Frame Time:' line"),
        (lambda: "", r"empty or has no HIERARCHY"),
        (lambda: SMALL.replace("HIERARCHY", "HIERARCHIE"), r"line 1: expected 'HIERARCHY'"),
    ],
)
def test_bad_files_raise_one_clear_error(tmp_path, make, match):
    path = tmp_path / "bad.bvh"
    path.write_text(make())
    with pytest.raises(DualFlowError, match=match):
        read_bvh(path)


def test_missing_and_binary_files(tmp_path):
    with pytest.raises(DualFlowError, match="no such file"):
        read_bvh(tmp_path / "nope.bvh")
    (tmp_path / "bin.bvh").write_bytes(b"\x00\x01\x02" * 10)
    with pytest.raises(DualFlowError, match="binary"):
        read_bvh(tmp_path / "bin.bvh")

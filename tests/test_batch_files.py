"""Which files retarget-check takes from a folder: plain files, subfolders, InterGen's
person1/person2 layout (the reactor of each pair, InterHuman-AS labels) and its own output."""

import json

import numpy as np
import pytest

from dualflow.errors import DualFlowError
from ros_free_bridge.batch import clip_name, find_motion_files
from ros_free_bridge.errors import BridgeError


def touch(path):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"")
    return path


def names(files, folder):
    return [clip_name(f, folder) for f in files]


def test_plain_folder_takes_motion_files_only_and_subfolders_only_when_asked(tmp_path):
    for n in ("b.bvh", "a.npz", "c.NPY", "notes.txt", "sub/d.bvh"):
        touch(tmp_path / n)
    assert names(find_motion_files(tmp_path), tmp_path) == ["a.npz", "b.bvh", "c.NPY"]
    assert names(find_motion_files(tmp_path, recursive=True), tmp_path) == ["a.npz", "b.bvh", "c.NPY", "sub/d.bvh"]


def test_the_output_folder_inside_the_input_is_left_out(tmp_path):
    touch(tmp_path / "a.npz")
    touch(tmp_path / "out" / "clips" / "a.npz" / "trajectory.npz")  # a previous run's outputs
    assert names(find_motion_files(tmp_path, recursive=True, exclude=tmp_path / "out"), tmp_path) == ["a.npz"]
    assert len(find_motion_files(tmp_path, recursive=True)) == 2


@pytest.mark.parametrize("base", ["", "motions_processed"])
def test_intergen_layout_gives_one_clip_per_pair_its_reactor(tmp_path, base):
    people = tmp_path / base if base else tmp_path
    for person in ("person1", "person2"):
        for clip in ("10", "11"):
            touch(people / person / f"{clip}.npy")
    touch(people / "person1" / "12.npy")  # only one person of this clip
    files = find_motion_files(tmp_path, recursive=True)
    prefix = f"{base}/" if base else ""
    assert names(files, tmp_path) == [f"{prefix}person1/12.npy", f"{prefix}person2/10.npy", f"{prefix}person2/11.npy"]


def test_interhuman_as_labels_choose_the_reactor(tmp_path):
    for person in ("person1", "person2"):
        for clip in ("10", "11"):
            touch(tmp_path / "motions_processed" / person / f"{clip}.npy")
    (tmp_path / "actor_reactor.json").write_text(json.dumps({"10": "person2", "11": 1}))
    files = find_motion_files(tmp_path / "motions_processed")
    assert names(files, tmp_path) == ["motions_processed/person1/10.npy", "motions_processed/person2/11.npy"]
    (tmp_path / "actor_reactor.json").write_text(json.dumps({"10": "nobody"}))
    with pytest.raises(DualFlowError, match="actor must be 'person1' or 'person2'"):
        find_motion_files(tmp_path / "motions_processed")


def test_not_a_folder_is_one_clear_error(tmp_path):
    f = touch(tmp_path / "a.npz")
    with pytest.raises(BridgeError, match="not a folder"):
        find_motion_files(f)


def test_relative_names_are_posix_and_unique(tmp_path):
    a, b = touch(tmp_path / "x" / "walk.npz"), touch(tmp_path / "y" / "walk.npz")
    assert np.unique(names([a, b], tmp_path)).size == 2 and names([a], tmp_path) == ["x/walk.npz"]


def test_a_relative_folder_works_for_pairs_too(tmp_path, monkeypatch):
    for person in ("person1", "person2"):
        touch(tmp_path / "ig" / person / "7.npy")
    monkeypatch.chdir(tmp_path)
    files = find_motion_files("ig", recursive=True)
    assert names(files, "ig") == ["person2/7.npy"] and not files[0].is_absolute()


def test_with_recursive_a_pair_layout_is_found_in_any_subfolder(tmp_path):
    for person in ("person1", "person2"):
        touch(tmp_path / "sessions" / "day1" / person / "5.npy")
        touch(tmp_path / "sessions" / "day1" / person / "5.bvh")  # same stem, another file: its own clip
    touch(tmp_path / "sessions" / "solo.bvh")
    files = find_motion_files(tmp_path, recursive=True)
    assert names(files, tmp_path) == ["sessions/day1/person2/5.bvh", "sessions/day1/person2/5.npy", "sessions/solo.bvh"]


def test_labels_are_found_from_a_relative_motions_processed_folder(tmp_path, monkeypatch):
    for person in ("person1", "person2"):
        touch(tmp_path / "motions_processed" / person / "10.npy")
    (tmp_path / "actor_reactor.json").write_text(json.dumps({"10": "person2"}))
    monkeypatch.chdir(tmp_path / "motions_processed")
    assert names(find_motion_files("."), ".") == ["person1/10.npy"]

"""DD100 (Duolando, Siyao et al. 2024) in the layout Duolando's loader reads.

Layout (after Duolando's ``_train_test_split.py`` and ``_prepare_*_data.py``)::

    ROOT/
      motion/pos3d/{train,test}/<GENRE>_<CHOREO>_<TAKE>_00.npy   the follower (lady)
      motion/pos3d/{train,test}/<GENRE>_<CHOREO>_<TAKE>_01.npy   the leader (man)
      music/feature/{train,test}/<GENRE>_<CHOREO>_<TAKE>.npy     (T, 54) music features
      music/mp3/{train,test}/<take>.mp3                          optional audio

``pos3d``: SMPL-X joint positions (T, 165) or (T, 55, 3), metres, Y up, 30 fps (the first 22
are the SMPL body); music: :data:`dualflow.music.DUOLANDO54_LAYOUT`, beat one-hot in column 53.
The leader is the actor; the genre is the take name's first field. Like Duolando's loader, a
take without its partner or music file is skipped (``DuetSet.skipped``); ``music=False``
loads motion only.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dualflow.datasets.collection import DuetSet
from dualflow.datasets.files import load_array, load_features, require_dir
from dualflow.datasets.sample import DuetSample, positions_motion
from dualflow.errors import DualFlowError
from dualflow.motion.container import TwoPersonMotion

FPS = 30.0
FOLLOWER_SUFFIX = "_00.npy"
LEADER_SUFFIX = "_01.npy"
MUSIC_DIM = 54


def check_up_axis(positions_yup: np.ndarray, where: str) -> None:
    """Reject positions whose Y axis is not up: the head (15) must be above the pelvis (0) on average."""
    pos = np.asarray(positions_yup)
    pos = pos.reshape(len(pos), -1, 3)
    if np.mean(pos[:, 15, 1] - pos[:, 0, 1]) <= 0.1:
        raise DualFlowError(
            f"{where}: the head is not above the pelvis along Y; this loader expects Y-up SMPL-X "
            "positions (Duolando's pos3d) — convert the file or pass up='z'"
        )


def load_dd100(
    root: str | Path, split: str = "train", *, music: bool = True, up: str = "y", limit: int | None = None
) -> DuetSet:
    """Load one split ("train" | "test") of DD100 (module docstring). up: 'y' (Duolando) or 'z'."""
    if up not in ("y", "z"):
        raise DualFlowError(f"dd100: up must be 'y' or 'z', got {up!r}")
    root = Path(root)
    pos_dir = require_dir(
        root / "motion" / "pos3d" / split,
        f"DD100 motion/pos3d/{split}",
        "run Duolando's _train_test_split.py and _prepare_motion_data.py, or pass the dataset root",
    )
    music_dir = root / "music" / "feature" / split
    if music:
        require_dir(
            music_dir,
            f"DD100 music/feature/{split}",
            "run Duolando's _prepare_music_data.py, or load motion only with music=False",
        )
    takes = sorted(p.name[: -len(FOLLOWER_SUFFIX)] for p in pos_dir.glob(f"*{FOLLOWER_SUFFIX}"))
    leaders = {p.name[: -len(LEADER_SUFFIX)] for p in pos_dir.glob(f"*{LEADER_SUFFIX}")}
    if not takes and not leaders:
        raise DualFlowError(f"{pos_dir}: no <take>_00.npy / <take>_01.npy files; this is not DD100's pos3d folder")
    samples, skipped = [], {}
    for take in takes:
        if limit is not None and len(samples) >= int(limit):
            break
        if take not in leaders:
            skipped[take] = "no leader file (_01.npy)"
            continue
        music_path = music_dir / f"{take}.npy"
        if music and not music_path.is_file():
            skipped[take] = f"no music features {music_path.name}"
            continue
        people = []
        for suffix, role in ((LEADER_SUFFIX, "leader"), (FOLLOWER_SUFFIX, "follower")):
            path = pos_dir / f"{take}{suffix}"
            arr = load_array(path, ndim=(2, 3), min_rows=2)
            arr = arr.reshape(len(arr), -1, 3) if arr.ndim == 2 and arr.shape[1] % 3 == 0 else arr
            if arr.ndim != 3 or arr.shape[1] < 22 or arr.shape[2] != 3:
                raise DualFlowError(f"{path}: expected SMPL-X joint positions (T, 165) or (T, 55, 3), got {arr.shape}")
            if up == "z":
                arr = arr[..., [1, 2, 0]]  # Z-up file -> Y-up (the inverse of zup = yup[..., [2, 0, 1]])
            check_up_axis(arr[:, :22], str(path))
            people.append(positions_motion(arr, FPS, f"{take}_{role}", str(path)))
        n = min(p.n_frames for p in people)
        feats = None
        if music:
            feats = load_features(music_path, MUSIC_DIM, "Duolando music features")
            n = min(n, len(feats))
            feats = feats[:n]
        if n < 2:
            skipped[take] = "fewer than 2 frames"
            continue
        pair = TwoPersonMotion(people[0].slice(0, n), people[1].slice(0, n))
        mp3 = root / "music" / "mp3" / split / f"{take}.mp3"
        samples.append(
            DuetSample(
                source="dd100",
                name=take,
                motion=pair,
                music=feats,
                music_kind="duolando54" if feats is not None else None,
                music_path=mp3 if mp3.is_file() else None,
                genre=take.split("_")[0],
                roles=("leader", "follower"),
                meta={"pos3d": str(pos_dir)},
            )
        )
    return DuetSet("dd100", split, root, samples, skipped)

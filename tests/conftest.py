"""Shared test fixtures: where the real test data lives, and skipping when it is absent."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

# before any test module imports mujoco: on a machine without a display, importing sim sets
# MUJOCO_GL=egl, which MuJoCo reads once, at its first import (a test file that imported mujoco
# first left every later render in the run on GLFW, which fails headless)
import sim  # noqa: F401

#: ../shared/data beside the project root (override with DUALFLOW_SHARED_DATA).
SHARED_DATA = Path(
    os.environ.get("DUALFLOW_SHARED_DATA", Path(__file__).resolve().parents[1].parent / "shared" / "data")
)
CMU_DIR = SHARED_DATA / "mocap" / "cmu"
MUSIC_DIR = SHARED_DATA / "music"


def _require(path: Path) -> Path:
    if not path.exists():
        pytest.skip(f"real test data not found at {path} (../shared/data is absent on this machine)")
    return path


@pytest.fixture
def cmu_pair_paths() -> tuple[Path, Path]:
    """The CMU two-person trial 18_01 (actor) / 19_01 (partner), 120 fps BVH."""
    return _require(CMU_DIR / "18_01.bvh"), _require(CMU_DIR / "19_01.bvh")


@pytest.fixture
def music_dir() -> Path:
    return _require(MUSIC_DIR)


@pytest.fixture(autouse=True)
def _one_torch_thread():
    """One torch thread in tests that use torch: on a shared 2-core machine two threads
    contend and run many times slower. Tests that never import torch are left alone (some
    check that importing a package does not import it)."""
    torch = sys.modules.get("torch")
    if torch is None:
        yield
        return
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="session")
def tiny_checkpoint(tmp_path_factory):
    """An untrained `tiny` DualFlow checkpoint (seeded) with statistics of a synthetic mirror duet:
    real weights and files for the bridge's pipeline tests, cheap to run."""
    import torch

    from dualflow.checkpoint import save_checkpoint
    from dualflow.model import DualFlow, DualFlowConfig
    from dualflow.motion.features import encode_pair
    from dualflow.motion.normalization import NormStats
    from dualflow.synthetic import make_duet

    torch.manual_seed(0)
    feats, _ = encode_pair(make_duet("mirror", 4.0, 30.0, 0))
    path = tmp_path_factory.mktemp("ckpt") / "tiny"
    save_checkpoint(path, model=DualFlow(DualFlowConfig.preset("tiny")), stats=NormStats.from_features(feats))
    return path

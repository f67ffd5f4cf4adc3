"""Mean / standard-deviation statistics of the 262-d feature, shared by both persons.

    normalized = (features - mean) / std          features = normalized * std + mean

One set of statistics serves person A and person B (their features share a layout
and, after canonicalisation, similar ranges). ``std`` is floored at
:data:`STD_FLOOR` when computed: a column that never varies in the training data
(the identity rotation of a leaf joint, a contact that never fires) would
otherwise divide by zero; with the floor it normalises to ~0 and denormalises
to its constant. Statistics are stored as npz (keys ``mean`` and ``std``,
float64, read with ``allow_pickle=False``), written to a temporary name and
renamed so a file is complete or absent.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dualflow.errors import DualFlowError
from dualflow.motion.features import FEATURE_DIM

#: Smallest std kept by :meth:`NormStats.from_features` (feature units: metres,
#: metres per frame, 6D components, contact 0/1). 1e-4 is 0.1 mm for positions.
STD_FLOOR = 1e-4


def _vector(x, what: str) -> np.ndarray:
    arr = np.array(x, dtype=np.float64)
    if arr.shape != (FEATURE_DIM,):
        raise DualFlowError(f"normalization stats: {what} must have shape ({FEATURE_DIM},), got {tuple(arr.shape)}")
    if not np.isfinite(arr).all():
        col = int(np.argwhere(~np.isfinite(arr))[0][0])
        raise DualFlowError(
            f"normalization stats: {what} contains NaN or inf (first at column {col}); recompute the stats"
        )
    return arr


@dataclass(frozen=True)
class NormStats:
    """Per-column mean (262,) and std (262,) of the feature; std > 0 everywhere."""

    mean: np.ndarray
    std: np.ndarray

    def __post_init__(self) -> None:
        mean, std = _vector(self.mean, "mean"), _vector(self.std, "std")
        if (std <= 0).any():
            col = int(np.argwhere(std <= 0)[0][0])
            raise DualFlowError(
                f"normalization stats: std must be > 0, column {col} is {std[col]!r}; "
                f"floor it (NormStats.from_features uses {STD_FLOOR})"
            )
        mean.setflags(write=False)
        std.setflags(write=False)
        object.__setattr__(self, "mean", mean)
        object.__setattr__(self, "std", std)

    @classmethod
    def from_features(cls, features, std_floor: float = STD_FLOOR) -> NormStats:
        """Statistics over every row of ``features`` (..., 262): one person (T, 262),
        a pair (T, 2, 262), a batch (N, T, 2, 262), or a list of such arrays
        (all persons and frames pooled). ``std = max(std, std_floor)``."""
        if isinstance(features, (list, tuple)):
            if not features:
                raise DualFlowError("features: empty list; give at least one feature array")
            rows = np.concatenate([_rows(f) for f in features], axis=0)
        else:
            rows = _rows(features)
        return cls(rows.mean(axis=0), np.maximum(rows.std(axis=0), float(std_floor)))

    def normalize(self, features) -> np.ndarray:
        """(..., 262) -> (..., 262) in the input's float dtype (float32 stays float32)."""
        x = _check_last(features)
        return ((x - self.mean) / self.std).astype(x.dtype, copy=False)

    def denormalize(self, normalized) -> np.ndarray:
        """(..., 262) -> (..., 262), the inverse of :meth:`normalize`."""
        x = _check_last(normalized)
        return (x * self.std + self.mean).astype(x.dtype, copy=False)

    def save(self, path: str | os.PathLike) -> Path:
        """Write ``mean`` and ``std`` to an npz file (atomic: temp name, then rename)."""
        path = Path(path)
        if path.suffix != ".npz":
            raise DualFlowError(f"{path}: normalization stats are saved as .npz; use a path ending in .npz")
        if not path.parent.is_dir():
            raise DualFlowError(f"{path}: folder {path.parent} does not exist; create it first")
        tmp = path.with_name(path.name + ".partial.npz")
        with open(tmp, "wb") as fh:
            np.savez(fh, mean=self.mean, std=self.std)
        os.replace(tmp, path)
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> NormStats:
        """Read stats written by :meth:`save`; bad files raise DualFlowError naming the file."""
        from dualflow.motion.io.npfile import open_npz

        path = Path(path)
        with open_npz(path) as data:  # headers checked before allocating, no pickle
            missing = [k for k in ("mean", "std") if k not in data]
            if missing:
                raise DualFlowError(
                    f"{path}: normalization stats file lacks {', '.join(missing)}; write it with NormStats.save"
                )
            mean, std = data["mean"], data["std"]
        for what, arr in (("mean", mean), ("std", std)):
            if arr.dtype.kind != "f":
                raise DualFlowError(f"{path}, field {what!r}: expected floating-point numbers, got dtype {arr.dtype}")
        try:
            return cls(mean, std)
        except DualFlowError as exc:
            raise DualFlowError(f"{path}: {exc}") from None


def _check_last(x) -> np.ndarray:
    arr = np.asarray(x)
    if not np.issubdtype(arr.dtype, np.floating):
        arr = arr.astype(np.float64)
    if arr.ndim < 1 or arr.shape[-1] != FEATURE_DIM:
        raise DualFlowError(f"features: last axis must be {FEATURE_DIM}, got shape {tuple(arr.shape)}")
    return arr


def _rows(features) -> np.ndarray:
    arr = _check_last(features).astype(np.float64)
    rows = arr.reshape(-1, FEATURE_DIM)
    if rows.shape[0] == 0:
        raise DualFlowError("features: no rows; give at least one frame")
    if not np.isfinite(rows).all():
        row = int(np.argwhere(~np.isfinite(rows))[0][0])
        raise DualFlowError(f"features: contain NaN or inf (first at flattened row {row}); clean the data first")
    return rows

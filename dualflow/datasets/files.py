"""Small, strict file readers shared by the dataset loaders.

Each raises :class:`DualFlowError` naming the file, what is wrong and the fix.
Arrays are read with ``np.load(allow_pickle=False)``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dualflow.errors import DualFlowError


def require_dir(path: Path, what: str, fix: str) -> Path:
    """``path`` if it is a folder, else a DualFlowError naming it."""
    if not path.is_dir():
        raise DualFlowError(f"{path}: {what} folder not found; {fix}")
    return path


def require_file(path: Path, what: str, fix: str) -> Path:
    if not path.is_file():
        raise DualFlowError(f"{path}: {what} not found; {fix}")
    return path


def read_lines(path: Path) -> list[str]:
    """Non-empty, stripped lines of a UTF-8 text file."""
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise DualFlowError(f"{path}: not UTF-8 text; re-save it as UTF-8") from None
    except OSError as exc:
        raise DualFlowError(f"{path}: cannot read ({exc})") from None
    return [line.strip() for line in text.splitlines() if line.strip()]


def read_name_list(path: Path) -> list[str]:
    """Clip names, one per line (a trailing ``.npy``/``.txt`` suffix is dropped)."""
    names = []
    for line in read_lines(path):
        name = line.split()[0]
        for suffix in (".npy", ".txt"):
            if name.endswith(suffix):
                name = name[: -len(suffix)]
        names.append(name)
    return names


def load_features(path: Path, width: int, what: str) -> np.ndarray:
    """Per-frame features (T, ``width``) as float32 from a .npy; ``what`` names them in errors."""
    feats = load_array(path, ndim=(2,), min_rows=1).astype(np.float32)
    if feats.shape[1] != width:
        raise DualFlowError(f"{path}: expected {width}-d {what}, got {feats.shape[1]} columns")
    return feats


def load_array(path: Path, *, ndim: tuple[int, ...] = (2,), min_rows: int = 1) -> np.ndarray:
    """A finite numeric .npy array with ``ndim`` dimensions and >= ``min_rows`` rows."""
    try:
        arr = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise DualFlowError(f"{path}: file not found") from None
    except ValueError as exc:
        why = (
            "holds Python objects (pickle), which are never loaded"
            if "pickle" in str(exc).lower()
            else f"is damaged ({exc})"
        )
        raise DualFlowError(f"{path}: {why}; re-export it as a plain numeric .npy") from None
    except (OSError, EOFError) as exc:
        raise DualFlowError(f"{path}: not a readable .npy file ({exc})") from None
    if not isinstance(arr, np.ndarray) or arr.dtype.kind not in "fiu":
        raise DualFlowError(f"{path}: expected a numeric array, got {getattr(arr, 'dtype', type(arr))}")
    if arr.ndim not in ndim:
        raise DualFlowError(f"{path}: expected a {' or '.join(map(str, ndim))}-D array, got shape {arr.shape}")
    if arr.shape[0] < min_rows:
        raise DualFlowError(f"{path}: expected at least {min_rows} frames, got {arr.shape[0]}")
    if not np.isfinite(arr).all():
        row = int(np.argwhere(~np.isfinite(arr))[0][0])
        raise DualFlowError(f"{path}: contains NaN or inf (first at row {row}); clean the file")
    return arr

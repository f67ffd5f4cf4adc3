"""Reading ``.npy`` / ``.npz`` files that may be damaged or hostile, without pickle.

``numpy.load`` trusts a file's header: a header that declares 10^12 rows makes it
allocate terabytes before it reads a byte, and a truncated or damaged archive raises
any of half a dozen exception types. The readers here look at each array's header first
(magic, version, dtype, shape, with numpy's own header parser and its header-size limit)
and refuse, with one message naming the file and the field:

- an object dtype (it would need pickle), or a header numpy cannot parse;
- a declared size above ``max_bytes`` (default :data:`MAX_ARRAY_BYTES`), or larger than
  the data that follows the header (a truncated or lying file);
- a damaged archive (a bad zip directory, a CRC mismatch, a truncated member).

Every error is raised as the caller's error type (``error=``: each package has its own,
see ``DESIGN.md``), so :mod:`retarget` and :mod:`ros_free_bridge` use this module with
theirs. numpy only; nothing here imports torch.
"""

from __future__ import annotations

import zipfile
import zlib
from pathlib import Path

import numpy as np
from numpy.lib import format as npformat

from dualflow.errors import DualFlowError

#: The largest array a reader allocates (bytes): an AMASS clip of 10 minutes at 120 fps with
#: 52 joints is 90 MB; anything beyond 1 GiB in a motion, trajectory or statistics file is not
#: a plausible one.
MAX_ARRAY_BYTES = 1 << 30
#: numpy's own limit on the header's length (its default for ``max_header_size``).
MAX_HEADER_BYTES = 10000


def _header(fp, where: str, error: type[Exception]) -> tuple[tuple, bool, np.dtype, int]:
    """(shape, fortran_order, dtype, header length in bytes) of the .npy stream ``fp``."""
    start = fp.tell()
    try:
        version = npformat.read_magic(fp)
        if version == (1, 0):
            shape, fortran, dtype = npformat.read_array_header_1_0(fp, max_header_size=MAX_HEADER_BYTES)
        elif version in ((2, 0), (3, 0)):
            shape, fortran, dtype = npformat.read_array_header_2_0(fp, max_header_size=MAX_HEADER_BYTES)
        else:
            raise ValueError(f"unknown .npy format version {version}")
    except Exception as exc:  # noqa: BLE001 - numpy's header parser raises many types on hostile text
        why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise error(
            f"{where}: not a readable .npy array header ({why[:160]}); the file is damaged "
            "or not written by numpy.save / numpy.savez"
        ) from None
    return shape, fortran, dtype, fp.tell() - start


def _check_header(
    shape, dtype: np.dtype, data_bytes: int | None, where: str, max_bytes: int, error: type[Exception]
) -> None:
    if dtype.hasobject:
        raise error(
            f"{where}: holds Python objects (an object dtype, which needs pickle and is never "
            "loaded); re-save it as plain numeric arrays"
        )
    if any((not isinstance(n, int)) or n < 0 for n in shape):
        raise error(f"{where}: the header declares an invalid shape {shape}; the file is damaged")
    count = 1
    for n in shape:
        count *= n
    size = count * dtype.itemsize
    if size > max_bytes:
        raise error(
            f"{where}: the header declares shape {shape} of {dtype} ({size / 2**30:.3g} GiB), more than "
            f"the {max_bytes / 2**30:.3g} GiB this reader accepts; the file is damaged or not a motion/"
            "trajectory file (split it)"
        )
    if data_bytes is not None and data_bytes < size:
        raise error(
            f"{where}: the header declares {size} bytes of data ({shape} {dtype}) but only {data_bytes} "
            "follow; the file is truncated, re-export it"
        )


def read_npy(path, *, error: type[Exception] = DualFlowError, max_bytes: int = MAX_ARRAY_BYTES) -> np.ndarray:
    """The array of a ``.npy`` file, its header checked before anything is allocated."""
    path = Path(path)
    try:
        with open(path, "rb") as fp:
            size = path.stat().st_size
            shape, fortran, dtype, hlen = _header(fp, str(path), error)
            _check_header(shape, dtype, size - hlen, str(path), max_bytes, error)
            fp.seek(0)
            return npformat.read_array(fp, allow_pickle=False, max_header_size=MAX_HEADER_BYTES)
    except error:
        raise
    except OSError as exc:
        raise error(f"{path}: cannot read ({exc.strerror or exc})") from None
    except (ValueError, EOFError) as exc:
        raise error(f"{path}: damaged .npy data ({str(exc)[:160]}); re-export it") from None


class NpzFile:
    """The arrays of an ``.npz`` archive, each read on request with its header checked first.

    Use as a context manager. ``files`` lists the array names; ``key in npz`` tests one;
    ``npz[key]`` (or :meth:`get`) reads it, raising the caller's error type naming the file
    and the field for a missing, oversized, truncated, damaged or pickled array.
    """

    def __init__(self, path, *, error: type[Exception] = DualFlowError, max_bytes: int = MAX_ARRAY_BYTES):
        self.path = Path(path)
        self.error = error
        self.max_bytes = max_bytes
        try:
            with open(self.path, "rb") as fh:
                head = fh.read(4)
        except OSError as exc:
            raise error(f"{self.path}: cannot read ({exc.strerror or exc})") from None
        if head[:2] != b"PK":
            raise error(
                f"{self.path}: not a readable .npz archive (no zip header); the file is damaged, empty or of "
                "another kind"
            )
        try:
            self._zip = zipfile.ZipFile(self.path)
            members = self._zip.infolist()
        except (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, EOFError, ValueError, NotImplementedError) as exc:
            raise error(f"{self.path}: not a readable .npz archive ({exc}); is it truncated?") from None
        self._members = {m.filename[:-4] if m.filename.endswith(".npy") else m.filename: m for m in members}
        self.files = [k for k, m in self._members.items() if m.filename.endswith(".npy")]

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self._zip.close()

    def __contains__(self, key: str) -> bool:
        return key in self.files

    def __getitem__(self, key: str) -> np.ndarray:
        return self.get(key)

    def get(self, key: str, fix: str = "") -> np.ndarray:
        """The array ``key``; ``fix`` is added to the message when it is missing."""
        where = f"{self.path}, field {key!r}"
        if key not in self.files:
            have = ", ".join(sorted(self.files)) or "nothing"
            raise self.error(f"{where}: missing (the file has: {have}){'; ' + fix if fix else ''}")
        info = self._members[key]
        try:
            with self._zip.open(info) as fp:
                shape, fortran, dtype, hlen = _header(fp, where, self.error)
                _check_header(shape, dtype, info.file_size - hlen, where, self.max_bytes, self.error)
            with self._zip.open(info) as fp:
                return npformat.read_array(fp, allow_pickle=False, max_header_size=MAX_HEADER_BYTES)
        except self.error:
            raise
        except (zipfile.BadZipFile, OSError, EOFError, ValueError, zlib.error, NotImplementedError) as exc:
            raise self.error(
                f"{where}: cannot be read ({str(exc)[:160]}); the file is damaged or truncated, re-export it"
            ) from None


def open_npz(path, *, error: type[Exception] = DualFlowError, max_bytes: int = MAX_ARRAY_BYTES) -> NpzFile:
    """An :class:`NpzFile` on ``path`` (see there)."""
    return NpzFile(path, error=error, max_bytes=max_bytes)


def scalar(value: np.ndarray, where: str, error: type[Exception] = DualFlowError, what: str = "it") -> float:
    """One real number stored as a 0-d or 1-element array (an fps, a rate)."""
    arr = np.asarray(value)
    if arr.size != 1 or arr.dtype.kind not in "fiu":
        raise error(f"{where}: {what} must be one number, got {arr.dtype} of shape {arr.shape}")
    return float(arr.reshape(()))


def text(value: np.ndarray, where: str, error: type[Exception] = DualFlowError) -> str:
    """One string stored as a 0-d array (a name, a JSON header)."""
    arr = np.asarray(value)
    if arr.shape != () or arr.dtype.kind not in "US":
        raise error(f"{where}: must be one text string, got {arr.dtype} of shape {arr.shape}")
    v = arr.item()
    if isinstance(v, bytes):
        try:
            v = v.decode("utf-8")
        except UnicodeDecodeError:
            raise error(f"{where}: not UTF-8 text") from None
    return v

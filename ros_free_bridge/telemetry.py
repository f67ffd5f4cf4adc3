"""Crash-safe per-tick telemetry: a compact binary log that is valid up to its last flush.

File layout (little-endian):

1. one header line: ``DFTEL1 <json>\\n``; the JSON holds ``joint_names``, ``rate_hz``,
   ``fields`` (name, numpy dtype string, shape of each record field) and free ``meta``;
2. fixed-size records, one per tick, packed as the numpy structured dtype the header
   describes.

A crash can leave at most a partial last record, which :func:`read_telemetry` ignores, so
the file is always readable up to the last completed write. Records are flushed to the
operating system every ``flush_every`` ticks (default: every tick at 100 Hz costs a few
microseconds) and ``os.fsync``-ed on close. Events (faults, safety stops, the reason a run
ended) go to a JSON-lines file beside it, flushed at once: ``<name>.events.jsonl``.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ros_free_bridge.errors import BridgeError

MAGIC = b"DFTEL1 "


def tick_dtype(n_joints: int) -> np.dtype:
    """The record of one control tick. Angles in rad, times in s, latencies in s."""
    n = n_joints
    return np.dtype(
        [
            ("t", "<f8"),  # seconds since the loop started (monotonic)
            ("tick", "<u4"),
            ("lateness", "<f4"),  # wake-up time minus deadline
            ("compute", "<f4"),  # time spent in the tick before the bus write
            ("target", "<f4", (n,)),  # what upstream asked for (before the safety filter)
            ("command", "<f4", (n,)),  # what was sent
            ("measured", "<f4", (n,)),  # present positions read this tick (NaN if not read)
            ("intervention", "u1", (n,)),  # safety.Intervention flags per joint
            ("state", "u1"),  # bridge state code (see loop.State)
            ("faults", "<u4"),  # fault bit flags (see loop.Fault)
            ("actor_frame", "<i4"),  # newest actor frame index used (-1: none)
            ("generator_latency", "<f4"),  # seconds: generator compute for the newest frame
            ("retarget_latency", "<f4"),
            ("end_to_end", "<f4"),  # actor frame arrival -> bus write of its command (NaN if n/a)
        ]
    )


class TelemetryWriter:
    """Append tick records and events. Use as a context manager so close() always runs."""

    def __init__(self, path, joint_names, rate_hz: float, meta: dict | None = None, flush_every: int = 1):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.dtype = tick_dtype(len(joint_names))
        header = {
            "joint_names": list(joint_names),
            "rate_hz": float(rate_hz),
            "fields": [[name, self.dtype[name].base.str, list(self.dtype[name].shape)] for name in self.dtype.names],
            "meta": meta or {},
            "created_unix": time.time(),
        }
        self._fh = open(self.path, "wb")
        self._fh.write(MAGIC + json.dumps(header).encode() + b"\n")
        self._fh.flush()
        # the events belong to this run's tick file, which was just truncated: start them afresh too
        self._events = open(self.path.with_name(self.path.name + ".events.jsonl"), "w", buffering=1)
        self._buf = np.zeros(1, dtype=self.dtype)
        self._raw = self._buf.view(np.uint8)  # the record's bytes, zeroed before each tick
        self._fields = {name: self._buf[name] for name in self.dtype.names}  # views made once, not per tick
        self._flush_every = max(1, int(flush_every))
        self._pending = 0
        self.records = 0

    @property
    def events_path(self) -> Path:
        return Path(self._events.name)

    def record(self, **fields) -> None:
        """Append one tick; fields not given are zero. Unknown names are a KeyError."""
        self._raw[:] = 0
        views = self._fields
        for key, value in fields.items():
            views[key][0] = value
        self._fh.write(self._raw)
        self.records += 1
        self._pending += 1
        if self._pending >= self._flush_every:
            self._fh.flush()
            self._pending = 0

    def event(self, kind: str, **info) -> None:
        """Log an event (fault, stop, mode change) with the wall-clock and monotonic time."""
        info = {"kind": kind, "unix": time.time(), "monotonic": time.monotonic(), **info}
        self._events.write(json.dumps(info, default=_jsonable) + "\n")

    def close(self) -> None:
        if self._fh.closed:
            return
        self._fh.flush()
        os.fsync(self._fh.fileno())
        self._fh.close()
        self._events.flush()
        self._events.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _jsonable(obj):
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    return str(obj)


@dataclass
class Telemetry:
    """A telemetry file read back: ``records`` is a structured array (see :func:`tick_dtype`)."""

    joint_names: tuple[str, ...]
    rate_hz: float
    records: np.ndarray
    meta: dict
    events: list[dict]
    truncated_bytes: int  #: bytes of a partial last record (a crash mid-write), ignored

    def commands_trajectory(self, robot: str = ""):
        """The commands the run sent, as a RobotTrajectory at the control rate. The root is
        left at the origin, upright: a free robot is placed on the ground by whoever plays it."""
        from retarget import RobotTrajectory

        n = len(self.records)
        if n < 2:
            raise BridgeError("telemetry: fewer than 2 ticks were recorded; nothing to replay or check")
        return RobotTrajectory(self.joint_names, self.records["command"].astype(np.float64), np.zeros((n, 3)),
                               np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)), self.rate_hz, robot,
                               {"source": "telemetry commands"})


def read_telemetry(path) -> Telemetry:
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise BridgeError(f"{path}: cannot read telemetry ({exc.strerror})") from None
    if not raw.startswith(MAGIC) or b"\n" not in raw:
        raise BridgeError(f"{path}: not a telemetry file (missing the {MAGIC.decode().strip()} header)")
    line, body = raw.split(b"\n", 1)
    try:
        header = json.loads(line[len(MAGIC):])
        dtype = np.dtype([(name, base, tuple(shape)) for name, base, shape in header["fields"]])
    except (ValueError, KeyError, TypeError) as exc:
        raise BridgeError(f"{path}: telemetry header is malformed ({exc})") from None
    whole = len(body) // dtype.itemsize * dtype.itemsize
    records = np.frombuffer(body[:whole], dtype=dtype).copy()
    events = []
    events_path = path.with_name(path.name + ".events.jsonl")
    if events_path.exists():
        for text in events_path.read_text().splitlines():
            try:
                events.append(json.loads(text))
            except ValueError:
                break  # a partial last line after a crash
    return Telemetry(tuple(header["joint_names"]), float(header["rate_hz"]), records, header.get("meta", {}),
                     events, len(body) - whole)

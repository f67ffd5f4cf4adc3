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
            ("correction", "<f4", (n,)),  # the balance stabilizer's change to the target (0: off)
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

    def commands_trajectory(self, robot: str = "", without_correction: bool = False):
        """The commands the run sent, as a RobotTrajectory at the control rate. The root is
        left at the origin, upright: a free robot is placed on the ground by whoever plays it.
        ``without_correction``: minus the balance stabilizer's corrections (the ``correction``
        field; absent in files of older runs: none), i.e. the commands as the loop would have
        sent them open loop, for a check that runs its own stabilizer."""
        from retarget import RobotTrajectory

        n = len(self.records)
        if n < 2:
            raise BridgeError("telemetry: fewer than 2 ticks were recorded; nothing to replay or check")
        q = self.records["command"].astype(np.float64)
        if without_correction and "correction" in self.records.dtype.names:
            q = q - self.records["correction"].astype(np.float64)
        return RobotTrajectory(
            self.joint_names,
            q,
            np.zeros((n, 3)),
            np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)),
            self.rate_hz,
            robot,
            {"source": "telemetry commands"},
        )


#: Record fields every reader of a telemetry file relies on (plot, replay, demo's check).
REQUIRED_FIELDS = ("t", "tick", "target", "command", "measured", "state", "faults")
#: Per-joint fields: each must have one column per name in ``joint_names``.
JOINT_FIELDS = ("target", "command", "measured", "intervention")
#: Control rates a telemetry file may declare (Hz).
RATE_RANGE = (1.0, 10000.0)
#: Largest record accepted (bytes): a 1000-joint robot's record is about 14 kB.
MAX_RECORD_BYTES = 1 << 20
#: Largest commanded angle accepted, rad (the safety filter clips to the joint limits).
MAX_COMMAND_RAD = 1e3


def read_telemetry(path) -> Telemetry:
    """Read a telemetry file and its events. Anything a run cannot have written raises
    BridgeError naming the file (or the events file) and the field: a missing or malformed
    header (``joint_names`` unique texts, ``rate_hz`` in :data:`RATE_RANGE`, ``fields`` with
    plain numeric dtypes, the :data:`REQUIRED_FIELDS`, one column per joint name), no
    records, NaN or absurd commands. A partial last record and a partial last events line
    (a crash mid-write) are ignored, as the writer promises."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise BridgeError(f"{path}: cannot read telemetry ({exc.strerror})") from None
    if not raw.startswith(MAGIC) or b"\n" not in raw:
        raise BridgeError(
            f"{path}: not a telemetry file (missing the {MAGIC.decode().strip()} header line); give the "
            "telemetry.dftl a run wrote"
        )
    line, body = raw.split(b"\n", 1)
    header = _header(path, line[len(MAGIC) :])
    dtype = header["dtype"]
    whole = len(body) // dtype.itemsize * dtype.itemsize
    records = np.frombuffer(body[:whole], dtype=dtype).copy()
    if len(records) == 0:
        raise BridgeError(
            f"{path}: holds no tick records (the run ended before its first tick, or the file was cut); "
            "nothing to plot or replay"
        )
    command = records["command"]
    bad = ~np.isfinite(command) | (np.abs(command) > MAX_COMMAND_RAD)
    if bad.any():
        tick, joint = (int(i) for i in np.argwhere(bad.reshape(len(records), -1))[0])
        raise BridgeError(
            f"{path}: record {tick}: the command of joint {header['joint_names'][joint]!r} is "
            f"{float(command.reshape(len(records), -1)[tick, joint])!r}, which the bridge never sends; "
            "the file is damaged"
        )
    events = read_events(path.with_name(path.name + ".events.jsonl"))
    return Telemetry(
        tuple(header["joint_names"]), header["rate_hz"], records, header["meta"], events, len(body) - whole
    )


def _header(path: Path, text: bytes) -> dict:
    """The header's fields checked: joint_names, rate_hz, meta and the record dtype."""

    def bad(field: str, why: str) -> BridgeError:
        return BridgeError(f"{path}: header field {field!r}: {why}; the file is damaged or not written by the bridge")

    try:
        header = json.loads(text)
    except (ValueError, RecursionError) as exc:
        raise BridgeError(
            f"{path}: the telemetry header is not valid JSON ({str(exc)[:100]}); the file is damaged"
        ) from None
    if not isinstance(header, dict):
        raise BridgeError(f"{path}: the telemetry header must be a JSON object, got {type(header).__name__}")
    for key in ("joint_names", "rate_hz", "fields"):
        if key not in header:
            raise bad(key, "missing")
    names = header["joint_names"]
    if not isinstance(names, list) or not names or not all(isinstance(n, str) and n for n in names):
        raise bad("joint_names", "must be a non-empty list of joint names (text)")
    if len(set(names)) != len(names):
        raise bad("joint_names", "lists a joint twice")
    rate = header["rate_hz"]
    lo, hi = RATE_RANGE
    if isinstance(rate, bool) or not isinstance(rate, (int, float)) or not lo <= rate <= hi:
        raise bad("rate_hz", f"{rate!r} is not a control rate in {lo:g}-{hi:g} Hz")
    fields = header["fields"]
    if not isinstance(fields, list) or not fields:
        raise bad("fields", "must be a list of [name, dtype, shape]")
    spec = []
    for item in fields:
        if (
            not isinstance(item, list)
            or len(item) != 3
            or not isinstance(item[0], str)
            or not isinstance(item[1], str)
            or not isinstance(item[2], list)
            or not all(isinstance(k, int) and not isinstance(k, bool) and 0 <= k <= 100000 for k in item[2])
        ):
            raise bad("fields", f"entry {item!r:.80} is not [name, dtype, shape]")
        try:
            base = np.dtype(item[1])
        except (TypeError, ValueError, SyntaxError):
            raise bad("fields", f"{item[0]!r} has an unknown dtype {item[1]!r}") from None
        if base.kind not in "biuf" or base.hasobject or base.names is not None:
            raise bad("fields", f"{item[0]!r} has dtype {item[1]!r}; records hold plain numbers only")
        spec.append((item[0], base, tuple(item[2])))
    try:
        dtype = np.dtype(spec)
    except (TypeError, ValueError) as exc:
        raise bad("fields", f"not a record layout ({str(exc)[:80]})") from None
    if not 0 < dtype.itemsize <= MAX_RECORD_BYTES:
        raise bad("fields", f"a record of {dtype.itemsize} bytes")
    missing = [f for f in REQUIRED_FIELDS if f not in dtype.names]
    if missing:
        raise bad("fields", f"lacks {', '.join(missing)}")
    for f in JOINT_FIELDS:
        if f in dtype.names and dtype[f].shape != (len(names),):
            raise bad("joint_names", f"{len(names)} names, but field {f!r} has shape {dtype[f].shape}; they must agree")
    meta = header.get("meta", {})
    if not isinstance(meta, dict):
        raise bad("meta", f"must be a JSON object, got {type(meta).__name__}")
    return {"joint_names": names, "rate_hz": float(rate), "dtype": dtype, "meta": meta}


def read_events(path) -> list[dict]:
    """The events of ``<telemetry>.events.jsonl`` (none if the file is absent). A partial last
    line (a crash mid-write) is ignored; any other line that is not one JSON object with a
    ``kind`` raises BridgeError naming the file and the line."""
    path = Path(path)
    if not path.exists():
        return []
    try:
        text = path.read_bytes().decode("utf-8")
    except OSError as exc:
        raise BridgeError(f"{path}: cannot read the events file ({exc.strerror})") from None
    except UnicodeDecodeError as exc:
        raise BridgeError(
            f"{path}: the events file is not UTF-8 text (byte {exc.start}); it is damaged or not an "
            "events file; remove or replace it"
        ) from None
    lines = text.split("\n")
    complete, last = lines[:-1], lines[-1]  # text after the last newline: a line cut by a crash
    events = []
    for k, line in enumerate(complete, start=1):
        if not line.strip():
            continue
        try:
            event = json.loads(line)
        except (ValueError, RecursionError):
            event = None
        if not isinstance(event, dict) or not isinstance(event.get("kind"), str):
            raise BridgeError(
                f"{path}, line {k}: not an event (one JSON object with a 'kind' per line); the events "
                "file is damaged; remove or repair that line"
            )
        events.append(event)
    if last.strip():
        try:
            event = json.loads(last)
            if isinstance(event, dict) and isinstance(event.get("kind"), str):
                events.append(event)
        except (ValueError, RecursionError):
            pass
    return events

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
            # the loop's target before its stabilizer and safety filter; float64, the filter's own
            # precision, so that filtering it again is exact (Telemetry.open_loop_commands)
            ("target", "<f8", (n,)),
            ("correction", "<f4", (n,)),  # the balance stabilizer's change to the target (0: off)
            ("command", "<f4", (n,)),  # what was sent
            ("measured", "<f4", (n,)),  # present positions read this tick (NaN if not read)
            # the IMU sample read this tick, as the stabilizer got it (firmware_cfg.readings.ImuReading,
            # the IMU's frame; NaN: no IMU): rate rad/s, specific force m/s², orientation w, x, y, z
            ("imu_gyro", "<f4", (3,)),
            ("imu_accel", "<f4", (3,)),
            ("imu_quat", "<f4", (4,)),
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
        ``without_correction``: the commands the loop would have sent without its balance
        stabilizer (:meth:`open_loop_commands`), for a check that runs its own stabilizer."""
        self._require_ticks()
        source = "telemetry commands"
        if without_correction:
            q, source = self.open_loop_commands()
        else:
            q = self.records["command"].astype(np.float64)
        return self._trajectory(q, robot, source)

    def _require_ticks(self) -> None:
        if len(self.records) < 2:
            raise BridgeError("telemetry: fewer than 2 ticks were recorded; nothing to replay or check")

    def _trajectory(self, q: np.ndarray, robot: str, source: str):
        """Joint angles (T, n) rad at the control rate as a RobotTrajectory, the root left at the
        origin, upright."""
        from retarget import RobotTrajectory

        n = len(q)
        return RobotTrajectory(
            self.joint_names,
            q,
            np.zeros((n, 3)),
            np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)),
            self.rate_hz,
            robot,
            {"source": source},
        )

    def _corrected(self) -> bool:
        """The stabilizer changed some tick's target."""
        r = self.records
        return "correction" in r.dtype.names and bool(np.any(r["correction"]))

    def open_loop_commands(self) -> tuple[np.ndarray, str]:
        """(commands (T, n) rad, how they were found): what the loop's safety filter made of its
        targets before the balance stabilizer, i.e. what it would have sent open loop.

        A run with no correction: its commands. Otherwise the recorded ``target`` of each tick
        (the loop's pre-stabilizer target) is filtered again from the filter's start state and
        limits (the ``safety_filter`` event, and ``degraded`` ones); ``command - correction``
        would not do, since where the filter clipped a corrected command that difference is not
        what the filter makes of the target. Files written before the ``safety_filter`` event:
        ``command - correction``, said so in the returned text. Raises BridgeError when the
        events do not describe the run: on a joint the stabilizer never touched, the filtered
        targets must give the recorded commands back."""
        r = self.records
        command = r["command"].astype(np.float64)
        if not self._corrected():
            return command, "telemetry commands (no stabilizer correction)"
        correction = r["correction"].astype(np.float64)
        settings = _filter_settings(self)
        if settings is None:
            return command - correction, (
                "telemetry commands minus the stabilizer's corrections (a file without the safety_filter "
                "event: inexact on ticks where the safety filter changed a corrected command)"
            )
        q = _refilter(r["target"].astype(np.float64), *settings)
        untouched = np.cumsum(correction != 0, axis=0) == 0  # no correction on this joint yet
        err = np.where(untouched, np.abs(q - command), 0.0)
        if err.max() > OPEN_LOOP_TOLERANCE:
            k, j = np.unravel_index(int(np.argmax(err)), err.shape)
            raise BridgeError(
                f"telemetry: the recorded targets filtered with the safety_filter event's limits give "
                f"{q[k, j]:.4f} rad for joint {self.joint_names[j]!r} at record {k}, but the run sent "
                f"{command[k, j]:.4f} rad; the events file does not belong to this run (or was edited)"
            )
        return q, "the loop's pre-stabilizer targets through its safety filter (open loop)"

    def loop_replay(self, robot: str = ""):
        """What a check needs to play the run's balance feedback as the loop did: (the loop's
        pre-stabilizer targets as a RobotTrajectory at the control rate, a callable making the
        loop's safety filter (:class:`LoopFilter`) afresh, the readings' age in ticks: 1 with the
        split-phase bus, else 0). None for a run without stabilizer corrections or without the
        ``safety_filter`` event (then :meth:`open_loop_commands` is what there is)."""
        self._require_ticks()
        settings = _filter_settings(self) if self._corrected() else None
        if settings is None:
            return None
        targets = self._trajectory(
            self.records["target"].astype(np.float64), robot, "the loop's pre-stabilizer targets"
        )
        age = 1 if any(e.get("kind") == "split_phase_bus" for e in self.events) else 0
        names = tuple(self.joint_names)

        def make_filter(joint_names, start):  # sim.check.CheckConfig.command_filter; the run's own start
            if tuple(joint_names) != names:
                raise BridgeError(
                    f"telemetry: the check's joints {tuple(joint_names)} are not the run's {names}; "
                    "check the run with the robot it used"
                )
            return LoopFilter(*settings)

        return targets, make_filter, age


#: rad: on a joint the stabilizer never corrected, the targets filtered again and the sent commands
#: (recorded as float32) may differ by this much
OPEN_LOOP_TOLERANCE = 1e-5


def _filter_settings(tel: Telemetry):
    """(dt s, start (n,), JointLimits, [(record, max_velocity (n,)), ...]) from the ``safety_filter``
    and ``degraded`` events; None for a file without them. Raises BridgeError naming the
    field of a malformed event."""
    from ros_free_bridge.control.safety import JointLimits

    found = [e for e in tel.events if e["kind"] == "safety_filter"]
    if not found:
        return None
    event, n = found[-1], len(tel.joint_names)

    def joints(e: dict, key: str) -> np.ndarray:
        v = e.get(key)
        try:
            arr = np.asarray(v, dtype=np.float64)
        except (TypeError, ValueError):
            arr = np.empty(0)
        if arr.shape != (n,) or not np.all(np.isfinite(arr)):
            raise BridgeError(
                f"telemetry events: {e['kind']} field {key!r} must be {n} finite numbers (one per joint); "
                "the events file is damaged"
            )
        return arr

    dt = event.get("dt")
    if isinstance(dt, bool) or not isinstance(dt, (int, float)) or abs(dt * tel.rate_hz - 1.0) > 1e-6:
        raise BridgeError(
            f"telemetry events: safety_filter field 'dt' is {dt!r}, not the period of the file's rate "
            f"{tel.rate_hz:g} Hz; the events file does not belong to this run"
        )
    try:
        limits = JointLimits(
            tel.joint_names, *(joints(event, k) for k in ("lower", "upper", "max_velocity", "max_acceleration"))
        )
    except BridgeError as exc:
        raise BridgeError(f"telemetry events: safety_filter: {exc}; the events file is damaged") from None
    changes = []
    for e in tel.events:
        if e["kind"] == "degraded" and "record" in e:
            k = e["record"]
            if isinstance(k, bool) or not isinstance(k, int) or k < 0:
                raise BridgeError(f"telemetry events: degraded field 'record' is {k!r}; the events file is damaged")
            changes.append((k, joints(e, "max_velocity")))
    return float(dt), joints(event, "start"), limits, sorted(changes, key=lambda c: c[0])


class LoopFilter:
    """The loop's safety filter replayed, one tick per call (q (n,) rad -> the command): a
    SafetyFilter of period ``dt`` s started at ``start`` with ``limits``, its velocity limits
    replaced from call k on for each (k, max_velocity) in ``changes``."""

    def __init__(self, dt: float, start: np.ndarray, limits, changes: list):
        from ros_free_bridge.control.safety import SafetyFilter

        self._filter = SafetyFilter(limits, dt)
        self._filter.reset(start)
        self._limits, self._pending, self._k = limits, list(changes), 0

    def __call__(self, q: np.ndarray) -> np.ndarray:
        from ros_free_bridge.control.safety import JointLimits

        lim = self._limits
        while self._pending and self._pending[0][0] <= self._k:
            vmax = self._pending.pop(0)[1]
            self._filter.limits = JointLimits(lim.names, lim.lower, lim.upper, vmax, lim.max_acceleration)
        self._k += 1
        return self._filter.step(q)[0]


def _refilter(target: np.ndarray, dt: float, start: np.ndarray, limits, changes: list) -> np.ndarray:
    """The targets (T, n) through :class:`LoopFilter`."""
    f = LoopFilter(dt, start, limits, changes)
    out = np.empty_like(target)
    for k in range(len(target)):
        out[k] = f(target[k])
    return out


#: Record fields every reader of a telemetry file relies on (plot, replay, demo's check).
REQUIRED_FIELDS = ("t", "tick", "target", "command", "measured", "state", "faults")
#: Per-joint fields: each must have one column per name in ``joint_names``.
JOINT_FIELDS = ("target", "command", "measured", "intervention")
#: Control rates a telemetry file may declare (Hz).
RATE_RANGE = (1.0, 10000.0)
#: Largest record accepted (bytes): a 1000-joint robot's record is about 21 kB.
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

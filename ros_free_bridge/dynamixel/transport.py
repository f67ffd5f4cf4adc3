"""The control loop's :class:`~ros_free_bridge.transports.base.Transport` for one Dynamixel bus.

Per tick (protocol 2.0): ``write_goal`` is one SYNC_WRITE of Goal Position; ``read_state``
one FAST_SYNC_READ of Present Position plus ``slow_per_cycle`` servos' status blocks
(round robin) and, where the config has one, the IMU device's READ. With
:meth:`DynamixelTransport.pipeline` on, the cycle is split: ``write_goal`` sends the goals
and the read request, and the next ``read_state`` takes the reply that arrived meanwhile.
Protocol 1.0 buses are read servo by servo. Units: rad, rad/s, N·m, °C, V (mapping in
:mod:`.servos`); every failure is a BridgeError naming the servo. The transport composes
:mod:`.bus` (port and primitives), :mod:`.cycle` (packets, split phase), :mod:`.servos`
(units, limits), :mod:`.recovery` (alerts, reboot, watchdog) and :mod:`.imu`; the design
and the safety rules are in docs/dynamixel.md.
"""

from __future__ import annotations

import atexit
import time
import weakref
from dataclasses import dataclass, field

import dynamixel_sdk as sdk
import numpy as np

from firmware_cfg.config import BusConfig
from firmware_cfg.device_models import load_device_model
from firmware_cfg.servo_models import load_servo_model
from ros_free_bridge.dynamixel.bus import DynamixelBus
from ros_free_bridge.dynamixel.cycle import BusCycle
from ros_free_bridge.dynamixel.imu import ImuDevice
from ros_free_bridge.dynamixel.recovery import Recovery, RecoveryPolicy
from ros_free_bridge.dynamixel.servos import ServoSet
from ros_free_bridge.errors import BridgeError
from ros_free_bridge.transports.base import STOP_POLICIES, JointState

_NONE: frozenset[int] = frozenset()


@dataclass
class DynamixelStats:
    """Counters for diagnostics: cycles, retries, fallbacks and recoveries."""

    cycles: int = 0
    read_retries: int = 0
    alerts: int = 0
    reboots: int = 0
    watchdog_trips: int = 0
    fast_sync_read: bool = True
    notes: list[str] = field(default_factory=list)
    imu_reads: int = 0  #: IMU samples read (0 on a bus without an IMU device)
    imu_misses: int = 0  #: IMU reads that got no valid reply


class DynamixelTransport:
    """:class:`~ros_free_bridge.transports.base.Transport` for one Dynamixel bus of a
    robot's hardware config. Use as a context manager or open()/close().

    ``port`` overrides the config's; ``joint_names`` picks and orders the joints;
    ``stop_policy`` 'hold' or 'limp' (close, errors, exit); ``recovery``: what a hardware
    alert triggers; ``retries`` per transfer; ``slow_per_cycle`` status blocks read per
    tick; ``latency_ms``: the adapter's latency for reply timeouts where its latency timer
    cannot be read. ``apply_settings`` (attribute, default True): write the config's RAM
    settings at open."""

    def __init__(
        self,
        bus: BusConfig,
        *,
        port: str | None = None,
        joint_names: tuple[str, ...] | None = None,
        stop_policy: str = "hold",
        recovery: RecoveryPolicy | None = None,
        retries: int = 2,
        slow_per_cycle: int = 1,
        latency_ms: float = 16.0,
    ) -> None:
        if bus.protocol not in ("1.0", "2.0"):
            raise BridgeError(
                f"bus {bus.name!r} uses {bus.protocol}; the Dynamixel transport needs protocol 1.0 or 2.0"
            )
        if stop_policy not in STOP_POLICIES:
            raise BridgeError(f"stop_policy {stop_policy!r} is not one of {STOP_POLICIES}")
        self.servos = ServoSet(bus, joint_names)
        self.joint_names = self.servos.joint_names
        self.bus_cfg = bus
        self.stop_policy = stop_policy
        self.slow_per_cycle = max(0, int(slow_per_cycle))
        self.apply_settings = True
        self.stats = DynamixelStats()
        imu_cfg = next((d for d in bus.devices if d.role == "imu"), None)
        labels = {s.cfg.id: s.cfg.joint for s in self.servos.servos}
        if imu_cfg is not None:
            labels[imu_cfg.id] = f"{imu_cfg.model} IMU"
        self.bus = DynamixelBus(
            port or bus.port, bus.baud, bus.protocol_version, retries=retries, latency_ms=latency_ms, names=labels
        )
        #: the bus's IMU device (the OP3's OpenCR), read once per cycle; None without one
        self.imu = (
            None
            if imu_cfg is None
            else ImuDevice(self.bus, imu_cfg.id, load_device_model(imu_cfg.model), self.stats.notes)
        )
        self.recovery = Recovery(self.bus, self.servos, recovery or RecoveryPolicy(), self.stats)
        self.cycle = BusCycle(self.bus, self.servos, self.stats, self.imu)
        self._atexit = None
        self._pipelined = False
        self._alerted: frozenset[int] = _NONE  # servos whose alert the last fast reply handled

    # ------------------------------------------------------------------ life cycle
    def open(self) -> None:
        """Open the port, check every servo's model (and the IMU device's), read torque and
        EEPROM limits, apply the RAM settings, build the packets, read the positions."""
        if self.bus.port is not None:
            return
        self.bus.open()
        try:
            if self.bus.latency_note:
                self.stats.notes.append(self.bus.latency_note)
            for sv in self.servos.servos:
                self._check_model(sv)
            if self.imu is not None:
                self.imu.open()
            for i, sv in enumerate(self.servos.servos):
                self.servos.torque_on[i] = self.servos.torque_cmd[i] = bool(self.bus.read(sv.cfg.id, sv.torque)[0])
                self._narrow_to_eeprom(i)
            if self.apply_settings:
                for sv in self.servos.servos:
                    self.recovery.apply_ram_settings(sv)
            self.cycle.make_groups()
            self._read_positions()
        except BaseException:
            self.bus.close()
            raise
        ref = weakref.ref(self)
        self._atexit = lambda: ref() is not None and ref().close()
        atexit.register(self._atexit)

    def _check_model(self, sv) -> None:
        number = self.bus.ping(sv.cfg.id)
        if number != sv.model.model_number:
            try:
                found = load_servo_model(number, protocol=sv.model.protocol).name
            except Exception:
                found = "unknown model"
            raise BridgeError(
                f"{self.bus.label(sv.cfg.id)}: model number {number} ({found}) but the config "
                f"says {sv.model.name} ({sv.model.model_number}); fix the config or the wiring"
            )

    def close(self) -> None:
        """Apply the stop policy and release the port (safe to call twice)."""
        if self.bus.port is None:
            return
        try:
            self.safe_stop(self.stop_policy)
        except BridgeError:
            if self.stop_policy == "limp":
                self.recovery.broadcast_torque_off()
        finally:
            self.bus.close()
            self.cycle.reset()
            if self._atexit is not None:
                atexit.unregister(self._atexit)
                self._atexit = None

    def __enter__(self) -> DynamixelTransport:
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ Transport
    def read_state(self) -> JointState:
        """Present positions of every servo, plus the status block of ``slow_per_cycle``
        servos (round robin) and the IMU's sample. In the split-phase cycle (:meth:`pipeline`)
        the positions are the reply to the request that ``write_goal`` sent on the previous
        tick, and ``stamp`` is when that request left; the last request of the call (a
        status or IMU READ) is sent but collected on the next bus transfer."""
        cyc, imu = self.cycle, self.imu
        if imu is not None:
            imu.take()  # a split-phase IMU reply collected before the last goal write
        pending = cyc.pending
        if pending is not None and (
            pending[0] == "bulk" and self.slow_per_cycle == 1 or pending[0] == "fast" and self.slow_per_cycle == 0
        ):
            state = self._read_arrived()
            if state is not None:
                return state
        try:
            if cyc.pending is not None:
                cyc.settle()
                if imu is not None:
                    imu.take()
            if cyc.fast_ready is not None:
                self._finish_fast()
            else:
                self._read_positions()
            if cyc.slow_ready is not None:
                self._finish_slow()
            if cyc.bulk_status is not None:
                (i, val, error), cyc.bulk_status = cyc.bulk_status, None
                self._apply_status(i, val, error, alert_handled=i in self._alerted)
            self._read_status_blocks()
            if imu is not None:
                self._cycle_imu()
        except BridgeError:
            self._on_error()
            raise
        self.stats.cycles += 1
        return self.servos.reading(None if imu is None else imu.reading)

    def _read_status_blocks(self) -> None:
        """This tick's status blocks, round robin (one rides with each split-phase bulk
        read); in the split phase without bulk reads the last is sent, not waited for."""
        bulk = self._pipelined and self.cycle.bulk is not None
        k = min(self.slow_per_cycle, len(self.servos)) - bulk
        imu_due = self.imu is not None and self.imu.due()
        for j in range(k):
            i = self.cycle.next_status_servo()
            if not (self._pipelined and not bulk and j == k - 1 and not imu_due and self.cycle.send_slow(i)):
                self._read_slow(i)

    def _read_arrived(self) -> JointState | None:
        """The split-phase cycle's common tick in one pass (:meth:`BusCycle.take_arrived`):
        the same values :meth:`read_state`'s general path gives (tested); None when the
        reply is not all there or not clean, and the general path takes over."""
        got = self.cycle.take_arrived()
        if got is None:
            return None
        ticks, status = got
        self.servos.set_position(ticks)
        self.servos.state.stamp = self.cycle.fast_sent
        self._alerted = _NONE
        try:
            if status is not None:
                self._apply_status(status[0], status[1], 0)
            state = self.servos.reading(None if self.imu is None else self.imu.reading)
            if self.imu is not None:
                self._cycle_imu()
        except BridgeError:
            self._on_error()
            raise
        self.stats.cycles += 1
        return state

    def _cycle_imu(self) -> None:
        """The IMU device's read of this bus cycle: in the split-phase cycle the request is
        sent now and its reply collected before the next transfer (the sample reaches the
        next reading, stamped when the request left); otherwise one blocking READ."""
        imu = self.imu
        if not imu.due():
            imu.reading = None
        elif self._pipelined:
            self.cycle.send_imu()
        else:
            imu.read()
        self.stats.imu_reads, self.stats.imu_misses = imu.reads, imu.misses

    def write_goal(self, positions: np.ndarray) -> None:
        q = np.asarray(positions, float)
        if q.shape != (len(self.servos),):
            raise BridgeError(f"Dynamixel: write_goal needs shape ({len(self.servos)},), got {q.shape}")
        ticks = self.servos.goal_ticks(q.tolist())
        try:
            if self._pipelined:
                self.cycle.send_cycle(ticks)
            else:
                self.cycle.send_goals(ticks)
        except BridgeError:
            self._on_error()
            raise

    def pipeline(self, enabled: bool = True) -> bool:
        """Switch the split-phase bus cycle on or off; returns whether it is on.

        On (protocol 2.0 buses whose servos answer FAST_SYNC_READ; elsewhere False and
        nothing changes): ``write_goal`` sends SYNC_WRITE and the read request and returns;
        the next ``read_state`` takes the reply that arrived meanwhile (it waits, up to the
        reply timeout, only for bytes still missing). The loop never blocks for the bus
        time of a cycle; the positions it reads were sampled when the previous tick's
        request reached the servos (``stamp``). With ``slow_per_cycle`` > 0 the request is a
        FAST_BULK_READ that also brings one servo's status block. Faults keep the blocking
        path's policy (a missing or garbled reply is retried at once, then an error naming
        the silent servo); any transfer first collects a reply still on the wire."""
        if self.bus.port is not None:
            self.cycle.settle()
        self.cycle.fast_ready = None
        self._pipelined = bool(enabled) and self.cycle.fast is not None and self.stats.fast_sync_read
        if self._pipelined and self.slow_per_cycle > 0 and self.cycle.bulk is None and not self.cycle.bulk_refused:
            self.cycle.make_bulk()
        return self._pipelined

    @property
    def pipelined(self) -> bool:
        """Whether the split-phase bus cycle is on (:meth:`pipeline`)."""
        return self._pipelined

    def set_torque(self, enabled: bool) -> None:
        if enabled:
            self._read_positions()
            self.cycle.send_goals(self.servos.present_goal())
        for i, sv in enumerate(self.servos.servos):
            self.servos.torque_cmd[i] = enabled
            self.bus.write(sv.cfg.id, sv.torque, 1 if enabled else 0)
            self.servos.torque_on[i] = enabled

    def safe_stop(self, policy: str = "hold") -> None:
        if policy not in STOP_POLICIES:
            raise BridgeError(f"safe_stop: policy {policy!r} is not one of {STOP_POLICIES}")
        if policy == "limp":
            self.servos.torque_cmd[:] = False
            self.recovery.broadcast_torque_off()
            failures = []
            for i, sv in enumerate(self.servos.servos):
                try:
                    self.bus.write(sv.cfg.id, sv.torque, 0)
                    self.servos.torque_on[i] = False
                except BridgeError as exc:
                    failures.append(str(exc))
            if failures:
                raise BridgeError("safe_stop limp: " + "; ".join(failures))
            return
        self._read_positions()
        self.cycle.send_goals(self.servos.present_goal())

    @property
    def lower(self) -> np.ndarray:
        """Joint lower limits (n,) rad in force: the config's, narrowed at ``open`` to the
        servo's EEPROM position limits, so never wider than either."""
        return self.servos.lower.copy()

    @property
    def upper(self) -> np.ndarray:
        return self.servos.upper.copy()

    def position_limits(self) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper) (n,) rad in force; the control loop adopts them after ``open``."""
        return self.lower, self.upper

    def recover(self, joint: str) -> str:
        """Reboot and restore one servo after a hardware alert (:meth:`Recovery.recover`)."""
        return self.recovery.recover(joint)

    # ------------------------------------------------------------------ internals
    def _narrow_to_eeprom(self, i: int) -> None:
        sv = self.servos.servos[i]
        names = (
            ("min_position_limit", "max_position_limit")
            if sv.model.has("min_position_limit")
            else ("cw_angle_limit", "ccw_angle_limit")
            if sv.model.has("cw_angle_limit")
            else None
        )
        if names is None:
            return
        lo_t = self.bus.read(sv.cfg.id, sv.model.register(names[0]))[0]
        hi_t = self.bus.read(sv.cfg.id, sv.model.register(names[1]))[0]
        if lo_t >= hi_t:
            return  # wheel / multi-turn setting: no position limits in EEPROM
        note = self.servos.narrow(i, lo_t, hi_t)
        if note:
            self.stats.notes.append(note)

    def _read_positions(self) -> None:
        """Every position, blocking; a fast reply's alert bits are handled at once."""
        ticks, kind, errors = self.cycle.read_positions()
        if kind == "p1" and self.bus.protocol == 1.0:
            for i, error in enumerate(errors):
                self.recovery.note_p1_error(i, error)
        self.servos.set_position(ticks)
        self.servos.state.stamp = time.monotonic()
        self._alerted = frozenset()
        if kind == "fast" and any(errors):
            self._alerted = self.recovery.on_fast_read_errors(np.array(errors, np.uint8))

    def _finish_fast(self) -> None:
        """Use a collected split-phase position read; a failed one (counted as a retry by
        the settle) is replaced by a blocking read (bounded retries, then an error naming
        the silent servo)."""
        (result, sent), self.cycle.fast_ready = self.cycle.fast_ready, None
        if result != sdk.COMM_SUCCESS:
            self._read_positions()
            return
        self.servos.set_position(self.cycle.fast_values)
        self.servos.state.stamp = sent
        self._alerted = frozenset()
        if any(self.cycle.fast_errors):
            self._alerted = self.recovery.on_fast_read_errors(np.array(self.cycle.fast_errors, np.uint8))

    def _finish_slow(self) -> None:
        """Use a collected split-phase status READ; a failed or refused one is read again
        the blocking way (which retries, and raises on a refusal)."""
        (i, data, result, error), self.cycle.slow_ready = self.cycle.slow_ready, None
        _, _, length = self.cycle.slow_block(i)
        if result == sdk.COMM_SUCCESS and len(data) == length and not error & 0x7F:
            self._apply_status(i, self.cycle.decode_slow(i, bytes(data)), error)
        else:
            self.stats.read_retries += result == sdk.COMM_SUCCESS  # a short or refused reply (failures: the settle)
            self._read_slow(i)

    def _read_slow(self, i: int) -> None:
        data, error = self.cycle.read_slow(i)
        self._apply_status(i, self.cycle.decode_slow(i, data), error)

    def _apply_status(self, i: int, val: dict[str, int], error: int, alert_handled: bool = False) -> None:
        """Servo ``i``'s raw status values into the state (:meth:`ServoSet.apply_units`), a
        tripped bus watchdog recovered, and its status error byte acted on."""
        self.servos.apply_units(i, val)
        if val.get("watchdog", 0) in (-1, 255):
            self.recovery.recover_bus_watchdog()
        self.recovery.status_error(i, error, alert_handled)

    def _on_error(self) -> None:
        """After a communication failure: 'limp' switches torque off by broadcast;
        'hold' leaves the servos on their last goal, which is holding."""
        if self.stop_policy == "limp":
            self.recovery.broadcast_torque_off()

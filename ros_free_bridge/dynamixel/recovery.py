"""What the transport does when a servo raises a hardware alert or its Bus Watchdog trips.

:class:`RecoveryPolicy` says which decoded hardware errors reboot a servo automatically
(then: settings re-applied, goal = present, torque back on if the host had it on; at most
``max_reboots`` per servo and session). :class:`Recovery` acts on a servo's status error
byte (protocol 2.0: the alert bit 0x80 → Hardware Error Status, register 70; protocol 1.0:
the byte's own hardware bits) and records what stays wrong in ``JointState.errors``
(joint → description), which the control loop treats as a hardware fault.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ros_free_bridge.dynamixel.bus import DynamixelBus
from ros_free_bridge.dynamixel.protocol import ALERT_BIT, P1_HARDWARE_MASK, decode_hardware_error
from ros_free_bridge.dynamixel.servos import Servo, ServoSet, servo_tick_limits
from ros_free_bridge.errors import BridgeError


@dataclass(frozen=True)
class RecoveryPolicy:
    """What to do on a hardware alert. ``reboot_on``: the decoded error names for which
    the servo is rebooted automatically (then settings re-applied, goal = present, torque
    back on if it was on); at most ``max_reboots`` per servo per session. Overheating is
    not in the default set: a hot servo must cool down, not restart."""

    reboot: bool = True
    reboot_on: frozenset[str] = frozenset({"overload", "electrical shock", "input voltage"})
    max_reboots: int = 3
    reboot_wait_s: float = 2.0


class Recovery:
    """Alert handling for the servos ``servos`` on ``bus``; counts into ``stats`` (the
    transport's :class:`~ros_free_bridge.dynamixel.transport.DynamixelStats`)."""

    def __init__(self, bus: DynamixelBus, servos: ServoSet, policy: RecoveryPolicy, stats) -> None:
        self.bus, self.servos, self.policy, self.stats = bus, servos, policy, stats

    def status_error(self, i: int, error: int, alert_handled: bool = False) -> None:
        """Act on servo ``i``'s status error byte from a status read: an alert is handled
        (unless ``alert_handled``: the same reply's alert was just acted on), no alert
        clears the servo's entry in ``errors``."""
        if self.bus.protocol == 2.0:
            if error & ALERT_BIT:
                if not alert_handled:
                    self.on_alert(i)
            else:
                self.servos.state.errors.pop(self.servos.joint_names[i], None)
        else:
            self.note_p1_error(i, error)

    def note_p1_error(self, i: int, error: int) -> None:
        """Protocol 1.0: the status error byte's hardware bits name what is wrong, or clear it."""
        joint = self.servos.joint_names[i]
        bits = error & P1_HARDWARE_MASK
        if bits:
            self.servos.state.errors[joint] = ", ".join(decode_hardware_error(bits, 1))
        else:
            self.servos.state.errors.pop(joint, None)

    def on_fast_read_errors(self, errors: np.ndarray) -> frozenset[int]:
        """The fast reply keeps every servo's status error byte (the SDK's group reads drop
        it): a hardware alert (bit 0x80) is handled at once rather than when the round-robin
        status read next reaches that servo. A servo already reported stays with the status
        read (which clears the report once the alert is gone). Returns the servos handled."""
        done = set()
        for i in np.flatnonzero(errors & ALERT_BIT):
            if self.servos.joint_names[i] not in self.servos.state.errors:
                self.on_alert(int(i))
                done.add(int(i))
        return frozenset(done)

    def on_alert(self, i: int) -> None:
        """Read servo ``i``'s register 70 and torque; reboot it when the policy says so,
        else record the error (with why it was not rebooted)."""
        sv, joint = self.servos.servos[i], self.servos.joint_names[i]
        self.stats.alerts += 1
        bits = self.bus.read(sv.cfg.id, sv.model.register("hardware_error_status"))[0]
        names = decode_hardware_error(bits)
        text = ", ".join(names) or "alert without a hardware error bit"
        torque = bool(self.bus.read(sv.cfg.id, sv.torque)[0])
        if not torque:
            self.servos.torque_on[i] = False  # the servo's Shutdown switched torque off
        pol = self.policy
        if pol.reboot and names and set(names) <= pol.reboot_on and sv.reboots < pol.max_reboots:
            try:
                done = self.recover(joint)
                self.stats.notes.append(f"{self.bus.label(sv.cfg.id)}: {done}")
            except BridgeError as exc:
                self.servos.state.errors[joint] = f"{text}; recovery failed: {exc}"
            return
        reason = (
            "policy does not reboot on this"
            if set(names) - pol.reboot_on or not pol.reboot
            else f"already rebooted {sv.reboots} times"
        )
        self.servos.state.errors[joint] = f"{text} (servo ID {sv.cfg.id}; torque {'on' if torque else 'off'}; {reason})"

    def recover(self, joint: str) -> str:
        """Recover one servo after a hardware alert: read register 70, reboot (protocol 2.0),
        wait, re-apply settings, goal = present, torque on if it was on. Returns what was done."""
        i = self.servos.joint_names.index(joint)
        sv = self.servos.servos[i]
        sid = sv.cfg.id
        was_on = bool(self.servos.torque_cmd[i])  # what the host commanded, not what Shutdown left
        has_hw = sv.model.has("hardware_error_status")
        bits = self.bus.read(sid, sv.model.register("hardware_error_status"))[0] if has_hw else 0
        self.bus.reboot(sid)
        self.stats.reboots += 1
        sv.reboots += 1
        self._wait_for_reboot(sid)
        if has_hw:
            left = self.bus.read(sid, sv.model.register("hardware_error_status"))[0]
            if left:
                self.servos.torque_on[i] = False
                raise BridgeError(
                    f"{self.bus.label(sid)}: hardware error persists after REBOOT: "
                    f"{', '.join(decode_hardware_error(left))}; torque stays off, inspect the servo"
                )
        self.servos.torque_on[i] = False  # a reboot switches torque off
        self.apply_ram_settings(sv)
        value, _ = self.bus.read(sid, sv.present)
        self.bus.write(sid, sv.goal, int(np.clip(value, *servo_tick_limits(sv.cfg, sv.model))))
        if was_on:
            self.bus.write(sid, sv.torque, 1)
            self.servos.torque_on[i] = True
        done = (
            f"rebooted after {', '.join(decode_hardware_error(bits)) or 'alert'}; settings re-applied, goal = present"
            + (", torque on" if was_on else "")
        )
        self.servos.state.errors.pop(joint, None)
        return done

    def _wait_for_reboot(self, sid: int) -> None:
        """Poll with PINGs rather than sleeping: every packet on the bus also feeds the other
        servos' Bus Watchdog, which a silent wait of this length would trip."""
        deadline = time.monotonic() + self.policy.reboot_wait_s
        time.sleep(0.02)
        while True:
            try:
                self.bus.ping(sid, retries=0)
                return
            except BridgeError:
                if time.monotonic() > deadline:
                    raise BridgeError(
                        f"{self.bus.label(sid)}: did not come back within "
                        f"{self.policy.reboot_wait_s:.1f} s of REBOOT; power-cycle it"
                    ) from None
                time.sleep(0.01)

    def apply_ram_settings(self, sv: Servo) -> None:
        """Write the RAM settings the config implies (EEPROM ones are provisioning's job)."""
        for name, value in sv.settings.items():
            reg = sv.model.register(name)
            if reg.eeprom:
                continue
            if name == "bus_watchdog":
                self.bus.write(sv.cfg.id, reg, 0)  # clears a tripped watchdog (-1) before a new period
            self.bus.write(sv.cfg.id, reg, value)

    def recover_bus_watchdog(self) -> None:
        """The host was silent for longer than a servo's Bus Watchdog(98) period: tripped
        servos have stopped where they were and refuse goals. For every servo on the bus:
        clear the watchdog (write 0), goal = present, set the period again."""
        for sv in self.servos.servos:
            period = sv.settings.get("bus_watchdog", 0)
            if period <= 0:
                continue
            reg = sv.model.register("bus_watchdog")
            if self.bus.read(sv.cfg.id, reg)[0] not in (-1, 255):
                continue
            self.bus.write(sv.cfg.id, reg, 0)
            ticks = self.bus.read(sv.cfg.id, sv.present)[0]
            self.bus.write(sv.cfg.id, sv.goal, int(np.clip(ticks, *servo_tick_limits(sv.cfg, sv.model))))
            self.bus.write(sv.cfg.id, reg, period)
            self.stats.watchdog_trips += 1
            self.stats.notes.append(
                f"{self.bus.label(sv.cfg.id)}: bus watchdog had expired (host silent > "
                f"{period * 20} ms); cleared, goal = present"
            )

    def broadcast_torque_off(self) -> None:
        """One SYNC_WRITE Torque Enable = 0 to every servo (no reply needed): the cheapest
        way to make the bus safe when individual writes are failing."""
        try:
            self.bus.sync_write(self.servos.servos[0].torque, {sid: 0 for sid in self.servos.ids})
            self.servos.torque_on[:] = False
        except BridgeError:
            pass

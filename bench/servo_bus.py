"""Servo-bus speed: SYNC_WRITE + FAST_SYNC_READ cycles for 20 XM430-W350 servos through the
Dynamixel transport, against the byte-level emulator with wire timing on.

For 1, 2 and 4 Mbit/s it prints, per cycle (median and 99th percentile over the run):

- ``theory``: the bus time of the packets, 10 bits per byte, return delay 0:
  SYNC_WRITE of 20 × 4-byte goals = 7 + 1 + 4 + 20·5 + 2 = 114 bytes, FAST_SYNC_READ
  instruction 7 + 1 + 4 + 20 + 2 = 34 bytes, its reply 7 + 1 + 20·(1 + 1 + 4 + 2) = 168
  bytes; at 1 Mbit/s 1.14 ms + 2.02 ms (the issue's "about 1.1 ms + 2.0 ms");
- ``sdk``: the same two packets sent with bare dynamixel-sdk calls (the baseline, same run);
- ``transport``: our ``write_goal`` + position read (unit conversion, limit checks, retries);
- ``host``: host-side time per cycle = cycle − time spent waiting for the reply's bytes
  (from the end of the read instruction's write to the arrival of the reply's last byte),
  i.e. Python, the SDK's packet code and our code; target < 0.3 ms;
- ``split``: the split-phase cycle the control loop runs (``DynamixelTransport.pipeline``):
  wall time of ``write_goal`` (goals + read request out) plus ``read_state`` called once the
  reply is there: the host's time per cycle with nothing waited for; target < 0.3 ms. Twice:
  positions alone (FAST_SYNC_READ, ``slow_per_cycle`` 0) and with the control loop's setting
  (``slow_per_cycle`` 1: a FAST_BULK_READ that also brings one servo's status block); next to
  the floor under it, the same bytes through bare system calls (tcflush, write, read) with no
  Python work, same run, same port;

then the host CPU per cycle measured with no emulator running (a recorded reply is written
into the pty as the request leaves), ours next to the same work with the bare SDK's groups,
alternating cycle by cycle (:func:`host_cpu`); and a sustained fixed-rate bus loop at
2 Mbit/s and 250 Hz (the target; the ROBOTIS OP3 framework runs 125 Hz), ours next to the
bare SDK on the same clock: achieved rate, ticks that overran or were skipped, lateness.

The emulator runs in a child process (its own interpreter and GIL), so the host figures
are not inflated by the emulator's Python; it still needs CPU (about 0.3-0.6 ms per packet
of 20 servos), which on a loaded 2-core machine delays replies. On a loaded machine the
percentiles show the scheduler's jitter; the medians and the same-run baselines are the
figures to compare, and the load average is printed with them.

    python bench/servo_bus.py [--cycles 400] [--seconds 3] [--quick]
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import os
import select
import statistics
import sys
import termios
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.table import NA, Row, cpu_counters, parse_args, script_main, steal_percent, verdict  # noqa: E402

N_SERVOS = 20
#: FAST_BULK_READ (positions + one 49-byte status block) over FAST_SYNC_READ: request 5 bytes per servo
#: instead of 1, reply 45 bytes more
BULK_EXTRA_BYTES = 4 * N_SERVOS + 45
QUICK = ["--cycles", "60", "--seconds", "1"]
TARGET_HOST_MS = 0.3
TARGET_HZ = 250.0
OP3_FRAMEWORK_HZ = 125.0


def theory_ms(baud: int) -> tuple[float, float]:
    """(sync write, fast sync read instruction + reply) bus time in ms at ``baud``."""
    sw = 7 + 1 + 4 + N_SERVOS * 5 + 2
    fsr = (7 + 1 + 4 + N_SERVOS + 2) + (7 + 1 + N_SERVOS * 8)
    return sw * 10e3 / baud, fsr * 10e3 / baud


NICE = [0]
RT = [0]  # --rt: SCHED_FIFO priority of the emulator and of the sustained loops (0: normal scheduling)


class _Emulator:
    """The bus emulator in a child process, at this bench's --nice."""

    def __init__(self, baud: int, devices=()) -> None:
        from ros_free_bridge.emulators.process import EmulatorProcess

        units = list(range(1, N_SERVOS + 1)) + list(devices)
        self._proc = EmulatorProcess(units, baud, wire_timing=True, nice=NICE[0], realtime=RT[0])
        self.port = self._proc.port

    def stop(self) -> None:
        self._proc.stop()


def _instrument(port) -> dict:
    """Record the arrival time of the last byte read and the end of the last write."""
    marks = {"last_rx": 0.0, "tx_done": 0.0}
    read, write = port.readPort, port.writePort

    def read_port(length):
        data = read(length)
        if data:
            marks["last_rx"] = time.perf_counter()
        return data

    def write_port(packet):
        n = write(packet)
        marks["tx_done"] = time.perf_counter()
        return n

    port.readPort, port.writePort = read_port, write_port
    return marks


def _renice() -> None:
    """Raise this process's scheduling priority by ``--nice`` (negative needs root or
    CAP_SYS_NICE); on a shared, loaded machine it cuts the wake-up latency of the pty
    hand-offs that otherwise dominate the wall-clock figures."""
    if NICE[0]:
        try:
            os.setpriority(os.PRIO_PROCESS, 0, NICE[0])
        except OSError as exc:
            print(f"(--nice {NICE[0]} not applied: {exc.strerror})", file=sys.stderr)


def _pct(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


def bench_baud(baud: int, cycles: int) -> dict:
    import dynamixel_sdk as sdk

    from firmware_cfg.config import load_config, robot_config_path
    from ros_free_bridge.dynamixel.transport import DynamixelTransport

    bus = load_config(robot_config_path("op3"), check_mjcf=False).buses[0]
    bus = dataclasses.replace(bus, baud=baud, devices=())  # the servos alone (the IMU: imu_cost)
    emu = _Emulator(baud)
    try:
        t = DynamixelTransport(bus, port=emu.port, slow_per_cycle=0, latency_ms=20.0)
        t.open()
        try:
            marks = _instrument(t.bus.port)
            q = t.read_state().position
            amp = np.minimum(0.2, 0.5 * (t.upper - t.lower))
            cycle_ms, wait_ms = [], []
            for k in range(cycles + 20):
                goal = np.clip(q + amp * np.sin(0.05 * k), t.lower, t.upper)
                t0 = time.perf_counter()
                t.write_goal(goal)
                t._read_positions()
                t1 = time.perf_counter()
                if k >= 20:  # warm-up
                    cycle_ms.append((t1 - t0) * 1e3)
                    wait_ms.append((marks["last_rx"] - marks["tx_done"]) * 1e3)
            host_ms = [c - w for c, w in zip(cycle_ms, wait_ms)]
            retries = t.stats.read_retries
            fast = t.stats.fast_sync_read

            # split phase (what the control loop runs): write_goal sends the goals and the read
            # request and returns; read_state, called once the reply is surely there, takes it.
            # Their wall time together is the host's time per cycle, with nothing waited for.
            # slow 0: FAST_SYNC_READ of the positions alone; slow 1 (the control loop's setting):
            # FAST_BULK_READ of the positions plus one servo's status block, round robin.
            settle = (sum(theory_ms(baud)) + BULK_EXTRA_BYTES * 10e3 / baud + 3.0) * 1e-3
            split = {}
            for slow in (0, 1):
                t.slow_per_cycle = slow
                t.pipeline(True)
                wall, cpu, late = [], [], 0
                for k in range(cycles + 20):
                    goal = np.clip(q + amp * np.sin(0.05 * k), t.lower, t.upper)
                    c0, t0 = time.thread_time(), time.perf_counter()
                    t.write_goal(goal)
                    c1, t1 = time.thread_time(), time.perf_counter()
                    j = t.cycle.pending[1]
                    need = (t.cycle.bulk[j][0] if j >= 0 else t.cycle.fast).reply_length
                    time.sleep(settle)
                    late += t.bus.port.ser.in_waiting < need
                    c2, t2 = time.thread_time(), time.perf_counter()
                    t.read_state()
                    c3, t3 = time.thread_time(), time.perf_counter()
                    if k >= 20:
                        wall.append((t1 - t0 + t3 - t2) * 1e3)
                        cpu.append((c1 - c0 + c3 - c2) * 1e3)
                t.pipeline(False)
                split[slow] = (wall, cpu, late)
            t.slow_per_cycle = 0

            # the floor under the split-phase figure (same run, same port): the same bytes with
            # bare system calls - discard input, write goals + FAST_SYNC_READ request, read the
            # reply once it is there - and no Python work around them
            fd = t.bus.port._fd
            packets = t.cycle.writer.encode(t.servos.to_ticks(q)) + t.cycle.fast.request
            need = t.cycle.fast.reply_length
            floor_ms, floor_cpu = [], []
            for k in range(cycles + 20):
                c0, t0 = time.thread_time(), time.perf_counter()
                termios.tcflush(fd, termios.TCIFLUSH)
                os.write(fd, packets)
                c1, t1 = time.thread_time(), time.perf_counter()
                time.sleep(settle)
                c2, t2 = time.thread_time(), time.perf_counter()
                got = os.read(fd, need) if select.select([fd], [], [], 0)[0] else b""
                c3, t3 = time.thread_time(), time.perf_counter()
                if k >= 20 and len(got) == need:
                    floor_ms.append((t1 - t0 + t3 - t2) * 1e3)
                    floor_cpu.append((c1 - c0 + c3 - c2) * 1e3)

            # baseline: the same packets with bare SDK calls on the same open port
            port, ph = t.bus.port, t.bus.ph
            w = sdk.GroupSyncWrite(port, ph, 116, 4)
            r = sdk.GroupSyncRead(port, ph, 132, 4)
            for sid in range(1, N_SERVOS + 1):
                w.addParam(sid, [0, 8, 0, 0])
                r.addParam(sid)
            sdk_ms = []
            for k in range(cycles + 20):
                t0 = time.perf_counter()
                w.txPacket()
                port.is_using = False
                r.fastSyncRead()
                t1 = time.perf_counter()
                if k >= 20:
                    sdk_ms.append((t1 - t0) * 1e3)
        finally:
            t.close()
    finally:
        emu.stop()
    sw, fsr = theory_ms(baud)
    return {
        "baud": baud,
        "theory_sw": sw,
        "theory_fsr": fsr,
        "cycle": cycle_ms,
        "sdk": sdk_ms,
        "host": host_ms,
        "wait": wait_ms,
        "retries": retries,
        "fast": fast,
        "split": split[0][0],
        "split_cpu": split[0][1],
        "late": split[0][2] + split[1][2],
        "split_bulk": split[1][0],
        "split_bulk_cpu": split[1][1],
        "floor": floor_ms,
        "floor_cpu": floor_cpu,
    }


#: the IMU's READ in each cycle: instruction 14 bytes + status 11 + 18 data bytes (OpenCR, 32..49)
IMU_READ_BYTES = 14 + 11 + 18


def imu_cost(baud: int, cycles: int) -> dict:
    """What reading the OP3's OpenCR IMU (ID 200) in every bus cycle adds: one transport on
    the op3 bus (20 servos + the OpenCR, emulator with wire timing), its IMU device switched
    on and off cycle by cycle, so the baseline is the same bus without the IMU read, same
    run. Blocking cycle: wall time of write_goal + read_state (``slow_per_cycle`` 0).
    Split-phase cycle: host wall time of read_state + write_goal with every reply already
    there (each preceded by a pause the bytes need)."""
    from firmware_cfg.config import load_config, robot_config_path
    from ros_free_bridge.dynamixel.transport import DynamixelTransport

    bus = dataclasses.replace(load_config(robot_config_path("op3"), check_mjcf=False).buses[0], baud=baud)
    emu = _Emulator(baud, devices=[(d.id, d.model) for d in bus.devices])
    settle = (sum(theory_ms(baud)) + IMU_READ_BYTES * 10e3 / baud + 3.0) * 1e-3
    out = {"blocking": ([], []), "split": ([], [])}
    try:
        t = DynamixelTransport(bus, port=emu.port, slow_per_cycle=0, latency_ms=20.0)
        with t:
            imu, q = t.imu, t.read_state().position
            for k in range(2 * (cycles + 20)):
                t.imu = imu if k % 2 == 0 else None
                t0 = time.perf_counter()
                t.write_goal(q)
                t.read_state()
                if k >= 40:
                    out["blocking"][k % 2].append((time.perf_counter() - t0) * 1e3)
            t.imu = imu
            t.pipeline(True)
            t.write_goal(q)
            for k in range(2 * (cycles + 20)):
                t.imu = imu if k % 2 == 0 else None
                time.sleep(settle)
                t0 = time.perf_counter()
                t.read_state()  # positions in; with the IMU: its READ goes out
                t1 = time.perf_counter()
                time.sleep(settle)
                t2 = time.perf_counter()
                t.write_goal(q)  # with the IMU: its reply collected; goals + next request out
                t3 = time.perf_counter()
                if k >= 40:
                    out["split"][k % 2].append((t1 - t0 + t3 - t2) * 1e3)
            misses = imu.misses
    finally:
        emu.stop()
    return {"baud": baud, "theory": IMU_READ_BYTES * 10e3 / baud, "misses": misses, **out}


def host_cpu(baud: int, cycles: int) -> dict:
    """Host CPU per SYNC_WRITE + FAST_SYNC_READ cycle, ours next to the bare SDK (the
    baseline), alternating cycle by cycle so both see the same machine load.

    No emulator runs while measuring: after the transport has opened against the emulator,
    its thread is stopped and a recorded reply of the 20 servos is written into the pty the
    moment the FAST_SYNC_READ request leaves, so nothing is ever waited for and no other
    Python shares the core. ``time.thread_time`` of one cycle is then our code (or the
    SDK's) + pyserial + the pty system calls: what the host spends per cycle."""
    import dynamixel_sdk as sdk

    from firmware_cfg.config import load_config, robot_config_path
    from ros_free_bridge.dynamixel import protocol as dp
    from ros_free_bridge.dynamixel.transport import DynamixelTransport
    from ros_free_bridge.emulators import DynamixelBusEmulator

    bus = dataclasses.replace(load_config(robot_config_path("op3"), check_mjcf=False).buses[0], baud=baud, devices=())
    emu = DynamixelBusEmulator(servos=range(1, N_SERVOS + 1), baud=baud, wire_timing=False, return_delay_us=0.0).start()
    t = DynamixelTransport(bus, port=emu.port_path, slow_per_cycle=0, latency_ms=20.0)
    try:
        t.open()
        q = t.read_state().position
        emu._stop.set()  # bench-only use of the emulator's internals: the host is alone on the pty from here
        emu._thread.join()
        emu._thread = None
        master = emu._master
        reply = dp.encode_fast_status(
            [(0, sid, (2048 + 7 * sid).to_bytes(4, "little")) for sid in range(1, N_SERVOS + 1)]
        )
        port = t.bus.port
        write = port.writePort

        def write_and_answer(packet):
            n = write(packet)
            if packet[7] == dp.FAST_SYNC_READ:
                os.write(master, reply)
            return n

        def drain() -> None:
            try:
                while os.read(master, 65536):
                    pass
            except BlockingIOError:
                pass

        port.writePort = write_and_answer
        w = sdk.GroupSyncWrite(port, t.bus.ph, 116, 4)
        r = sdk.GroupSyncRead(port, t.bus.ph, 132, 4)
        for sid in range(1, N_SERVOS + 1):
            w.addParam(sid, [0, 8, 0, 0])
            r.addParam(sid)
        ticks_per_rad = 4096 / (2 * np.pi)

        def ours(k: int) -> None:
            t.write_goal(np.clip(q + 0.2 * np.sin(0.05 * k), t.lower, t.upper))
            t._read_positions()

        def bare_sdk(k: int) -> None:  # the same work with the SDK's groups: convert, pack, send, read, unpack
            goal = np.clip(q + 0.2 * np.sin(0.05 * k), t.lower, t.upper)
            for sid, v in zip(range(1, N_SERVOS + 1), np.rint(2048 + goal * ticks_per_rad).astype(int).tolist()):
                w.changeParam(sid, list(v.to_bytes(4, "little", signed=True)))
            w.txPacket()
            port.is_using = False
            r.fastSyncRead()
            port.is_using = False
            np.array([r.getData(sid, 132, 4) for sid in range(1, N_SERVOS + 1)]) / ticks_per_rad

        per = {"ours": [], "sdk": []}
        for k in range(cycles + 20):
            for name, fn in (("ours", ours), ("sdk", bare_sdk)):
                drain()
                c0 = time.thread_time()
                fn(k)
                c1 = time.thread_time()
                if k >= 20:
                    per[name].append((c1 - c0) * 1e3)
        drain()
    finally:
        t.close()
        emu.stop()
    return per


def _sdk_loop_baseline(port_name: str, baud: int):
    """The pre-numpy hot path as a baseline: dynamixel-sdk's stock PortHandler (its reply
    loops poll the port without sleeping) and groups, plus the same one-servo status READ
    per tick. Returns (tick function, close function)."""
    import dynamixel_sdk as sdk

    port = sdk.PortHandler(port_name)
    port.openPort()
    port.setBaudRate(baud)
    ph = sdk.PacketHandler(2.0)
    w = sdk.GroupSyncWrite(port, ph, 116, 4)
    r = sdk.GroupSyncRead(port, ph, 132, 4)
    for sid in range(1, N_SERVOS + 1):
        w.addParam(sid, [0, 8, 0, 0])
        r.addParam(sid)
    slow = [0]

    def tick(goal_ticks) -> None:
        for sid, v in zip(range(1, N_SERVOS + 1), goal_ticks):
            w.changeParam(sid, list(int(v).to_bytes(4, "little", signed=True)))
        w.txPacket()
        port.is_using = False
        try:  # the SDK raises IndexError on a truncated fast reply; a retry would follow in the transport
            if r.fastSyncRead() == sdk.COMM_SUCCESS:
                [r.getData(sid, 132, 4) for sid in range(1, N_SERVOS + 1)]
        except IndexError:
            pass
        port.is_using = False
        ph.readTxRx(port, slow[0] + 1, 98, 49)  # bus watchdog .. present temperature: read_state's status block
        port.is_using = False
        slow[0] = (slow[0] + 1) % N_SERVOS

    return tick, port.closePort


def sustained(baud: int, hz: float, seconds: float, use_sdk: bool = False, split: bool = True) -> dict:
    """A bus-only fixed-rate loop at ``hz``: per tick, goals out and a full ``read_state``
    (positions + one servo's status block). Ours: the transport on ros_free_bridge's
    clock (sleep, then spin the last 0.5 ms) with GC in the slack and a short GIL switch
    interval (ros_free_bridge.control.realtime), with the split-phase cycle the control loop uses
    (``split``; positions are then the reply to the previous tick's request).
    ``use_sdk``: the same ticks through the bare SDK (:func:`_sdk_loop_baseline`, blocking)
    on the same clock, without the GC measures."""
    from firmware_cfg.config import load_config, robot_config_path
    from ros_free_bridge.control.clock import FixedRateClock
    from ros_free_bridge.control.realtime import LoopGc, realtime_priority, switch_interval
    from ros_free_bridge.dynamixel.transport import DynamixelTransport

    bus = dataclasses.replace(load_config(robot_config_path("op3"), check_mjcf=False).buses[0], baud=baud, devices=())
    emu = _Emulator(baud)
    lateness, busy = [], []
    clock = FixedRateClock(hz)
    n = int(seconds * hz)
    try:
        if use_sdk:
            tick, close = _sdk_loop_baseline(emu.port, baud)
            goal0 = np.full(N_SERVOS, 2048.0)

            def step(k: int) -> None:
                tick(np.rint(goal0 + 65.0 * np.sin(2 * np.pi * 0.5 * k / hz)).astype(int).tolist())

            gc_ctx, si_ctx = contextlib.nullcontext(), contextlib.nullcontext()
        else:
            t = DynamixelTransport(bus, port=emu.port, slow_per_cycle=1, latency_ms=20.0)
            t.open()
            close = t.close
            q = t.read_state().position
            t.pipeline(split)

            def step(k: int) -> None:  # as the control loop: read (the reply to the last request), then write
                t.read_state()
                t.write_goal(np.clip(q + 0.1 * np.sin(2 * np.pi * 0.5 * k / hz), t.lower, t.upper))

            gc_ctx, si_ctx = LoopGc(), switch_interval()
        try:
            # the stock SDK polls the port without sleeping: at SCHED_FIFO it would hold a core, so the
            # baseline loop keeps normal scheduling (its emulator is SCHED_FIFO like ours under --rt)
            with gc_ctx as lgc, si_ctx, realtime_priority(0 if use_sdk else RT[0]):
                clock.start()
                start = time.monotonic()
                for k in range(n):
                    tk = clock.wait()
                    step(k)
                    done = time.monotonic()
                    lateness.append(tk.lateness * 1e3)
                    busy.append((done - tk.woke) * 1e3)
                    if lgc is not None:
                        lgc.collect_in_slack(tk.due + clock.period - done)
                elapsed = time.monotonic() - start
        finally:
            close()
    finally:
        emu.stop()
    return {
        "hz": n / elapsed,
        "overruns": int(np.sum(np.asarray(busy) + np.asarray(lateness) > 1e3 / hz)),
        "skipped": clock.missed,
        "n": n,
        "busy": busy,
        "lateness": lateness,
    }


def rows(quick: bool = False, argv: list[str] = ()) -> list[Row]:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cycles", type=int, default=400)
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--bauds", default="1000000,2000000,4000000")
    ap.add_argument(
        "--nice",
        type=int,
        default=0,
        help="scheduling priority for host and emulator, e.g. -10 (needs root); default 0",
    )
    ap.add_argument(
        "--rt",
        type=int,
        default=0,
        help="SCHED_FIFO priority (1-99, needs CAP_SYS_NICE) for the emulator and the sustained loops: "
        "the bus then answers like hardware on a busy machine; default 0 (normal scheduling)",
    )
    args = parse_args(ap, argv, quick, QUICK)
    NICE[0] = args.nice
    RT[0] = args.rt
    _renice()

    print(
        f"servo bus benchmark: {N_SERVOS} × XM430-W350, emulator with wire timing in a child process; "
        f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}, nice {args.nice}, "
        f"{'SCHED_FIFO ' + str(args.rt) if args.rt else 'normal scheduling'}"
    )
    print("times in ms per cycle, median / p99; theory = packet bytes × 10 bits / baud")
    hdr = (
        f"{'baud':>8} {'theory sw+fsr':>15} {'sdk baseline':>14} {'transport':>14} {'reply wait':>12} "
        f"{'host (target <0.3)':>20} {'split phase':>14} retries"
    )
    print(hdr)
    out = []
    host_target = f"< {TARGET_HOST_MS:g}"
    for baud in (int(b) for b in args.bauds.split(",")):
        r = bench_baud(baud, args.cycles)
        m = statistics.median
        th = r["theory_sw"] + r["theory_fsr"]
        print(
            f"{baud:>8} {r['theory_sw']:6.2f}+{r['theory_fsr']:.2f}={th:4.2f} "
            f"{m(r['sdk']):6.2f}/{_pct(r['sdk'], 99):5.2f} {m(r['cycle']):6.2f}/{_pct(r['cycle'], 99):5.2f} "
            f"{m(r['wait']):5.2f}/{_pct(r['wait'], 99):5.2f} {m(r['host']):9.3f}/{_pct(r['host'], 99):6.3f}"
            f"{' ok' if m(r['host']) < TARGET_HOST_MS else ' OVER':>5} {m(r['split']):7.3f}/{_pct(r['split'], 99):6.3f}"
            f" (CPU {m(r['split_cpu']):.3f}; with a status block {m(r['split_bulk']):.3f}, CPU "
            f"{m(r['split_bulk_cpu']):.3f}; bare I/O floor {m(r['floor']):.3f}, CPU {m(r['floor_cpu']):.3f})"
            f" {r['retries']:>5}"
            + ("" if r["fast"] else "  (SYNC_READ fallback)")
            + (f"  ({r['late']} split-phase replies not complete after theory + 3 ms)" if r["late"] else "")
        )
        mbit = f"{baud / 1e6:g} Mbit/s"
        out.append(
            Row(
                f"bus cycle, sync write + fast sync read, 20 servos @ {mbit} (ms median; theory {th:.2f}; "
                "baseline bare SDK)",
                m(r["cycle"]),
                m(r["sdk"]),
                "",
                NA,
            )
        )
        out.append(
            Row(
                f"host-side time per bus cycle @ {mbit}, wall clock: cycle minus reply wait "
                "(ms median; load shows here)",
                m(r["host"]),
                "",
                host_target,
                verdict(m(r["host"]) < TARGET_HOST_MS),
            )
        )
        out.append(
            Row(
                f"host-side time per split-phase bus cycle @ {mbit}, FAST_SYNC_READ, wall clock: write_goal + "
                f"read_state with the reply already there (ms median; its CPU {m(r['split_cpu']):.3f}; baseline: "
                f"the same bytes with bare system calls; load {os.getloadavg()[0]:.1f})",
                m(r["split"]),
                m(r["floor"]),
                host_target,
                verdict(m(r["split"]) < TARGET_HOST_MS),
            )
        )
        out.append(
            Row(
                f"the same with the control loop's setting (slow_per_cycle 1: FAST_BULK_READ + one status block) "
                f"@ {mbit} (ms median; its CPU {m(r['split_bulk_cpu']):.3f}; baseline: bare system calls)",
                m(r["split_bulk"]),
                m(r["floor"]),
                host_target,
                verdict(m(r["split_bulk"]) < TARGET_HOST_MS),
            )
        )
    ic = imu_cost(2_000_000, max(40, args.cycles // 4))
    m = statistics.median
    for mode, what in (
        ("blocking", "blocking cycle (write_goal + read_state), wall clock"),
        ("split", "split-phase cycle (read_state + write_goal, replies already there), host wall clock"),
    ):
        mine, base = ic[mode]
        print(
            f"IMU (OpenCR, ID 200) read in every cycle at 2 Mbit/s, {what}: with {m(mine):.3f} ms, without "
            f"{m(base):.3f} ms (adds {m(mine) - m(base):.3f}; its bytes on the wire {ic['theory']:.3f} ms)"
        )
        out.append(
            Row(
                f"op3 bus cycle with the OpenCR IMU read @ 2 Mbit/s, {what} (ms median; the IMU READ's bytes "
                f"on the wire {ic['theory']:.3f} ms; baseline: the same bus without the IMU, same run)",
                m(mine),
                m(base),
                "",
                NA,
            )
        )
    hc = host_cpu(2_000_000, args.cycles)
    m = statistics.median
    print(
        f"host CPU per cycle at 2 Mbit/s (reply injected, no emulator running, nothing waited for): ours median "
        f"{m(hc['ours']):.3f} ms (p99 {_pct(hc['ours'], 99):.3f}), bare dynamixel-sdk {m(hc['sdk']):.3f} ms "
        f"(p99 {_pct(hc['sdk'], 99):.3f}); target < {TARGET_HOST_MS} ms"
    )
    out.append(
        Row(
            "host CPU per bus cycle @ 2 Mbit/s, write goals + fast sync read + convert (ms median; baseline bare SDK)",
            m(hc["ours"]),
            m(hc["sdk"]),
            host_target,
            verdict(m(hc["ours"]) < TARGET_HOST_MS),
        )
    )
    runs = {}
    for name, use_sdk, split in (
        ("ours, split phase", False, True),
        ("ours, blocking cycle", False, False),
        ("bare SDK", True, False),
    ):
        cpu0 = cpu_counters()
        r = runs[name] = sustained(2_000_000, TARGET_HZ, args.seconds, use_sdk=use_sdk, split=split)
        r["steal"] = steal_percent(cpu0, cpu_counters())
        print(
            f"sustained {TARGET_HZ:.0f} Hz at 2 Mbit/s, {name}: {r['hz']:.1f} Hz; "
            f"{r['overruns']}/{r['n']} ticks overran, "
            f"{r['skipped']} skipped; lateness p50 {m(r['lateness']):.3f} / p99 {_pct(r['lateness'], 99):.3f} ms; "
            f"busy per tick p50 {m(r['busy']):.2f} / p99 {_pct(r['busy'], 99):.2f} ms of {1e3 / TARGET_HZ:.1f}; "
            f"load {os.getloadavg()[0]:.2f}; CPU time stolen by the host {r['steal']:.1f} %"
        )
    mine, blocking, base = runs.values()
    sched = f"; --rt {RT[0]}: emulator and our loop SCHED_FIFO" if RT[0] else ""
    sched += (
        f"; load {os.getloadavg()[0]:.1f}; CPU time stolen by the host {mine['steal']:.1f} % (ours), "
        f"{base['steal']:.1f} % (SDK)"
    )
    out.append(
        Row(
            f"sustained bus loop @ 2 Mbit/s, {TARGET_HZ:.0f} Hz asked (Hz achieved; ROBOTIS OP3 framework "
            f"{OP3_FRAMEWORK_HZ:.0f} Hz; baseline bare SDK{sched})",
            mine["hz"],
            base["hz"],
            "",
            NA,
        )
    )
    out.append(
        Row(
            f"ticks overrun + skipped in the sustained {TARGET_HZ:.0f} Hz bus loop (baseline bare SDK{sched})",
            f"{mine['overruns']} + {mine['skipped']} / {mine['n']}",
            f"{base['overruns']} + {base['skipped']} / {base['n']}",
            f"{TARGET_HZ:.0f} Hz sustained: 0",
            verdict(mine["overruns"] + mine["skipped"] == 0),
        )
    )
    out.append(
        Row(
            f"the same, ours with the blocking cycle (write, then wait for the read's reply; baseline bare SDK{sched})",
            f"{blocking['overruns']} + {blocking['skipped']} / {blocking['n']}",
            f"{base['overruns']} + {base['skipped']} / {base['n']}",
            "",
            NA,
        )
    )
    out.append(
        Row(
            f"bus loop lateness p99 @ {TARGET_HZ:.0f} Hz (ms; baseline bare SDK{sched})",
            _pct(mine["lateness"], 99),
            _pct(base["lateness"], 99),
            f"< {0.2e3 / TARGET_HZ:.1f}",
            verdict(_pct(mine["lateness"], 99) < 0.2e3 / TARGET_HZ),
        )
    )
    return out


def main(argv: list[str] | None = None) -> int:
    return script_main(rows, argv)


if __name__ == "__main__":
    raise SystemExit(main())

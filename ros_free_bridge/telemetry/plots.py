"""Figures of a run from its telemetry: commands vs measurements, timing, safety.

Each function writes one PNG (matplotlib, Agg backend) and returns its path.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ros_free_bridge.control.loop import Fault, State
from ros_free_bridge.control.safety import Intervention
from ros_free_bridge.telemetry.log import Telemetry


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(plt, fig, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def plot_joints(tel: Telemetry, path: Path) -> Path:
    """One panel per joint: target (upstream), command (sent) and measured angle, rad."""
    plt = _pyplot()
    r = tel.records
    n = len(tel.joint_names)
    cols = 4
    rows = int(np.ceil(n / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 2.2 * rows), sharex=True, squeeze=False)
    for j, name in enumerate(tel.joint_names):
        ax = axes[j // cols][j % cols]
        ax.plot(r["t"], r["target"][:, j], lw=0.8, color="0.6", label="target")
        ax.plot(r["t"], r["command"][:, j], lw=1.2, label="command")
        ax.plot(r["t"], r["measured"][:, j], lw=1.0, ls="--", label="measured")
        ax.set_title(name, fontsize=9)
    for k in range(n, rows * cols):
        axes[k // cols][k % cols].axis("off")
    axes[0][0].legend(fontsize=7)
    for ax in axes[-1]:
        ax.set_xlabel("time (s)")
    return _save(plt, fig, path)


def plot_timing(tel: Telemetry, path: Path) -> Path:
    """Tick lateness and compute time, stage latencies and end-to-end latency, ms."""
    plt = _pyplot()
    r = tel.records
    fig, (a, b) = plt.subplots(2, 1, figsize=(10, 6), sharex=True)
    period_ms = 1e3 / tel.rate_hz
    a.plot(r["t"], r["lateness"] * 1e3, lw=0.6, label="tick lateness")
    a.plot(r["t"], r["compute"] * 1e3, lw=0.6, label="tick compute")
    a.axhline(period_ms, color="r", lw=0.8, ls=":", label=f"period {period_ms:.1f} ms")
    a.set_ylabel("ms")
    a.legend(fontsize=8)
    for field, label in (
        ("generator_latency", "generator"),
        ("retarget_latency", "retarget"),
        ("end_to_end", "end to end"),
    ):
        v = r[field] * 1e3
        ok = np.isfinite(v)
        b.plot(r["t"][ok], v[ok], ".", ms=2, label=label)
    b.set_ylabel("ms")
    b.set_xlabel("time (s)")
    b.legend(fontsize=8)
    return _save(plt, fig, path)


def plot_safety(tel: Telemetry, path: Path) -> Path:
    """Bridge state, safety interventions per kind and faults over time."""
    plt = _pyplot()
    r = tel.records
    fig, (a, b, c) = plt.subplots(3, 1, figsize=(10, 6), sharex=True)
    a.step(r["t"], r["state"], where="post")
    a.set_yticks([s.value for s in State], [s.name for s in State], fontsize=7)
    for flag in (Intervention.NONFINITE, Intervention.POSITION, Intervention.VELOCITY, Intervention.ACCELERATION):
        b.plot(r["t"], ((r["intervention"] & flag) > 0).sum(axis=1), lw=0.8, label=flag.name.lower())
    b.set_ylabel("joints clamped")
    b.legend(fontsize=7)
    for k, flag in enumerate(f for f in Fault if f):
        hit = (r["faults"] & flag) > 0
        if hit.any():
            c.plot(r["t"][hit], np.full(hit.sum(), k), "|", ms=8, label=flag.name.lower())
    c.set_yticks([k for k, f in enumerate(f for f in Fault if f)], [f.name.lower() for f in Fault if f], fontsize=6)
    c.set_xlabel("time (s)")
    return _save(plt, fig, path)


def plot_all(tel: Telemetry, out_dir: Path) -> list[Path]:
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    return [
        plot_joints(tel, out_dir / "joints.png"),
        plot_timing(tel, out_dir / "timing.png"),
        plot_safety(tel, out_dir / "safety.png"),
    ]

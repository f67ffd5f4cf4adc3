"""Check reports: a JSON summary and a markdown page with matplotlib plots.

Files are written under a temporary name and renamed, so a report is complete or
absent. Plots (PNG, Agg backend, no display needed):
- ``joints.png``: each joint's measured angle, command and limits (rad) over time;
- ``torque.png``: each servo's drive torque (N m) with its stall torque;
- ``balance.png``: centre-of-mass and measured-ZMP margins to the support polygon (mm),
  root height (m) and torso tilt (deg); the entry transition (before 0 s) shaded.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from sim.check import CheckResult, lift_offs, steps_taken


def _atomic_write_text(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".partial")
    tmp.write_text(text)
    tmp.replace(path)


def write_json(result: CheckResult, path) -> Path:
    path = Path(path)
    _atomic_write_text(path, json.dumps(result.summary(), indent=2, allow_nan=False, default=_json_default) + "\n")
    return path


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o).__name__)


def write_report(result: CheckResult, out_dir, stem: str = "check") -> dict[str, Path]:
    """Write ``<stem>.json``, ``<stem>.md`` and the plots into ``out_dir``; return the paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"json": write_json(result, out / f"{stem}.json")}
    paths.update(_plots(result, out, stem))
    paths["markdown"] = out / f"{stem}.md"
    _atomic_write_text(paths["markdown"], markdown(result, {k: v.name for k, v in paths.items() if k.endswith("png")}))
    return paths


def verdict(result: CheckResult) -> str:
    """One line: ``PASS`` (with the number of warnings), or ``FAIL: <reason> at <t> s: <detail>`` (the
    detail says so when it happened while entering the clip's first pose from standing)."""
    if result.passed:
        n = len(result.warnings)
        return "PASS" + (f" ({n} warning{'s' if n != 1 else ''})" if n else "")
    f = result.failures[0]
    return f"FAIL: {f.reason} at {f.time:.2f} s: {f.detail}"


def stabilizer_line(result: CheckResult) -> str:
    """How the check's balance stabilizer ran: on, with its largest correction, or off and why."""
    st = result.metrics.get("stabilizer", {})
    if not st.get("on"):
        return f"stabilizer off ({st.get('why_off', 'not run')})"
    return (
        f"stabilizer on, largest correction {st['max_correction_rad']:.3f} rad "
        f"({st['max_correction_joint']} at {st['max_correction_time_s']:.2f} s)"
    )


def warning_lines(result: CheckResult) -> list[str]:
    """One line per warning: ``warning: <kind> at <t> s: <detail>``."""
    return [f"warning: {w.kind} at {w.time:.2f} s: {w.detail}" for w in result.warnings]


def markdown(result: CheckResult, images: dict[str, str] | None = None) -> str:
    """The check report as Markdown: verdict, findings, summary, per-joint table, then the plots in ``images``."""
    lines = [f"# Physical check: {result.robot} ({result.mode} base)", "", f"**{verdict(result)}**", ""]
    lines += _findings_lines(result)
    lines += _summary_lines(result)
    lines += _joint_table_lines(result)
    lines += _image_lines(images)
    return "\n".join(lines)


def _findings_lines(result: CheckResult) -> list[str]:
    """Warnings, unchecked reasons, robot-reading notes and the failure table, each block only if present."""
    lines: list[str] = []
    if result.warnings:
        lines += ["Warnings (measured, not failures):", ""]
        lines += [f"- {w.kind} at {w.time:.2f} s: {w.detail}" for w in result.warnings]
        lines.append("")
    if result.not_checked:
        lines += ["Not checked (no data to judge by):", ""]
        lines += [f"- {reason}: {why}" for reason, why in result.not_checked.items()]
        lines.append("")
    if result.notes:
        lines += ["How the robot was read:", ""]
        lines += [f"- {note}" for note in result.notes]
        lines.append("")
    if result.failures:
        lines += ["| reason | first at (s) | phase | detail |", "|---|---|---|---|"]
        lines += [f"| {f.reason} | {f.time:.2f} | {f.phase} | {f.detail} |" for f in result.failures]
        lines.append("")
    return lines


def _entry_text(m: dict) -> str:
    """How the simulation started: from the first frame or by a transition from the standing pose."""
    entry, how = m.get("entry_transition_s", 0.0), m.get("entry") or {}
    return (
        f"entered from the standing pose by a {entry:.2f} s minimum-jerk transition (times before 0 s; "
        f"largest move {how.get('largest_move_joint')} {how.get('largest_move_rad', 0.0):.2f} rad)"
        if entry
        else "started in the first frame's pose"
    )


def _foot_slip_text(m: dict) -> str:
    """Largest slide per foot in mm, with the worst stance and the stance counts when known."""
    worst = m.get("worst_stance")
    slip = ", ".join(f"{s * 1000:.1f} mm" for s in m["foot_slip_m"]) or "n/a"
    if worst:
        slip += (
            f" (worst: the {worst['foot']} foot, stance from {worst['start_s']:.2f} s to {worst['end_s']:.2f} s; "
            "stances per foot "
            f"{', '.join(str(n) for n in m['stances'])})"
        )
    return slip


def _steps_text(m: dict) -> str:
    """The robot's steps (by the person's rule, sim.check.steps_as_a_person) and lift-offs."""
    steps, lifts = m.get("steps") or [], lift_offs(m)
    if not steps:
        return f"feet off the floor: {lifts} times"
    return (
        f"steps (counted as a person's are, scaled to the robot): {steps_taken(m)} "
        f"({', '.join(str(n) for n in steps)} per foot); feet off the floor: {lifts} times"
    )


def _summary_lines(result: CheckResult) -> list[str]:
    """The '## Summary' section: timing, stabilizer, contacts, human distance, slip and balance margins."""
    m = result.metrics
    entered, slip = _entry_text(m), _foot_slip_text(m)
    place = m.get("actor_placement")
    return [
        "## Summary",
        "",
        f"- clip {m['duration_s']:.2f} s, simulated {m['simulated_s']:.2f} s; control {m['control_hz']:g} Hz, "
        f"physics {m['physics_hz']:g} Hz; {entered}",
        f"- {stabilizer_line(result)}",
        f"- self-collision ticks: {m['self_collision_ticks']} {m['self_collision_pairs'] or ''}",
        f"- max ground penetration: {_fmt(m['max_ground_penetration_m'], 1000, 'mm')} (feet: "
        f"{_fmt(m.get('max_foot_penetration_m'), 1000, 'mm')})",
        f"- min distance to the human (measured up to 100 mm): {_fmt(m['min_human_distance_m'], 1000, 'mm')}"
        + (
            ""
            if not place
            else f"; the human scaled {place['scale']:.3f}, moved by "
            f"({', '.join(f'{v:.2f}' for v in place['offset_m'])}) m, turned {place['yaw_deg']:.0f} deg"
        ),
        f"- largest slide of a foot within one stance, per foot: {slip}",
        f"- {_steps_text(m)}",
        f"- min centre-of-mass margin: {_fmt(m['min_com_margin_m'], 1000, 'mm')}; min ZMP margin (centre of "
        f"pressure to the support edge): {_fmt(m.get('min_zmp_margin_m'), 1000, 'mm')}; max tilt "
        f"{_fmt(m['max_tilt_deg'], 1, 'deg')}",
        "",
    ]


def _joint_table_lines(result: CheckResult) -> list[str]:
    """The '## Per joint' table: tracking error, torque, saturation and speed per joint."""
    m = result.metrics
    lines = [
        "## Per joint",
        "",
        "| joint | rms err (rad) | max err (rad) | max torque (N m) | stall (N m) | saturated (s) | "
        "max cmd speed (rad/s) | no-load speed (rad/s) | speed hits |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for j in result.joint_names:
        lines.append(
            f"| {j} | {_num(m['tracking_rms_rad'][j])} | {_num(m['tracking_max_rad'][j])} | "
            f"{_num(m['max_abs_torque_nm'][j])} | {_num(m['stall_torque_nm'][j])} | "
            f"{_num(m['torque_saturation_s'][j])} | "
            f"{_num(m['max_command_speed_rad_s'][j])} | {_num(m['no_load_speed_rad_s'][j])} | "
            f"{m['speed_limit_hits'][j]} |"
        )
    lines.append("")
    return lines


def _image_lines(images: dict[str, str] | None) -> list[str]:
    """One section per plot that was written (keys joints_png, torque_png, balance_png)."""
    lines: list[str] = []
    for key, title in (
        ("joints_png", "Joint angle, command and limits"),
        ("torque_png", "Servo torque"),
        ("balance_png", "Balance"),
    ):
        if images and key in images:
            lines += [f"## {title}", "", f"![{title}]({images[key]})", ""]
    return lines


def _num(v) -> str:
    return "n/a" if v is None else f"{v:.3f}"


def _fmt(v, scale: float, unit: str) -> str:
    return "n/a" if v is None or not math.isfinite(v) else f"{v * scale:.1f} {unit}"


def _plots(result: CheckResult, out: Path, stem: str) -> dict[str, Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s, names = result.series, result.joint_names
    t = s["t"]
    n = len(names)
    cols = 4
    rows = math.ceil(n / cols)
    paths = {}

    grid = {"left": 0.06, "right": 0.99, "bottom": 0.07, "top": 0.95, "hspace": 0.45, "wspace": 0.25}
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 1.8 * rows), sharex=True, squeeze=False, gridspec_kw=grid)
    for j, ax in enumerate(axes.flat):
        if j >= n:
            ax.axis("off")
            continue
        ax.plot(t, s["q_cmd"][:, j], "--", color="tab:orange", lw=1, label="command")
        ax.plot(t, s["q"][:, j], color="tab:blue", lw=1, label="measured")
        for lim in (result.lower[j], result.upper[j]):  # none drawn for a joint without known limits
            if np.isfinite(lim):
                ax.axhline(lim, color="tab:red", lw=0.8, ls=":", label="limits" if lim == result.upper[j] else None)
        _light_axes(ax, names[j])
    axes[0, 0].legend(fontsize=7)
    fig.supxlabel("time (s)")
    fig.supylabel("angle (rad)")
    paths["joints_png"] = _save(fig, out / f"{stem}_joints.png")

    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 1.8 * rows), sharex=True, squeeze=False, gridspec_kw=grid)
    stall = result.metrics["stall_torque_nm"]
    for j, ax in enumerate(axes.flat):
        if j >= n:
            ax.axis("off")
            continue
        ax.plot(t, s["torque"][:, j], color="tab:green", lw=1)
        if stall[names[j]] is not None:
            ax.axhline(stall[names[j]], color="tab:red", lw=0.8, ls=":")
            ax.axhline(-stall[names[j]], color="tab:red", lw=0.8, ls=":")
        _light_axes(ax, names[j])
    fig.supxlabel("time (s)")
    fig.supylabel("servo torque (N m)")
    paths["torque_png"] = _save(fig, out / f"{stem}_torque.png")

    fig, axes = plt.subplots(3, 1, figsize=(8, 6), sharex=True, gridspec_kw={"left": 0.1, "right": 0.98, "top": 0.97})
    axes[0].plot(t, s["com_margin"] * 1000, color="tab:purple", label="centre of mass")
    if "zmp_margin" in s:
        axes[0].plot(t, s["zmp_margin"] * 1000, color="tab:olive", lw=0.8, label="ZMP (centre of pressure)")
        axes[0].legend(fontsize=7)
    axes[0].axhline(0, color="tab:red", lw=0.8, ls=":")
    axes[0].set_ylabel("support margin (mm)")
    axes[1].plot(t, s["root_height"], color="tab:blue")
    axes[1].set_ylabel("root height (m)")
    axes[2].plot(t, s["tilt_deg"], color="tab:brown")
    axes[2].set_ylabel("tilt (deg)")
    axes[2].set_xlabel("time (s)")
    for ax in axes:
        if result.first_failure_time is not None:
            ax.axvline(result.first_failure_time, color="k", lw=0.8, ls="--")
        if len(t) and t[0] < 0:  # the entry transition ends where the clip starts
            ax.axvspan(t[0], 0.0, color="0.9", lw=0)
    paths["balance_png"] = _save(fig, out / f"{stem}_balance.png")
    return paths


def _light_axes(ax, title: str) -> None:
    """Few ticks and small labels: drawing 20 small axes stays fast."""
    from matplotlib.ticker import MaxNLocator

    ax.set_title(title, fontsize=8, pad=2)
    ax.xaxis.set_major_locator(MaxNLocator(4))
    ax.yaxis.set_major_locator(MaxNLocator(3))
    ax.tick_params(labelsize=6, length=2, pad=1)


def _save(fig, path: Path) -> Path:
    import matplotlib.pyplot as plt

    tmp = path.with_name(path.stem + ".partial.png")
    fig.savefig(tmp, dpi=72)
    plt.close(fig)
    tmp.replace(path)
    return path

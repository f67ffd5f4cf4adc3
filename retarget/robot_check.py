"""Validate a robot folder (``dualflow-bridge robot check DIR``): every problem with its fix.

Contract: :func:`check_robot_folder` returns a :class:`CheckResult` of problems, to-dos and
notes, each one line ``<file>: <field>: <what is wrong>; <the fix>``: the model loads; every
site, body, geom and joint the profile names exists (all listed); the profile binds as the
retargeter binds it; a free-standing robot has feet and no capsule pair touches standing; the
hardware config maps every actuated joint to one servo within the joint's range. Lines still
marked ``# FILL IN`` and a missing hardware config are to-dos and notes, failures only with
``hardware=True`` (before the first power-on). See docs/retargeting.md, section 8.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from retarget.errors import RetargetError

#: What ``robot init`` puts after a value it had to guess (a comment-only line is not a marker).
MARKER = "# FILL IN"
TOLERANCE = 1e-6  # rad, as firmware_cfg.config.MJCF_TOLERANCE


@dataclass
class CheckResult:
    """Outcome of :func:`check_robot_folder`: one line per problem, to-do and note."""

    folder: Path
    problems: list = field(default_factory=list)
    todos: list = field(default_factory=list)
    notes: list = field(default_factory=list)
    summary: str = ""

    @property
    def ok(self) -> bool:
        return not self.problems


def _marked_lines(path: Path) -> list:
    try:
        return [
            i + 1
            for i, line in enumerate(path.read_text().splitlines())
            if MARKER in line and not line.lstrip().startswith("#")
        ]
    except OSError:
        return []


def _lines(nums: list) -> str:
    if len(nums) == 1:
        return f"line {nums[0]} is"
    shown = ", ".join(str(n) for n in nums[:6]) + (", ..." if len(nums) > 6 else "")
    return f"{len(nums)} lines ({shown}) are"


def check_robot_folder(folder: str | Path, hardware: bool = False) -> CheckResult:
    """Check the robot folder ``folder`` (see the module docstring)."""
    import mujoco

    from firmware_cfg.errors import ConfigError
    from firmware_cfg.registry import HARDWARE_FILE, INIT_HINT, resolve

    folder = Path(folder)
    res = CheckResult(folder)
    P = res.problems.append
    if not folder.is_dir():
        P(f"{folder}: not a folder; give a robot folder (`{INIT_HINT}` makes one)")
        return res
    try:
        robot = resolve(folder)
    except ConfigError as exc:
        P(str(exc))
        return res
    try:
        m = mujoco.MjModel.from_xml_path(str(robot.mjcf))
    except ValueError as exc:
        P(
            f"{robot.mjcf}: MuJoCo cannot load it ({str(exc).splitlines()[0]}); fix the model "
            "(`python -m mujoco.viewer --mjcf FILE` shows the same error)"
        )
        return res
    facts = _ModelFacts.of(m)
    profile = _check_profile(robot, folder, facts, res)
    if robot.hardware is None:
        msg = (
            f"{folder}: no {HARDWARE_FILE}: simulation only; `{INIT_HINT}` writes a skeleton to fill in "
            "(servo IDs, directions, offsets, port)"
        )
        (P if hardware else res.notes.append)(msg)
    else:
        _check_hardware(robot, m, facts.hinges, facts.actuated, facts.ctrl, res)
    _check_left_to_fill(robot, folder, hardware, res)
    res.summary = (
        f"{robot.name}: model {robot.mjcf.name} ({len(facts.actuated)} actuated joints, "
        f"{'free-standing' if facts.floating else 'fixed base'})"
        + (
            f", profile with {len(profile.keypoints)} keypoints, {len(profile.capsules)} capsules, "
            f"{len(profile.collision_pairs)} collision pairs{', feet' if profile.feet else ''}"
            if profile
            else ""
        )
        + (f", hardware config with {robot.hardware.name}" if robot.hardware else "")
    )
    return res


@dataclass
class _ModelFacts:
    """What the checks need from the MJCF: names by kind (body, site, geom, key), hinge joints
    (name -> id), a free root, the actuated hinges in actuator order and their ctrlrange."""

    names: dict
    hinges: dict
    floating: bool
    actuated: list
    ctrl: dict

    @classmethod
    def of(cls, m) -> _ModelFacts:
        import mujoco

        names = {
            kind: {mujoco.mj_id2name(m, obj, i) for i in range(n)} - {None}
            for kind, obj, n in (
                ("body", mujoco.mjtObj.mjOBJ_BODY, m.nbody),
                ("site", mujoco.mjtObj.mjOBJ_SITE, m.nsite),
                ("geom", mujoco.mjtObj.mjOBJ_GEOM, m.ngeom),
                ("key", mujoco.mjtObj.mjOBJ_KEY, m.nkey),
            )
        }
        hinges = {
            mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j): j
            for j in range(m.njnt)
            if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE
        }
        floating = any(m.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE for j in range(m.njnt))
        actuated = []  # hinge names in actuator order
        ctrl = {}
        for a in range(m.nu):
            if m.actuator_trntype[a] == mujoco.mjtTrn.mjTRN_JOINT:
                j = int(m.actuator_trnid[a, 0])
                jn = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j)
                if jn in hinges and jn not in actuated:
                    actuated.append(jn)
                    if m.actuator_ctrllimited[a]:
                        ctrl[jn] = tuple(float(v) for v in m.actuator_ctrlrange[a])
        return cls(names, hinges, floating, actuated, ctrl)


def _check_profile(robot, folder: Path, facts: _ModelFacts, res: CheckResult):
    """The profile's checks (names in the model, feet of a free-standing robot, the stand
    keyframe, binding as the retargeter binds it, capsules apart when standing); the profile or None."""
    from firmware_cfg.registry import INIT_HINT, PROFILE_FILE

    P = res.problems.append
    if robot.profile is None:
        P(f"{folder}: no {PROFILE_FILE}; write one with `{INIT_HINT}` (or copy a bundled robot's and edit it)")
        return None
    from retarget.profile import RetargetProfile

    try:
        profile = RetargetProfile.load(robot.profile)
    except RetargetError as exc:
        P(str(exc))
        return None
    src = str(robot.profile)
    before = len(res.problems)
    _check_names(profile, src, facts, P)
    if facts.floating and not profile.feet:
        P(
            f"{src}: field feet: missing, and {robot.mjcf.name} stands free (it has a free joint); give "
            "feet: {left: {body: ..., corners: [...]}, right: ...} (the soles' corners in the foot bodies' frames), "
            f"or rerun `{INIT_HINT}`"
        )
    if profile.stand_keyframe not in facts.names["key"]:
        res.notes.append(
            f"{src}: field stand_keyframe: the model has no keyframe {profile.stand_keyframe!r}; the "
            'solvers start from its zero pose (qpos0) instead; add <key name="stand" qpos=...> '
            "to the MJCF for a better seed"
        )
    if len(res.problems) == before:
        from retarget.kinematics import RobotKinematics
        from retarget.robot import RetargetRobot

        try:
            rb = RetargetRobot(RobotKinematics.from_xml(robot.mjcf), profile)
        except RetargetError as exc:
            P(str(exc))
        else:
            _check_stand_overlaps(rb, profile, src, P)
    return profile


def _check_names(profile, src: str, facts: _ModelFacts, P) -> None:
    """Every site, body, geom and joint the profile names exists in the model (all listed)."""
    from firmware_cfg.registry import INIT_HINT

    def need(kind, name, f):
        if name not in facts.names[kind]:
            known = sorted(facts.names[kind])
            listed = ", ".join(known[:12]) + (", ..." if len(known) > 12 else "")
            P(
                f"{src}: field {f}: the model has no {kind} {name!r}; name one of its {kind}s ({listed or 'none'}), "
                f"or rerun `{INIT_HINT}`"
            )

    for k in profile.keypoints:
        if k.site is not None:
            need("site", k.site, f"keypoints.{k.human}.site")
        else:
            need("body", k.body, f"keypoints.{k.human}.body")
    for c in profile.capsules.values():
        if c.geom is not None:
            need("geom", c.geom, f"capsules.{c.name}.geom")
        else:
            need("body", c.body, f"capsules.{c.name}.body")
    for side, foot in profile.feet.items():
        need("body", foot.body, f"feet.{side}.body")
        if foot.geom is not None:
            need("geom", foot.geom, f"feet.{side}.geom")
    hinges = facts.hinges
    for group, table in (("joint_limits", profile.joint_limits), ("velocity_limits", profile.velocity_limits)):
        for jn in table:
            if jn not in hinges:
                P(
                    f"{src}: field {group}.{jn}: the model has no hinge joint {jn!r}; use one of "
                    f"{', '.join(list(hinges)[:12])}{', ...' if len(hinges) > 12 else ''}"
                )


def _check_stand_overlaps(rb, profile, src: str, P) -> None:
    """No capsule pair overlaps in the stand pose (no retarget could keep it apart)."""
    if not rb.collision_pairs:
        return
    d = rb.evaluate(rb.x_stand[None])["collision"][0]
    for (a, b), v in zip(rb.collision_pairs, d):
        ra, rb_ = rb.capsules[a].radius, rb.capsules[b].radius
        dist = math.sqrt(max(v + (ra + rb_ + profile.collision_margin) ** 2, 0.0))
        gap = dist - ra - rb_
        if gap < 0:
            P(
                f"{src}: field collision_pairs: [{a}, {b}] overlap by {-1000 * gap:.1f} mm in the stand pose, so "
                "no retarget can keep them apart; shrink their radius or remove the pair"
            )


def _check_left_to_fill(robot, folder: Path, hardware: bool, res: CheckResult) -> None:
    """Lines still marked for filling in (to-dos; problems with ``hardware``), and a missing README."""
    from firmware_cfg.registry import README_FILE

    for path in (robot.profile, robot.hardware):
        if path is None:
            continue
        marked = _marked_lines(path)
        if marked:
            msg = (
                f"{path}: {_lines(marked)} still marked '{MARKER}' (values robot init had to guess); "
                "put in the real robot's values and delete the markers"
            )
            (res.problems.append if hardware else res.todos.append)(msg)
    if not (folder / README_FILE).is_file():
        res.notes.append(f"{folder}: no {README_FILE}; its first heading would describe the robot in `robot list`")


def _check_hardware(robot, m, hinges: dict, actuated: list, ctrl: dict, res: CheckResult) -> None:
    from firmware_cfg.config import load_config
    from firmware_cfg.errors import ConfigError
    from firmware_cfg.registry import parse_mjcf

    P = res.problems.append
    src = str(robot.hardware)
    try:
        cfg = load_config(robot.hardware, check_mjcf=False)
    except ConfigError as exc:
        P(str(exc))
        return
    if cfg.mjcf is not None:
        named = Path(cfg.mjcf).resolve()
        if not named.is_file():
            P(f"{src}: field mjcf: {cfg.mjcf} does not exist; point it at {robot.mjcf} (relative to the file)")
        elif named != robot.mjcf.resolve():
            try:
                included = {Path(e.get("file", "")).name for e in parse_mjcf(named).iter("include")}
            except ConfigError:
                included = set()
            if robot.mjcf.name not in included:
                P(
                    f"{src}: field mjcf: names {named}, but the folder's model is {robot.mjcf}; "
                    "point it at the same model"
                )
    mapped = {}
    free = [j for j in actuated if j not in {s.joint for s in cfg.servos}]  # actuated, no servo yet
    for bi, bus in enumerate(cfg.buses):
        for si, s in enumerate(bus.servos):
            where = f"{src}: buses[{bi}].servos[{si}]"
            mapped[s.joint] = where
            if s.joint not in hinges:
                which = (
                    f"one still without a servo ({', '.join(free)})"
                    if free
                    else f"one of its joints ({', '.join(actuated[:12])}{', ...' if len(actuated) > 12 else ''})"
                )
                P(f"{where}.joint: {s.joint!r} is not a hinge joint of {robot.mjcf.name}; use {which}")
                continue
            if s.joint not in actuated:
                P(
                    f"{where}.joint: {s.joint!r} has no actuator in {robot.mjcf.name}, "
                    "so the simulation cannot drive it; "
                    "add a <position joint=...> actuator or remove the servo"
                )
            j = hinges[s.joint]
            if m.jnt_limited[j]:
                lo, hi, what = float(m.jnt_range[j, 0]), float(m.jnt_range[j, 1]), "the MJCF range"
            elif s.joint in ctrl:
                (lo, hi), what = ctrl[s.joint], "its actuator's ctrlrange (the joint has no range)"
            else:
                continue
            if s.lower < lo - TOLERANCE or s.upper > hi + TOLERANCE:
                P(
                    f"{where}.limits: [{s.lower:.4f}, {s.upper:.4f}] rad is wider than {what} [{lo:.4f}, {hi:.4f}] "
                    f"of joint {s.joint!r}; narrow it to fit"
                )
    missing = [j for j in actuated if j not in mapped]
    if missing:
        P(
            f"{src}: buses: no servo drives the actuated joint(s) {', '.join(missing)}; add one entry per joint "
            "({id: N, joint: NAME, limits: [lo, hi]}), in the MJCF's actuator order"
        )
    order = [s.joint for s in cfg.servos if s.joint in actuated]
    if not missing and order != [j for j in actuated if j in order]:
        res.notes.append(
            f"{src}: the servos are not listed in the MJCF's actuator order; the bridge maps them by "
            "joint name, so this only matters for reading the file"
        )


__all__ = ["CheckResult", "check_robot_folder"]

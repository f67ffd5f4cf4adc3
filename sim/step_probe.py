"""Can this free-standing robot step? Stepping leaders streamed with steps on, judged in physics.

Contract: :func:`probe_steps` streams a few SYNTHETIC stepping leaders (:func:`dualflow.synthetic.make_leader`:
steps on the beat, in place or swaying, some turning or travelling) through the streaming
retargeter with steps on (``StreamingConfig(balance=True, steps=True)``, as the live bridge runs
a robot whose profile says ``streaming_steps: true``) and plays each through the physics check
(:func:`sim.check.check_trajectory`, free base, stabilizer on; ``check_config(robot)`` gives the
check's config, as ``dualflow-bridge robot init`` passes the one ``check`` uses, with the bridge's
safety filter: :func:`ros_free_bridge.robots.bridge_check_config`).
:class:`StepProbe` says whether every clip passed, and per clip the verdict, the first failure
and the steps taken. :func:`choose_step_pace` probes at slower and slower paces
(``StreamingConfig.step_pace``) and returns the first at which every clip passes; ``robot init``
writes the profile's ``streaming_steps`` and ``step_pace`` from it. The step timing was tuned on
the bundled op3; measured with these probes (as ``robot init`` runs them, with the bridge's safety
filter), the published OP3 (servos with 4.5 x the op3's armature, answering at about 3 Hz) passes
all 4 leaders at pace 1 (it fell on 2 at pace 1 while the stabilizer still rolled its ankles on
two feet: sim.stabilizer.default_gains), and the Unitree G1 (6 cm wide soles, position servos at
kp 500) falls at every pace: it keeps its feet planted rather than fall.
"""

from __future__ import annotations

from dataclasses import dataclass, field

#: the leaders' seeds (the default draws: in-place and swaying steps, a turn, travel) and length (s)
PROBE_SEEDS = (0, 1, 2, 3)
PROBE_SECONDS = 6.0
#: the step paces :func:`choose_step_pace` tries, fastest first
PROBE_PACES = (1.0, 1.5, 2.0)


@dataclass(frozen=True)
class ProbeClip:
    """One leader's outcome: ``passed``, the check's ``reason`` and first failure time (s, clip
    time; None when passed), the robot's steps in physics (counted by the person's rule:
    :func:`sim.check.steps_as_a_person`) and the person's (touch-downs)."""

    name: str
    passed: bool
    reason: str
    first_failure_s: float | None
    robot_steps: int
    person_steps: int


@dataclass(frozen=True)
class StepProbe:
    """The probe at one ``pace``: its ``clips`` (:class:`ProbeClip`)."""

    pace: float = 1.0
    clips: list = field(default_factory=list)

    @property
    def passed(self) -> bool:
        return bool(self.clips) and all(c.passed for c in self.clips)

    def summary(self) -> str:
        """One line: how many clips passed, and each failure with its time."""
        ok = sum(c.passed for c in self.clips)
        fails = [f"{c.name} {c.reason} at {c.first_failure_s:.2f} s" for c in self.clips if not c.passed]
        robot, person = sum(c.robot_steps for c in self.clips), sum(c.person_steps for c in self.clips)
        head = f"at step_pace {self.pace:g}: {ok} of {len(self.clips)} stepping leaders pass in physics with steps on"
        return f"{head} ({robot} steps to the leaders' {person})" + ("; " + ", ".join(fails) if fails else "")


def probe_steps(
    robot,
    pace: float = 1.0,
    seeds=PROBE_SEEDS,
    seconds: float = PROBE_SECONDS,
    progress=None,
    check_config=None,
    planner=None,
) -> StepProbe:
    """Stream ``len(seeds)`` stepping leaders for ``robot`` (a bundled name or a robot folder)
    with steps on, the step phases at ``pace`` x their lengths (``StreamingConfig.step_pace``),
    and judge each in physics (module docstring). ``progress(name)`` is called before each clip;
    ``check_config(robot)`` makes the check's :class:`sim.check.CheckConfig` (None: the free-base
    defaults, commands played as they are); ``planner(robot)`` gives the
    :class:`retarget.robot.RetargetRobot` that plans (None: :func:`retarget.robot.load_robot`;
    the bridge's is :func:`ros_free_bridge.robots.planning_robot`, within its loop's limits)."""
    from dualflow.synthetic import make_leader
    from retarget.robot import load_robot, robot_ref
    from retarget.schedule import count_steps
    from retarget.streaming import StreamingConfig, StreamingRetargeter, paced
    from retarget.targets import make_targets
    from sim.check import CheckConfig, check_trajectory, steps_taken

    rb = (planner or load_robot)(robot)
    ref = robot_ref(robot)
    fps = 30.0
    streamer = StreamingRetargeter(rb, fps, paced(StreamingConfig(balance=True, steps=True), pace))
    config = CheckConfig(mode="free") if check_config is None else check_config(robot)
    clips = []
    for seed in seeds:
        motion = make_leader(seconds=seconds, fps=fps, seed=int(seed))
        if progress is not None:
            progress(motion.name)
        res = check_trajectory(streamer.run(motion), config, robot=ref)
        clips.append(
            ProbeClip(
                motion.name,
                bool(res.passed),
                str(res.reason),
                None if res.passed else float(res.first_failure_time),
                steps_taken(res.metrics),
                int(count_steps(make_targets(rb, motion).contacts)),
            )
        )
    return StepProbe(float(pace), clips)


def choose_step_pace(
    robot, paces=PROBE_PACES, progress=None, check_config=None, planner=None
) -> tuple[float | None, list]:
    """The first of ``paces`` at which :func:`probe_steps` passes every clip (None: none did),
    and the probes run (:class:`StepProbe`, in order)."""
    probes = []
    for pace in paces:
        probe = probe_steps(robot, pace, progress=progress, check_config=check_config, planner=planner)
        probes.append(probe)
        if probe.passed:
            return float(pace), probes
    return None, probes

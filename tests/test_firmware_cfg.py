"""The hardware config: the bundled op3 file, and one clear error per kind of mistake."""

from __future__ import annotations

import copy
import math
from pathlib import Path

import pytest
import yaml

from firmware_cfg.config import (
    load_config,
    mjcf_joint_ranges,
    parse_config,
    robot_config_path,
    save_config,
)
from firmware_cfg.errors import ConfigError

OP3 = robot_config_path("op3")
OP3_MJCF = Path(__file__).resolve().parents[1] / "firmware_cfg" / "robots" / "op3" / "op3.xml"
BRIEF_ORDER = (
    "r_sho_pitch l_sho_pitch r_sho_roll l_sho_roll r_el l_el r_hip_yaw l_hip_yaw r_hip_roll "
    "l_hip_roll r_hip_pitch l_hip_pitch r_knee l_knee r_ank_pitch l_ank_pitch r_ank_roll "
    "l_ank_roll head_pan head_tilt"
).split()


def op3_data() -> dict:
    return yaml.safe_load(OP3.read_text())


def test_bundled_op3_config():
    cfg = load_config(OP3, check_mjcf=False)
    assert cfg.robot == "op3" and len(cfg.buses) == 1
    bus = cfg.buses[0]
    assert bus.baud == 2_000_000 and bus.protocol == "2.0" and bus.protocol_version == 2.0
    assert [s.id for s in bus.servos] == list(range(1, 21))
    assert list(cfg.joint_names) == BRIEF_ORDER
    assert {s.model for s in bus.servos} == {"XM430-W350"}
    assert all(s.return_delay_us == 0 for s in bus.servos)
    pi = math.pi
    # the real OP3's axes: the right shoulder lowers and the right knee flexes with negative angles
    expect = {
        "head_pan": (-0.5 * pi, 0.5 * pi),
        "r_sho_roll": (-0.5 * pi, 0.3 * pi),
        "l_sho_roll": (-0.3 * pi, 0.5 * pi),
        "l_knee": (-0.1 * pi, 0.8 * pi),
        "r_knee": (-0.8 * pi, 0.1 * pi),
        "r_hip_yaw": (-0.45 * pi, 0.45 * pi),
        "l_hip_roll": (-0.3 * pi, 0.3 * pi),
        "r_hip_pitch": (-0.4 * pi, 0.4 * pi),
        "l_ank_roll": (-0.45 * pi, 0.45 * pi),
    }
    for joint, (lo, hi) in expect.items():
        s = cfg.servo(joint)
        assert s.lower == pytest.approx(lo, abs=1e-6) and s.upper == pytest.approx(hi, abs=1e-6), joint
    # ROBOTIS's framework maps joint angle = servo angle about the centre tick
    assert all(s.direction == 1 and s.zero_offset == 0.0 for s in bus.servos)
    # the OpenCR sub-controller (IMU) is a device on the same bus
    assert [(d.id, d.model, d.role) for d in bus.devices] == [(200, "OpenCR", "imu")]


def test_op3_limits_never_wider_than_the_mjcf():
    cfg = load_config(OP3)  # validates against the MJCF named in the file
    assert cfg.mjcf == OP3_MJCF.resolve()
    ranges = mjcf_joint_ranges(OP3_MJCF)
    for s in cfg.servos:
        lo, hi = ranges[s.joint]
        assert lo - 1e-6 <= s.lower and s.upper <= hi + 1e-6, s.joint


def test_round_trip_through_save(tmp_path):
    cfg = load_config(OP3, check_mjcf=False)
    out = save_config(cfg, tmp_path / "op3_copy.yaml")
    again = load_config(out, check_mjcf=False)
    assert again.buses == cfg.buses and again.stop_policy == cfg.stop_policy
    assert not (tmp_path / "op3_copy.yaml.tmp").exists()


def mutate(fn) -> dict:
    d = copy.deepcopy(op3_data())
    d.pop("mjcf")
    fn(d)
    return d


def servo(d, i):
    return d["buses"][0]["servos"][i]


@pytest.mark.parametrize(
    "change, pattern",
    [
        (
            lambda d: servo(d, 4).update(id=3),
            r"buses\[0\]\.servos\[4\]\.id: duplicate servo ID 3 \(also at buses\[0\]\.servos\[2\]\.id\)",
        ),
        (lambda d: servo(d, 1).update(joint="r_sho_pitch"), r"servos\[1\]\.joint: duplicate joint 'r_sho_pitch'"),
        (
            lambda d: servo(d, 0).update(model="XM999"),
            r"servos\[0\]\.model: unknown servo model 'XM999'; known: .*XM430-W350",
        ),
        (lambda d: servo(d, 0).update(model="AX-12A"), r"servos\[0\]\.model: AX-12A speaks protocol 1\.0"),
        (
            lambda d: servo(d, 12).update(limits=[-0.3, 3.3]),
            r"servos\[12\]\.limits: .*outside XM430-W350's position range",
        ),
        (lambda d: servo(d, 0).update(zero_offset=2.0), r"servos\[0\]\.limits: .*fix zero_offset"),
        (lambda d: servo(d, 0).update(limits=[1.0, -1.0]), r"servos\[0\]\.limits: lower 1\.0 must be below upper"),
        (lambda d: servo(d, 0).update(direction=2), r"servos\[0\]\.direction: 2 must be 1 or -1"),
        (lambda d: servo(d, 0).update(return_delay_us=3), r"servos\[0\]\.return_delay_us: 3 must be an even integer"),
        (lambda d: servo(d, 0).update(status_return_level=0), r"servos\[0\]\.status_return_level: 0 makes"),
        (
            lambda d: servo(d, 0).update(bus_watchdog_ms=30),
            r"servos\[0\]\.bus_watchdog_ms: 30 must be a multiple of 20",
        ),
        (
            lambda d: servo(d, 0).update(temperature_limit_c=120),
            r"servos\[0\]\.temperature_limit_c: 120 must be an integer 1\.\.100",
        ),
        (
            lambda d: servo(d, 0).update(voltage_limits_v=[5.0, 12.0]),
            r"servos\[0\]\.voltage_limits_v: \[5\.0, 12\.0\] V must satisfy 9\.5",
        ),
        (lambda d: servo(d, 0).update(pid={"p": 800, "q": 1}), r"servos\[0\]\.pid\.q: unknown field"),
        (
            lambda d: servo(d, 0).update(pid={"p": 20000}),
            r"servos\[0\]\.pid\.p: 20000 must be an integer register value",
        ),
        (lambda d: servo(d, 0).update(limts=[0, 1]), r"servos\[0\]\.limts: unknown field"),
        (lambda d: servo(d, 0).pop("limits"), r"servos\[0\]\.limits: required"),
        (lambda d: d["buses"][0].update(baud=1234), r"servos\[0\]\.model: XM430-W350 cannot run at the bus baud 1234"),
        (lambda d: d["buses"][0].update(protocol="3.0"), r"buses\[0\]\.protocol: '3\.0' is not one of"),
        (lambda d: d["buses"][0].pop("port"), r"buses\[0\]\.port: required"),
        (lambda d: d.update(stop_policy="freeze"), r"stop_policy: 'freeze' is not one of"),
        (
            lambda d: d["servo_defaults"].update(profile_velocity=-1.0),
            r"servos\[0\]\.profile_velocity: -1\.0 must be >= 0",
        ),
        (
            lambda d: d["buses"][0]["devices"][0].update(id=5),
            r"buses\[0\]\.devices\[0\]\.id: duplicate bus ID 5 \(also at buses\[0\]\.servos\[4\]\.id\)",
        ),
        (
            lambda d: d["buses"][0]["devices"][0].update(role="camera"),
            r"buses\[0\]\.devices\[0\]\.role: 'camera' is not one of",
        ),
        (lambda d: d["buses"][0]["devices"][0].pop("model"), r"buses\[0\]\.devices\[0\]\.model: required"),
        (lambda d: d["buses"][0]["devices"][0].update(port=1), r"buses\[0\]\.devices\[0\]\.port: unknown field"),
    ],
)
def test_each_mistake_names_the_file_and_field(change, pattern):
    with pytest.raises(ConfigError, match=r"^op3-test\.yaml: (buses\[0\]\.)?" + pattern):
        parse_config(mutate(change), source="op3-test.yaml")


def test_serial_link_bus_rules():
    base = {
        "robot": "t",
        "buses": [
            {
                "name": "b",
                "port": "/dev/ttyACM0",
                "baud": 1000000,
                "protocol": "serial-link",
                "servos": [{"id": 0, "joint": "a", "limits": [-1, 1]}],
            }
        ],
    }
    cfg = parse_config(base)
    assert cfg.buses[0].servos[0].model is None
    with pytest.raises(ConfigError, match=r"servos\[0\]\.pid: not used on a serial-link bus"):
        bad = copy.deepcopy(base)
        bad["buses"][0]["servos"][0]["pid"] = {"p": 1}
        parse_config(bad)
    with pytest.raises(ConfigError, match=r"servos\[0\]\.id: 40 must be an integer 0\.\.31"):
        bad = copy.deepcopy(base)
        bad["buses"][0]["servos"][0]["id"] = 40
        parse_config(bad)


MJCF = """<mujoco>
  <compiler angle="{angle}"/>
  <default><joint limited="true"/><default class="arm"><joint range="{lo} {hi}"/></default></default>
  <worldbody><body name="torso"><freejoint name="root"/>
    <body name="a" childclass="arm"><joint name="r_sho_pitch" axis="0 1 0"/>
      <body name="b"><joint name="l_sho_pitch" range="{lo} {hi}"/></body></body>
  </body></worldbody>
</mujoco>"""


def two_joint_cfg(lower, upper):
    return {
        "robot": "t",
        "buses": [
            {
                "name": "b",
                "port": "/dev/x",
                "baud": 2000000,
                "protocol": "2.0",
                "servos": [
                    {"id": 1, "joint": "r_sho_pitch", "model": "XM430-W350", "limits": [lower, upper]},
                    {"id": 2, "joint": "l_sho_pitch", "model": "XM430-W350", "limits": [lower, upper]},
                ],
            }
        ],
    }


def test_mjcf_checks_joints_limits_degrees_and_default_classes(tmp_path):
    deg = tmp_path / "deg.xml"
    deg.write_text(MJCF.format(angle="degree", lo=-90, hi=90))
    rad = tmp_path / "rad.xml"
    rad.write_text(MJCF.format(angle="radian", lo=-1.0, hi=1.0))
    assert mjcf_joint_ranges(deg)["r_sho_pitch"] == pytest.approx((-math.pi / 2, math.pi / 2))
    assert mjcf_joint_ranges(rad) == {"r_sho_pitch": (-1.0, 1.0), "l_sho_pitch": (-1.0, 1.0)}
    parse_config(two_joint_cfg(-1.5, 1.5), mjcf=deg)
    with pytest.raises(
        ConfigError,
        match=r"servos\[0\]\.limits: \[-1\.5000, 1\.5000\] rad is wider than the MJCF range \[-1\.0000, 1\.0000\]",
    ):
        parse_config(two_joint_cfg(-1.5, 1.5), mjcf=rad)
    d = two_joint_cfg(-0.5, 0.5)
    d["buses"][0]["servos"][1]["joint"] = "l_knee"
    with pytest.raises(ConfigError, match=r"servos\[1\]\.joint: 'l_knee' is not a hinge joint of .*rad\.xml"):
        parse_config(d, mjcf=rad)
    with pytest.raises(ConfigError, match="MJCF not found"):
        parse_config(two_joint_cfg(-0.5, 0.5), mjcf=tmp_path / "missing.xml")


def test_file_level_errors(tmp_path):
    with pytest.raises(ConfigError, match="hardware config not found.*bundled robot .*op3"):
        load_config(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("robot: [unclosed")
    with pytest.raises(ConfigError, match=r"bad\.yaml: not valid YAML"):
        load_config(bad)
    bad.write_text("robot: x\nbuses: []\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml: buses: required"):
        load_config(bad)


def test_firmware_cfg_imports_nothing_of_ours_and_no_torch():
    import subprocess
    import sys

    code = (
        "import sys, firmware_cfg.config, firmware_cfg.serial_link, firmware_cfg.servo_models\n"
        "ours = [m for m in sys.modules if m.split('.')[0] in "
        "('ros_free_bridge', 'sim', 'retarget', 'dualflow', 'torch')]\n"
        "assert not ours, ours\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr

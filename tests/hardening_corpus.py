"""A corpus of malformed input files, each run through the command that reads it.

Used by ``tests/test_hardening_corpus.py`` (every case must end in exit code 2 with one
line naming the file) and runnable on its own to tabulate outcomes by format and kind of
damage, e.g. to compare two revisions of the code::

    python tests/hardening_corpus.py            # the code on PYTHONPATH / installed
    PYTHONPATH=/tmp/base python tests/hardening_corpus.py --limit-memory 12

The corpus is generated from good files written by the package itself (a synthetic
leader, a standing robot trajectory, a short telemetry file, a tiny checkpoint, the
bundled robots' configs) by truncation, bit flips, wrong or missing keys, wrong dtypes,
forged headers declaring absurd sizes, deep nesting, NaN and out-of-range values.

Each case runs in this process through ``ros_free_bridge.cli.main`` with stdout and
stderr captured. Outcomes:

``ok``          exit 2 and exactly one ``error:`` line on stderr naming the file
``unclear``     exit 2, but the message has several lines or does not name the file
``traceback``   an exception other than SystemExit escaped (a bug)
``accepted``    exit 0: the damage went unnoticed
``exit N``      any other exit code (1: judged as a fault or a failed verdict)
``hang``        still running after the per-case guard (``--case-timeout``)
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
import signal
import sys
import time
import zipfile
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

#: the fixed-base bundled robot: stable, needs no hardware config for sim / record
MODEL_ROBOT = "ub14"
#: the bundled robot with a hardware config (hardware.yaml and profile cases copy its folder)
HARDWARE_ROBOT = "op3"


@dataclass
class Case:
    fmt: str  #: format (bvh, motion-npz, ...)
    damage: str  #: kind of damage
    path: Path  #: the damaged file (or folder)
    argv: list  #: the command line
    names: tuple = ()  #: strings of which one must appear in the message (default: the file's name)

    def __post_init__(self) -> None:
        if not self.names:
            self.names = (self.path.name,)

    @property
    def label(self) -> str:
        return f"{self.fmt}/{self.damage}"


@dataclass
class Outcome:
    kind: str
    code: int | None
    message: str
    seconds: float = 0.0
    extra: dict = field(default_factory=dict)


# ---------------------------------------------------------------------------------------------
# byte-level damage
# ---------------------------------------------------------------------------------------------
def truncated(data: bytes, frac: float) -> bytes:
    return data[: int(len(data) * frac)]


def flipped(data: bytes, seed: int, n: int = 8, start: int = 0) -> bytes:
    """``n`` random bits flipped at positions >= ``start`` (seeded)."""
    rng = np.random.default_rng(seed)
    b = bytearray(data)
    for pos in rng.integers(start, len(b), n):
        b[pos] ^= 1 << int(rng.integers(0, 8))
    return bytes(b)


def flipped_letters(data: bytes, seed: int, n: int = 4, among: bytes | None = None) -> bytes:
    """``n`` letters (keywords, joint names; or the bytes in ``among``) changed by flipping
    one of their low bits."""
    rng = np.random.default_rng(seed)
    b = bytearray(data)
    letters = [i for i, c in enumerate(b) if (c in among if among else chr(c).isalpha())]
    for pos in rng.choice(letters, n, replace=False):
        b[pos] ^= 1 << int(rng.integers(0, 3))
    return bytes(b)


def garbage(n: int, seed: int = 0) -> bytes:
    return np.random.default_rng(seed).integers(0, 256, n, dtype=np.uint8).tobytes()


def npy_bytes(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, arr, allow_pickle=True)
    return buf.getvalue()


def forged_npy(shape, descr: str = "<f8", payload: bytes = b"\0" * 64, header: str | None = None) -> bytes:
    """A .npy whose header declares ``shape`` / ``descr`` whatever follows it."""
    if header is None:
        header = repr({"descr": descr, "fortran_order": False, "shape": tuple(shape)})
    text = header.encode("latin1")
    pad = 64 - (10 + len(text) + 1) % 64
    text = text + b" " * pad + b"\n"
    return b"\x93NUMPY\x01\x00" + len(text).to_bytes(2, "little") + text + payload


def write_npz(path: Path, members: dict) -> Path:
    """An npz from ``members``: name -> array (saved as .npy) or raw bytes (stored as is)."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        for name, value in members.items():
            z.writestr(name + ".npy", value if isinstance(value, bytes) else npy_bytes(np.asanyarray(value)))
    return path


def npz_members(path: Path) -> dict:
    with np.load(path, allow_pickle=False) as d:
        return {k: d[k] for k in d.files}


# ---------------------------------------------------------------------------------------------
# the corpus
# ---------------------------------------------------------------------------------------------
class Builder:
    def __init__(self, root: Path):
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)
        self.cases: list[Case] = []
        self._n = 0

    def file(self, fmt: str, damage: str, ext: str, data: bytes | None = None) -> Path:
        self._n += 1
        d = self.root / fmt
        d.mkdir(exist_ok=True)
        p = d / f"{self._n:03d}_{damage.replace('/', '_').replace(' ', '_')}{ext}"
        if data is not None:
            p.write_bytes(data)
        return p

    def add(self, fmt: str, damage: str, path: Path, argv: list, names: tuple = ()) -> None:
        self.cases.append(Case(fmt, damage, path, [str(a) for a in argv], names))

    def out(self, tag: str) -> Path:
        return self.root / "out" / tag


def build_corpus(root: Path, *, quick: bool = False) -> list[Case]:
    """Write the malformed files under ``root`` and return the cases (argv ready to run)."""
    from dualflow.motion.io import save_motion
    from dualflow.synthetic import make_duet, make_leader

    root = Path(root)
    if (root / ".hardening_corpus").exists():  # a corpus written before: start afresh
        shutil.rmtree(root)
    root.mkdir(parents=True, exist_ok=True)
    (root / ".hardening_corpus").touch()
    b = Builder(root)
    good = root / "good"
    good.mkdir(parents=True, exist_ok=True)
    leader = make_leader(2.0, 30.0, 0)
    save_motion(leader, good / "leader.npz")
    save_motion(leader, good / "leader.bvh")
    save_motion(make_duet("mirror", 2.0, 30.0, 0), good / "duet.npz")
    _motion_cases(b, good, leader)
    _trajectory_cases(b, good)
    _telemetry_cases(b, good)
    _checkpoint_cases(b, good)
    _robot_folder_cases(b, good)
    _music_cases(b, good)
    _joint_map_cases(b, good)
    _train_config_cases(b, good)
    return b.cases


def _info(b: Builder, fmt: str, damage: str, path: Path, names=()) -> None:
    b.add(fmt, damage, path, ["motion", "info", path], names)


def _run_actor(b: Builder, fmt: str, damage: str, path: Path) -> None:
    b.add(
        fmt,
        damage + " (run --actor)",
        path,
        [
            "run",
            "--actor",
            path,
            "--robot",
            MODEL_ROBOT,
            "--partner",
            "imitate",
            "--transport",
            "record",
            "--max-duration",
            "0.3",
            "--quiet",
            "-o",
            b.out("run_actor"),
        ],
    )


def _bvh_text(depth: int, frames: int = 2, frame_time: str = "0.0333333") -> str:
    lines = ["HIERARCHY", "ROOT j0", "{", "OFFSET 0 0 0", "CHANNELS 3 Xposition Yposition Zposition"]
    for k in range(1, depth):
        lines += [f"JOINT j{k}", "{", "OFFSET 0 1 0", "CHANNELS 1 Xrotation"]
    lines += ["End Site", "{", "OFFSET 0 1 0", "}"] + ["}"] * depth
    n = 3 + (depth - 1)
    lines += ["MOTION", f"Frames: {frames}", f"Frame Time: {frame_time}"] + [" ".join(["0"] * n)] * frames
    return "\n".join(lines) + "\n"


def _motion_cases(b: Builder, good: Path, leader) -> None:
    from dualflow.motion.features import encode_person

    bvh = (good / "leader.bvh").read_bytes()
    text = bvh.decode()
    head, _, motion = text.partition("MOTION")
    motion_lines = motion.strip().splitlines()  # Frames:, Frame Time:, rows
    rows = motion_lines[2:]

    def bvh_with(damage, frames=None, frame_time=None, rows_=None, hierarchy=None, run=False):
        r = rows if rows_ is None else rows_
        ft = motion_lines[1] if frame_time is None else f"Frame Time: {frame_time}"
        fr = f"Frames: {len(r) if frames is None else frames}"
        data = ((hierarchy or head) + "MOTION\n" + "\n".join([fr, ft] + r) + "\n").encode()
        p = b.file("bvh", damage, ".bvh", data)
        _info(b, "bvh", damage, p)
        if run:
            _run_actor(b, "bvh", damage, p)

    for frac in (0.1, 0.5, 0.9, 0.995):
        p = b.file("bvh", f"truncated {frac:g}", ".bvh", truncated(bvh, frac))
        _info(b, "bvh", "truncated", p)
        if frac == 0.5:
            _run_actor(b, "bvh", "truncated", p)
    _info(b, "bvh", "empty", b.file("bvh", "empty", ".bvh", b""))
    for seed in range(6):
        _info(
            b,
            "bvh",
            "bit flips",
            b.file("bvh", f"flips{seed}", ".bvh", flipped_letters(bvh[: len(head)], seed) + bvh[len(head) :]),
        )
    _info(b, "bvh", "garbage bytes", b.file("bvh", "garbage", ".bvh", garbage(4000)))
    _info(b, "bvh", "wrong format", b.file("bvh", "npz_inside", ".bvh", (good / "leader.npz").read_bytes()))
    _info(b, "bvh", "NUL bytes", b.file("bvh", "nul", ".bvh", bvh[:200] + b"\0" * 100 + bvh[300:]))
    _info(b, "bvh", "not UTF-8", b.file("bvh", "latin1", ".bvh", bvh.replace(b"pelvis", "pélvis".encode("latin1"))))
    for depth in (300, 1000, 20000):
        p = b.file("bvh", f"nested {depth}", ".bvh", _bvh_text(depth).encode())
        _info(b, "bvh", "deep nesting", p)
        if depth == 1000:
            _run_actor(b, "bvh", "deep nesting", p)
    bvh_with("frames 10^12", frames=10**12)
    bvh_with("frames negative", frames=-3)
    bvh_with("frames 0", frames=0, rows_=[])
    bvh_with("1 frame", rows_=rows[:1], run=True)
    bvh_with("frame time 0", frame_time="0")
    bvh_with("fps 1e9", frame_time="1e-9")
    bvh_with("fps 1e-6", frame_time="1e6", run=True)
    bvh_with("frame time nan", frame_time="nan")
    bvh_with("frame time negative", frame_time="-0.03")
    nan_rows = list(rows)
    nan_rows[3] = " ".join(["nan"] + rows[3].split()[1:])
    bvh_with("NaN value", rows_=nan_rows)
    inf_rows = list(rows)
    inf_rows[4] = " ".join(rows[4].split()[:-1] + ["inf"])
    bvh_with("inf value", rows_=inf_rows)
    big_rows = [" ".join(["1e300"] * len(r.split())) for r in rows]
    bvh_with("huge values", rows_=big_rows)
    bvh_with("channels 10^9", hierarchy=head.replace("CHANNELS 6", "CHANNELS 1000000000", 1))
    bvh_with("channels negative", hierarchy=head.replace("CHANNELS 6", "CHANNELS -1", 1))
    first_offset = head.index("OFFSET")
    end = head.index("\n", first_offset)
    bvh_with("offset 1e300", hierarchy=head[:first_offset] + "OFFSET 1e300 1e300 1e300" + head[end:])
    bvh_with("no MOTION", hierarchy=head, rows_=[], frames=0)
    wide = ["HIERARCHY", "ROOT r", "{", "OFFSET 0 0 0", "CHANNELS 3 Xposition Yposition Zposition"]
    for k in range(5000):
        wide += [f"JOINT w{k}", "{", "OFFSET 0 0.1 0", "CHANNELS 3 Xrotation Yrotation Zrotation", "}"]
    wide += [
        "}",
        "MOTION",
        "Frames: 2",
        "Frame Time: 0.033",
        " ".join(["0"] * (3 + 3 * 5000)),
        " ".join(["0"] * (3 + 3 * 5000)),
    ]
    _info(b, "bvh", "5000 joints", b.file("bvh", "wide", ".bvh", ("\n".join(wide) + "\n").encode()))

    # -- our motion npz --------------------------------------------------------------------
    src = good / "leader.npz"
    raw = src.read_bytes()
    members = npz_members(src)

    def mnpz(damage, run=False, drop=(), **changes):
        m = {k: v for k, v in members.items() if k not in drop}
        m.update(changes)
        p = write_npz(b.file("motion-npz", damage, ".npz"), m)
        _info(b, "motion-npz", damage, p)
        if run:
            _run_actor(b, "motion-npz", damage, p)

    for frac in (0.1, 0.5, 0.9):
        p = b.file("motion-npz", f"truncated {frac:g}", ".npz", truncated(raw, frac))
        _info(b, "motion-npz", "truncated", p)
        if frac == 0.9:
            _run_actor(b, "motion-npz", "truncated", p)
    _info(b, "motion-npz", "empty", b.file("motion-npz", "empty", ".npz", b""))
    for seed in range(5):
        _info(b, "motion-npz", "bit flips", b.file("motion-npz", f"flips{seed}", ".npz", flipped(raw, seed, 8, 30)))
    _info(b, "motion-npz", "garbage bytes", b.file("motion-npz", "garbage", ".npz", b"PK\x03\x04" + garbage(3000, 1)))
    mnpz("missing positions", drop=("positions",), run=True)
    mnpz("missing fps", drop=("fps",), run=True)
    for label, fps in (
        ("fps 0", 0.0),
        ("fps negative", -30.0),
        ("fps 1e-6", 1e-6),
        ("fps 1e9", 1e9),
        ("fps nan", np.nan),
    ):
        mnpz(label, fps=np.array(fps), run=label in ("fps 1e-6", "fps 1e9"))
    mnpz("fps text", fps=np.array("thirty"))
    mnpz("fps vector", fps=np.array([30.0, 30.0]))
    mnpz("fps empty", fps=np.zeros(0))
    pos = members["positions"]
    mnpz("1 frame", positions=pos[:1], contacts=members["contacts"][:1], run=True)
    mnpz("0 frames", positions=pos[:0], contacts=members["contacts"][:0])
    p2 = pos.copy()
    p2[5, 3, 1] = np.nan
    mnpz("NaN", positions=p2)
    p3 = pos.copy()
    p3[7, 0, 2] = np.inf
    mnpz("inf", positions=p3)
    mnpz("huge values", positions=np.full_like(pos, 3e38))
    mnpz("dtype bool", positions=pos > 0)
    mnpz("dtype complex", positions=pos.astype(complex))
    mnpz("dtype int", positions=(pos * 1000).astype(np.int32))
    mnpz("dtype text", positions=np.array([["a"] * 3] * 22))
    m_obj = {k: v for k, v in members.items()}
    m_obj["positions"] = npy_bytes(np.array([{"a": 1}] * 4, dtype=object))
    p = write_npz(b.file("motion-npz", "object dtype", ".npz"), m_obj)
    _info(b, "motion-npz", "object dtype (pickle)", p)
    mnpz("shape 21 joints", positions=pos[:, :21])
    mnpz("shape 2-D", positions=pos[:, :, 0])
    mnpz("shape scalar", positions=np.array(1.0))
    mnpz("header 10^12 rows", positions=forged_npy((10**12, 22, 3)), run=True)
    mnpz("header longer than data", positions=forged_npy((60, 22, 3), payload=b"\0" * 800))
    mnpz("header huge dims", positions=forged_npy((2**40, 2**40, 3)))
    mnpz("header negative dim", positions=forged_npy((-5, 22, 3)))
    mnpz("header bad descr", positions=forged_npy((4, 22, 3), descr="<zz"))
    mnpz("header not a dict", positions=forged_npy((), header="[1, 2, 3]"))
    mnpz("header huge text", positions=forged_npy((), header="{" + " " * 60000 + "}"))
    mnpz("unknown format", format=np.array("dualflow-motion-9"))
    mnpz("format number", format=np.array(3.0))
    mnpz("contacts shape", contacts=np.zeros((3, 4), bool))

    # -- duet npz ----------------------------------------------------------------------------
    dsrc = good / "duet.npz"
    draw = dsrc.read_bytes()
    dm = npz_members(dsrc)

    def dnpz(damage, drop=(), **changes):
        m = {k: v for k, v in dm.items() if k not in drop}
        m.update(changes)
        _info(b, "duet-npz", damage, write_npz(b.file("duet-npz", damage, ".npz"), m))

    dnpz("missing reactor", drop=("reactor_positions",))
    dnpz("length mismatch", reactor_positions=dm["reactor_positions"][:-5])
    dnpz("meta not JSON", meta=np.array("{not json"))
    dnpz("fps 1e-6", fps=np.array(1e-6))
    rp = dm["reactor_positions"].copy()
    rp[3, 3, 0] = np.nan
    dnpz("NaN", reactor_positions=rp)
    dnpz("1 frame", actor_positions=dm["actor_positions"][:1], reactor_positions=dm["reactor_positions"][:1])
    dnpz("header 10^12 rows", actor_positions=forged_npy((10**12, 22, 3)))
    _info(b, "duet-npz", "truncated", b.file("duet-npz", "truncated", ".npz", truncated(draw, 0.6)))
    for seed in range(2):
        _info(b, "duet-npz", "bit flips", b.file("duet-npz", f"flips{seed}", ".npz", flipped(draw, seed + 10, 8, 30)))

    # -- AMASS-style npz -----------------------------------------------------------------------
    joints24 = np.concatenate([leader.positions, leader.positions[:, :2]], axis=1)
    amass = {
        "joints": joints24,
        "mocap_framerate": np.array(30.0),
        "poses": np.zeros((leader.n_frames, 156)),
        "trans": leader.positions[:, 0],
    }

    def anpz(damage, drop=(), **changes):
        m = {k: v for k, v in amass.items() if k not in drop}
        m.update(changes)
        _info(b, "amass-npz", damage, write_npz(b.file("amass-npz", damage, ".npz"), m))

    anpz("no joints (poses only)", drop=("joints",))
    anpz("21 joints", joints=joints24[:, :21])
    anpz("framerate 0", mocap_framerate=np.array(0.0))
    anpz("framerate 1e-6", mocap_framerate=np.array(1e-6))
    anpz("framerate 1e9", mocap_framerate=np.array(1e9))
    anpz("missing framerate", drop=("mocap_framerate",))
    anpz("framerate text", mocap_framerate=np.array("120fps"))
    anpz("joints text", joints=np.array(["x"] * 10))
    anpz("header 10^12 rows", joints=forged_npy((10**12, 24, 3)))
    anpz("1 frame", joints=joints24[:1])
    j2 = joints24.copy()
    j2[1, 1, 1] = np.nan
    anpz("NaN", joints=j2)
    araw = write_npz(good / "amass.npz", amass).read_bytes()
    _info(b, "amass-npz", "truncated", b.file("amass-npz", "truncated", ".npz", truncated(araw, 0.7)))
    for seed in range(2):
        _info(b, "amass-npz", "bit flips", b.file("amass-npz", f"flips{seed}", ".npz", flipped(araw, seed + 20, 8, 30)))

    # -- HumanML3D npy (T, 22, 3), Y up ---------------------------------------------------------
    yup = leader.positions[..., [0, 2, 1]] * np.array([1.0, 1.0, -1.0])
    hraw = npy_bytes(yup)

    def hnpy(damage, data: bytes, run=False):
        p = b.file("humanml3d-npy", damage, ".npy", data)
        _info(b, "humanml3d-npy", damage, p)
        if run:
            _run_actor(b, "humanml3d-npy", damage, p)

    for frac in (0.05, 0.5, 0.95):
        hnpy(f"truncated {frac:g}", truncated(hraw, frac))
    hnpy("empty", b"")
    for seed in range(3):
        hnpy(f"bit flips {seed}", flipped(hraw[:128], seed + 30, 3, 8) + hraw[128:])
    hnpy("garbage bytes", b"\x93NUMPY" + garbage(2000, 3))
    hnpy("header 10^12 rows", forged_npy((10**12, 22, 3)), run=True)
    hnpy("header huge dims", forged_npy((2**31, 2**31, 3)))
    hnpy("header bad descr", forged_npy((10, 22, 3), descr="|O"))
    hnpy("header unparsable", forged_npy((), header="{'descr': '<f8', 'shape': (10, 22, 3)"))
    hnpy("header version 9", b"\x93NUMPY\x09\x00" + hraw[8:])
    hnpy("header length huge", hraw[:8] + b"\xff\xff" + hraw[10:])
    hnpy("object dtype (pickle)", npy_bytes(np.array([{"x": 1}] * 5, dtype=object)))
    hnpy("dtype text", npy_bytes(np.array(["a"] * 66).reshape(1, 22, 3)))
    hnpy("dtype complex", npy_bytes(yup.astype(complex)))
    hnpy("0 frames", npy_bytes(yup[:0]))
    hnpy("1 frame", npy_bytes(yup[:1]), run=True)
    y2 = yup.copy()
    y2[4, 2, 1] = np.nan
    hnpy("NaN", npy_bytes(y2), run=True)
    hnpy("inf", npy_bytes(np.where(np.arange(yup.size).reshape(yup.shape) == 9, np.inf, yup)))
    hnpy("shape 23 joints", npy_bytes(np.concatenate([yup, yup[:, :1]], axis=1)))
    hnpy("shape 4-D", npy_bytes(yup[None]))
    hnpy("shape 0-D", npy_bytes(np.array(1.0)))
    hnpy(
        "fortran order",
        forged_npy(
            (60, 22, 3),
            header="{'descr': '<f8', 'fortran_order': True, 'shape': (60, 22, 3)}",
            payload=yup.tobytes()[:100],
        ),
    )

    # -- InterGen npy ----------------------------------------------------------------------------
    feats = encode_person(leader)
    raw492 = np.zeros((leader.n_frames, 492))
    raw492[:, :66] = (leader.positions[..., [0, 2, 1]] * np.array([1.0, 1.0, -1.0]))[..., [0, 2, 1]].reshape(-1, 66)

    def inpy(damage, arr=None, data=None):
        p = b.file("intergen-npy", damage, ".npy", npy_bytes(arr) if data is None else data)
        _info(b, "intergen-npy", damage, p)

    f2 = feats.copy()
    f2[3, 10] = np.nan
    inpy("features NaN", f2)
    inpy("features 1 frame", feats[:1])
    inpy("features huge values", np.full_like(feats, 3e38))
    inpy("features truncated", data=truncated(npy_bytes(feats), 0.5))
    inpy("features header 10^12 rows", data=forged_npy((10**12, 262)))
    inpy("raw NaN", np.where(np.arange(raw492.size).reshape(raw492.shape) == 5, np.nan, raw492))
    inpy("raw truncated", data=truncated(npy_bytes(raw492), 0.3))
    inpy("pair 1 frame", np.stack([feats[:1], feats[:1]], axis=1))
    for seed in range(2):
        inpy(
            f"features bit flips {seed}", data=flipped(npy_bytes(feats)[:128], seed + 40, 3, 8) + npy_bytes(feats)[128:]
        )


def _trajectory_cases(b: Builder, good: Path) -> None:
    from retarget.robot import load_robot
    from retarget.trajectory import RobotTrajectory
    from ros_free_bridge.robots import resolve_robot

    files = resolve_robot(MODEL_ROBOT)
    robot = load_robot(files.mjcf, files.profile)
    stand = np.asarray(robot.x_stand)[robot.n_root :]
    traj = RobotTrajectory.standing(robot.joint_names, stand, 30, 30.0, np.asarray(robot.x_stand)[:3], MODEL_ROBOT)
    src = traj.save_npz(good / "trajectory.npz")
    raw = src.read_bytes()
    members = npz_members(src)
    header = json.loads(str(members["header"]))

    def check(damage, path):
        b.add(
            "trajectory-npz", damage, path, ["check", path, "--robot", MODEL_ROBOT, "--no-plots", "-o", b.out("check")]
        )

    def tnpz(damage, drop=(), **changes):
        m = {k: v for k, v in members.items() if k not in drop}
        m.update(changes)
        check(damage, write_npz(b.file("trajectory-npz", damage, ".npz"), m))

    for frac in (0.1, 0.5, 0.95):
        check("truncated", b.file("trajectory-npz", f"truncated {frac:g}", ".npz", truncated(raw, frac)))
    check("empty", b.file("trajectory-npz", "empty", ".npz", b""))
    for seed in range(4):
        check("bit flips", b.file("trajectory-npz", f"flips{seed}", ".npz", flipped(raw, seed + 50, 8, 30)))
    check("garbage bytes", b.file("trajectory-npz", "garbage", ".npz", garbage(5000, 5)))
    check("wrong format", b.file("trajectory-npz", "motion_inside", ".npz", (good / "leader.npz").read_bytes()))
    tnpz("missing header", drop=("header",))
    tnpz("missing joint_pos", drop=("joint_pos",))
    tnpz("header not JSON", header=np.array("{joint_names: ["))
    tnpz("header a list", header=np.array(json.dumps([1, 2])))
    tnpz("header null", header=np.array("null"))
    tnpz("header an int", header=np.array("7"))
    tnpz("joint_names not a list", header=np.array(json.dumps({**header, "joint_names": 5})))
    tnpz(
        "joint_names of another robot",
        header=np.array(json.dumps({**header, "joint_names": [f"j{k}" for k in range(len(robot.joint_names))]})),
    )
    tnpz("joint_names short", header=np.array(json.dumps({**header, "joint_names": header["joint_names"][:-1]})))
    for label, fps in (
        ("fps 0", 0.0),
        ("fps negative", -1.0),
        ("fps 1e-6", 1e-6),
        ("fps 1e9", 1e9),
        ("fps nan", np.nan),
    ):
        tnpz(label, fps=np.float64(fps))
    tnpz("fps vector", fps=np.array([30.0, 30.0]))
    tnpz("fps text", fps=np.array("fast"))
    q = members["joint_pos"]
    tnpz("1 frame", joint_pos=q[:1], root_pos=members["root_pos"][:1], root_quat=members["root_quat"][:1])
    tnpz("0 frames", joint_pos=q[:0], root_pos=members["root_pos"][:0], root_quat=members["root_quat"][:0])
    q2 = q.copy()
    q2[4, 2] = np.nan
    tnpz("NaN", joint_pos=q2)
    tnpz("huge values", joint_pos=np.full_like(q, 1e30))
    tnpz("dtype text", joint_pos=np.array([["x"] * q.shape[1]] * q.shape[0]))
    tnpz("dtype int", joint_pos=q.astype(np.int64))
    tnpz("dtype bool", joint_pos=q > 0)
    tnpz("root_quat zero", root_quat=np.zeros_like(members["root_quat"]))
    tnpz("root_quat shape", root_quat=members["root_quat"][:, :3])
    tnpz("joint_pos 1-D", joint_pos=q[:, 0])
    tnpz("header 10^12 rows", joint_pos=forged_npy((10**12, q.shape[1])))
    tnpz("header longer than data", joint_pos=forged_npy((30, q.shape[1]), payload=b"\0" * 100))
    obj = dict(members)
    obj["header"] = npy_bytes(np.array([{"joint_names": 1}], dtype=object))
    check("object dtype (pickle)", write_npz(b.file("trajectory-npz", "object", ".npz"), obj))


def _telemetry_cases(b: Builder, good: Path) -> None:
    from ros_free_bridge.telemetry.log import MAGIC, TelemetryWriter

    robot = MODEL_ROBOT
    from retarget.robot import load_robot
    from ros_free_bridge.robots import resolve_robot

    files = resolve_robot(robot)
    model = load_robot(files.mjcf, files.profile)
    names = list(model.joint_names)
    n = len(names)
    stand = np.asarray(model.x_stand)[model.n_root :]
    src = good / "telemetry.dftl"
    with TelemetryWriter(src, names, 100.0, meta={"robot": robot}) as w:
        for k in range(40):
            q = stand.astype(np.float32)
            w.record(t=k / 100, tick=k, target=q, command=q, measured=q, state=3)
        w.event("end", state="STOPPED", reason="the motion ended")
    raw = src.read_bytes()
    events = (good / "telemetry.dftl.events.jsonl").read_bytes()
    line, body = raw.split(b"\n", 1)
    header = json.loads(line[len(MAGIC) :])

    def both(damage, path, names_=()):
        b.add("telemetry", damage + " (plot)", path, ["plot", path, "-o", b.out("plot")], names_)
        b.add(
            "telemetry", damage + " (replay)", path, ["replay", path, "--robot", robot, "--transport", "record"], names_
        )

    def tel(damage, head=None, body_=None, raw_=None):
        if raw_ is None:
            h = header if head is None else head
            htext = h if isinstance(h, bytes) else json.dumps(h).encode()
            raw_ = MAGIC + htext + b"\n" + (body if body_ is None else body_)
        p = b.file("telemetry", damage, ".dftl", raw_)
        p.with_name(p.name + ".events.jsonl").write_bytes(events)
        both(damage, p)

    def without(key):
        return {k: v for k, v in header.items() if k != key}

    tel("truncated header", raw_=raw[:30])
    tel("no magic", raw_=b"XXXXXX " + raw[7:])
    tel("empty", raw_=b"")
    tel("header not JSON", head=b"{joint_names: [")
    tel("header a list", head=[1, 2, 3])
    tel("missing joint_names", head=without("joint_names"))
    tel("missing rate_hz", head=without("rate_hz"))
    tel("missing fields", head=without("fields"))
    tel("rate 0", head={**header, "rate_hz": 0})
    tel("rate negative", head={**header, "rate_hz": -100})
    tel("rate NaN", head=json.dumps({**header, "rate_hz": float("nan")}).encode())
    tel("rate 1e9", head={**header, "rate_hz": 1e9})
    tel("rate text", head={**header, "rate_hz": "fast"})
    tel("5 names for the columns", head={**header, "joint_names": names[:5]})
    tel("names not text", head={**header, "joint_names": list(range(n))})
    tel("names duplicated", head={**header, "joint_names": [names[0]] * n})
    fields = header["fields"]
    tel("object field", head={**header, "fields": [[f[0], "|O" if f[0] == "command" else f[1], f[2]] for f in fields]})
    tel("unknown dtype", head={**header, "fields": [[f[0], "<zz" if f[0] == "t" else f[1], f[2]] for f in fields]})
    tel(
        "negative shape", head={**header, "fields": [[f[0], f[1], [-3] if f[0] == "command" else f[2]] for f in fields]}
    )
    tel("huge shape", head={**header, "fields": [[f[0], f[1], [10**9] if f[0] == "command" else f[2]] for f in fields]})
    tel("no command field", head={**header, "fields": [f for f in fields if f[0] != "command"]})
    tel("fields not a list", head={**header, "fields": "t,command"})
    tel("0 records", body_=b"")
    tel("1 record", body_=body[: len(body) // 40])
    rec_size = len(body) // 40
    arr = bytearray(body)
    # NaN in the first joint command of tick 10 (the command field's offset in the record)
    from ros_free_bridge.telemetry.log import tick_dtype

    off = tick_dtype(n).fields["command"][1]
    arr[10 * rec_size + off : 10 * rec_size + off + 4] = np.float32(np.nan).tobytes()
    tel("NaN command", body_=bytes(arr))
    tel(
        "huge command",
        body_=bytes(arr[: 5 * rec_size])
        + bytes(arr[5 * rec_size :]).replace(np.float32(stand[0]).tobytes(), np.float32(3e38).tobytes()),
    )
    for seed in range(2):  # in the header's JSON punctuation (records carry no checksum: a flip there is a value)
        tel(f"bit flips {seed}", raw_=flipped_letters(line, seed + 60, 2, b'{}[]":,') + raw[len(line) :])

    # -- the events file beside a good telemetry file ----------------------------------------
    def ev(damage, data: bytes):
        p = b.file("telemetry-events", damage, ".dftl", raw)
        ep = p.with_name(p.name + ".events.jsonl")
        ep.write_bytes(data)
        b.add("telemetry-events", damage + " (plot)", p, ["plot", p, "-o", b.out("plot")], (ep.name,))
        b.add(
            "telemetry-events",
            damage + " (replay)",
            p,
            ["replay", p, "--robot", robot, "--transport", "record"],
            (ep.name,),
        )

    ev("binary", garbage(500, 7))
    ev("not UTF-8", events.replace(b"STOPPED", "STÖPPED".encode("latin1")))
    ev("a list line", b"[1, 2, 3]\n" + events)
    ev("garbage mid-file", events + b"{{{{\n" + events)
    ev("record without kind", b'{"unix": 1}\n' + events)


def _checkpoint_cases(b: Builder, good: Path) -> None:
    import torch
    from safetensors.torch import load_file, save_file

    from dualflow.checkpoint import save_checkpoint
    from dualflow.model import DualFlow, DualFlowConfig
    from dualflow.motion.features import encode_pair
    from dualflow.motion.normalization import NormStats
    from dualflow.synthetic import make_duet

    torch.manual_seed(0)
    feats, _ = encode_pair(make_duet("mirror", 4.0, 30.0, 0))
    base = save_checkpoint(
        good / "ckpt", model=DualFlow(DualFlowConfig.preset("tiny")), stats=NormStats.from_features(feats)
    )
    config = json.loads((base / "config.json").read_text())
    weights = load_file(str(base / "model.safetensors"))

    def ck(damage, edit, names=()):
        d = b.file("checkpoint", damage, "")
        shutil.copytree(base, d)
        edit(d)
        b.add(
            "checkpoint",
            damage,
            d,
            [
                "run",
                "--model",
                d,
                "--robot",
                MODEL_ROBOT,
                "--generator",
                "thread",
                "--transport",
                "record",
                "--seconds",
                "1",
                "--max-duration",
                "0.3",
                "--quiet",
                "-o",
                b.out("run_ckpt"),
            ],
            names or (d.name,),
        )

    def cfg(change):
        def edit(d):
            c = json.loads(json.dumps(config))
            change(c)
            (d / "config.json").write_text(json.dumps(c))

        return edit

    def wts(change):
        def edit(d):
            w = {k: v.clone() for k, v in weights.items()}
            change(w)
            save_file(w, str(d / "model.safetensors"))

        return edit

    def raw_file(name, transform):
        def edit(d):
            (d / name).write_bytes(transform((d / name).read_bytes()))

        return edit

    first = next(iter(weights))
    ck("config missing", lambda d: (d / "config.json").unlink())
    ck("config not JSON", raw_file("config.json", lambda s: s[:-20]))
    ck("config a list", raw_file("config.json", lambda s: b"[1, 2]"))
    ck("version text", cfg(lambda c: c.update(version="1")))
    ck("version list", cfg(lambda c: c.update(version=[1])))
    ck("version null", cfg(lambda c: c.update(version=None)))
    ck("version 99", cfg(lambda c: c.update(version=99)))
    ck("format wrong", cfg(lambda c: c.update(format="other")))
    ck("model missing", cfg(lambda c: c.pop("model")))
    ck("model a list", cfg(lambda c: c.update(model=[1])))
    ck("width changed", cfg(lambda c: c["model"].update(width=48)))
    ck("width text", cfg(lambda c: c["model"].update(width="32")))
    ck("width negative", cfg(lambda c: c["model"].update(width=-32)))
    ck("unknown model key", cfg(lambda c: c["model"].update(colour="red")))
    ck("weights NaN", wts(lambda w: w[first].fill_(float("nan"))))
    ck("weights inf", wts(lambda w: w[first].fill_(float("inf"))))
    ck("weights int32", wts(lambda w: w.update({k: v.to(torch.int32) for k, v in w.items()})))
    ck("weight missing", wts(lambda w: w.pop(first)))
    ck("weight extra", wts(lambda w: w.update(extra=torch.zeros(3))))
    ck("weight shape", wts(lambda w: w.update({first: torch.zeros(7, 5)})))
    ck("weights truncated", raw_file("model.safetensors", lambda s: truncated(s, 0.5)))
    ck("weights garbage", raw_file("model.safetensors", lambda s: garbage(len(s) // 10, 8)))
    ck("weights header length huge", raw_file("model.safetensors", lambda s: (2**62).to_bytes(8, "little") + s[8:]))
    ck("stats missing", lambda d: (d / "norm_stats.npz").unlink())
    ck("stats NaN", lambda d: write_npz(d / "norm_stats.npz", {"mean": np.full(262, np.nan), "std": np.ones(262)}))
    ck("stats std zero", lambda d: write_npz(d / "norm_stats.npz", {"mean": np.zeros(262), "std": np.zeros(262)}))
    ck("stats shape", lambda d: write_npz(d / "norm_stats.npz", {"mean": np.zeros(5), "std": np.ones(5)}))
    ck("stats truncated", raw_file("norm_stats.npz", lambda s: truncated(s, 0.5)))
    ck(
        "stats header 10^12",
        lambda d: write_npz(d / "norm_stats.npz", {"mean": forged_npy((10**12,)), "std": np.ones(262)}),
    )


def _robot_folder_cases(b: Builder, good: Path) -> None:
    from firmware_cfg.registry import resolve

    found = resolve(HARDWARE_ROBOT)
    folder = Path(found.mjcf).parent
    hw_text = Path(found.hardware).read_text()
    profile_text = Path(found.profile).read_text() if found.profile else ""

    def robot_case(fmt, damage, name, content: bytes):
        d = b.file(fmt, damage, "")
        shutil.copytree(folder, d)
        (d / name).write_bytes(content)
        b.add(
            fmt,
            damage,
            d,
            [
                "run",
                "--robot",
                d,
                "--partner",
                "imitate",
                "--transport",
                "record",
                "--seconds",
                "1",
                "--max-duration",
                "0.3",
                "--quiet",
                "-o",
                b.out("run_robot"),
            ],
            (name,),
        )

    def hw(damage, content):
        robot_case(
            "hardware-yaml",
            damage,
            Path(found.hardware).name,
            content if isinstance(content, bytes) else content.encode(),
        )

    hw("not YAML", hw_text.replace("buses:", "buses: [\n  {", 1))
    hw("empty", "")
    hw("top-level list", "- 1\n- 2\n")
    hw("no buses", hw_text.split("\nbuses:")[0] + "\n")
    hw("servo id text", hw_text.replace("id: 1,", "id: one,", 1).replace("id: 1\n", "id: one\n", 1))
    hw("limits NaN", _replace_first_limits(hw_text, "[.nan, 1.0]"))
    hw("limits reversed", _replace_first_limits(hw_text, "[1.0, -1.0]"))
    hw("limits wider than the MJCF", _replace_first_limits(hw_text, "[-6.0, 6.0]"))
    hw("unknown servo model", hw_text.replace("model: XM430-W350", "model: XX999", 1))
    hw("baud negative", hw_text.replace("baud: 2000000", "baud: -1", 1))
    hw("stop_policy unknown", hw_text.replace("stop_policy: hold", "stop_policy: explode", 1))
    hw("binary garbage", garbage(3000, 9))
    hw("deep nesting", "robot: " + "[" * 5000 + "]" * 5000 + "\n")
    hw("alias bomb", _alias_bomb())

    def prof(damage, content):
        robot_case(
            "profile-yaml",
            damage,
            Path(found.profile).name,
            content if isinstance(content, bytes) else content.encode(),
        )

    prof("another robot's profile", profile_text.replace(f"robot: {HARDWARE_ROBOT}", "robot: ub14", 1))
    prof("not YAML", profile_text + "\nkeypoints: [\n")
    prof("empty", "")
    prof("no keypoints", "robot: op3\n")
    prof(
        "unknown human joint",
        profile_text.replace("keypoints:\n", "keypoints:\n  tail: {site: head, weight: 1.0}\n", 1),
    )
    prof("weight NaN", profile_text.replace("weight: 1.0", "weight: .nan", 1))
    prof("weight negative", profile_text.replace("weight: 1.0", "weight: -1.0", 1))
    prof("binary garbage", garbage(2000, 10))
    prof("deep nesting", "robot: " + "[" * 5000 + "]" * 5000 + "\n")
    prof("alias bomb", _alias_bomb())


def _replace_first_limits(text: str, value: str) -> str:
    import re

    return re.sub(r"limits: \[[^\]]*\]", f"limits: {value}", text, count=1)


def _alias_bomb() -> str:
    lines = ['a: &a ["x","x","x","x","x","x","x","x","x"]']
    prev = "a"
    for k in "bcdefghi":
        lines.append(f"{k}: &{k} [" + ",".join([f"*{prev}"] * 9) + "]")
        prev = k
    return "\n".join(lines) + "\n"


def _music_cases(b: Builder, good: Path) -> None:
    import soundfile as sf

    sr = 22050
    wav = good / "click.wav"
    sf.write(wav, (0.1 * np.sin(np.arange(sr * 2) * 0.05)).astype(np.float32), sr)
    raw = wav.read_bytes()

    def mu(damage, data: bytes, ext=".wav"):
        p = b.file("music", damage, ext, data)
        b.add(
            "music",
            damage,
            p,
            [
                "run",
                "--music",
                p,
                "--robot",
                MODEL_ROBOT,
                "--generator",
                "thread",
                "--transport",
                "record",
                "--seconds",
                "1",
                "--max-duration",
                "0.3",
                "--quiet",
                "-o",
                b.out("run_music"),
            ],
        )

    mu("empty", b"")
    mu("garbage bytes", garbage(5000, 11))
    mu("truncated header", raw[:30])
    buf = io.BytesIO()
    sf.write(buf, np.full(sr, np.nan, np.float32), sr, format="WAV", subtype="FLOAT")
    mu("NaN samples", buf.getvalue())
    buf = io.BytesIO()
    sf.write(buf, np.zeros(0, np.float32), sr, format="WAV", subtype="FLOAT")
    mu("0 samples", buf.getvalue())
    mu("text as mp3", b"this is not audio\n" * 50, ".mp3")
    buf = io.BytesIO()
    sf.write(buf, np.zeros(20, np.float32), sr, format="WAV", subtype="FLOAT")
    mu("20 samples", buf.getvalue())


def _joint_map_cases(b: Builder, good: Path) -> None:
    bvh = good / "leader.bvh"

    def jm(damage, text: str, ext=".yaml"):
        p = b.file("joint-map", damage, ext, text.encode())
        b.add("joint-map", damage, p, ["motion", "info", bvh, "--joint-map", p])

    jm("not YAML", "joints: {pelvis: [")
    jm("a list", "- pelvis\n- head\n")
    jm("unknown SMPL joint", "joints: {tail: Hips}\n")
    jm("unknown source joint", "base: smpl\njoints: {pelvis: NoSuchJoint}\n")
    jm("no joints key", "base: smpl\n")
    jm("not JSON", '{"joints": ', ".json")
    jm("deep nesting", "joints: " + "[" * 5000 + "]" * 5000 + "\n")
    jm("alias bomb", _alias_bomb())


def _train_config_cases(b: Builder, good: Path) -> None:
    def tc(damage, data: bytes, ext=".yaml"):
        p = b.file("train-config", damage, ext, data)
        b.add("train-config", damage, p, ["train", "--config", p, "--out", b.out("train")])

    tc("not YAML", b"steps: [1, 2")
    tc("a list", b"- steps\n- 10\n")
    tc("unknown field", b"stepz: 10\n")
    tc("wrong type", b"steps: many\n")
    tc("model width text", b"model: {width: wide}\n")
    tc("binary garbage", garbage(500, 12))
    tc("deep nesting", b"steps: " + b"[" * 5000 + b"]" * 5000 + b"\n")
    tc("not JSON", b'{"steps": ', ".json")


# ---------------------------------------------------------------------------------------------
# running
# ---------------------------------------------------------------------------------------------
class _Hang(BaseException):
    pass


def run_case(case: Case, timeout_s: float = 0.0) -> Outcome:
    """Run one case through the CLI in this process and classify what happened."""
    from ros_free_bridge.cli import main

    out, err = io.StringIO(), io.StringIO()
    old = None
    if timeout_s > 0:

        def on_alarm(signum, frame):
            raise _Hang()

        old = signal.signal(signal.SIGALRM, on_alarm)
        signal.setitimer(signal.ITIMER_REAL, timeout_s)
    t0 = time.monotonic()
    code = None
    exc = None
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                code = main(case.argv)
            except SystemExit as e:
                code = e.code if isinstance(e.code, int) else (0 if e.code is None else 2)
    except _Hang:
        exc = "hang"
    except BaseException as e:  # noqa: BLE001 - classifying what escaped is the point
        exc = e
    finally:
        if timeout_s > 0:
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, old)
    dt = time.monotonic() - t0
    text = err.getvalue()
    if exc == "hang":
        return Outcome("hang", None, text[-300:], dt)
    if exc is not None:
        return Outcome("traceback", None, f"{type(exc).__name__}: {str(exc)[:200]}", dt)
    lines = [line for line in text.splitlines() if line.strip()]
    errors = [line for line in lines if line.startswith("error:")]
    if code == 2:
        if len(errors) == 1 and any(n in errors[0] for n in case.names) and len(errors[0]) < 2000:
            return Outcome("ok", 2, errors[0], dt)
        return Outcome("unclear", 2, text[-400:], dt)
    if code == 0:
        return Outcome("accepted", 0, (out.getvalue() + text)[-300:], dt)
    return Outcome(f"exit {code}", code, (out.getvalue() + text)[-300:], dt)


def table(cases: list[Case], outcomes: list[Outcome]) -> str:
    """Outcome counts by format and kind of damage, as a markdown table."""
    kinds = ["ok", "unclear", "traceback", "accepted", "exit 1", "hang"]
    extra = sorted({o.kind for o in outcomes} - set(kinds))
    kinds += extra
    by_fmt: dict = defaultdict(Counter)
    for c, o in zip(cases, outcomes):
        by_fmt[c.fmt][o.kind] += 1
    rows = ["| format | cases | " + " | ".join(kinds) + " |", "|---|---|" + "---|" * len(kinds)]
    total = Counter()
    for fmt, cnt in by_fmt.items():
        total.update(cnt)
        rows.append(f"| {fmt} | {sum(cnt.values())} | " + " | ".join(str(cnt.get(k, 0)) for k in kinds) + " |")
    rows.append(f"| **all** | {sum(total.values())} | " + " | ".join(str(total.get(k, 0)) for k in kinds) + " |")
    return "\n".join(rows)


def main(argv=None) -> int:
    import argparse
    import tempfile

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--root", help="where to write the corpus (default: a temporary folder)")
    p.add_argument("--case-timeout", type=float, default=120.0, help="seconds before a case counts as a hang")
    p.add_argument(
        "--limit-memory",
        type=float,
        default=0.0,
        metavar="GIB",
        help="cap this process's address space (an absurd allocation then fails instead of swapping)",
    )
    p.add_argument("--only", help="run only the formats named (comma-separated)")
    p.add_argument("--json", help="write every case's outcome to this JSON file")
    p.add_argument("-v", "--verbose", action="store_true", help="print each case as it runs")
    args = p.parse_args(argv)
    os.environ.setdefault("MUJOCO_GL", "egl")
    root = Path(args.root or tempfile.mkdtemp(prefix="hardening_corpus_"))
    cases = build_corpus(root)
    if args.only:
        keep = set(args.only.split(","))
        cases = [c for c in cases if c.fmt in keep]
    if args.limit_memory:
        import resource

        cap = int(args.limit_memory * 2**30)
        resource.setrlimit(resource.RLIMIT_AS, (cap, cap))
    outcomes = []
    for k, c in enumerate(cases):
        o = run_case(c, args.case_timeout)
        outcomes.append(o)
        if args.verbose or o.kind != "ok":
            print(
                f"[{k + 1}/{len(cases)}] {c.label}: {o.kind} ({o.seconds:.1f} s) {o.message.strip()[:160]!r}",
                file=sys.__stderr__,
                flush=True,
            )
    print(table(cases, outcomes))
    if args.json:
        Path(args.json).write_text(
            json.dumps(
                [
                    {
                        "format": c.fmt,
                        "damage": c.damage,
                        "path": str(c.path),
                        "argv": c.argv,
                        "outcome": o.kind,
                        "code": o.code,
                        "message": o.message,
                        "seconds": round(o.seconds, 2),
                    }
                    for c, o in zip(cases, outcomes)
                ],
                indent=1,
            )
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

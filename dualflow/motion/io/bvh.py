"""The BVH format: a robust reader, forward kinematics, and a writer.

Contract: any hierarchy, channel order and Euler order per joint, End Sites (kept as joints
named ``<parent>_end``), any line endings, position channels on any joint. A joint's local
transform is T(offset, with channel values where they exist) · R_c1 · R_c2 · R_c3 (rotation
channels in listed order, intrinsic, degrees). It knows nothing of SMPL, units or up axes
(that is :mod:`dualflow.motion.io.bvh_motion`). Errors are :class:`dualflow.DualFlowError`
naming the file and line.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dualflow.errors import DualFlowError

#: Deepest joint chain accepted (a human skeleton is about 10 deep; hands and face rigs 30).
MAX_DEPTH = 256
#: Most joints (End Sites included) and channels accepted in one hierarchy.
MAX_JOINTS = 10000
#: Largest absolute OFFSET or channel value accepted, in file units (degrees for rotations):
#: 1e7 is 10 km in millimetres; anything larger is damage, not capture.
MAX_VALUE = 1e7
#: Frame times accepted, seconds: 1 to 1000 fps (dualflow.motion.io.units.FPS_RANGE).
FRAME_TIME_RANGE = (1e-3, 1.0)

_CHANNEL_NAMES = {
    "xposition": "Xposition",
    "yposition": "Yposition",
    "zposition": "Zposition",
    "xrotation": "Xrotation",
    "yrotation": "Yrotation",
    "zrotation": "Zrotation",
}


@dataclass(frozen=True)
class BvhJoint:
    """One node of a BVH hierarchy.

    ``offset`` (3,) is in file units; ``channels`` are canonical names such as
    ``"Xposition"`` / ``"Zrotation"`` in file order (empty for an End Site).
    """

    name: str
    parent: int
    offset: tuple[float, float, float]
    channels: tuple[str, ...] = ()
    is_end_site: bool = False

    @property
    def rotation_axes(self) -> str:
        """Rotation channel axes in file order, e.g. ``"ZYX"``."""
        return "".join(c[0] for c in self.channels if c.endswith("rotation"))


@dataclass(frozen=True)
class BvhClip:
    """A parsed BVH file: the hierarchy and the motion channels.

    ``motion`` is (T, C) float64 with C = the total number of channels in joint
    order; angles in degrees, lengths in file units. ``source`` names the file for
    error messages; ``first_motion_line`` is the 1-based line of frame 0 in it.
    """

    joints: tuple[BvhJoint, ...]
    frame_time: float
    motion: np.ndarray
    source: str = "<bvh>"
    first_motion_line: int = 0

    def __post_init__(self) -> None:
        motion = np.asarray(self.motion, dtype=np.float64)
        if motion.ndim != 2 or motion.shape[1] != self.n_channels:
            raise DualFlowError(
                f"{self.source}: motion must have shape (T, {self.n_channels}), got {tuple(motion.shape)}"
            )
        object.__setattr__(self, "motion", motion)

    # -- structure ---------------------------------------------------------
    @property
    def names(self) -> tuple[str, ...]:
        return tuple(j.name for j in self.joints)

    @property
    def parents(self) -> tuple[int, ...]:
        return tuple(j.parent for j in self.joints)

    @property
    def n_channels(self) -> int:
        return sum(len(j.channels) for j in self.joints)

    @property
    def n_frames(self) -> int:
        return int(self.motion.shape[0])

    @property
    def fps(self) -> float:
        return 1.0 / self.frame_time

    def channel_offsets(self) -> list[int]:
        """Index of each joint's first channel in a motion row."""
        starts, k = [], 0
        for j in self.joints:
            starts.append(k)
            k += len(j.channels)
        return starts

    def index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise DualFlowError(
                f"{self.source}: no joint named {name!r}; the file has: {', '.join(self.names)}"
            ) from None

    def slice(self, start: int, stop: int | None = None) -> BvhClip:
        return BvhClip(
            self.joints, self.frame_time, self.motion[start:stop], self.source, self.first_motion_line + start
        )

    # -- kinematics --------------------------------------------------------
    def local_transforms(self) -> tuple[np.ndarray, np.ndarray]:
        """Per-joint local translations (T, J, 3) in file units and rotation
        matrices (T, J, 3, 3), from the channels (see the module docstring)."""
        T, J = self.n_frames, len(self.joints)
        trans = np.empty((T, J, 3))
        rots = np.empty((T, J, 3, 3))
        for j, (joint, start) in enumerate(zip(self.joints, self.channel_offsets())):
            trans[:, j] = joint.offset
            rot = None
            for k, channel in enumerate(joint.channels):
                axis = "XYZ".index(channel[0])
                values = self.motion[:, start + k]
                if channel.endswith("position"):
                    trans[:, j, axis] = values
                else:
                    r = axis_rotation(axis, np.deg2rad(values))
                    rot = r if rot is None else rot @ r
            rots[:, j] = np.eye(3) if rot is None else rot
        return trans, rots

    def forward_kinematics(self) -> tuple[np.ndarray, np.ndarray]:
        """Global joint positions (T, J, 3) in file units and global rotation
        matrices (T, J, 3, 3); vectorised over frames, one pass over joints."""
        trans, rots = self.local_transforms()
        pos = np.empty_like(trans)
        glob = np.empty_like(rots)
        for j, parent in enumerate(self.parents):
            if parent < 0:
                pos[:, j] = trans[:, j]
                glob[:, j] = rots[:, j]
            else:
                pos[:, j] = pos[:, parent] + np.einsum("tab,tb->ta", glob[:, parent], trans[:, j])
                glob[:, j] = glob[:, parent] @ rots[:, j]
        return pos, glob

    def global_positions(self) -> np.ndarray:
        """(T, J, 3) global joint positions in file units (End Sites included)."""
        return self.forward_kinematics()[0]

    def rest_positions(self) -> np.ndarray:
        """(J, 3) joint positions of the hierarchy's zero pose (all channels 0, roots at
        their OFFSET), in file units."""
        pos = np.zeros((len(self.joints), 3))
        for j, joint in enumerate(self.joints):
            base = pos[joint.parent] if joint.parent >= 0 else 0.0
            pos[j] = base + np.asarray(joint.offset)
        return pos


def axis_rotation(axis: int, angle: np.ndarray) -> np.ndarray:
    """(T, 3, 3) rotation matrices about coordinate axis 0/1/2 (x/y/z) by ``angle`` (T,) rad."""
    c, s = np.cos(angle), np.sin(angle)
    m = np.zeros(angle.shape + (3, 3))
    i, k = [(1, 2), (2, 0), (0, 1)][axis]
    m[..., axis, axis] = 1.0
    m[..., i, i] = c
    m[..., k, k] = c
    m[..., i, k] = -s
    m[..., k, i] = s
    return m


# ---------------------------------------------------------------------------
# Reading
# ---------------------------------------------------------------------------
class _Tokens:
    """Whitespace tokens of the HIERARCHY section with their 1-based line numbers."""

    def __init__(self, lines: list[str], source: str) -> None:
        self.source = source
        self.items: list[tuple[str, int]] = []
        self.pos = 0
        self.motion_line = None  # index into lines of the MOTION keyword
        for i, line in enumerate(lines):
            words = line.replace("{", " { ").replace("}", " } ").split()
            if words and words[0].upper() == "MOTION":
                self.motion_line = i
                break
            self.items.extend((w, i + 1) for w in words)
        self.last_line = len(lines)

    def error(self, msg: str, line: int | None = None) -> DualFlowError:
        if line is None:
            line = self.items[self.pos][1] if self.pos < len(self.items) else self.last_line
        return DualFlowError(f"{self.source}, line {line}: {msg}")

    def next(self, what: str) -> tuple[str, int]:
        if self.pos >= len(self.items):
            raise self.error(f"file ends inside the HIERARCHY, expected {what} (truncated file?)")
        item = self.items[self.pos]
        self.pos += 1
        return item

    def peek(self) -> str | None:
        return self.items[self.pos][0] if self.pos < len(self.items) else None

    def expect(self, word: str) -> int:
        tok, line = self.next(repr(word))
        if tok.upper() != word.upper():
            raise self.error(f"expected {word!r}, found {tok!r}", line)
        return line

    def number(self, what: str) -> float:
        tok, line = self.next(what)
        try:
            value = float(tok)
        except ValueError:
            raise self.error(f"expected a number for {what}, found {tok!r}", line) from None
        if not np.isfinite(value) or abs(value) > MAX_VALUE:
            raise self.error(f"{what} is {tok!r}; it must be a finite number within ±{MAX_VALUE:g}", line)
        return value


def _parse_joint(tok: _Tokens, name: str, parent: int, joints: list[BvhJoint], line: int, depth: int = 1) -> None:
    if depth > MAX_DEPTH:
        raise tok.error(
            f"joint {name!r} is nested {depth} joints deep, more than the {MAX_DEPTH} this reader "
            "accepts; the HIERARCHY is damaged (unbalanced braces?)",
            line,
        )
    if len(joints) >= MAX_JOINTS:
        raise tok.error(f"the HIERARCHY has more than {MAX_JOINTS} joints; the file is damaged or not a skeleton", line)
    tok.expect("{")
    tok.expect("OFFSET")
    offset = tuple(tok.number(f"the OFFSET of {name!r}") for _ in range(3))
    channels: tuple[str, ...] = ()
    if (tok.peek() or "").upper() == "CHANNELS":
        tok.next("CHANNELS")
        count_tok, count_line = tok.next("the channel count")
        try:
            count = int(count_tok)
        except ValueError:
            raise tok.error(f"CHANNELS of {name!r} must start with a count, found {count_tok!r}", count_line) from None
        if not 0 <= count <= 6:
            raise tok.error(
                f"CHANNELS of {name!r} says {count}; a joint has 0 to 6 channels (X/Y/Z position and rotation)",
                count_line,
            )
        names = []
        for _ in range(count):
            ch, ch_line = tok.next(f"{count} channel names for {name!r}")
            canon = _CHANNEL_NAMES.get(ch.lower())
            if canon is None:
                raise tok.error(
                    f"unknown channel {ch!r} for joint {name!r} (CHANNELS says {count}; "
                    "valid names are X/Y/Z position and X/Y/Z rotation)",
                    ch_line,
                )
            names.append(canon)
        if len(set(names)) != len(names):
            raise tok.error(f"joint {name!r} lists a channel twice: {' '.join(names)}", count_line)
        channels = tuple(names)
    if any(j.name == name for j in joints):
        raise tok.error(f"joint name {name!r} is used twice; joint names must be unique", line)
    index = len(joints)
    joints.append(BvhJoint(name, parent, offset, channels))
    n_end = 0
    while True:
        word, word_line = tok.next(f"JOINT, End Site or '}}' closing {name!r}")
        key = word.upper()
        if key == "}":
            return
        if key == "JOINT":
            child, child_line = tok.next("a joint name")
            _parse_joint(tok, child, index, joints, child_line, depth + 1)
        elif key == "END":
            site, _ = tok.next("'Site'")
            if site.upper() != "SITE":
                raise tok.error(f"expected 'End Site', found 'End {site}'", word_line)
            tok.expect("{")
            tok.expect("OFFSET")
            end_offset = tuple(tok.number(f"the End Site OFFSET of {name!r}") for _ in range(3))
            tok.expect("}")
            n_end += 1
            end_name = f"{name}_end" if n_end == 1 else f"{name}_end{n_end}"
            joints.append(BvhJoint(end_name, index, end_offset, (), True))
        else:
            raise tok.error(f"expected JOINT, End Site or '}}' inside {name!r}, found {word!r}", word_line)


def parse_bvh_text(text: str, source: str = "<bvh>") -> BvhClip:
    """Parse BVH text (see :func:`read_bvh`)."""
    lines = text.splitlines()  # handles \r\n, \r and \n, mixed
    tok = _Tokens(lines, source)
    if not tok.items:
        raise DualFlowError(f"{source}: the file is empty or has no HIERARCHY; is it a BVH file?")
    joints = _parse_hierarchy(tok)
    if tok.motion_line is None:
        raise DualFlowError(f"{source}, line {len(lines)}: no MOTION section (truncated file?)")
    n_frames, frame_time, first_row = _parse_motion_header(lines, tok.motion_line + 1, source)
    rows, row_lines = _motion_rows(lines, first_row, n_frames, source)
    n_channels = sum(len(j.channels) for j in joints)
    motion = _motion_values(rows, row_lines, n_frames, n_channels, source)
    return BvhClip(tuple(joints), frame_time, motion, source, row_lines[0])


def _parse_hierarchy(tok: _Tokens) -> list[BvhJoint]:
    """The joints of the HIERARCHY section (every ROOT and its subtree), in file order."""
    tok.expect("HIERARCHY")
    joints: list[BvhJoint] = []
    while tok.peek() is not None:
        word, line = tok.next("ROOT")
        if word.upper() != "ROOT":
            raise tok.error(f"expected ROOT, found {word!r}", line)
        name, name_line = tok.next("the root joint's name")
        _parse_joint(tok, name, -1, joints, name_line)
    if not joints:
        raise tok.error("the HIERARCHY has no ROOT joint")
    return joints


def _parse_motion_header(lines: list[str], i: int, source: str) -> tuple[int, float, int]:
    """(frame count, frame time in s, index of the line after the header) from the 'Frames:' and
    'Frame Time:' lines that follow MOTION (``i``: the index of the line after MOTION)."""
    header: dict[str, tuple[str, int]] = {}
    while i < len(lines) and len(header) < 2:
        stripped = lines[i].strip()
        i += 1
        if not stripped:
            continue
        key, sep, value = stripped.partition(":")
        key = " ".join(key.split()).lower()
        if not sep or key not in ("frames", "frame time"):
            raise DualFlowError(
                f"{source}, line {i}: expected 'Frames: N' and 'Frame Time: dt' after MOTION, found {stripped[:40]!r}"
            )
        header[key] = (value.strip(), i)
    for key in ("frames", "frame time"):
        if key not in header:
            raise DualFlowError(
                f"{source}, line {len(lines)}: the MOTION section has no '{key.title()}:' line (truncated file?)"
            )
    try:
        n_frames = int(header["frames"][0])
    except ValueError:
        raise DualFlowError(
            f"{source}, line {header['frames'][1]}: 'Frames:' must be an integer, found {header['frames'][0]!r}"
        ) from None
    try:
        frame_time = float(header["frame time"][0])
    except ValueError:
        raise DualFlowError(
            f"{source}, line {header['frame time'][1]}: 'Frame Time:' must be a number, "
            f"found {header['frame time'][0]!r}"
        ) from None
    lo, hi = FRAME_TIME_RANGE
    if not lo <= frame_time <= hi:  # NaN fails too
        raise DualFlowError(
            f"{source}, line {header['frame time'][1]}: 'Frame Time:' must be > 0, within {lo:g}-{hi:g} seconds "
            f"(1 to 1000 fps), found {header['frame time'][0]!r}; fix it to the capture's frame period"
        )
    if n_frames <= 0:
        raise DualFlowError(
            f"{source}, line {header['frames'][1]}: the file has zero frames ('Frames: {n_frames}'); "
            "a motion needs at least one frame"
        )
    return n_frames, frame_time, i


def _motion_rows(lines: list[str], start: int, n_frames: int, source: str) -> tuple[list[str], list[int]]:
    """The non-blank lines from ``start`` on and their 1-based line numbers; exactly ``n_frames`` of them."""
    rows: list[str] = []
    row_lines: list[int] = []
    for k in range(start, len(lines)):
        if lines[k].strip():
            rows.append(lines[k])
            row_lines.append(k + 1)
    if len(rows) < n_frames:
        where = row_lines[-1] if row_lines else len(lines)
        raise DualFlowError(
            f"{source}, line {where}: 'Frames: {n_frames}' but only {len(rows)} motion lines follow "
            "(truncated file?); re-export it or fix the Frames: count"
        )
    if len(rows) > n_frames:
        raise DualFlowError(
            f"{source}, line {row_lines[n_frames]}: 'Frames: {n_frames}' but {len(rows)} motion lines follow; "
            "fix the Frames: count"
        )
    return rows, row_lines


def _motion_values(rows: list[str], row_lines: list[int], n_frames: int, n_channels: int, source: str) -> np.ndarray:
    """The channel values (n_frames, n_channels) of the motion rows, each a finite number within MAX_VALUE."""
    counts = np.fromiter((len(r.split()) for r in rows), dtype=np.int64, count=len(rows))
    bad = np.flatnonzero(counts != n_channels)
    if bad.size:
        k = int(bad[0])
        hint = " (truncated file?)" if k == len(rows) - 1 and counts[k] < n_channels else ""
        raise DualFlowError(
            f"{source}, line {row_lines[k]}: expected {n_channels} values (the HIERARCHY declares "
            f"{n_channels} channels), found {counts[k]}{hint}"
        )
    try:
        motion = np.array(" ".join(rows).split(), dtype=np.float64).reshape(n_frames, n_channels)
    except ValueError:
        for r, line_no in zip(rows, row_lines):
            for word in r.split():
                try:
                    float(word)
                except ValueError:
                    raise DualFlowError(f"{source}, line {line_no}: {word!r} is not a number") from None
        raise
    finite = np.isfinite(motion) & (np.abs(motion) <= MAX_VALUE)
    if not finite.all():
        k, c = np.argwhere(~finite)[0]
        raise DualFlowError(
            f"{source}, line {row_lines[k]}: channel {c + 1} is {float(motion[k, c])}; "
            f"motion values must be finite numbers within ±{MAX_VALUE:g} (drop or repair that frame)"
        )
    return motion


def read_bvh(path: str | os.PathLike) -> BvhClip:
    """Read a BVH file into a :class:`BvhClip` (hierarchy + raw channels).

    Raises DualFlowError naming the file and line for any malformed input:
    truncated hierarchy or motion, wrong number of values on a line, non-numbers,
    NaN/inf, zero frames, unknown channels, duplicate joint names.
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise DualFlowError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise DualFlowError(f"{path}: is a directory, expected a .bvh file") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        text = raw.decode("latin-1")
    if "\x00" in text[:4096]:
        raise DualFlowError(f"{path}: looks binary, not a text BVH file")
    return parse_bvh_text(text, source=str(path))


# ---------------------------------------------------------------------------
# Writing
# ---------------------------------------------------------------------------
def _fmt(values, precision: int) -> str:
    return " ".join(f"{v:.{precision}f}" for v in values)


def bvh_text(clip: BvhClip, precision: int = 6) -> str:
    """The BVH text of ``clip`` (tab-indented, LF line endings)."""
    children: dict[int, list[int]] = {j: [] for j in range(len(clip.joints))}
    roots = []
    for j, joint in enumerate(clip.joints):
        (children[joint.parent] if joint.parent >= 0 else roots).append(j)
    # the file lists joints depth-first; motion columns follow that order
    starts = clip.channel_offsets()
    columns: list[int] = []
    out = ["HIERARCHY"]

    def emit(j: int, depth: int) -> None:
        joint = clip.joints[j]
        columns.extend(range(starts[j], starts[j] + len(joint.channels)))
        pad = "\t" * depth
        if joint.is_end_site:
            out.extend([f"{pad}End Site", f"{pad}{{", f"{pad}\tOFFSET {_fmt(joint.offset, precision)}", f"{pad}}}"])
            return
        out.append(f"{pad}{'ROOT' if joint.parent < 0 else 'JOINT'} {joint.name}")
        out.append(f"{pad}{{")
        out.append(f"{pad}\tOFFSET {_fmt(joint.offset, precision)}")
        if joint.channels:
            out.append(f"{pad}\tCHANNELS {len(joint.channels)} {' '.join(joint.channels)}")
        for c in children[j]:
            emit(c, depth + 1)
        out.append(f"{pad}}}")

    for r in roots:
        emit(r, 0)
    out.append("MOTION")
    out.append(f"Frames: {clip.n_frames}")
    out.append(f"Frame Time: {clip.frame_time:.8f}")
    out.extend(_fmt(row, precision) for row in clip.motion[:, columns])
    return "\n".join(out) + "\n"


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` via a temporary file in the same folder and a rename,
    so the file is either complete or absent."""
    path = Path(path)
    if not path.parent.exists():
        raise DualFlowError(f"{path}: folder {path.parent} does not exist; create it first")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".partial", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def write_bvh(clip: BvhClip, path: str | os.PathLike, precision: int = 6) -> None:
    """Write ``clip`` as a BVH file (atomically)."""
    atomic_write_bytes(path, bvh_text(clip, precision).encode("ascii"))

"""Stick-figure previews of one or two people: an mp4 (imageio-ffmpeg) or a gif (Pillow).

Speed comes from drawing directly, not through matplotlib's 3D axes or
FuncAnimation: one reused Agg figure, a fixed perspective camera framing the whole
clip, the ground grid rendered once and restored per frame (blitting), and only
the bones' line segments updated. Frames stream into the video encoder.

Camera (world frame: metres, Z up): it looks at the centre of the clip's bounding
box from ``azimuth_deg`` (0 = from +X, 90 = from +Y) and ``elevation_deg`` above
the horizon; a point p projects as

    d = p - eye,   u = f * (d . right) / (d . forward),   v = f * (d . up') / (d . forward)

Colours: the actor blue, the reactor orange; each person's left limbs are drawn
lighter than the right limbs so mirror images can be told apart.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dualflow.errors import DualFlowError
from dualflow.motion.container import Motion, TwoPersonMotion
from dualflow.motion.skeleton import JOINT_NAMES, PARENTS

PERSON_COLOURS: tuple[str, ...] = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728")
_LEFT = np.array([JOINT_NAMES[j].startswith("left") for j in range(1, len(PARENTS))])
_HEAD = JOINT_NAMES.index("head")


@dataclass(frozen=True)
class PreviewConfig:
    """Video size (pixels), output frame rate (None: the motion's, at most 25 for gif),
    camera angles (degrees), ground-grid spacing (m) and an optional title."""

    width: int = 640
    height: int = 480
    fps: float | None = None
    azimuth_deg: float = -60.0
    elevation_deg: float = 18.0
    grid_step: float = 0.5
    title: str = ""
    max_gif_fps: float = 25.0


class _Camera:
    """Fixed perspective camera framing a bounding box (see the module docstring)."""

    def __init__(self, lo: np.ndarray, hi: np.ndarray, azimuth_deg: float, elevation_deg: float) -> None:
        az, el = np.deg2rad(azimuth_deg), np.deg2rad(elevation_deg)
        to_camera = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        self.forward = -to_camera
        self.right = np.cross(self.forward, [0.0, 0.0, 1.0])
        self.right /= np.linalg.norm(self.right)
        self.up = np.cross(self.right, self.forward)
        centre = 0.5 * (lo + hi)
        radius = 0.5 * np.linalg.norm(hi - lo) + 0.3
        self.eye = centre + to_camera * (radius * 2.5)
        self.focal = 1.0

    def project(self, points: np.ndarray) -> np.ndarray:
        """(..., 3) world points -> (..., 2) image-plane coordinates."""
        d = points - self.eye
        depth = np.maximum(d @ self.forward, 1e-3)
        return self.focal * np.stack([d @ self.right, d @ self.up], axis=-1) / depth[..., None]

    def depth(self, points: np.ndarray) -> np.ndarray:
        return (points - self.eye) @ self.forward


def _people(motion) -> list[Motion]:
    if isinstance(motion, TwoPersonMotion):
        return [motion.actor, motion.reactor]
    if isinstance(motion, Motion):
        return [motion]
    people = list(motion)
    if not people or not all(isinstance(m, Motion) for m in people):
        raise DualFlowError("preview: give a Motion, a TwoPersonMotion or a list of Motion objects")
    return people


def _shade(colour: str, amount: float) -> tuple[float, float, float]:
    from matplotlib.colors import to_rgb

    rgb = np.array(to_rgb(colour))
    return tuple(rgb + (1.0 - rgb) * amount)


class FrameRenderer:
    """Renders frames of a fixed set of people into (H, W, 3) uint8 images."""

    def __init__(self, people: Sequence[Motion], config: PreviewConfig) -> None:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.collections import LineCollection
        from matplotlib.figure import Figure

        self.people = list(people)
        self.config = config
        allpos = np.concatenate([m.positions.reshape(-1, 3) for m in self.people])
        lo, hi = allpos.min(axis=0), allpos.max(axis=0)
        lo[2] = min(lo[2], 0.0)
        step = config.grid_step
        glo = np.floor((lo[:2] - 0.5) / step) * step
        ghi = np.ceil((hi[:2] + 0.5) / step) * step
        self.camera = _Camera(np.r_[glo, lo[2]], np.r_[ghi, hi[2]], config.azimuth_deg, config.elevation_deg)

        dpi = 100
        self.fig = Figure(figsize=(config.width / dpi, config.height / dpi), dpi=dpi, facecolor="white")
        self.canvas = FigureCanvasAgg(self.fig)
        ax = self.fig.add_axes((0, 0, 1, 1))
        ax.set_axis_off()
        self.ax = ax

        # ground grid on z = 0
        xs = np.arange(glo[0], ghi[0] + 1e-9, step)
        ys = np.arange(glo[1], ghi[1] + 1e-9, step)
        segs = [[(x, glo[1], 0.0), (x, ghi[1], 0.0)] for x in xs] + [[(glo[0], y, 0.0), (ghi[0], y, 0.0)] for y in ys]
        grid = self.camera.project(np.asarray(segs))
        ax.add_collection(LineCollection(grid, colors="#c8c8c8", linewidths=0.8, zorder=0))
        # fit the view to the grid and every projected joint, keeping aspect
        margin = 0.4
        floor = np.array(
            [[x, y, 0.0] for x in (lo[0] - margin, hi[0] + margin) for y in (lo[1] - margin, hi[1] + margin)]
        )
        pts = np.concatenate([self.camera.project(floor), self.camera.project(allpos)])
        (u0, v0), (u1, v1) = pts.min(axis=0), pts.max(axis=0)
        aspect = config.width / config.height
        cu, cv, hu, hv = (u0 + u1) / 2, (v0 + v1) / 2, (u1 - u0) / 2 * 1.05, (v1 - v0) / 2 * 1.08
        if hu / hv < aspect:
            hu = hv * aspect
        else:
            hv = hu / aspect
        ax.set_xlim(cu - hu, cu + hu)
        ax.set_ylim(cv - hv, cv + hv)
        if config.title:
            ax.text(0.02, 0.97, config.title, transform=ax.transAxes, va="top", fontsize=9, color="#333333")

        self.bones, self.heads = [], []
        for k, _ in enumerate(self.people):
            colour = PERSON_COLOURS[k % len(PERSON_COLOURS)]
            colours = [_shade(colour, 0.45) if left else _shade(colour, 0.0) for left in _LEFT]
            lc = LineCollection([], colors=colours, linewidths=3.0, capstyle="round", animated=True)
            head = ax.plot([], [], "o", ms=9, color=colour, animated=True)[0]
            ax.add_collection(lc)
            self.bones.append(lc)
            self.heads.append(head)
        self.clock = ax.text(
            0.98, 0.03, "", transform=ax.transAxes, ha="right", fontsize=9, color="#333333", animated=True
        )
        self.canvas.draw()
        self.background = self.canvas.copy_from_bbox(self.fig.bbox)
        self._child = np.arange(1, len(PARENTS))
        self._parent = np.asarray(PARENTS[1:])

    def render(self, frame: int, time_s: float | None = None) -> np.ndarray:
        """(H, W, 3) uint8 image of ``frame`` (a new array)."""
        return self.render_rgba(frame, time_s)[:, :, :3].copy()

    def render_rgba(self, frame: int, time_s: float | None = None) -> np.ndarray:
        """(H, W, 4) uint8 view of the canvas showing ``frame``; valid until the next call."""
        self.canvas.restore_region(self.background)
        frames = [m.positions[min(frame, m.n_frames - 1)] for m in self.people]
        order = np.argsort([-self.camera.depth(p.mean(axis=0)) for p in frames])  # far first
        for k in order:
            uv = self.camera.project(frames[k])
            self.bones[k].set_segments(np.stack([uv[self._parent], uv[self._child]], axis=1))
            self.heads[k].set_data([uv[_HEAD, 0]], [uv[_HEAD, 1]])
            self.ax.draw_artist(self.bones[k])
            self.ax.draw_artist(self.heads[k])
        if time_s is not None:
            self.clock.set_text(f"{time_s:5.2f} s")
            self.ax.draw_artist(self.clock)
        return np.asarray(self.canvas.buffer_rgba())


def _temp_like(path: Path) -> Path:
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".partial{path.suffix}", dir=path.parent)
    os.close(fd)
    return Path(tmp)


def render_preview(motion, out_path, config: PreviewConfig = PreviewConfig()) -> Path:
    """Draw ``motion`` (Motion, TwoPersonMotion or list of Motion) as stick figures into
    ``out_path`` (.mp4 or .gif). Returns the path. The file appears complete or not at all."""
    out = Path(out_path)
    ext = out.suffix.lower()
    if ext not in (".mp4", ".gif"):
        raise DualFlowError(f"{out}: preview output must end in .mp4 or .gif")
    if not out.parent.exists():
        raise DualFlowError(f"{out}: folder {out.parent} does not exist; create it first")
    if config.width < 64 or config.height < 64 or config.width % 2 or config.height % 2:
        raise DualFlowError(f"preview size {config.width}x{config.height}: width and height must be even and >= 64")
    people = _people(motion)
    fps = config.fps or people[0].fps
    if ext == ".gif":
        fps = min(fps, config.max_gif_fps)
    people = [m.resample(fps) for m in people]
    n = max(m.n_frames for m in people)
    renderer = FrameRenderer(people, config)
    tmp = _temp_like(out)
    try:
        if ext == ".mp4":
            import imageio_ffmpeg

            writer = imageio_ffmpeg.write_frames(
                str(tmp),
                (config.width, config.height),
                fps=fps,
                codec="libx264",
                pix_fmt_in="rgba",
                pix_fmt_out="yuv420p",
                macro_block_size=2,
                output_params=["-f", "mp4", "-preset", "veryfast"],
                ffmpeg_log_level="error",
            )
            writer.send(None)
            for i in range(n):
                writer.send(renderer.render_rgba(i, i / fps))
            writer.close()
        else:
            from PIL import Image

            frames = []
            palette = None
            for i in range(n):
                img = Image.fromarray(renderer.render_rgba(i, i / fps)).convert("RGB")
                if palette is None:
                    palette = img.quantize(colors=64, method=Image.Quantize.MEDIANCUT)
                frames.append(img.quantize(palette=palette, dither=Image.Dither.NONE))
            frames[0].save(
                tmp,
                format="GIF",
                save_all=True,
                append_images=frames[1:],
                duration=int(round(1000.0 / fps)),
                loop=0,
                optimize=False,
            )
        os.replace(tmp, out)
    finally:
        if tmp.exists():
            tmp.unlink()
    return out

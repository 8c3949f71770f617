"""Pictures of rollouts and training runs (matplotlib only; arrays in, figures out).

Every function takes plain arrays or lists and returns a
:class:`matplotlib.figure.Figure`; given a ``path`` it also writes the file,
atomically (a temporary name in the same directory, then ``os.replace``), so a
failed write never leaves a partial file behind. Figures are drawn on the
non-interactive Agg canvas and never go through ``pyplot``, so no display is
needed and no global backend state is touched (figures embed in notebooks
all the same).

Positions are normalised by the length scale ``L`` (the box is ``bounds``,
by default ``[-1, 1]^D``), shape ``(T, N, D)``; radii ``(N,)`` are normalised
too and particles are drawn as circles of their true radius in box units. A
``mask`` ``(N,)`` hides padding particles. Pass ``box_half_size`` (``L`` in m)
to label radii in millimetres, and ``bounds`` (per axis ``(low, high)`` in
units of ``L``) to draw a rectangular box: a container more than twice as wide
as tall (:data:`WIDE_ASPECT`) is drawn with its panels stacked, truth above
prediction, at most :data:`WIDE_WIDTH_IN` inches wide, instead of side by side.

Every frame of an animation moves one :class:`~matplotlib.collections.EllipseCollection`
per panel (new offsets only, in 2-D), so drawing 10^4 disks costs one
collection draw, not 10^4 patches (timed by ``benchmarks/render.py``).

Spheres (``D = 3``) are drawn in one perspective view of the cube, from the
front, a little above and to the side, with its edges drawn: every sphere is
a disc of its projected radius, painted back to front and darkened with
depth. One view keeps the truth and prediction panels side by side at a
readable size, and the bed's height and layering read directly off it; three
orthogonal projections would need three panels per frame, and in each of them
the spheres of a settled bed overlap their neighbours in depth anyway, so the
depth cue (order and shading) is what tells them apart.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import matplotlib
import numpy as np
from matplotlib import animation
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.cm import ScalarMappable
from matplotlib.collections import EllipseCollection
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from dispgns.arrays import Box, ParticleMask, Positions, Radii
from dispgns.files import atomic_path

__all__ = [
    "WIDE_ASPECT",
    "WIDE_WIDTH_IN",
    "ffmpeg_executable",
    "frame_grid",
    "plot_error_curves",
    "plot_rollout_errors",
    "plot_statistics",
    "plot_training_curve",
    "rollout_animation",
    "save_figure",
    "save_rollout_animation",
]

# A box as an array or as ``((lo, hi),) * D`` (what ``ModelConfig.bounds`` and dataset metadata hold).
_BoxLike = Box | Sequence[Sequence[float]]

_PAD = 0.04  # margin around the box, in box units

# A box drawn more than WIDE_ASPECT times as wide as tall gets its panels stacked (side by side,
# a 16:1 container would be a thin line in each half of the figure), WIDE_WIDTH_IN inches wide.
WIDE_ASPECT = 2.0
WIDE_WIDTH_IN = 16.0


# ----------------------------------------------------------------------------
# files
# ----------------------------------------------------------------------------


def _atomic_write(path, write: Callable[[str], None]) -> str:
    """Call ``write(tmp)`` on a temporary path next to ``path`` (same extension), then rename it."""
    with atomic_path(path) as temporary:
        write(str(temporary))
    return os.fspath(path)


def _new_figure(figsize, dpi, layout=None) -> Figure:
    # A whole number of pixels, a hair above: matplotlib < 3.11 truncates figsize * dpi (8.4 in at 50 dpi is
    # 419.99999... pixels, so 419), newer releases round it; both then give the same image size.
    figsize = tuple((round(inches * dpi) + 1e-3) / dpi for inches in figsize)
    fig = Figure(figsize=figsize, dpi=dpi, layout=layout)
    FigureCanvasAgg(fig)
    return fig


def save_figure(fig: Figure, path: str | os.PathLike, *, dpi: float | None = None) -> str:
    """Write ``fig`` to ``path`` atomically (format from the extension).

    The image has exactly the figure's size (``figsize * dpi`` pixels; no
    tight bounding box). Returns ``path`` as a string.
    """
    fmt = os.path.splitext(os.fspath(path))[1].lstrip(".").lower() or "png"
    return _atomic_write(path, lambda tmp: fig.savefig(tmp, format=fmt, dpi=dpi if dpi is not None else fig.dpi))


def ffmpeg_executable() -> str | None:
    """Path of an ffmpeg binary: imageio-ffmpeg's, else one on ``PATH``, else ``None``."""
    try:
        import imageio_ffmpeg

        exe = imageio_ffmpeg.get_ffmpeg_exe()
        if exe and os.path.exists(exe):
            return exe
    except Exception:  # noqa: BLE001 - not installed, or no binary for this platform
        pass
    return shutil.which("ffmpeg")


# ----------------------------------------------------------------------------
# particles
# ----------------------------------------------------------------------------


def _prepare(trajectories: Sequence[Any], radius, mask):
    """Numpy copies with padding particles removed; checks shapes."""
    radius = np.asarray(radius, np.float64)
    if radius.ndim != 1:
        raise ValueError(f"radius must have shape (N,), got {radius.shape}")
    n = radius.shape[0]
    real = np.ones(n, bool) if mask is None else np.asarray(mask, bool)
    if real.shape != (n,):
        raise ValueError(f"mask must have shape ({n},), got {real.shape}")
    out = []
    for traj in trajectories:
        traj = np.asarray(traj, np.float64)
        if traj.ndim != 3 or traj.shape[1] != n or traj.shape[2] not in (2, 3):
            raise ValueError(
                f"trajectories must have shape (T, {n}, D) with D = 2 or 3 (normalised positions), got {traj.shape}"
            )
        out.append(traj[:, real])
    lengths = {t.shape[0] for t in out}
    if len(lengths) != 1:
        raise ValueError(f"trajectories must have the same number of frames, got {sorted(lengths)}")
    if len({t.shape[2] for t in out}) != 1:
        raise ValueError(f"trajectories must have the same dimension, got {[t.shape[2] for t in out]}")
    return out, radius[real]


# The 3-D camera: turned _AZIMUTH degrees about the vertical, raised _ELEVATION degrees, at
# _DISTANCE box half-sizes from the centre; at the centre's depth one box unit stays one unit.
_AZIMUTH, _ELEVATION, _DISTANCE = 30.0, 20.0, 5.0
_DEPTH_SHADE = 0.55  # the farthest sphere keeps this fraction of its colour's brightness


def _camera(points):
    """Screen ``(..., 2)`` coordinates, scale ``(...)`` and depth ``(...)`` (larger: nearer) of ``(..., 3)`` points."""
    az, el = np.radians(_AZIMUTH), np.radians(_ELEVATION)
    x, y, z = points[..., 0], points[..., 1], points[..., 2]
    # Turn about the vertical so the camera looks along -y' ...
    right = np.cos(az) * x + np.sin(az) * y
    toward = np.sin(az) * x - np.cos(az) * y
    # ... then raise it by the elevation: higher points come nearer, nearer points show lower.
    up = np.cos(el) * z - np.sin(el) * toward
    depth = np.cos(el) * toward + np.sin(el) * z
    scale = _DISTANCE / (_DISTANCE - depth)
    return np.stack([right * scale, up * scale], axis=-1), scale, depth


_CUBE_CORNERS = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
_CUBE_EDGES = [(i, j) for i in range(8) for j in range(i + 1, 8) if np.sum(_CUBE_CORNERS[i] != _CUBE_CORNERS[j]) == 1]


def _box(bounds, dim: int) -> np.ndarray:
    """``(D, 2)`` per-axis ``(low, high)`` of the box in units of ``L``; ``None``: ``[-1, 1]^D``."""
    if bounds is None:
        return np.tile([-1.0, 1.0], (dim, 1))
    try:
        box = np.asarray(bounds, np.float64)
    except (TypeError, ValueError):
        box = None
    if box is None or box.shape != (dim, 2) or not np.all(np.isfinite(box)) or np.any(box[:, 1] <= box[:, 0]):
        raise ValueError(
            f"bounds must be {dim} pairs (low, high) with low < high, in units of L, for {dim}-D positions; "
            f"got {bounds!r}"
        )
    return box


def _corners(box: np.ndarray) -> np.ndarray:
    """The 8 corners of a 3-D box, in the order of :data:`_CUBE_CORNERS`."""
    return box[:, 0] + (_CUBE_CORNERS + 1.0) / 2.0 * (box[:, 1] - box[:, 0])


def _limits(box: np.ndarray) -> tuple[tuple[float, float], tuple[float, float]]:
    """Axis limits ``(x, y)`` of a panel: the box (projected in 3-D) and a margin."""
    if box.shape[0] == 2:
        lo, hi = box[:, 0], box[:, 1]
    else:
        screen = _camera(_corners(box))[0]
        lo, hi = screen.min(axis=0), screen.max(axis=0)
    return (lo[0] - _PAD, hi[0] + _PAD), (lo[1] - _PAD, hi[1] + _PAD)


def _aspect(box: np.ndarray) -> float:
    """Width over height of a panel."""
    (x0, x1), (y0, y1) = _limits(box)
    return (x1 - x0) / (y1 - y0)


def _view(positions, radius, colours, norm, cmap):
    """What one frame draws: ``(offsets (N, 2), diameters (N,), face colours (N, 4))``, back to front.

    2-D: the positions and diameters themselves. 3-D: the perspective view of the module
    docstring, sorted far to near so nearer spheres cover farther ones.
    """
    rgba = matplotlib.colormaps[cmap](norm(colours))
    if positions.shape[-1] == 2:
        return positions, 2.0 * radius, rgba
    screen, scale, depth = _camera(positions)
    order = np.argsort(depth, kind="stable")
    nearness = (depth + np.sqrt(3.0)) / (2.0 * np.sqrt(3.0))
    shade = _DEPTH_SHADE + (1.0 - _DEPTH_SHADE) * np.clip(nearness, 0.0, 1.0)
    rgba = rgba.copy()
    rgba[:, :3] *= shade[:, None]
    return screen[order], (2.0 * radius * scale)[order], rgba[order]


def _radius_scale(radius, box_half_size):
    """Colour values and label: radii in mm when ``box_half_size`` is known."""
    if box_half_size is None:
        return radius, "radius  a / L"
    return radius * box_half_size * 1e3, "radius (mm)"


def _radius_norm(values) -> Normalize:
    lo, hi = (float(np.min(values)), float(np.max(values))) if values.size else (0.0, 1.0)
    if hi - lo < 1e-12:
        lo, hi = lo - 0.5 * max(abs(lo), 1e-3), hi + 0.5 * max(abs(hi), 1e-3)
    return Normalize(lo, hi)


def _box_axes(ax, label: str | None, box: np.ndarray) -> None:
    """Equal aspect, no ticks, the box's walls drawn, limits the box and a margin."""
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    for spine in ax.spines.values():
        spine.set_visible(False)
    xlim, ylim = _limits(box)
    ax.set_xlim(*xlim)
    ax.set_ylim(*ylim)
    if box.shape[0] == 2:
        (x0, x1), (y0, y1) = box
        ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, edgecolor="black", linewidth=1.5, zorder=3))
    else:
        corners, _, depth = _camera(_corners(box))
        back = int(np.argmin(depth))  # edges at the farthest corner lie behind the spheres
        for i, j in _CUBE_EDGES:
            behind = back in (i, j)
            ax.plot(
                *corners[[i, j]].T,
                color="grey" if behind else "black",
                linewidth=0.8 if behind else 1.2,
                linestyle="--" if behind else "-",
                zorder=1 if behind else 3,
            )
    if label:
        ax.set_title(label)


def _particles(ax, positions, radius, colour_values, norm, cmap) -> EllipseCollection:
    """Circles of diameter ``2 a`` in data units (``units="xy"``; projected in 3-D), coloured by radius."""
    offsets, diameters, faces = _view(positions, radius, colour_values, norm, cmap)
    collection = EllipseCollection(
        diameters,
        diameters,
        np.zeros_like(diameters),
        units="xy",
        offsets=offsets,
        offset_transform=ax.transData,
        facecolors=faces,
        edgecolors="black",
        linewidths=0.3,
        zorder=2,
    )
    ax.add_collection(collection)
    return collection


def _move_particles(collection, positions, radius, colour_values, norm, cmap) -> None:
    offsets, diameters, faces = _view(positions, radius, colour_values, norm, cmap)
    collection.set_offsets(offsets)
    if positions.shape[-1] == 3:  # sizes, colours and drawing order change with depth
        collection.set_widths(diameters)
        collection.set_heights(diameters)
        collection.set_facecolor(faces)


def _time_label(frame: int, frame_dt: float | None, input_frames: int | None) -> str:
    text = f"frame {frame}" if frame_dt is None else f"t = {frame * frame_dt:.4f} s  (frame {frame})"
    if input_frames is not None and frame < input_frames:
        text += ", input"
    return text


def _animation_figsize(box: np.ndarray, n_panels: int) -> tuple[float, float]:
    """Panels side by side in 9 x 4.2 inches; a wide box's panels stacked, :data:`WIDE_WIDTH_IN` wide at most."""
    aspect = _aspect(box)
    if aspect <= WIDE_ASPECT:
        return (9.0, 4.2)
    width = min(WIDE_WIDTH_IN, 3.0 * aspect)  # 3 inches of height per panel until the width is capped
    return (width + 1.2, n_panels * (width / aspect + 0.35) + 0.45)


class _Scene:
    """Panels of particle trajectories (side by side, or stacked for a wide box), updated frame by frame."""

    def __init__(self, panels, radius, *, frame_dt, input_frames, box_half_size, bounds, cmap, figsize, dpi):
        self.trajectories = [traj for _, traj in panels]
        self.frame_dt = frame_dt
        self.input_frames = input_frames
        colours, colour_label = _radius_scale(radius, box_half_size)
        norm = _radius_norm(colours)
        self.style = (radius, colours, norm, cmap)
        box = _box(bounds, self.trajectories[0].shape[-1])
        stacked = _aspect(box) > WIDE_ASPECT
        if figsize is None:
            figsize = _animation_figsize(box, len(panels))
        self.fig = _new_figure(figsize, dpi, layout="constrained")
        axes = (
            self.fig.subplots(len(panels), 1, squeeze=False)[:, 0]
            if stacked
            else self.fig.subplots(1, len(panels), squeeze=False)[0]
        )
        self.collections = []
        for ax, (label, traj) in zip(axes, panels):
            _box_axes(ax, label, box)
            self.collections.append(_particles(ax, traj[0], radius, colours, norm, cmap))
        self.fig.colorbar(
            ScalarMappable(norm=norm, cmap=cmap), ax=list(axes), label=colour_label, shrink=1.0 if stacked else 0.85
        )
        self.title = self.fig.suptitle(_time_label(0, frame_dt, input_frames))
        # Lay out once, then freeze: re-running the constrained layout on every
        # frame costs more than drawing the particles.
        self.fig.canvas.draw()
        self.fig.set_layout_engine("none")

    def update(self, frame: int):
        for collection, traj in zip(self.collections, self.trajectories):
            _move_particles(collection, traj[frame], *self.style)
        self.title.set_text(_time_label(frame, self.frame_dt, self.input_frames))
        return [*self.collections, self.title]


def _frame_indices(n_frames: int, start: int, stop: int | None, stride: int) -> list[int]:
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    indices = list(range(n_frames))[start:stop:stride]
    if not indices:
        raise ValueError(f"no frames selected from {n_frames} with start={start}, stop={stop}, stride={stride}")
    return indices


def _panels(truth, prediction, titles):
    if prediction is None:
        return [truth], [titles[0]]
    return [truth, prediction], list(titles)


def rollout_animation(
    truth: Positions,
    prediction: Positions | None = None,
    radius: Radii | None = None,
    *,
    mask: ParticleMask | None = None,
    frame_dt: float | None = 1.5e-3,
    input_frames: int | None = 6,
    start: int = 0,
    stop: int | None = None,
    stride: int = 1,
    fps: float = 20.0,
    box_half_size: float | None = None,
    bounds: _BoxLike | None = None,
    titles: Sequence[str] = ("ground truth", "prediction"),
    figsize: tuple[float, float] | None = None,
    dpi: float = 80,
    cmap: str = "viridis",
) -> tuple[Figure, animation.FuncAnimation]:
    """Side-by-side animation (ground truth | prediction) for notebooks.

    Args:
      truth: ``(T, N, D)`` normalised positions, ``D = 2`` (disks) or 3
        (spheres, in perspective). prediction: the same shape, or ``None``
        for a single panel.
      radius: ``(N,)`` normalised radii (circles drawn to scale).
      mask: optional ``(N,)`` bool hiding padding particles.
      frame_dt: frame spacing in s for the title (``None``: frame numbers).
      input_frames: frames ``< input_frames`` are marked "input" in the title
        (``None``: no marks).
      start, stop, stride: the frames shown, ``range(T)[start:stop:stride]``.
      fps: frames per second. box_half_size: ``L`` in m to label radii in mm.
      bounds: the box, per axis ``(low, high)`` in units of ``L`` (``None``:
        ``[-1, 1]^D``); a box wider than :data:`WIDE_ASPECT` times its height
        stacks the panels.
      titles: panel titles. figsize, dpi: figure size (inches) and resolution;
        ``figsize=None``: 9 x 4.2 inches, or for a wide box
        ``(w + 1.2) x (panels (w / aspect + 0.35) + 0.45)`` with
        ``w = min(16, 3 aspect)``.
      cmap: matplotlib colour map for the radius.

    Returns:
      ``(fig, anim)``: the figure and a
      :class:`matplotlib.animation.FuncAnimation` (e.g. ``anim.to_jshtml()``).
    """
    if radius is None:
        raise ValueError("radius (N,) is required to draw particles to scale")
    trajectories, labels = _panels(truth, prediction, titles)
    trajectories, radius = _prepare(trajectories, radius, mask)
    frames = _frame_indices(trajectories[0].shape[0], start, stop, stride)
    scene = _Scene(
        list(zip(labels, trajectories)),
        radius,
        frame_dt=frame_dt,
        input_frames=input_frames,
        box_half_size=box_half_size,
        bounds=bounds,
        cmap=cmap,
        figsize=figsize,
        dpi=dpi,
    )
    anim = animation.FuncAnimation(scene.fig, scene.update, frames=frames, interval=1000.0 / fps, blit=False)
    return scene.fig, anim


def _rgb_frames(scene: _Scene, frames: Sequence[int]):
    """Render each frame on the Agg canvas; yields ``(H, W, 3)`` uint8 arrays."""
    canvas = scene.fig.canvas
    for frame in frames:
        scene.update(frame)
        canvas.draw()
        yield np.asarray(canvas.buffer_rgba())[..., :3].copy()


def _write_gif(scene: _Scene, frames: Sequence[int], path: str, fps: float) -> None:
    from PIL import Image

    # Frames are quantised to a palette as they are rendered (1 byte per pixel)
    # so a 500-frame rollout does not sit in memory as RGBA.
    images = (Image.fromarray(rgb).quantize(colors=256) for rgb in _rgb_frames(scene, frames))
    first = next(images)
    first.save(path, format="GIF", save_all=True, append_images=images, duration=int(round(1000.0 / fps)), loop=0)


def _write_mp4(scene: _Scene, frames: Sequence[int], path: str, fps: float, ffmpeg: str) -> None:
    with matplotlib.rc_context({"animation.ffmpeg_path": ffmpeg}):
        writer = animation.FFMpegWriter(fps=fps)
        with writer.saving(scene.fig, path, scene.fig.dpi):
            for frame in frames:
                scene.update(frame)
                writer.grab_frame()


def save_rollout_animation(
    path: str | os.PathLike,
    truth: Positions,
    prediction: Positions | None = None,
    radius: Radii | None = None,
    *,
    mp4: bool = True,
    mask: ParticleMask | None = None,
    frame_dt: float | None = 1.5e-3,
    input_frames: int | None = 6,
    start: int = 0,
    stop: int | None = None,
    stride: int = 1,
    fps: float = 20.0,
    box_half_size: float | None = None,
    bounds: _BoxLike | None = None,
    titles: Sequence[str] = ("ground truth", "prediction"),
    figsize: tuple[float, float] | None = None,
    dpi: float = 80,
    cmap: str = "viridis",
) -> dict[str, Any]:
    """Write the side-by-side animation as a GIF, and as an MP4 if ffmpeg exists.

    Args:
      path: output path; its extension (``.gif``/``.mp4``, if any) is dropped
        and ``<path>.gif`` and ``<path>.mp4`` are written.
      mp4: also write the MP4 (needs ffmpeg: imageio-ffmpeg's binary or one
        on ``PATH``; without one the MP4 is skipped and the reason returned).
      Other arguments as in :func:`rollout_animation`.

    Returns:
      ``{"gif": path, "mp4": path or None, "frames": n, "mp4_skipped": reason
      or None}``. Each file is written atomically. The GIF holds exactly
      ``n`` frames (every frame differs: its title shows the time).
    """
    if radius is None:
        raise ValueError("radius (N,) is required to draw particles to scale")
    base = os.fspath(path)
    if os.path.splitext(base)[1].lower() in (".gif", ".mp4"):
        base = os.path.splitext(base)[0]
    trajectories, labels = _panels(truth, prediction, titles)
    trajectories, radius = _prepare(trajectories, radius, mask)
    frames = _frame_indices(trajectories[0].shape[0], start, stop, stride)
    scene = _Scene(
        list(zip(labels, trajectories)),
        radius,
        frame_dt=frame_dt,
        input_frames=input_frames,
        box_half_size=box_half_size,
        bounds=bounds,
        cmap=cmap,
        figsize=figsize,
        dpi=dpi,
    )
    result: dict[str, Any] = {"gif": None, "mp4": None, "frames": len(frames), "mp4_skipped": None}
    result["gif"] = _atomic_write(base + ".gif", lambda tmp: _write_gif(scene, frames, tmp, fps))
    if not mp4:
        result["mp4_skipped"] = "not requested"
    else:
        ffmpeg = ffmpeg_executable()
        if ffmpeg is None:
            result["mp4_skipped"] = "no ffmpeg binary found (pip install imageio-ffmpeg, or put ffmpeg on PATH)"
        else:
            result["mp4"] = _atomic_write(base + ".mp4", lambda tmp: _write_mp4(scene, frames, tmp, fps, ffmpeg))
    return result


def frame_grid(
    truth: Positions,
    prediction: Positions | None = None,
    radius: Radii | None = None,
    frames: Sequence[int] = (0, 100, 200, 300, 400),
    *,
    mask: ParticleMask | None = None,
    frame_dt: float | None = 1.5e-3,
    box_half_size: float | None = None,
    bounds: _BoxLike | None = None,
    row_labels: Sequence[str] = ("ground truth", "prediction"),
    panel_size: float = 2.4,
    dpi: float = 100,
    cmap: str = "viridis",
    path: str | os.PathLike | None = None,
) -> Figure:
    """Still grid of snapshots like the paper's figures.

    Rows are ground truth and prediction (one row if ``prediction`` is
    ``None``), columns the requested frames (negative indices count from the
    end), each titled with its time. A box wider than :data:`WIDE_ASPECT`
    times its height is drawn in one column instead: for each frame, truth
    above prediction, each panel titled with both.

    Args:
      truth, prediction: ``(T, N, D)`` normalised positions (D = 2 or 3).
      radius: ``(N,)`` normalised radii. frames: frame indices.
      mask: optional ``(N,)`` bool. frame_dt: s per frame for the titles.
      box_half_size: ``L`` in m to label radii in mm.
      bounds: the box, per axis ``(low, high)`` in units of ``L`` (``None``:
        ``[-1, 1]^D``).
      row_labels: labels of the rows. panel_size: inches per panel (its
        height; a wide box's panels are ``min(16, panel_size * aspect)``
        inches wide).
      dpi: resolution. cmap: colour map for the radius.
      path: if given, the PNG (or other extension) is written atomically.

    Returns:
      The figure, ``(len(frames) * panel_size + 1.2) x (rows * panel_size +
      0.4)`` inches for a box at most :data:`WIDE_ASPECT` times as wide as
      tall, so the image is that times ``dpi`` pixels.
    """
    if radius is None:
        raise ValueError("radius (N,) is required to draw particles to scale")
    trajectories, labels = _panels(truth, prediction, row_labels)
    trajectories, radius = _prepare(trajectories, radius, mask)
    n_frames = trajectories[0].shape[0]
    frames = [int(f) for f in frames]
    for f in frames:
        if not -n_frames <= f < n_frames:
            raise ValueError(f"frame {f} out of range for a trajectory of {n_frames} frames")
    frames = [f % n_frames for f in frames]
    if not frames:
        raise ValueError("frames must name at least one frame")
    colours, colour_label = _radius_scale(radius, box_half_size)
    norm = _radius_norm(colours)
    box = _box(bounds, trajectories[0].shape[-1])
    aspect = _aspect(box)
    rows, cols = len(trajectories), len(frames)
    if aspect > WIDE_ASPECT:
        width = min(WIDE_WIDTH_IN, panel_size * aspect)
        fig = _new_figure((width + 1.2, rows * cols * (width / aspect + 0.35) + 0.2), dpi, layout="constrained")
        axes = fig.subplots(rows * cols, 1, squeeze=False)
        for c, frame in enumerate(frames):
            for r, (label, traj) in enumerate(zip(labels, trajectories)):
                ax = axes[c * rows + r, 0]
                _box_axes(ax, f"{label}, {_time_label(frame, frame_dt, None)}", box)
                _particles(ax, traj[frame], radius, colours, norm, cmap)
    else:
        fig = _new_figure((cols * panel_size + 1.2, rows * panel_size + 0.4), dpi, layout="constrained")
        axes = fig.subplots(rows, cols, squeeze=False)
        for r, (label, traj) in enumerate(zip(labels, trajectories)):
            for c, frame in enumerate(frames):
                ax = axes[r, c]
                _box_axes(ax, _time_label(frame, frame_dt, None) if r == 0 else None, box)
                _particles(ax, traj[frame], radius, colours, norm, cmap)
                if c == 0:
                    ax.set_ylabel(label)
    fig.colorbar(ScalarMappable(norm=norm, cmap=cmap), ax=axes.ravel().tolist(), label=colour_label, shrink=0.8)
    if path is not None:
        save_figure(fig, path)
    return fig


# ----------------------------------------------------------------------------
# curves
# ----------------------------------------------------------------------------


def _positive(values) -> np.ndarray:
    """Float array with non-positive and non-finite entries hidden (log axes)."""
    values = np.asarray(values, np.float64)
    return np.where(np.isfinite(values) & (values > 0), values, np.nan)


def _curve(value):
    """A list, or a :func:`dispgns.metrics.summarize` entry ``{"mean", "std"}``."""
    if isinstance(value, Mapping):
        return np.asarray(value["mean"], np.float64), np.asarray(value.get("std", []), np.float64)
    return np.asarray(value, np.float64), None


def plot_error_curves(
    curves: Mapping[str, Any],
    *,
    frame_dt: float | None = None,
    ylabel: str = "MSE (normalised units$^2$)",
    title: str | None = None,
    figsize: tuple[float, float] = (6.0, 4.0),
    dpi: float = 100,
    path: str | os.PathLike | None = None,
) -> Figure:
    """Per-frame error curves on a log scale (model vs. baselines).

    Args:
      curves: label -> per-frame values over the predicted frames (entry ``k``
        is ``k + 1`` model steps after the last input frame), as a list, or as
        a ``{"mean": [...], "std": [...]}`` entry of
        :func:`dispgns.metrics.summarize` (drawn with a ±std band).
      frame_dt: s per frame: the x axis is then the time after the last input
        frame in s, else the number of model steps.
      ylabel, title, figsize, dpi: labels and size. path: write atomically.

    Returns:
      The figure. Non-positive values are left out (log scale).
    """
    fig = _new_figure(figsize, dpi, layout="constrained")
    ax = fig.subplots()
    for label, value in curves.items():
        if value is None:
            continue
        mean, std = _curve(value)
        steps = np.arange(1, mean.size + 1, dtype=np.float64)
        x = steps * frame_dt if frame_dt is not None else steps
        (line,) = ax.plot(x, _positive(mean), label=label)
        if std is not None and std.size == mean.size:
            ax.fill_between(
                x, _positive(mean - std), _positive(mean + std), color=line.get_color(), alpha=0.2, linewidth=0
            )
    ax.set_yscale("log")
    ax.set_xlabel("time after the last input frame (s)" if frame_dt is not None else "model steps")
    ax.set_ylabel(ylabel)
    ax.grid(True, which="major", alpha=0.3)
    if curves:
        ax.legend()
    if title:
        ax.set_title(title)
    if path is not None:
        save_figure(fig, path)
    return fig


def plot_rollout_errors(
    metrics: Mapping[str, Any],
    *,
    frame_dt: float | None = None,
    title: str | None = None,
    path: str | os.PathLike | None = None,
    **kwargs,
) -> Figure:
    """Model vs. constant velocity vs. chaos floor from a metrics dict.

    Args:
      metrics: a :func:`dispgns.metrics.rollout_metrics` dict (or the
        :func:`dispgns.metrics.summarize` of several): reads ``per_frame_mse``,
        ``constant_velocity_per_frame_mse`` and, if present,
        ``chaos_floor_per_frame_mse``.
      frame_dt: s per frame (default: the dict's ``frame_dt`` if it holds one).
      title, path, kwargs: as in :func:`plot_error_curves`.
    """
    if frame_dt is None and isinstance(metrics.get("frame_dt"), (int, float)):
        frame_dt = float(metrics["frame_dt"])
    curves = {
        "model": metrics.get("per_frame_mse"),
        "constant velocity": metrics.get("constant_velocity_per_frame_mse"),
        "chaos floor (1e-6 L perturbation)": metrics.get("chaos_floor_per_frame_mse"),
    }
    curves = {label: value for label, value in curves.items() if value is not None}
    return plot_error_curves(curves, frame_dt=frame_dt, title=title, path=path, **kwargs)


def _scalar(metrics: Mapping[str, Any], key: str) -> float | None:
    value = metrics.get(key)
    if isinstance(value, Mapping):
        value = value.get("mean")
    return float(value) if isinstance(value, (int, float)) else None


def plot_statistics(
    metrics: Mapping[str, Any],
    *,
    frame_dt: float | None = None,
    box_half_size: float | None = None,
    title: str | None = None,
    figsize: tuple[float, float] = (13.0, 4.0),
    dpi: float = 100,
    path: str | os.PathLike | None = None,
) -> Figure:
    """The suspension statistics of a rollout: truth, model, constant velocity and chaos floor overlaid.

    Three panels: the mean height against time, the final height profile
    (particles per slab against height) and the final frame's g(r).

    Args:
      metrics: a :func:`dispgns.metrics.rollout_metrics` dict computed with
        ``statistics=True``, or the :func:`dispgns.metrics.summarize` of
        several (curves are then means over trajectories).
      frame_dt: s per frame; box_half_size: ``L`` in m (default: the dict's).
      title, figsize, dpi: labels and size. path: write atomically.
    """
    frame_dt = _scalar(metrics, "frame_dt") if frame_dt is None else frame_dt
    box_half_size = _scalar(metrics, "box_half_size") if box_half_size is None else box_half_size
    scale, unit = (box_half_size * 1e3, "mm") if box_half_size else (1.0, "L")
    fig = _new_figure(figsize, dpi, layout="constrained")
    height_ax, profile_ax, rdf_ax = fig.subplots(1, 3)

    def mean_of(key):
        value = metrics.get(key)
        return None if value is None else _curve(value)[0]

    truth = mean_of("mean_height_truth")
    if truth is not None:
        steps = np.arange(1, truth.size + 1, dtype=np.float64)
        x = steps * frame_dt if frame_dt else steps
        error = mean_of("mean_height_error")
        lines = {
            "truth": truth,
            "model": None if error is None else truth + error,
            "constant velocity": mean_of("constant_velocity_mean_height"),
            "chaos floor": mean_of("chaos_floor_mean_height"),
        }
        for label, value in lines.items():
            if value is not None:
                height_ax.plot(x, value * scale, label=label, linestyle="--" if label == "chaos floor" else "-")
        height_ax.set_xlabel("time after the last input frame (s)" if frame_dt else "model steps")
        height_ax.set_ylabel(f"mean height ({unit})")
        low = np.nanmin(truth) * scale
        span = (np.nanmax(truth) - np.nanmin(truth)) * scale
        height_ax.set_ylim(low - 0.3 * span, np.nanmax(truth) * scale + 0.3 * span)
        height_ax.legend()
    profile = mean_of("height_profile_truth")
    if profile is not None:
        edges = np.linspace(-1.0, 1.0, profile.size + 1) * scale
        for label, key in (
            ("truth", "height_profile_truth"),
            ("model", "height_profile"),
            ("constant velocity", "constant_velocity_height_profile"),
            ("chaos floor", "chaos_floor_height_profile"),
        ):
            value = mean_of(key)
            if value is not None:
                profile_ax.stairs(value, edges, orientation="horizontal", label=label)
        profile_ax.set_xlabel("particles per slab (final frame)")
        profile_ax.set_ylabel(f"height ({unit})")
        profile_ax.legend()
    r = mean_of("rdf_r")
    if r is not None:
        for label, key in (("truth", "rdf_truth"), ("model", "rdf"), ("chaos floor", "chaos_floor_rdf")):
            value = mean_of(key)
            if value is not None:
                rdf_ax.plot(r * scale, value, label=label, linestyle="--" if label == "chaos floor" else "-")
        rdf_ax.set_xlabel(f"r ({unit})")
        rdf_ax.set_ylabel("g(r), final frame")
        rdf_ax.legend()
    for ax in (height_ax, profile_ax, rdf_ax):
        ax.grid(True, alpha=0.3)
    if title:
        fig.suptitle(title)
    if path is not None:
        save_figure(fig, path)
    return fig


def _running_mean(values: np.ndarray, window: int) -> np.ndarray:
    if window <= 1 or values.size < window:
        return values
    kernel = np.ones(window) / window
    valid = np.convolve(values, kernel, mode="valid")
    return np.concatenate([np.full(window - 1, np.nan), valid])


def plot_training_curve(
    steps: Sequence[float],
    loss: Sequence[float],
    *,
    validation: Mapping[str, tuple[Sequence[float], Sequence[float]]]
    | tuple[Sequence[float], Sequence[float]]
    | None = None,
    smooth: int = 0,
    logy: bool = True,
    title: str | None = None,
    figsize: tuple[float, float] = (6.0, 4.0),
    dpi: float = 100,
    path: str | os.PathLike | None = None,
) -> Figure:
    """Training loss (and validation metrics) against the training step.

    Args:
      steps, loss: the training log as plain lists of equal length.
      validation: ``(steps, values)`` for one validation series, or a mapping
        label -> ``(steps, values)`` for several (e.g. one-step loss and
        rollout MSE).
      smooth: if > 1, also draw the running mean of the loss over this many
        log entries (the raw loss is then drawn faint).
      logy: log scale for the values. title, figsize, dpi: labels and size.
      path: write atomically.
    """
    steps = np.asarray(steps, np.float64)
    loss = np.asarray(loss, np.float64)
    if steps.shape != loss.shape or steps.ndim != 1:
        raise ValueError(f"steps and loss must be 1-D lists of equal length, got {steps.shape} and {loss.shape}")
    fig = _new_figure(figsize, dpi, layout="constrained")
    ax = fig.subplots()
    transform = _positive if logy else (lambda v: np.asarray(v, np.float64))
    if smooth > 1:
        ax.plot(steps, transform(loss), color="C0", alpha=0.3, linewidth=0.8)
        ax.plot(steps, transform(_running_mean(loss, smooth)), color="C0", label=f"training loss (mean of {smooth})")
    else:
        ax.plot(steps, transform(loss), color="C0", label="training loss")
    if validation is not None:
        series = {"validation": validation} if not isinstance(validation, Mapping) else dict(validation)
        for i, (label, (val_steps, values)) in enumerate(series.items()):
            val_steps = np.asarray(val_steps, np.float64)
            values = np.asarray(values, np.float64)
            if val_steps.shape != values.shape:
                raise ValueError(f"validation {label!r}: steps {val_steps.shape} and values {values.shape} differ")
            ax.plot(val_steps, transform(values), marker="o", markersize=3, color=f"C{i + 1}", label=label)
    if logy:
        ax.set_yscale("log")
    ax.set_xlabel("training step")
    ax.set_ylabel("loss")
    ax.grid(True, alpha=0.3)
    ax.legend()
    if title:
        ax.set_title(title)
    if path is not None:
        save_figure(fig, path)
    return fig

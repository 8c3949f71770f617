"""Pictures: files written atomically, frame counts, sizes, and particles drawn to scale."""

from __future__ import annotations

import os

import numpy as np
import pytest
from matplotlib.figure import Figure
from PIL import Image

from dispgns import render as R


def _trajectory(t=12, n=15, seed=0):
    """Particles falling inside the box; normalised units."""
    rng = np.random.default_rng(seed)
    start = rng.uniform(-0.7, 0.7, (n, 2))
    fall = np.linspace(0.0, 0.2, t)[:, None, None] * np.array([0.0, -1.0])
    truth = start[None] + fall
    radius = rng.choice([0.02, 0.03, 0.04, 0.05], n)
    return truth, truth + rng.normal(0, 0.01, truth.shape), radius


def _files(directory):
    return sorted(os.listdir(directory))


def test_animation_gif_and_mp4(tmp_path):
    truth, prediction, radius = _trajectory()
    result = R.save_rollout_animation(
        tmp_path / "rollout.gif", truth, prediction, radius, stride=2, start=1, box_half_size=0.1, fps=10, dpi=40
    )
    assert result["frames"] == len(range(12)[1::2]) == 6
    assert result["gif"] == str(tmp_path / "rollout.gif")
    with Image.open(result["gif"]) as gif:
        assert gif.n_frames == 6
        assert gif.size == (int(9.0 * 40), int(4.2 * 40))
        assert gif.info["duration"] == 100
    if R.ffmpeg_executable() is None:
        assert result["mp4"] is None and "ffmpeg" in result["mp4_skipped"]
    else:
        assert result["mp4"] == str(tmp_path / "rollout.mp4")
        assert result["mp4_skipped"] is None
        assert os.path.getsize(result["mp4"]) > 1000
    assert _files(tmp_path) == ["rollout.gif", "rollout.mp4"][: 1 if result["mp4"] is None else 2]


def test_animation_frame_range_and_single_panel_without_mp4(tmp_path, monkeypatch):
    truth, _, radius = _trajectory(t=10)
    monkeypatch.setattr(R, "ffmpeg_executable", lambda: None)
    mask = np.arange(truth.shape[1]) < 10
    result = R.save_rollout_animation(tmp_path / "truth", truth, None, radius, mask=mask, start=2, stop=7, dpi=30)
    assert result["mp4"] is None and "ffmpeg" in result["mp4_skipped"]
    with Image.open(tmp_path / "truth.gif") as gif:
        assert gif.n_frames == 5
    result = R.save_rollout_animation(tmp_path / "again", truth, None, radius, mp4=False, stop=2, dpi=30)
    assert result["mp4_skipped"] == "not requested"
    assert _files(tmp_path) == ["again.gif", "truth.gif"]
    with pytest.raises(ValueError, match="no frames"):
        R.save_rollout_animation(tmp_path / "none", truth, None, radius, start=20)


def test_notebook_animation_object():
    truth, prediction, radius = _trajectory(t=5)
    fig, anim = R.rollout_animation(truth, prediction, radius, stride=2, dpi=30)
    assert isinstance(fig, Figure)
    assert "<script" in anim.to_jshtml()


def test_frame_grid_png_size(tmp_path):
    truth, prediction, radius = _trajectory()
    path = tmp_path / "grid.png"
    fig = R.frame_grid(truth, prediction, radius, frames=(0, 5, -1), box_half_size=0.1, dpi=50, path=path)
    assert isinstance(fig, Figure)
    with Image.open(path) as png:
        assert png.format == "PNG"
        assert png.size == (round((3 * 2.4 + 1.2) * 50), round((2 * 2.4 + 0.4) * 50))
    assert _files(tmp_path) == ["grid.png"]
    with pytest.raises(ValueError, match="out of range"):
        R.frame_grid(truth, prediction, radius, frames=(12,))


def test_particles_are_round_to_scale_and_in_the_box(tmp_path):
    """One disk of radius 0.5 at (0.3, 0.1): its pixels form a circle of the right size and place."""
    truth = np.array([[[0.3, 0.1]]])
    path = tmp_path / "disk.png"
    fig = R.frame_grid(truth, None, np.array([0.5]), frames=(0,), frame_dt=None, dpi=100, panel_size=4.0, path=path)
    ax = fig.axes[0]
    rgb = np.asarray(Image.open(path).convert("RGB")).astype(int)
    height = rgb.shape[0]
    # Box corners in pixels (matplotlib's display origin is the bottom left).
    (x0, y0), (x1, y1) = ax.transData.transform([(-1, -1), (1, 1)])
    assert x1 - x0 == pytest.approx(y1 - y0, rel=1e-6)  # equal aspect
    scale = (x1 - x0) / 2.0  # pixels per box unit
    # The disk's colour: the colour map's value at the (single) radius.
    inside = rgb[int(height - y1) + 3 : int(height - y0) - 3, int(x0) + 3 : int(x1) - 3]
    white = np.all(inside > 240, axis=-1)
    dark = np.all(inside < 60, axis=-1)
    disk = ~white & ~dark
    area = disk.sum() + dark.sum()  # edge line pixels are part of the disk outline
    assert area == pytest.approx(np.pi * (0.5 * scale) ** 2, rel=0.05)
    rows, cols = np.nonzero(disk)
    assert cols.max() - cols.min() == pytest.approx(rows.max() - rows.min(), abs=2)  # round
    assert cols.max() - cols.min() == pytest.approx(1.0 * scale, abs=4)  # diameter 2a = 1 box unit
    centre_x = x0 + 3 + 0.5 * (cols.max() + cols.min())
    centre_y = height - (int(height - y1) + 3 + 0.5 * (rows.max() + rows.min()))
    assert centre_x == pytest.approx(x0 + 1.3 * scale, abs=2)
    assert centre_y == pytest.approx(y0 + 1.1 * scale, abs=2)


def test_curve_plots(tmp_path):
    curves = {
        "model": [1e-5, 2e-5, 0.0, 4e-5],
        "constant velocity": {"mean": [1e-6, 1e-4, 1e-3, 1e-2], "std": [0, 1e-5, 1e-4, 1e-3]},
    }
    fig = R.plot_error_curves(curves, frame_dt=1.5e-3, path=tmp_path / "errors.png", dpi=50)
    assert fig.axes[0].get_yscale() == "log"
    metrics = {
        "frame_dt": 1.5e-3,
        "per_frame_mse": [1e-5, 2e-5],
        "constant_velocity_per_frame_mse": [1e-6, 1e-3],
        "chaos_floor_per_frame_mse": [1e-14, 1e-12],
    }
    fig = R.plot_rollout_errors(metrics, path=tmp_path / "rollout_errors.png")
    assert len(fig.axes[0].get_lines()) == 3
    fig = R.plot_training_curve(
        list(range(0, 100, 10)),
        [1.0 / (s + 1) for s in range(10)],
        validation={"one-step": ([0, 50, 90], [1.0, 0.1, 0.05]), "rollout MSE": ([0, 90], [0.1, 0.01])},
        smooth=3,
        path=tmp_path / "training.png",
        dpi=50,
    )
    assert len(fig.axes[0].get_lines()) == 4
    R.plot_training_curve([0, 1], [1.0, 0.5], validation=([1], [0.7]), logy=False, path=tmp_path / "t2.png")
    for name in ("errors.png", "rollout_errors.png", "training.png", "t2.png"):
        with Image.open(tmp_path / name) as png:
            assert png.format == "PNG" and os.path.getsize(tmp_path / name) > 1000
    with Image.open(tmp_path / "errors.png") as png:
        assert png.size == (300, 200)
    assert len(_files(tmp_path)) == 4


def test_failing_writes_leave_no_partial_file(tmp_path, monkeypatch):
    truth, prediction, radius = _trajectory(t=4)
    (tmp_path / "old.png").write_bytes(b"previous content")

    def broken_savefig(self, fname, **kwargs):
        with open(fname, "wb") as handle:
            handle.write(b"partial")
        raise OSError("disk full")

    with monkeypatch.context() as patch:
        patch.setattr(Figure, "savefig", broken_savefig)
        with pytest.raises(OSError, match="disk full"):
            R.frame_grid(truth, prediction, radius, frames=(0,), path=tmp_path / "grid.png")
        with pytest.raises(OSError, match="disk full"):
            R.plot_error_curves({"model": [1.0]}, path=tmp_path / "old.png")
    assert _files(tmp_path) == ["old.png"]
    assert (tmp_path / "old.png").read_bytes() == b"previous content"

    def broken_save(self, fp, *args, **kwargs):
        with open(fp, "wb") as handle:
            handle.write(b"GIF89a partial")
        raise OSError("disk full")

    with monkeypatch.context() as patch:
        patch.setattr(Image.Image, "save", broken_save)
        with pytest.raises(OSError, match="disk full"):
            R.save_rollout_animation(tmp_path / "anim", truth, prediction, radius, dpi=30)
    assert _files(tmp_path) == ["old.png"]


def _disk_width_px(path, fig):
    """Width in box units (of the panel's data scale) of the one coloured disk in a single-panel PNG."""
    rgb = np.asarray(Image.open(path).convert("RGB")).astype(int)
    ax = fig.axes[0]
    (x0, _), (x1, _) = ax.transData.transform([(0, 0), (1, 0)])
    box = ax.get_window_extent()  # the panel only, not the colour bar
    top = rgb.shape[0] - int(box.y1)
    panel = rgb[top : top + int(box.height), int(box.x0) : int(box.x1)]
    colourful = (panel.max(axis=-1) - panel.min(axis=-1)) > 40  # the colour map's colours; lines are grey
    cols = np.nonzero(colourful.any(axis=0))[0]
    return (cols.max() - cols.min() + 1) / (x1 - x0)


@pytest.mark.parametrize("toward_camera", [0.0, 0.8])
def test_spheres_are_drawn_in_perspective_to_scale(tmp_path, toward_camera):
    # A sphere of radius 0.3 at the cube's centre keeps its size (the camera's scale is 1 at the
    # centre's depth); moved 0.8 towards the camera it grows by 5 / (5 - depth).
    az, el = np.radians(30.0), np.radians(20.0)
    direction = np.array([np.sin(az), -np.cos(az), 0.0])  # horizontal direction towards the camera
    truth = (toward_camera * direction)[None, None]
    depth = np.cos(el) * toward_camera
    path = tmp_path / "sphere.png"
    fig = R.frame_grid(truth, None, np.array([0.3]), frames=(0,), frame_dt=None, dpi=100, panel_size=4.0, path=path)
    assert _disk_width_px(path, fig) == pytest.approx(0.6 * 5.0 / (5.0 - depth), rel=0.04)


def test_3d_animation_and_grid_of_spheres(tmp_path):
    truth, prediction, radius = _trajectory(t=6, n=20)
    lift = lambda x: np.concatenate([x[..., :1], 0.3 * np.sin(x[..., :1] * 5), x[..., 1:]], axis=-1)
    result = R.save_rollout_animation(tmp_path / "r", lift(truth), lift(prediction), radius, mp4=False, dpi=30)
    with Image.open(result["gif"]) as gif:
        assert gif.n_frames == 6 and gif.size == (int(9.0 * 30), int(4.2 * 30))
    R.frame_grid(lift(truth), lift(prediction), radius, frames=(0, -1), dpi=30, path=tmp_path / "g.png")
    with Image.open(tmp_path / "g.png") as png:
        assert png.size == (round((2 * 2.4 + 1.2) * 30), round((2 * 2.4 + 0.4) * 30))
    with pytest.raises(ValueError, match="same dimension"):
        R.frame_grid(lift(truth), prediction, radius, frames=(0,))


def test_wide_box_is_drawn_to_its_aspect_with_panels_stacked(tmp_path):
    """A container 4x wider than tall: its walls, limits and pixels keep 4:1; a disk near the right wall shows."""
    bounds = ((-4.0, 4.0), (-1.0, 1.0))
    truth = np.array([[[3.5, -0.5]], [[3.5, -0.6]]])
    path = tmp_path / "wide.png"
    fig = R.frame_grid(truth, truth, np.array([0.4]), frames=(0, 1), frame_dt=None, bounds=bounds, dpi=50, path=path)
    axes = [ax for ax in fig.axes if ax.get_title()]  # the panels, not the colour bar
    assert len(axes) == 4  # one column: frame 0 truth, prediction, frame 1 truth, prediction
    assert [ax.get_title() for ax in axes[:2]] == ["ground truth, frame 0", "prediction, frame 0"]
    for ax in axes:
        assert ax.get_xlim() == pytest.approx((-4.04, 4.04))
        assert ax.get_ylim() == pytest.approx((-1.04, 1.04))
        (x0, y0), (x1, y1) = ax.transData.transform([(-4, -1), (4, 1)])
        assert (x1 - x0) / (y1 - y0) == pytest.approx(4.0, rel=1e-6)
        (wall,) = ax.patches
        assert (wall.get_x(), wall.get_y(), wall.get_width(), wall.get_height()) == (-4.0, -1.0, 8.0, 2.0)
    # Panels stacked above each other, each as wide as the box and its margins over their height.
    first, second = (ax.get_window_extent() for ax in axes[:2])
    assert second.y1 < first.y0
    assert first.width == pytest.approx(8.08 / 2.08 * first.height, rel=0.01)
    # The disk at x = 3.5 is drawn where it is, beyond the square [-1, 1]^2.
    rgb = np.asarray(Image.open(path).convert("RGB")).astype(int)
    cx, cy = axes[0].transData.transform((3.5, -0.5))
    pixel = rgb[int(round(rgb.shape[0] - cy)), int(round(cx))]
    assert (pixel.max() - pixel.min()) > 40  # the colour map's colour, not white or black

    result = R.save_rollout_animation(
        tmp_path / "wide", truth, truth, np.array([0.4]), bounds=bounds, mp4=False, dpi=20
    )
    with Image.open(result["gif"]) as gif:
        width = min(R.WIDE_WIDTH_IN, 3.0 * 8.08 / 2.08)
        assert gif.size == (int((width + 1.2) * 20), int((2 * (width * 2.08 / 8.08 + 0.35) + 0.45) * 20))
    square = R.frame_grid(truth[:, :, :] / 4, None, np.array([0.1]), frames=(0,), bounds=((-1, 1), (-1, 1)))
    assert square.axes[0].get_xlim() == pytest.approx((-1.04, 1.04))
    with pytest.raises(ValueError, match="bounds must be 2 pairs"):
        R.frame_grid(truth, None, np.array([0.4]), frames=(0,), bounds=((4.0, -4.0), (-1.0, 1.0)))
    with pytest.raises(ValueError, match="bounds must be 2 pairs"):
        R.frame_grid(truth, None, np.array([0.4]), frames=(0,), bounds=((-4.0, 4.0),))

"""Rendering at 10^4 particles: how long `dispgns render`'s animation takes; prints JSON.

Draws the side-by-side (here stacked: the box is wide) animation of
:func:`dispgns.render.save_rollout_animation` for ``--particles`` disks (default
10^4) in both panels, truth and prediction, over ``--frames`` frames (default
100), as `dispgns render` and `dispgns demo` do: a GIF (and with ``--mp4`` an
MP4), the default size and resolution for the box. The disks have the paper's
radii (2-5 mm, L = 0.1 m) in a container of the paper's height 16x wider (the
``wide16`` box, bounds ``((-16, 16), (-1, 1))``), on a jittered lattice that
falls and shakes from frame to frame, so every frame differs.

Reported (median of ``--repeats`` runs, each a fresh figure and file):
``gif_s`` (wall clock of the whole GIF: figure set-up, drawing, palette
quantisation, writing), ``gif_cpu_s`` (this process's CPU time for the same:
on a loaded machine the wall clock measures the load, the CPU time much less
so), ``ms_per_frame`` and ``cpu_ms_per_frame``, the GIF's size and pixels; with
``--mp4`` the same for the MP4. For comparison, ``one_patch_per_particle_ms_per_frame``
draws ``--baseline-frames`` frames the way a collection avoids: a new
:class:`matplotlib.patches.Circle` per particle per frame, in one panel
(drawing only, no file; CPU time), so ``collection_speedup``, its CPU time per
frame over the collections' (two panels, GIF written), understates the gain.
The last line is the summary with the machine (CPU model, cores, load average).

Usage: python benchmarks/render.py [--particles 10000] [--frames 100] [--repeats 3] [--mp4]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import tempfile
import time

import _machine
import numpy as np

BOUNDS = ((-16.0, 16.0), (-1.0, 1.0))  # the wide16 box in units of L = 0.1 m
RADII = np.array([2.0, 2.5, 3.0, 3.5, 4.0, 4.5, 5.0]) * 1e-3 / 0.1  # the paper's radii / L


def machine_info() -> dict:
    return _machine.machine_info(python=platform.python_version())


def trajectories(n: int, frames: int, seed: int = 0):
    """Truth and prediction ``(frames, n, 2)`` in the wide box, radii ``(n,)``, all in units of L."""
    rng = np.random.default_rng(seed)
    (x0, x1), (y0, y1) = BOUNDS
    rows = max(1, int(round(np.sqrt(n * (y1 - y0) / (x1 - x0)))))
    cols = -(-n // rows)
    x, y = np.meshgrid(np.linspace(x0 + 0.06, x1 - 0.06, cols), np.linspace(y0 + 0.06, y1 - 0.06, rows))
    start = np.stack([x.ravel(), y.ravel()], axis=-1)[:n]
    fall = np.linspace(0.0, -0.05, frames)[:, None, None] * np.array([0.0, 1.0])
    truth = start[None] + fall + rng.normal(0.0, 0.005, (frames, n, 2))
    prediction = truth + rng.normal(0.0, 0.01, truth.shape)
    return truth, prediction, rng.choice(RADII, n)


def one_patch_per_particle_ms(truth, radius, frames: int) -> float:
    """Median CPU ms to draw one frame with a new Circle patch per particle (what a collection avoids)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Circle

    fig = Figure(figsize=(17.2, 2.6), dpi=80)
    canvas = FigureCanvasAgg(fig)
    ax = fig.subplots()
    ax.set_xlim(BOUNDS[0])
    ax.set_ylim(BOUNDS[1])
    ax.set_aspect("equal")
    times = []
    for frame in range(frames):
        start = time.process_time()
        for patch in list(ax.patches):
            patch.remove()
        for (x, y), a in zip(truth[frame], radius):
            ax.add_patch(Circle((x, y), a, facecolor="C0", edgecolor="black", linewidth=0.3))
        canvas.draw()
        times.append(time.process_time() - start)
    return 1e3 * statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--particles", type=int, default=10_000)
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--mp4", action="store_true", help="also time the MP4 (needs ffmpeg)")
    parser.add_argument("--baseline-frames", type=int, default=3, help="frames drawn one patch per particle")
    args = parser.parse_args()

    from PIL import Image

    from dispgns.render import ffmpeg_executable, save_rollout_animation

    truth, prediction, radius = trajectories(args.particles, args.frames)
    runs = []
    with tempfile.TemporaryDirectory() as scratch:
        for repeat in range(args.repeats):
            base = os.path.join(scratch, f"rollout{repeat}")
            start, cpu = time.perf_counter(), time.process_time()
            save_rollout_animation(
                base, truth, prediction, radius, mp4=False, bounds=BOUNDS, box_half_size=0.1, input_frames=None
            )
            gif_s, gif_cpu_s = time.perf_counter() - start, time.process_time() - cpu
            with Image.open(base + ".gif") as gif:
                size, n_frames = gif.size, gif.n_frames
            run = {"gif_s": gif_s, "gif_cpu_s": gif_cpu_s, "gif_bytes": os.path.getsize(base + ".gif")}
            if args.mp4 and ffmpeg_executable() is not None:
                start = time.perf_counter()
                save_rollout_animation(
                    base, truth, prediction, radius, mp4=True, bounds=BOUNDS, box_half_size=0.1, input_frames=None
                )
                # The call writes the GIF again before the MP4: the MP4's own time is the difference.
                run["mp4_s"] = time.perf_counter() - start - gif_s
                run["mp4_bytes"] = os.path.getsize(base + ".mp4")
            runs.append(run)
            print(json.dumps({"repeat": repeat, **run}), flush=True)
    gif_s = statistics.median(r["gif_s"] for r in runs)
    summary = {
        "benchmark": "render",
        "particles_per_panel": args.particles,
        "panels": 2,
        "frames": n_frames,
        "gif_pixels": list(size),
        "gif_s": gif_s,
        "gif_s_runs": [r["gif_s"] for r in runs],
        "ms_per_frame": 1e3 * gif_s / n_frames,
        "gif_cpu_s": statistics.median(r["gif_cpu_s"] for r in runs),
        "cpu_ms_per_frame": 1e3 * statistics.median(r["gif_cpu_s"] for r in runs) / n_frames,
        "gif_mb": statistics.median(r["gif_bytes"] for r in runs) / 1e6,
    }
    if all("mp4_s" in r for r in runs) and args.mp4:
        summary["mp4_s"] = statistics.median(r["mp4_s"] for r in runs)
        summary["mp4_mb"] = statistics.median(r["mp4_bytes"] for r in runs) / 1e6
    if args.baseline_frames > 0:
        # One panel with patches against two panels with collections: the ratio understates the gain.
        patches_ms = one_patch_per_particle_ms(truth, radius, args.baseline_frames)
        summary["one_patch_per_particle_ms_per_frame"] = patches_ms
        summary["collection_speedup"] = patches_ms / summary["cpu_ms_per_frame"]
    summary.update(machine_info())
    print(json.dumps(summary))


if __name__ == "__main__":
    main()

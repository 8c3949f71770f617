"""Dataset presets and generation: sample initial states, simulate them in batches, write.

A :class:`DatasetSpec` says what to generate: per split, groups of
trajectories drawn from a radii list, the frame count and spacing, the
physics and the precision. :func:`generate_dataset` turns a spec and a seed
into a dataset directory (see :mod:`dispgns.data.format`):

1. every trajectory gets its own key, ``fold_in(fold_in(PRNGKey(seed),
   split_id), index)``, so changing one split never changes another;
2. initial states follow the authors' protocol: exactly what
   :func:`dispgns.physics.sample_initial_state` draws for that key, with one
   compilation for the whole dataset (:func:`sample_initial_states`);
3. trajectories are sorted by particle count, padded and simulated together
   by :func:`dispgns.physics.simulate_batch`: one call, or a few when the
   counts differ enough that padding everything to the largest would cost
   more than another compilation (:func:`plan_batches`);
4. the dataset is written into a temporary directory beside the target and
   renamed into place, so a failure never leaves a partial dataset.
"""

from __future__ import annotations

import concurrent.futures
import contextvars
import dataclasses
import itertools
import math
import numbers
import os
import threading
import warnings
from collections.abc import Callable, Mapping, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import DTypeLike

from dispgns.arrays import Positions, PRNGKey, Radii
from dispgns.data.format import (
    SPLITS,
    DatasetMetadata,
    Trajectory,
    radii_groups,
    split_filename,
    staged_directory,
    training_statistics,
    write_metadata,
    write_split,
)
from dispgns.physics import (
    InitialState,
    PhysicsConfig,
    PlacementError,
    particle_count_range,
    place_particles,
    sample_initial_state,
    simulate_batch,
)
from dispgns.tuning import thresholds

__all__ = [
    "DatasetSpec",
    "KEY_DERIVATION",
    "LANES",
    "MAX_FRAME_MOVE",
    "PAPER3D_DT_S",
    "PAPER3D_HALF_SIZE_M",
    "PAPER_TRAIN_RADII_M",
    "PRESETS",
    "RadiiGroup",
    "SPLIT_IDS",
    "FrameMoveWarning",
    "UnstableSimulationError",
    "WARN_FRAME_MOVE",
    "generate_dataset",
    "largest_frame_move",
    "paper3d_spec",
    "paper_spec",
    "plan_batches",
    "preset",
    "sample_initial_states",
    "tiny_spec",
    "trajectory_key",
]

SPLIT_IDS = {"train": 0, "valid": 1, "test": 2, "test_unseen": 3}
KEY_DERIVATION = "fold_in(fold_in(jax.random.PRNGKey(seed), split_ids[split]), index)"

# progress(stage, done, total): stage "place" counts trajectories whose
# initial state is drawn, stage "simulate" counts frames per trajectory
# (averaged over the concurrently simulated groups).
ProgressFn = Callable[[str, int, int], None]


@dataclasses.dataclass(frozen=True)
class RadiiGroup:
    """``count`` trajectories whose radii are drawn uniformly from ``radii_m`` (m)."""

    count: int
    radii_m: tuple[float, ...]

    def __post_init__(self):
        object.__setattr__(self, "radii_m", tuple(float(r) for r in self.radii_m))
        if not (isinstance(self.count, int) and self.count >= 0):
            raise ValueError(f"a radii group's count must be an integer >= 0, got {self.count!r}")
        if not self.radii_m or not all(math.isfinite(r) and r > 0 for r in self.radii_m):
            raise ValueError(f"a radii group needs a non-empty list of radii > 0 m, got {list(self.radii_m)}")


@dataclasses.dataclass(frozen=True)
class DatasetSpec:
    """What to generate (everything but the seed and the output directory).

    Attributes:
      splits: per split name (``train``, ``valid``, ``test``,
        ``test_unseen``), a tuple of :class:`RadiiGroup` (``(count, radii)``
        pairs are accepted). Trajectories are indexed across the groups of a
        split in order; splits whose total count is 0 are dropped.
      n_frames: frames per trajectory T (frame 0 is the initial state).
      save_every: Euler steps between frames (15 in the paper: 1.5 ms).
      physics: the ground-truth model.
      dim: spatial dimension D.
      precision: ``"float32"`` (default, fast) or ``"float64"`` (needs
        ``jax_enable_x64``).
      name: the preset name, recorded in the metadata.
      length_scale: ``L`` in m, the length positions and radii are divided
        by (``None``: the box's vertical half-size, the paper's 0.1 m). The
        box is then ``bounds = ((-h_d / L, h_d / L) for each axis)`` in the
        stored units.
    """

    splits: Mapping[str, tuple[RadiiGroup, ...]]
    n_frames: int = 500
    save_every: int = 15
    physics: PhysicsConfig = PhysicsConfig()
    dim: int = 2
    precision: str = "float32"
    name: str | None = None
    length_scale: float | None = None

    def __post_init__(self):
        unknown = sorted(set(self.splits) - set(SPLITS))
        if unknown:
            raise ValueError(f"unknown split(s) {unknown}, expected some of {list(SPLITS)}")
        splits = {}
        for split in SPLITS:
            groups = tuple(
                g if isinstance(g, RadiiGroup) else RadiiGroup(int(g[0]), tuple(g[1]))
                for g in self.splits.get(split, ())
            )
            groups = tuple(g for g in groups if g.count > 0)
            if groups:
                splits[split] = groups
        object.__setattr__(self, "splits", splits)
        if not splits:
            raise ValueError("a dataset spec needs at least one trajectory")
        if not (isinstance(self.n_frames, int) and self.n_frames >= 1):
            raise ValueError(f"n_frames must be an integer >= 1, got {self.n_frames!r}")
        if not (isinstance(self.save_every, int) and self.save_every >= 1):
            raise ValueError(f"save_every must be an integer >= 1, got {self.save_every!r}")
        if self.dim not in (2, 3):
            raise ValueError(f"dim must be 2 or 3, got {self.dim!r}")
        if self.precision not in ("float32", "float64"):
            raise ValueError(f"precision must be 'float32' or 'float64', got {self.precision!r}")
        half = min(self.physics.half_sizes(self.dim))
        for split, groups in splits.items():
            for group in groups:
                if max(group.radii_m) >= half / 2:
                    raise ValueError(
                        f"{split}: radius {max(group.radii_m)} m does not fit the box: expected "
                        f"radii below half the smallest box half-size, {half / 2} m"
                    )
        if self.length_scale is None:
            object.__setattr__(self, "length_scale", self.physics.height)
        elif not (
            isinstance(self.length_scale, int | float) and math.isfinite(self.length_scale) and self.length_scale > 0
        ):
            raise ValueError(f"length_scale must be a length > 0 in m or None, got {self.length_scale!r}")
        object.__setattr__(self, "length_scale", float(self.length_scale))

    @property
    def bounds(self) -> tuple[tuple[float, float], ...]:
        """The box in units of ``length_scale``, one ``(lo, hi)`` per axis."""
        scale = lambda h: float(f"{h / self.length_scale:.12g}")
        return tuple((-scale(h), scale(h)) for h in self.physics.half_sizes(self.dim))

    @property
    def counts(self) -> dict[str, int]:
        """Trajectories per split."""
        return {split: sum(g.count for g in groups) for split, groups in self.splits.items()}

    @property
    def n_trajectories(self) -> int:
        return sum(self.counts.values())

    @property
    def connectivity_radius(self) -> float:
        """4 x the largest training radius / L (every radius if there is no train split)."""
        groups = self.splits.get("train") or [g for gs in self.splits.values() for g in gs]
        largest = max(max(g.radii_m) for g in groups)
        return float(f"{4.0 * largest / self.length_scale:.12g}")

    def items(self) -> list[tuple[str, int, tuple[float, ...]]]:
        """``(split, index, radii_m)`` of every trajectory, in storage order."""
        out = []
        for split, groups in self.splits.items():
            index = 0
            for group in groups:
                for _ in range(group.count):
                    out.append((split, index, group.radii_m))
                    index += 1
        return out

    def replace(
        self,
        *,
        n_frames: int | None = None,
        counts: Mapping[str, int] | None = None,
        radii_m: Sequence[float] | None = None,
        unseen_radii_m: Sequence[Sequence[float]] | None = None,
        precision: str | None = None,
    ) -> DatasetSpec:
        """A modified copy.

        Args:
          n_frames: new frame count.
          counts: new trajectory count per split; a split's count is spread
            evenly over its radii groups (earlier groups get the remainder).
            A split missing from the spec gets the training radii
            (``test_unseen``: an error unless ``unseen_radii_m`` is given).
          radii_m: new radii list (m) for ``train``, ``valid`` and ``test``.
          unseen_radii_m: new radii lists (m) for ``test_unseen``, one group each.
          precision: ``"float32"`` or ``"float64"``.
        """
        splits = {split: list(groups) for split, groups in self.splits.items()}
        if radii_m is not None:
            for split in ("train", "valid", "test"):
                if split in splits:
                    splits[split] = [RadiiGroup(sum(g.count for g in splits[split]), tuple(radii_m))]
        if unseen_radii_m is not None:
            total = sum(g.count for g in splits.get("test_unseen", []))
            splits["test_unseen"] = [RadiiGroup(0, tuple(r)) for r in unseen_radii_m]
            splits["test_unseen"] = _spread(splits["test_unseen"], total)
        for split, count in (counts or {}).items():
            if split not in SPLITS:
                raise ValueError(f"unknown split {split!r}, expected one of {list(SPLITS)}")
            groups = splits.get(split)
            if not groups:
                if split == "test_unseen":
                    raise ValueError("test_unseen has no radii in this spec: give unseen radii as well")
                source = splits.get("train") or next(iter(splits.values()))
                groups = [RadiiGroup(0, source[0].radii_m)]
            splits[split] = _spread(groups, count)
        return dataclasses.replace(
            self,
            splits={s: tuple(g) for s, g in splits.items()},
            n_frames=self.n_frames if n_frames is None else n_frames,
            precision=self.precision if precision is None else precision,
        )


def _spread(groups: list[RadiiGroup], total: int) -> list[RadiiGroup]:
    if not groups:
        return groups
    base, extra = divmod(int(total), len(groups))
    return [RadiiGroup(base + (i < extra), g.radii_m) for i, g in enumerate(groups)]


def _mm(*values: float) -> tuple[float, ...]:
    return tuple(round(v * 1e-3, 12) for v in values)


PAPER_TRAIN_RADII_M = _mm(2.0, 2.5, 3.0, 3.5, 4.0, 4.5, 5.0)


def paper_spec() -> DatasetSpec:
    """The paper's protocol: 16 train, 6 valid, 6 test, 12 unseen-radii test; 500 frames, 1.5 ms apart."""
    return DatasetSpec(
        splits={
            "train": (RadiiGroup(16, PAPER_TRAIN_RADII_M),),
            "valid": (RadiiGroup(6, PAPER_TRAIN_RADII_M),),
            "test": (RadiiGroup(6, PAPER_TRAIN_RADII_M),),
            "test_unseen": (RadiiGroup(6, _mm(2.75, 4.25)), RadiiGroup(6, _mm(2.25, 3.25, 3.75, 4.75))),
        },
        n_frames=500,
        save_every=15,
        name="paper",
    )


def tiny_spec() -> DatasetSpec:
    """Five trajectories of 35-55 large disks and 60 frames, for tests and demos.

    Train radii {4, 6, 8, 10} mm, unseen {4.5, 5.5, 7, 9} mm. The spread matters: the
    protocol sizes N by the largest radius, and narrow lists of large radii
    (e.g. {7, 8, 9, 10} mm) are often too dense to place without overlap.
    """
    radii = _mm(4.0, 6.0, 8.0, 10.0)
    return DatasetSpec(
        splits={
            "train": (RadiiGroup(2, radii),),
            "valid": (RadiiGroup(1, radii),),
            "test": (RadiiGroup(1, radii),),
            "test_unseen": (RadiiGroup(1, _mm(4.5, 5.5, 7.0, 9.0)),),
        },
        n_frames=60,
        save_every=15,
        name="tiny",
    )


def wide_spec(factor: int) -> DatasetSpec:
    """The paper's protocol in a container ``factor`` times wider than the paper's box, same height.

    Box half-sizes ``(0.1 factor, 0.1)`` m, positions in units of the paper's
    ``L = 0.1`` m (``bounds = ((-factor, factor), (-1, 1))``), the paper's
    radii lists and 500 frames; a handful of trajectories per split (4 train,
    2 valid, 4 test, 2 + 2 unseen-radii test), 150-225 x ``factor`` disks each.
    The physics uses a 20 mm cut-off (4 largest radii: the LJ force there is
    under 1 % of its value at contact) with cell lists, so its cost grows
    linearly with the width.
    """
    return DatasetSpec(
        splits={
            "train": (RadiiGroup(4, PAPER_TRAIN_RADII_M),),
            "valid": (RadiiGroup(2, PAPER_TRAIN_RADII_M),),
            "test": (RadiiGroup(4, PAPER_TRAIN_RADII_M),),
            "test_unseen": (RadiiGroup(2, _mm(2.75, 4.25)), RadiiGroup(2, _mm(2.25, 3.25, 3.75, 4.75))),
        },
        n_frames=500,
        save_every=15,
        physics=PhysicsConfig(box_half_size=(0.1 * factor, 0.1), cutoff=0.02),
        name=f"wide{factor}",
        length_scale=0.1,
    )


def wide4_spec() -> DatasetSpec:
    """:func:`wide_spec` 4: a box 0.8 m wide, 0.2 m tall, ~600-900 disks per trajectory."""
    return wide_spec(4)


def wide16_spec() -> DatasetSpec:
    """:func:`wide_spec` 16: a box 3.2 m wide, 0.2 m tall, ~2,400-3,600 disks per trajectory."""
    return wide_spec(16)


# Half-size L of the paper3d cube. The 2-D protocol in a cube of the paper's L = 0.1 m would
# place ~0.7 (2L)^2 (L - z0) / (2 a_max)^3 = 2,800-3,500 spheres, 15x the 2-D graphs: far beyond
# a 2-core CPU training budget. In an 8 cm cube the paper's radii and packing rule give 180-230
# spheres for the training list (the 3-D reference run has 182), graphs of the 2-D paper's
# size in nodes. Smaller cubes fail the rule itself: with the unseen list {2.75, 4.25} mm the
# walls take so much of a 6 cm cube that its ~150 spheres cannot be placed without overlap.
PAPER3D_HALF_SIZE_M = 0.04
# Euler step of the paper3d physics: a quarter of the paper's 1e-4 s (60 steps per 1.5 ms frame).
# At 1e-4 s explicit Euler is unstable once the spheres form a bed in this cube: a sphere weighs up
# to 3x a paper disk and the bed is deeper, so contacts are squeezed into the stiff part of the
# pair force, and 12 of 32 training trajectories (seed 0) blew up near frame 100 (accelerations
# up to 70 radii per frame^2, spheres crossing the cube in one frame). At 2.5e-5 s the same
# starts settle calmly and agree with 1.25e-5 and 6.25e-6 s (largest acceleration 1.5 radii per
# frame^2, largest speed within 6 %); tests/test_generate.py holds it.
PAPER3D_DT_S = 2.5e-5


def paper3d_spec() -> DatasetSpec:
    """Spheres in a cube: the paper's radii lists and protocol in 3-D, sized for CPU training.

    The box is ``[-0.04, 0.04]^3`` m (:data:`PAPER3D_HALF_SIZE_M`), so the packing formula
    gives 180-230 spheres per trajectory with the training radii (up to ~360 with the unseen
    list {2.75, 4.25} mm); 200 frames of 1.5 ms (0.3 s: spheres settle ~3x faster than the
    paper's disks and the bed forms within it), each 60 Euler steps of :data:`PAPER3D_DT_S`
    (the paper's 1e-4 s is unstable in a bed of spheres). 32 train, 4 valid, 6 test and 12
    unseen-radii test trajectories (the paper's unseen lists).
    """
    return DatasetSpec(
        splits={
            "train": (RadiiGroup(32, PAPER_TRAIN_RADII_M),),
            "valid": (RadiiGroup(4, PAPER_TRAIN_RADII_M),),
            "test": (RadiiGroup(6, PAPER_TRAIN_RADII_M),),
            "test_unseen": (RadiiGroup(6, _mm(2.75, 4.25)), RadiiGroup(6, _mm(2.25, 3.25, 3.75, 4.75))),
        },
        n_frames=200,
        save_every=60,
        physics=PhysicsConfig(box_half_size=PAPER3D_HALF_SIZE_M, dt=PAPER3D_DT_S),
        dim=3,
        name="paper3d",
    )


PRESETS: dict[str, Callable[[], DatasetSpec]] = {
    "paper": paper_spec,
    "paper3d": paper3d_spec,
    "tiny": tiny_spec,
    "wide4": wide4_spec,
    "wide16": wide16_spec,
}


def preset(name: str) -> DatasetSpec:
    """The named preset spec (``"paper"``, ``"paper3d"``, ``"tiny"``, ``"wide4"`` or ``"wide16"``)."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}, expected one of {sorted(PRESETS)}")
    return PRESETS[name]()


# ----------------------------------------------------------------------------- initial states


def trajectory_key(seed: int, split: str, index: int) -> PRNGKey:
    """The PRNG key of trajectory ``index`` of ``split`` (independent of every other trajectory)."""
    return jax.random.fold_in(jax.random.fold_in(jax.random.PRNGKey(seed), SPLIT_IDS[split]), index)


class _Draw(NamedTuple):
    keys: tuple
    start_height: float
    n_particles: int


def sample_initial_states(
    keys: Sequence[PRNGKey],
    radii_lists: Sequence[Sequence[float]],
    config: PhysicsConfig = PhysicsConfig(),
    *,
    dim: int = 2,
    dtype: DTypeLike = jnp.float32,
    progress: Callable[[int], None] | None = None,
    labels: Sequence[str] | None = None,
) -> list[InitialState]:
    """Many :func:`~dispgns.physics.sample_initial_state` draws, with one compilation.

    ``sample_initial_state`` jit-compiles its placement loop for every
    distinct particle count (about 0.7 s each: 30 s for the 40 paper
    trajectories). Placement is sequential in index order, so placing extra
    trailing particles never moves the first ``N``; here every trajectory is
    placed with the same padded count and cut back to its own ``N``. The
    result equals ``sample_initial_state(keys[i], radii_lists[i], config,
    dim=dim, dtype=dtype)`` exactly (tested). That equality relies on
    prefix-stable random draws (``jax_threefry_partitionable``, the JAX
    default); without it this falls back to one ``sample_initial_state``
    call per trajectory.

    Args:
      keys: one PRNG key per trajectory.
      radii_lists: per trajectory, the radii (m) to draw from.
      config, dim, dtype: as for ``sample_initial_state``.
      progress: called with the number of states placed so far.
      labels: per trajectory, a name used in error messages.

    Returns:
      One :class:`~dispgns.physics.InitialState` per key, holding numpy
      arrays: position ``(N, D)`` m, velocity ``(N, D)`` m/s, radius ``(N,)`` m.

    Raises:
      PlacementError: some trajectory's packing is too dense.
    """
    labels = labels or [f"trajectory {i}" for i in range(len(keys))]
    if not jax.config.jax_threefry_partitionable:
        states = []
        for i, (key, radii) in enumerate(zip(keys, radii_lists)):
            try:
                states.append(sample_initial_state(key, radii, config, dim=dim, dtype=dtype))
            except PlacementError as error:
                raise PlacementError(f"{labels[i]}: {error}") from None
            if progress is not None:
                progress(i + 1)
        return states

    half = config.height  # the vertical half-size: the start height's range
    draws = []
    for key, radii, label in zip(keys, radii_lists, labels):
        # Steps 1-2 of sample_initial_state, with the same key split and dtypes.
        subkeys = jax.random.split(key, 5)
        start_height = float(jax.random.uniform(subkeys[0], (), minval=-0.25 * half, maxval=0.0))
        low, high = particle_count_range(start_height, max(radii), config, dim, radii_choices=radii)
        n_particles = int(jax.random.randint(subkeys[1], (), low, high + 1))
        if start_height + 2 * max(radii) > half:
            raise PlacementError(f"{label}: start height {start_height} m leaves no room for radius {max(radii)} m")
        draws.append(_Draw(subkeys, start_height, n_particles))
    n_pad = max(d.n_particles for d in draws)
    states = []
    for i, (draw, radii, label) in enumerate(zip(draws, radii_lists, labels)):
        n = draw.n_particles
        choices = np.asarray(radii, dtype=float)
        # numpy for every count-dependent shape: eager jnp ops compile once per shape.
        choice = np.asarray(jax.random.randint(draw.keys[2], (n_pad,), 0, choices.size))[:n]
        radius = choices.astype(dtype)[choice]
        # Tiny trailing particles: placed after the real ones, they never move them.
        padded = np.full((n_pad,), 1e-3 * choices.min(), dtype)
        padded[:n] = radius
        position, placed = place_particles(draw.keys[3], jnp.asarray(padded), draw.start_height, config, dim=dim)
        placed = np.asarray(placed)[:n]
        if not placed.all():
            first = int(np.argmin(placed))
            raise PlacementError(
                f"{label}: could not place particle {first} of {n} (radius {radius[first]:.4g} m) without "
                f"overlap; the packing is too dense for the radii {list(radii)} m above y0 = "
                f"{draw.start_height:.4g} m (large radii leave little room near the walls). Use smaller radii."
            )
        # Step 5, as in sample_initial_state.
        vs = config.settling_speed(float(choices.min()), dim)
        velocity = jax.random.uniform(draw.keys[4], (dim,), dtype, -vs, vs)
        velocity = np.asarray(velocity.at[-1].multiply(0.25))
        velocity = np.broadcast_to(velocity, (n, dim)).copy()
        states.append(InitialState(np.asarray(position)[:n], velocity, radius, draw.start_height))
        if progress is not None:
            progress(i + 1)
    return states


# ----------------------------------------------------------------------------- batching

# Rough CPU costs, used only to decide how to group trajectories: the
# all-pairs step costs about 1.7e-9 s per particle pair, a simulate_batch
# compilation about 2.5 s. The grouping depends on nothing else (not on the
# machine), so a seed always gives the same dataset.
_SECONDS_PER_PAIR_STEP = 1.7e-9
_SECONDS_PER_COMPILE = 2.5
# Charged once per group beyond its own lane's time, so that concurrency is
# only used when it saves real time (compilations compete for the cores).
_SECONDS_PER_GROUP = 0.5
# The plan assumes two groups run at the same time. It is a fixed constant,
# not the machine's thread count (dispgns.tuning.Thresholds.generation_threads),
# so that the grouping, and with it the data, never depends on the machine.
LANES = 2


def _group_costs(counts: Sequence[int], cuts: Sequence[int], n_steps: int) -> list[float]:
    return [
        _SECONDS_PER_COMPILE + _SECONDS_PER_PAIR_STEP * n_steps * (end - start) * counts[end - 1] ** 2
        for start, end in zip(cuts[:-1], cuts[1:])
    ]


def _makespan(costs: Sequence[float], lanes: int) -> float:
    """Wall time of running ``costs`` on ``lanes`` workers, longest first (LPT)."""
    loads = [0.0] * lanes
    for cost in sorted(costs, reverse=True):
        loads[loads.index(min(loads))] += cost
    return max(loads)


def _balance(
    counts: Sequence[int], cuts: list[int], n_steps: int, size: int, lanes: int, max_groups: int = 4
) -> list[int]:
    """Cuts (starting from ``cuts``) with the shortest estimated wall time on ``lanes`` workers.

    Up to ``max_groups`` groups are searched exhaustively when that is cheap
    (the usual few dozen trajectories); otherwise groups are split greedily.
    """
    total = len(counts)

    def score(candidate):
        if any(end - start > size for start, end in zip(candidate[:-1], candidate[1:])):
            return math.inf, 0
        groups = len(candidate) - 1
        return _makespan(_group_costs(counts, candidate, n_steps), lanes) + _SECONDS_PER_GROUP * groups, groups

    best, best_score = cuts, score(cuts)
    if math.comb(max(total - 1, 0), max_groups - 1) <= 50_000:
        for inner_count in range(max_groups):
            for inner in itertools.combinations(range(1, total), inner_count):
                candidate = [0, *inner, total]
                candidate_score = score(candidate)
                if candidate_score < best_score:
                    best, best_score = candidate, candidate_score
        return best
    while True:
        splits = [sorted(best + [c]) for c in range(1, total) if c not in best]
        scored = [(score(c), c) for c in splits]
        if not scored:
            return best
        candidate_score, candidate = min(scored, key=lambda item: item[0])
        if candidate_score[0] >= best_score[0] - 1e-9:
            return best
        best, best_score = candidate, candidate_score


def plan_batches(
    particle_counts: Sequence[int], n_steps: int, *, batch_size: int | None = None, lanes: int = LANES
) -> list[list[int]]:
    """Group trajectories for concurrent :func:`~dispgns.physics.simulate_batch` calls.

    Trajectories are sorted by particle count and cut into contiguous
    groups, each padded to its largest count. The all-pairs force costs
    ``B N^2`` per step, so a few trajectories with many particles make one
    big batch wasteful, while every group costs a compilation. The cuts
    first minimise the estimated total cost (dynamic programming over the
    sorted counts); then the cuts that give the shortest estimated wall time
    of running the groups on ``lanes`` threads are searched for.

    Args:
      particle_counts: N of every trajectory.
      n_steps: Euler steps per trajectory.
      batch_size: maximum trajectories per group (``None``: no limit).
      lanes: groups run at the same time.

    Returns:
      Groups of trajectory indices (each in increasing particle count),
      the most expensive first.
    """
    order = sorted(range(len(particle_counts)), key=lambda i: (particle_counts[i], i))
    counts = [particle_counts[i] for i in order]
    total = len(counts)
    size = total if batch_size is None else batch_size
    # best[j]: cheapest total cost of the first j sorted trajectories; cut[j]: start of the last group.
    best = [0.0] + [math.inf] * total
    cut = [0] * (total + 1)
    for end in range(1, total + 1):
        for start in range(max(0, end - size), end):
            cost = best[start] + _group_costs(counts, [start, end], n_steps)[0]
            if cost < best[end]:
                best[end], cut[end] = cost, start
    cuts, end = [total], total
    while end > 0:
        end = cut[end]
        cuts.insert(0, end)
    cuts = _balance(counts, cuts, n_steps, size, lanes)
    costs = _group_costs(counts, cuts, n_steps)
    groups = [order[start:end] for start, end in zip(cuts[:-1], cuts[1:])]
    return [group for _, group in sorted(zip(costs, groups), key=lambda item: -item[0])]


# ----------------------------------------------------------------------------- stability

# Explicit Euler at the paper's step is only just stable once a 2-D bed has settled: a run can
# start to oscillate (accelerations alternating in sign from frame to frame) and within some
# tens of frames throw particles across the box. Healthy paper-preset trajectories move a particle
# at most ~0.5-0.9 of the smallest radius between stored frames; the onset reaches ~1-1.2.

#: Default bound on any particle's move between two stored frames, in units of the trajectory's
#: smallest radius. Past it the particle can pass through a neighbour within a frame: the run has
#: left what the physics resolves, and generation refuses it.
MAX_FRAME_MOVE = 2.0

#: A trajectory whose largest frame-to-frame move exceeds this (in smallest radii), but not
#: the bound, is kept with a warning: the Euler step is at its stability limit there.
WARN_FRAME_MOVE = 1.0


class UnstableSimulationError(RuntimeError):
    """A simulated trajectory blew up: positions not finite, or a move past the bound."""


class FrameMoveWarning(UserWarning):
    """A kept trajectory moves a particle more than :data:`WARN_FRAME_MOVE` smallest radii in a frame."""


def largest_frame_move(position: Positions, radius: Radii) -> tuple[float, int, int]:
    """The largest distance any particle moves between two consecutive stored frames.

    Args:
      position: ``(T, N, D)`` centres, any length unit (host array).
      radius: ``(N,)`` radii in the same unit.

    Returns:
      ``(move, frame, particle)``: the largest Euclidean move in units of the
      smallest radius, the frame it ends at (the move is from ``frame - 1``
      to ``frame``) and the particle; ``(inf, frame, particle)`` at the first
      position that is not finite; ``(0.0, 0, 0)`` for fewer than two frames
      or no particles.
    """
    position = np.asarray(position, np.float64)
    if position.ndim != 3:
        raise ValueError(f"position must be (T, N, D), got shape {position.shape}")
    finite = np.isfinite(position).all(axis=-1)
    if not finite.all():
        frame, particle = np.argwhere(~finite)[0]
        return math.inf, int(frame), int(particle)
    if position.shape[0] < 2 or position.shape[1] == 0:
        return 0.0, 0, 0
    smallest = float(np.min(radius))
    moves = np.linalg.norm(np.diff(position, axis=0), axis=-1)
    step, particle = np.unravel_index(int(np.argmax(moves)), moves.shape)
    return float(moves[step, particle] / smallest), int(step) + 1, int(particle)


def _check_stability(label: str, position, radius, config: PhysicsConfig, max_frame_move: float) -> float:
    """Raise :class:`UnstableSimulationError` past ``max_frame_move``, warn past :data:`WARN_FRAME_MOVE`;
    return the largest move (smallest radii)."""
    move, frame, particle = largest_frame_move(position, radius)
    advice = (
        f"explicit Euler with dt = {config.dt:g} s is unstable here. Generate with a smaller step "
        "(DatasetSpec.physics.dt, save_every raised to keep the frame interval), or another seed; "
        "max_frame_move (--max-frame-move) keeps such trajectories"
    )
    if not math.isfinite(move):
        raise UnstableSimulationError(
            f"{label}: particle {particle}'s position is not finite at frame {frame}: {advice}"
        )
    where = f"{label}: particle {particle} moves {move:.3g} smallest radii between frames {frame - 1} and {frame}"
    if move > max_frame_move:
        raise UnstableSimulationError(
            f"{where}, more than max_frame_move = {max_frame_move:g} (healthy runs stay under ~0.9): {advice}"
        )
    if move > WARN_FRAME_MOVE:
        warnings.warn(
            f"{where} (healthy runs stay under ~0.9): the Euler step is at its stability limit there; "
            f"the trajectory is kept (the bound is max_frame_move = {max_frame_move:g})",
            FrameMoveWarning,
            stacklevel=3,  # the caller of generate_dataset
        )
    return move


class _Cancelled(Exception):
    """Raised inside a worker's progress callback to stop its simulation early."""


def _simulate_groups(
    groups: list[list[int]],
    states: Sequence[InitialState],
    spec: DatasetSpec,
    dtype,
    report: ProgressFn,
    lanes: int,
    compiler_options: Mapping[str, Any] | None = None,
) -> list[np.ndarray]:
    """Simulate every group (concurrently, up to ``lanes`` at a time); positions per trajectory in m."""
    counts = [int(s.position.shape[0]) for s in states]
    positions: list[np.ndarray | None] = [None] * len(states)
    frames_done = [0] * len(groups)
    lock = threading.Lock()
    cancelled = threading.Event()
    # JAX configuration is thread-local: workers must see the caller's x64 setting.
    x64 = bool(jax.config.jax_enable_x64)
    report("simulate", 0, spec.n_frames)

    def run(index: int) -> None:
        with jax.enable_x64(x64):
            simulate_group(index)

    def simulate_group(index: int) -> None:
        members = groups[index]
        n_pad = max(counts[i] for i in members)
        x0 = np.zeros((len(members), n_pad, spec.dim), dtype)
        v0 = np.zeros_like(x0)
        radius = np.ones((len(members), n_pad), dtype)
        mask = np.zeros((len(members), n_pad), bool)
        for row, i in enumerate(members):
            n = counts[i]
            x0[row, :n] = states[i].position
            v0[row, :n] = states[i].velocity
            radius[row, :n] = states[i].radius
            mask[row, :n] = True

        def on_frames(done: int) -> None:
            if cancelled.is_set():
                raise _Cancelled
            with lock:
                frames_done[index] = done + 1
                # Frames per trajectory, averaged over the groups.
                report("simulate", sum(frames_done) // len(groups), spec.n_frames)

        xs = np.asarray(
            simulate_batch(
                x0,
                v0,
                radius,
                mask,
                spec.physics,
                n_frames=spec.n_frames,
                save_every=spec.save_every,
                progress=on_frames,
                compiler_options=compiler_options,
            )
        )
        for row, i in enumerate(members):
            positions[i] = xs[row, :, : counts[i]]

    if len(groups) == 1 or lanes == 1:
        for index in range(len(groups)):
            run(index)
        return positions
    pool = concurrent.futures.ThreadPoolExecutor(
        max_workers=min(lanes, len(groups)), thread_name_prefix="dispgns-simulate"
    )
    # Each worker runs in a copy of the caller's context: a use_thresholds block around the call reaches them.
    futures = [pool.submit(contextvars.copy_context().run, run, index) for index in range(len(groups))]
    try:
        for future in concurrent.futures.as_completed(futures):
            future.result()
    except BaseException:
        # Stop the other workers at their next chunk instead of finishing their run.
        cancelled.set()
        for future in futures:
            future.cancel()
        raise
    finally:
        pool.shutdown(wait=True)
    return positions


# ----------------------------------------------------------------------------- generation


def generate_dataset(
    spec: DatasetSpec,
    out_dir: str | os.PathLike,
    seed: int,
    *,
    overwrite: bool = False,
    batch_size: int | None = None,
    progress: ProgressFn | None = None,
    compiler_options: Mapping[str, Any] | None = None,
    max_frame_move: float = MAX_FRAME_MOVE,
) -> DatasetMetadata:
    """Generate the dataset ``spec`` describes into ``out_dir``; deterministic for a seed.

    Initial states are drawn for every trajectory (one compilation), then the
    trajectories are simulated in groups of similar particle count chosen by
    :func:`plan_batches`, up to ``dispgns.tuning.thresholds().generation_threads``
    groups at once in threads, and
    the dataset is written to a staging directory that is renamed into place.
    The same seed, spec and ``batch_size`` give the same files (on the same
    machine and software: the float32 dynamics is chaotic, so a different
    grouping, CPU or XLA version diverges visibly over 500 frames).

    Args:
      spec: what to generate.
      out_dir: the dataset directory to create. It must not exist or be
        empty, unless ``overwrite`` (then it must hold a dispgns dataset,
        which is replaced only once the new one is complete).
      seed: integer in ``[0, 2^32)``.
      overwrite: replace an existing dataset.
      batch_size: at most this many trajectories per ``simulate_batch``
        call (``None``: no limit, the fastest; smaller only to save memory).
        The grouping is chosen by :func:`plan_batches`; the value is recorded
        in the metadata.
      progress: optional ``progress(stage, done, total)`` callback.
      compiler_options: XLA options for the physics (e.g.
        :func:`dispgns.tuning.physics_compiler_options`; float32 data then
        differ from data generated without them in the last bits).
      max_frame_move: refuse the dataset when a particle of some trajectory
        moves more than this many of the trajectory's smallest radius between
        two stored frames (a blown-up Euler step; see :data:`MAX_FRAME_MOVE`).
        Past :data:`WARN_FRAME_MOVE` a :class:`FrameMoveWarning` names the
        trajectory. Every trajectory's largest move is stored in its
        ``attrs["largest_frame_move"]``. With ``math.inf`` only positions
        that are not finite refuse the dataset (the warning still applies).

    Returns:
      The metadata written beside the split files.

    Raises:
      FileExistsError: ``out_dir`` holds something and ``overwrite`` is off.
      PlacementError: a requested packing cannot be placed without overlap.
      UnstableSimulationError: a trajectory blew up (see ``max_frame_move``);
        nothing is written.
      ValueError: bad seed, ``max_frame_move`` not > 0, or float64 without
        ``jax_enable_x64``.
      OSError: ``out_dir`` cannot be written.
    """
    if not (isinstance(seed, (int, np.integer)) and 0 <= int(seed) < 2**32):
        raise ValueError(f"seed must be an integer in [0, 2^32), got {seed!r}")
    seed = int(seed)
    if spec.precision == "float64" and not jax.config.jax_enable_x64:
        raise ValueError(
            "precision 'float64' needs jax_enable_x64: enable it before creating any array "
            "(jax.config.update('jax_enable_x64', True), or `with jax.enable_x64(True):`)"
        )
    dtype = np.float64 if spec.precision == "float64" else np.float32
    if batch_size is not None and batch_size < 1:
        raise ValueError(f"batch_size must be >= 1 or None, got {batch_size!r}")
    if isinstance(max_frame_move, bool) or not (isinstance(max_frame_move, numbers.Real) and max_frame_move > 0):
        raise ValueError(f"max_frame_move must be a number > 0 (smallest radii per frame), got {max_frame_move!r}")
    config = spec.physics
    half = spec.length_scale  # positions and radii are stored in units of it
    items = spec.items()
    total = len(items)
    report = progress or (lambda stage, done, total: None)

    # Entered first so that an unwritable or occupied target fails before the long run.
    with staged_directory(out_dir, overwrite=overwrite) as staging:
        labels = [f"{split} trajectory {index:05d}" for split, index, _ in items]
        keys = [trajectory_key(seed, split, index) for split, index, _ in items]
        states = sample_initial_states(
            keys,
            [radii for _, _, radii in items],
            config,
            dim=spec.dim,
            dtype=dtype,
            labels=labels,
            progress=lambda done: report("place", done, total),
        )
        counts = [int(s.position.shape[0]) for s in states]
        groups = plan_batches(counts, spec.n_frames * spec.save_every, batch_size=batch_size)
        threads = thresholds().generation_threads
        positions = _simulate_groups(groups, states, spec, dtype, report, threads, compiler_options)
        # Checked before anything is written: a blown-up run refuses the whole dataset.
        moves = []
        for i in range(total):  # a loop, not a comprehension: the warnings' stacklevel counts frames
            moves.append(
                _check_stability(labels[i], positions[i], np.asarray(states[i].radius), config, max_frame_move)
            )

        trajectories: dict[str, list[Trajectory]] = {split: [] for split in spec.splits}
        for i, (split, index, radii) in enumerate(items):
            state = states[i]
            # The exact SI state the physics started from (float32 -> float64 is exact).
            x0 = np.asarray(state.position).astype(np.float64)
            v0 = np.asarray(state.velocity).astype(np.float64)
            # Radii as listed (0.004, not float32(0.004)): they round to what ran in either precision.
            listed = np.asarray(radii, np.float64)
            ran = np.asarray(state.radius).astype(np.float64)
            a0 = listed[np.argmin(np.abs(ran[:, None] - listed[None, :]), axis=1)]
            trajectories[split].append(
                Trajectory(
                    position=(positions[i].astype(np.float64) / half).astype(np.float32),
                    radius=(a0 / half).astype(np.float32),
                    initial_position=x0,
                    initial_velocity=v0,
                    initial_radius=a0,
                    particle_type=np.zeros((counts[i],), np.int32),
                    attrs={
                        "seed": seed,
                        "split": split,
                        "index": index,
                        "radii_m": list(radii),
                        "start_height_m": float(state.start_height),
                        "n_particles": counts[i],
                        "largest_frame_move": round(moves[i], 6),
                    },
                )
            )
        for split, group in trajectories.items():
            write_split(staging / split_filename(split), group, box_half_size=half, bounds=spec.bounds)
        metadata = DatasetMetadata(
            dim=spec.dim,
            sequence_length=spec.n_frames,
            frame_dt=spec.save_every * config.dt,
            save_every=spec.save_every,
            box_half_size=config.box_half_size,
            length_scale=half,
            bounds=spec.bounds,
            connectivity_radius=spec.connectivity_radius,
            trajectory_counts=spec.counts,
            radii={split: radii_groups((g.count, g.radii_m) for g in groups) for split, groups in spec.splits.items()},
            physics=config.to_dict(),
            has_initial_state=True,
            seed=seed,
            batch_size=batch_size,
            key_derivation=KEY_DERIVATION,
            split_ids={split: SPLIT_IDS[split] for split in spec.splits},
            precision=spec.precision,
            source="generated",
            preset=spec.name,
            particle_counts={split: [t.n_particles for t in group] for split, group in trajectories.items()},
            **training_statistics(trajectories),
        )
        write_metadata(staging, metadata)
    return metadata

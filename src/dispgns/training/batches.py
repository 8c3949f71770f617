"""Training examples: windows of trajectories, shuffled deterministically, padded to a few budgets.

An example is a window of ``C + k + u`` consecutive frames of one trajectory
(``C`` input frames, ``k`` frames the model predicts when training with ``k``
pushforward steps, then the targets of the ``u`` steps the loss is taken on,
one without unrolling). A batch stacks ``B`` examples, padded to a
node budget (particle slots), with a static graph capacity per example and a
static edge budget for the batch's merged graph, both sized by the graph
capacity policy (:mod:`dispgns.graph`, on the ladder of
:mod:`dispgns.capacity`): the jitted training step compiles once per distinct
``(node budget, capacity, edge budget)``, and those repeat.

Mirror augmentation (optional): the physics is symmetric under ``x_d -> -x_d``
for every axis but the last (gravity), so each example of batch ``i`` may be
reflected on those axes, drawn from ``default_rng([seed, 1, i])``.

Order and resume: batch ``i`` is a pure function of ``(seed, i)``: epoch ``e
= i // batches_per_epoch`` uses the permutation ``default_rng([seed,
e]).permutation(num_examples)`` and batch ``i`` takes the next ``B`` examples
of it (the ``num_examples % B`` left over in an epoch are skipped in that
epoch only). A run resumes exactly from the number of batches it has
consumed, which is the training step when every step consumes one batch.

Units: positions and radii in normalised box units, as stored.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np
from flax import struct
from jaxtyping import ArrayLike, Bool, Float, Int

import dispgns
from dispgns.arrays import BatchMask, BatchRadii, node_budget
from dispgns.data import Trajectory
from dispgns.graph import (
    Bounds,
    GraphCapacity,
    as_bounds,
    capacity_for_counts,
    edge_budget_for,
    grow_capacity,
    grow_edge_budget,
    host_count_pairs,
    host_max_cell_occupancy,
    uses_cell_list,
)
from dispgns.model import ModelConfig

# Shapes (jaxtyping, no runtime check): B examples of W = C + k + u frames each, example ids.
_BatchFrames = Float[ArrayLike, "B W N D"]
_ExampleIds = Int[ArrayLike, "B 2"]
_Ids = Int[ArrayLike, "K"]
_Horizontal = Float[ArrayLike, "*shape 2"]
_Flips = Bool[ArrayLike, "B D-1"]
_Turns = Int[ArrayLike, "B"]
# One entry per window (M windows of all trajectories), host int arrays.
_WindowIds = Int[np.ndarray, "M"]

__all__ = ["Batch", "BatchStream", "ExampleIndex", "example_index", "quarter_turns"]


@struct.dataclass
class Batch:
    """``B`` padded examples (a pytree; ``capacity`` is static).

    Attributes:
      position: ``(B, W, N, D)`` float32 frames; ``W = C + k + u`` (inputs,
        the ``k`` pushforward frames, the ``u`` targets of the loss). Padding
        rows are zero.
      radius: ``(B, N)`` float32; padding entries are 1.
      mask: ``(B, N)`` bool, ``False`` for padding particles.
      example: ``(B, 2)`` int32 ``(trajectory, first frame)`` of each example
        (bookkeeping only).
      capacity: static :class:`~dispgns.graph.GraphCapacity` of each
        example's graph (ordered pairs ``s != r``), with head-room for the
        noise.
      edge_budget: static edge slots of the merged graph of the whole batch
        (real edges, self-loops of every particle slot included), or
        ``None``: ``B`` times the slots of one example's graph.
    """

    position: _BatchFrames
    radius: BatchRadii
    mask: BatchMask
    example: _ExampleIds
    capacity: GraphCapacity = struct.field(pytree_node=False)
    edge_budget: int | None = struct.field(pytree_node=False, default=None)

    @property
    def batch_size(self) -> int:
        return int(self.position.shape[0])

    @property
    def node_budget(self) -> int:
        return int(self.position.shape[2])

    def with_capacity(self, capacity: GraphCapacity, edge_budget: int | None | str = "same") -> Batch:
        """The same examples with another graph capacity (and edge budget), e.g. after an overflow."""
        return self.replace(capacity=capacity, edge_budget=self.edge_budget if edge_budget == "same" else edge_budget)


class ExampleIndex(NamedTuple):
    """The windows of a set of trajectories (some listed more than once, see :func:`example_index`).

    ``trajectory (M,)`` and ``start (M,)`` int arrays.
    """

    trajectory: _WindowIds
    start: _WindowIds

    def __len__(self) -> int:
        return int(self.trajectory.shape[0])


def example_index(
    frame_counts: Sequence[int], window: int, early_windows: int = 0, early_repeats: int = 1
) -> ExampleIndex:
    """Every window of ``window`` consecutive frames, trajectory by trajectory, in order.

    A trajectory of ``T`` frames gives ``max(0, T - window + 1)`` examples. The windows starting
    at frames ``0 .. early_windows - 1`` are listed ``early_repeats`` times (the extra copies
    after the trajectory's windows), so an epoch draws them that many times (less any of the few
    examples an epoch leaves over, see :class:`BatchStream`).
    """
    if window < 2:
        raise ValueError(f"window must be >= 2 frames, got {window}")
    if int(early_windows) != early_windows or early_windows < 0:
        raise ValueError(f"early_windows must be an integer >= 0, got {early_windows!r}")
    if int(early_repeats) != early_repeats or early_repeats < 1:
        raise ValueError(f"early_repeats must be an integer >= 1, got {early_repeats!r}")
    traj, start = [], []
    for k, t in enumerate(frame_counts):
        m = max(0, int(t) - window + 1)
        starts = np.arange(m, dtype=np.int64)
        starts = np.concatenate([starts] + [starts[: int(early_windows)]] * (int(early_repeats) - 1))
        traj.append(np.full(starts.shape, k, np.int64))
        start.append(starts)
    return ExampleIndex(
        np.concatenate(traj) if traj else np.zeros((0,), np.int64),
        np.concatenate(start) if start else np.zeros((0,), np.int64),
    )


def quarter_turns(xy: _Horizontal, turns: int) -> _Horizontal:
    """``xy`` ``(..., 2)`` (the horizontal components) turned by ``turns`` quarter turns counter-clockwise.

    One turn maps ``(x, y)`` to ``(-y, x)``: a rotation by 90 degrees about the vertical axis,
    exact in floating point (only swaps and sign changes). Works on NumPy and JAX arrays.
    """
    x, y = xy[..., 0], xy[..., 1]
    for _ in range(int(turns) % 4):
        x, y = -y, x
    stack = np.stack if isinstance(xy, np.ndarray) else jnp.stack
    return stack([x, y], axis=-1)


class BatchStream:
    """Deterministic, resumable stream of padded training batches.

    Args:
      trajectories: sequence of objects with ``.position`` ``(T, N, D)`` and
        ``.radius`` ``(N,)`` (normalised units), e.g. the dataset reader's.
        They are copied to float32 arrays once.
      input_sequence_length: ``C``.
      batch_size: ``B``.
      connectivity_radius: graph radius (normalised units).
      seed: data-order seed.
      pushforward_steps: ``k``; windows hold ``C + k + u`` frames.
      unroll_steps: ``u`` (1), the consecutive steps the loss is taken on.
      shuffle: ``False`` keeps examples in order (e.g. for validation).
      node_budgets: allowed particle-slot counts; ``None``: one budget, the
        largest ``N`` rounded up to a multiple of 8.
      compact_edges: give every example one graph capacity (fitting the
        largest example) and every batch an ``edge_budget`` that fits its own
        edges, so that the per-edge work follows the batch's real edges
        (default); ``False``: no budget, each batch's capacity fits its
        largest example.
      capacity_margin, capacity_extra: head-room of a capacity over the most
        pairs found in the example's graph frames: ``pairs * (1 + margin) +
        extra`` (the training noise moves pairs across the radius), see
        :func:`dispgns.graph.capacity_for_counts`.
      use_cell_list: build training graphs with the jax-md cell list; ``None``
        (default): :func:`dispgns.graph.uses_cell_list` of the node budget.
        Its per-cell capacity fits the fullest cell of any frame.
      bounds: the box (``None``: ``[-1, 1]^D``).
      mirror: reflect each example on the horizontal axes with probability
        1/2, drawn per batch index (so resuming replays the same batches);
        needs a box symmetric about 0.
      quarter_turns: turn each example by ``k`` quarter turns about the
        vertical axis, ``k`` uniform in 0..3, drawn per batch index from a
        stream of its own (the mirror draws are those without it); ``D = 3``
        and a box whose two horizontal sides are equal and symmetric about 0.
      early_windows, early_repeats: the windows starting at each
        trajectory's first ``early_windows`` frames are examples
        ``early_repeats`` times over (:func:`example_index`).
      shards: the batch is split into this many equal parts, one per device
        (data parallelism, :mod:`dispgns.training.distributed`): the edge
        budget is then that of the largest part's merged graph, the same in
        every process.
    """

    def __init__(
        self,
        trajectories: Sequence[Trajectory],
        *,
        input_sequence_length: int,
        batch_size: int,
        connectivity_radius: float,
        seed: int = 0,
        pushforward_steps: int = 0,
        unroll_steps: int = 1,
        shuffle: bool = True,
        node_budgets: Sequence[int] | None = None,
        capacity_margin: float = 0.03,
        capacity_extra: int = 64,
        use_cell_list: bool | None = None,
        bounds: Bounds | None = None,
        compact_edges: bool = True,
        mirror: bool = False,
        shards: int = 1,
        quarter_turns: bool = False,
        early_windows: int = 0,
        early_repeats: int = 1,
    ):
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        self.input_sequence_length = int(input_sequence_length)
        if isinstance(unroll_steps, bool) or int(unroll_steps) != unroll_steps or unroll_steps < 1:
            raise ValueError(f"unroll_steps must be an integer >= 1, got {unroll_steps!r}")
        self.pushforward_steps = int(pushforward_steps)
        self.unroll_steps = int(unroll_steps)
        self.window = self.input_sequence_length + self.pushforward_steps + self.unroll_steps
        self.batch_size = int(batch_size)
        self.seed = int(seed)
        self.mirror = bool(mirror)
        if int(shards) != shards or shards < 1 or batch_size % shards:
            raise ValueError(f"shards must be an integer >= 1 that divides batch_size {batch_size}, got {shards!r}")
        self.shards = int(shards)
        self.quarter_turns = bool(quarter_turns)
        self.shuffle = bool(shuffle)
        self.connectivity_radius = float(connectivity_radius)
        self.capacity_margin = float(capacity_margin)
        self.capacity_extra = int(capacity_extra)
        self.positions, self.radii = [], []
        for k, traj in enumerate(trajectories):
            x = np.asarray(traj.position, np.float32)
            a = np.asarray(traj.radius, np.float32)
            if x.ndim != 3 or a.shape != (x.shape[1],):
                raise ValueError(
                    f"trajectory {k}: expected position (T, N, D) and radius (N,), got {x.shape} and {a.shape}"
                )
            self.positions.append(x)
            self.radii.append(a)
        if not self.positions:
            raise ValueError("BatchStream needs at least one trajectory")
        dims = {x.shape[2] for x in self.positions}
        if len(dims) != 1:
            raise ValueError(f"trajectories have different dimensions {sorted(dims)}")
        self.dim = dims.pop()
        bounds = as_bounds(bounds, self.dim)
        if self.mirror and any(abs(lo + hi) > 1e-12 for lo, hi in bounds):
            raise ValueError(f"mirror augmentation needs a box symmetric about 0, got {bounds}")
        if self.quarter_turns and (self.dim != 3 or bounds[0] != bounds[1] or abs(bounds[0][0] + bounds[0][1]) > 1e-12):
            raise ValueError(
                "quarter-turn augmentation needs 3-D trajectories in a box with equal horizontal sides "
                f"symmetric about 0, got D = {self.dim} and {bounds}"
            )
        self.index = example_index([x.shape[0] for x in self.positions], self.window, early_windows, early_repeats)
        if len(self.index) < self.batch_size:
            raise ValueError(
                f"{len(self.index)} examples of {self.window} frames, fewer than one batch of {self.batch_size}"
            )

        max_n = max(x.shape[1] for x in self.positions)
        self.node_budgets = sorted({int(b) for b in node_budgets}) if node_budgets else [node_budget([max_n])]
        if self.node_budgets[-1] < max_n:
            raise ValueError(f"node budgets {self.node_budgets} cannot hold {max_n} particles")

        # Pairs in each example's graph frames: the last input and, with
        # pushforward or unrolling, the frames the model will have predicted.
        c = self.input_sequence_length
        last_graph_frame = c + self.pushforward_steps + self.unroll_steps - 2
        per_frame = [host_count_pairs(x, connectivity_radius=self.connectivity_radius) for x in self.positions]
        self.pairs = np.array(
            [
                per_frame[t][s + c - 1 : s + last_graph_frame + 1].max()
                for t, s in zip(self.index.trajectory, self.index.start)
            ],
            np.int64,
        )
        self.compact_edges = bool(compact_edges)
        if use_cell_list is None:
            use_cell_list = uses_cell_list(
                self.node_budgets[-1], self.dim, connectivity_radius=self.connectivity_radius, bounds=bounds
            )
        self.occupancy = None
        if use_cell_list:
            self.occupancy = max(
                host_max_cell_occupancy(x, connectivity_radius=self.connectivity_radius, bounds=bounds)
                for x in self.positions
            )
        self.position = 0

    @classmethod
    def for_training(
        cls,
        trajectories: Sequence[Trajectory],
        model_config: ModelConfig,
        # step.py imports this module, so TrainConfig is named through the package (resolved when read).
        train_config: dispgns.training.step.TrainConfig,
        **kwargs: Any,
    ) -> BatchStream:
        """The stream a run with these configs needs (``C``, ``B``, radius, seed, pushforward, unrolling, box)."""
        return cls(
            trajectories,
            input_sequence_length=model_config.input_sequence_length,
            batch_size=train_config.batch_size,
            connectivity_radius=model_config.connectivity_radius,
            seed=train_config.seed,
            pushforward_steps=train_config.pushforward_steps,
            unroll_steps=train_config.unroll_steps,
            bounds=model_config.bounds,
            mirror=train_config.mirror_augmentation,
            quarter_turns=train_config.quarter_turn_augmentation,
            early_windows=train_config.early_windows,
            early_repeats=train_config.early_repeats,
            **kwargs,
        )

    # -- sizes ---------------------------------------------------------------------------------
    @property
    def num_examples(self) -> int:
        return len(self.index)

    @property
    def batches_per_epoch(self) -> int:
        return self.num_examples // self.batch_size

    def _edge_need(self, ids) -> int:
        """Edge slots the merged graph of examples ``ids`` needs: pairs with head-room plus every self-loop."""
        pairs = self.pairs[np.asarray(ids, np.int64)]
        with_room = np.ceil(pairs * (1.0 + self.capacity_margin)) + self.capacity_extra
        return int(np.sum(with_room)) + len(pairs) * self._node_budget(ids)

    def _node_budget(self, ids) -> int:
        n_max = max(self.positions[t].shape[1] for t in self.index.trajectory[np.asarray(ids, np.int64)])
        return next(b for b in self.node_budgets if b >= n_max)

    def capacity_for(self, ids: _Ids) -> GraphCapacity:
        """Graph capacity of each example of a batch of examples ``ids`` (on the ladder)."""
        ids = np.asarray(ids, np.int64)
        pairs = self.pairs.max() if self.compact_edges else self.pairs[ids].max()
        return capacity_for_counts(
            int(pairs),
            self._node_budget(ids),
            occupancy=self.occupancy,
            margin=self.capacity_margin,
            extra=self.capacity_extra,
        )

    def edge_budget_for(self, ids: _Ids) -> int | None:
        """Edge slots of the merged graph of one shard of examples ``ids`` (on the ladder; ``None``: no compaction).

        With ``shards`` parts, the budget of the part that needs most (every
        device compiles the same program).
        """
        if not self.compact_edges:
            return None
        parts = np.array_split(np.asarray(ids, np.int64), self.shards)
        # Fewer examples than shards (one process's part of a batch split over more devices than it holds
        # examples): the empty shards need no edges.
        return edge_budget_for(max(self._edge_need(part) for part in parts if part.size))

    @staticmethod
    def grow(batch: Batch) -> Batch:
        """``batch`` with a larger capacity and edge budget, after an overflow of the training step."""
        n = batch.node_budget
        budget = None if batch.edge_budget is None else grow_edge_budget(batch.edge_budget)
        return batch.with_capacity(grow_capacity(batch.capacity, n), budget)

    # -- order ---------------------------------------------------------------------------------
    def epoch_order(self, epoch: int) -> _Ids:
        """Example ids of ``epoch`` in the order they are drawn."""
        if not self.shuffle:
            return np.arange(self.num_examples)
        return np.random.default_rng([self.seed, int(epoch)]).permutation(self.num_examples)

    def batch_examples(self, i: int) -> _Ids:
        """Example ids of batch ``i`` (counting from the start of training)."""
        if i < 0:
            raise ValueError(f"batch index must be >= 0, got {i}")
        epoch, j = divmod(int(i), self.batches_per_epoch)
        return self.epoch_order(epoch)[j * self.batch_size : (j + 1) * self.batch_size]

    def batch(self, i: int, part: slice = slice(None)) -> Batch:
        """Batch ``i`` (a pure function of ``seed`` and ``i``), or the ``part`` of it one process holds.

        A part keeps the whole batch's capacity and edge budget (all processes
        compile the same program).
        """
        ids = self.batch_examples(i)
        flips = None
        if self.mirror:
            flips = np.random.default_rng([self.seed, 1, int(i)]).integers(0, 2, (len(ids), self.dim - 1)) == 1
        turns = None
        if self.quarter_turns:
            turns = np.random.default_rng([self.seed, 2, int(i)]).integers(0, 4, len(ids))
        if part == slice(None):
            return self.make_batch(ids, flips, turns=turns)
        local = self.make_batch(
            ids[part],
            None if flips is None else flips[part],
            turns=None if turns is None else turns[part],
            nodes=self._node_budget(ids),
        )
        return local.with_capacity(self.capacity_for(ids), self.edge_budget_for(ids))

    def make_batch(
        self,
        ids: Sequence[int],
        flips: _Flips | None = None,
        *,
        turns: _Turns | None = None,
        nodes: int | None = None,
    ) -> Batch:
        """A padded batch of the given example ids.

        Args:
          ids: example ids.
          flips: optional ``(len(ids), D - 1)`` bool: reflect example ``k`` on
            axis ``d`` (``x_d -> -x_d``) where ``flips[k, d]``.
          turns: optional ``(len(ids),)`` int (D = 3): then turn example ``k``
            by ``turns[k]`` quarter turns about the vertical axis,
            ``(x, y) -> (-y, x)`` per turn.
          nodes: particle slots (``None``: the smallest node budget that holds them).
        """
        ids = np.asarray(ids, np.int64)
        trajs, starts = self.index.trajectory[ids], self.index.start[ids]
        nodes = self._node_budget(ids) if nodes is None else int(nodes)
        b = len(ids)
        position = np.zeros((b, self.window, nodes, self.dim), np.float32)
        radius = np.ones((b, nodes), np.float32)
        mask = np.zeros((b, nodes), bool)
        for k, (t, s) in enumerate(zip(trajs, starts)):
            n = self.positions[t].shape[1]
            position[k, :, :n] = self.positions[t][s : s + self.window]
            if flips is not None:
                position[k, :, :n, :-1] *= np.where(flips[k], -1.0, 1.0).astype(np.float32)
            if turns is not None:
                position[k, :, :n, :2] = quarter_turns(position[k, :, :n, :2], int(turns[k]))
            radius[k, :n] = self.radii[t]
            mask[k, :n] = True
        capacity = self.capacity_for(ids)
        example = np.stack([trajs, starts], axis=1).astype(np.int32)
        return Batch(
            position=position,
            radius=radius,
            mask=mask,
            example=example,
            capacity=capacity,
            edge_budget=self.edge_budget_for(ids),
        )

    # -- iteration -------------------------------------------------------------------------------
    def __iter__(self) -> Iterator[Batch]:
        return self

    def __next__(self) -> Batch:
        batch = self.batch(self.position)
        self.position += 1
        return batch

    def state_dict(self) -> dict[str, int]:
        """What to checkpoint to resume the data order exactly."""
        return {"position": int(self.position), "seed": self.seed}

    def load_state_dict(self, state: dict[str, int]) -> None:
        if int(state.get("seed", self.seed)) != self.seed:
            raise ValueError(f"data-order seed mismatch: checkpoint {state['seed']}, stream {self.seed}")
        self.position = int(state["position"])

"""Data-parallel training over every device of every process, on JAX's own runtime.

A 1-D mesh spans all devices JAX sees (in a multi-process run, every
process's devices). Each global batch of ``B`` examples is split over the
mesh axis, ``B / devices`` examples per device; parameters and optimiser
state are replicated. The step is :func:`dispgns.training.train_step` itself,
applied from the outside with ``shard_map`` and its ``axis_name``: every
device computes its examples' share of the loss of the whole batch (the
error sum over the whole batch's particle count), XLA sums the shares and
their gradients over the axis, and every device applies the same update.
On one device nothing changes.

Equal to one device with the same global batch up to the order of float
summation: the noise of every example comes from the same key as on one
device, and the loss is normalised by the whole batch's particle count.

Processes. Start JAX's runtime with ``jax.distributed.initialize()``
(coordinator address, process count and id given, or found by JAX in the
environment, e.g. under SLURM) first thing in the script: before importing
``dispgns.physics``, ``dispgns.graph`` or anything that imports them
(``dispgns.training`` does), because jax-md starts JAX's backend at import.
On the CPU the processes talk over gloo, JAX's default CPU collectives. Each
process then reads only its slice of every batch
(``BatchStream(..., shards=devices)`` builds the whole batch's edge budgets
from its index, so all processes agree on them without exchanging data);
:meth:`DataParallel.global_batch` assembles the global arrays from the local
slices. Only process 0 should write logs and pictures; checkpoints are orbax
multi-process checkpoints that every process takes part in.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Mapping
from typing import Any

import jax
import numpy as np
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P
from jaxtyping import ArrayLike, PyTree, Shaped

from dispgns.arrays import Flag, PRNGKey, Scalar
from dispgns.training.batches import Batch
from dispgns.training.step import TrainState, train_step
from dispgns.tuning import jitted

__all__ = ["DataParallel"]

AXIS = "data"
# Parameters, optimiser state, keys: any pytree of arrays.
_Tree = PyTree[Shaped[ArrayLike, "..."]]


@dataclasses.dataclass(frozen=True)
class DataParallel:
    """Data parallelism over a 1-D mesh of devices (hashable: the mesh is static).

    Attributes:
      mesh: a 1-D ``jax.sharding.Mesh`` whose axis is named ``"data"``
        (default: every device JAX sees, in every process).
    """

    mesh: jax.sharding.Mesh = dataclasses.field(default_factory=lambda: jax.make_mesh((jax.device_count(),), (AXIS,)))

    def __post_init__(self):
        if tuple(self.mesh.axis_names) != (AXIS,):
            raise ValueError(f"DataParallel needs a 1-D mesh with the axis {AXIS!r}, got axes {self.mesh.axis_names}")

    @property
    def devices(self) -> int:
        return int(self.mesh.devices.size)

    @property
    def is_primary(self) -> bool:
        """Whether this process writes logs, pictures and exported models (process 0)."""
        return jax.process_index() == 0

    def check_batch_size(self, batch_size: int) -> None:
        """A clear error when the global batch does not split evenly over the devices."""
        if batch_size % self.devices:
            raise ValueError(
                f"the global batch size {batch_size} does not split over {self.devices} devices: "
                f"choose a multiple of {self.devices} (train.batch_size) or another device count"
            )

    def local_examples(self, batch_size: int) -> slice:
        """The slice of every global batch this process holds (its devices' examples, in mesh order)."""
        self.check_batch_size(batch_size)
        per_device = batch_size // self.devices
        mine = [k for k, device in enumerate(self.mesh.devices.flat) if device.process_index == jax.process_index()]
        if mine != list(range(mine[0], mine[-1] + 1)):
            raise ValueError("this process's devices are not contiguous on the mesh")
        return slice(mine[0] * per_device, (mine[-1] + 1) * per_device)

    def replicate(self, tree: _Tree) -> _Tree:
        """``tree`` replicated on every device of the mesh (parameters, optimiser state, keys)."""
        sharding = NamedSharding(self.mesh, P())
        return jax.tree_util.tree_map(lambda x: jax.make_array_from_process_local_data(sharding, np.asarray(x)), tree)

    def global_batch(self, local: Batch) -> Batch:
        """The global batch from this process's slice of it (every process passes its own)."""
        sharding = NamedSharding(self.mesh, P(AXIS))
        processes = jax.process_count()

        def assemble(x):
            x = np.asarray(x)
            return jax.make_array_from_process_local_data(sharding, x, (x.shape[0] * processes,) + x.shape[1:])

        arrays = {f: assemble(getattr(local, f)) for f in ("position", "radius", "mask", "example")}
        return local.replace(**arrays)

    def step(
        self, compiler_options: Mapping[str, Any] | None = None
    ) -> Callable[[TrainState, Batch, PRNGKey], tuple[TrainState, dict[str, Scalar | Flag]]]:
        """``step(state, batch, key) -> (state, metrics)``: :func:`train_step` with the batch split over the mesh.

        ``state`` and ``key`` replicated, ``batch`` split along its first axis
        (:meth:`global_batch`); the outputs are replicated.
        """
        return functools.partial(jitted(_sharded_step, compiler_options, static_argnames=("parallel",)), parallel=self)

    def train_step(
        self,
        state: TrainState,
        batch: Batch,
        key: PRNGKey,
        compiler_options: Mapping[str, Any] | None = None,
    ) -> tuple[TrainState, dict[str, Scalar | Flag]]:
        """One data-parallel optimiser step (see :meth:`step`)."""
        return self.step(compiler_options)(state, batch, key)

    @staticmethod
    def barrier(name: str) -> None:
        """Wait until every process gets here (a no-op with one process)."""
        if jax.process_count() > 1:
            from jax.experimental import multihost_utils

            multihost_utils.sync_global_devices(name)

    @staticmethod
    def local(tree: _Tree) -> _Tree:
        """This process's copy of replicated arrays, as numpy (for host work: validation, export)."""
        return jax.tree_util.tree_map(lambda x: np.asarray(x.addressable_data(0)), tree)


def _sharded_step(state, batch, key, *, parallel: DataParallel):
    step = functools.partial(train_step, axis_name=AXIS)
    # check_vma=False: each device differentiates its own share of the loss and train_step sums the shares'
    # gradients over the axis itself (as under pmap). With JAX's varying-axis typing on, autodiff would sum
    # them once more, and the fused kernels' custom backward passes would have to declare their typing.
    sharded = jax.shard_map(
        step, mesh=parallel.mesh, in_specs=(P(), P(AXIS), P()), out_specs=(P(), P()), check_vma=False
    )
    return sharded(state, batch, key)

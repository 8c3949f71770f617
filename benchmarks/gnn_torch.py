"""The paper network in plain PyTorch next to dispgns, timed in alternation on the same inputs.

The authors' own times (``benchmarks/gnn.py``: 330 ms per training step, 49
ms per rollout step) were measured on an earlier machine. This script gives a
comparison on the machine at hand: the same encoder-processor-decoder (2,587,010
parameters, the paper's defaults), features, radius graph, random-walk noise,
loss and Adam step (without dispgns' standardisation of velocities and
targets, which costs nothing measurable), written the way a PyTorch GNS
usually is: per-edge concatenation ``[x_i, x_j, e_ij]`` into the first
message layer (as the authors' code does; dispgns splits that layer so the
node parts are computed once per node, ~29 % fewer per-edge FLOPs;
``--split-first-layer`` gives PyTorch the same), ``index_select`` gathers,
``index_add_`` sums, the graph from ``torch.cdist``. It is our
re-implementation, not the authors' code. Inputs are those of
``benchmarks/gnn.py`` (2 examples of 220 particles, ~2,400 edges each,
self-loops included, for a training step; one for a rollout step).

Rounds alternate the two frameworks (a few PyTorch steps, then a few dispgns
steps, who goes first alternating) so that both see the same machine, whose
speed drifts within minutes. PyTorch always computes in float32;
``--matmul-dtype bfloat16`` switches dispgns' matmuls only.

    pip install torch==2.13.0      # CPU build; not a dependency of dispgns
    python benchmarks/gnn_torch.py [--rounds 8] [--split-first-layer] [--matmul-dtype bfloat16]

Prints a few lines and ends with one JSON line: medians per framework and the
ratios ``torch / dispgns``.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import jax
import jax.numpy as jnp
import numpy as np
import torch

from dispgns import tuning

tuning.tune_host_allocator()  # before jax-md's import (in gnn) starts JAX's CPU backend, as the command line does

from gnn import machine_info, trajectories
from torch import nn

from dispgns.model import ModelConfig
from dispgns.simulator import fit_capacity, rollout_scan
from dispgns.training import BatchStream, TrainConfig, compute_normalization, create_train_state, train_step

LATENT, HIDDEN, BLOCKS, C, D = 128, 128, 10, 6, 2
RADIUS_GRAPH, CLIP, NOISE = 0.2, 4.0, 5e-4


def mlp(fan_in: int, out: int, layer_norm: bool = True) -> nn.Sequential:
    layers = [nn.Linear(fan_in, HIDDEN), nn.ReLU(), nn.Linear(HIDDEN, HIDDEN), nn.ReLU(), nn.Linear(HIDDEN, out)]
    return nn.Sequential(*layers, *([nn.LayerNorm(out)] if layer_norm else []))


class Block(nn.Module):
    def __init__(self, split_first_layer: bool):
        super().__init__()
        self.message, self.node, self.node_2, self.edge = (
            mlp(3 * LATENT, LATENT),
            mlp(2 * LATENT, LATENT),
            mlp(LATENT, LATENT),
            mlp(LATENT, LATENT),
        )
        self.split_first_layer = split_first_layer

    def forward(self, x, e, senders, receivers):
        if self.split_first_layer:
            # dispgns' form: [x_i, x_j, e_ij] W = (x W_i)[i] + (x W_j)[j] + e W_e, node parts once per node.
            first, w = self.message[0], self.message[0].weight
            h = (
                (x @ w[:, :LATENT].T).index_select(0, receivers)
                + (x @ w[:, LATENT : 2 * LATENT].T).index_select(0, senders)
                + e @ w[:, 2 * LATENT :].T
                + first.bias
            )
            m = self.message[1:](h)
        else:
            m = self.message(torch.cat([x.index_select(0, receivers), x.index_select(0, senders), e], dim=-1))
        summed = torch.zeros_like(x).index_add_(0, receivers, m)
        x = x + self.node_2(self.node(torch.cat([summed, x], dim=-1)))
        return x, e + self.edge(m)


class Network(nn.Module):
    def __init__(self, split_first_layer: bool = False):
        super().__init__()
        self.node_encoder = mlp((C - 1) * D + 2 * D + 1, LATENT)
        self.edge_encoder = mlp(C * D + 2, LATENT)
        self.blocks = nn.ModuleList(Block(split_first_layer) for _ in range(BLOCKS))
        self.decoder = mlp(LATENT, D, layer_norm=False)

    def forward(self, node_features, edge_features, senders, receivers):
        x, e = self.node_encoder(node_features), self.edge_encoder(edge_features)
        for block in self.blocks:
            x, e = block(x, e, senders, receivers)
        return self.decoder(x)


def features(position_seq, radius):
    """The paper's node and edge features and the radius graph (self-loops included) of one example."""
    last = position_seq[-1]
    vel = (position_seq[1:] - position_seq[:-1]).permute(1, 0, 2).reshape(last.shape[0], -1)
    inv_a = (1.0 / radius)[:, None]
    walls = torch.clamp(torch.cat([last + 1.0, 1.0 - last], dim=-1) * inv_a, -CLIP, CLIP)
    nodes = torch.cat([vel * inv_a, walls, radius[:, None]], dim=-1)
    receivers, senders = torch.nonzero(torch.cdist(last, last) < RADIUS_GRAPH, as_tuple=True)
    a_sum = (radius[senders] + radius[receivers])[:, None]
    rel = (last[senders] - last[receivers]) / a_sum
    rel_vel = (vel[senders] - vel[receivers]) / a_sum
    edges = torch.cat([rel, torch.linalg.norm(rel, dim=-1, keepdim=True), rel_vel, a_sum], dim=-1)
    return nodes, edges, senders, receivers


def torch_train_step(net, opt, windows, radii, generator):
    """One Adam step on a batch of examples (windows ``(C + 1, N, D)``), merged into one graph."""
    node_list, edge_list, send_list, recv_list, targets, offset = [], [], [], [], [], 0
    for window, radius in zip(windows, radii):
        # dispgns' random walk: velocity noise cumulated over time, position noise zero at the first frame.
        velocity_noise = torch.cumsum(torch.randn(window[1:C].shape, generator=generator) * (NOISE / (C - 1) ** 0.5), 0)
        noise = torch.cat([torch.zeros_like(window[:1]), torch.cumsum(velocity_noise, 0)])
        noisy = window[:C] + noise
        nodes, edges, s, r = features(noisy, radius)
        targets.append((window[C] - 2 * window[C - 1] + window[C - 2] - (noise[-1] - noise[-2])) / radius[:, None])
        node_list.append(nodes), edge_list.append(edges)
        send_list.append(s + offset), recv_list.append(r + offset)
        offset += nodes.shape[0]
    out = net(torch.cat(node_list), torch.cat(edge_list), torch.cat(send_list), torch.cat(recv_list))
    loss = torch.mean(torch.sum((out - torch.cat(targets)) ** 2, dim=-1))
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()
    return float(loss.detach())


@torch.no_grad()
def torch_rollout_step(net, window, radius):
    nodes, edges, s, r = features(window, radius)
    acc = net(nodes, edges, s, r) * radius[:, None]
    nxt = 2 * window[-1] - window[-2] + acc
    return torch.cat([window[1:], nxt[None]])


def timed(fn) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rounds", type=int, default=8, help="alternating rounds (medians over them)")
    parser.add_argument(
        "--split-first-layer",
        action="store_true",
        help="PyTorch also splits the first message layer as dispgns does (same FLOPs)",
    )
    parser.add_argument(
        "--matmul-dtype",
        default="float32",
        choices=("float32", "bfloat16"),
        help="dispgns' ModelConfig.matmul_dtype (PyTorch stays float32)",
    )
    args = parser.parse_args()
    torch.set_num_threads(len(os.sched_getaffinity(0)))
    torch.manual_seed(0)

    trajs = trajectories(220, 110)
    net = Network(args.split_first_layer)
    n_params = sum(p.numel() for p in net.parameters())
    opt = torch.optim.Adam(net.parameters(), lr=1e-4)
    generator = torch.Generator().manual_seed(0)

    # dispgns: the step and inputs of benchmarks/gnn.py.
    # dispgns with its opt-in CPU settings, as the command line runs it.
    model_config = tuning.tuned_model_config(ModelConfig(matmul_dtype=args.matmul_dtype))
    options, train_config = tuning.network_compiler_options(model_config), TrainConfig()
    state = create_train_state(
        jax.random.key(0), model_config, train_config, compute_normalization(trajs, noise_std=train_config.noise_std)
    )
    stream = BatchStream(trajs, input_sequence_length=C, batch_size=2, connectivity_radius=RADIUS_GRAPH, seed=0)
    late = np.flatnonzero(stream.index.start >= stream.index.start.max() - 4)
    ids = [late[0], late[-1]]
    batch = stream.make_batch(ids)
    key = jax.random.key(0)
    compiled = tuning.jitted(train_step, options).lower(state, batch, key).compile()
    starts = stream.index.start[ids]
    windows = [
        torch.tensor(np.asarray(t.position[s : s + C + 1]))
        for t, s in zip([trajs[int(stream.index.trajectory[i])] for i in ids], starts)
    ]
    radii = [torch.tensor(np.asarray(trajs[int(stream.index.trajectory[i])].radius)) for i in ids]
    edges_torch = [int(features(w[:C], a)[2].shape[0]) for w, a in zip(windows, radii)]

    traj = trajs[0]
    start = traj.position.shape[0] - 6
    jwindow = jnp.asarray(traj.position[start - 100 : start - 94])
    jradius = jnp.asarray(traj.radius)
    mask = jnp.ones(jradius.shape, bool)
    capacity = fit_capacity(traj.position[start - 100 :], model_config)
    chunk_steps = 20
    scan = tuning.jitted(rollout_scan, options, static_argnames=("n_steps", "model_config", "capacity"))
    chunk = lambda: scan(
        state.params, jwindow, jradius, n_steps=chunk_steps, model_config=model_config, capacity=capacity, mask=mask
    )
    twindow, tradius = torch.tensor(np.asarray(jwindow)), torch.tensor(np.asarray(jradius))

    def torch_rollout(steps):
        w = twindow
        for _ in range(steps):
            w = torch_rollout_step(net, w, tradius)
        return w

    # Warm-up (compilation, allocator, thread pools).
    jax.block_until_ready(compiled(state, batch, key))
    if bool(np.any(jax.block_until_ready(chunk())[1])):
        raise SystemExit(f"the timed rollout chunk outgrew its graph capacity ({capacity})")
    torch_train_step(net, opt, windows, radii, generator)
    torch_rollout(2)

    per = 3
    work = {
        "torch_train": lambda: np.median(
            [timed(lambda: torch_train_step(net, opt, windows, radii, generator)) for _ in range(per)]
        ),
        "dispgns_train": lambda: np.median(
            [timed(lambda: jax.block_until_ready(compiled(state, batch, key))) for _ in range(per)]
        ),
        "torch_rollout": lambda: timed(lambda: torch_rollout(chunk_steps)) / chunk_steps,
        "dispgns_rollout": lambda: timed(lambda: jax.block_until_ready(chunk())) / chunk_steps,
    }
    times = {k: [] for k in work}
    order = list(work)
    for r in range(args.rounds):
        # Who goes first alternates, so neither always runs right after the other.
        for name in order if r % 2 == 0 else order[1::-1] + order[:1:-1]:
            times[name].append(work[name]())
    ms = {k: 1e3 * float(np.median(v)) for k, v in times.items()}
    print(
        f"training step: PyTorch {ms['torch_train']:.1f} ms, dispgns {ms['dispgns_train']:.1f} ms; "
        f"rollout step: PyTorch {ms['torch_rollout']:.1f} ms, dispgns {ms['dispgns_rollout']:.1f} ms",
        flush=True,
    )
    report = {
        "machine": {**machine_info(), "torch": torch.__version__, "torch_threads": torch.get_num_threads()},
        "torch_parameters": n_params,
        "edges_per_example_torch": edges_torch,
        "edges_per_example_dispgns": [int(p) + int(n) for p, n in zip(stream.pairs[ids], batch.mask.sum(axis=1))],
        "edge_slots_per_example_dispgns": int(batch.capacity.edges + batch.node_budget),
        "torch_split_first_layer": args.split_first_layer,
        **{f"{k}_step_ms": v for k, v in ms.items()},
        "train_step_ratio_torch_over_dispgns": ms["torch_train"] / ms["dispgns_train"],
        "rollout_step_ratio_torch_over_dispgns": ms["torch_rollout"] / ms["dispgns_rollout"],
        "dispgns_matmul_dtype": args.matmul_dtype,
        "rounds": args.rounds,
    }
    print(json.dumps(report, default=lambda o: o.item() if hasattr(o, "item") else str(o)))


if __name__ == "__main__":
    main()

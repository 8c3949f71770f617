"""Export a trained paper-size network for the rollout timings of ``benchmarks/gnn.py``.

The benchmark times rollouts with trained weights: untrained ones move the
particles unphysically (in a full rollout they all leave the box and the
graph empties) and so would time steps on graphs the simulator never meets.
The weights in
``benchmarks/data/paper_network`` came from (37 minutes on the 2-core
development machine)::

    dispgns generate --preset paper --seed 0 --out /tmp/paper/data
    dispgns train --data /tmp/paper/data --out /tmp/paper/run128 \\
        --config experiments/paper/config.yaml \\
        --set model.latent_size=128 --set model.hidden_size=128 --set model.message_passing_steps=10 \\
        --set train.validate_every=3000 --set train.checkpoint_every=1000 \\
        --set train.validation_trajectories=2 --steps 12000
    python benchmarks/paper_network.py /tmp/paper/run128

that is the paper's network (2,587,010 parameters) with the shipped model's
recipe, stopped early. It is a timing fixture, not a model to simulate with:
the shipped model (``dispgns.load_pretrained``) is the better simulator.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

from dispgns.training.checkpoint import export_model, load_params

TARGET = Path(__file__).resolve().parent / "data" / "paper_network"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("run", type=Path, help="the training run directory (dispgns train --out RUN)")
    parser.add_argument("--out", type=Path, default=TARGET, help="model directory to write")
    args = parser.parse_args(argv)
    params, model_config, info = load_params(args.run, best=True)
    # As the shipped model does: centres the network puts beyond a wall go back onto it.
    model_config = dataclasses.replace(model_config, keep_inside_box=True)
    log = [json.loads(line) for line in (args.run / "log.jsonl").read_text().splitlines() if line.strip()]
    record = dict(info.get("record", {}))
    record["purpose"] = "timing fixture of benchmarks/gnn.py (see benchmarks/paper_network.py)"
    record["validation_log"] = [
        [r["step"], r.get("valid_rollout_mse"), r.get("valid_one_step_loss")]
        for r in log
        if r.get("kind") == "validation"
    ]
    export_model(args.out, params, model_config, record)
    print(f"wrote {args.out} from {info['source']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

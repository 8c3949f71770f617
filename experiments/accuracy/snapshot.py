"""Export the best checkpoint of the accuracy run as a model directory, for a commit of the run in progress.

    python experiments/accuracy/snapshot.py [--run experiments/accuracy/run] [--out experiments/accuracy/best_model]

The run's ``best/`` (its orbax checkpoint with the optimiser state) is not committed; its parameters are,
as an exported model (``params.msgpack`` + ``model.json``, what ``dispgns evaluate --model`` and
``load_pretrained`` read). The checkpoint is copied to a temporary directory first, so that a training
process writing into the run at the same time is never disturbed.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", default=str(HERE / "run"))
    parser.add_argument("--out", default=str(HERE / "best_model"))
    args = parser.parse_args(argv)

    from dispgns.training.checkpoint import export_model, load_params

    run = Path(args.run)
    if not (run / "best").is_dir():
        print(f"{run / 'best'}: no best checkpoint yet", file=sys.stderr)
        return 1
    with tempfile.TemporaryDirectory() as tmp:
        copy = Path(tmp) / "run"
        copy.mkdir()
        shutil.copy2(run / "config.json", copy / "config.json")
        shutil.copytree(run / "best", copy / "best", ignore=shutil.ignore_patterns("*.orbax-checkpoint-tmp*"))
        params, model_config, info = load_params(copy, best=True)
    record = dict(info["record"])
    record["run"] = str(run)
    export_model(args.out, params, model_config, record)
    validation = record.get("validation", {})
    print(
        json.dumps({"out": args.out, "step": record["steps"], "valid_rollout_mse": validation.get("valid_rollout_mse")})
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""A dataset whose train split is the first K trajectories of another dataset's (the valid split is copied).

    python experiments/accuracy/subset.py datasets/acc400 16 datasets/acc16

The data-scaling runs (``data_scaling.py``) train on subsets of the same files, so that every run validates
on the same trajectories. Regenerating with ``--train-count K`` is not the same: ``dispgns generate``
simulates trajectories in batches and float32 rounding depends on the grouping, so the chaotic rollouts
differ. The metadata keeps every field of the source but the train counts and the training statistics.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("source", type=Path)
    parser.add_argument("count", type=int)
    parser.add_argument("out", type=Path)
    args = parser.parse_args(argv)

    import h5py

    from dispgns.data.format import load_dataset, training_statistics

    metadata = json.loads((args.source / "metadata.json").read_text())
    available = metadata["trajectory_counts"]["train"]
    if not 1 <= args.count <= available:
        print(f"error: count must lie in [1, {available}] (the train split of {args.source}), got {args.count}")
        return 2
    staging = args.out.with_name(args.out.name + ".partial")
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    shutil.copy(args.source / "valid.h5", staging / "valid.h5")
    with h5py.File(args.source / "train.h5", "r") as source, h5py.File(staging / "train.h5", "w") as target:
        for key, value in source.attrs.items():
            target.attrs[key] = value
        for name in sorted(source.keys())[: args.count]:
            source.copy(source[name], target, name)
    metadata["trajectory_counts"]["train"] = args.count
    (group,) = metadata["radii"]["train"]
    group["count"] = args.count
    metadata["particle_counts"]["train"] = metadata["particle_counts"]["train"][: args.count]
    metadata["num_particles_max"] = max(max(counts) for counts in metadata["particle_counts"].values())
    (staging / "metadata.json").write_text(json.dumps(metadata, indent=1))
    _, splits = load_dataset(staging, ["train"])
    metadata.update(training_statistics(splits))
    (staging / "metadata.json").write_text(json.dumps(metadata, indent=1))
    load_dataset(staging)  # validates every file
    staging.rename(args.out)
    valid = metadata["trajectory_counts"]["valid"]
    print(f"wrote {args.out}: train {args.count} (first of {available}), valid {valid}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The adversarial trial of issue 18, category by category: every case a user can get wrong, and what happens.

Each case states what is expected and records what was observed; the script prints one JSON object
(``{"summary": {category: {"cases", "passed", "failed"}}, "cases": [...]}``) and exits 1 if any case failed.

Categories (``--only api,cli,...``; all by default):

- ``api``: misuse of the Python API (``simulate``, ``rollout``, ``rollout_batch``, ``predict_*``,
  ``sample_initial_state``): NaN/inf, metres for normalised units, particles outside the box, a box larger than the
  model's bounds, zero particles, non-positive radii, overlaps, wrong shapes and dtypes, traced inputs. Expected:
  a ``ValueError`` naming the argument (and the particle where there is one), or a finite, in-box result.
- ``cli``: bad command lines. Expected: exit 2, one error line on stderr, no traceback, nothing written.
- ``corrupt``: damaged datasets (truncated or garbage HDF5, a flipped bit, NaN in stored positions, missing or
  malformed metadata) and models. Expected as for ``cli``.
- ``checkpoint``: damaged checkpoints of a run (``_METADATA``, deleted ``state/``, truncated array chunks, the whole
  latest one removed). Expected: ``--resume`` names the damaged one, falls back to the newest intact one and
  ends with parameters equal to an uninterrupted run's; a damaged best checkpoint is one clean error.
- ``readonly``: outputs that cannot be written (a file where a directory should be, a read-only file system).
  Expected: exit 2, one line naming the path, nothing half-written.
- ``signals``: SIGKILL, SIGINT and SIGTERM at several moments of ``train`` (start-up, training, checkpointing,
  export), ``generate`` and ``evaluate``. Expected: exit 130/143 (or -9), no crash at exit, the next run removes
  what was left and says so, and the resumed run's parameters equal an uninterrupted run's; no duplicated records.

Run from a checkout (the read-only cases mount a small tmpfs and need root; without it they are skipped)::

    nice -n 10 python tools/adversarial_trial.py --work /tmp/trial [--only api,cli]

Costly parts: the ``signals`` and ``checkpoint`` categories train a 16-wide network on the ``tiny`` preset
(about 30 runs of up to 60 steps; ~15-25 min on a loaded 2-core machine); ``api`` and ``cli`` take ~2 min.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import traceback
from pathlib import Path

import numpy as np

CATEGORIES = ("api", "cli", "corrupt", "checkpoint", "readonly", "signals")
# Words of a crash at exit or of a library's internals leaking into a user-facing message.
CRASH_WORDS = ("Traceback", "terminate called", "pure virtual", "Segmentation fault", "Event loop is closed")
INTERNAL_WORDS = ("strict=False", "ArrayRestoreArgs", "tensorstore", "TensorStore")
TINY_TRAIN = [
    *("--set", "model.latent_size=16", "--set", "model.hidden_size=16", "--set", "model.message_passing_steps=2"),
    *("--set", "train.log_every=10", "--set", "train.checkpoint_every=20", "--set", "train.validate_every=20"),
    *("--set", "train.validation_rollout_frames=10", "--no-progress"),
]
STEPS = 60  # every training run of the trial ends here; the reference run is uninterrupted


class Trial:
    def __init__(self, work: Path, match: list[str] | None = None):
        self.work = work
        self.match = match
        self.results: list[dict] = []

    def record(self, category: str, case: str, expected: str, passed: bool, observed: str) -> None:
        entry = dict(category=category, case=case, expected=expected, observed=observed[:600], passed=bool(passed))
        self.results.append(entry)
        print(("PASS " if passed else "FAIL ") + f"[{category}] {case}: {observed[:300]}", file=sys.stderr, flush=True)

    def run(self, category: str, case: str, expected: str, check) -> None:
        """``check()`` returns ``(passed, observed)``; an exception in the trial itself is a failure too."""
        if self.match and not any(m in case for m in self.match):
            return
        try:
            passed, observed = check()
        except Exception as error:  # the trial reports, it does not stop
            passed, observed = False, f"trial error: {type(error).__name__}: {error} {traceback.format_exc()[-300:]}"
        finally:
            stop_children()  # a case that timed out leaves no command running into the next one
        self.record(category, case, expected, passed, observed)


# ----------------------------------------------------------------------------- helpers


def cli(argv, *, timeout=900, cwd=None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "dispgns", *map(str, argv)], capture_output=True, text=True, timeout=timeout, cwd=cwd
    )


def error_lines(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if "error:" in line]


def clean_failure(proc, *, code=2, words=(), absent=()) -> tuple[bool, str]:
    """Exit ``code``, exactly one error line holding ``words``, no traceback or library internals, ``absent`` absent."""
    errors = error_lines(proc.stderr)
    bad = [w for w in CRASH_WORDS + INTERNAL_WORDS if w in proc.stderr]
    missing = [w for w in words if w.lower() not in proc.stderr.lower()]
    written = [str(p) for p in absent if Path(p).exists()]
    passed = proc.returncode == code and len(errors) == 1 and not bad and not missing and not written
    observed = f"exit {proc.returncode}; {errors[-1] if errors else proc.stderr.strip()[-300:]!r}"
    if bad:
        observed += f"; crash/internal words {bad}"
    if missing:
        observed += f"; missing words {missing}"
    if written:
        observed += f"; written {written}"
    if len(errors) > 1:
        observed += f"; {len(errors)} error lines"
    return passed, observed


def raises_value_error(call, words) -> tuple[bool, str]:
    try:
        out = call()
    except ValueError as error:
        text = str(error)
        missing = [w for w in words if w not in text]
        return not missing, f"ValueError: {text[:400]}" + (f" (missing words {missing})" if missing else "")
    except Exception as error:
        return False, f"{type(error).__name__} (not ValueError): {str(error)[:300]}"
    return False, f"returned without error: {describe(out)}"


def describe(out) -> str:
    leaves = [np.asarray(x) for x in (out if isinstance(out, tuple | list) else [out])]
    return ", ".join(f"shape {x.shape}, finite {bool(np.isfinite(x).all())}" for x in leaves if x.dtype.kind == "f")


def finite_inside(call, bounds, real=None) -> tuple[bool, str]:
    """The call returns positions that are finite and inside ``bounds`` (or raises a ValueError: also fine).

    ``real``: ``(N,)`` bool, the particles to look at (padding rows are meaningless).
    """
    try:
        out = call()
    except ValueError as error:
        return True, f"ValueError: {str(error)[:300]}"
    except Exception as error:
        return False, f"{type(error).__name__}: {str(error)[:300]}"
    x = np.asarray(out[0] if isinstance(out, tuple) else out)
    if real is not None:
        x = x[..., real, :]
    b = np.asarray(bounds)
    finite = bool(np.isfinite(x).all())
    inside = finite and bool(np.all((x >= b[:, 0] - 1e-6) & (x <= b[:, 1] + 1e-6)))
    return finite and inside, f"returned shape {x.shape}, finite {finite}, inside the box {inside}"


def params_equal(run_a: Path, run_b: Path) -> tuple[bool, str]:
    """Exported models of two runs: equal to the resume test's tolerance (rtol 1e-6, atol 1e-7)."""
    import jax

    from dispgns.training.checkpoint import load_model

    a = jax.tree_util.tree_leaves(load_model(run_a / "model")[0])
    b = jax.tree_util.tree_leaves(load_model(run_b / "model")[0])
    worst = max(float(np.max(np.abs(np.asarray(x) - np.asarray(y)))) for x, y in zip(a, b))
    close = all(np.allclose(np.asarray(x), np.asarray(y), rtol=1e-6, atol=1e-7) for x, y in zip(a, b))
    return close, f"max |difference| of the parameters {worst:.3g}"


def no_duplicate_records(run: Path) -> bool:
    steps = [(r["kind"], r["step"]) for r in map(json.loads, (run / "log.jsonl").read_text().splitlines())]
    return len(steps) == len(set(steps))


@contextlib.contextmanager
def read_only_mount(path: Path, size: str = "4m"):
    """A small tmpfs at ``path``, yielded writable; ``remount()`` turns it read-only."""
    path.mkdir(parents=True, exist_ok=True)
    subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)], check=True)
    try:
        yield lambda: subprocess.run(["mount", "-o", "remount,ro", str(path)], check=True)
    finally:
        subprocess.run(["umount", str(path)], check=False)


def can_mount() -> bool:
    return os.geteuid() == 0 and shutil.which("mount") is not None


# ----------------------------------------------------------------------------- api


def api_cases(trial: Trial, work: Path) -> None:
    import jax
    import jax.numpy as jnp

    import dispgns
    from dispgns.data import load_dataset

    _, splits = load_dataset(work / "tiny", ["test"])
    truth = splits["test"][0]
    params, model_config, _ = dispgns.load_pretrained()
    c = model_config.input_sequence_length
    bounds = np.asarray(model_config.bounds)
    window, radius = truth.position[:c].copy(), truth.radius.copy()

    def roll(x=None, a=None, n=3, **kw):
        return lambda: dispgns.rollout(
            params, window if x is None else x, radius if a is None else a, n, model_config=model_config, **kw
        )

    def edited(index, value, frame=-1):
        x = window.copy()
        x[(frame, *index)] = value
        return x

    def radii(index, value):
        a = radius.copy()
        a[index] = value
        return a

    refuse = "ValueError naming the argument and the particle"
    ok = "finite positions inside the model's bounds"
    cases = [
        ("rollout: NaN position", refuse, roll(edited((5, 0), np.nan)), ["positions", "finite", "particle 5"]),
        ("rollout: inf position", refuse, roll(edited((7, 1), np.inf)), ["positions", "finite", "particle 7"]),
        ("rollout: -inf in the oldest frame", refuse, roll(edited((0, 1), -np.inf, 0)), ["positions", "finite"]),
        ("rollout: metres instead of units", refuse, roll(window * 0.1, radius * 0.1), ["metres", "divide"]),
        ("rollout: particle outside the box", refuse, roll(edited((3, 0), 1.5)), ["particle 3", "outside"]),
        ("rollout: box 3x larger than bounds", refuse, roll(window * 3), ["outside", "model's bounds"]),
        ("rollout: just beyond the wall", refuse, roll(edited((2, 1), -1.0001)), ["particle 2", "outside"]),
        ("rollout: zero particles", refuse, roll(window[:, :0], radius[:0]), ["no particles"]),
        ("rollout: negative radius", refuse, roll(a=radii(4, -0.03)), ["radius", "particle 4"]),
        ("rollout: zero radius", refuse, roll(a=radii(0, 0.0)), ["radius", "particle 0"]),
        ("rollout: NaN radius", refuse, roll(a=radii(1, np.nan)), ["radius", "particle 1"]),
        ("rollout: radius of the wrong shape", refuse, roll(a=radius[:-1]), ["radius", "shape"]),
        ("rollout: window one frame short", refuse, roll(window[1:]), ["positions", "shape"]),
        ("rollout: 3-D positions, 2-D model", refuse, roll(np.concatenate([window, window[..., :1]], -1)), ["shape"]),
        ("rollout: n_steps = 0", refuse, roll(n=0), ["n_steps"]),
        ("rollout: n_steps = 2.5", refuse, roll(n=2.5), ["n_steps"]),
        ("rollout: mask of the wrong shape", refuse, roll(mask=np.ones(3, bool)), ["mask", "shape"]),
    ]
    for name, expected, call, words in cases:
        trial.run("api", name, expected, lambda call=call, words=words: raises_value_error(call, words))

    x = window.copy()
    x[:, 1] = x[:, 0]  # two coincident particles: the network takes overlaps, never NaN
    padding = np.arange(radius.size) != 1
    oks = [
        ("rollout: a valid window", roll()),
        ("rollout: python lists", roll(window.tolist(), radius.tolist())),
        ("rollout: float64 inputs", roll(window.astype(np.float64), radius.astype(np.float64))),
        ("rollout: a centre exactly on the wall", roll(edited((2, 1), -1.0))),
        ("rollout: coincident particles", roll(x)),
    ]
    for name, call in oks:
        trial.run("api", name, ok, lambda call=call: finite_inside(call, bounds))
    trial.run(
        "api",
        "rollout: NaN in a masked padding row",
        ok + " for the real particles",
        lambda: finite_inside(roll(edited((1, 0), np.nan), mask=padding), bounds, real=padding),
    )

    def traced():
        return jax.jit(lambda w: dispgns.rollout(params, w, radius, 2, model_config=model_config))(window)

    trial.run(
        "api",
        "rollout under jit (traced input)",
        "ValueError naming the pure core",
        lambda: raises_value_error(traced, ["rollout_scan"]),
    )

    def batch_bad():
        xs = np.stack([window, window])
        xs[1, -1, 6, 0] = 9.0
        return dispgns.rollout_batch(params, xs, np.stack([radius, radius]), 2, model_config=model_config)

    trial.run(
        "api", "rollout_batch: one bad trajectory", refuse, lambda: raises_value_error(batch_bad, ["trajectory 1"])
    )
    for name, fn in (
        ("predict_acceleration", dispgns.predict_acceleration),
        ("predict_position", dispgns.predict_position),
    ):
        trial.run(
            "api",
            f"{name}: NaN position",
            refuse,
            lambda fn=fn: raises_value_error(
                lambda: fn(params, edited((5, 0), np.nan), radius, model_config=model_config), ["finite"]
            ),
        )

    # The physics, in m.
    config = dispgns.PhysicsConfig()
    x0 = np.array([[-0.05, 0.0], [0.0, 0.0], [0.05, 0.0]])
    v0, a0 = np.zeros_like(x0), np.full(3, 3e-3)

    def sim(x=x0, v=v0, a=a0, n=3, **kw):
        return lambda: dispgns.simulate(x, v, a, config, n_frames=n, **kw)

    def put(array, index, value):
        array = np.array(array, dtype=float)
        array[index] = value
        return array

    half = config.half_sizes(2)[0]
    box = np.array([[-half, half]] * 2)
    physics = [
        ("simulate: one NaN position", sim(put(x0, (1, 0), np.nan)), ["x0", "finite", "particle 1"]),
        ("simulate: inf velocity", sim(v=put(v0, (2, 1), np.inf)), ["v0", "finite"]),
        ("simulate: negative radius", sim(a=put(a0, 0, -3e-3)), ["radius", "particle 0"]),
        ("simulate: zero radius", sim(a=put(a0, 2, 0.0)), ["radius", "particle 2"]),
        ("simulate: particle at 0.5 m in a 0.1 m box", sim(put(x0, (0, 0), 0.5)), ["x0", "particle 0", "box"]),
        ("simulate: normalised units (x10)", sim(x0 * 10, a=a0 * 10), ["x0", "outside"]),
        ("simulate: coincident particles", sim(put(x0, (1, 0), -0.05)), ["overlap", "particles 0 and 1"]),
        ("simulate: deep overlap", sim(put(x0, (1, 0), 0.049)), ["overlap"]),
        ("simulate: zero particles", sim(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0)), ["no particles"]),
        ("simulate: radius of the wrong shape", sim(a=a0[:2]), ["radius", "shape"]),
        ("simulate: n_frames = 0", sim(n=0), ["n_frames"]),
        ("simulate: a particle wider than the box", sim(x0[:1], v0[:1], np.array([0.15])), ["radius", "half-size"]),
    ]
    for name, call, words in physics:
        trial.run("api", name, refuse, lambda call=call, words=words: raises_value_error(call, words))
    trial.run("api", "simulate: a valid state", "finite, inside the box", lambda: finite_inside(sim(n=20), box))
    trial.run(
        "api",
        "simulate: 30 m/s initial velocity",
        "finite, inside the box (or a clear ValueError)",
        lambda: finite_inside(sim(v=np.full_like(v0, 30.0), n=20), box),
    )

    # Initial states.
    key = jax.random.key(0)

    def sample(radii_choices, **kw):
        return lambda: dispgns.sample_initial_state(key, radii_choices, config, **kw)

    initial = [
        ("sample_initial_state([0.09]): radius too large", sample([0.09]), ["too large"]),
        ("sample_initial_state([1e-5]): tens of millions", sample([1e-5]), ["max_particles"]),
        ("sample_initial_state([]): no radii", sample([]), ["radii_choices"]),
        ("sample_initial_state([nan])", sample([np.nan]), ["radii_choices"]),
        ("sample_initial_state([-1e-3])", sample([-1e-3]), ["radii_choices"]),
        ("sample_initial_state([3.0]): mm for m", sample([3.0]), ["radius"]),
        ("sample_initial_state: n_particles = 0", sample([3e-3], n_particles=0), ["n_particles"]),
        ("sample_initial_state: n_particles = 2.5", sample([3e-3], n_particles=2.5), ["n_particles"]),
        ("sample_initial_state: start height outside", sample([3e-3], start_height=0.5), ["start_height"]),
        ("sample_initial_state: 2-D radii array", sample([[3e-3, 4e-3]]), ["radii_choices"]),
    ]
    for name, call, words in initial:

        def timed(call=call, words=words):
            start = time.perf_counter()
            passed, observed = raises_value_error(call, words)
            took = time.perf_counter() - start
            return passed and took < 30, f"{observed} ({took:.1f} s)"

        trial.run("api", name, refuse + ", up front", timed)

    def placed(radii_choices, seeds, **kw):
        from dispgns.physics import PlacementError
        from dispgns.validation import check_overlaps

        outcomes = []
        for seed in seeds:
            try:
                state = dispgns.sample_initial_state(jax.random.key(seed), radii_choices, config, **kw)
            except (ValueError, PlacementError) as error:  # must say what to pass
                outcomes.append(("n_particles" in str(error), f"seed {seed}: {str(error)[:160]}"))
                continue
            x = np.asarray(state.position)
            inside = bool(np.isfinite(x).all() and np.all(np.abs(x) <= half))
            try:
                check_overlaps(x, np.asarray(state.radius), "position", fraction=0.999)
                apart = True
            except ValueError:
                apart = False
            outcomes.append((inside and apart, f"seed {seed}: {x.shape[0]} particles, inside {inside}, apart {apart}"))
        return all(o[0] for o in outcomes), "; ".join(o[1] for o in outcomes)

    trial.run(
        "api",
        "sample_initial_state: the paper's radii",
        "finite, inside, non-overlapping",
        lambda: placed([2.25e-3, 3.25e-3, 3.75e-3, 4.75e-3], [0, 1]),
    )
    trial.run(
        "api",
        "sample_initial_state([3e-3]): one radius",
        "a state, or an error saying to pass n_particles",
        lambda: placed([3e-3], [0, 1, 2]),
    )
    trial.run(
        "api",
        "sample_initial_state: 3-D",
        "finite, inside, non-overlapping",
        lambda: placed([4e-3, 5e-3], [0], dim=3, n_particles=50),
    )

    def jitted_checkify():
        from jax.experimental import checkify

        from dispgns.validation import checkify_inputs

        def f(x, a):
            checkify_inputs(x, a, bounds=model_config.bounds)
            return x

        err, _ = jax.jit(checkify.checkify(f))(jnp.asarray(edited((5, 0), np.nan)[-1]), jnp.asarray(radius))
        try:
            err.throw()
        except Exception as error:
            return "finite" in str(error), f"{type(error).__name__}: {str(error)[:200]}"
        return False, "no error under checkify"

    trial.run("api", "checkify_inputs under jit: NaN", "a checkify error naming the check", jitted_checkify)


# ----------------------------------------------------------------------------- cli


def cli_cases(trial: Trial, work: Path) -> None:
    tiny = work / "tiny"
    out = work / "cli-out"
    afile = work / "a-file"
    afile.write_text("not a directory\n")
    yaml_bad = work / "bad.yaml"
    yaml_bad.write_text("model: [unclosed\n")
    yaml_list = work / "list.yaml"
    yaml_list.write_text("- 1\n- 2\n")
    yaml_field = work / "field.yaml"
    yaml_field.write_text("model:\n  latent_size: -3\n")
    not_npz = work / "not.npz"
    not_npz.write_text("hello")
    cases = [
        ("train: --steps -5", ["train", "--data", tiny, "--out", out, "--steps", "-5"], ["num_steps"]),
        (
            "train: --set model.latent_size=abc",
            ["train", "--data", tiny, "--out", out, "--set", "model.latent_size=abc"],
            ["latent_size"],
        ),
        (
            "train: --set without a section",
            ["train", "--data", tiny, "--out", out, "--set", "latent=3"],
            ["SECTION.FIELD"],
        ),
        ("train: --set unknown field", ["train", "--data", tiny, "--out", out, "--set", "model.nope=1"], ["nope"]),
        (
            "train: --config missing.yaml",
            ["train", "--data", tiny, "--out", out, "--config", work / "missing.yaml"],
            ["missing.yaml"],
        ),
        ("train: --config malformed YAML", ["train", "--data", tiny, "--out", out, "--config", yaml_bad], ["YAML"]),
        ("train: --config a YAML list", ["train", "--data", tiny, "--out", out, "--config", yaml_list], ["mapping"]),
        (
            "train: --config invalid field value",
            ["train", "--data", tiny, "--out", out, "--config", yaml_field],
            ["latent_size"],
        ),
        ("train: --config unknown name", ["train", "--data", tiny, "--out", out, "--config", "gpu"], ["cpu"]),
        ("train: --data missing", ["train", "--data", work / "nowhere", "--out", out], ["nowhere"]),
        ("train: --resume with no run", ["train", "--data", tiny, "--out", out, "--resume"], ["no run to resume"]),
        ("train: --out is a file", ["train", "--data", tiny, "--out", afile], ["a-file"]),
        ("evaluate: --splits nosuch", ["evaluate", "--data", tiny, "--out", out, "--splits", "nosuch"], ["nosuch"]),
        (
            "evaluate: --model missing",
            ["evaluate", "--data", tiny, "--out", out, "--model", work / "nomodel"],
            ["nomodel"],
        ),
        ("evaluate: --best without --model", ["evaluate", "--data", tiny, "--out", out, "--best"], ["--best"]),
        ("evaluate: --frames 3", ["evaluate", "--data", tiny, "--out", out, "--frames", "3"], ["frames"]),
        ("evaluate: --out is a file", ["evaluate", "--data", tiny, "--out", afile], ["a-file"]),
        ("render: --index 99", ["render", "--data", tiny, "--split", "test", "--index", "99", "--out", out], ["99"]),
        (
            "render: --out pics.gif",
            ["render", "--data", tiny, "--split", "test", "--out", work / "pics.gif"],
            ["directory"],
        ),
        (
            "render: --predictions missing",
            ["render", "--data", tiny, "--predictions", work / "p.h5", "--out", out],
            ["p.h5"],
        ),
        ("demo: --radii a,b", ["demo", "--radii", "a,b", "--out", out], ["radii"]),
        ("demo: --radii -3", ["demo", "--radii=-3", "--out", out], ["radii"]),
        ("demo: --radii 95 (mm, larger than the box)", ["demo", "--radii", "95", "--out", out], ["radi"]),
        ("demo: --frames 0", ["demo", "--frames", "0", "--out", out], ["frames"]),
        ("demo: --out is a file", ["demo", "--out", afile], ["a-file"]),
        ("generate: --preset nosuch", ["generate", "--preset", "nosuch", "--out", out], ["nosuch"]),
        ("generate: --seed -1", ["generate", "--preset", "tiny", "--seed", "-1", "--out", out], ["seed"]),
        ("generate: --frames 1", ["generate", "--preset", "tiny", "--frames", "1", "--out", out], ["frames"]),
        ("generate: --radii 0", ["generate", "--preset", "tiny", "--radii", "0", "--out", out], ["radi"]),
        ("generate: into an existing dataset", ["generate", "--preset", "tiny", "--out", tiny], ["--overwrite"]),
        ("export: unknown format", ["export", "nosuch", tiny, "--out", out], ["nosuch"]),
        (
            "export gsd: --index 99",
            ["export", "extxyz", tiny, "--split", "test", "--index", "99", "--out", out],
            ["99"],
        ),
        ("import-npz: not an npz", ["import-npz", not_npz, "--out", out, "--trust-pickle"], ["not.npz"]),
        ("import-npz: without --trust-pickle", ["import-npz", not_npz, "--out", out], ["trust-pickle"]),
        ("import extxyz: missing file", ["import", "extxyz", work / "none.extxyz", "--out", out], ["none.extxyz"]),
        ("no subcommand", [], []),
        ("unknown subcommand", ["fly"], ["fly"]),
    ]
    for name, argv, words in cases:

        def check(argv=argv, words=words):
            shutil.rmtree(out, ignore_errors=True)
            proc = cli(argv)
            if not argv:  # help text and status 2
                return proc.returncode == 2 and "Traceback" not in proc.stderr, f"exit {proc.returncode}"
            return clean_failure(proc, words=words, absent=[out])

        trial.run("cli", name, "exit 2, one error line, nothing written", check)


# ----------------------------------------------------------------------------- corrupt files


def corrupt_cases(trial: Trial, work: Path) -> None:
    import h5py

    tiny = work / "tiny"
    out = work / "corrupt-out"

    def damaged(name, damage):
        target = work / "corrupt" / name
        shutil.rmtree(target, ignore_errors=True)
        shutil.copytree(tiny, target)
        damage(target)
        return target

    def truncate(path, fraction=0.5):
        data = path.read_bytes()
        path.write_bytes(data[: int(len(data) * fraction)])

    def flip_bit(directory):
        path = directory / "test.h5"
        with h5py.File(path, "r") as f:
            key = next(iter(f))
            dataset = f[key]["position"]
            offset = dataset.id.get_offset()
            size = dataset.id.get_storage_size()
        if offset is None:  # chunked: find a chunk
            with h5py.File(path, "r") as f:
                info = f[key]["position"].id.get_chunk_info(0)
                offset, size = info.byte_offset, info.size
        data = bytearray(path.read_bytes())
        data[offset + size // 2] ^= 0x10
        path.write_bytes(bytes(data))

    def nan_position(directory):
        with h5py.File(directory / "test.h5", "r+") as f:
            key = next(iter(f))
            x = f[key]["position"][...]
            x[3, 2, 0] = np.nan
            del f[key]["position"]
            f[key].create_dataset("position", data=x)

    def wrong_radius_shape(directory):
        with h5py.File(directory / "test.h5", "r+") as f:
            key = next(iter(f))
            a = f[key]["radius"][...]
            del f[key]["radius"]
            f[key].create_dataset("radius", data=a[:-2])

    def negative_radius(directory):
        with h5py.File(directory / "test.h5", "r+") as f:
            key = next(iter(f))
            a = f[key]["radius"][...]
            a[1] = -a[1]
            del f[key]["radius"]
            f[key].create_dataset("radius", data=a)

    def metadata_edit(change):
        def edit(directory):
            values = json.loads((directory / "metadata.json").read_text())
            change(values)
            (directory / "metadata.json").write_text(json.dumps(values))

        return edit

    damages = [
        ("test.h5 truncated to half", lambda d: truncate(d / "test.h5"), ["test.h5"]),
        ("test.h5 empty", lambda d: (d / "test.h5").write_bytes(b""), ["test.h5"]),
        ("test.h5 random bytes", lambda d: (d / "test.h5").write_bytes(os.urandom(4096)), ["test.h5"]),
        ("test.h5 one flipped bit in positions", flip_bit, ["test.h5"]),
        ("test.h5 NaN in stored positions", nan_position, ["test.h5", "position"]),
        ("test.h5 radius of the wrong length", wrong_radius_shape, ["test.h5", "radius"]),
        ("test.h5 a negative radius", negative_radius, ["test.h5", "radius"]),
        ("test.h5 deleted", lambda d: (d / "test.h5").unlink(), ["test.h5"]),
        ("metadata.json deleted", lambda d: (d / "metadata.json").unlink(), ["metadata.json"]),
        ("metadata.json not JSON", lambda d: (d / "metadata.json").write_text("{oops"), ["metadata.json"]),
        ("metadata.json a list", lambda d: (d / "metadata.json").write_text("[]"), ["metadata.json"]),
        ("metadata.json dim = 7", metadata_edit(lambda v: v.update(dim=7)), ["metadata.json", "dim"]),
        ("metadata.json bounds a string", metadata_edit(lambda v: v.update(bounds="box")), ["metadata.json", "bounds"]),
        ("metadata.json dt negative", metadata_edit(lambda v: v.update(dt=-1.0)), ["metadata.json"]),
        ("metadata.json without dim", metadata_edit(lambda v: v.pop("dim", None)), ["metadata.json", "dim"]),
    ]
    for name, damage, words in damages:

        def check(name=name, damage=damage, words=words):
            shutil.rmtree(out, ignore_errors=True)
            data = damaged(name.split()[0].replace(".", "_") + str(abs(hash(name)) % 1000), damage)
            proc = cli(["evaluate", "--data", data, "--splits", "test", "--out", out, "--no-progress", "--no-chaos"])
            passed, observed = clean_failure(proc, words=words, absent=[out])
            if passed and str(data) not in proc.stderr and "metadata.json deleted" not in name:
                return False, observed + " (the file is not named with its directory)"
            return passed, observed

        trial.run("corrupt", f"evaluate on a dataset with {name}", "exit 2, one line naming the file", check)

    # Damaged exported models.
    shutil.rmtree(work / "corrupt-model", ignore_errors=True)
    from dispgns.pretrained import pretrained_path

    for name, damage in (
        ("params.msgpack truncated", lambda d: truncate(d / "params.msgpack")),
        ("params.msgpack garbage", lambda d: (d / "params.msgpack").write_bytes(os.urandom(1000))),
        ("model.json not JSON", lambda d: (d / "model.json").write_text("{")),
        ("model.json of another network", lambda d: _edit_model_json(d)),
    ):

        def check(name=name, damage=damage):
            shutil.rmtree(out, ignore_errors=True)
            model = work / "corrupt-model" / str(abs(hash(name)) % 10000)
            shutil.copytree(pretrained_path(), model)
            damage(model)
            proc = cli(["render", "--data", tiny, "--split", "test", "--model", model, "--out", out, "--no-mp4"])
            return clean_failure(proc, words=[str(model)], absent=[out])

        trial.run("corrupt", f"render with a model whose {name}", "exit 2, one line naming the file", check)


def _edit_model_json(directory: Path) -> None:
    values = json.loads((directory / "model.json").read_text())
    values["model"]["latent_size"] = 32
    (directory / "model.json").write_text(json.dumps(values))


# ----------------------------------------------------------------------------- runs: a reference and helpers


def reference_run(work: Path) -> Path:
    run = work / "reference"
    if not (run / "model" / "model.json").is_file():
        shutil.rmtree(run, ignore_errors=True)
        proc = cli(["train", "--data", work / "tiny", "--out", run, *TINY_TRAIN, "--steps", STEPS])
        if proc.returncode != 0:
            raise RuntimeError(f"the reference run failed: {proc.stderr[-2000:]}")
    return run


def resume(run: Path, work: Path) -> subprocess.CompletedProcess:
    return cli(["train", "--data", work / "tiny", "--out", run, *TINY_TRAIN, "--steps", STEPS, "--resume"])


def checkpoint_cases(trial: Trial, work: Path) -> None:
    reference = reference_run(work)

    def delete_state(path):
        shutil.rmtree(path / "state")

    def corrupt_metadata(path):
        for name in ("_CHECKPOINT_METADATA", "state/_METADATA"):
            if (path / name).exists():
                (path / name).write_text("{not json")

    def truncate_chunks(path):
        for file in (path / "state").rglob("*"):
            if file.is_file() and "ocdbt" in str(file.relative_to(path)) and file.stat().st_size > 64:
                file.write_bytes(file.read_bytes()[:32])

    def garbage_chunks(path):
        for file in (path / "state").rglob("*"):
            if file.is_file() and "d/" in str(file.relative_to(path)):
                file.write_bytes(os.urandom(file.stat().st_size))

    def delete_extra(path):
        shutil.rmtree(path / "extra", ignore_errors=True)

    for name, damage in (
        ("_METADATA corrupt", corrupt_metadata),
        ("state/ deleted", delete_state),
        ("array chunks truncated", truncate_chunks),
        ("array chunks overwritten", garbage_chunks),
        ("extra/ deleted", delete_extra),
    ):

        def check(name=name, damage=damage):
            run = work / "checkpoint" / name.split()[0].strip("_/")
            shutil.rmtree(run, ignore_errors=True)
            shutil.copytree(reference, run, ignore=shutil.ignore_patterns("model"))
            latest = max(int(p.name) for p in (run / "checkpoints").iterdir() if p.name.isdigit())
            damage(run / "checkpoints" / str(latest))
            proc = resume(run, work)
            said = f"checkpoints/{latest}" in proc.stderr and "intact" in proc.stderr
            crash = [w for w in CRASH_WORDS + INTERNAL_WORDS if w in proc.stderr]
            if proc.returncode != 0:
                return False, f"exit {proc.returncode}: {proc.stderr.strip()[-400:]}"
            equal, detail = params_equal(run, reference)
            lines = [line for line in proc.stderr.splitlines() if "damaged" in line or "intact" in line]
            return said and equal and not crash and no_duplicate_records(run), f"{lines}; {detail}; crash {crash}"

        trial.run("checkpoint", f"--resume with the latest checkpoint's {name}", "falls back, says so, exact", check)

    def damaged_best():
        run = work / "checkpoint" / "best"
        shutil.rmtree(run, ignore_errors=True)
        shutil.copytree(reference, run, ignore=shutil.ignore_patterns("model"))
        for step in (run / "best").iterdir():
            if step.name.isdigit():
                shutil.rmtree(step / "state")
        out = work / "checkpoint" / "best-eval"
        proc = cli(["evaluate", "--model", run, "--best", "--data", work / "tiny", "--splits", "test", "--out", out])
        return clean_failure(proc, words=["best"], absent=[out])

    trial.run("checkpoint", "evaluate --best with a damaged best checkpoint", "exit 2, one line", damaged_best)

    def all_damaged():
        run = work / "checkpoint" / "all"
        shutil.rmtree(run, ignore_errors=True)
        shutil.copytree(reference, run, ignore=shutil.ignore_patterns("model"))
        for step in (run / "checkpoints").iterdir():
            if step.name.isdigit():
                shutil.rmtree(step / "state")
        return clean_failure(resume(run, work), words=["cannot resume"])

    trial.run("checkpoint", "--resume with every checkpoint damaged", "exit 2, one line", all_damaged)


# ----------------------------------------------------------------------------- read-only outputs


def readonly_cases(trial: Trial, work: Path) -> None:
    tiny = work / "tiny"
    blocker = work / "blocker"
    blocker.write_text("a file where a directory would go\n")
    under_file = [
        ("generate", ["generate", "--preset", "tiny", "--frames", "8", "--out", blocker / "data"]),
        ("train", ["train", "--data", tiny, "--out", blocker / "run", "--steps", "2", *TINY_TRAIN]),
        ("evaluate", ["evaluate", "--data", tiny, "--splits", "test", "--frames", "10", "--out", blocker / "ev"]),
        ("render", ["render", "--data", tiny, "--split", "test", "--out", blocker / "pics", "--no-mp4"]),
        ("demo", ["demo", "--frames", "20", "--out", blocker / "demo", "--no-mp4"]),
        ("export", ["export", "extxyz", tiny, "--split", "test", "--out", blocker / "x"]),
    ]
    for name, argv in under_file:
        trial.run(
            "readonly",
            f"{name} --out below a file",
            "exit 2, one line naming the path",
            lambda argv=argv: clean_failure(cli(argv), words=[str(blocker)]),
        )
    if not can_mount():
        trial.record("readonly", "read-only file system", "skipped", True, "skipped: not root or no mount")
        return
    mount = work / "ro"
    with read_only_mount(mount) as remount:
        remount()
        for name, argv in under_file:
            argv = [str(a).replace(str(blocker), str(mount)) for a in argv]
            trial.run(
                "readonly",
                f"{name} --out on a read-only file system",
                "exit 2, one line naming the path",
                lambda argv=argv: clean_failure(cli(argv), words=[str(mount)]),
            )
    with read_only_mount(mount, size="64k") as remount:
        full = ["generate", "--preset", "tiny", "--out", mount / "data"]
        trial.run(
            "readonly",
            "generate onto a file system that fills up",
            "exit 2, one line, nothing half-written",
            lambda: _full_disk(cli(full), mount),
        )


def _full_disk(proc, mount: Path) -> tuple[bool, str]:
    passed, observed = clean_failure(proc, words=["data"])
    left = sorted(p.name for p in mount.iterdir())
    return passed and not left, f"{observed}; left on the file system: {left}"


# ----------------------------------------------------------------------------- signals


def wait_for(proc, condition, timeout=600, poll=0.005) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            return False
        if condition():
            return True
        time.sleep(poll)
    return False


def usual_status(returncode: int, signum: int) -> bool:
    """The status a shell would report for ``signum`` (128 + signum): exited with it after cleaning up, or killed
    by the signal itself (before the command installed its handler, e.g. during start-up); 0 when the signal came
    after the run had finished. An abort (-6) or a segmentation fault (-11) is not."""
    return returncode in (128 + signum, -signum, 0)


# The commands started by start() and not yet seen to end.
_children: list[subprocess.Popen] = []


def start(argv) -> subprocess.Popen:
    proc = subprocess.Popen(
        [sys.executable, "-m", "dispgns", *map(str, argv)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    _children.append(proc)
    return proc


def stop_children() -> None:
    """Kill (SIGKILL) and reap every command start() began that still runs: a case's timeout ends its child too."""
    while _children:
        proc = _children.pop()
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


def has(path: Path, pattern: str) -> bool:
    try:
        return any(path.glob(pattern))
    except OSError:
        return False


def signal_cases(trial: Trial, work: Path) -> None:
    reference = reference_run(work)
    tiny = work / "tiny"
    # When to signal a training run, as a condition on its directory.
    moments = {
        "start-up": lambda run: (run / "config.json").is_file() or has(run, ".config.json.*"),
        "training": lambda run: (run / "checkpoints" / "20").is_dir(),
        "checkpointing": lambda run: has(run / "checkpoints", "*orbax-checkpoint-tmp*"),
        "export": lambda run: has(run, ".model*tmp*") or has(run, "model.*") or (run / "model").is_dir(),
    }
    signals = {"SIGKILL": signal.SIGKILL, "SIGINT": signal.SIGINT, "SIGTERM": signal.SIGTERM}
    for moment, condition in moments.items():
        for sig_name, signum in signals.items():

            def check(moment=moment, condition=condition, sig_name=sig_name, signum=signum):
                run = work / "signals" / f"{moment}-{sig_name}"
                for _ in range(3):  # a short moment (the export) can pass between two looks on a loaded machine
                    shutil.rmtree(run, ignore_errors=True)
                    proc = start(["train", "--data", tiny, "--out", run, *TINY_TRAIN, "--steps", STEPS])
                    reached = wait_for(proc, lambda: condition(run))
                    if reached:
                        break
                    proc.wait(timeout=600)
                if not reached:
                    return False, f"moment not caught in 3 tries (the run ended with {proc.returncode})"
                proc.send_signal(signum)
                _, err = proc.communicate(timeout=600)
                expected = -signal.SIGKILL if signum == signal.SIGKILL else 128 + signum
                crash = [w for w in CRASH_WORDS if w in err]
                status_ok = usual_status(proc.returncode, signum)
                if not (run / "config.json").is_file():  # killed before the run existed: start anew
                    again = cli(["train", "--data", tiny, "--out", run, *TINY_TRAIN, "--steps", STEPS, "--overwrite"])
                else:
                    again = resume(run, work)
                if again.returncode != 0:
                    return False, f"exit {proc.returncode}, then the next run failed: {again.stderr.strip()[-400:]}"
                equal, detail = params_equal(run, reference)
                leftovers = [p.name for p in run.rglob("*") if ".tmp" in p.name or "orbax-checkpoint-tmp" in p.name]
                unique = no_duplicate_records(run)
                said = [line for line in again.stderr.splitlines() if "removed" in line]
                passed = status_ok and not crash and equal and not leftovers and unique
                return passed, (
                    f"exit {proc.returncode} (expected {expected}); crash {crash}; "
                    f"next run: {said or 'nothing removed'}; {detail}; leftovers {leftovers}; unique records {unique}"
                )

            trial.run(
                "signals",
                f"train: {sig_name} at {moment}",
                "usual status, no crash, leftovers removed, exact resume",
                check,
            )

    # generate and evaluate: killed half-way, then run again.
    for sig_name, signum in signals.items():

        def check_generate(sig_name=sig_name, signum=signum):
            out = work / "signals" / f"generate-{sig_name}"
            shutil.rmtree(out, ignore_errors=True)
            argv = ["generate", "--preset", "tiny", "--seed", "0", "--out", out]
            proc = start(argv)
            time.sleep(8)  # mid-simulation on this machine (the whole command takes ~20 s)
            proc.send_signal(signum)
            _, err = proc.communicate(timeout=300)
            crash = [w for w in CRASH_WORDS if w in err]
            nothing = not out.exists() or not any(out.iterdir())
            again = cli(argv)
            if again.returncode != 0:
                return False, f"exit {proc.returncode}; the next run failed: {again.stderr.strip()[-300:]}"
            same = _same_dataset(out, tiny)
            left = [p.name for p in out.parent.iterdir() if p.name.startswith(f".{out.name}") or ".tmp" in p.name]
            expected = -signal.SIGKILL if signum == signal.SIGKILL else 128 + signum
            passed = usual_status(proc.returncode, signum) and not crash and nothing and same and not left
            return passed, (
                f"exit {proc.returncode} (expected {expected}); crash {crash}; output absent after the kill {nothing}; "
                f"rerun identical {same}; leftovers {left}"
            )

        trial.run(
            "signals",
            f"generate: {sig_name} half-way",
            "usual status, nothing written, rerun identical",
            check_generate,
        )

        def check_evaluate(sig_name=sig_name, signum=signum):
            out = work / "signals" / f"evaluate-{sig_name}"
            shutil.rmtree(out, ignore_errors=True)
            argv = ["evaluate", "--data", tiny, "--model", reference, "--out", out, "--no-progress"]
            proc = start(argv)
            time.sleep(10)
            proc.send_signal(signum)
            _, err = proc.communicate(timeout=300)
            crash = [w for w in CRASH_WORDS if w in err]
            nothing = not out.exists()
            again = cli(argv)
            left = [p.name for p in out.parent.iterdir() if p.name.startswith(f".{out.name}") or ".tmp" in p.name]
            expected = -signal.SIGKILL if signum == signal.SIGKILL else 128 + signum
            rerun_ok = again.returncode == 0
            passed = usual_status(proc.returncode, signum) and not crash and nothing and rerun_ok and not left
            return passed, (
                f"exit {proc.returncode} (expected {expected}); crash {crash}; output absent {nothing}; rerun exit "
                f"{again.returncode}; leftovers {left}"
            )

        trial.run(
            "signals", f"evaluate: {sig_name} half-way", "usual status, nothing written, rerun works", check_evaluate
        )


def _same_dataset(a: Path, b: Path) -> bool:
    from dispgns.data import load_dataset

    _, x = load_dataset(a)
    _, y = load_dataset(b)
    return all(
        np.array_equal(s.position, t.position) and np.array_equal(s.radius, t.radius)
        for split in x
        for s, t in zip(x[split], y[split])
    )


# ----------------------------------------------------------------------------- main


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, required=True, help="scratch directory (created; reused across runs)")
    parser.add_argument("--only", default=",".join(CATEGORIES), help=f"comma-separated categories of {CATEGORIES}")
    parser.add_argument(
        "--match", default="", help="only the cases whose name holds one of these comma-separated texts"
    )
    args = parser.parse_args()
    # A background job of a non-interactive shell starts with SIGINT ignored, and its children inherit that:
    # their "Ctrl-C" would be no signal at all. A handler (unlike SIG_IGN) is reset to the default by exec.
    signal.signal(signal.SIGINT, signal.default_int_handler)
    only = [c for c in args.only.split(",") if c]
    unknown = sorted(set(only) - set(CATEGORIES))
    if unknown:
        parser.error(f"unknown categories {unknown}; expected some of {CATEGORIES}")
    work = args.work.absolute()
    work.mkdir(parents=True, exist_ok=True)
    if not (work / "tiny" / "metadata.json").is_file():
        proc = cli(["generate", "--preset", "tiny", "--seed", "0", "--out", work / "tiny"])
        if proc.returncode != 0:
            print(proc.stderr, file=sys.stderr)
            return 1
    trial = Trial(work, [m for m in args.match.split(",") if m] or None)
    runners = dict(
        api=api_cases,
        cli=cli_cases,
        corrupt=corrupt_cases,
        checkpoint=checkpoint_cases,
        readonly=readonly_cases,
        signals=signal_cases,
    )
    for category in only:
        runners[category](trial, work)
    summary = {}
    for category in only:
        mine = [r for r in trial.results if r["category"] == category]
        summary[category] = dict(
            cases=len(mine), passed=sum(r["passed"] for r in mine), failed=sum(not r["passed"] for r in mine)
        )
    print(json.dumps({"summary": summary, "cases": trial.results}, indent=1))
    return 0 if all(r["passed"] for r in trial.results) else 1


if __name__ == "__main__":
    sys.exit(main())

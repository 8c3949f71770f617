"""Bad input at every public boundary: a clear error naming the argument, the particle and the range.

Table-driven: each case is (what the user did, the call, the exception type, key words of the message).
Every case fails before anything is compiled, so the whole table runs in a few seconds.
"""

import json
import os
import signal
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dispgns
from dispgns.model import ModelConfig, init_params
from dispgns.physics import PhysicsConfig, particle_count_range, sample_initial_state, simulate
from dispgns.simulator import predict_acceleration, predict_position, rollout, rollout_batch
from dispgns.validation import checkify_inputs

TINY = ModelConfig(latent_size=8, hidden_size=8, message_passing_steps=1)
C = TINY.input_sequence_length


def _window(n=4):
    """A valid (C, N, 2) window in normalised units: particles on a line, at rest, radius 0.03."""
    x = np.stack([np.linspace(-0.6, 0.6, n), np.full(n, -0.5)], axis=-1).astype(np.float32)
    return np.repeat(x[None], C, axis=0), np.full(n, 0.03, np.float32)


@pytest.fixture(scope="module")
def params():
    return init_params(jax.random.key(0), TINY)


def _with(index, value, frame=-1, n=4, radius=None):
    x, a = _window(n)
    if index is not None:
        x[frame, index[0], index[1]] = value
    if radius is not None:
        a = np.asarray(radius, np.float32)
    return x, a


def _metres():
    x, a = _window()
    return x * 0.1, a * 0.1


ROLLOUT_CASES = [
    ("nan position", lambda: _with((2, 0), np.nan), ["positions", "finite", "(5, 2)"]),
    ("inf position in an old frame", lambda: _with((1, 1), np.inf, frame=0), ["positions", "finite", "(0, 1)"]),
    ("zero radius", lambda: _with(None, 0, radius=[0.03, 0.0, 0.03, 0.03]), ["radius", "> 0", "particle 1"]),
    ("negative radius", lambda: _with(None, 0, radius=[0.03, 0.03, -0.03, 0.03]), ["radius", "particle 2"]),
    ("nan radius", lambda: _with(None, 0, radius=[np.nan, 0.03, 0.03, 0.03]), ["radius", "particle 0"]),
    ("outside the model's bounds", lambda: _with((3, 0), 1.7), ["positions", "particle 3", "model's bounds"]),
    ("box larger than the bounds", lambda: (_window()[0] * 3, _window()[1]), ["particle 0", "outside"]),
    ("metres instead of normalised units", _metres, ["metres", "normalised", "divide"]),
]


@pytest.mark.parametrize("call", ["rollout", "predict_acceleration", "predict_position"])
@pytest.mark.parametrize(("case", "make", "words"), ROLLOUT_CASES, ids=[c[0] for c in ROLLOUT_CASES])
def test_host_conveniences_of_the_learned_simulator_refuse_bad_states(params, call, case, make, words):
    x, a = make()
    with pytest.raises(ValueError) as info:
        if call == "rollout":
            rollout(params, x, a, 3, model_config=TINY)
        else:
            {"predict_acceleration": predict_acceleration, "predict_position": predict_position}[call](
                params, x, a, model_config=TINY
            )
    for word in words:
        assert word in str(info.value), (word, str(info.value))


def test_rollout_batch_names_the_trajectory_and_ignores_padding(params):
    x, a = _window()
    xs, as_ = np.stack([x, x]), np.stack([a, a])
    xs[1, -1, 2, 0] = 5.0
    with pytest.raises(ValueError, match=r"trajectory 1, particle 2"):
        rollout_batch(params, xs, as_, 2, model_config=TINY)
    # The same row as padding is never looked at (nor are padding NaNs).
    xs[1, :, 2] = np.nan
    mask = np.ones((2, 4), bool)
    mask[1, 2] = False
    out = rollout_batch(params, xs, as_, 2, model_config=TINY, mask=mask)
    assert np.isfinite(np.asarray(out)[1][:, [0, 1, 3]]).all()


def test_a_valid_state_passes_and_padding_nan_is_ignored(params):
    x, a = _window()
    x[:, 1] = np.nan
    a[1] = -1.0
    mask = np.array([True, False, True, True])
    out = np.asarray(rollout(params, x, a, 2, model_config=TINY, mask=mask))
    assert np.isfinite(out[:, mask]).all()


# ----------------------------------------------------------------------------- the physics


def _state(n=3):
    x = np.array([[-0.05, 0.0], [0.0, 0.0], [0.05, 0.0]])[:n]
    return x, np.zeros_like(x), np.full(n, 3e-3)


def _edit(position=None, velocity=None, radius=None):
    x, v, a = _state()
    for array, change in ((x, position), (v, velocity), (a, radius)):
        if change is not None:
            index, value = change
            array[index] = value
    return x, v, a


PHYSICS_CASES = [
    ("nan position", lambda: _edit(position=((1, 0), np.nan)), ["x0", "finite", "particle 1"]),
    ("inf velocity", lambda: _edit(velocity=((2, 1), np.inf)), ["v0", "finite", "particle 2"]),
    ("negative radius", lambda: _edit(radius=(0, -3e-3)), ["radius", "> 0", "particle 0"]),
    ("zero radius", lambda: _edit(radius=(2, 0.0)), ["radius", "particle 2"]),
    ("outside the box", lambda: _edit(position=((0, 0), 0.5)), ["x0", "particle 0", "box", "L = 0.1 m"]),
    ("normalised units", lambda: (_state()[0] * 10, _state()[1], _state()[2]), ["x0", "outside the box"]),
    ("coincident particles", lambda: _edit(position=((1, 0), -0.05)), ["particles 0 and 1", "overlap"]),
    ("deep overlap", lambda: _edit(position=((1, 0), 0.049)), ["particles 1 and 2", "overlap"]),
    ("no particles", lambda: (np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0)), ["no particles"]),
    ("a particle wider than the box", lambda: _edit(radius=(1, 0.15)), ["radius", "particle 1", "half-size 0.1"]),
]


@pytest.mark.parametrize(("case", "make", "words"), PHYSICS_CASES, ids=[c[0] for c in PHYSICS_CASES])
def test_simulate_refuses_bad_states(case, make, words):
    x, v, a = make()
    with pytest.raises(ValueError) as info:
        simulate(x, v, a, n_frames=2)
    for word in words:
        assert word in str(info.value), (word, str(info.value))


def test_simulate_batch_checks_only_real_particles():
    x, v, a = _state()
    x = np.stack([x, x])
    x[1, 2] = [0.5, 0.5]  # padding: never looked at
    mask = np.array([[True] * 3, [True, True, False]])
    out = dispgns.simulate_batch(x, np.zeros_like(x), np.stack([a, a]), mask, n_frames=2, save_every=1)
    assert np.isfinite(np.asarray(out)[:, :, :2]).all()
    x[0, 1] = [0.5, 0.5]
    with pytest.raises(ValueError, match=r"trajectory 0, particle 1"):
        dispgns.simulate_batch(x, np.zeros_like(x), np.stack([a, a]), mask, n_frames=2, save_every=1)


# ----------------------------------------------------------------------------- initial states

INITIAL_CASES = [
    ("radius too large for any particle", dict(radii_choices=[0.09]), ValueError, ["too large", "n_particles"]),
    ("tiny radius: millions of particles", dict(radii_choices=[1e-5]), ValueError, ["max_particles", "particles"]),
    ("explicit count beyond the guard", dict(radii_choices=[3e-3], n_particles=2_000_000), ValueError, ["2,000,000"]),
    ("zero count", dict(radii_choices=[3e-3], n_particles=0), ValueError, ["n_particles", ">= 1"]),
    ("nan radius", dict(radii_choices=[np.nan]), ValueError, ["radii_choices", "> 0"]),
    ("empty radii", dict(radii_choices=[]), ValueError, ["radii_choices"]),
]


@pytest.mark.parametrize(("case", "kwargs", "error", "words"), INITIAL_CASES, ids=[c[0] for c in INITIAL_CASES])
def test_sample_initial_state_refuses_up_front(case, kwargs, error, words):
    with pytest.raises(error) as info:
        sample_initial_state(jax.random.key(0), **kwargs)
    for word in words:
        assert word in str(info.value), (word, str(info.value))


@pytest.mark.parametrize(("dim", "half", "radius", "seeds"), [(2, 0.1, 3e-3, [0, 1, 2]), (3, 0.04, 4e-3, [0])])
def test_one_radius_places_with_the_count_capped_below_jamming(dim, half, radius, seeds):
    # One radius: the protocol's count (sized for square cells) fills 0.55 of the area with equal disks, beyond
    # where random placement jams; the count is capped at RANDOM_PACKING_LIMIT instead of failing every seed.
    config = PhysicsConfig(box_half_size=half)
    limit = dispgns.physics.initial.RANDOM_PACKING_LIMIT[dim]
    for seed in seeds:
        state = sample_initial_state(jax.random.key(seed), [radius], config, dim=dim)
        x, a = np.asarray(state.position, np.float64), np.asarray(state.radius, np.float64)
        protocol_low, _ = particle_count_range(state.start_height, radius, config, dim)
        low, high = particle_count_range(state.start_height, radius, config, dim, radii_choices=[radius])
        assert low <= len(a) <= high < protocol_low  # the cap binds, and the count is in its range
        region = (2 * half) ** (dim - 1) * (half - state.start_height)
        volume = len(a) * (np.pi * radius**2 if dim == 2 else 4 / 3 * np.pi * radius**3)
        assert volume / region <= limit
        gaps = np.linalg.norm(x[:, None] - x[None], axis=-1) - (a[:, None] + a[None]) + np.eye(len(a))
        assert gaps.min() >= -1e-7 and np.all(np.abs(x) <= half - a[:, None] + 1e-7)


def test_the_cap_leaves_the_paper_radii_lists_alone():
    # The paper's lists fill 0.29-0.39 of the area: their counts stay the protocol's (datasets unchanged).
    config = PhysicsConfig()
    for radii in ([2e-3, 2.5e-3, 3e-3, 3.5e-3, 4e-3, 4.5e-3, 5e-3], [2.75e-3, 4.25e-3], [4e-3, 6e-3, 8e-3, 10e-3]):
        for y0 in np.linspace(-0.025, 0, 11):
            assert particle_count_range(y0, max(radii), config) == particle_count_range(
                y0, max(radii), config, radii_choices=radii
            )


def test_a_drawn_count_that_does_not_place_says_what_to_pass():
    with pytest.raises(dispgns.physics.PlacementError, match=r"pass n_particles \(about \d+ fit here\)"):
        sample_initial_state(jax.random.key(0), [3e-3], start_height=-0.02, candidates=1, max_rounds=1)
    # A given count that fits does place.
    state = sample_initial_state(jax.random.key(0), [3e-3], n_particles=200, start_height=-0.02)
    assert state.position.shape == (200, 2)


def test_placement_in_blocks_is_the_placement_in_one_call():
    key = jax.random.key(3)
    radius = jnp.full((700,), 1.5e-3)  # more than one block of 512
    full = dispgns.physics.place_particles(key, radius, -0.05, PhysicsConfig())
    import dispgns.physics.initial as initial

    old = initial._BLOCK
    try:
        initial._BLOCK = 10_000
        one = dispgns.physics.place_particles(key, radius, -0.05, PhysicsConfig())
    finally:
        initial._BLOCK = old
    np.testing.assert_array_equal(np.asarray(full[0]), np.asarray(one[0]))
    np.testing.assert_array_equal(np.asarray(full[1]), np.asarray(one[1]))


def _ctrl_c_on():
    """In a child about to start: SIGINT back to its default (a background job of a non-interactive shell, pytest
    under ``nohup ... &`` included, starts with SIGINT ignored, and Python then never raises KeyboardInterrupt)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.mark.slow
def test_ctrl_c_stops_a_long_placement():
    code = textwrap.dedent(
        """
        import sys, jax
        from dispgns.physics import sample_initial_state
        print("start", flush=True)
        try:
            sample_initial_state(jax.random.key(0), [1e-4], max_particles=10**7)
        except KeyboardInterrupt:
            print("interrupted", flush=True)
            sys.exit(130)
        """
    )
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True, preexec_fn=_ctrl_c_on)
    assert proc.stdout.readline().strip() == "start"
    import time

    time.sleep(4.0)
    proc.send_signal(signal.SIGINT)
    try:
        out, _ = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 130 and "interrupted" in out


# ----------------------------------------------------------------------------- under jit: checkify


def test_checkify_inputs_reports_under_jit():
    from jax.experimental import checkify

    def checked(x, a):
        checkify_inputs(x, a, bounds=((-1.0, 1.0), (-1.0, 1.0)))
        return x * 2

    f = jax.jit(checkify.checkify(checked))
    x, a = _window()
    err, _ = f(x[-1], a)
    err.throw()  # nothing wrong
    x[-1, 2, 0] = 3.0
    err, _ = f(x[-1], a)
    with pytest.raises(Exception, match="outside the box"):
        err.throw()


# ----------------------------------------------------------------------------- files: checksums, leftovers


def _one_split(path):
    from dispgns.data import Trajectory, write_split

    x = np.tile(np.array([[[0.0, 0.0], [0.02, 0.03]]], np.float32), (8, 1, 1))
    radius = np.array([3e-3, 3e-3], np.float32)
    return write_split(path, [Trajectory(position=x, radius=radius, particle_type=np.zeros(2, np.int32))])


def test_a_flipped_bit_in_stored_positions_is_caught(tmp_path):
    import h5py

    from dispgns.data import DatasetError, read_split

    path = _one_split(tmp_path / "test.h5")
    with h5py.File(path) as f:
        offset = f["00000/position"].id.get_chunk_info(0).byte_offset
    raw = bytearray(path.read_bytes())
    raw[offset + 5] ^= 0x10
    path.write_bytes(bytes(raw))
    with pytest.raises(DatasetError, match=r"damaged") as info:
        read_split(path)
    assert str(tmp_path) in str(info.value)  # the file with its directory


def test_files_written_without_checksums_still_load(tmp_path):
    import h5py

    from dispgns.data import read_split

    path = tmp_path / "old.h5"
    with h5py.File(path, "w") as f:
        f.attrs["format_version"] = 1
        g = f.create_group("00000")
        g["position"] = np.tile(np.array([[[0.0, 0.0], [0.02, 0.03]]], np.float32), (8, 1, 1))
        g["radius"] = np.array([3e-3, 3e-3], np.float32)
        g["particle_type"] = np.zeros(2, np.int32)
    (trajectory,) = read_split(path)
    assert trajectory.position.shape == (8, 2, 2)


def test_leftovers_of_dead_writers_are_removed_and_a_set_aside_output_restored(tmp_path):
    from dispgns.files import leftovers, remove_leftovers

    target = tmp_path / "out"
    dead = 2**22 + 12345  # above Linux's pid_max: no such process
    (tmp_path / f".out.tmp-{dead}-abc_12").mkdir()
    (tmp_path / f".out.{dead}-0123456789ab.tmp.gif").write_text("x")
    (tmp_path / ".out.0123456789ab.tmp.gif").write_text("x")  # an older name without a pid
    mine = tmp_path / f".out.tmp-{__import__('os').getpid()}-live_1"
    mine.mkdir()  # a writer that still runs: kept
    old = tmp_path / f".out.old-{dead}-abcd1234.tmp"
    old.mkdir()
    (old / "metrics.json").write_text("{}")
    (tmp_path / ".other.tmp-1-x").mkdir()  # another target's: kept
    assert len(leftovers(target)) == 4
    done = dict(remove_leftovers(target))
    assert done[old] == f"restored as {target}" and (target / "metrics.json").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["out", mine.name, ".other.tmp-1-x"])


def _cli(argv, capsys):
    from dispgns.cli import main

    code = main(argv)
    captured = capsys.readouterr()
    return code, captured.out, captured.err


@pytest.mark.parametrize("command", ["demo", "render"])
def test_render_and_demo_refuse_to_overwrite_before_any_work(command, tmp_path, capsys):
    out = tmp_path / "pics"
    out.mkdir()
    (out / "notes.txt").write_text("keep me")
    argv = [command, "--out", str(out)] + (["--data", str(tmp_path / "no-data")] if command == "render" else [])
    code, _, err = _cli(argv, capsys)
    assert code == 2 and "exists and is not empty" in err and "--overwrite" in err and "Traceback" not in err
    code, _, err = _cli(argv + ["--overwrite"], capsys)
    assert code == 2 and "not a dispgns" in err
    assert (out / "notes.txt").read_text() == "keep me"
    code, _, err = _cli([command, "--out", str(tmp_path / "pics.gif")] + argv[3:], capsys)
    assert code == 2 and "expected a directory" in err
    blocker = tmp_path / "file"
    blocker.write_text("")
    code, _, err = _cli([command, "--out", str(blocker / "sub")] + argv[3:], capsys)
    assert code == 2 and "cannot write to" in err and "not a writable directory" in err


def test_an_unwritable_output_is_one_line_for_evaluate_style_staging(tmp_path, capsys, monkeypatch):
    import dispgns.files

    def refuse(*args, **kwargs):
        raise PermissionError(30, "Read-only file system", str(tmp_path / "x"))

    monkeypatch.setattr(dispgns.files.tempfile, "mkdtemp", refuse)
    from dispgns.cli import CLIError
    from dispgns.cli._common import output_directory

    with pytest.raises(CLIError, match=r"^cannot write to .*: Read-only file system$"):
        with output_directory(tmp_path / "out", overwrite=False, marker="m", kind="k"):
            pass
    assert not list(tmp_path.iterdir())


# ----------------------------------------------------------------------------- train defaults


def _train_args(*extra):
    from dispgns.cli import build_parser

    return build_parser().parse_args(["train", "--data", "d", "--out", "r", *extra])


def test_bare_train_uses_the_shipped_models_cpu_config_and_the_paper_is_one_flag_away():
    from dispgns.cli.train import resolve_configs
    from dispgns.pretrained import load_pretrained

    model, train, explicit = resolve_configs(_train_args(), 0.2)
    _, shipped, _ = load_pretrained()
    assert (model.latent_size, model.message_passing_steps) == (shipped.latent_size, shipped.message_passing_steps)
    assert train.num_steps == 120_000 and train.mirror_augmentation
    assert explicit == {"model": {}, "train": {}}  # a resumed run keeps its own configuration
    model, train, _ = resolve_configs(_train_args("--config", "paper_gpu", "--set", "train.seed=3"), 0.2)
    assert (model.latent_size, model.message_passing_steps, train.num_steps, train.seed) == (128, 10, 2_000_000, 3)
    model, train, _ = resolve_configs(_train_args("--config", "paper"), 0.2)
    assert not train.standardize and train.min_learning_rate == 0.0


def test_shipped_configs_and_the_experiment_files_stay_in_sync():
    from pathlib import Path

    from dispgns.pretrained import CONFIG_NAMES, named_config

    experiments = Path(__file__).parents[1] / "experiments" / "paper"
    files = {"cpu": "config.yaml", "paper_gpu": "paper_gpu.yaml", "paper": "paper_exact.yaml"}
    assert set(CONFIG_NAMES) == set(files)
    for name, file in files.items():
        assert named_config(name).path.read_text() == (experiments / file).read_text(), name


def test_an_unknown_config_name_lists_the_shipped_ones(tmp_path, capsys):
    code, _, err = _cli(["train", "--data", str(tmp_path), "--out", str(tmp_path / "r"), "--config", "gpu"], capsys)
    assert code == 2 and "cpu, paper_gpu, paper" in err


# ----------------------------------------------------------------------------- damaged checkpoints


def _saved_run(run, model_config, steps=(10, 20), stored_model=None):
    from dispgns.training import TrainConfig, create_train_state
    from dispgns.training.checkpoint import Checkpointer, run_config, write_json

    train_config = TrainConfig(standardize=False)
    state = create_train_state(jax.random.key(0), model_config, train_config)
    norm = {k: np.asarray(v) for k, v in state.params["normalization"].items()}
    config = run_config(model_config, train_config, norm)
    write_json(run / "config.json", config)
    saving = Checkpointer(run, keep=5, config=run_config(stored_model or model_config, train_config, norm))
    for step in steps:
        saving.save(state.replace(step=jnp.asarray(step, state.step.dtype)), jax.random.key(1), data_position=step)
    saving.close()
    return state, config


def _delete_state(path):
    import shutil

    shutil.rmtree(path / "state")


def _corrupt_metadata(path):
    for name in ("_CHECKPOINT_METADATA", "state/_METADATA"):
        if (path / name).exists():
            (path / name).write_text("{not json")


def _truncate_arrays(path):
    for file in (path / "state").rglob("*"):
        if file.is_file() and "ocdbt" in str(file.relative_to(path)) and file.stat().st_size > 64:
            file.write_bytes(file.read_bytes()[:32])


@pytest.mark.parametrize("damage", [_delete_state, _corrupt_metadata, _truncate_arrays])
def test_resume_falls_back_to_the_newest_intact_checkpoint_and_says_which_was_damaged(damage, tmp_path):
    from dispgns.training.checkpoint import Checkpointer

    state, config = _saved_run(tmp_path, TINY)
    damage(tmp_path / "checkpoints" / "20")
    checkpointer = Checkpointer(tmp_path, keep=5, config=config)
    try:
        restored, _, extra = checkpointer.restore(state, jax.random.key(1))
    finally:
        checkpointer.close()
    assert int(restored.step) == 10
    (reason,) = extra["skipped"]
    assert "checkpoints/20" in reason and "damaged" in reason and "strict" not in reason


def test_resume_accepts_a_checkpoint_written_before_a_model_field_existed(tmp_path):
    """A checkpoint whose stored config lacks a later ModelConfig field (at its default) still resumes."""
    from dispgns.training.checkpoint import Checkpointer

    state, config = _saved_run(tmp_path, TINY, steps=(10,))
    stored = tmp_path / "checkpoints" / "10" / "extra" / "metadata"
    assert stored.exists()
    older = json.loads(stored.read_text())
    del older["config"]["model"]["symmetrize"]  # as written before `symmetrize` was added
    stored.write_text(json.dumps(older))
    checkpointer = Checkpointer(tmp_path, keep=5, config=config)
    try:
        restored, _, _ = checkpointer.restore(state, jax.random.key(1))
    finally:
        checkpointer.close()
    assert int(restored.step) == 10

    # Not at its default: a real disagreement, named.
    older["config"]["model"]["latent_size"] = 99
    stored.write_text(json.dumps(older))
    checkpointer = Checkpointer(tmp_path, keep=5, config=config)
    try:
        with pytest.raises(Exception, match="latent_size: checkpoint 99"):
            checkpointer.restore(state, jax.random.key(1))
    finally:
        checkpointer.close()


def test_evaluate_on_a_run_whose_checkpoints_are_of_another_model_speaks_cli(tmp_path, tiny_dataset, capsys):
    import dataclasses

    run = tmp_path / "run"
    _saved_run(run, TINY, steps=(10,), stored_model=dataclasses.replace(TINY, latent_size=16))
    # A valid dataset: evaluate reads it before the model (its dimension picks the shipped model).
    code, _, err = _cli(["evaluate", "--model", str(run), "--data", str(tiny_dataset)], capsys)
    assert code == 2, err
    assert "written for another configuration" in err and "latent_size" in err
    assert "strict" not in err and "Traceback" not in err and "ArrayRestoreArgs" not in err


# ----------------------------------------------------------------------------- signals: exit status, clean shutdown

TINY_TRAIN = [
    "--set",
    "model.latent_size=16",
    "--set",
    "model.hidden_size=16",
    "--set",
    "model.message_passing_steps=2",
    "--set",
    "train.log_every=10",
    "--set",
    "train.checkpoint_every=20",
    "--set",
    "train.validate_every=20",
    "--set",
    "train.validation_rollout_frames=10",
    "--no-progress",
]


def test_a_run_with_a_weight_average_exports_the_average_and_refuses_another_decay_on_resume(
    tiny_dataset, tmp_path, capsys
):
    from dispgns.training.checkpoint import load_model, load_params

    run = tmp_path / "run"
    argv = ["train", "--data", str(tiny_dataset), "--out", str(run), *TINY_TRAIN, "--set", "train.ema_decay=0.9"]
    code, _, err = _cli([*argv, "--steps", "20"], capsys)
    assert code == 0, err
    exported, _, _ = load_model(run / "model")
    averaged, _, info = load_params(run, best=True)  # the checkpoint of step 20, read back
    raw, _, _ = load_params(run, best=True, averaged=False)
    assert info["record"]["steps"] == 20
    leaves = jax.tree_util.tree_leaves
    for a, b in zip(leaves(exported), leaves(averaged), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert not all(np.allclose(a, b) for a, b in zip(leaves(exported["network"]), leaves(raw["network"])))
    # The decay decides what is learned: a resumed run keeps it, and says so.
    code, _, err = _cli([*argv[:-1], "train.ema_decay=0.5", "--steps", "30", "--resume"], capsys)
    assert code == 2
    assert "ema_decay" in err and "0.9" in err and "0.5" in err and "Traceback" not in err


@pytest.mark.slow
@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_a_signalled_training_exits_with_its_usual_status_and_resumes_exactly(signum, tiny_dataset, tmp_path):
    import time

    from dispgns.cli import main
    from dispgns.training.checkpoint import load_model

    run = tmp_path / "run"
    argv = [sys.executable, "-m", "dispgns", "train", "--data", str(tiny_dataset), "--out", str(run), *TINY_TRAIN]
    proc = subprocess.Popen([*argv, "--steps", "100000"], stderr=subprocess.PIPE, text=True, preexec_fn=_ctrl_c_on)
    # Up to 30 min: under a load of ~15 on 2 cores the first checkpoint took over 10 min, and a signal sent at
    # start-up instead (killed by it, -15, before the handler exists) tests something else.
    deadline = time.monotonic() + 1800
    while not (run / "checkpoints" / "20").is_dir() and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.5)
    assert (run / "checkpoints" / "20").is_dir(), "the first checkpoint was not reached"
    proc.send_signal(signum)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 128 + signum, err
    for crash in ("Traceback", "terminate called", "pure virtual", "Segmentation", "Event loop is closed"):
        assert crash not in err, err
    assert "(interrupted, not the final one)" in err
    stopped = int(json.loads((run / "model" / "model.json").read_text())["record"]["steps"])
    assert stopped >= 20
    resumed = subprocess.run([*argv, "--steps", str(stopped + 10), "--resume"], capture_output=True, text=True)
    assert resumed.returncode == 0, resumed.stderr
    whole = tmp_path / "whole"
    assert (
        main(["train", "--data", str(tiny_dataset), "--out", str(whole), *TINY_TRAIN, "--steps", str(stopped + 10)])
        == 0
    )
    a = jax.tree_util.tree_leaves(load_model(run / "model")[0])
    b = jax.tree_util.tree_leaves(load_model(whole / "model")[0])
    for x, y in zip(a, b):  # the tolerance of test_training_loop's in-process resume test
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-6, atol=1e-7)
    log = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    steps = [(r["kind"], r["step"]) for r in log]
    assert len(steps) == len(set(steps))  # no record written twice


def test_a_sigterm_becomes_an_interrupt_with_status_143(tmp_path):
    import os
    import time

    from dispgns.cli._common import interrupted_status, reset_interrupts, sigterm_as_interrupt

    reset_interrupts()
    assert interrupted_status() == 130  # Ctrl-C's when no signal was turned into the interrupt
    with pytest.raises(KeyboardInterrupt), sigterm_as_interrupt():
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(5)
    assert interrupted_status() == 143
    assert signal.getsignal(signal.SIGTERM) == signal.SIG_DFL


@pytest.mark.parametrize("signum, status", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_a_signal_during_start_up_waits_for_the_imports_then_exits_with_its_usual_status(signum, status, tmp_path):
    # The signal lands at the start of the start-up imports, before jaxlib's and h5py's extensions initialise
    # (inside one, it used to leave an ImportError traceback or a segmentation fault).
    import os

    (tmp_path / "signal_now.py").write_text(f"import os\nos.kill(os.getpid(), {int(signum)})\n")
    code = textwrap.dedent(
        """
        import sys
        import dispgns.cli as cli
        cli._START_UP_MODULES = ("signal_now", *cli._START_UP_MODULES)
        sys.argv = ["dispgns", "generate", "--preset", "tiny", "--out", sys.argv[1]]
        cli.entry()
        """
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), *sys.path])}
    out = tmp_path / "out"
    proc = subprocess.run(
        [sys.executable, "-c", code, str(out)],
        capture_output=True,
        text=True,
        env=env,
        preexec_fn=_ctrl_c_on,
        timeout=300,
    )
    assert (proc.returncode, proc.stderr.strip(), proc.stdout) == (status, "dispgns: interrupted", "")
    assert not out.exists()


def test_an_import_error_caused_by_ctrl_c_is_an_interrupt(monkeypatch, capsys, tmp_path):
    import dispgns.data as data_module
    from dispgns.cli import main

    def interrupted_import(*args, **kwargs):
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as interrupt:  # what an extension's initialisation turns a Ctrl-C into
            raise ImportError("Encountered an error while initializing the extension.") from interrupt

    monkeypatch.setattr(data_module, "generate_dataset", interrupted_import)
    assert main(["generate", "--preset", "tiny", "--out", str(tmp_path / "out")]) == 130
    assert capsys.readouterr().err.strip().endswith("dispgns generate: interrupted")

    def broken_import(*args, **kwargs):
        raise ImportError("no module named nowhere")

    monkeypatch.setattr(data_module, "generate_dataset", broken_import)
    with pytest.raises(ImportError, match="nowhere"):  # any other ImportError stays what it is
        main(["generate", "--preset", "tiny", "--out", str(tmp_path / "out2")])


def test_a_run_killed_as_it_started_is_replaced_by_the_next_run(tiny_dataset, tmp_path, capsys):
    from dispgns.cli import main

    # What a SIGKILL between the checkpointer's folders and config.json leaves (seen in the adversarial trial):
    # a config temporary of a process that is gone, and empty best/ and checkpoints/.
    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    run = tmp_path / "run"
    (run / "best").mkdir(parents=True)
    (run / "checkpoints").mkdir()
    (run / f".config.json.{int(gone.stdout)}-278f623032ae.tmp.json").write_text("{")
    argv = ["train", "--data", str(tiny_dataset), "--out", str(run), "--steps", "2", "--no-progress"]
    argv += ["--set", "model.latent_size=8", "--set", "model.hidden_size=8", "--set", "model.message_passing_steps=1"]
    assert main(argv) == 0
    error = capsys.readouterr().err
    assert "left by a run killed as it started" in error and ".config.json." in error
    assert (run / "config.json").is_file() and (run / "model").is_dir()
    assert not [p.name for p in run.iterdir() if ".tmp" in p.name]

    # Anything else in the folder and it is not a killed start: refused as before.
    other = tmp_path / "other"
    (other / "checkpoints").mkdir(parents=True)
    (other / "notes.txt").write_text("mine\n")
    assert main([*argv[:4], str(other), *argv[5:]]) == 2
    assert "exists and is not empty" in capsys.readouterr().err
    assert (other / "notes.txt").is_file()


def test_a_checkpoint_that_cannot_be_written_is_an_oserror_naming_its_folder(tmp_path):
    from dispgns.training.checkpoint import Checkpointer

    state, config = _saved_run(tmp_path, TINY, steps=(10,))
    saving = Checkpointer(tmp_path, keep=5, config=config)
    # The checkpoints folder becomes unwritable: a file stands where it was (chmod does not stop root).
    (tmp_path / "checkpoints").rename(tmp_path / "kept")
    (tmp_path / "checkpoints").write_text("not a folder\n")
    try:
        with pytest.raises(OSError) as info:
            saving.save(state.replace(step=jnp.asarray(20, state.step.dtype)), jax.random.key(1), data_position=20)
    finally:
        saving.close()
    assert info.value.filename == str(tmp_path / "checkpoints" / "20"), info.value
    assert (tmp_path / "kept" / "10").is_dir()


@pytest.mark.parametrize("bounds", ["box", 5, [[0, "x"], [1, 2]], [1, 2]])
def test_malformed_bounds_in_metadata_name_the_field(bounds, tiny_dataset, tmp_path):
    import shutil

    from dispgns.data import DatasetError, read_metadata

    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    values = json.loads((data / "metadata.json").read_text())
    values["bounds"] = bounds
    (data / "metadata.json").write_text(json.dumps(values))
    with pytest.raises(DatasetError, match=r"metadata.json: 'bounds' is .* pair of numbers per axis"):
        read_metadata(data)


# ----------------------------------------------------------------------------- several signals, unwritable checkpoints


def _train_argv(data, run, steps, *extra):
    return [sys.executable, "-m", "dispgns", "train", "--data", str(data), "--out", str(run), *TINY_TRAIN,
            "--steps", str(steps), *extra]  # fmt: skip


def _wait_for(proc, condition, timeout=900):
    import time

    deadline = time.monotonic() + timeout
    while not condition() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    return condition()


def _same_parameters(run_a, run_b):
    from dispgns.training.checkpoint import load_model

    a = jax.tree_util.tree_leaves(load_model(run_a / "model")[0])
    b = jax.tree_util.tree_leaves(load_model(run_b / "model")[0])
    for x, y in zip(a, b):  # the tolerance of test_training_loop's in-process resume test
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-6, atol=1e-7)


@pytest.fixture(scope="module")
def uninterrupted_run(tiny_dataset, tmp_path_factory):
    """A 60-step run of the tiny network, never interrupted: what every interrupted run must end equal to."""
    run = tmp_path_factory.mktemp("uninterrupted") / "run"
    done = subprocess.run(_train_argv(tiny_dataset, run, 60), capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    return run


@pytest.mark.slow
def test_sigterm_again_and_again_exits_143_every_time_and_the_run_ends_exact(tiny_dataset, uninterrupted_run, tmp_path):
    """SIGTERM at start-up of a resume, mid-training and just after a checkpoint, then a resume to the end."""
    run = tmp_path / "run"
    moments = [
        lambda: (run / "checkpoints" / "20").is_dir(),  # training, after the first checkpoint
        lambda: (run / "checkpoints" / "40").is_dir(),  # right after the next one
        lambda: True,  # start-up of a resumed run (before or while it compiles)
    ]
    for number, moment in enumerate(moments):
        proc = subprocess.Popen(
            _train_argv(tiny_dataset, run, 60, *(["--resume"] if number else [])), stderr=subprocess.PIPE, text=True
        )
        assert _wait_for(proc, moment), proc.communicate()[1]
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=600)
        # 143 from our handler, or -15 when the signal came before the handler was installed (start-up):
        # both are the shell's status 143, and neither is a crash at exit.
        assert proc.returncode in (143, -signal.SIGTERM), (number, proc.returncode, err)
        for crash in ("Traceback", "terminate called", "pure virtual", "Segmentation", "Event loop is closed"):
            assert crash not in err, err
    done = subprocess.run(_train_argv(tiny_dataset, run, 60, "--resume"), capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    _same_parameters(run, uninterrupted_run)
    log = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    steps = [(r["kind"], r["step"]) for r in log]
    assert len(steps) == len(set(steps))


def _mount_tmpfs(path, size="32m"):
    import os
    import shutil

    if os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("mounting a file system needs root")
    path.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)]).returncode != 0:
        pytest.skip("cannot mount a tmpfs here")


def test_a_split_written_onto_a_full_disk_is_one_oserror_with_nothing_left(tmp_path):
    # HDF5 writing to the disk itself failed in its closing flush with a RuntimeError (a traceback; a
    # segmentation fault at exit was reported) and kept the file open; now the file is one Python write.
    import errno

    from dispgns.data import Trajectory, read_split, write_split

    mount = tmp_path / "full"
    _mount_tmpfs(mount, size="64k")
    try:
        x = np.zeros((60, 300, 2), np.float32) + np.linspace(-0.5, 0.5, 300, dtype=np.float32)[None, :, None]
        big = [Trajectory(position=x, radius=np.full(300, 1e-3, np.float32), particle_type=np.zeros(300, np.int32))]
        with pytest.raises(OSError) as info:
            write_split(mount / "train.h5", big)
        assert info.value.errno == errno.ENOSPC
        assert list(mount.iterdir()) == []  # no partial file, no temporary
        small = _one_split(mount / "test.h5")  # the library is in a clean state: the next write works
        assert read_split(small)[0].position.shape == (8, 2, 2)
    finally:
        subprocess.run(["umount", str(mount)])


@pytest.mark.slow
def test_generate_onto_a_disk_that_fills_up_is_one_line_exit_2_and_nothing_left(tmp_path):
    mount = tmp_path / "full"
    _mount_tmpfs(mount, size="64k")
    try:
        out = mount / "data"
        argv = [sys.executable, "-m", "dispgns", "generate", "--preset", "tiny", "--out", str(out)]
        done = subprocess.run(argv, capture_output=True, text=True)
        errors = [line for line in done.stderr.splitlines() if "error:" in line]
        assert done.returncode == 2 and len(errors) == 1 and "Traceback" not in done.stderr, done.stderr
        assert f"cannot write to {out}: No space left on device" in errors[0]
        assert list(mount.iterdir()) == []
    finally:
        subprocess.run(["umount", str(mount)])


@pytest.mark.slow
@pytest.mark.parametrize("how", ["read-only file system", "checkpoints folder replaced by a file"])
def test_checkpoints_unwritable_mid_training_one_line_and_the_earlier_checkpoint_resumes(
    how, tiny_dataset, uninterrupted_run, tmp_path
):
    """The place of the checkpoints stops taking writes after step 20 (root is not stopped by chmod: the file
    system is remounted read-only, or a file takes the checkpoints folder's place)."""
    mount = tmp_path / "mnt"
    if how == "read-only file system":
        _mount_tmpfs(mount)
    else:
        mount.mkdir()
    run = mount / "run"
    try:
        proc = subprocess.Popen(_train_argv(tiny_dataset, run, 60), stderr=subprocess.PIPE, text=True)
        assert _wait_for(proc, lambda: (run / "checkpoints" / "20").is_dir()), proc.communicate()[1]
        if how == "read-only file system":
            subprocess.run(["mount", "-o", "remount,ro", str(mount)], check=True)
        else:
            (run / "checkpoints").rename(run / "aside")
            (run / "checkpoints").write_text("a file where the checkpoints folder was\n")
        _, err = proc.communicate(timeout=900)
        assert proc.returncode == 2, err
        errors = [line for line in err.splitlines() if "error:" in line]
        assert len(errors) == 1 and "Traceback" not in err and "Event loop" not in err, err
        assert f"cannot write to {run}" in errors[0] and "training stopped" in errors[0], errors[0]
        assert f"{run / 'checkpoints' / '20'} (step 20), is intact" in errors[0], errors[0]
        if how == "read-only file system":
            assert "Read-only file system" in errors[0]
            subprocess.run(["mount", "-o", "remount,rw", str(mount)], check=True)
        else:
            (run / "checkpoints").unlink()
            (run / "aside").rename(run / "checkpoints")
        done = subprocess.run(_train_argv(tiny_dataset, run, 60, "--resume"), capture_output=True, text=True)
        assert done.returncode == 0, done.stderr
        _same_parameters(run, uninterrupted_run)
    finally:
        if how == "read-only file system":
            subprocess.run(["umount", str(mount)])


@pytest.mark.parametrize("command", ["generate", "evaluate", "export"])
def test_an_output_below_a_file_is_one_line_naming_the_output_before_any_work(command, tiny_dataset, tmp_path, capsys):
    blocker = tmp_path / "blocker"
    blocker.write_text("a file where a directory would go\n")
    out = blocker / "out"
    argv = {
        "generate": ["generate", "--preset", "tiny", "--out", str(out)],
        "evaluate": ["evaluate", "--data", str(tiny_dataset), "--splits", "test", "--out", str(out)],
        "export": ["export", "extxyz", str(tiny_dataset), "--split", "test", "--out", str(out)],
    }[command]
    code, _, err = _cli(argv, capsys)
    assert code == 2, err
    (line,) = [line for line in err.splitlines() if "error:" in line]
    assert f"cannot write to {out}" in line and ".tmp" not in line, line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["blocker"]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="Linux reports the umask in /proc/self/status")
def test_written_files_get_the_umask_read_without_changing_it(tmp_path, monkeypatch):
    import dispgns.files

    previous = os.umask(0o027)
    try:
        # Setting the umask to read it would leave other threads' new files without one for a moment.
        monkeypatch.setattr(dispgns.files.os, "umask", lambda mask: pytest.fail("the umask was changed"))
        with dispgns.files.atomic_path(tmp_path / "out.txt") as temporary:
            temporary.write_text("x")
        assert (tmp_path / "out.txt").stat().st_mode & 0o777 == 0o640
    finally:
        monkeypatch.undo()
        os.umask(previous)


@pytest.mark.parametrize("status", ["Umask:\n", "Umask:\tx27\n", "Name:\tpython\n"])
def test_an_unexpected_process_status_falls_back_to_reading_the_umask_by_setting_it(monkeypatch, status):
    import io

    import dispgns.files

    monkeypatch.setattr(dispgns.files, "open", lambda *args, **kwargs: io.StringIO(status), raising=False)
    previous = os.umask(0o027)
    try:
        assert dispgns.files._umask() == 0o027
    finally:
        os.umask(previous)

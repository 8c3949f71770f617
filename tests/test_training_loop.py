"""The training loop, orbax checkpoints, exact resume, exported models and ``dispgns train``."""

import json

import jax
import numpy as np
import pytest

from dispgns.cli import main
from dispgns.data import load_dataset
from dispgns.training import TrainConfig, compute_normalization, create_train_state
from dispgns.training.batches import BatchStream
from dispgns.training.checkpoint import Checkpointer, CheckpointError, export_model, load_model
from dispgns.training.loop import Validator, train

LOOP = TrainConfig(
    learning_rate=1e-3,
    log_every=5,
    validate_every=10,
    checkpoint_every=10,
    keep_checkpoints=2,
    validation_examples=8,
    validation_trajectories=1,
    validation_rollout_frames=10,
)
TINY_ARGS = [
    "--set",
    "model.latent_size=16",
    "--set",
    "model.hidden_size=16",
    "--set",
    "model.message_passing_steps=2",
    "--set",
    "train.log_every=10",
    "--set",
    "train.validate_every=20",
    "--set",
    "train.checkpoint_every=20",
    "--set",
    "train.validation_rollout_frames=20",
    "--no-progress",
]


def leaves(tree):
    return [np.asarray(x) for x in jax.tree_util.tree_leaves(tree)]


@pytest.fixture(scope="module")
def data(tiny_dataset):
    _, splits = load_dataset(tiny_dataset, ["train", "valid"])
    return splits["train"], splits["valid"]


def fresh(data, model_config, train_config=LOOP):
    train_trajs, _ = data
    norm = compute_normalization(train_trajs, noise_std=train_config.noise_std)
    init_key, key = jax.random.split(jax.random.key(train_config.seed))
    state = create_train_state(init_key, model_config, train_config, norm)
    stream = BatchStream.for_training(train_trajs, model_config, train_config)
    return state, stream, key


def test_resume_equals_uninterrupted(data, tiny_model_config, tmp_path):
    state, stream, key = fresh(data, tiny_model_config)
    whole = train(state, stream, key, until_step=20).state

    state, stream, key = fresh(data, tiny_model_config)
    first = Checkpointer(tmp_path / "run", keep=2)
    half = train(state, stream, key, until_step=10, checkpointer=first).state
    first.close()
    # A new process would rebuild everything from scratch and restore.
    template, stream, _ = fresh(data, tiny_model_config)
    again = Checkpointer(tmp_path / "run", keep=2)
    restored, restored_key, extra = again.restore(template, jax.random.key(123))
    assert int(restored.step) == 10 and extra["data_position"] == 10
    np.testing.assert_array_equal(jax.random.key_data(restored_key), jax.random.key_data(key))
    for a, b in zip(leaves(half.opt_state), leaves(restored.opt_state)):
        np.testing.assert_array_equal(a, b)
    resumed = train(restored, stream, restored_key, until_step=20, checkpointer=again).state
    again.close()
    assert int(resumed.step) == int(whole.step) == 20
    for a, b in zip(leaves(whole.params), leaves(resumed.params)):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7)
    # And training changed something: the comparison is not trivially true.
    assert not all(np.array_equal(a, b) for a, b in zip(leaves(whole.params), leaves(template.params)))


def test_loop_logs_validates_and_keeps_last_and_best(data, tiny_model_config, tmp_path):
    state, stream, key = fresh(data, tiny_model_config)
    records = []
    validator = Validator(data[1], tiny_model_config, LOOP)
    checkpointer = Checkpointer(tmp_path / "run", keep=2)
    values = iter([3.0, 1.0, 2.0])
    scored = lambda params: {"valid_rollout_mse": next(values)}
    result = train(
        state, stream, key, until_step=30, validator=scored, checkpointer=checkpointer, on_log=records.append
    )
    checkpointer.close()
    assert [r["step"] for r in records if r["kind"] == "train"] == [5, 10, 15, 20, 25, 30]
    # Wall and CPU time of the process, so accuracy per CPU-hour can be plotted from the log.
    for name in ("elapsed_s", "cpu_s"):
        times = [r[name] for r in records]
        assert all(t >= 0 for t in times) and times == sorted(times), name
    assert records[-1]["cpu_s"] > 0
    assert [(r["step"], r["valid_rollout_mse"]) for r in records if r["kind"] == "validation"] == [
        (10, 3.0),
        (20, 1.0),
        (30, 2.0),
    ]
    assert sorted(int(p.name) for p in (tmp_path / "run" / "checkpoints").iterdir() if p.name.isdigit()) == [20, 30]
    assert [p.name for p in (tmp_path / "run" / "best").iterdir() if p.name.isdigit()] == ["20"]
    assert not result.interrupted and int(result.state.step) == 30
    # The real validator: finite numbers, deterministic.
    first, second = validator(result.state.params), validator(result.state.params)
    assert first == second and np.isfinite(first["valid_one_step_loss"]) and first["valid_rollout_frames"] == 10


def test_best_is_kept_when_validations_fall_between_checkpoints(data, tiny_model_config, tmp_path):
    import dataclasses

    config = dataclasses.replace(LOOP, validate_every=5, checkpoint_every=4, keep_checkpoints=1)
    state, stream, key = fresh(data, tiny_model_config, config)
    checkpointer = Checkpointer(tmp_path / "run", keep=1)
    values = iter([3.0, 1.0, 2.0])
    train(state, stream, key, until_step=12, validator=lambda params: {"valid_rollout_mse": next(values)},
          checkpointer=checkpointer)  # fmt: skip
    checkpointer.close()
    assert [p.name for p in (tmp_path / "run" / "best").iterdir() if p.name.isdigit()] == ["10"]
    assert [p.name for p in (tmp_path / "run" / "checkpoints").iterdir() if p.name.isdigit()] == ["12"]


def test_keyboard_interrupt_checkpoints_and_returns(data, tiny_model_config, tmp_path):
    state, stream, key = fresh(data, tiny_model_config)
    checkpointer = Checkpointer(tmp_path / "run", keep=2)

    def interrupt(step, metrics):
        if step == 7:
            raise KeyboardInterrupt

    result = train(state, stream, key, until_step=30, checkpointer=checkpointer, on_step=interrupt)
    assert result.interrupted and int(result.state.step) == 7
    assert checkpointer.latest_step() == 7
    checkpointer.close()


def test_exported_model_round_trip_and_errors(data, tiny_model_config, tmp_path):
    state, _, _ = fresh(data, tiny_model_config)
    directory = export_model(tmp_path / "model", state.params, tiny_model_config, {"steps": 0})
    params, config, info = load_model(directory)
    assert config == tiny_model_config and info["record"] == {"steps": 0}
    for a, b in zip(leaves(state.params), leaves(params)):
        np.testing.assert_array_equal(a, b)
    # Replacing keeps one complete directory.
    export_model(directory, state.params, tiny_model_config, {"steps": 1})
    assert load_model(directory)[2]["record"] == {"steps": 1}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model"]

    info = json.loads((directory / "model.json").read_text())
    info["model"]["latent_size"] = 32
    (directory / "model.json").write_text(json.dumps(info))
    with pytest.raises(CheckpointError, match=r"params.msgpack: .* has shape .* expected"):
        load_model(directory)
    (directory / "params.msgpack").write_bytes(b"not msgpack")
    with pytest.raises(CheckpointError, match="params.msgpack"):
        load_model(directory)
    with pytest.raises(CheckpointError, match="model.json: not found"):
        load_model(tmp_path / "nowhere")


# ----------------------------------------------------------------------------- the CLI


def cli_params(run):
    return leaves(load_model(run / "model")[0])


def test_cli_train_resume_equals_uninterrupted(tiny_dataset, tmp_path, capsys):
    whole, split = tmp_path / "whole", tmp_path / "split"
    assert main(["train", "--data", str(tiny_dataset), "--out", str(whole), "--steps", "40", *TINY_ARGS]) == 0
    assert main(["train", "--data", str(tiny_dataset), "--out", str(split), "--steps", "20", *TINY_ARGS]) == 0
    assert (
        main(["train", "--data", str(tiny_dataset), "--out", str(split), "--steps", "40", "--resume", "--no-progress"])
        == 0
    )
    for a, b in zip(cli_params(whole), cli_params(split)):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7)
    records = [json.loads(line) for line in (split / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in records if r["kind"] == "train"] == [10, 20, 30, 40]
    assert {r["step"] for r in records if r["kind"] == "validation"} == {20, 40}
    config = json.loads((split / "config.json").read_text())
    assert config["model"]["latent_size"] == 16 and config["model"]["connectivity_radius"] == 0.4
    assert config["train"]["num_steps"] == 40
    assert (split / "training_curve.png").stat().st_size > 1000
    # The checkpoint carries the resolved config too.
    again = Checkpointer(split)
    template = create_train_state(
        jax.random.key(0),
        load_model(split / "model")[1],
        TrainConfig(num_steps=40),
        {k: np.asarray(v, np.float32) for k, v in config["normalization"].items()},
    )
    _, _, extra = again.restore(template, jax.random.key(0))
    again.close()
    assert extra["config"]["model"] == config["model"] and extra["step"] == 40

    # A resumed run must keep its model and learning settings.
    code = main(
        [
            "train",
            "--data",
            str(tiny_dataset),
            "--out",
            str(split),
            "--resume",
            "--set",
            "model.input_sequence_length=5",
            "--no-progress",
        ]
    )
    err = capsys.readouterr().err
    assert code == 2 and "input_sequence_length: checkpoint 6, requested 5" in err
    code = main(
        [
            "train",
            "--data",
            str(tiny_dataset),
            "--out",
            str(split),
            "--resume",
            "--set",
            "train.noise_std=0.1",
            "--no-progress",
        ]
    )
    assert code == 2 and "noise_std" in capsys.readouterr().err


def test_cli_train_bad_inputs_leave_nothing(tiny_dataset, tmp_path, capsys):
    run = tmp_path / "run"

    def fails(*argv, match):
        assert main(["train", *argv, "--no-progress"]) == 2
        err = capsys.readouterr().err
        assert match in err, err

    fails("--data", str(tmp_path / "missing"), "--out", str(run), match="metadata.json: not found")
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "metadata.json").write_text('{"dim": 2')
    fails("--data", str(broken), "--out", str(run), match="metadata.json: cannot be read as JSON")
    fails(
        "--data",
        str(tiny_dataset),
        "--out",
        str(run),
        "--set",
        "model.latent_size=0",
        match="ModelConfig.latent_size must be an integer >= 1",
    )
    fails("--data", str(tiny_dataset), "--out", str(run), "--set", "model.dim=3", match="'dim' is 2")
    fails("--data", str(tiny_dataset), "--out", str(run), "--set", "nosection", match="SECTION.FIELD=VALUE")
    config = tmp_path / "config.yaml"
    config.write_text("model:\n  latent_sise: 8\n")
    fails(
        "--data",
        str(tiny_dataset),
        "--out",
        str(run),
        "--config",
        str(config),
        match="unknown ModelConfig field(s) ['latent_sise']",
    )
    fails("--data", str(tiny_dataset), "--out", str(run), "--resume", match="no run to resume")
    assert not run.exists()
    blocker = tmp_path / "file"
    blocker.write_text("")
    fails("--data", str(tiny_dataset), "--out", str(blocker / "run"), match="cannot create the run directory")
    occupied = tmp_path / "occupied"
    occupied.mkdir()
    (occupied / "notes.txt").write_text("mine")
    fails("--data", str(tiny_dataset), "--out", str(occupied), match="exists and is not empty")
    fails("--data", str(tiny_dataset), "--out", str(occupied), "--overwrite", match="not a dispgns run")
    assert sorted(p.name for p in occupied.iterdir()) == ["notes.txt"]


def test_interrupt_during_a_save_waits_for_it_then_stops(data, tiny_model_config, tmp_path, monkeypatch):
    import os
    import signal

    state, stream, key = fresh(data, tiny_model_config)
    checkpointer = Checkpointer(tmp_path / "run", keep=2)
    manager = checkpointer._last
    save = manager.save
    saved = []

    def interrupted_save(step, *args, **kwargs):
        saved.append(step)
        os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C just as orbax starts writing the step
        return save(step, *args, **kwargs)

    monkeypatch.setattr(manager, "save", interrupted_save)
    result = train(state, stream, key, until_step=30, checkpointer=checkpointer)
    assert result.interrupted and int(result.state.step) == 10 and checkpointer.latest_step() == 10
    assert saved == [10]  # the interrupt handling did not save step 10 a second time
    assert not list((tmp_path / "run").rglob("*orbax-checkpoint-tmp*"))
    restored, _, extra = checkpointer.restore(state, key)
    assert int(restored.step) == 10 and extra["data_position"] == 10
    checkpointer.close()


@pytest.mark.parametrize("signal_name", ["SIGINT", "SIGTERM"])
def test_an_interrupted_export_says_so_and_resume_exports_the_model(signal_name, tiny_dataset, tmp_path, capsys):
    import os
    import signal

    import dispgns.training.checkpoint as checkpoint_module

    run = tmp_path / "run"
    real_export = checkpoint_module.export_model

    def export_then_signal(directory, *args, **kwargs):
        os.kill(os.getpid(), getattr(signal, signal_name))  # lands while the model is being written
        return real_export(directory, *args, **kwargs)

    # A shell starts background jobs with SIGINT ignored, and the command keeps an ignored signal ignored
    # (as a user's `nohup`/`&` asks): give this process Python's usual Ctrl-C handler for the test.
    previous_sigint = signal.signal(signal.SIGINT, signal.default_int_handler)
    checkpoint_module.export_model = export_then_signal
    try:
        code = main(["train", "--data", str(tiny_dataset), "--out", str(run), "--steps", "20", *TINY_ARGS])
    finally:
        checkpoint_module.export_model = real_export
        signal.signal(signal.SIGINT, previous_sigint)
    assert code == {"SIGINT": 130, "SIGTERM": 143}[signal_name]
    error = capsys.readouterr().err
    assert "interrupted while exporting the model of step 20" in error and "was not updated" in error
    assert "--resume" in error and not (run / "model").exists()
    assert signal.getsignal(signal.SIGTERM) == signal.SIG_DFL  # the command's handler is gone again

    resumed = main(["train", "--data", str(tiny_dataset), "--out", str(run), "--resume", "--no-progress"])
    assert resumed == 0
    assert load_model(run / "model")[2]["record"]["steps"] == 20


def test_weight_average_resumes_exactly_and_is_what_validation_and_load_params_see(data, tiny_model_config, tmp_path):
    import dataclasses

    from dispgns.training.checkpoint import load_params, run_config

    config = dataclasses.replace(LOOP, ema_decay=0.9)
    state, stream, key = fresh(data, tiny_model_config, config)
    whole = train(state, stream, key, until_step=20).state

    state, stream, key = fresh(data, tiny_model_config, config)
    run = tmp_path / "run"
    values = run_config(tiny_model_config, config, state.params["normalization"])
    (run).mkdir()
    (run / "config.json").write_text(json.dumps(values))
    seen = []

    def validator(params):
        seen.append(params)
        return {"valid_rollout_mse": float(len(seen))}  # the first validation is the best

    first = Checkpointer(run, keep=2, config=values)
    half = train(state, stream, key, until_step=10, checkpointer=first, validator=validator).state
    first.close()
    # Validation scored the moving average, not the raw weights.
    for a, b in zip(leaves(seen[0]["network"]), leaves(half.ema)):
        np.testing.assert_array_equal(a, b)
    template, stream, _ = fresh(data, tiny_model_config, config)
    again = Checkpointer(run, keep=2, config=values)
    restored, restored_key, _ = again.restore(template, jax.random.key(123))
    for a, b in zip(leaves(half.ema), leaves(restored.ema)):
        np.testing.assert_array_equal(a, b)
    resumed = train(restored, stream, restored_key, until_step=20, checkpointer=again).state
    again.close()
    for a, b in zip(leaves((whole.params, whole.ema)), leaves((resumed.params, resumed.ema))):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7)
    # The average lags the weights: the comparison above is not that of two equal trees.
    assert not all(np.allclose(a, b) for a, b in zip(leaves(whole.ema), leaves(whole.params["network"])))
    # A run directory's parameters (latest or best checkpoint) are the averaged ones.
    latest, _, _ = load_params(run)
    best, _, info = load_params(run, best=True)
    assert info["record"]["steps"] == 10
    for a, b in zip(leaves(latest["network"]), leaves(resumed.ema)):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(leaves(best["network"]), leaves(half.ema)):
        np.testing.assert_array_equal(a, b)
    raw, _, _ = load_params(run, best=True, averaged=False)
    for a, b in zip(leaves(raw["network"]), leaves(half.params["network"])):
        np.testing.assert_array_equal(a, b)
    # A state without an average cannot take these checkpoints: a named disagreement, not "damaged" (which
    # would send restore through every older checkpoint in turn).
    plain, _, _ = fresh(data, tiny_model_config, LOOP)
    other = Checkpointer(run, keep=2, config=values)
    try:
        with pytest.raises(CheckpointError, match="ema_decay: checkpoint 0.9") as caught:
            other.restore(plain, jax.random.key(0))
    finally:
        other.close()
    assert caught.value.mismatch and "damaged" not in str(caught.value)


def test_a_checkpoint_without_an_average_is_a_named_mismatch_for_a_state_with_one(data, tiny_model_config, tmp_path):
    """The other direction of the check above: turning the average on in a run whose checkpoints have none."""
    import dataclasses

    from dispgns.training.checkpoint import run_config

    state, stream, key = fresh(data, tiny_model_config, LOOP)
    run = tmp_path / "run"
    run.mkdir()
    values = run_config(tiny_model_config, LOOP, state.params["normalization"])
    (run / "config.json").write_text(json.dumps(values))
    writer = Checkpointer(run, keep=2, config=values)
    train(state, stream, key, until_step=5, checkpointer=writer)
    writer.close()

    averaged, _, _ = fresh(data, tiny_model_config, dataclasses.replace(LOOP, ema_decay=0.9))
    reader = Checkpointer(run, keep=2, config=values)
    try:
        with pytest.raises(CheckpointError, match=r"ema_decay: checkpoint 0\.0 \(without a weight average\)") as caught:
            reader.restore(averaged, jax.random.key(0))
    finally:
        reader.close()
    assert caught.value.mismatch and "damaged" not in str(caught.value)
    assert "the restoring state with one" in str(caught.value)


def test_resume_on_other_validation_files_warns_that_validations_do_not_compare(tiny_dataset, tmp_path, capsys):
    """A dataset regenerated on another machine is not bit-identical: the resumed run says its scores moved files."""
    import shutil

    import h5py

    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    run = tmp_path / "run"
    assert main(["train", "--data", str(data), "--out", str(run), "--steps", "20", *TINY_ARGS]) == 0
    recorded = json.loads((run / "config.json").read_text())["dataset"]["valid_fingerprint"]
    assert isinstance(recorded, str) and len(recorded) == 16
    capsys.readouterr()

    # The same files: no warning.
    assert main(["train", "--data", str(data), "--out", str(run), "--resume", "--steps", "30", *TINY_ARGS]) == 0
    assert "validation trajectories" not in capsys.readouterr().err

    with h5py.File(data / "valid.h5", "r+") as store:
        group = store[sorted(store)[0]]
        group["position"][-1, 0, 0] += 1e-6  # a last-frame rounding difference
    assert main(["train", "--data", str(data), "--out", str(run), "--resume", "--steps", "40", *TINY_ARGS]) == 0
    error = capsys.readouterr().err
    assert f"{data / 'valid.h5'}: not the validation trajectories this run was validated on up to step 30" in error
    assert f"was {recorded}" in error
    now = json.loads((run / "config.json").read_text())["dataset"]["valid_fingerprint"]
    assert now != recorded
    # The checkpoint of step 40 records the new files: resuming on them is silent.
    assert main(["train", "--data", str(data), "--out", str(run), "--resume", "--steps", "50", *TINY_ARGS]) == 0
    assert "validation trajectories" not in capsys.readouterr().err


def test_a_second_resume_from_the_same_checkpoint_warns_again(tiny_dataset, tmp_path, capsys):
    """config.json is rewritten when a run resumes; the checkpoint's own record says what it was validated on."""
    import shutil

    import h5py

    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    run = tmp_path / "run"
    assert main(["train", "--data", str(data), "--out", str(run), "--steps", "20", *TINY_ARGS]) == 0
    with h5py.File(data / "valid.h5", "r+") as store:
        group = store[sorted(store)[0]]
        group["position"][-1, 0, 0] += 1e-6
    capsys.readouterr()
    # A resume that ends before its next checkpoint (already at its last step), then the same resume again.
    for _ in range(2):
        assert main(["train", "--data", str(data), "--out", str(run), "--resume", "--steps", "20", *TINY_ARGS]) == 0
        error = capsys.readouterr().err
        assert "not the validation trajectories this run was validated on up to step 20" in error


def test_a_resume_past_a_damaged_checkpoint_compares_with_the_one_it_restores(tiny_dataset, tmp_path, capsys):
    """The intact checkpoint before a damaged one was validated on the earlier files: its own record says so."""
    import shutil

    import h5py

    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    run, keep = tmp_path / "run", ["--set", "train.keep_checkpoints=2"]
    assert main(["train", "--data", str(data), "--out", str(run), "--steps", "20", *keep, *TINY_ARGS]) == 0
    with h5py.File(data / "valid.h5", "r+") as store:
        group = store[sorted(store)[0]]
        group["position"][-1, 0, 0] += 1e-6
    assert main(["train", "--data", str(data), "--out", str(run), "--resume", "--steps", "40", *keep, *TINY_ARGS]) == 0
    assert "validated on up to step 20" in capsys.readouterr().err
    shutil.rmtree(run / "checkpoints" / "40" / "state")  # step 40 (saved with the new files) is damaged
    # Back at step 20 (saved with the earlier files), already at --steps 20: nothing is trained or saved.
    assert main(["train", "--data", str(data), "--out", str(run), "--resume", "--steps", "20", *keep, *TINY_ARGS]) == 0
    error = capsys.readouterr().err
    assert "checkpoints/40" in error and "damaged" in error
    assert "not the validation trajectories this run was validated on up to step 20" in error


def test_the_validation_warning_needs_other_files_or_other_settings(capsys):
    """Runs recorded before fingerprints existed, and data without a validation split, resume silently."""
    import dataclasses
    from pathlib import Path

    from dispgns.cli.train import _warn_if_validation_changed

    data, loop = Path("data"), dataclasses.asdict(LOOP)
    for validated, now in [
        ({}, "b"),  # a config without a dataset record
        ({"dataset": {"path": "data"}}, "b"),  # written before the fingerprint
        ({"dataset": {"valid_fingerprint": "a"}}, None),  # no validation split now: nothing is validated
        ({"dataset": {"valid_fingerprint": "a"}}, "a"),  # the same files
    ]:
        _warn_if_validation_changed({**validated, "train": loop}, {"valid_fingerprint": now}, LOOP, data, 7)
        assert capsys.readouterr().err == ""
    # How long and how often do not change what a validation scores.
    longer = dataclasses.replace(LOOP, num_steps=LOOP.num_steps + 10, validate_every=LOOP.validate_every + 1)
    _warn_if_validation_changed({"train": loop}, {"valid_fingerprint": "a"}, longer, data, 7)
    assert capsys.readouterr().err == ""
    # A record without training settings (a Checkpointer given no run config) has nothing to compare.
    more = dataclasses.replace(LOOP, validation_trajectories=LOOP.validation_trajectories + 1)
    for validated in ({}, {"train": None}, {"train": {"seed": 0}}):
        _warn_if_validation_changed(validated, {"valid_fingerprint": "a"}, more, data, 7)
        assert capsys.readouterr().err == ""

    recorded_a = {"dataset": {"valid_fingerprint": "a"}, "train": loop}
    _warn_if_validation_changed(recorded_a, {"valid_fingerprint": "b"}, LOOP, data, 7)
    assert "validated on up to step 7 (fingerprint b, was a;" in capsys.readouterr().err
    _warn_if_validation_changed({"train": loop}, {"valid_fingerprint": "a"}, more, data, 7)
    error = capsys.readouterr().err
    assert "the validation settings changed after step 7 (train.validation_trajectories" in error
    _warn_if_validation_changed({"train": loop}, {"valid_fingerprint": None}, more, data, 7)  # nothing to validate
    assert "validation settings" not in capsys.readouterr().err
    assert "do not compare with the earlier ones" in error

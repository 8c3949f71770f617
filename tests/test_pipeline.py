"""End to end on the tiny preset: train -> evaluate -> render -> demo, with the documented files."""

import json

import h5py
import numpy as np
import pytest
from PIL import Image

from dispgns.cli import main
from dispgns.data import load_dataset, read_split

TRAIN = [
    "--set",
    "model.latent_size=16",
    "--set",
    "model.hidden_size=16",
    "--set",
    "model.message_passing_steps=2",
    "--set",
    "train.learning_rate=3e-3",
    "--set",
    "train.lr_decay_steps=400",
    "--set",
    "train.min_learning_rate=1e-5",
    "--set",
    "train.validate_every=200",
    "--set",
    "train.validation_rollout_frames=30",
    "--steps",
    "400",
    "--no-progress",
]


@pytest.fixture(scope="module")
def trained(tiny_dataset, tmp_path_factory):
    run = tmp_path_factory.mktemp("pipeline") / "run"
    assert main(["train", "--data", str(tiny_dataset), "--out", str(run), *TRAIN]) == 0
    return run


def test_trained_model_beats_constant_velocity_on_training_trajectories(tiny_dataset, trained, tmp_path, capsys):
    out = tmp_path / "eval-train"
    assert (
        main(
            [
                "evaluate",
                "--model",
                str(trained),
                "--data",
                str(tiny_dataset),
                "--splits",
                "train",
                "--out",
                str(out),
                "--no-chaos",
                "--no-progress",
            ]
        )
        == 0
    )
    report = json.loads((out / "metrics.json").read_text())
    for m in report["splits"]["train"]["trajectories"]:
        assert m["finite"] and m["mse"] < m["constant_velocity_mse"], (m["mse"], m["constant_velocity_mse"])
    assert "| rollout MSE |" in capsys.readouterr().out


def test_evaluate_writes_metrics_predictions_and_plots(tiny_dataset, trained, tmp_path):
    out = tmp_path / "eval"
    assert (
        main(["evaluate", "--model", str(trained), "--data", str(tiny_dataset), "--out", str(out), "--no-progress"])
        == 0
    )
    report = json.loads((out / "metrics.json").read_text())
    _, splits = load_dataset(tiny_dataset, ["test", "test_unseen"])
    assert set(report["splits"]) == {"test", "test_unseen"}
    assert report["model"]["source"].endswith("model") and report["frames"] == 60
    for split, trajectories in splits.items():
        entry = report["splits"][split]
        assert entry["chaos_floor"] and entry["summary"]["n_trajectories"] == len(trajectories)
        metrics = entry["trajectories"][0]
        assert len(metrics["per_frame_mse"]) == 60 - 6
        for key in (
            "mse",
            "rmse_mm",
            "rmse_diameters",
            "mse_h1",
            "mse_h10",
            "mse_h50",
            "constant_velocity_mse",
            "chaos_floor_mse",
            "wall_violations_total",
            "overlaps_total",
            "kinetic_energy_relative_error",
            "mean_height_error",
        ):
            assert key in metrics, key
        assert metrics["mse_h100"] is None  # longer than the 54 predicted frames: reported as missing
        assert 0 <= metrics["chaos_floor_mse"] < metrics["constant_velocity_mse"]
        assert np.isclose(metrics["rmse_mm"], np.sqrt(metrics["mse"]) * 0.1 * 1e3)
        predicted = read_split(out / "predictions" / f"{split}.h5")
        assert len(predicted) == len(trajectories)
        for p, t in zip(predicted, trajectories):
            assert p.position.shape == t.position.shape
            np.testing.assert_array_equal(p.position[:6], t.position[:6])
            np.testing.assert_array_equal(p.radius, t.radius)
        with h5py.File(out / "predictions" / f"{split}.h5") as f:
            assert f.attrs["predicted"]
        assert Image.open(out / f"error_curves_{split}.png").size[0] > 300
        # The suspension statistics, for the model and both references, and their picture.
        for key in ("rdf_l1", "chaos_floor_rdf_l1", "constant_velocity_rdf_l1", "chaos_floor_sinkhorn_position_final"):
            assert np.isfinite(metrics[key]), key
        assert Image.open(out / f"statistics_{split}.png").size[0] > 300


def test_render_from_predictions_and_from_model(tiny_dataset, trained, tmp_path, capsys):
    evaluated = tmp_path / "eval"
    assert (
        main(
            [
                "evaluate",
                "--model",
                str(trained),
                "--data",
                str(tiny_dataset),
                "--splits",
                "test",
                "--out",
                str(evaluated),
                "--no-chaos",
                "--no-progress",
            ]
        )
        == 0
    )
    prefix = tmp_path / "pictures" / "test0"
    assert (
        main(
            [
                "render",
                "--data",
                str(tiny_dataset),
                "--split",
                "test",
                "--predictions",
                str(evaluated / "predictions" / "test.h5"),
                "--out",
                str(prefix),
                "--stride",
                "3",
            ]
        )
        == 0
    )
    gif = Image.open(prefix / "rollout.gif")
    assert gif.n_frames == 20  # 60 frames, every 3rd
    assert (prefix / "rollout.mp4").stat().st_size > 1000
    assert Image.open(prefix / "rollout_grid.png").size[0] > 500
    model_prefix = tmp_path / "pictures" / "model"
    assert (
        main(
            [
                "render",
                "--data",
                str(tiny_dataset),
                "--split",
                "test",
                "--model",
                str(trained),
                "--out",
                str(model_prefix),
                "--start",
                "10",
                "--stop",
                "30",
                "--no-mp4",
            ]
        )
        == 0
    )
    assert Image.open(model_prefix / "rollout.gif").n_frames == 10
    assert not (model_prefix / "rollout.mp4").exists()
    # The same rollout, whether rendered from the file or from the model.
    a, b = Image.open(prefix / "rollout_grid.png"), Image.open(model_prefix / "rollout_grid.png")
    assert np.array_equal(np.asarray(a), np.asarray(b))
    capsys.readouterr()
    assert (
        main(["render", "--data", str(tiny_dataset), "--split", "test", "--index", "5", "--model", str(trained)]) == 2
    )
    assert "--index 5: test has trajectories 0..0" in capsys.readouterr().err
    assert (
        main(
            ["render", "--data", str(tiny_dataset), "--split", "test", "--model", str(trained), "--grid-frames", "0,99"]
        )
        == 2
    )
    assert "frame 99 is outside 0..59" in capsys.readouterr().err


def test_demo_writes_its_files(trained, tmp_path, capsys):
    out = tmp_path / "demo"
    assert (
        main(
            [
                "demo",
                "--model",
                str(trained),
                "--out",
                str(out),
                "--frames",
                "40",
                "--seed",
                "3",
                "--stride",
                "4",
                "--radii",
                "4,6,8,10",
            ]
        )
        == 0
    )
    printed = capsys.readouterr().out
    assert "seed 3" in printed and "rollout MSE" in printed and "constant-velocity baseline" in printed
    report = json.loads((out / "metrics.json").read_text())
    assert report["seed"] == 3 and report["radii_mm"] == [4.0, 6.0, 8.0, 10.0] and report["frames"] == 40
    assert len(report["metrics"]["per_frame_mse"]) == 34 and "chaos_floor_mse" in report["metrics"]
    assert {"physics_s", "gnn_rollout_s"} <= set(report["timings"])
    assert Image.open(out / "rollout.gif").n_frames == 10
    for name in ("rollout.mp4", "rollout_grid.png", "error_curve.png"):
        assert (out / name).stat().st_size > 1000, name


def test_bad_inputs_exit_with_a_message(tiny_dataset, trained, tmp_path, capsys):
    cases = [
        (["evaluate", "--model", str(tmp_path), "--data", str(tiny_dataset)], "neither an exported model"),
        (["evaluate", "--model", str(trained), "--data", str(tmp_path)], "metadata.json: not found"),
        (["evaluate", "--model", str(trained), "--data", str(tiny_dataset), "--splits", "nope"], "no split 'nope'"),
        (["evaluate", "--model", str(trained), "--data", str(tiny_dataset), "--frames", "3"], "--frames 3"),
        (["render", "--data", str(tiny_dataset), "--predictions", str(tmp_path / "none.h5")], "file not found"),
        (["demo", "--model", str(trained), "--radii", "2,x"], "--radii '2,x'"),
        (["demo", "--best"], "--best needs --model"),
    ]
    for argv, message in cases:
        assert main(argv) == 2, argv
        assert message in capsys.readouterr().err, argv


def test_evaluate_is_atomic_and_render_checks_what_it_is_given(tiny_dataset, trained, tmp_path, capsys):
    out = tmp_path / "eval"
    evaluate = [
        "evaluate",
        "--model",
        str(trained),
        "--data",
        str(tiny_dataset),
        "--splits",
        "test",
        "--max-trajectories",
        "1",
        "--frames",
        "20",
        "--no-chaos",
        "--no-progress",
        "--out",
        str(out),
    ]
    assert main(evaluate) == 0
    capsys.readouterr()
    assert main(evaluate) == 2 and "exists and is not empty" in capsys.readouterr().err
    assert main(evaluate + ["--overwrite"]) == 0
    assert sorted(p.name for p in out.iterdir()) == [
        "error_curves_test.png",
        "metrics.json",
        "predictions",
        "statistics_test.png",
    ]
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no staging left behind
    other = tmp_path / "precious"
    other.mkdir()
    (other / "notes.txt").write_text("keep me")
    capsys.readouterr()
    assert main(evaluate[:-1] + [str(other), "--overwrite"]) == 2
    assert "not a dispgns evaluation" in capsys.readouterr().err and (other / "notes.txt").read_text() == "keep me"

    # A short prediction (--frames 20) renders against the first 20 frames of its trajectory.
    predictions = str(out / "predictions" / "test.h5")
    render = ["render", "--data", str(tiny_dataset), "--no-mp4", "--predictions", predictions]
    assert main(render + ["--split", "test", "--stride", "1", "--out", str(tmp_path / "short")]) == 0
    assert Image.open(tmp_path / "short" / "rollout.gif").n_frames == 20
    cases = [
        (["--split", "train"], "is not a prediction of train trajectory 0"),
        (["--split", "test", "--fps", "nan"], "--fps a finite number > 0"),
        (["--split", "test", "--grid-frames", ","], "at least one"),
    ]
    for extra, message in cases:
        assert main(render + extra + ["--out", str(tmp_path / "bad")]) == 2, extra
        assert message in capsys.readouterr().err, extra
    assert not list(tmp_path.glob("bad*"))


def test_damaged_files_are_reported_not_raised(tiny_dataset, tmp_path, capsys):
    import shutil

    damaged = tmp_path / "damaged"
    shutil.copytree(tiny_dataset, damaged)
    raw = bytearray((damaged / "test.h5").read_bytes())
    raw[1536:1600] = b"\xff" * 64
    (damaged / "test.h5").write_bytes(bytes(raw))
    assert main(["render", "--data", str(damaged), "--split", "test", "--out", str(tmp_path / "r")]) == 2
    assert "test.h5: cannot be read" in capsys.readouterr().err
    with h5py.File(damaged / "valid.h5", "r+") as f:
        del f["00000"]["position"]
        f["00000"].create_group("position")
    with pytest.raises(Exception, match="field 'position' is not an HDF5 dataset"):
        read_split(damaged / "valid.h5")


def _network_leaves(run_or_model):
    import jax

    from dispgns.training.checkpoint import load_params

    params, _, _ = load_params(run_or_model)
    return jax.tree_util.tree_leaves(params)


def test_init_from_starts_at_the_models_parameters_and_normalisation(tiny_dataset, trained, tmp_path):
    # One step with a vanishing learning rate: the exported model is the state the run started from.
    run = tmp_path / "fine"
    assert main(["train", "--data", str(tiny_dataset), "--out", str(run), "--init-from", str(trained / "model"),
                 "--set", "train.learning_rate=1e-30", "--set", "train.min_learning_rate=0",
                 "--steps", "1", "--no-progress"]) == 0  # fmt: skip
    for a, b in zip(_network_leaves(run / "model"), _network_leaves(trained / "model"), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6, atol=1e-20)
    config = json.loads((run / "config.json").read_text())
    assert config["init_from"]["model"] == str(trained / "model")
    assert config["model"]["latent_size"] == 16  # the model's network, not the default configuration's
    stored = json.loads((trained / "config.json").read_text())["normalization"]
    for k, v in stored.items():
        np.testing.assert_allclose(config["normalization"][k], v, rtol=1e-6)


@pytest.mark.slow
def test_init_from_trains_on_from_the_model(tiny_dataset, trained, tmp_path):
    run = tmp_path / "fine"
    args = ["--set", "train.log_every=20", "--set", "train.validate_every=1000", "--set", "train.learning_rate=1e-4",
            "--steps", "20", "--no-progress"]  # fmt: skip
    assert main(["train", "--data", str(tiny_dataset), "--out", str(run), "--init-from", str(trained), *args]) == 0
    first = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    fresh = tmp_path / "fresh"
    assert main(["train", "--data", str(tiny_dataset), "--out", str(fresh), *TRAIN[:6], *args]) == 0
    scratch = [json.loads(line) for line in (fresh / "log.jsonl").read_text().splitlines()]
    loss = next(r["loss"] for r in first if r["kind"] == "train")
    loss_scratch = next(r["loss"] for r in scratch if r["kind"] == "train")
    # Measured: 1.26 against 2.10 (a fresh network's loss is about D = 2, the variance of standardised targets).
    assert loss < 0.75 * loss_scratch, (loss, loss_scratch)
    assert json.loads((run / "model" / "model.json").read_text())["record"]["init_from"]["model"] == str(trained)


def test_init_from_grows_the_network_into_a_larger_one_with_the_same_predictions(tiny_dataset, trained, tmp_path):
    import jax

    from dispgns.data import load_dataset
    from dispgns.simulator import fit_capacity, predict_step
    from dispgns.training.checkpoint import load_params

    run = tmp_path / "grown"
    assert main(["train", "--data", str(tiny_dataset), "--out", str(run), "--init-from", str(trained / "model"),
                 "--set", "model.message_passing_steps=3", "--set", "model.hidden_size=20",
                 "--set", "train.learning_rate=1e-30", "--set", "train.min_learning_rate=0",
                 "--steps", "1", "--no-progress"]) == 0  # fmt: skip
    config = json.loads((run / "config.json").read_text())
    assert config["init_from"]["grown"] == {"hidden_size": [16, 20], "message_passing_steps": [2, 3]}
    assert config["model"]["message_passing_steps"] == 3 and config["model"]["hidden_size"] == 20
    trajectory = load_dataset(tiny_dataset, ["valid"])[1]["valid"][0]
    window, radius = jax.numpy.asarray(trajectory.position[:6]), jax.numpy.asarray(trajectory.radius)
    steps = []
    for source in (trained / "model", run / "model"):
        params, model_config, _ = load_params(source)
        capacity = fit_capacity(window[-1], model_config, margin=0.5)
        steps.append(predict_step(params, window, radius, model_config=model_config, capacity=capacity).acceleration)
    assert np.abs(np.asarray(steps[0])).max() > 0
    np.testing.assert_allclose(steps[1], steps[0], rtol=1e-4, atol=1e-6 * np.abs(np.asarray(steps[0])).max())


def test_init_from_refuses_another_network_and_a_changed_start_on_resume(tiny_dataset, trained, tmp_path, capsys):
    run = tmp_path / "fine"
    code = main(["train", "--data", str(tiny_dataset), "--out", str(run), "--init-from", str(trained),
                 "--set", "model.latent_size=32", "--steps", "1", "--no-progress"])  # fmt: skip
    assert code == 2 and not run.exists()
    assert "model.latent_size = 32 (the model has 16)" in capsys.readouterr().err
    code = main(["train", "--data", str(tiny_dataset), "--out", str(run), "--init-from", str(trained),
                 "--set", "model.message_passing_steps=1", "--steps", "1", "--no-progress"])  # fmt: skip
    assert code == 2 and not run.exists()
    assert "model.message_passing_steps = 1 (the model has 2)" in capsys.readouterr().err
    assert main(["train", "--data", str(tiny_dataset), "--out", str(run), "--steps", "1", *TRAIN[:6],
                 "--no-progress"]) == 0  # fmt: skip
    code = main(["train", "--data", str(tiny_dataset), "--out", str(run), "--resume", "--init-from", str(trained),
                 "--no-progress"])  # fmt: skip
    assert code == 2
    assert "from random weights" in capsys.readouterr().err
    code = main(["train", "--data", str(tiny_dataset), "--out", str(tmp_path / "x"), "--init-from", "no-such-model",
                 "--no-progress"])  # fmt: skip
    assert code == 2 and "no shipped model 'no-such-model'" in capsys.readouterr().err


def test_time_estimate_ignores_the_recompiling_steps():
    # A run whose graph budget grows twice in its first steps: each growth recompiles (tens of seconds), the
    # steady state is 0.25 s/step. The estimate is the steady state's, not the mean's 3.0 s/step.
    from dispgns.cli.train import _StepTimer

    times = iter(np.cumsum([0.0, 0.25, 30.0, 0.25, 0.25, 25.0] + [0.25] * 20))
    written = []
    timer = _StepTimer(0, 1000, written.append, clock=lambda: float(next(times)))
    step = timer.wrap(lambda step, metrics: None)
    for k in range(1, 30):
        step(k, {})
    assert len(written) == 1
    assert written[0].startswith("measured 0.25 s/step: the remaining 979 steps take about 4 min"), written


def test_paper_ship_writes_the_records_validation_under_one_name_and_no_machine_path(trained, tmp_path, monkeypatch):
    # experiments/paper/run.py's ship() on an exported run: its record names the last validation "validation" (as a
    # checkpoint's does, and as the package's record test reads), and keeps only the dataset's own name.
    import importlib.util
    from pathlib import Path

    from dispgns.training.checkpoint import load_model

    path = Path(__file__).resolve().parents[1] / "experiments" / "paper" / "run.py"
    spec = importlib.util.spec_from_file_location("paper_run", path)
    paper_run = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(paper_run)
    monkeypatch.setattr(paper_run, "REPO", tmp_path)  # the package directory it writes into
    summaries = {"keep_inside_box_on": {"splits": {"test": {"mse": {"mean": 1e-3}}}}}
    paper_run.ship(trained, summaries, keep_inside_box=True, best=False, name="tiny", extra={"selection": {"x": 1}})
    _, config, info = load_model(tmp_path / "src" / "dispgns" / "pretrained" / "tiny")
    record = info["record"]
    exported = json.loads((trained / "model" / "model.json").read_text())["record"]
    assert "last_validation" in exported and "last_validation" not in record
    assert record["validation"] == exported["last_validation"] and record["validation"]["valid_rollout_mse"] > 0
    assert record["dataset"]["path"] == Path(exported["dataset"]["path"]).name != exported["dataset"]["path"]
    assert record["evaluation"] == {"keep_inside_box_on": {"test": {"mse": {"mean": 1e-3}}}}
    assert record["selection"] == {"x": 1} and config.keep_inside_box and not config.symmetrize

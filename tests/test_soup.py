"""experiments/accuracy/soup.py and ensemble.py: weight averages (one dataset, one architecture) and ensembles."""

import dataclasses

import jax
import numpy as np
import pytest
from experiment_scripts import NORM, load_experiment

from dispgns.model import ModelConfig, init_params
from dispgns.training.checkpoint import export_model, load_model


@pytest.fixture(scope="module")
def soup():
    return load_experiment("soup")


def _export(directory, seed, config, norm=NORM):
    export_model(directory, init_params(jax.random.key(seed), config, norm), config, {"steps": seed})
    return str(directory)


def test_the_soup_is_the_leafwise_mean_and_keeps_the_first_models_settings(soup, tmp_path):
    config = ModelConfig(latent_size=8, hidden_size=8, message_passing_steps=1)
    a = _export(tmp_path / "a", 0, dataclasses.replace(config, symmetrize=True))
    b = _export(tmp_path / "b", 1, config)
    assert soup.main([str(tmp_path / "soup"), a, b]) == 0
    mixed, mixed_config, info = load_model(tmp_path / "soup")
    (pa, config_a, _), (pb, _, _) = load_model(a), load_model(b)
    expected = jax.tree_util.tree_map(lambda x, y: (x + y) / 2, pa, pb)
    for got, want in zip(jax.tree_util.tree_leaves(mixed), jax.tree_util.tree_leaves(expected), strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-7)
    assert mixed_config == config_a and info["record"]["soup_of"] == [a, b]
    # Different weights really were averaged (a soup of one model would pass the check above trivially).
    leaves = zip(jax.tree_util.tree_leaves(pa["network"]), jax.tree_util.tree_leaves(pb["network"]), strict=True)
    assert any(not np.allclose(x, y) for x, y in leaves)


def test_models_of_other_data_or_architecture_are_refused_and_nothing_is_written(soup, tmp_path, capsys):
    config = ModelConfig(latent_size=8, hidden_size=8, message_passing_steps=1)
    a = _export(tmp_path / "a", 0, config)
    wider = _export(tmp_path / "wider", 1, ModelConfig(latent_size=16, hidden_size=8, message_passing_steps=1))
    other_data = _export(tmp_path / "other", 2, config, {**NORM, "velocity_std": np.full(2, 0.07)})
    assert soup.main([str(tmp_path / "s1"), a, wider]) == 2
    assert "model configuration differs" in capsys.readouterr().err
    assert soup.main([str(tmp_path / "s2"), a, other_data]) == 2
    assert "normalisation differs" in capsys.readouterr().err
    assert not (tmp_path / "s1").exists() and not (tmp_path / "s2").exists()


def test_a_shipped_name_is_read_unless_a_path_of_that_name_exists(soup, tmp_path, monkeypatch):
    from dispgns.pretrained import load_pretrained

    monkeypatch.chdir(tmp_path)
    assert soup.main(["soup", "paper", "paper"]) == 0  # the soup of a model with itself is the model
    mixed, _, info = load_model(tmp_path / "soup")
    shipped, _, _ = load_pretrained("paper")
    for got, want in zip(jax.tree_util.tree_leaves(mixed), jax.tree_util.tree_leaves(shipped), strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-6)
    assert info["record"]["soup_of"] == ["dispgns.pretrained:paper"] * 2
    local = _export(tmp_path / "paper", 3, ModelConfig(latent_size=8, hidden_size=8, message_passing_steps=1))
    assert soup.main(["soup2", "paper", local]) == 0  # ./paper exists: it is the path, not the shipped model
    assert load_model(tmp_path / "soup2")[2]["record"]["soup_of"] == ["paper", local]


def test_a_missing_model_or_best_checkpoint_is_a_one_line_error(soup, tmp_path, capsys):
    a = _export(tmp_path / "a", 0, ModelConfig(latent_size=8, hidden_size=8, message_passing_steps=1))
    assert soup.main([str(tmp_path / "s"), a, str(tmp_path / "absent")]) == 2
    assert "absent" in capsys.readouterr().err
    assert soup.main([str(tmp_path / "s"), a, "no-such-model"]) == 2
    assert "no-such-model" in capsys.readouterr().err
    assert soup.main([str(tmp_path / "s"), a, a + ":best"]) == 2  # an exported model has no best checkpoint
    assert capsys.readouterr().err.startswith("soup.py: ")
    assert not (tmp_path / "s").exists()


@pytest.fixture(scope="module")
def ensemble():
    return load_experiment("ensemble")


def _graph_inputs(config, seed=0):
    rng = np.random.default_rng(seed)
    nodes = rng.normal(size=(5, config.node_feature_size)).astype(np.float32)
    edges = rng.normal(size=(6, config.edge_feature_size)).astype(np.float32)
    return nodes, edges, np.array([1, 2, 0, 3, 4, 2]), np.array([0, 0, 1, 2, 3, 4])


@pytest.mark.parametrize(
    ("field", "values"),
    [("hidden_size", (8, 8)), ("hidden_size", (8, 16)), ("message_passing_steps", (1, 2))],
    ids=["one shape: stacked", "two widths: one by one", "two depths: one by one"],
)
def test_the_ensemble_predicts_the_mean_of_its_members_and_refuses_other_data(ensemble, tmp_path, field, values):
    from dispgns.cli import CLIError
    from dispgns.model import apply_network

    base = ModelConfig(latent_size=8, hidden_size=8, message_passing_steps=1)
    config = dataclasses.replace(base, **{field: values[0]})
    a = _export(tmp_path / "a", 0, config)
    b = _export(tmp_path / "b", 1, dataclasses.replace(config, **{field: values[1]}))
    params, got_config, info, shapes = ensemble.ensemble([a, b])
    assert got_config == config and info["ensemble"] == [a, b] and info["source"] == f"ensemble of {a} + {b}"
    # Members of one shape are stacked (one vmapped network); of two, each runs with its own shape.
    if values[0] == values[1]:
        assert shapes is None and "ensemble_shapes" not in info
    else:
        assert [s[field] for s in shapes] == list(values) and info["ensemble_shapes"] == list(shapes)
    inputs = _graph_inputs(config)
    network = ensemble.mean_of_members(apply_network, shapes)
    mean = network(params["network"], *inputs, model_config=config)
    outputs = [apply_network(load_model(m)[0]["network"], *inputs, model_config=load_model(m)[1]) for m in (a, b)]
    assert not np.allclose(outputs[0], outputs[1])
    np.testing.assert_allclose(mean, (outputs[0] + outputs[1]) / 2, rtol=1e-5, atol=1e-6)
    jitted = jax.jit(lambda networks, *graph: network(networks, *graph, model_config=config))
    np.testing.assert_allclose(jitted(params["network"], *inputs), mean, rtol=1e-5, atol=1e-6)
    other = _export(tmp_path / "other", 2, config, {**NORM, "velocity_std": np.full(2, 0.07)})
    with pytest.raises(CLIError, match="normalisation differs"):
        ensemble.ensemble([a, other])
    # Shapes may differ; what the network sees (features, graph) may not.
    other_graph = _export(tmp_path / "radius", 3, dataclasses.replace(config, connectivity_radius=0.1))
    with pytest.raises(CLIError, match="model configuration differs"):
        ensemble.ensemble([a, other_graph])


@pytest.mark.parametrize("second", ["itself", "itself widened"])
def test_ensemble_of_a_model_and_an_equivalent_one_evaluates_as_that_model_with_evaluates_flags(
    ensemble, tiny_dataset, tiny_model_config, tmp_path, monkeypatch, second
):
    import json

    import dispgns.cli._common as cli_common
    import dispgns.simulator as simulator
    from dispgns.cli import main
    from dispgns.model import grow_network

    replaced = simulator.apply_network, cli_common._load  # by main_ensemble while it runs, and put back after
    # (put back after this test too, should main_ensemble fail to: the later tests must not run with its replacements)
    monkeypatch.setattr(simulator, "apply_network", simulator.apply_network)
    monkeypatch.setattr(cli_common, "_load", cli_common._load)
    model = _export(tmp_path / "m", 0, tiny_model_config)
    other = model
    if second == "itself widened":
        # Net2Net growth computes what the model computes with twice the hidden width: the ensemble then takes the
        # path of members of two shapes (each run with its own), and must still evaluate as the model.
        params, config = load_model(model)[:2]
        wide = dataclasses.replace(config, hidden_size=2 * config.hidden_size)
        grown = dict(params, network=grow_network(jax.random.key(1), params["network"], config, wide))
        export_model(tmp_path / "wide", grown, wide, {"steps": 0, "grown": True})
        other = str(tmp_path / "wide")
    args = ["--data", str(tiny_dataset), "--splits", "valid", "--no-chaos", "--no-statistics", "--symmetrize"]
    assert main(["evaluate", "--model", model, *args, "--out", str(tmp_path / "one")]) == 0
    assert ensemble.main_ensemble([f"{model},{other}", *args, "--out", str(tmp_path / "two")]) == 0
    assert (simulator.apply_network, cli_common._load) == replaced
    one, two = (json.loads((tmp_path / d / "metrics.json").read_text()) for d in ("one", "two"))
    assert two["model"]["source"] == f"ensemble of {model} + {other}"
    # metrics.json names every member with its network's shape and training record.
    members = two["model"]["record"]["ensemble"]
    assert [m["source"] for m in members] == [model, other]
    records, widths = [{"steps": 0}] * 2, [tiny_model_config.hidden_size] * 2
    if second == "itself widened":
        records[1], widths[1] = {"steps": 0, "grown": True}, 2 * widths[1]
    assert [m["record"] for m in members] == records
    assert [m["shape"]["hidden_size"] for m in members] == widths
    # --symmetrize reached the ensemble (without it the rollouts differ: the tiny model is not mirror-symmetric).
    mse = [m["splits"]["valid"]["summary"]["mse"]["mean"] for m in (one, two)]
    np.testing.assert_allclose(mse[1], mse[0], rtol=1e-4)
    if second == "itself widened":  # and the wide member is used: widened from other weights, it changes the result
        params = load_model(_export(tmp_path / "b", 1, tiny_model_config))[0]
        grown = dict(params, network=grow_network(jax.random.key(1), params["network"], config, wide))
        export_model(tmp_path / "wide-b", grown, wide, {"steps": 1})
        assert ensemble.main_ensemble([f"{model},{tmp_path / 'wide-b'}", *args, "--out", str(tmp_path / "ab")]) == 0
        ab = json.loads((tmp_path / "ab" / "metrics.json").read_text())
        assert not np.isclose(ab["splits"]["valid"]["summary"]["mse"]["mean"], mse[0], rtol=1e-3)

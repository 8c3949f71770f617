"""The top-level package: every public name resolves, and importing it stays light."""

import subprocess
import sys

import pytest

import dispgns


def test_every_public_name_resolves_and_unknown_names_fail():
    for name in dispgns.__all__:
        assert getattr(dispgns, name) is not None, name
    assert set(dispgns.__all__) <= set(dir(dispgns))
    assert dispgns.rollout is __import__("dispgns.simulator", fromlist=["rollout"]).rollout
    with pytest.raises(AttributeError, match="not_a_name"):
        _ = dispgns.not_a_name


def test_import_and_cli_help_do_not_load_jax_md():
    code = (
        "import sys, dispgns, dispgns.cli; "
        "assert 'jax_md' not in sys.modules, 'import dispgns loaded jax-md'; "
        "dispgns.simulate; assert 'jax_md' in sys.modules"
    )
    subprocess.run([sys.executable, "-c", code], check=True)

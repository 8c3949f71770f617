"""Publishing: licence, typing marker, citation file, metadata, and an sdist that carries its tests."""

import tomllib
from pathlib import Path

import yaml

import dispgns

ROOT = Path(__file__).resolve().parents[1]


def test_licence_typing_marker_and_project_metadata():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert project["license"] == "MIT" and "MIT License" in (ROOT / "LICENSE").read_text()
    assert "Typing :: Typed" in project["classifiers"]
    assert any(url.startswith("https://") for url in project["urls"].values())
    assert (Path(dispgns.__file__).parent / "py.typed").is_file()
    # Every dependency has a lower bound (checked with older releases by tools/check_lower_bounds.sh).
    assert all(">=" in requirement for requirement in project["dependencies"])


def test_citation_file_cites_dispgns_and_the_paper():
    citation = yaml.safe_load((ROOT / "CITATION.cff").read_text())
    assert citation["cff-version"] == "1.2.0" and citation["title"].startswith("dispgns")
    paper = citation["preferred-citation"]
    assert paper["title"] == "A Graph Neural Network Simulation of Dispersed Systems"
    assert [a["family-names"] for a in paper["authors"]] == ["Hashemi", "Izadkhah"] and paper["year"] == 2025


def test_sdist_manifest_carries_what_the_tests_read():
    manifest = (ROOT / "MANIFEST.in").read_text().split()
    # experiments: test_bad_input compares the packaged configs with experiments/paper, and
    # test_three_d_pipeline runs experiments/three_d/ship.py. Checked with a fresh install of the sdist
    # and its fast tests run from the unpacked tree (see tools/check_sdist.sh).
    for needed in ("tests", "notebooks", "tools", "experiments", "CONTRIBUTING.md", "LICENSE", "CITATION.cff"):
        assert needed in manifest, needed
    assert (ROOT / "tests" / "conftest.py").is_file() and any((ROOT / "tests" / "data").glob("*.npz"))


def test_every_shipped_model_is_package_data_and_all_fit_in_15_mb(tmp_path):
    # setuptools expands package-data patterns with glob(recursive=True) under src/dispgns: every file
    # of every shipped model directory (a second one, e.g. pretrained/sedimentation-3d, included)
    # must match one. Checked with a wheel built from the tree on 2026-12-02: the second directory is in it.
    import glob

    from dispgns.pretrained import shipped_models

    patterns = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]["dispgns"]
    root = Path(dispgns.__file__).parent
    fake = tmp_path / "pretrained" / "sedimentation-3d"
    fake.mkdir(parents=True)
    for name in ("params.msgpack", "model.json", "training_curve.png"):
        (fake / name).write_bytes(b"x")
    for base, names in ((root, shipped_models()), (tmp_path, ["sedimentation-3d"])):
        covered = {Path(p) for pattern in patterns for p in glob.glob(str(base / pattern), recursive=True)}
        for name in names:
            files = [p for p in (base / "pretrained" / name).rglob("*") if p.is_file() and "__pycache__" not in p.parts]
            assert files and all(p in covered for p in files), (name, files)
    total = sum(p.stat().st_size for name in shipped_models() for p in (root / "pretrained" / name).rglob("*"))
    assert 1e6 < total <= 15e6, f"the shipped models take {total / 1e6:.1f} MB"

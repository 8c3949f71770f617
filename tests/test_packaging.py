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
    for needed in ("tests", "notebooks", "tools", "CONTRIBUTING.md", "LICENSE", "CITATION.cff"):
        assert needed in manifest, needed
    assert (ROOT / "tests" / "conftest.py").is_file() and any((ROOT / "tests" / "data").glob("*.npz"))

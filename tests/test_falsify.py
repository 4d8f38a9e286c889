"""Tests of ashc falsify: the vectorised batch of random closed loops against the guaranteed bound."""

import json

import numpy as np
import pytest

from ashc_cli.artefacts import read_artefact

from .conftest import SPECS, ashc


@pytest.mark.parametrize("spec", sorted(SPECS.glob("*.yaml")), ids=lambda p: p.stem)
def test_no_violation_on_any_spec(spec, tmp_path):
    proc = ashc("falsify", str(spec), "--out", str(tmp_path), "--runs", "6", "--t-final", "2", "--json")
    assert proc.returncode == 0, proc.stderr
    data = json.loads(proc.stdout)
    assert 0 < data["max_ratio"] <= 1.0
    assert data["runs"] == 6


def test_batch_is_reproducible_and_keeps_what_it_drew(tmp_path):
    spec = SPECS / "nonlinear_cascade.yaml"
    a = json.loads(ashc("falsify", str(spec), "--out", str(tmp_path / "a"), "--runs", "8", "--t-final", "2", "--json", check=True).stdout)
    b = json.loads(ashc("falsify", str(spec), "--out", str(tmp_path / "b"), "--runs", "8", "--t-final", "2", "--json", check=True).stdout)
    assert a["max_ratio"] == b["max_ratio"]
    art = read_artefact(tmp_path / "a" / "falsify.h5").values
    assert art["run_ratio"].shape == (8,)
    assert np.sum(art["W0"] > 0) >= 4 and np.sum(art["W0"] == 0) >= 1   # runs off and on the manifold


def test_a_broken_bound_is_found(tmp_path):
    # Shrink the gain G a thousandfold in memory: the falsifier must now see errors above the "bound".
    from ashc_cli import falsify
    from ashc_cli.pipeline import DESIGN, design_model, run
    from ashc_cli.spec import load_spec
    spec = load_spec(SPECS / "nonlinear_cascade.yaml")
    arts = run(spec, tmp_path, DESIGN)
    honest = falsify.falsify(design_model(spec, arts), arts, 8, t_final=2.0)
    arts["bound"].values["gain"] = arts["bound"].values["gain"] * 1e-3
    broken = falsify.falsify(design_model(spec, arts), arts, 8, t_final=2.0)
    assert honest.values["max_ratio"] <= 1.0 < broken.values["max_ratio"]
    assert not broken.checks["falsify_ratio"].passed

"""Tests of ashc regress: every spec against its golden summary values (what CI regression runs use)."""

import json
import shutil

import pytest

from ashc_cli.products.regress import compare

from .conftest import ROOT, SPECS, ashc

GOLDEN = ROOT / "tests" / "golden"


@pytest.mark.slow
def test_regress_passes_on_main(tmp_path):
    # The CLI on two specs; every spec of specs/ is compared with its golden file in tests/test_specs.py, on the
    # design its check made.
    specs = tmp_path / "specs"
    specs.mkdir()
    for name in ("linear_double", "nonlinear_cascade"):
        shutil.copy(SPECS / f"{name}.yaml", specs)
    proc = ashc("regress", str(specs), "--golden", str(GOLDEN), "--out", str(tmp_path / "o"), "--json")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    rows = json.loads(proc.stdout)
    assert [r["spec"] for r in rows] == ["linear_double", "nonlinear_cascade"]
    assert all(r["status"] == "ok" for r in rows)


def test_every_spec_has_a_golden_file():
    assert {p.stem for p in SPECS.glob("*.yaml")} == {p.stem for p in GOLDEN.glob("*.json")}


def test_a_changed_golden_value_fails_naming_the_key(tmp_path):
    specs, golden = tmp_path / "specs", tmp_path / "golden"
    specs.mkdir()
    golden.mkdir()
    shutil.copy(SPECS / "nonlinear_cascade.yaml", specs)
    gold = json.loads((GOLDEN / "nonlinear_cascade.json").read_text())
    gold["keys"]["bound.gain"]["value"] *= 1.01
    (golden / "nonlinear_cascade.json").write_text(json.dumps(gold))
    proc = ashc("regress", str(specs), "--golden", str(golden), "--out", str(tmp_path / "o"))
    assert proc.returncode == 3
    assert "bound.gain" in proc.stdout and "differs from golden" in proc.stdout
    assert "1 of 1 spec(s) differ" in proc.stderr


def test_compare_rules():
    assert compare("a", 1.00001, {"value": 1.0, "rtol": 1e-4}) is None
    assert "differs" in compare("a", 1.001, {"value": 1.0, "rtol": 1e-4})
    assert compare("r", 1e-12, {"value": 1e-10, "at_most": True}) is None
    assert "exceeds" in compare("r", 1e-9, {"value": 1e-10, "at_most": True})
    assert "golden True" in compare("v", False, {"value": True})
    assert "missing" in compare("k", None, {"value": 1.0})

"""Tests of summary and eval on artefacts (ashc_cli.outputs.query)."""

import json
import re

import numpy as np
import pytest

from ashc_cli.design.artefacts import Artefact
from ashc_cli.errors import ArtefactError, SpecError
from ashc_cli.design.pipeline import load_all
from ashc_cli.outputs.query import evaluate, no_negative_zero, number_text, parse_point, summary

from .conftest import ashc


def test_parse_point():
    assert parse_point("xi=0.5, x1=-2e-3") == {"xi": 0.5, "x1": -0.002}
    for bad, fragment in (("xi", "not name=value"), ("xi=abc", "not a number"), ("", "no values"), ("xi=inf", "not finite")):
        with pytest.raises(SpecError, match=fragment):
            parse_point(bad)


def test_negative_zero_is_zero():
    # -0.0 printed as "-0" (eval, check tables) or "-0.0" (summary, JSON) was a sign that meant nothing.
    assert number_text(-0.0, ".4g") == "0" and number_text(-0.0, "g") == "0" and number_text(-1e-300, ".4g") == "-1e-300"
    assert number_text(np.float64(-0.0), ".10g") == "0" and number_text(-0.5, ".4g") == "-0.5"
    data = no_negative_zero({"a": [[-126.1875, -0.0]], "b": (-0.0, 1), "c": np.array([-0.0, 2.0]), "d": "-0.0", "e": True,
                             "f": float("nan"), "g": -0})
    assert json.dumps({k: v for k, v in data.items() if k != "c"}) == '{"a": [[-126.1875, 0.0]], "b": [0.0, 1], "d": "-0.0", "e": true, "f": NaN, "g": 0}'
    assert str(data["c"]) == "[0. 2.]"
    assert str(parse_point("xi=-0")["xi"]) == "0.0"


def test_summary_and_eval_have_no_negative_zero(paper_design):
    # kappa(V) = [[-126.19, -0.0]] came out of the kappa stage; summary reports it as 0.0.
    text = json.dumps(summary(paper_design))
    assert not re.search(r"-0\.0(?![0-9])", text)
    assert str(evaluate(paper_design, "kappa", {"xi": -0.0})) == "[0.0]"


def test_evaluate(paper_design):
    assert evaluate(paper_design, "kappa", {"xi": 0.0}) == [0.0]
    with pytest.raises(SpecError, match="needs a value for xi"):
        evaluate(paper_design, "p", {})
    with pytest.raises(SpecError, match="unknown variable"):
        evaluate(paper_design, "p", {"xi": 0.1, "zeta": 1})
    with pytest.raises(SpecError, match="cannot be evaluated"):
        evaluate(paper_design, "W", {"xi": 0.1})
    # m (real only for |x4| <= 126.91) is certified for y = x4 in kappa(V) = [-126.19, 0]: refused beyond, as
    # are b and c (built from m), before anything is evaluated.
    for name, x4 in (("m", 500), ("m", -126.5), ("m", 1.0), ("b", -130), ("c", 3)):
        with pytest.raises(SpecError, match=r"outside the set where m is certified.*y in kappa\(V\) = \[-126\.188, 0\]"):
            evaluate(paper_design, name, {"x1": 0, "x2": 0, "x3": 0, "x4": x4})
    assert evaluate(paper_design, "m", {"x4": 0.0}) == pytest.approx([0.0], abs=1e-15)
    with pytest.raises(SpecError, match="b needs a value for x4"):
        evaluate(paper_design, "b", {"x1": 0, "x2": 0, "x3": 0})
    partial = {k: v for k, v in paper_design.items() if k != "delta"}
    with pytest.raises(ArtefactError, match="no delta.h5"):
        evaluate(partial, "b", {"x1": 0, "x2": 0, "x3": 0, "x4": -1})


def test_summary_has_checks(paper_design):
    data = summary(paper_design)
    assert set(data) == set(paper_design)
    assert data["stabilise"]["checks"]["lmi_margin"]["passed"] is True
    assert data["bound"]["gain"] > 0


def test_inverse_without_m_domain_is_refused(paper_design):
    # An inverse.h5 of an older ashc does not say where m is certified: m is not evaluated from it.
    old = paper_design["inverse"]
    stripped = Artefact(stage="inverse", values={k: v for k, v in old.values.items() if k != "m_domain"}, exprs=old.exprs,
                        checks=old.checks, meta=old.meta, provenance=old.provenance)
    with pytest.raises(ArtefactError, match="records no m_domain"):
        evaluate({**paper_design, "inverse": stripped}, "m", {"x4": -7.0})


# --- through the CLI: exit code and the one-line message -------------------------------------------------

def _cli_eval(out, name, at):
    return ashc("eval", str(out), name, "--at", at)


def test_cuk_eval_m_only_where_certified(cli_run):
    out = cli_run["out"]
    inside = _cli_eval(out, "m", "x4=-6.9732")
    assert inside.returncode == 0 and inside.stdout.strip() == "m(x4=-6.9732) = [0.3677045851]"
    beyond = _cli_eval(out, "m", "x4=-126.5")       # m is still real there, but m(x) lies outside V
    assert beyond.returncode == 2, beyond.stderr
    assert beyond.stderr == ("error: eval m: y = h(x) = -126.5 is outside the set where m is certified, y in kappa(V) = [-126.188, 0]; "
                             "expected a state x with h(x) in [-126.188, 0] (inverse.m_domain)\n")
    assert beyond.stdout == ""
    b = _cli_eval(out, "b", "x1=1,x2=2,x3=3,x4=20")
    assert b.returncode == 2 and "(b is built from m)" in b.stderr and "[-126.188, 0]" in b.stderr


def test_cuk_headline_and_summary_have_no_infinite_interval(cli_run):
    line = next(l for l in cli_run["design"].stderr.splitlines() if l.startswith("inverse"))  # progress: stderr
    assert "m real for y in [-126.915, 126.915]; certified for y in kappa(V) = [-126.188, 0]" in line and "inf" not in line
    entry = json.loads(ashc("summary", str(cli_run["out"]), "--json", check=True).stdout)["inverse"]
    assert entry["m_domain"] == [[pytest.approx(-126.18750467), 0.0]] and entry["m_domain_set"] == "kappa(V)"
    assert "inf" not in json.dumps(entry).replace("m_real_on_Y", "") and None not in entry["m_real_interval"]


@pytest.fixture(scope="module")
def ladder_numeric(tmp_path_factory):
    """A 2-stage ladder (n = 8) designed on the numeric path: m is a Chebyshev interpolant of kappa^-1."""
    folder = tmp_path_factory.mktemp("ladder2")
    spec = folder / "ladder2.yaml"
    ashc("example", "ladder", "--stages", "2", "--output", str(spec), check=True)
    design = ashc("design", str(spec), "--out", str(folder / "out"), "--numeric", check=True)
    return {"out": folder / "out", "design": design}


def test_ladder_m_refused_above_kappa_V(ladder_numeric):
    # The issue: m(v32 = 90) returned 2.76e9 with exit 0 on the 64-state ladder (an extrapolated polynomial).
    out = ladder_numeric["out"]
    arts = load_all(out)
    entry = summary(arts)["inverse"]
    assert entry["method"].startswith("Chebyshev")
    (lo, hi), = entry["m_domain"]
    assert [lo, hi] == entry["kappa_range"][0] == entry["m_real_interval"]
    shown = f"y in kappa(V) = [{lo:.6g}, {hi:.6g}]"
    for name, at in (("m", "v8=90"), ("b", "i1=0,v2=1,i7=0,v8=90")):
        proc = _cli_eval(out, name, at)
        assert proc.returncode == 2, proc.stdout + proc.stderr
        assert proc.stderr.startswith(f"error: eval {name}: y = h(x) = 90 is outside the set where m is certified") and proc.stderr.count("\n") == 1
        assert shown in proc.stderr and proc.stdout == ""
    for name, at in (("m", {"v8": lo - 1e-3}), ("m", {"v8": hi + 1e-3}), ("c", {"i1": 0, "v2": 1, "i7": 0, "v8": 90})):
        with pytest.raises(SpecError, match=rf"eval {name}: .*outside the set where m is certified.*{re.escape(shown)}"):
            evaluate(arts, name, at)
    assert np.isfinite(evaluate(arts, "m", {"v8": (lo + hi) / 2})[0]) and np.isfinite(evaluate(arts, "m", {"v8": hi})[0])
    mid = _cli_eval(out, "m", f"v8={(lo + hi) / 2}")
    assert mid.returncode == 0 and mid.stdout.startswith("m(v8=")


def test_ladder_headline_and_summary_have_no_inf(ladder_numeric):
    line = next(l for l in ladder_numeric["design"].stderr.splitlines() if l.startswith("inverse"))  # progress: stderr
    assert "inf" not in line and "m (Chebyshev interpolant of kappa^-1) certified for y in kappa(V) = [9.90084, 24.2467]" in line
    entry = summary(load_all(ladder_numeric["out"]))["inverse"]
    assert "inf" not in json.dumps(entry) and None not in entry["m_real_interval"]


def test_eval_accepts_every_declared_name_and_refuses_undeclared_ones(cli_run):
    # Issue: `ashc eval DIR m --at` with all state names was refused because m uses only x4.
    out = cli_run["out"]
    proc = ashc("eval", str(out), "m", "--at", "x1=10.3256,x2=2.0561,x3=-4.9785,x4=-6.9732")
    assert proc.returncode == 0, proc.stderr
    proc = ashc("eval", str(out), "m", "--at", "x1=1,x2=1,x3=1,x4=-6.9732,u=0.5,xi=0.3,v=1")   # inputs and abstract names too
    assert proc.returncode == 0, proc.stderr
    proc = ashc("eval", str(out), "m", "--at", "x4=-6.9732,x9=1")
    assert proc.returncode == 2 and "unknown variable(s) x9" in proc.stderr


def test_p_and_kappa_only_on_V(paper_design):
    # V = [0, 0.95]: p and kappa are solved there; beyond it (a fitted p would extrapolate its end piece) eval refuses.
    assert evaluate(paper_design, "p", {"xi": 0.95})
    with pytest.raises(SpecError, match=r"eval p: xi=1.2 is outside V = \[0, 0.95\]"):
        evaluate(paper_design, "p", {"xi": 1.2})
    with pytest.raises(SpecError, match=r"eval kappa: xi=-0.1 is outside V"):
        evaluate(paper_design, "kappa", {"xi": -0.1})

"""Tests of summary and eval on artefacts (ashc_cli.query)."""

import pytest

from ashc_cli.errors import ArtefactError, DesignError, SpecError
from ashc_cli.query import evaluate, parse_point, summary


def test_parse_point():
    assert parse_point("xi=0.5, x1=-2e-3") == {"xi": 0.5, "x1": -0.002}
    for bad, fragment in (("xi", "not name=value"), ("xi=abc", "not a number"), ("", "no values"), ("xi=inf", "not finite")):
        with pytest.raises(SpecError, match=fragment):
            parse_point(bad)


def test_evaluate(paper_design):
    assert evaluate(paper_design, "kappa", {"xi": 0.0}) == [0.0]
    with pytest.raises(SpecError, match="needs a value for xi"):
        evaluate(paper_design, "p", {})
    with pytest.raises(SpecError, match="unknown variable"):
        evaluate(paper_design, "p", {"xi": 0.1, "zeta": 1})
    with pytest.raises(SpecError, match="cannot be evaluated"):
        evaluate(paper_design, "W", {"xi": 0.1})
    with pytest.raises(DesignError, match="not real"):
        evaluate(paper_design, "m", {"x1": 0, "x2": 0, "x3": 0, "x4": 500})
    partial = {k: v for k, v in paper_design.items() if k != "delta"}
    with pytest.raises(ArtefactError, match="no delta.h5"):
        evaluate(partial, "b", {"x1": 0, "x2": 0, "x3": 0, "x4": -1})


def test_summary_has_checks(paper_design):
    data = summary(paper_design)
    assert set(data) == set(paper_design)
    assert data["stabilise"]["checks"]["lmi_margin"]["passed"] is True
    assert data["bound"]["gain"] > 0

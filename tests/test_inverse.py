"""Tests of stage 4, the left inverse m and conditions (i), (ii), SimuLocalRequire."""

import math

import numpy as np
import pytest
import sympy as sp

from ashc_cli.errors import DesignError
from ashc_cli.model import build_model
from ashc_cli.spec import parse_spec_text
from ashc_cli.stages import inverse, kappa, manifold

from .conftest import CUK_PAPER_M

X0 = [10.3256, 2.0561, -4.9785, -6.9732]


def test_m_at_the_papers_point(paper_design, paper_model):
    # eq. egm and Section V-D: xi0 = m(x0) = 0.3677 (4 decimals printed).
    m = paper_model.numeric(paper_design["inverse"].exprs["m"], list(paper_model.x))
    assert m(*X0)[0, 0] == pytest.approx(0.3677, abs=5e-5)


def test_m_is_eq_egm(paper_design, paper_model):
    P = paper_model.params
    E, G_L, R_i = P["E"], P["G_L"], P["R_i"]
    x4 = paper_model.x[3]
    papers = (-E + 2 * x4 + sp.sqrt(E**2 - 4 * G_L * R_i * x4**2)) / (2 * (G_L * R_i + 1) * x4 - 2 * E)
    f = paper_model.numeric(sp.Matrix([paper_design["inverse"].exprs["m"][0] - papers]), [x4])
    assert np.abs(f(np.linspace(-126, 126, 1001))).max() < 1e-12


def test_left_inverse_on_V(paper_design, paper_model):
    # m(p(xi)) = xi on V to 1e-9, checked here on points of our own.
    art = paper_design["inverse"]
    xi = np.linspace(0, 0.95, 977)
    p = paper_model.numeric(paper_design["manifold"].exprs["p"], list(paper_model.xi))(xi)[:, 0, :]
    m = paper_model.numeric(art.exprs["m"], list(paper_model.x))(*p)[0, 0]
    assert np.abs(m - xi).max() < 1e-9
    assert art.values["left_inverse_residual"] < 1e-9


def test_m_real_exactly_for_x4_within_126_91(paper_design, paper_model):
    # eq. mEquation: solvable iff |x4| <= E / (2 sqrt(R_i G_L)) = 126.91.
    lo, hi = paper_design["inverse"].values["m_real_interval"]
    exact = 12.0 / (2 * math.sqrt(0.05 * 44.7e-3))
    assert hi == pytest.approx(exact, rel=1e-12) and lo == pytest.approx(-exact, rel=1e-12)
    assert round(hi, 2) == 126.91
    m = paper_model.numeric(paper_design["inverse"].exprs["m"], list(paper_model.x))
    assert np.isfinite(m(0, 0, 0, -126.9)[0, 0]) and np.isnan(m(0, 0, 0, -126.92)[0, 0])


def test_conditions_and_cover(paper_design):
    art = paper_design["inverse"]
    lo, hi = art.values["kappa_range"][0]
    assert lo <= -120 and hi >= 0  # kappa(V) covers Y = [-120, 0] (eq. SimuLocalRequire)
    assert art.values["condition_ii"] < 1e-9 and art.values["condition_ii_symbolic"]
    assert art.values["condition_i"] < 1e-9
    assert all(c.passed for c in art.checks.values())


def run_inverse_with(*pairs):
    text = CUK_PAPER_M.read_text()
    for old, new in pairs:
        assert old in text
        text = text.replace(old, new)
    model = build_model(parse_spec_text(text))
    man = manifold.run(model, {})
    return inverse.run(model, {"manifold": man, "kappa": kappa.run(model, {"manifold": man})})


def test_V_not_covering_Y_is_refused():
    with pytest.raises(DesignError, match=r"does not cover Y.*SimuLocalRequire"):
        run_inverse_with(("domain: [[0, 0.95]]", "domain: [[0, 0.9]]"))


def test_p_not_injective_is_refused():
    # On [0, 1] kappa turns (kappa(0) = kappa(1) = 0): no branch is a left inverse.
    with pytest.raises(DesignError, match="not injective"):
        run_inverse_with(("domain: [[0, 0.95]]", "domain: [[0, 1.0]]"))


def test_Y_beyond_where_m_is_real_is_refused():
    with pytest.raises(DesignError, match="where m is real"):
        run_inverse_with(("output_set: [[-120, 0]]", "output_set: [[-130, 0]]"))

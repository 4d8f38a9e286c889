"""Tests of stage 3, kappa = h o p (eq. SimuDesignCond2)."""

import numpy as np
import sympy as sp


def test_kappa_is_eq_egKappa(paper_design, paper_model):
    kappa = paper_design["kappa"].exprs["kappa"][0]
    P = paper_model.params
    xi = paper_model.xi[0]
    papers = P["E"] * xi * (xi - 1) / ((xi - 1) ** 2 + P["G_L"] * P["R_i"] * xi**2)
    assert sp.simplify(kappa - papers) == 0


def test_kappa_on_V(paper_design):
    art = paper_design["kappa"]
    lo, hi = np.asarray(art.values["kappa_range"])[0]
    # kappa(0) = 0 and kappa(0.95) = -126.19 (Fig. kappa_xi): V = [0, 0.95] reaches below -120.
    assert hi == 0.0
    assert lo < -120.0
    assert art.checks["kappa_finite"].passed

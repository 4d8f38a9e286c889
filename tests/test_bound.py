"""Tests of stage 6, the error bound (eqs. egConditionB, iota, egErrorBound) against the paper's numbers."""

import numpy as np
import pytest

from ashc_cli.stages import bound

PAPER_M = np.array([[0.4804, 0.0102, 0.0002, -0.0093], [0.0102, 0.5304, 0.0081, 0.0001],
                    [0.0002, 0.0081, 0.4824, -0.0135], [-0.0093, 0.0001, -0.0135, 0.5304]])
C = np.array([[0.0, 0.0, 0.0, 1.0]])


def test_alpha_h_exact(paper_design):
    # ERRATA item 4: the largest c with M >= c C^T C is 1 / (C M^-1 C^T); the paper prints it rounded down as 0.52.
    alpha_h = paper_design["bound"].values["alpha_h"]
    assert alpha_h == pytest.approx(1.0 / (C @ np.linalg.solve(PAPER_M, C.T))[0, 0], rel=1e-12)
    assert alpha_h >= 0.52
    assert np.linalg.eigvalsh(PAPER_M - alpha_h * C.T @ C).min() > -1e-12  # M >= alpha_h C^T C
    assert np.linalg.eigvalsh(PAPER_M - 1.001 * alpha_h * C.T @ C).min() < 0   # and it is the largest


def test_dbar_delta_one_within_1_percent_of_1760(paper_design):
    # Fig. delta_Compare (left), q = 0, delta = 1: the paper reads dbar = 1760 off its figure (ERRATA item 5).
    dbar = paper_design["bound"].values["dbar_q0_identity"]
    assert dbar == pytest.approx(1760, rel=0.01)
    assert paper_design["bound"].values["dbar_argmax"][1][0] == pytest.approx(0.95)


def test_dbar_egDelta_within_0_1_percent_of_12_35(paper_design):
    # Fig. delta_Compare (right), q = 0, delta of eq. egDelta: dbar = 12.35; its maximum is at xi = 0 (ERRATA item 6).
    art = paper_design["bound"]
    assert art.values["dbar_q0"] == pytest.approx(12.35, rel=1e-3)
    assert art.values["dbar_argmax"][0][0] == pytest.approx(0.0, abs=1e-6)
    assert art.values["dbar_q0_squared"] == pytest.approx(art.values["dbar_q0"] ** 2)


def test_papers_bound_1453_from_its_rounded_inputs():
    # Final remark of Section V: sqrt(1/0.26) x 12.35 x 60 = 1453.22 (eq. egErrorBound, lambda = 2, eps = 1).
    assert bound.error_bound_gain(0.52, 2.0, 1.0, 12.35) * 60 == pytest.approx(1453.22, abs=0.005)


def test_exact_bound_from_the_tools_numbers(paper_design):
    art = paper_design["bound"].values
    assert art["epsilon"] == 1.0
    gain = np.sqrt(2.0 / (art["alpha_h"] * 1.0 * 1.0)) * art["dbar_q0"]
    assert art["gain"] == pytest.approx(gain, rel=1e-12)
    # With the exact alpha_h = 0.52984 and dbar = 12.3526 the paper's 1453.22 becomes 1440.0.
    assert art["gain"] * 60 == pytest.approx(1439.97, abs=0.05)
    assert art["gain_comparison"] == pytest.approx(art["gain"] / np.sqrt(2))


def test_least_squares_q_never_increases_theta(paper_design):
    v = paper_design["bound"].values
    assert np.all(v["theta_norm_ls_manifold"] <= v["theta_norm_q0"] + 1e-12)
    assert v["dbar_ls"] <= v["dbar_q0"]


def test_theta_norms_least_squares_is_a_projection():
    rng = np.random.default_rng(0)
    L = np.linalg.cholesky(PAPER_M)
    dpd = rng.normal(size=(4, 1, 50))
    g = rng.normal(size=(4, 1, 50))
    full, ls = bound.theta_norms(L, dpd, None), bound.theta_norms(L, dpd, g)
    for k in range(50):
        a, b = L.T @ dpd[:, :, k], L.T @ g[:, :, k]
        resid = a - b * (b.T @ a) / (b.T @ b)
        assert ls[k] == pytest.approx(np.linalg.norm(resid))
        assert full[k] == pytest.approx(np.sqrt(dpd[:, 0, k] @ PAPER_M @ dpd[:, 0, k]))

"""Tests of ashc_cli.design.contraction.structured: the metric a large plant's structure gives, checked by an
eigenvalue, used instead of an SDP, and proved above 64 states by the banded Cholesky."""

import numpy as np
import pytest

from ashc_cli.design.contraction import structured
from ashc_cli.design.contraction.vertex import largest_decay_rate_for
from ashc_cli.design.stages import stabilise
from ashc_cli.numerics import proofs
from ashc_cli.problem.examples import ladder
from ashc_cli.problem.model import build_model
from ashc_cli.problem.spec import parse_spec_text


def _lc_line(n_pairs: int, L: float, C: float, r: float, G: float, u: float = 0.0) -> np.ndarray:
    """An LC line i_k' = (v_{k-1} - v_k - r i_k) / L, v_k' = (i_k - i_{k+1} - G v_k) / C, first coupling scaled by 1 - u."""
    n = 2 * n_pairs
    A = np.zeros((n, n))
    for k in range(n_pairs):
        i, v = 2 * k, 2 * k + 1
        A[i, i], A[v, v] = -r / L, -G / C
        A[i, v], A[v, i] = -1 / L, 1 / C
        if k + 1 < n_pairs:
            A[v, i + 2], A[i + 2, v] = -1 / C, 1 / L
    A[0, 1] *= 1 - u
    A[1, 0] *= 1 - u
    return A


def test_the_balancing_diagonal_is_the_stored_energy_of_an_lc_line():
    L, C = 2e-3, 5e-4
    A = _lc_line(6, L, C, r=0.1, G=0.02)
    d = structured.balancing_diagonal(A)
    # d_v / d_i = C / L: the energy L i^2 / 2 + C v^2 / 2 up to a common factor
    np.testing.assert_allclose(d[1::2] / d[0::2], C / L, rtol=1e-10)
    assert d.sum() == pytest.approx(A.shape[0])
    S = A.T @ np.diag(d) + np.diag(d) @ A
    np.testing.assert_allclose(S - np.diag(np.diag(S)), 0.0, atol=1e-9 * np.abs(S).max())   # the couplings cancel


def test_a_diagonal_that_certifies_the_rate_is_taken_and_a_plant_without_skew_couplings_falls_back():
    L, C, r, G = 2e-3, 5e-4, 0.1, 0.02
    vertices = [_lc_line(6, L, C, r, G, u) for u in (0.0, 1.0)]
    exact = min(2 * r / L, 2 * G / C)                  # the energy metric's rate: the losses over the storage
    M, name, tried = structured.structured_M(vertices, 0.9 * exact, "auto")
    assert name == structured.BALANCE and tried[0][1] == pytest.approx(exact, rel=1e-9)
    assert largest_decay_rate_for(vertices, M) > 0.9 * exact
    assert structured.structured_M(vertices, 1.01 * exact, "diagonal") is None      # above what a diagonal M gives: the SDP's turn
    # a one-sided coupling: no pair to balance, the identity fails, only the Lyapunov candidate remains
    A = np.array([[-1.0, 30.0], [0.0, -1.0]])
    found = structured.structured_M([A], 1.0, "auto")
    assert found is not None and found[1] == structured.LYAPUNOV_MEAN
    assert [t for t, _ in found[2]] == [structured.IDENTITY, structured.LYAPUNOV_MEAN]
    assert structured.structured_M([A], 1.0, "diagonal") is None


def test_the_128_state_ladder_is_certified_without_an_sdp_and_proved_above_64_states():
    model = build_model(parse_spec_text(ladder(32)))
    assert model.n == 128 > proofs.MAX_PROOF_STATES
    art = stabilise.run(model, {})
    assert art.meta["solver"].startswith("none: M = " + structured.BALANCE) and art.meta["structure"] == "diagonal"
    assert art.checks["lmi_margin"].evidence == proofs.PROVED and art.values["lmi_margin_proved"] <= 0
    assert art.checks["M_positive"].evidence == proofs.PROVED
    # the proof is not a formality: at a rate the metric cannot carry the same proof fails
    from ashc_cli.design.contraction.proof import prove_lmi
    poly = stabilise.polytopes(model, stabilise.sparse_jacobian(model.f, model.x))[0][0]
    M, K = art.values["M"], np.zeros((model.m, model.n))
    rate = largest_decay_rate_for([np.asarray(A) for A in poly.matrices], M)
    assert prove_lmi(model, poly, K, M, 0.99 * rate)[0] <= 0
    assert prove_lmi(model, poly, K, M, 1.01 * rate)[0] == np.inf

"""Tests of ashc_cli.design.contraction.network: networks of dissipative terms, their diagonal M and a banded proof."""

import numpy as np
import pytest
import scipy.sparse as sps

from ashc_cli.numerics import proofs
from ashc_cli.design.contraction import network, terms
from ashc_cli.problem.examples import rc_ladder
from ashc_cli.problem.model import build_model, sparse_jacobian
from ashc_cli.problem.spec import parse_spec_text
from ashc_cli.design.stages import stabilise


def _ladder_lower_matrix(N: int) -> np.ndarray:
    """The ladder's Jacobian with every diode slope at its lowest on the box, written from the equations: node 1
    grounded through g(x1) (x1 in [-0.05, 0.05]: slope >= 40 e^-2 + 1), each branch g(x(k-1) - xk) (differences in
    [-0.1, 0.1]: slope >= 40 e^-4 + 1)."""
    ground, branch = 40 * np.exp(-2.0) + 1, 40 * np.exp(-4.0) + 1
    A = np.zeros((N, N))
    A[0, 0] -= ground
    for k in range(1, N):
        c = np.zeros(N)
        c[k - 1], c[k] = 1.0, -1.0
        A -= branch * np.outer(c, c)
    return A


def test_a_ladder_of_fifty_diodes_gets_M_identity_and_the_laplacian_rate():
    model = build_model(parse_spec_text(rc_ladder(50)))
    art = stabilise.run(model, {})
    assert art.meta["polytope"] == "Jacobian terms (network)"
    np.testing.assert_array_equal(art.values["M"], np.eye(50))       # the network's own storage function, exactly
    A = _ladder_lower_matrix(50)
    expected = float(np.linalg.eigvalsh(-(A + A.T)).min())          # M = I: lambda = lambda_min(-(A + A^T))
    assert art.values["lambda"] == pytest.approx(expected * (1 - network.BACKOFF), rel=1e-9)
    assert art.checks["lmi_margin"].evidence == "proved" and art.checks["M_positive"].evidence == "proved"


def test_dissipative_storage_finds_capacitances_and_refuses_a_non_dissipative_term():
    # x1' = (-g(x1 - x2)) / C1, x2' = g(x1 - x2) / C2 - x2: the diode is dissipative under M = diag(C1, C2)
    text = """
name: two_caps
parameters: {C1: 2.0, C2: 0.5}
concrete:
  states: [x1, x2]
  inputs: [u]
  f_bar: ["-(exp(4*(x1 - x2)) - 1)/C1 - x1/C1", "(exp(4*(x1 - x2)) - 1)/C2 - x2/C2"]
  g: [["1"], ["0"]]
  h: ["x1"]
  input_bounds: [[0, 1]]
  output_set: [[0.1, 0.3]]
  state_box: [[-1, 1], [-1, 1]]
stabilisability: {method: polytopic_lmi, decay_rate: maximise}
abstract:
  states: [xi]
  inputs: [v]
  phi_bar: ["0"]
  l: ["xi"]
  domain: [[0, 1]]
"""
    model = build_model(parse_spec_text(text))
    T = terms.decompose(model, sparse_jacobian(model.f, model.x))
    net = network.dissipative_storage(T, 2)
    assert net is not None and net.dissipative == [0]
    assert net.d[0] / net.d[1] == pytest.approx(2.0 / 0.5, rel=1e-12)
    # flip the sign of the diode at node 2: b is no longer -c up to the capacitances
    bad = build_model(parse_spec_text(text.replace('"(exp(4*(x1 - x2)) - 1)/C2 - x2/C2"', '"-(exp(4*(x1 - x2)) - 1)/C2 - x2/C2"')))
    assert network.dissipative_storage(terms.decompose(bad, sparse_jacobian(bad.f, bad.x)), 2) is None


def test_the_banded_proof_bounds_lambda_min_of_a_long_tridiagonal_matrix():
    from flint import arb

    for n in (100, 1000):
        S = {}
        for i in range(n):
            S[(i, i)] = arb(2)
            if i + 1 < n:
                S[(i, i + 1)] = S[(i + 1, i)] = arb(-1)
        exact = 2 - 2 * np.cos(np.pi / (n + 1))
        bound = proofs.sparse_psd_lower_bound(S, n)
        assert 0 < bound <= exact
        # and an indefinite matrix is not "proved" positive
        S[(0, 0)] = arb(0.5)
        S[(n // 2, n // 2)] = arb(-1)
        assert proofs.sparse_psd_lower_bound(S, n) == -np.inf


def test_network_rate_is_the_generalised_eigenvalue():
    rng = np.random.default_rng(1)
    A = -np.diag(rng.uniform(1, 2, 6)) + 0.1 * rng.normal(size=(6, 6))
    d = rng.uniform(0.5, 2, 6)
    lam = network.largest_rate(sps.csr_matrix(A), d)
    M = np.diag(d)
    assert np.linalg.eigvalsh(A.T @ M + M @ A + lam * M).max() == pytest.approx(0.0, abs=1e-10)

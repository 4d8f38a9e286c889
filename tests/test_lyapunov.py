"""Tests of ashc_cli.design.contraction.lyapunov: large linear plants without an SDP, and refusals before memory runs out."""

import numpy as np
import pytest

from ashc_cli.design.contraction import lyapunov
from ashc_cli.errors import DesignError
from ashc_cli.problem.examples import chain
from ashc_cli.problem.model import build_model
from ashc_cli.problem.spec import parse_spec_text
from ashc_cli.design.stages import stabilise


def test_a_chain_of_one_hundred_masses_gets_its_M_from_the_lyapunov_equation():
    model = build_model(parse_spec_text(chain(100)))
    art = stabilise.run(model, {})
    assert "Lyapunov" in art.meta["solver"] and model.n == 200
    A = np.asarray(art.values["A_vertices"])[0]
    sup = -2 * np.linalg.eigvals(A).real.max()
    assert art.values["lambda"] == pytest.approx(sup * (1 - stabilise.BISECTION_RTOL), rel=1e-9)
    M, lam = art.values["M"], art.values["lambda"]
    assert np.linalg.eigvalsh(A.T @ M + M @ A + lam * M).max() < 0 < np.linalg.eigvalsh(M).min()


def test_lyapunov_M_solves_the_equation_and_refuses_a_rate_beyond_the_eigenvalues():
    A = np.array([[-1.0, 2.0], [0.0, -3.0]])
    M = lyapunov.lyapunov_M(A, 1.0)
    S = A.T @ M + M @ A + 1.0 * M
    # M solves the equation with -I on the right, scaled to trace 2: S is a negative multiple of I
    assert S[0, 0] < 0
    np.testing.assert_allclose(S, S[0, 0] * np.eye(2), atol=1e-12)
    assert np.trace(M) == pytest.approx(2.0)
    assert lyapunov.lyapunov_M(A, 2.0) is None                     # A + I has the eigenvalue 0


def test_an_sdp_that_would_not_fit_is_refused_with_its_estimate(monkeypatch):
    monkeypatch.setattr(lyapunov, "available_memory", lambda: 1.0e9)
    from ashc_cli.design.contraction import vertex

    monkeypatch.setattr(vertex, "FULL_MAX_STATES", 1000)            # force the full-M SDP on a 64-state plant
    monkeypatch.setattr(stabilise, "structured_M", lambda *args: None)   # as if no structured M certified it
    from ashc_cli.problem.examples import ladder

    model = build_model(parse_spec_text(ladder(16).replace("structure: auto", "structure: full")))
    with pytest.raises(DesignError, match=r"stabilisability\.structure: the full-M SDP of eq\. \(28\) for n = 64 states .* would need about "
                                          r"\d+\.\d GiB, more than the 0\.7 GiB available"):
        stabilise.run(model, {})
    assert lyapunov.sdp_memory_estimate(200, 2, "full") > 24 * 2**30 > lyapunov.sdp_memory_estimate(200, 2, "diagonal")

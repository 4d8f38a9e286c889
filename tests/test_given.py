"""Tests of ashc_cli.design.contraction.given: method given with M and K from the spec or the linearisation, proved by
the vertex argument when df/dx has few terms, else by the norm-bound test whose cost grows with the entries."""

import numpy as np
import sympy as sp
import pytest
import scipy.linalg as sla
import yaml

from ashc_cli.design.contraction import given
from ashc_cli.design.stages import stabilise
from ashc_cli.errors import DesignError, SpecError
from ashc_cli.numerics import proofs
from ashc_cli.problem import examples
from ashc_cli.problem.model import build_model, sparse_jacobian
from ashc_cli.problem.spec import parse_spec_text

from .conftest import SPECS


def ring(N: int = 8, theta: float = 0.15, **stab) -> str:
    """`ashc example ring` (N pendulums coupled all to all, 2 N + N (N - 1) / 2 distinct terms: 44 at N = 8) with method
    given and M: lyapunov, the angles' box +-theta."""
    spec = yaml.safe_load(examples.ring(N))
    spec["stabilisability"] = {"method": "given", "decay_rate": "maximise", "M": "lyapunov", **stab}
    spec["concrete"]["state_box"] = [[-theta, theta] if k % 2 == 0 else [-0.5, 0.5] for k in range(2 * N)]
    return yaml.safe_dump(spec, sort_keys=False, width=300)


def test_a_plant_with_44_distinct_terms_is_proved_by_the_norm_bound_test_and_holds_at_sampled_corners():
    model = build_model(parse_spec_text(ring(8)))
    art = stabilise.run(model, {})
    assert art.meta["route"].startswith("the norm-bound test") and "44 distinct nonlinear terms" in art.meta["norm_bound"]
    assert art.checks["lmi_margin"].evidence == proofs.PROVED and art.values["lmi_margin_proved"] <= 0
    M, lam = art.values["M"], float(art.values["lambda"])
    assert lam > 0.5                                                    # 0.955 measured; the sampled supremum of this M is higher
    # attack: the corners of the state box and random points, where |sin| and the couplings are extreme
    J = model.numeric(sparse_jacobian(model.f, model.x), list(model.x) + list(model.u))
    rng = np.random.default_rng(7)
    box = np.r_[model.state_box, model.U]
    points = np.r_[box[:, 0] + rng.random((300, len(box))) * np.ptp(box, axis=1), np.where(rng.random((300, len(box))) < 0.5, box[:, 0], box[:, 1])]
    worst = max(np.linalg.eigvalsh(A.T @ M + M @ A + lam * M).max() for A in (np.asarray(J(*pt)).reshape(model.n, model.n) for pt in points))
    assert worst < 0


def test_the_norm_bound_holds_for_every_deviation_within_its_bounds_and_the_proof_refuses_a_rate_above_it():
    rng = np.random.default_rng(1)
    n = 6
    R = rng.normal(size=(n, n))
    M = R @ R.T + n * np.eye(n)
    C = np.abs(rng.normal(size=(n, n))) * (rng.random((n, n)) < 0.5)
    b = given.beta(M, C)
    for _ in range(200):
        D = C * rng.uniform(-1, 1, size=(n, n))
        D[rng.random((n, n)) < 0.3] = 0.0
        D = np.where(rng.random((n, n)) < 0.5, np.sign(D) * C, D)          # many at the ends of their range
        assert sla.eigh(-(D.T @ M + M @ D), M, eigvals_only=True).min() >= -2 * b * (1 + 1e-12)
    A0 = -3 * np.eye(n) + 0.3 * rng.normal(size=(n, n))
    nb = given.NormBound(A0, 0.05 * C, True, int(np.count_nonzero(C)))
    rate = given.largest_rate(nb, M, np.zeros((n, n)))
    assert rate > 0
    model = build_model(parse_spec_text(ring(3)))                      # only its g is read, and only with a gain
    assert given.prove(model, nb, M, np.zeros((1, n)), 0.99 * rate)[0] <= 0
    assert given.prove(model, nb, M, np.zeros((1, n)), 1.01 * rate)[0] > 0


def test_lqr_and_lyapunov_give_a_proved_certificate_on_the_inverted_pendulum_by_the_vertex_argument():
    text = (SPECS / "inverted_pendulum.yaml").read_text().replace("  method: polytopic_lmi\n", "  method: given\n  M: lyapunov\n  K: lqr\n")
    model = build_model(parse_spec_text(text))
    art = stabilise.run(model, {})
    A0 = np.array([[0.0, 1.0], [9.81, -0.5]])                   # df/dx at the centre of the state box (x1 = 0)
    B = np.array([[0.0], [2.0]])
    P = sla.solve_continuous_are(A0, B, np.eye(2), np.eye(1))
    np.testing.assert_allclose(art.values["K"], -B.T @ P, rtol=1e-9)
    assert art.meta["route"].startswith("the vertices") and art.meta["K_source"].startswith("lqr")
    assert art.checks["lmi_margin"].evidence == proofs.PROVED and float(art.values["lambda"]) == 1.0


@pytest.mark.parametrize("edit, where", [
    (lambda s: s.replace("  M: lyapunov\n", "  M: lyapunov\n  K: lqr\n"), "stabilisability.K"),                   # K with identity feedback
    (lambda s: s.replace("  M: lyapunov\n", "  M: lyapunov\n  linearise_at: {x: [0.0], u: [0.0]}\n"), "stabilisability.linearise_at.x"),
    (lambda s: s.replace("  method: given\n", "  method: polytopic_lmi\n"), "stabilisability.M"),
])
def test_given_keys_out_of_place_are_refused_naming_them(edit, where):
    text = edit(ring(2))
    with pytest.raises(SpecError, match=where.replace(".", r"\.")):
        build_model(parse_spec_text(text))


def test_a_metric_that_cannot_carry_the_box_is_refused_with_the_rate_it_allows():
    model = build_model(parse_spec_text(ring(8, theta=1.2)))
    with pytest.raises(DesignError, match=r"stabilisability\.M: does not satisfy eq\. \(28\) at any positive decay rate by the norm-bound test .*\(the largest lambda it allows is -"):
        stabilise.run(model, {})


def test_polytopic_lmi_on_too_many_terms_takes_the_norm_bound_test_by_itself_and_says_so():
    text = ring(8).replace("  method: given\n", "  method: polytopic_lmi\n").replace("  M: lyapunov\n", "")
    art = stabilise.run(build_model(parse_spec_text(text)), {})
    assert art.meta["route"].startswith("automatic: the norm-bound test") and art.meta["method"] == "polytopic_lmi"
    assert art.checks["lmi_margin"].evidence == proofs.PROVED and float(art.values["lambda"]) > 0.5
    assert "(method polytopic_lmi, by automatic: the norm-bound test" in stabilise.headline(art)
    # where even that proves nothing, the refusal names both and what to change
    wide = ring(8, theta=1.2).replace("  method: given\n", "  method: polytopic_lmi\n").replace("  M: lyapunov\n", "")
    with pytest.raises(DesignError, match=r"^stabilisability: df/dx has 44 distinct nonlinear terms .*; the norm-bound test with M from the Lyapunov"):
        stabilise.run(build_model(parse_spec_text(wide)), {})


def test_a_gain_from_lqr_on_the_norm_bound_route_is_proved_with_b_k_in_ball_arithmetic():
    art = stabilise.run(build_model(parse_spec_text(ring(8, feedback="linear_gain", K="lqr"))), {})
    assert art.meta["route"].startswith("the norm-bound test") and art.meta["K_source"].startswith("lqr")
    assert np.any(art.values["K"] != 0) and art.checks["lmi_margin"].evidence == proofs.PROVED


def _mixed_network(N: int = 11) -> str:
    """A chain of N nodes with three kinds of nonlinearity: a sine and a cubic damping at each node and a saturating
    (tanh) coupling on each edge: 2 N + (N - 1) distinct nonlinear terms in df/dx (cos x_i, x_i^2, tanh^2 of each
    edge), 32 at N = 11."""
    f = []
    for i in range(1, N + 1):
        t = f"-a*x{i} - d*sin(x{i}) - e*x{i}**3"
        t += f" - c*tanh(x{i} - x{i - 1})" if i > 1 else ""
        t += f" - c*tanh(x{i} - x{i + 1})" if i < N else ""
        f.append(f'"{t}"')
    states = ", ".join(f"x{i}" for i in range(1, N + 1))
    g = ", ".join(['["1"]'] + ['["0"]'] * (N - 1))
    box = ", ".join(["[-1, 1]"] * N)
    return (f"name: mixed_network\nparameters: {{a: 1.0, c: 0.5, d: 0.3, e: 0.2}}\n"
            f"concrete: {{states: [{states}], inputs: [u], f_bar: [{', '.join(f)}], g: [{g}], h: [x{N}],\n"
            f"           input_bounds: [[-1, 1]], output_set: [[-0.5, 0.5]], state_box: [{box}]}}\n"
            "stabilisability: {method: polytopic_lmi, decay_rate: 1.0}\n"
            'abstract: {states: [xi], inputs: [v], phi_bar: ["0"], l: ["xi"], domain: [[-0.5, 0.5]]}\n')


def test_a_network_of_32_terms_of_three_kinds_is_proved_and_says_by_which_route():
    # issue 43: sines, cubes and saturating couplings, 32 distinct terms: beyond the vertex enumeration, so the
    # automatic route is the norm-bound test; the rate asked for is proved, and the stage's line names the route
    from ashc_cli.design.contraction import terms as term_mod
    from ashc_cli.design.pipeline import STAGES, headline
    from ashc_cli.problem.model import sparse_jacobian

    model = build_model(parse_spec_text(_mixed_network()))
    found = term_mod.decompose(model, sparse_jacobian(model.f, model.x))
    kinds = {type(t).__name__ for th in found.thetas for t in sp.preorder_traversal(th) if isinstance(t, sp.Function)}
    assert len(found.thetas) == 32 and {"cos", "tanh"} <= kinds
    art = stabilise.run(model, {})
    assert art.values["lambda"] == 1.0 and art.checks["lmi_margin"].evidence == "proved" and art.values["lmi_margin_proved"] < 0
    assert "norm-bound test" in art.meta["route"] and "norm-bound test" in headline(STAGES["stabilise"], art)

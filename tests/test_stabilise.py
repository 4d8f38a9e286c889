"""Tests of stage 1, stabilisability (eq. egLMI)."""

import re

import numpy as np
import pytest

from ashc_cli.errors import DesignError
from ashc_cli.problem.model import build_model
from ashc_cli.paper import cite
from ashc_cli.problem.spec import load_spec, parse_spec_text
from ashc_cli.design.contraction import terms, vertex
from ashc_cli.design.stages import stabilise

from .conftest import CUK


def model_with(*pairs):
    text = CUK.read_text()
    for old, new in pairs:
        assert old in text
        text = text.replace(old, new)
    return build_model(parse_spec_text(text))


def test_affine_form_is_the_papers_A(paper_model):
    A, b = stabilise.affine_form(paper_model)
    num = paper_model.numeric(A, list(paper_model.u))
    R_i, L_1, C_2, G_L, L_3, C_4 = 0.05, 10e-3, 11e-3, 44.7e-3, 10e-3, 11e-3
    u = 0.3
    # eq. ConvertSystemLinear (with G_l read as G_L, ERRATA item 2)
    expected = np.array([[-R_i / L_1, -(1 - u) / L_1, 0, 0], [(1 - u) / C_2, 0, u / C_2, 0],
                         [0, -u / L_3, 0, -1 / L_3], [0, 0, 1 / C_4, -G_L / C_4]])
    assert np.allclose(num(u), expected, rtol=1e-14)
    assert list(b) == [paper_model.params["E"] / paper_model.params["L_1"], 0, 0, 0]


def test_papers_M_is_verified_at_both_vertices(paper_design):
    # eq. egM with lambda = 2: A(u)^T M + M A(u) + 2 M <= 0 at u = 0 and u = 1.
    art = paper_design["stabilise"]
    margins = art.values["vertex_margins"]
    assert np.all(margins < 0)
    assert margins == pytest.approx([-0.51310, -0.0018510], rel=1e-3)
    assert art.values["lmi_margin"] <= 0 and art.checks["lmi_margin"].passed


def test_own_lmi_solution_is_certified_and_rechecked():
    model = build_model(load_spec(CUK))
    art = stabilise.run(model, {})
    M, lam = art.values["M"], art.values["lambda"]
    assert lam == 2.0
    # Independent numpy re-check on a sweep of U (eq. egLMI), not the stage's own numbers.
    for u in np.linspace(0, 1, 101):
        A = np.asarray(model.numeric(stabilise.affine_form(model)[0], list(model.u))(u))
        assert np.linalg.eigvalsh(A.T @ M + M @ A + lam * M).max() <= 0
    assert np.linalg.eigvalsh(M).min() > 0
    assert art.values["lmi_margin"] < -1e-3


def test_maximise_finds_the_largest_rate():
    art = stabilise.run(model_with(("decay_rate: 2.0", "decay_rate: maximise")), {})
    lam = art.values["lambda"]
    # lambda <= -2 max Re eig(A(1)) = 2.0314 (a necessary bound), and lambda = 2 is feasible.
    assert 2.0 < lam <= 2.0314
    assert art.values["lmi_margin"] <= 0


def test_infeasible_rate_names_the_largest_feasible():
    with pytest.raises(DesignError, match=r"infeasible at lambda = 3.*below 2\.0[0-9]* \(the largest the solver certifies\)"):
        stabilise.run(model_with(("decay_rate: 2.0", "decay_rate: 3.0")), {})


def test_given_M_that_does_not_certify():
    model = model_with(("method: polytopic_lmi", "method: given"), ("feedback: identity", "feedback: identity\n  M: [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]"))
    # Messages cite the paper's numbering (eq. egLMI is printed as its number, ashc_cli/paper.py).
    with pytest.raises(DesignError, match=re.escape(cite("does not satisfy eq. egLMI"))):
        stabilise.run(model, {})


def test_f_not_affine_in_x_is_refused():
    model = model_with(('"x1/C_2"', '"x1**2/C_2"'))
    with pytest.raises(DesignError, match="not affine in x"):
        stabilise.run(model, {})


def test_linear_gain_makes_an_unstable_plant_incrementally_stable():
    from .conftest import SPECS

    model = build_model(load_spec(SPECS / "unstable_linear.yaml"))
    art = stabilise.run(model, {})
    M, K, lam = art.values["M"], art.values["K"], art.values["lambda"]
    A = np.array([[0.0, 1.0], [1.0, 0.0]])
    B = np.array([[0.0], [1.0]])
    assert np.linalg.eigvals(A).real.max() > 0          # not incrementally stable on its own
    Acl = A + B @ K
    # Independent re-check of (A + B K)^T M + M (A + B K) <= -lambda M (eq. egLMI with k = u + K (z - x)).
    assert np.linalg.eigvalsh(Acl.T @ M + M @ Acl + lam * M).max() <= 0
    assert np.linalg.eigvalsh(M).min() > 0 and lam == 2.0


def test_identity_feedback_on_an_unstable_plant_suggests_linear_gain():
    from .conftest import SPECS

    text = (SPECS / "unstable_linear.yaml").read_text().replace("feedback: linear_gain", "feedback: identity")
    with pytest.raises(DesignError, match="feedback: linear_gain"):
        stabilise.run(build_model(parse_spec_text(text)), {})


def ladder_model(stages: int, *pairs):
    from ashc_cli.problem.examples import ladder

    text = ladder(stages)
    for old, new in pairs:
        assert old in text
        text = text.replace(old, new)
    return build_model(parse_spec_text(text))


def test_diagonal_M_certifies_the_ladder():
    # The ladder's stored energy H = diag(L, C, ...) certifies lambda = 2 min(r/L, G_c/C) = 4 (examples.py), so
    # a diagonal M exists for the spec's lambda = 2; the re-check below is independent of the stage's numbers.
    model = ladder_model(2, ("decay_rate: 2.0", "decay_rate: 2.0\n  structure: diagonal"))
    art = stabilise.run(model, {})
    M = art.values["M"]
    assert art.meta["structure"] == "diagonal" and np.count_nonzero(M - np.diag(np.diag(M))) == 0
    A_num = model.numeric(stabilise.affine_form(model)[0], list(model.u))
    for u in np.linspace(0, 1, 11):
        A = np.asarray(A_num(u), dtype=float)
        assert np.linalg.eigvalsh(A.T @ M + M @ A + 2.0 * M).max() < 0
    assert np.diag(M).min() > 0


def test_auto_structure_is_full_for_small_plants_and_diagonal_first_for_large(monkeypatch):
    assert stabilise.structures("auto", stabilise.FULL_MAX_STATES) == ["full"]
    assert stabilise.structures("auto", stabilise.FULL_MAX_STATES + 1) == ["diagonal", "full"]
    assert stabilise.structures("full", 500) == ["full"]
    monkeypatch.setattr(vertex, "FULL_MAX_STATES", 4)
    art = stabilise.run(ladder_model(2), {})
    assert art.meta["structure"] == "diagonal" and art.meta["tried"] == ["diagonal"]


OSCILLATOR = """
name: damped_oscillator
parameters: {}
concrete:
  states: [x1, x2]
  inputs: [u]
  f_bar: ["x2", "-x1 - x2"]
  g: [["0"], ["1"]]
  h: ["x1"]
  input_bounds: [[-1, 1]]
  output_set: [[-0.5, 0.5]]
stabilisability: {method: polytopic_lmi, decay_rate: 0.2, feedback: identity, structure: STRUCTURE}
abstract: {states: [xi], inputs: [w], phi_bar: ["0"], l: ["xi"], domain: [[-1, 1]]}
"""


def test_a_plant_without_diagonal_certificate_falls_back_to_full(monkeypatch):
    # x1' = x2: the (1, 1) entry of A^T D + D A + lambda D is lambda d1 > 0 for every diagonal D, so no diagonal M
    # exists; a full one does (A is Hurwitz with eigenvalues -1/2 +- 0.87 i, so any lambda < 1 is feasible).
    with pytest.raises(DesignError, match="infeasible at lambda = 0.2.*M diagonal"):
        stabilise.run(build_model(parse_spec_text(OSCILLATOR.replace("STRUCTURE", "diagonal"))), {})
    monkeypatch.setattr(vertex, "FULL_MAX_STATES", 1)
    art = stabilise.run(build_model(parse_spec_text(OSCILLATOR.replace("STRUCTURE", "auto"))), {})
    assert art.meta["tried"] == ["diagonal", "full"] and art.meta["structure"] == "full"
    assert art.values["lmi_margin"] < 0


def test_maximise_with_a_diagonal_M_reaches_the_energy_rate():
    # With M = H the ladder's rate is 2 min(r/L, G_c/C) = 4 (examples.py); no diagonal M does better here, since
    # the capacitors' own decay G_c/C = 2 bounds lambda/2 through the diagonal entries of A^T D + D A + lambda D.
    model = ladder_model(1, ("decay_rate: 2.0", "decay_rate: maximise\n  structure: diagonal"))
    art = stabilise.run(model, {})
    assert art.values["lambda"] == pytest.approx(4.0, rel=2 * stabilise.BISECTION_RTOL)
    assert art.values["lmi_margin"] <= 0


# --- Decay rate not capped by the normalisation of M (specs/quarter_car.yaml) -------------------------------

QUARTER_CAR_PARAMS = {"m_s": 300.0, "m_u": 40.0, "k_s": 16000.0, "c_s": 1000.0, "k_t": 190000.0}


def quarter_car_A(m_s=300.0, m_u=40.0, k_s=16000.0, c_s=1000.0, k_t=190000.0):
    """A of the quarter car, written from its equations of motion (x = z_s, z_s', z_u, z_u'), not from the stage."""
    return np.array([[0.0, 1.0, 0.0, 0.0],
                     [-k_s / m_s, -c_s / m_s, k_s / m_s, c_s / m_s],
                     [0.0, 0.0, 0.0, 1.0],
                     [k_s / m_u, c_s / m_u, -(k_s + k_t) / m_u, -c_s / m_u]])


def modal_M(A):
    """M = W^H W with W = V^-1 (A = V diag(mu) W): A^T M + M A = W^H diag(2 Re mu) W <= 2 max Re mu M exactly."""
    W = np.linalg.inv(np.linalg.eig(A)[1])
    return (W.conj().T @ W).real


def min_condition_M(A, lam, margin=1e-6):
    """Independent SDP (own code, not the stage's): minimise k subject to I <= M <= k I and
    A^T M + M A + lam M <= -margin k I.  Returns M, or None when infeasible or not certified in numpy."""
    import cvxpy as cp

    n = A.shape[0]
    M, k = cp.Variable((n, n), symmetric=True), cp.Variable()
    cp.Problem(cp.Minimize(k), [M >> np.eye(n), M << k * np.eye(n), A.T @ M + M @ A + lam * M << -margin * k * np.eye(n)]).solve(solver=cp.CLARABEL)
    if M.value is None:
        return None
    Mv = 0.5 * (M.value + M.value.T)
    return Mv if np.linalg.eigvalsh(A.T @ Mv + Mv @ A + lam * Mv).max() < 0 else None


def quarter_car_model(*pairs):
    from .conftest import SPECS

    text = (SPECS / "quarter_car.yaml").read_text()
    for old, new in pairs:
        assert old in text
        text = text.replace(old, new)
    return build_model(parse_spec_text(text))


def test_quarter_car_supremum_is_known_independently():
    # The independent numbers the stage is measured against. A is constant, so every feasible lambda is
    # below -2 max Re eig(A) (Lyapunov), and the modal M reaches it exactly (margin 0, not strict).
    A = quarter_car_A()
    sup = -2 * np.linalg.eigvals(A).real.max()
    assert sup == pytest.approx(2.86656, abs=1e-5)
    Mm = modal_M(A)
    assert np.linalg.eigvalsh(A.T @ Mm + Mm @ A + sup * Mm).max() <= 1e-12 * np.linalg.norm(Mm, 2)
    # Bisection with the own minimum-condition-number SDP: feasible up to within 1e-3 of sup, not above it.
    lo, hi = 2.0, 3.0
    for _ in range(12):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if min_condition_M(A, mid) is not None else (lo, mid)
    assert sup * (1 - 1e-3) < lo <= sup
    # At lambda = 2.7 every certificate has trace(M) / lambda_min(M) > 4000 = n / M_MIN_EIG, so the old
    # normalisation (trace(M) = n, M >= 1e-3 I) could not hold any of them: minimise trace(M) with M >= I.
    import cvxpy as cp

    M = cp.Variable((4, 4), symmetric=True)
    cp.Problem(cp.Minimize(cp.trace(M)), [M >> np.eye(4), A.T @ M + M @ A + 2.7 * M << 0]).solve(solver=cp.CLARABEL)
    assert M.value is not None and np.trace(M.value) > 4 / stabilise.M_MIN_EIG
    # ... and indeed the maximum-margin problem alone refuses 2.7 (what `decay_rate: 2.7` used to report).
    assert stabilise.solve_lmi([A], 2.7)[1] >= -stabilise.MARGIN_TOL


def test_quarter_car_maximise_reaches_the_supremum():
    model = quarter_car_model()
    A = quarter_car_A()
    assert np.allclose(np.asarray(model.numeric(stabilise.affine_form(model)[0], list(model.u))(0.0), dtype=float), A, rtol=1e-14)
    art = stabilise.run(model, {})
    lam, M = art.values["lambda"], art.values["M"]
    sup = -2 * np.linalg.eigvals(A).real.max()
    assert sup * (1 - 1e-3) <= lam <= sup          # "within 1%" of the supremum; old code: 2.5002 (12.8 % short)
    assert art.values["lmi_margin"] <= 0 and art.checks["lmi_margin"].passed
    # Independent numpy re-check with the hand-written A, and M outside the old normalisation's reach.
    eig = np.linalg.eigvalsh(M)
    assert eig.min() > 0 and np.linalg.eigvalsh(A.T @ M + M @ A + lam * M).max() <= 0
    assert eig.sum() / eig.min() > 4 / stabilise.M_MIN_EIG and eig.max() / eig.min() > 4000
    assert art.meta["formulation"] == "scale_free"


def test_quarter_car_fixed_rate_above_the_old_cap_is_accepted():
    art = stabilise.run(quarter_car_model(("decay_rate: maximise", "decay_rate: 2.7")), {})
    M = art.values["M"]
    assert art.values["lambda"] == 2.7 and art.meta["formulation"] == "scale_free"
    assert art.values["lmi_margin"] <= 0 and art.meta["scale_free_relative_margin"] < -stabilise.MARGIN_TOL
    A = quarter_car_A()
    assert np.linalg.eigvalsh(M).min() > 0 and np.linalg.eigvalsh(A.T @ M + M @ A + 2.7 * M).max() < 0


def test_quarter_car_rate_above_the_supremum_names_it():
    with pytest.raises(DesignError, match=r"infeasible at lambda = 2.9.*below 2\.866[0-9]* \(the largest the solver certifies\)"):
        stabilise.run(quarter_car_model(("decay_rate: maximise", "decay_rate: 2.9")), {})


def test_maximise_with_a_far_more_ill_conditioned_M():
    # A ten times stiffer tyre: the best M has condition number about 4.5e4; the rate still comes within
    # 1e-3 of -2 max Re eig(A), and the M found is re-checked here in numpy.
    A = quarter_car_A(k_t=1.9e6)
    sup = -2 * np.linalg.eigvals(A).real.max()
    lam, M = stabilise.largest_decay_rate([A])
    assert sup * (1 - 1e-3) <= lam <= sup
    eig = np.linalg.eigvalsh(M)
    assert eig.max() / eig.min() > 2e4
    assert np.linalg.eigvalsh(A.T @ M + M @ A + lam * M).max() <= 0


# --- The maximise search against independently known rates -------------------------------------------------

def ladder_A(stages: int, params: dict, u: float) -> np.ndarray:
    """A(u) of the ladder written from its circuit equations (examples.py docstring), not from the stage:
    L i_j' = v_(j-1) - v_(j+1) - r i_j, C v_j' = i_(j-1) - i_(j+1) - G_c v_j, the first coupling scaled by 1 - u."""
    n, L, C, r, G = 4 * stages, params["L"], params["C"], params["r"], params["G_c"]
    A = np.zeros((n, n))
    for k in range(n):                      # state k + 1: an inductor current when k is even
        H, loss = (L, r) if k % 2 == 0 else (C, G)
        A[k, k] = -loss / H
        if k >= 1:
            A[k, k - 1] = (1 - u if k == 1 else 1.0) / H
        if k + 1 < n:
            A[k, k + 1] = -(1 - u if k == 0 else 1.0) / H
    return A


def test_maximise_reaches_the_ladders_known_rate(monkeypatch):
    # n = 16: M = H = diag(L, C, ...) gives A^T H + H A + lambda H = -2 D + lambda H <= 0 exactly up to
    # lambda* = 2 min(r/L, G_c/C), and no M does better: at u = 1 the chain v2, i3, ..., v16 has odd length,
    # so its skew part has a null vector on the capacitors alone, an eigenvector of A(1) with eigenvalue
    # -G_c/C, and Re eig(A) <= -lambda/2 is necessary.  So lambda* is known, and it equals the search's bound.
    model = ladder_model(4, ("decay_rate: 2.0", "decay_rate: maximise"))
    p = model.spec.parameters
    lam_star = 2 * min(p["r"] / p["L"], p["G_c"] / p["C"])
    A0, A1 = ladder_A(4, p, 0.0), ladder_A(4, p, 1.0)
    assert -2 * np.linalg.eigvals(A1).real.max() == pytest.approx(lam_star, rel=1e-9)
    H = np.diag([p["L"] if k % 2 == 0 else p["C"] for k in range(16)])
    assert max(np.linalg.eigvalsh(A.T @ H + H @ A + lam_star * H).max() for A in (A0, A1)) <= 1e-12
    A_num = model.numeric(stabilise.affine_form(model)[0], list(model.u))
    assert np.allclose(np.asarray(A_num(1.0), dtype=float), A1, rtol=1e-12, atol=0)

    tried = []
    certify = vertex.certify_rate
    monkeypatch.setattr(vertex, "certify_rate", lambda A_list, lam, *a, **k: tried.append(lam) or certify(A_list, lam, *a, **k))
    art = stabilise.run(model, {})
    lam, M = art.values["lambda"], art.values["M"]
    assert lam_star * (1 - stabilise.BISECTION_RTOL) <= lam <= lam_star
    # The bound is attained, so the first rate tried (the bound less half the tolerance) ends the search (the
    # rates are tried on A / s, s the largest spectral radius, stored as meta lmi_scale).
    scale = art.meta["lmi_scale"]
    assert scale == pytest.approx(max(np.abs(np.linalg.eigvals(A)).max() for A in (A0, A1)), rel=1e-12)
    assert [t * scale for t in tried] == [pytest.approx(lam_star * (1 - stabilise.BISECTION_RTOL / 2), rel=1e-12)]
    assert art.meta["structure"] == "full" and art.checks["lmi_margin"].evidence == "proved"
    for u in np.linspace(0, 1, 11):
        A = ladder_A(4, p, u)
        assert np.linalg.eigvalsh(A.T @ M + M @ A + lam * M).max() <= 0
    assert np.linalg.eigvalsh(M).min() > 0


def test_maximise_comes_down_to_the_diagonal_ladders_rate():
    # Duty cycle in [0.1, 0.9] and a diagonal M: the diagonal entries of A^T D + D A + lambda D are
    # d_j (2 A_jj + lambda), so lambda <= 2 G_c/C = 4 for every diagonal M, and H reaches it; the eigenvalue
    # bound is far above (about 5.4), so the search has to come down through infeasible rates.
    model = ladder_model(4, ("decay_rate: 2.0", "decay_rate: maximise\n  structure: diagonal"), ("- - 0.0\n    - 1.0", "- - 0.1\n    - 0.9"))
    p = model.spec.parameters
    lam_star = 2 * min(p["r"] / p["L"], p["G_c"] / p["C"])
    bound = min(-2 * np.linalg.eigvals(ladder_A(4, p, u)).real.max() for u in (0.1, 0.9))
    assert bound > 1.25 * lam_star
    art = stabilise.run(model, {})
    lam, M = art.values["lambda"], art.values["M"]
    assert lam_star * (1 - stabilise.BISECTION_RTOL) <= lam <= lam_star
    low, high = art.meta["bisection_bracket"]
    assert low == lam and lam_star <= high <= lam + stabilise.BISECTION_RTOL * bound
    assert np.count_nonzero(M - np.diag(np.diag(M))) == 0 and np.diag(M).min() > 0
    for u in np.linspace(0.1, 0.9, 9):
        A = ladder_A(4, p, u)
        assert np.linalg.eigvalsh(A.T @ M + M @ A + lam * M).max() <= 0


def common_rate_brute_force(A_list, lo=0.0, hi=None, steps=30):
    """Own bisection (not the stage's code): the largest lambda with an M, I <= M, A^T M + M A + lambda M <= 0
    at every A, found by cvxpy feasibility problems; returns the last feasible and first infeasible rate."""
    import cvxpy as cp

    n = A_list[0].shape[0]
    hi = min(-2 * np.linalg.eigvals(A).real.max() for A in A_list) if hi is None else hi
    for _ in range(steps):
        mid = 0.5 * (lo + hi)
        M = cp.Variable((n, n), symmetric=True)
        problem = cp.Problem(cp.Minimize(0), [M >> np.eye(n)] + [A.T @ M + M @ A + mid * M << 0 for A in A_list])
        problem.solve(solver=cp.CLARABEL)
        lo, hi = (mid, hi) if problem.status == "optimal" else (lo, mid)
    return lo, hi


SWITCHED_PAIR = [np.array([[-1.0, 2.0], [0.0, -2.0]]), np.array([[-2.0, 0.0], [2.0, -1.0]])]


def test_dual_bound_is_sound_and_maximise_matches_a_brute_force_bisection():
    # Two vertices whose common rate is well below the eigenvalue bound 2 (no closed form): the stage's answer
    # against an own bisection, and the infeasibility bound from the duals at a rate above the optimum must
    # lie at or above the brute-force optimum (it proves infeasibility) and below the rate tried (it helps).
    feasible, infeasible = common_rate_brute_force(SWITCHED_PAIR)
    assert infeasible - feasible < 1e-6 and infeasible < 1.5
    lam, M = stabilise.largest_decay_rate(SWITCHED_PAIR)
    assert feasible * (1 - stabilise.BISECTION_RTOL) <= lam <= infeasible
    assert max(np.linalg.eigvalsh(A.T @ M + M @ A + lam * M).max() for A in SWITCHED_PAIR) <= 0
    trial = 0.5 * (infeasible + 2.0)
    M_none, _, _, how = stabilise.certify_rate(SWITCHED_PAIR, trial)
    assert M_none is None
    assert max(feasible, lam) <= how["infeasible_from"] < trial


def test_dual_bound_by_hand():
    # A = diag(-1, -3), best rate 2.  Z = I: S(mu) = 2 A + mu I >= 0 from mu = 6 on, a valid but weak bound,
    # shown only when the rate tried is above it; a Z of the wrong sign is projected to 0 and proves nothing.
    # For a diagonal M only diag(S) counts, and Z = e1 e1^T gives diag(S(mu)) = (mu - 2, 0): the exact rate.
    A = np.diag([-1.0, -3.0])
    assert stabilise.infeasible_from([A], [np.eye(2)], 7.0) == pytest.approx(6.0, rel=1e-8)
    assert stabilise.infeasible_from([A], [np.eye(2)], 5.0) == np.inf
    assert stabilise.infeasible_from([A], [-np.eye(2)], 7.0) == np.inf
    assert stabilise.infeasible_from([A], [np.diag([1.0, 0.0])], 7.0, structure="diagonal") == pytest.approx(2.0, rel=1e-8)


def test_maximise_survives_a_solver_failure_at_one_rate(monkeypatch):
    # A failing scale-free solve near the supremum leaves the rates certified before it; only a search
    # that certifies nothing reports the failure.
    from ashc_cli.errors import NumericalError

    def failing(*args, **kwargs):
        raise NumericalError("stabilise", "Clarabel failed (test)", "a solvable LMI")

    A = quarter_car_A()
    monkeypatch.setattr(vertex, "solve_lmi_scale_free", failing)
    lam, M = stabilise.largest_decay_rate([A])
    assert 2.0 < lam < 2.86656 and np.linalg.eigvalsh(A.T @ M + M @ A + lam * M).max() <= 0
    monkeypatch.setattr(vertex, "solve_with_clarabel", failing)
    with pytest.raises(NumericalError, match="test"):
        stabilise.largest_decay_rate([A])


# --- issue 19: enclosed Jacobian ranges, jumps, the plant's own time scale, bounded feedback gains ------------

def _two_state(f2, *, box="[[-1.5, 1.5], [-1.5, 1.5]]", rate="1.0", U="[[-3, 3]]", feedback="identity", f1="-x1 + x2", g2="1", extra=""):
    return build_model(parse_spec_text(f"""
name: two_state
{extra}
concrete:
  states: [x1, x2]
  inputs: [u]
  f_bar: ["{f1}", "{f2}"]
  g: [["0"], ["{g2}"]]
  h: ["x1"]
  input_bounds: {U}
  output_set: [[0.1, 0.5]]
  {'state_box: ' + box if box else ''}
stabilisability: {{method: polytopic_lmi, decay_rate: {rate}, feedback: {feedback}}}
abstract:
  states: [xi]
  inputs: [v]
  phi_bar: ["0"]
  l: ["xi"]
  domain: [[0, 2]]
"""))


STEEP_F2 = "-0.5*x1 - 2*x2 + 0.04*tanh(50000*(x1 + 0.0517))"


@pytest.mark.slow
def test_a_steep_band_is_inside_the_enclosed_range_and_the_lmi_is_refused():
    # df2/dx1 = -0.5 + 2000 sech^2(50000 (x1 + 0.0517)) reaches 1999.5 in a band 1e-4 wide that a grid misses:
    # the enclosure has it, and no M certifies lambda = 1 (a honest "no" instead of a sampled "yes").
    model = _two_state(STEEP_F2)
    _, A_list, ranges, meta = terms.jacobian_polytope(model)
    assert meta["ranges_proved"]
    assert ranges[0, 0] <= -0.5 and 1999.5 <= ranges[0, 1] <= 1999.5 * (1 + 1e-5)
    assert meta["ranges_sampled"][0][1] < 1.0                   # what the grid saw
    # the term polytope (theta = tanh(...)^2 in [0, 1], df2/dx1 = -0.5 + 2000 (1 - theta)) is tried first
    with pytest.raises(DesignError, match=r"infeasible at lambda = 1 .*corner tanh\(.*\)\*\*2 = 0 of the ranges of the nonlinear terms"):
        stabilise.run(model, {})


def test_enclosed_ranges_prove_the_lmi_of_a_smooth_plant():
    art = stabilise.run(_two_state("-0.5*x1 - 2*x2 + 0.04*tanh(5*(x1 + 0.0517))"), {})
    assert art.meta["ranges_proved"] and art.checks["lmi_margin"].evidence == "proved"


def test_sampled_ranges_say_sampled(monkeypatch):
    monkeypatch.setattr(terms, "enclose_entry", lambda *a, **k: None)
    art = stabilise.run(_two_state("-0.5*x1 - 2*x2 + 0.04*tanh(5*(x1 + 0.0517))"), {})
    assert not art.meta["ranges_proved"] and art.checks["lmi_margin"].evidence == "sampled"
    assert "only sampled" in art.meta["lmi_proof"]


@pytest.mark.parametrize("f2, box, ok", [
    ("-0.5*x1 - 2*x2 - 0.1*sign(x1)", "[[-1.5, 1.5], [-1.5, 1.5]]", False),     # the jump at x1 = 0 is in the box
    ("-0.5*x1 - 2*x2 - 0.1*sign(x1)", "[[0.2, 1.5], [-1.5, 1.5]]", True),       # sign is constant on the box
    ("-0.5*x1 - 2*x2 - 0.1*abs(x1)", "[[-1.5, 1.5], [-1.5, 1.5]]", True),       # abs is Lipschitz
    ("-0.5*x1 - 2*x2 - 0.1*max(x1, 0)", "[[-1.5, 1.5], [-1.5, 1.5]]", True),
])
def test_jumps_are_refused_where_they_lie_in_the_box(f2, box, ok):
    model = _two_state(f2, box=box)
    if ok:
        art = stabilise.run(model, {})
        assert art.checks["lmi_margin"].passed and art.checks["lmi_margin"].evidence == "proved"
    else:
        with pytest.raises(DesignError, match=r"concrete\.f_bar\[1\]: sign\(x1\) jumps where x1 = 0.*not Lipschitz"):
            stabilise.run(model, {})


def test_a_jump_without_a_state_box_is_not_affine():
    with pytest.raises(DesignError, match="not affine in x"):
        stabilise.run(_two_state("-0.5*x1 - 2*x2 - 0.1*sign(x1)", box=None), {})


def test_the_lmi_is_solved_on_the_plants_own_time_scale():
    # x' = (A x + B u) / tau with A a Jordan block at -1: the certified rate scales as 1 / tau, the same rate at
    # every time scale (sup 2 / tau, not attained). A fixed absolute tolerance refused the slow plant (margin -5e-9
    # against 1e-7).
    def plant(tau, rate):
        return _two_state("-x2/tau", f1="(-x1 + x2)/tau", g2="1/tau", box=None, rate=rate, extra=f"parameters: {{tau: {tau!r}}}")

    rates = []
    for tau in (1e-8, 1.0, 1e8):
        art = stabilise.run(plant(tau, "maximise"), {})
        rates.append(art.values["lambda"] * tau)
        assert art.checks["lmi_margin"].evidence == "proved" and art.values["lmi_margin"] < 0
        assert stabilise.run(plant(tau, repr(1.5 / tau)), {}).checks["lmi_margin"].passed
        with pytest.raises(DesignError, match="infeasible"):
            stabilise.run(plant(tau, repr(2.01 / tau)), {})
    assert 1.98 <= min(rates) and max(rates) <= 2.0
    assert max(rates) - min(rates) <= 1e-6 * max(rates)


def test_feedback_with_a_full_rank_B_is_bounded_and_small():
    # B = I: the maximum-margin LMI was unbounded ("decay_rate below 0"); K = -B^+ (A + 2 I) would do, and the
    # smallest gain the rate allows is what the certified region needs.
    model = build_model(parse_spec_text("""
name: full_rank_B
concrete:
  states: [x1, x2]
  inputs: [u1, u2]
  f_bar: ["x1 + x2", "x2"]
  g: [["1", "0"], ["0", "1"]]
  h: ["x1"]
  input_bounds: [[-10, 10], [-10, 10]]
  output_set: [[-1, 1]]
stabilisability: {method: polytopic_lmi, decay_rate: 1.0, feedback: linear_gain}
abstract:
  states: [xi]
  inputs: [v]
  phi_bar: ["0"]
  l: ["-xi", "0"]
  domain: [[-1.5, 1.5]]
"""))
    art = stabilise.run(model, {})
    K, M = np.asarray(art.values["K"]), np.asarray(art.values["M"])
    A = np.array([[1.0, 1.0], [0.0, 1.0]])
    Acl = A + K
    assert np.linalg.eigvalsh(Acl.T @ M + M @ Acl + 1.0 * M).max() < 0
    assert np.abs(K).max() < 10          # K = -(A + 2 I) has entries of 3; nothing near the unbounded solution


def test_feedback_gain_on_the_unstable_linear_spec_is_small():
    # x1' = x2, x2' = x1 + u at lambda = 2: the maximum-margin LMI returned K = [-1168, -484]; the smallest-gain
    # one a gain of order 1, which certifies a region of output radius about 100 times larger (test_bound).
    from .conftest import SPECS

    art = stabilise.run(build_model(load_spec(SPECS / "unstable_linear.yaml")), {})
    K = np.asarray(art.values["K"]).ravel()
    assert np.abs(K).max() < 10
    Acl = np.array([[0.0, 1.0], [1.0 + K[0], K[1]]])
    M = np.asarray(art.values["M"])
    assert np.linalg.eigvalsh(Acl.T @ M + M @ Acl + 2.0 * M).max() < 0


def test_maximise_on_a_motor_with_tanh_friction_returns_a_certified_rate():
    # A DC motor with friction c tanh(k w): lambda = 1 and 3 are feasible; maximise exited 4 ("numpy re-check finds
    # margin 1.1 > 0") when the sampled ranges missed the friction's steepest slope.
    model = build_model(parse_spec_text("""
name: dc_motor
parameters: {J: 0.01, b: 0.1, K: 0.01, R: 1.0, L: 0.5, c: 0.02, k: 20.0}
concrete:
  states: [w, i]
  inputs: [u]
  f_bar: ["(-b*w + K*i - c*tanh(k*w))/J", "(-K*w - R*i)/L"]
  g: [["0"], ["1/L"]]
  h: ["w"]
  input_bounds: [[-12, 12]]
  output_set: [[-1, 1]]
  state_box: [[-20, 20], [-20, 20]]
stabilisability: {method: polytopic_lmi, decay_rate: maximise}
abstract:
  states: [xi]
  inputs: [v]
  phi_bar: ["0"]
  l: ["xi"]
  domain: [[-2, 2]]
"""))
    art = stabilise.run(model, {})
    assert art.values["lambda"] >= 3.0
    assert art.checks["lmi_margin"].evidence == "proved" and art.checks["lmi_margin"].passed


def test_an_inverted_pendulum_gets_a_gain_and_a_local_certificate_that_holds(tmp_path):
    # x2' = a sin(x1) - b x2 + c u: one term cos(x1) in [cos 1, 1] over the box; K synthesised on its two corners.
    from ashc_cli.products.falsify import falsify
    from ashc_cli.design.pipeline import DESIGN, design_model, run

    from .conftest import SPECS

    spec = load_spec(SPECS / "inverted_pendulum.yaml")
    arts = run(spec, tmp_path, DESIGN)
    st, bd = arts["stabilise"], arts["bound"].values
    assert st.meta["polytope"] == "Jacobian terms" and st.checks["lmi_margin"].evidence == "proved"
    K, M, lam = np.asarray(st.values["K"]).ravel(), np.asarray(st.values["M"]), float(st.values["lambda"])
    a, b, c = 9.81, 0.5, 2.0
    for x1 in np.linspace(-1, 1, 201):          # the closed loop at every angle of the box, independently of the stage
        A = np.array([[0.0, 1.0], [a * np.cos(x1) + c * K[0], -b + c * K[1]]])
        assert np.linalg.eigvalsh(A.T @ M + M @ A + lam * M).max() < 0
    assert 0 < bd["w0_max_certified"] < np.inf and 0 < bd["v_max_certified"] < np.inf     # local: the box and no clipping
    art = falsify(design_model(spec, arts), arts, 64, t_final=5.0)
    assert art.values["max_ratio"] <= 1.0 and art.values["certificate_counterexamples"] == 0


#: Two tanks in cascade with Torricelli outflows, written for these tests: df/dx has c / (2 sqrt(x)), not finite at
#: x = 0, which the state box excludes; the equilibria at u = xi are x1 = (b xi / c1)^2, x2 = (b xi / c2)^2.
TWO_TANKS = """
name: two_tanks
parameters: {c1: 0.5, c2: 0.4, b: 0.3}
concrete:
  states: [x1, x2]
  inputs: [u]
  f_bar: ["-c1*sqrt(x1)", "c1*sqrt(x1) - c2*sqrt(x2)"]
  g: [["b"], ["0"]]
  h: ["x2"]
  input_bounds: [[0.5, 4]]
  output_set: [[1, 5]]
  state_box: [[0.05, 30], [0.05, 30]]
stabilisability: {method: polytopic_lmi, decay_rate: maximise, feedback: identity}
abstract:
  states: [xi]
  inputs: [v]
  phi_bar: ["0"]
  l: ["xi"]
  domain: [[1, 4]]
  delta: identity
interface: {q: least_squares, saturate: true}
"""


def test_a_jacobian_singular_at_the_origin_outside_the_box_is_no_crash():
    # The constant entries of the polytope's matrices were read off df/dx at x = 0 (1/sqrt(0): a TypeError, exit 1).
    model = build_model(parse_spec_text(TWO_TANKS))
    art = stabilise.run(model, {})
    assert art.values["lambda"] > 0 and art.checks["lmi_margin"].passed and art.checks["M_positive"].passed
    _, A_list, ranges, meta = terms.jacobian_polytope(model)
    # df2/dx2 = -c2 / (2 sqrt(x2)) ranges over [-0.4 / (2 sqrt(0.05)), -0.4 / (2 sqrt(30))]; df1/dx2 = 0 stays 0.
    k = meta["jacobian_entries"].index("df2/dx2")
    assert ranges[k][0] == pytest.approx(-0.2 / np.sqrt(0.05), rel=1e-9) and ranges[k][1] == pytest.approx(-0.2 / np.sqrt(30), rel=1e-9)
    assert all(A[0, 1] == 0 for A in A_list)


# Audit finding 6: x' = -exp(u) x + u has a Jacobian -exp(u) free of x but not affine in u; the vertices of U do not
# bound it (refused before as "A(u) is not affine in u"), the term polytope over U does: rate 2 e^-1 = 0.7358.
EXP_INPUT = """
name: exp_input
concrete:
  states: [x]
  inputs: [u]
  f: ["-exp(u)*x + u"]
  h: ["x"]
  input_bounds: [[-1, 1]]
  output_set: [[-0.2, 0.2]]
stabilisability: {method: polytopic_lmi, decay_rate: maximise}
abstract:
  states: [xi]
  inputs: [v]
  phi_bar: ["0"]
  l: ["xi"]
  domain: [[-0.5, 0.5]]
"""


def test_a_jacobian_of_the_input_alone_is_certified_over_U_for_every_state(tmp_path):
    from scipy.integrate import solve_ivp

    from ashc_cli.design.pipeline import DESIGN, run

    arts = run(parse_spec_text(EXP_INPUT), tmp_path, DESIGN)
    st, bd = arts["stabilise"], arts["bound"].values
    assert 2 * np.exp(-1.0) * (1 - 1e-5) <= st.values["lambda"] <= 2 * np.exp(-1.0) and st.checks["lmi_margin"].evidence == "proved"
    assert "state_box" not in st.meta and not np.isfinite(bd["w0_max_certified"])       # no state box: every x
    # the global claim attacked from far starts: u = SAT(l(xi)) (q = 0 for a plant given as f), xi' = v
    M, lam, eps, alpha_h, G = (float(np.ravel(bd[k])[0]) for k in ("M", "lambda", "epsilon", "alpha_h", "gain"))
    for x0, v in ((5.0, 0.1), (-8.0, -0.1), (20.0, 0.0)):
        def rhs(t, z, v=v):
            xi, x = z
            u = np.clip(xi, -1, 1)
            return [v, -np.exp(u) * x + u]

        xi0 = 0.2
        p0 = xi0 * np.exp(-xi0)                      # the manifold: exp(xi) p = xi
        sol = solve_ivp(rhs, (0.0, 2.5), [xi0, x0], rtol=1e-10, atol=1e-12, max_step=0.01)
        psi = sol.y[0] * np.exp(-sol.y[0])
        bound = np.sqrt(M * (p0 - x0) ** 2 * np.exp(-(lam - eps) * sol.t) / alpha_h) + G * abs(v)
        assert np.all(np.abs(psi - sol.y[1]) <= bound)


def test_a_refusal_suggests_only_what_the_tool_accepts_for_the_plant(tmp_path):
    # Issue 39: too many nonlinear terms used to suggest method: given (refused with the same message), and an
    # unstable plant written as f(x, u) was told to use feedback: linear_gain (refused: not input-affine).
    from ashc_cli.design.pipeline import run
    from ashc_cli.errors import DesignError
    from .bad_inputs import MANY_TERMS, UNSTABLE_GENERAL

    hints = {}
    for text in (MANY_TERMS, UNSTABLE_GENERAL):
        with pytest.raises(DesignError) as exc:
            run(parse_spec_text(text), tmp_path / text[6:16], ("stabilise",))
        assert "linear_gain" not in exc.value.expected, exc.value.line()
        hints[text] = exc.value.expected
    # too many terms: the hint's decay rate and method given (with an M) are accepted and certify
    assert hints[MANY_TERMS].startswith("decay_rate <= 0.2 (or maximise)") and "method: given with your M" in hints[MANY_TERMS]
    art = run(parse_spec_text(MANY_TERMS.replace("decay_rate: 0.5", "decay_rate: 0.19")), tmp_path / "many_ok", ("stabilise",))["stabilise"]
    assert art.meta["route"].startswith("automatic: the norm-bound test")
    given_M = MANY_TERMS.replace("{method: polytopic_lmi, decay_rate: 0.5}", "{method: given, decay_rate: 0.19, M: lyapunov}")
    assert run(parse_spec_text(given_M), tmp_path / "many_given", ("stabilise",))["stabilise"].values["lambda"] == 0.19
    # the hints given are accepted: with linear_gain where it applies (input-affine, constant g), the plant is certified
    text = UNSTABLE_GENERAL.replace('f: ["x + sin(u)"]', 'f_bar: ["x"], g: [["1"]]')
    with pytest.raises(DesignError, match="feedback: linear_gain"):
        run(parse_spec_text(text), tmp_path / "affine", ("stabilise",))
    gain = text.replace("decay_rate: 0.5}", "decay_rate: 0.5, feedback: linear_gain}")
    art = run(parse_spec_text(gain), tmp_path / "gain", ("stabilise",))["stabilise"]
    assert art.values["lambda"] == 0.5


def test_a_plant_no_certificate_can_fit_is_refused_at_a_named_state_before_any_lmi(tmp_path, monkeypatch):
    # Issue 39: a unicycle at rest was refused after 24 min, naming a corner of the term ranges no state reaches.  The
    # precheck samples real states (and the centre with one coordinate at an end or at 0) before the enclosures.
    from ashc_cli.design.pipeline import run
    from .bad_inputs import CART

    def no_polytope(*args, **kwargs):
        raise AssertionError("the term polytope was built")

    monkeypatch.setattr(stabilise, "polytopes", no_polytope)
    with pytest.raises(DesignError, match=r"^stabilisability: no M certifies any decay rate lambda > 0 .* at x = \[0, 0, 0, 1\] df/dx has the eigenvalue 0") as exc:
        run(parse_spec_text(CART), tmp_path / "identity", ("stabilise",))
    assert exc.value.where == "stabilisability" and "feedback: linear_gain" in exc.value.expected     # g is constant: accepted
    gain = CART.replace("decay_rate: 0.5}", "decay_rate: 0.5, feedback: linear_gain}")
    with pytest.raises(DesignError, match=r"at x = \[0, 0, 0, 0\] the mode s = 0 of df/dx .* not reachable from the inputs \(rank \[A - s I, B\] < 4"):
        run(parse_spec_text(gain), tmp_path / "gain", ("stabilise",))


def test_the_precheck_refutes_nothing_a_certificate_exists_for():
    # Necessary conditions only: every spec of specs/ that certifies passes it (the LMI decides); the Cuk converter's
    # df/dx has eigenvalues with negative real parts everywhere, and with linear_gain the unstable linear plant's mode
    # is reachable.
    from ashc_cli.design.contraction.precheck import refute_rate
    from ashc_cli.problem.model import sparse_jacobian

    for spec in (CUK, CUK.parent / "unstable_linear.yaml", CUK.parent / "quarter_car.yaml"):
        model = build_model(load_spec(spec))
        refute_rate(model, sparse_jacobian(model.f, model.x), 0.0)


def test_a_state_outside_the_outputs_cone_is_left_out_and_integrated_beside(tmp_path):
    # Issue 43: a lag whose output y = x is tracked, with a state q' = x (a position integrating it) that never acts
    # on y: its mode s = 0 refutes every M of the whole plant (the precheck names q and says it cannot influence y);
    # the design leaves q out (named on the stage's line and the design's), certifies the lag as without q, and
    # simulate integrates q beside the loop (q(t) = the integral of x, exactly the trapezoid of the samples here)
    from scipy.integrate import cumulative_trapezoid

    from ashc_cli.design.pipeline import headline, run, STAGES
    from ashc_cli.problem.influence import cone_model, output_cone

    from .bad_inputs import LAG_TASK

    plain = LAG_TASK.split("task:")[0]
    text = plain.replace('states: [x], inputs: [u], f_bar: ["-2*x"], g: [["1"]]', 'states: [x, q], inputs: [u], f_bar: ["-2*x", "x"], g: [["1"], ["0"]]')
    text += ("simulate:\n  tracking: {t_final: 4.0, xi0: [0.0], x0: on_manifold, reference_levels: [0.5, -0.5], dwell: 2.0,\n"
             "             abstract_controller: {kind: setpoint, gain: 2.0, v_max: 0.5}}\n")
    full = build_model(parse_spec_text(text))
    assert output_cone(full) == ([0], [1])
    with pytest.raises(DesignError, match=r"the mode lives in q, which cannot influence y .* leave them out of concrete.states"):
        stabilise.run(full, {})
    model = cone_model(parse_spec_text(text))
    assert model.n == 1 and model.beside.names == ("q",) and model.beside.index == (1,)
    arts = run(parse_spec_text(text), tmp_path / "with_q", ("simulate",))
    st = arts["stabilise"]
    assert st.values["lambda"] == 2.0 and st.meta["left_out"]["states"] == ["q"]
    assert "left out q" in headline(STAGES["stabilise"], st)
    assert run(parse_spec_text(plain), tmp_path / "without", ("stabilise",))["stabilise"].values["lambda"] == 2.0
    v = arts["simulate"].values
    t, x, q = (np.asarray(v[k]) for k in ("tracking/t", "tracking/x", "tracking/x_beside"))
    assert x.shape == q.shape == (1, t.size) and q[0, 0] == 0.0 and abs(q[0, -1]) > 0.1
    assert np.abs(q[0] - cumulative_trapezoid(x[0], t, initial=0.0)).max() < 1e-12

"""Stage 4: the left inverse m of p, and the conditions that tie it to the output (Section IV-C).

m solves kappa(m(x)) = h(x) (eq. (21c)); of the branches sympy finds, the one with m(p(xi)) = xi
on V is kept (eq. (34) for the Cuk converter).  The stage checks, each with a stored number:

* p is injective on V: a left inverse exists (m(p(xi)) = xi on a grid of V), and kappa is strictly monotone;
* V covers Y (eq. (10)): kappa(V) contains the output box Y;
* condition (i) of Theorem 6: p(m(x)) = x on Im(p), i.e. p(m(p(xi))) = p(xi);
* condition (ii) of Theorem 6, through Corollary 1 for linear h: x - p(m(x)) in Ker(h),
  i.e. h(x) = kappa(m(x)) on random samples of X_y = {x : h(x) in Y} (and symbolically where sympy can);
* where m is real: the output interval on which every radicand of m is non-negative (eq. (33):
  |x4| <= E / (2 sqrt(R_i G_L)) = 126.91 V for the converter), which must contain Y.

Where m is certified (``values/m_domain``, one [lo, hi] row per output; ``meta/m_domain_set`` names the set and
``meta/m_domain`` says why).  m is only used (``ashc eval``, the m-relation run) for states x with h(x) in it:

* scalar output, m = kappa^-1(h(x)): kappa(V), intersected with the interval where m is real.  Outside kappa(V)
  the value m(x) lies outside V, where nothing is certified; a Chebyshev interpolant of kappa^-1 is a
  polynomial fitted on kappa(V) only and extrapolates beyond it (its ``m_real_interval`` is kappa(V) too:
  that is where kappa^-1 is known to exist);
* affine p with one abstract state and one output: kappa(V) (m(x) lies in V exactly when h(x) is in kappa(V));
  other affine shapes and the closed form for several outputs: Y, the set the checks cover (X_y = h^-1(Y)).

``m_real_interval`` has an infinite end only where that is proved: symbolically (no radicand, or a radicand
that stays non-negative), or because m is linear.

When p is affine, p(xi) = P xi + p0, m(x) = K (x - p0) for any sizes, K the left inverse of P chosen for condition
(ii); a spec may give m itself (``abstract.m``), checked, not trusted (docs/guide.md, "Design options": the left
inverse m); ``meta/construction`` names the construction used.
"""

from __future__ import annotations

import itertools

import numpy as np
import scipy.optimize as sopt
import sympy as sp

from ashc_cli.numerics import proofs
from ashc_cli.design.artefacts import Artefact, Check
from ashc_cli.errors import DesignError, FitError
from ashc_cli.problem.grids import domain_grid, sample_states_with_output
from ashc_cli.problem.model import Model, sparse_jacobian, tidy
from ashc_cli.design.inverse_construct import (COMPOSE_SAFETY, CONDITION_II_RTOL, LEFT_INVERSE_TOL, Branch, augment_outputs, branch_residuals, closed_form_branches,
                                               composed_tolerances, kappa_inverse_on_Y, note_augmented, numeric_inverse)
from ashc_cli.design.inverse_proofs import mark_proved, prove_affine_inverse, prove_multi_inverse, prove_scalar_inverse, prove_scalar_rows, real_interval, relabel_proved
from ashc_cli.design.upstream import DOMAIN_RTOL, certified_set, format_box, p_function, sample_box

NAME = "inverse"
UPSTREAM = ("manifold", "kappa")

SAMPLES = 2000
#: A left inverse K of an affine p satisfies condition (ii) exactly when max |C (I - P K)| is below this (relative to max |C|).
CONDITION_II_MATRIX_RTOL = 1e-10
#: The names of the constructions of m (``meta/construction``).
PSEUDO_INVERSE = "pseudo-inverse"
LEAST_NORM = "least-norm left inverse with C(I - P K) = 0"
KAPPA_INVERSE = "kappa^-1(h(x))"
EXPLICIT = "explicit (spec)"


def output_symbol() -> sp.Symbol:
    """The symbol standing for the output value y while solving kappa(mu) = y."""
    return sp.Symbol("_y", real=True)


def _format_interval(lo: float, hi: float) -> str:
    """``[lo, hi]``, ``y >= lo``, ``y <= hi`` or ``every y`` (infinite ends only as words)."""
    lo, hi = float(lo) + 0.0, float(hi) + 0.0   # + 0.0: no "-0"
    if np.isfinite(lo) and np.isfinite(hi):
        return f"y in [{lo:.6g}, {hi:.6g}]"
    if np.isfinite(lo):
        return f"y >= {lo:.6g}"
    if np.isfinite(hi):
        return f"y <= {hi:.6g}"
    return "every y"


def _certify(art: Artefact, model: Model, box: np.ndarray, name: str, meaning: str) -> None:
    """Store where m is certified (values/m_domain, meta/m_domain_set, meta/m_domain) and h, to evaluate y = h(x)."""
    box = np.asarray(box, dtype=float).reshape(model.p, 2) + 0.0
    if not np.all(np.isfinite(box)) or np.any(box[:, 0] > box[:, 1]):
        raise DesignError("abstract.domain", f"the outputs where m is certified, {box.tolist()}, are not a bounded box", "a bounded V and Y")
    art.values["m_domain"] = box
    art.meta.update({"m_domain_set": name, "m_domain": meaning, "m_domain_rtol": DOMAIN_RTOL})
    art.exprs["h"] = model.h


def x_y_samples(model: Model, p_grid: np.ndarray) -> np.ndarray:
    """The ``SAMPLES`` random states of X_y = {x : h(x) in Y} (seed 0) on which condition (ii) is measured.

    Parameters
    ----------
    model : Model
        The spec's systems (h, C, Y, ``state_box``).
    p_grid : ndarray (n, N)
        p on the grid of V (the manifold's ``p_grid``), for the sampling box when the spec gives no ``concrete.state_box``.

    Returns
    -------
    ndarray (n, k)
        k <= ``SAMPLES`` states (k = ``SAMPLES`` for a linear h; fewer if rejection sampling rarely meets X_y).
    """
    h_num = model.numeric(model.h, list(model.x))
    return sample_states_with_output(h_num, model.C, model.Y, sample_box(model, p_grid), SAMPLES)


def _condition_ii_measure(model: Model, p_num, m: sp.Matrix, samples: np.ndarray) -> float:
    """max |h(x) - h(p(m(x)))| / |Y| over the samples of X_y (inf without samples, NaN where m is not real).

    ``p_num`` is p for numpy (:func:`ashc_cli.design.upstream.p_function`).
    """
    if not samples.size:
        return np.inf
    h_num = model.numeric(model.h, list(model.x))
    m_val = np.broadcast_to(model.numeric(m, list(model.x))(*samples)[:, 0, :], (model.n_hat, samples.shape[1]))
    x_proj = np.broadcast_to(p_num(*m_val)[:, 0, :], samples.shape)
    # h(x) = h(p(m(x))) = kappa(m(x)) on X_y (eq. (21c); Corollary 1 for linear h).
    return float(np.abs(h_num(*samples)[:, 0, :] - h_num(*x_proj)[:, 0, :]).max() / max(1.0, np.ptp(model.Y, axis=1).max()))


def _checks_common(art: Artefact, model: Model, p_num, m: sp.Matrix, p_grid: np.ndarray,
                   failure: tuple[str, str] | None = None, tol_i: float = LEFT_INVERSE_TOL, tol_ii: float = CONDITION_II_RTOL,
                   cond_i_points: np.ndarray | None = None) -> None:
    """Conditions (i) and (ii) of Theorem 6, measured the same way on every path.

    ``p_num`` is p for numpy (:func:`ashc_cli.design.upstream.p_function`).  ``failure`` (what, expected)
    replaces the generic explanation when condition (ii) fails (the affine path knows why: no left inverse of
    P satisfies C (I - P K) = 0).  ``tol_i`` and ``tol_ii`` are the tolerances of the two conditions (larger than
    the defaults for a hand-written m composed with a fitted p: :func:`composed_tolerances`).  ``cond_i_points``
    (states of Im(p), columns) replaces p_grid for condition (i) where m is fitted on Y only (X_y cap Im(p)).
    """
    m_num = model.numeric(m, list(model.x))
    on = p_grid if cond_i_points is None else cond_i_points
    m_back = np.broadcast_to(m_num(*on)[:, 0, :], (model.n_hat, on.shape[1]))
    p_back = np.broadcast_to(p_num(*m_back)[:, 0, :], on.shape)
    cond_i = float(np.abs(p_back - on).max() / max(1.0, np.abs(on).max()))
    cond_ii = _condition_ii_measure(model, p_num, m, x_y_samples(model, p_grid))
    if not cond_ii <= tol_ii:   # NaN (m not real at a sample) fails too
        what, expected = failure or ("", "x - p(m(x)) in Ker(h) (Corollary 1), or abstract.m written by hand (checked, not trusted)")
        raise DesignError("abstract", f"condition (ii) of Theorem 6 fails: |h(x - p(m(x)))| reaches {cond_ii:.3g} on X_y{what}", expected, check="condition_ii")
    art.values.update({"condition_i": cond_i, "condition_ii": cond_ii})
    art.checks["condition_i"] = Check(cond_i, cond_i <= tol_i, f"Theorem 6 (i): max |p(m(x)) - x| / max|x| on Im(p) (<= {tol_i:.3g})")
    art.checks["condition_ii"] = Check(cond_ii, cond_ii <= tol_ii, f"Theorem 6 (ii) via Corollary 1: max |h(x - p(m(x)))| / |Y| on samples of X_y (<= {tol_ii:.3g})")


def p_is_affine(man: Artefact, model: Model) -> bool:
    """Whether p is affine in xi: dp/dxi free of xi (for a series, of degree 0 in its chopped power basis, as
    its formula reads).

    Parameters
    ----------
    man : Artefact
        The manifold stage's artefact (series or expression ``dp_dxi``).
    model : Model
        The spec's systems (xi).

    Returns
    -------
    bool
    """
    if "dp_dxi" in man.series:
        return man.series["dp_dxi"].is_constant()
    return not any(e.free_symbols & set(model.xi) for e in man.expr("dp_dxi"))


def _affine_parts(model: Model, expr: sp.Matrix, jacobian: sp.Matrix) -> tuple[np.ndarray, np.ndarray]:
    """(J, c) with expr(xi) = J xi + c numerically, for an expression affine in xi and its stored Jacobian."""
    J = np.array(model.substitute(jacobian), dtype=float).reshape(expr.shape[0], model.n_hat)
    c = np.array(model.substitute(expr.xreplace({s: 0 for s in model.xi})), dtype=float).reshape(-1)
    return J, c


def choose_left_inverse(P: np.ndarray, C: np.ndarray | None) -> dict:
    """The left inverse K of P (K P = I) used for m(x) = K (x - p0), chosen with condition (ii) in view (eq. (24)).

    Every left inverse of a P of full column rank is K = P^+ + Z (I - P P^+).  With a linear h = C x,
    condition (ii) holds for every x iff C (I - P K) = 0, i.e. C P K = C.  P^+ is kept when it satisfies
    that (it is then the least-norm solution anyway); otherwise the least-norm K of the linear system
    K P = I, C P K = C (in vec(K), Frobenius norm) is taken from ``numpy.linalg.lstsq``, and used when its
    residual shows the system is solvable.  When it is not (or h is not linear), K = P^+.

    Parameters
    ----------
    P : ndarray (n, n_hat)
        The matrix of p(xi) = P xi + p0, of full column rank.
    C : ndarray (r, n) or None
        C of a linear h = C x (the stage passes the unit rows of the states a nonlinear h names); None: K = P^+.

    Returns
    -------
    dict
        K (n_hat x n); construction (``PSEUDO_INVERSE`` or ``LEAST_NORM``); residual_pinv and residual:
        max |C (I - P K)| / max(1, max |C|) for P^+ and for K (NaN for a nonlinear h); solvable (whether some
        left inverse satisfies C (I - P K) = 0; None for a nonlinear h); system_residual (of the least-squares
        solve, NaN if not needed).
    """
    n, n_hat = P.shape
    P_plus = np.linalg.pinv(P)
    out = {"K": P_plus, "construction": PSEUDO_INVERSE, "residual_pinv": np.nan, "residual": np.nan, "solvable": None, "system_residual": np.nan}
    if C is None:
        return out
    scale = max(1.0, float(np.abs(C).max()))
    r_plus = float(np.abs(C @ (np.eye(n) - P @ P_plus)).max()) / scale
    out.update(residual_pinv=r_plus, residual=r_plus)
    if r_plus <= CONDITION_II_MATRIX_RTOL:
        out["solvable"] = True
        return out
    # vec (column-major): vec(K P) = (P^T kron I_nhat) vec K and vec(C P K) = (I_n kron C P) vec K.
    system = np.vstack([np.kron(P.T, np.eye(n_hat)), np.kron(np.eye(n), C @ P)])
    rhs = np.concatenate([np.eye(n_hat).ravel(order="F"), C.ravel(order="F")])
    vec, *_ = np.linalg.lstsq(system, rhs, rcond=None)
    K = vec.reshape(n_hat, n, order="F")
    out["system_residual"] = float(np.abs(system @ vec - rhs).max())
    r_K = float(np.abs(C @ (np.eye(n) - P @ K)).max()) / scale
    left_K = float(np.abs(K @ P - np.eye(n_hat)).max())
    out["solvable"] = bool(r_K <= CONDITION_II_MATRIX_RTOL and left_K <= CONDITION_II_MATRIX_RTOL)
    if out["solvable"]:
        out.update(K=K, construction=LEAST_NORM, residual=r_K)
    return out


def _cover_affine(model: Model, kap: Artefact) -> tuple[list, np.ndarray]:
    """eq. (10) for an affine kappa: the vertices of Y no xi in V reaches (a linear program per vertex,
    kappa(V) being a convex polytope), and the box of kappa over the corners of V."""
    K, k0 = _affine_parts(model, kap.expr("kappa"), kap.expr("dkappa_dxi"))
    missing = []
    for vertex in itertools.product(*[(lo, hi) for lo, hi in model.Y]):
        lp = sopt.linprog(np.zeros(model.n_hat), A_eq=K, b_eq=np.array(vertex) - k0, bounds=[tuple(b) for b in model.V], method="highs")
        if lp.status != 0:
            missing.append(list(vertex))
    corners = np.array(list(itertools.product(*[(lo, hi) for lo, hi in model.V]))).T
    k_corners = K @ corners + k0[:, None]
    return missing, np.c_[k_corners.min(axis=1), k_corners.max(axis=1)]


def _output_states_map(model: Model) -> np.ndarray:
    """T with rows e_j for the states x_j that h names: h(x) = H(T x) (every state if h names none)."""
    named = [j for j, xj in enumerate(model.x) if any(xj in e.free_symbols for e in model.h)]
    rows = named or list(range(model.n))
    return np.eye(model.n)[rows]


def _cover_nonlinear(model: Model, kap: Artefact) -> tuple[float, str, str, bool]:
    """eq. (10) for a nonlinear kappa: kappa(V) is the interval of kappa's extremes on V for one
    abstract state and one output (continuity), else a bounded search per point of a grid of Y.

    Returns (value, description, failure text, covers)."""
    Y = model.Y
    k_range = np.asarray(kap.value("kappa_range"), dtype=float)
    if model.n_hat == 1 and model.p == 1:
        value = float(max(k_range[0, 0] - Y[0, 0], Y[0, 1] - k_range[0, 1]))
        return (value, "eq. (10): kappa(V) contains Y (<= 0)",
                f"kappa(V) = [{k_range[0, 0]:.6g}, {k_range[0, 1]:.6g}] does not contain Y = {Y[0].tolist()}", value <= 0)
    value = _cover_by_search(model, kap)
    return (value, f"eq. (10): largest |kappa(xi) - y| / |Y| left by a search for xi in V, on a {COVER_POINTS}-point grid of Y (<= 1e-9)",
            f"some outputs of Y are not kappa(xi) for any xi in V (residual {value:.3g})", value <= 1e-9)


def _run_linear(model: Model, man: Artefact, kap: Artefact) -> Artefact:
    """The left inverse m(x) = K (x - p0) of an affine p(xi) = P xi + p0 (K from :func:`choose_left_inverse`), and its checks."""
    p = man.expr("p")
    P, p0 = _affine_parts(model, p, man.expr("dp_dxi"))
    sv = np.linalg.svd(P, compute_uv=False)
    if sv.min() <= 1e-12 * max(1.0, sv.max()):
        raise DesignError("abstract", f"p(xi) = P xi + p0 is not injective: P has rank {int(np.sum(sv > 1e-12 * sv.max()))} < n_hat = {model.n_hat}",
                          "P of full column rank (Theorem 6)", check="left_inverse")
    C = model.C
    # A nonlinear h reads the states it names: h(x) = H(T x) with T the rows e_j of those states.  Condition (ii)
    # h(x) = h(p(m(x))) then holds for every x when T (I - P K) = 0, the linear case with C replaced by T.
    T = C if C is not None else _output_states_map(model)
    choice = choose_left_inverse(P, T)
    kappa_affine = C is not None or proofs.affine_in(kap.expr("kappa"), list(model.xi))
    proof = prove_affine_inverse(model, man, kap, T, choice["K"], kappa_affine)
    K_m = proof["K"]             # the doubles nearest the exact left inverse where it is proved
    m = sp.Matrix(K_m.tolist()) * (model.x - sp.Matrix(p0.tolist()))
    grid = np.asarray(man.value("xi_grid"))
    p_grid = np.asarray(man.value("p_grid"))
    left_residual = float(np.abs(K_m @ (p_grid - p0[:, None]) - grid).max())

    # eq. (10): every vertex of Y is kappa(xi) for some xi in V (kappa(V) is a convex polytope when
    # kappa is affine; for a nonlinear h, kappa = h o p is not, and the cover is checked as for an explicit m).
    if kappa_affine:
        missing, k_range = _cover_affine(model, kap)
        K_kappa, _ = _affine_parts(model, kap.expr("kappa"), kap.expr("dkappa_dxi"))
        covers = not missing
        cover_value, cover_text = float(len(missing)), "eq. (10): vertices of Y not reached from V (0)"
        failure = f"no xi in V reaches the output(s) {missing}"
        min_dkappa = float(np.linalg.svd(K_kappa, compute_uv=False).min())
    else:
        k_range = np.asarray(kap.value("kappa_range"), dtype=float)
        cover_value, cover_text, failure, covers = _cover_nonlinear(model, kap)
        grid_dk = np.moveaxis(np.broadcast_to(model.numeric(kap.expr("dkappa_dxi"), list(model.xi))(*np.asarray(man.value("xi_grid"))),
                                              (model.p, model.n_hat, grid.shape[1])), -1, 0)
        min_dkappa = float(np.linalg.svd(grid_dk, compute_uv=False).min())
    if proof["covers"] is False:
        # Decided exactly (rationals): the linear program's tolerance may have let a small gap pass.
        covers = False
        if "kappa_V_exact" in proof:
            lo, hi = proof["kappa_V_exact"]
            y_text = "[" + ", ".join(repr(float(v)) for v in model.Y[0]) + "]"
            failure = (f"kappa(V) = [{lo!r}, {hi!r}] (exactly, in rationals) misses Y = {y_text} by {proof['covers_gap']:.3g}"
                       + (" (at the level of rounding: widen V or shrink Y by that much)" if proof["covers_gap"] <= 1e-12 * max(1.0, np.abs(model.Y).max()) else ""))
        else:
            failure = "an exact rational linear program finds a vertex of Y that no xi in V reaches (the gap is below the floating-point program's tolerance)"
    if not covers:
        raise DesignError("abstract.domain", f"kappa(V) does not cover Y (eq. (10)): {failure}",
                          "a larger domain V, or a smaller output_set", check="V_covers_Y")

    least_norm = choice["construction"] == LEAST_NORM
    method = ("linear: m(x) = K (x - p0), K the least-norm left inverse of P with C (I - P K) = 0 (P^+ fails condition (ii))" if least_norm
              else "linear: m(x) = P^+ (x - p0)")
    art = Artefact(stage=NAME, meta={"method": method, "construction": choice["construction"], "samples": SAMPLES, "sample_seed": 0,
                                      "left_inverse_tol": LEFT_INVERSE_TOL, "condition_ii_rtol": CONDITION_II_RTOL,
                                      "condition_ii_matrix_rtol": CONDITION_II_MATRIX_RTOL})
    art.exprs.update({"m": m, "dm_dx": sparse_jacobian(m, model.x)})
    symbolic_ii = bool(np.abs(T @ (np.eye(model.n) - P @ K_m)).max() < 1e-12)
    art.values.update({
        "V": model.V, "Y": model.Y, "kappa_range": k_range, "m_real_interval": np.array([-np.inf, np.inf]), "radicands": ["none"],
        "left_inverse_residual": left_residual, "condition_ii_symbolic": symbolic_ii,
        "min_abs_dkappa": min_dkappa,
        "left_inverse_matrix": K_m,
        # max |C (I - P K)| / max(1, max |C|) for P^+ and for the K used (NaN for a nonlinear h)
        "condition_ii_matrix_pinv": choice["residual_pinv"], "condition_ii_matrix": choice["residual"],
    })
    if least_norm:
        samples = x_y_samples(model, p_grid)
        pinv_m = sp.Matrix(np.linalg.pinv(P).tolist()) * (model.x - sp.Matrix(p0.tolist()))
        art.values["condition_ii_pseudo_inverse"] = _condition_ii_measure(model, p_function(man, model), pinv_m, samples)
    art.checks["left_inverse"] = Check(left_residual, left_residual <= LEFT_INVERSE_TOL, f"max |m(p(xi)) - xi| on V (<= {LEFT_INVERSE_TOL:g}): p is injective on V")
    art.checks["V_covers_Y"] = Check(cover_value, covers, cover_text)
    art.checks["m_real_on_Y"] = Check(0.0, True, "m is linear, hence real everywhere")
    which = "m = K (x - p0)" if least_norm else "m = P^+ (x - p0)"
    if model.n_hat == 1 and model.p == 1 and symbolic_ii and kappa_affine:
        # kappa(m(x)) = h(x) for every x and kappa is a bijection of R: m(x) is in V exactly when h(x) is in kappa(V).
        _certify(art, model, k_range, "kappa(V)", f"kappa(V): {which} is linear and real everywhere, and m(x) lies in V "
                 "(where the abstraction is certified) exactly when h(x) lies in kappa(V)")
    else:
        _certify(art, model, model.Y, "Y", f"Y: {which} is linear and real everywhere; conditions (i), (ii) are certified on "
                 "X_y = h^-1(Y), and kappa(V) is not an interval of one output here")
    failure = None
    if choice["solvable"] is False:
        failure = (f"; no left inverse K of P satisfies C (I - P K) = 0 (with K = P^+, max |C (I - P P^+)| = {choice['residual_pinv']:.3g}; "
                   f"least-squares residual of K P = I, C P K = C: {choice['system_residual']:.3g})",
                   "an abstraction whose kappa = C P has full row rank (at least as many abstract states as independent outputs), "
                   "or C^T in the range of P: change abstract.states, phi_bar or l, or the outputs h")
    _checks_common(art, model, p_function(man, model), m, p_grid, failure)
    art.meta["proof"] = proof["how"]
    art.values["left_inverse_exact_deviation"] = proof["K_deviation"]
    if proof["left_inverse"]:
        for name in ("left_inverse", "condition_i", "condition_ii", "m_real_on_Y"):
            relabel_proved(art, name, proof["how"])
    if proof["covers"]:
        relabel_proved(art, "V_covers_Y", proof["how"])
    return art


def _run_multi(model: Model, man: Artefact, kap: Artefact) -> Artefact:
    """The left inverse m(x) = kappa^-1(h(x)) for several abstract states and as many outputs (closed form).

    Checks as the scalar path: m(p(xi)) = xi on V; m finite on a grid of Y with kappa(m(y)) = y and m(y) in V
    there (so kappa(V) covers Y, eq. (10)); conditions (i) and (ii) of Theorem 6.
    """
    kappa = kap.expr("kappa")
    ys = [sp.Symbol(f"_y{k}", real=True) for k in range(model.p)]
    grid, p_grid = np.asarray(man.value("xi_grid")), np.asarray(man.value("p_grid"))
    h_num = model.numeric(model.h, list(model.x))
    y_grid = h_num(*p_grid)[:, 0, :]
    branches = closed_form_branches(model, kappa, ys)
    residuals = branch_residuals(model, branches, ys, y_grid, grid)
    best, best_residual = (branches[int(np.argmin(residuals))], min(residuals)) if branches else (None, np.inf)
    method, fit, cond_i_points = "closed form (sympy.solve of kappa(m) = y, several outputs)", None, None
    if best is None or best_residual > LEFT_INVERSE_TOL:
        fit = kappa_inverse_on_Y(model, man, kap, ys, y_grid, best_residual)
        best, best_residual, cond_i_points = fit["m_of_y"], fit["left_residual"], fit["p_points"]
        method = (f"tensor Chebyshev series of kappa^-1 on Y, degree {fit['degree']} per axis, from Newton solutions of kappa(xi) = y at its nodes "
                  "(no closed form)")
    m_of_y = tidy(sp.Matrix(best)) if fit is None else sp.Matrix(best)
    m = m_of_y.xreplace(dict(zip(ys, model.h)))
    Y, V = model.Y, model.V
    y_box = domain_grid(Y, 4001)
    m_on_Y = np.broadcast_to(model.numeric(m_of_y, ys)(*y_box)[:, 0, :], (model.n_hat, y_box.shape[1]))
    finite = bool(np.all(np.isfinite(m_on_Y)))
    excursion = float(np.max(np.r_[V[:, :1] - m_on_Y, m_on_Y - V[:, 1:]])) if finite else np.inf
    covers = finite and excursion <= 1e-12
    if not finite:
        raise DesignError("concrete.output_set", "m(y) = kappa^-1(y) is not real and finite on all of Y",
                          "Y inside the outputs where kappa^-1 is defined, or abstract.m written by hand (checked, not trusted)", check="m_real_on_Y")
    if not covers:
        raise DesignError("abstract.domain", f"kappa(V) does not cover Y (eq. (10)): kappa^-1(Y) leaves V by {excursion:.4g}",
                          "a larger domain V, or a smaller output_set", check="V_covers_Y")
    art = Artefact(stage=NAME, meta={"method": method, "construction": KAPPA_INVERSE, "samples": SAMPLES, "sample_seed": 0,
                                      "left_inverse_tol": LEFT_INVERSE_TOL, "condition_ii_rtol": CONDITION_II_RTOL})
    # dm/dx by the chain rule through the fitted series' derivative (its formula is for values only)
    dm_dx = sparse_jacobian(m, model.x) if fit is None else fit["dm_dy"].xreplace(dict(zip(ys, model.h))) * sparse_jacobian(model.h, model.x)
    art.exprs.update({"m": m, "m_of_y": m_of_y.xreplace({yk: sp.Symbol(f"y{k + 1}", real=True) for k, yk in enumerate(ys)}), "dm_dx": dm_dx})
    dkappa = np.moveaxis(np.broadcast_to(model.numeric(kap.expr("dkappa_dxi"), list(model.xi))(*grid), (model.p, model.n_hat, grid.shape[1])), -1, 0)
    smin = float(np.linalg.svd(dkappa, compute_uv=False).min())
    # Without radicands m is real for every y (proved); with them, only checked on a grid of Y: no interval to
    # state (NaN ends), the radicands are listed.
    radicands = sorted({str(pw.base) for e in m_of_y for pw in e.atoms(sp.Pow) if pw.exp.is_Rational and pw.exp.q % 2 == 0})
    real = np.array([-np.inf, np.inf]) if not radicands else np.array([np.nan, np.nan])
    art.values.update({
        "V": V, "Y": Y, "kappa_range": np.c_[y_grid.min(axis=1), y_grid.max(axis=1)], "m_real_interval": real,
        "radicands": radicands if radicands else ["none"], "left_inverse_residual": best_residual, "condition_ii_symbolic": False, "min_abs_dkappa": smin,
    })
    if fit is None:
        art.checks["left_inverse"] = Check(best_residual, True, f"max |m(p(xi)) - xi| on V (<= {LEFT_INVERSE_TOL:g}): p is injective on V")
    else:
        art.values.update({"m_fit_degree": fit["degree"], "m_fit_error": fit["error"], "m_fit_check_points": fit["check_points"]})
        art.checks["left_inverse"] = Check(best_residual, True, f"max |m(p(xi)) - xi| on the points of V's grid with kappa(xi) in Y and on the Newton "
                                                                f"solutions at a {fit['check_points']}-point grid of Y (<= {LEFT_INVERSE_TOL:g}): "
                                                                "p is injective where m is used")
    art.checks["V_covers_Y"] = Check(excursion, covers, "eq. (10): largest excursion of kappa^-1(Y) outside V on a grid of Y (<= 0)")
    art.checks["m_real_on_Y"] = Check(0.0, finite, "m = kappa^-1 real and finite on a grid of Y")
    _certify(art, model, Y, "Y", "Y: m = kappa^-1 is checked real, finite and inside V on a grid of Y (kappa(V) is not a box of outputs)"
             + ("; the series of kappa^-1 is fitted on Y only" if fit is not None else ""))
    _checks_common(art, model, p_function(man, model), m, p_grid, cond_i_points=cond_i_points)
    if fit is None:
        proof = prove_multi_inverse(model, kappa, m_of_y, ys)
    else:   # a fitted m: kappa(m(y)) = y holds to the fit only; its finiteness from the coefficients (|T_k| <= 1)
        proof = {"monotone": False, "covers": False, "left_inverse": False, "condition_ii": False, "real_on_Y": True,
                 "how": f"m is a Chebyshev series on Y: |m| <= {fit['series'].abs_bound():.4g} (the sum of its |coefficients|), real and finite"}
    art.meta["proof"] = proof["how"]
    mark_proved(art, proof)
    return art


#: Points of the grid of Y on which kappa(V) covering Y is checked for an explicit m with a nonlinear kappa of
#: several abstract states (a bounded least-squares solve of kappa(xi) = y per point).
COVER_POINTS = 400


def _cover_by_search(model: Model, kap: Artefact) -> float:
    """eq. (10) on a grid of Y: the largest |kappa(xi) - y| left by a bounded least-squares search
    for xi in V (from the nearest point of kappa's grid), relative to the size of Y (0 when covered)."""
    kappa_num = model.numeric(kap.expr("kappa"), list(model.xi))
    jac_num = model.numeric(kap.expr("dkappa_dxi"), list(model.xi))
    xs, ks = np.asarray(kap.value("xi_grid")), np.asarray(kap.value("kappa_grid"))
    ys = domain_grid(model.Y, COVER_POINTS)
    lo, hi = model.V[:, 0], model.V[:, 1]
    worst = 0.0
    for y in ys.T:
        start = xs[:, int(np.argmin(np.abs(ks - y[:, None]).sum(axis=0)))]
        fit = sopt.least_squares(lambda z: kappa_num(*z)[:, 0] - y, start, jac=lambda z: np.asarray(jac_num(*z), dtype=float).reshape(model.p, model.n_hat),
                                 bounds=(lo, hi), xtol=1e-15, ftol=1e-15, gtol=1e-15)
        worst = max(worst, float(np.abs(fit.fun).max()))
    return worst / max(1.0, float(np.ptp(model.Y, axis=1).max()))


def _explicit_covers(model: Model, kap: Artefact):
    """(kappa affine, kappa's range, cover value, check text): eq. (10), kappa(V) covers Y, for a given m (linear
    programs for an affine kappa, kappa's range for one state and one output, else a search per point of Y); a
    DesignError when it does not."""
    Y = model.Y
    kappa_affine = proofs.affine_in(kap.expr("kappa"), list(model.xi))
    if kappa_affine:
        missing, k_range = _cover_affine(model, kap)
        cover_value, covers = float(len(missing)), not missing
        cover_text = "eq. (10): vertices of Y not reached from V (0)"
        failure = f"no xi in V reaches the output(s) {missing}"
    else:
        k_range = np.asarray(kap.value("kappa_range"), dtype=float)
        if model.n_hat == 1 and model.p == 1:
            # kappa is continuous and V an interval: kappa(V) is the interval between its extremes on V.
            cover_value = float(max(k_range[0, 0] - Y[0, 0], Y[0, 1] - k_range[0, 1]))
            cover_text = "eq. (10): kappa(V) contains Y (<= 0)"
            failure = f"kappa(V) = [{k_range[0, 0]:.6g}, {k_range[0, 1]:.6g}] does not contain Y = {Y[0].tolist()}"
            covers = cover_value <= 0
        else:
            cover_value = _cover_by_search(model, kap)
            cover_text = f"eq. (10): largest |kappa(xi) - y| / |Y| left by a search for xi in V, on a {COVER_POINTS}-point grid of Y (<= 1e-9)"
            failure = f"some outputs of Y are not kappa(xi) for any xi in V (residual {cover_value:.3g})"
            covers = cover_value <= 1e-9
    if not covers:
        raise DesignError("abstract.domain", f"kappa(V) does not cover Y (eq. (10)): {failure}", "a larger domain V, or a smaller output_set", check="V_covers_Y")

    return kappa_affine, k_range, cover_value, cover_text


def _run_explicit(model: Model, man: Artefact, kap: Artefact) -> Artefact:
    """Check the left inverse the spec gives (``abstract.m``) and store it like the constructed ones.

    Checked, not trusted: m(p(xi)) = xi on the grid of V (symbolically when sympy reduces m(p(xi)) - xi to
    0), m real and finite on samples of X_y, condition (ii) on them (symbolically: h(p(m(x))) - h(x) = 0),
    condition (i), and kappa(V) covering Y (linear programs for an affine kappa, kappa's range on V for one
    abstract state and one output, else a bounded search per point of a grid of Y).

    Raises
    ------
    DesignError
        If m is not a left inverse of p on V (check ``left_inverse``), is not real and finite on X_y
        (``m_real_on_Y``), fails condition (ii) (``condition_ii``), or kappa(V) does not cover Y (``V_covers_Y``).
    """
    m = model.m_given
    grid, p_grid = np.asarray(man.value("xi_grid")), np.asarray(man.value("p_grid"))
    m_num = model.numeric(m, list(model.x))
    tol = composed_tolerances(model, man, m, p_grid)
    # A fitted p (floats, or a series) is never exactly a left inverse's partner: sympy is not asked (on a fit of degree
    # 80 it spent 900 s simplifying m(p(xi)) - xi).
    fitted = "p" in man.series or tol["p_error"] > 0
    p = None if fitted else man.expr("p")
    from_fit = f" (1e-9 plus {COMPOSE_SAFETY:g} x the fit error of p, {tol['p_error']:.2g} per state at most, through dm/dx)" if tol["left"] > LEFT_INVERSE_TOL else ""

    # m(p(xi)) = xi on V (Theorem 6, step 1: p is injective on V with m as its left inverse).
    back = np.broadcast_to(m_num(*p_grid)[:, 0, :], grid.shape)
    errors = np.abs(back - grid).max(axis=0)
    left_residual = float(errors.max()) if np.all(np.isfinite(back)) else np.inf
    if not left_residual <= tol["left"]:
        worst = int(np.argmax(np.where(np.isfinite(errors), errors, np.inf)))
        raise DesignError("abstract.m", f"the given m is not a left inverse of p on V: max |m(p(xi)) - xi| = {left_residual:.3g} (at xi = {np.round(grid[:, worst], 6).tolist()})",
                          f"m(p(xi)) = xi for every xi in V (Theorem 6), to {tol['left']:.3g}{from_fit}; or leave abstract.m out to have m constructed", check="left_inverse")
    polynomial = all(e.is_polynomial(*model.x) for e in m)
    symbolic_left = not fitted and proofs.symbolic_zero(list(m.xreplace(dict(zip(model.x, p))) - model.xi))

    # m real and finite where it is used: on the samples of X_y (everywhere when m is a polynomial).
    samples = x_y_samples(model, p_grid)
    m_on_samples = np.asarray(m_num(*samples)) if samples.size else np.zeros((model.n_hat, 1, 0))
    finite = bool(samples.size and np.all(np.isfinite(m_on_samples)))
    if not finite:
        raise DesignError("abstract.m", "the given m is not real and finite on the samples of X_y = {x : h(x) in Y}", "an m real and finite wherever h(x) is in Y", check="m_real_on_Y")
    radicands = sorted({str(pw.base) for e in m for pw in e.atoms(sp.Pow) if pw.exp.is_Rational and pw.exp.q % 2 == 0})

    # Condition (ii): h(p(m(x))) = h(x), symbolically when sympy can; sampled in _checks_common.
    symbolic_ii = not fitted and proofs.symbolic_zero(list(model.h.xreplace(dict(zip(model.x, p))).xreplace(dict(zip(model.xi, m))) - model.h))
    cond_ii = _condition_ii_measure(model, p_function(man, model), m, samples)
    if not cond_ii <= tol["ii"]:
        raise DesignError("abstract.m", f"the given m fails condition (ii) of Theorem 6: |h(x - p(m(x)))| reaches {cond_ii:.3g} on X_y",
                          "x - p(m(x)) in Ker(h) for x in X_y (Corollary 1): kappa(m(x)) = h(x); or leave abstract.m out to have m constructed", check="condition_ii")

    Y, V = model.Y, model.V
    kappa_affine, k_range, cover_value, cover_text = _explicit_covers(model, kap)

    grid_dk = np.moveaxis(np.broadcast_to(model.numeric(kap.expr("dkappa_dxi"), list(model.xi))(*grid), (model.p, model.n_hat, grid.shape[1])), -1, 0)
    art = Artefact(stage=NAME, meta={"method": "explicit m from the spec (abstract.m), checked", "construction": EXPLICIT, "samples": SAMPLES, "sample_seed": 0,
                                      "left_inverse_tol": tol["left"], "condition_i_tol": tol["i"], "condition_ii_rtol": tol["ii"]})
    art.exprs.update({"m": m, "dm_dx": sparse_jacobian(m, model.x)})
    art.values.update({
        "V": V, "Y": Y, "kappa_range": k_range,
        # A polynomial m is real everywhere; otherwise it is only checked real and finite on samples (NaN ends).
        "m_real_interval": np.array([-np.inf, np.inf]) if polynomial else np.array([np.nan, np.nan]),
        "radicands": radicands if radicands else ["none"], "left_inverse_residual": left_residual,
        "condition_ii_symbolic": bool(symbolic_ii), "min_abs_dkappa": float(np.linalg.svd(grid_dk, compute_uv=False).min()),
    })
    # Proved only for a polynomial m (defined everywhere); sympy's identities may hold only where m is real.
    proved_left, proved_ii = bool(polynomial and symbolic_left), bool(polynomial and symbolic_ii)
    left_text = f"max |m(p(xi)) - xi| on V (<= {tol['left']:.3g}{from_fit}): p is injective on V, with the spec's m as left inverse"
    art.checks["left_inverse"] = Check(left_residual, True, left_text + ("; proved (m(p(xi)) - xi simplifies to 0, sympy)" if proved_left else ""),
                                       proofs.PROVED if proved_left else proofs.SAMPLED)
    art.checks["V_covers_Y"] = Check(cover_value, True, cover_text)
    if polynomial:
        art.checks["m_real_on_Y"] = Check(0.0, True, "m is a polynomial in x, hence real everywhere", proofs.PROVED)
    else:
        art.checks["m_real_on_Y"] = Check(0.0, True, f"m real and finite on {samples.shape[1]} samples of X_y")
    if model.n_hat == 1 and model.p == 1 and kappa_affine and symbolic_ii:
        # kappa(m(x)) = h(x) for every x and kappa is an affine bijection of R: m(x) is in V exactly when h(x) is in kappa(V).
        _certify(art, model, k_range, "kappa(V)", "kappa(V): the spec's m satisfies kappa(m(x)) = h(x) for every x (sympy) and kappa is affine, "
                 "so m(x) lies in V (where the abstraction is certified) exactly when h(x) lies in kappa(V)")
    else:
        _certify(art, model, Y, "Y", "Y: the spec's m is checked (conditions (i), (ii)) on X_y = h^-1(Y)")
    _checks_common(art, model, p_function(man, model), m, p_grid, tol_i=tol["i"], tol_ii=tol["ii"])
    if proved_left:   # p(m(p(xi))) = p(xi) follows from m(p(xi)) = xi
        relabel_proved(art, "condition_i", "m(p(xi)) = xi symbolically")
    if proved_ii:
        relabel_proved(art, "condition_ii", "h(p(m(x))) - h(x) simplifies to 0, sympy")
    return art


def run(model: Model, upstream: dict[str, Artefact]) -> Artefact:
    """Find the left inverse m of p (h = kappa(m) on X_y: eqs. (11b), (21c)) and check (i), (ii) (eq. (23)) and eq. (10).

    Parameters
    ----------
    model : Model
        The spec's systems.
    upstream : dict of str to Artefact
        The manifold and kappa artefacts.

    Returns
    -------
    Artefact
        Expressions m (n_hat x 1, in x) and h; values V, Y, m_real_interval, m_domain (where m is certified),
        kappa_range and the residuals.

    Raises
    ------
    DesignError
        If the shapes are not supported, no branch of m is a left inverse on V (p not injective),
        kappa(V) does not cover Y, or m is not real on all of Y; for an explicit ``abstract.m``, if it is not
        a left inverse of p on V or fails condition (ii).
    """
    man, kap = upstream["manifold"], upstream["kappa"]
    if model.m_given is not None:
        return _run_explicit(model, man, kap)
    if p_is_affine(man, model):
        return _run_linear(model, man, kap)
    if model.n_hat > model.p:   # outputs augmented with the states that complete kappa to a square map
        aug, kap_aug, added = augment_outputs(model, man, kap)
        return note_augmented(_run_multi(aug, man, kap_aug), added)
    if model.n_hat != model.p:
        raise DesignError("abstract.states", f"the left inverse m = kappa^-1(h(x)) of a nonlinear p needs at least as many abstract states as outputs (n_hat = {model.n_hat}, p = {model.p})",
                          "an affine p (m = P^+ (x - p0)), more abstract states, or abstract.m written by hand (checked, not trusted)")
    if model.n_hat > 1:
        return _run_multi(model, man, kap)
    return _run_scalar(model, man, kap)


def _run_scalar(model: Model, man: Artefact, kap: Artefact) -> Artefact:
    """One abstract state and one output: m = kappa^-1(h(x)) (:func:`run`), its branch and where it is real."""
    b = _scalar_branch(model, man, kap)
    return _scalar_artefact(model, man, kap, b, _real_on_Y(model, b.m_of_y, b.y, b.y_grid))


def _scalar_branch(model: Model, man: Artefact, kap: Artefact) -> Branch:
    """The :class:`Branch` of kappa(m) = y that is a left inverse of p on V (a closed form, else a Chebyshev interpolant of kappa^-1); a DesignError naming
    where kappa turns when none is."""
    kappa = kap.expr("kappa")
    y = output_symbol()
    grid = np.asarray(man.value("xi_grid"))
    p_grid = np.asarray(man.value("p_grid"))
    h_num = model.numeric(model.h, list(model.x))
    y_grid = h_num(*p_grid)[0, 0]
    candidates = closed_form_branches(model, kappa, [y])
    residuals = branch_residuals(model, candidates, [y], y_grid[None, :], grid)
    branches = [b[0] for b in candidates]
    method = "closed form (sympy.solve of kappa(m) = y)"
    if not branches or min(residuals) > LEFT_INVERSE_TOL:
        kappa_fn = kap.series["kappa"] if "kappa" in kap.series else model.numeric(kappa, list(model.xi))
        pieces = getattr(kap.series.get("kappa"), "breaks", ())
        try:
            numeric = numeric_inverse(kappa_fn, grid[0], y_grid, y, pieces[1:-1] if len(pieces) else ())
        except FitError as exc:
            raise DesignError("abstract.m", f"kappa is strictly monotone on V = {model.V.tolist()} (so p is injective), but sympy finds no closed form "
                              f"of m and its piecewise Chebyshev interpolant misses kappa^-1 by {exc.measure:.3g} near y in [{exc.interval[0]:.6g}, "
                              f"{exc.interval[1]:.6g}] ({exc.reason}: kappa is too steep there for polynomial pieces)",
                              "abstract.m written by hand (it is checked, not trusted), or a smaller abstract.domain", check="left_inverse") from None
        if numeric is not None:
            branches, residuals = [numeric[0]], [numeric[1]]
            method = f"Chebyshev interpolant of kappa^-1 on kappa(V), {numeric[2]} (no closed form)"
    if not branches:
        raise DesignError("abstract", "kappa(m) = y has no closed-form solution m(y) and kappa is not strictly monotone on V",
                          "a kappa that is invertible on V, or abstract.m written by hand (checked, not trusted)", check="left_inverse")
    best = int(np.argmin(residuals))
    left_residual = residuals[best]
    if left_residual > LEFT_INVERSE_TOL:
        dk = np.diff(y_grid)
        turns = grid[0, 1:-1][np.sign(dk[1:]) != np.sign(dk[:-1])]
        where = f"; kappa turns at xi = {np.round(turns, 4).tolist()[:3]}" if turns.size else ""
        if not turns.size and method.startswith("Chebyshev"):
            raise DesignError("abstract.m", f"kappa is strictly monotone on V = {model.V.tolist()} (so p is injective), but sympy finds no closed form "
                              f"of m and its piecewise Chebyshev interpolant reaches only max |m(p(xi)) - xi| = "
                              f"{left_residual:.3g} (kappa is too steep in places for polynomial pieces)",
                              "abstract.m written by hand (it is checked, not trusted), or a smaller abstract.domain", check="left_inverse")
        raise DesignError("abstract.domain", f"p is not injective on V = {model.V.tolist()}: no branch of m satisfies m(p(xi)) = xi (best residual {left_residual:.3g}{where})",
                          "a domain V on which kappa is strictly monotone, or abstract.m written by hand (checked, not trusted)", check="left_inverse")
    m_of_y = tidy(sp.Matrix([branches[best]]))[0]
    return Branch(m_of_y, y, method, len(branches), left_residual, y_grid)


def _real_on_Y(model: Model, m_of_y: sp.Expr, y: sp.Symbol, y_grid: np.ndarray):
    """(lo, hi, radicands): where m is real; a DesignError if Y reaches outputs where m is not real or finite."""
    Y = model.Y
    real_lo, real_hi, radicands = real_interval(m_of_y, y, model)
    real_covers_Y = bool(real_lo <= Y[0, 0] and Y[0, 1] <= real_hi)
    m_on_Y = model.numeric([m_of_y], [y])(np.linspace(Y[0, 0], Y[0, 1], 20001))[0, 0]
    finite_on_Y = bool(np.all(np.isfinite(m_on_Y)))
    if not (real_covers_Y and finite_on_Y):
        k_lo, k_hi = float(y_grid.min()), float(y_grid.max())
        reach = f"kappa(V) = {format_box(np.array([[k_lo, k_hi]]))} on V = {format_box(model.V)}"
        if not real_covers_Y:
            what = (f"Y = {format_box(Y)} reaches outputs where m is not real (m is real only for y in "
                    f"{format_box(np.array([[real_lo, real_hi]]))}); {reach}")
        else:
            bad = np.linspace(Y[0, 0], Y[0, 1], 20001)[~np.isfinite(m_on_Y)]
            what = f"m is not finite at y = {bad[0]:.6g} in Y = {format_box(Y)}; {reach}"
        raise DesignError("concrete.output_set", what,
                          f"an output_set inside {format_box(np.array([[max(real_lo, k_lo), min(real_hi, k_hi)]]))} "
                          "(where m is real and kappa reaches), a larger domain V if kappa(V) is the limit, or abstract.m written by hand (checked, not trusted)", check="m_real_on_Y")

    return real_lo, real_hi, radicands


def _scalar_artefact(model: Model, man: Artefact, kap: Artefact, branch: Branch, real: tuple) -> Artefact:
    """Eq. (10) (kappa(V) covers Y), kappa's monotonicity, the certified set and the proofs, into the artefact
    (``real``: :func:`_real_on_Y`'s lo, hi and radicands)."""
    (m_of_y, y, method, n_branches, left_residual, y_grid), (real_lo, real_hi, radicands) = branch, real
    m = sp.Matrix([m_of_y.xreplace({y: model.h[0]})])
    kappa, xi, Y = kap.expr("kappa"), model.xi[0], model.Y
    grid, p_grid = np.asarray(man.value("xi_grid")), np.asarray(man.value("p_grid"))
    real_covers_Y = bool(real_lo <= Y[0, 0] and Y[0, 1] <= real_hi)
    # eq. (10): kappa(V) covers Y (kappa is continuous and V an interval, so kappa(V) is an interval).
    k_lo, k_hi = float(y_grid.min()), float(y_grid.max())
    covers = bool(k_lo <= Y[0, 0] and Y[0, 1] <= k_hi)
    if not covers:
        raise DesignError("abstract.domain", f"kappa(V) = [{k_lo:.6g}, {k_hi:.6g}] does not cover Y = {Y[0].tolist()} (eq. (10))",
                          "a larger domain V, or a smaller output_set", check="V_covers_Y")
    dkappa = np.asarray(model.numeric(kap.expr("dkappa_dxi"), list(model.xi))(*grid))[0, 0]
    monotone = bool(np.all(dkappa > 0) or np.all(dkappa < 0))

    symbolic_ii = bool(method.startswith("closed") and sp.simplify(kappa[0].xreplace({xi: m_of_y}) - y) == 0)

    art = Artefact(stage=NAME, meta={"branches": n_branches, "samples": SAMPLES, "sample_seed": 0, "method": method, "construction": KAPPA_INVERSE,
                                      "left_inverse_tol": LEFT_INVERSE_TOL, "condition_ii_rtol": CONDITION_II_RTOL})
    art.exprs.update({"m": m, "m_of_y": sp.Matrix([m_of_y.xreplace({y: sp.Symbol("y", real=True)})]), "dm_dx": sparse_jacobian(m, model.x)})
    if method.startswith("Chebyshev"):
        # The interpolant is a polynomial, real for every y, but it stands for kappa^-1 only on kappa(V), the
        # interval it was fitted on; beyond it, it extrapolates (and kappa^-1 need not exist).
        real_lo, real_hi = k_lo, k_hi
        certified = ([[k_lo, k_hi]], "kappa(V)", "kappa(V): the interval the Chebyshev interpolant of kappa^-1 was fitted on; outside it "
                     "the polynomial extrapolates and kappa^-1 need not exist")
    else:
        dom = [max(k_lo, real_lo), min(k_hi, real_hi)]
        whole = dom == [k_lo, k_hi]
        real_text = "m has no radicands, so it is real for every y" if not radicands else f"m is real for {_format_interval(real_lo, real_hi)}"
        name = "kappa(V)" if whole else "kappa(V) where m is real"
        certified = ([dom], name, f"{name}: {real_text}; outside kappa(V) the value m(x) lies outside V, where nothing is certified")
    art.values.update({
        "V": model.V, "Y": Y, "kappa_range": np.array([[k_lo, k_hi]]), "m_real_interval": np.array([real_lo, real_hi]),
        "radicands": radicands if radicands else ["none"], "left_inverse_residual": left_residual,
        "condition_ii_symbolic": bool(symbolic_ii),
        "min_abs_dkappa": float(np.abs(dkappa).min()),
    })
    art.checks["left_inverse"] = Check(left_residual, left_residual <= LEFT_INVERSE_TOL, f"max |m(p(xi)) - xi| on V (<= {LEFT_INVERSE_TOL:g}): p is injective on V")
    art.checks["kappa_monotone"] = Check(float(np.abs(dkappa).min()), monotone, "min |dkappa/dxi| on V (kappa strictly monotone, so p is injective)")
    art.checks["V_covers_Y"] = Check(float(max(k_lo - Y[0, 0], Y[0, 1] - k_hi)), covers, "eq. (10): kappa(V) contains Y (<= 0)")
    art.checks["m_real_on_Y"] = Check(float(max(real_lo - Y[0, 0], Y[0, 1] - real_hi)), real_covers_Y, "Y inside the output interval where m is real (<= 0)")
    _certify(art, model, *certified)
    _checks_common(art, model, p_function(man, model), m, p_grid)
    prove_scalar_rows(art, model, man, prove_scalar_inverse(model, kappa[0], kap.expr("dkappa_dxi")[0, 0], m_of_y, y, symbolic_ii), (m_of_y, y))
    return art


def summarise(art: Artefact) -> dict:
    """Headline numbers for ``ashc summary``.

    Parameters
    ----------
    art : Artefact
        The inverse stage's artefact.

    Returns
    -------
    dict
        JSON-able: V, m (as text), the residuals, m_real_interval (None for an infinite end), kappa_range, method,
        and, where recorded, construction, condition_ii_pseudo_inverse and m_domain with its set and meaning.
    """
    v = art.values
    out = {
        "V": np.asarray(v["V"]).tolist(), "m": [str(e) for e in art.exprs["m"]],
        "left_inverse_residual": float(v["left_inverse_residual"]), "condition_i": float(v["condition_i"]),
        "condition_ii": float(v["condition_ii"]), "condition_ii_symbolic": bool(v["condition_ii_symbolic"]),
        "m_real_interval": [float(b) if np.isfinite(b) else None for b in np.asarray(v["m_real_interval"])],
        "kappa_range": np.asarray(v["kappa_range"]).tolist(), "method": art.meta.get("method", "closed form (sympy.solve of kappa(m) = y)"),
    }
    if "construction" in art.meta:
        out["construction"] = art.meta["construction"]
    if "condition_ii_pseudo_inverse" in v:
        out["condition_ii_pseudo_inverse"] = float(v["condition_ii_pseudo_inverse"])
    if "m_domain" in v:
        out.update({"m_domain": (np.asarray(v["m_domain"], dtype=float) + 0.0).tolist(), "m_domain_set": art.meta.get("m_domain_set"),
                    "m_domain_meaning": art.meta.get("m_domain")})
    return out


def _real_text(art: Artefact) -> str:
    """Where m is real, in words; infinite ends only where they are proved (see the module docstring)."""
    lo, hi = np.asarray(art.values["m_real_interval"], dtype=float)
    method = str(art.meta.get("method", ""))
    if np.isnan(lo) or np.isnan(hi):
        return "m real and finite on a grid of Y"
    if np.isinf(lo) and np.isinf(hi):
        radicands = [str(r) for r in np.atleast_1d(art.values.get("radicands", ["none"]))]
        why = "linear" if method.startswith("linear") else "no radicands" if radicands in (["none"], []) else "every radicand is non-negative"
        m_of_y = art.exprs.get("m_of_y")
        poles = m_of_y is not None and not all(e.is_polynomial(*e.free_symbols) for e in m_of_y)
        return f"m real for every y{' where it is finite' if poles else ''} ({why})"
    return f"m real for {_format_interval(lo, hi)}"


def headline(art: Artefact) -> str:
    """One progress line.

    Parameters
    ----------
    art : Artefact
        The inverse stage's artefact.

    Returns
    -------
    str
        The residual m(p(xi)) - xi and the set where m is certified (and where m is real, unless m is a Chebyshev interpolant).
    """
    residual = f"m(p(xi)) - xi = {art.values['left_inverse_residual']:.2g}"
    if "m_domain" not in art.values:   # an artefact of an older ashc
        return f"{residual}; where m is certified is not recorded (an artefact of an older ashc: rerun with --force)"
    box, name, _ = certified_set(art)
    if str(art.meta.get("method", "")).startswith(("Chebyshev", "tensor Chebyshev")):
        return f"{residual}, m (Chebyshev interpolant of kappa^-1) certified for y in {name} = {format_box(box)}"
    return f"{residual}, {_real_text(art)}; certified for y in {name} = {format_box(box)}"

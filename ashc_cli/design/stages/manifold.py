"""Stage 2: the invariant manifold x = p(xi), solving the invariance PDE (eq. (14a))

    dp/dxi (xi) phi_bar(xi) = f_bar(p(xi)) + g(p(xi)) l(xi)        for all xi in V.

With phi_bar = 0 (Remark 5) the PDE is the algebraic equation f(p(xi), l(xi)) = 0: p(xi) is the
equilibrium of the concrete system under the constant input l(xi).  It is solved symbolically with the
parameters kept as symbols, so p reads like the paper's eq. (31).  Without a closed form (or above
``model.NUMERIC_THRESHOLD`` states) the equilibria are found by Newton continuation on Chebyshev nodes (sparse
Jacobians, sparse LU) and fitted by a Chebyshev series, which the artefact keeps numeric
(:class:`~ashc_cli.numerics.chebyshev.Series`: the later stages evaluate it with numpy; its formula, Horner's scheme,
is built only for the readers that need one, and the residual check covers both).

With phi_bar != 0 on a linear plant (f_bar(x) = A x + a, g = B constant) and affine phi_bar(xi) = S xi + s,
l(xi) = Q xi + q0, p(xi) = P xi + p0 where P solves the Sylvester equation A P + B Q = P S (Girard & Pappas
2009, Remark 3) and A p0 = P s - a - B q0; it has one solution when A and S share no eigenvalue.

Otherwise (phi_bar != 0, nonlinear plant, one abstract state) p is approximated by Chebyshev polynomials on V,
fitted by collocation (nonlinear least squares on the PDE residual at Chebyshev nodes), raising the degree
until the relative residual on an independent grid is below ``abstract.pde_tolerance`` (Remark 5).  The residual of the PDE is
evaluated on a grid of V and stored, together with the check that l maps V into U (Theorem 4).
"""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import scipy.linalg as sla
import sympy as sp

from ashc_cli.numerics import chebyshev
from ashc_cli.numerics import proofs
from ashc_cli.design import series_proofs
from ashc_cli.design.artefacts import Artefact, Check
from ashc_cli.errors import DesignError, NumericalError
from ashc_cli.problem.grids import domain_grid
from ashc_cli.problem.model import Model, within_budget
from ashc_cli.design.manifold_numeric import ManifoldPlant, equilibrium_error, manifold_field, resonance, solve_collocation, solve_numeric_equilibria

NAME = "manifold"
UPSTREAM: tuple[str, ...] = ()

GRID_POINTS = 2001
#: Largest PDE residual accepted, relative to the size of f_bar(p) + g(p) l along the manifold.
RESIDUAL_RTOL = 1e-9


def _solve_algebraic(model: Model) -> tuple[sp.Matrix, int]:
    """Solve f_bar(p) + g(p) l(xi) = 0 for p (eq. (14a) with phi_bar = 0).

    Returns
    -------
    p : sympy Matrix (n x 1)
        The branch that is real and finite on all of V.
    branches : int
        How many solutions sympy found.

    Raises
    ------
    DesignError
        If no closed-form solution exists, or none is real and finite on V.
    """
    P = sp.Matrix(sp.symbols(f"_p0:{model.n}", real=True))
    equations = manifold_field(model).xreplace(dict(zip(model.x, P)))
    # sympy.solve is given rational systems only: on transcendental ones (tanh, exp, sqrt of the unknowns) it
    # can run for minutes, depending on the hash seed, before giving up; those go to Newton continuation.
    rational = all(sp.sympify(e).is_rational_function(*P) for e in equations)
    try:
        # under a budget: a cubic with a tanh(xi) coefficient kept sympy's gcd busy for minutes
        solutions = within_budget(_solve_all, list(equations), list(P)) if rational else []
    except TimeoutError as exc:
        raise DesignError("abstract.p", f"sympy.solve of eq. (14a) stopped ({exc}), a safety stop (a clock: the numeric "
                          "path is not taken silently, or the design would depend on the machine's load)",
                          "--numeric with abstract.domain given (Newton continuation, no sympy), or abstract.p written by hand (it is checked)") from None
    except (NotImplementedError, ValueError):
        solutions = []
    # With domain: auto, V is not known yet: keep the branch real and finite on most of the search interval.
    grid = domain_grid(model.V if model.V is not None else _auto_search_box(model), 201)
    best, best_score, real = None, 0.0, []
    for sol in solutions:
        if set(sol) != set(P):
            continue  # a family of solutions: p is not determined
        p = sp.Matrix([sp.factor(sp.simplify(sol[s])) for s in P])
        values = model.numeric(p, list(model.xi))(*grid)
        score = float(np.mean(np.all(np.isfinite(values), axis=(0, 1))))
        if score == 1.0 and model.V is not None:
            real.append((p, values))
        if model.V is None and score > best_score:
            best, best_score = p, score
    if real:
        return _in_state_box(model, real, grid), len(solutions)
    if best is not None:
        return best, len(solutions)
    what = ("is not rational in x (sympy not tried)" if not rational
            else f"has no closed-form solution p(xi) real and finite on V ({len(solutions)} found)")
    raise DesignError("abstract.l", f"f_bar(p) + g(p) l(xi) = 0 {what}",
                      "l(xi) giving an isolated equilibrium for every xi in V (or a different V)")


def _in_state_box(model: Model, real: list, grid: np.ndarray) -> sp.Matrix:
    """Of the solutions of eq. (14a) real and finite on V, the first whose p(V) lies in ``concrete.state_box`` (all of
    them qualify without a state box): a levitated ball's p = [-xi, ...] (a negative gap) solves the equations too.

    Raises
    ------
    DesignError
        Naming ``abstract.p`` when every solution leaves the state box (and where the first one does).
    """
    box = model.state_box
    if box is None:
        return real[0][0]
    tol = 1e-9 * np.maximum(1.0, np.abs(box).max(axis=1))
    for p, values in real:
        v = values[:, 0, :]
        if np.all((v >= box[:, :1] - tol[:, None]) & (v <= box[:, 1:] + tol[:, None])):
            return p
    p, values = real[0]
    v = values[:, 0, :]
    out = np.maximum(box[:, :1] - v, v - box[:, 1:])
    i, k = np.unravel_index(int(np.argmax(out)), out.shape)
    at = ", ".join(f"{s} = {c:.4g}" for s, c in zip(model.xi, grid[:, k]))
    raise DesignError("abstract.p", f"eq. (14a) has {len(real)} solution(s) real on V, and none lies in concrete.state_box: "
                      f"p = {list(p)} puts {model.x[i]} = {v[i, k]:.4g} at {at}, outside [{box[i, 0]:g}, {box[i, 1]:g}]",
                      "abstract.p: the solution you mean (it is checked), or a state box (or a V) that holds one")


def _solve_all(equations: list, unknowns: list) -> list[dict]:
    """sympy.solve of the equations for the unknowns, every solution as a dict (:func:`within_budget` runs it)."""
    return sp.solve(equations, unknowns, dict=True)


def _affine_parts(exprs: sp.Matrix, args: sp.Matrix, model: Model) -> tuple[np.ndarray, np.ndarray] | None:
    """(J, c) with exprs = J args + c numerically, or None if exprs is not affine in args."""
    J = exprs.jacobian(args)
    if any(e.free_symbols & set(args) for e in J):
        return None
    c = exprs.xreplace({a: 0 for a in args})
    return np.array(model.substitute(J), dtype=float), np.array(model.substitute(c), dtype=float).reshape(-1)


#: A and S must have eigenvalues at least this far apart for the Sylvester equation to be well posed.
SYLVESTER_SEPARATION = 1e-8


def _solve_sylvester(model: Model) -> sp.Matrix | None:
    """p(xi) = P xi + p0 for a linear plant and affine phi_bar, l (Remark 3), or None.

    Raises
    ------
    DesignError
        If A and S share an eigenvalue (no unique solution) or A is singular where an offset is needed.
    """
    if not model.affine:
        return None
    parts = [_affine_parts(model.f_bar, model.x, model), _affine_parts(model.phi_bar, model.xi, model), _affine_parts(model.l, model.xi, model)]
    if any(part is None for part in parts) or any(e.free_symbols & set(model.x) for e in model.g):
        return None
    (A, a), (S, s0), (Q, q0) = parts
    B = np.array(model.substitute(model.g), dtype=float)
    gap = np.abs(np.linalg.eigvals(A)[:, None] - np.linalg.eigvals(S)[None, :]).min()
    if gap < SYLVESTER_SEPARATION:
        raise DesignError("abstract.phi_bar", f"A and S share an eigenvalue (distance {gap:.3g}): the Sylvester equation A P + B Q = P S has no unique solution",
                          "a phi_bar whose eigenvalues differ from the plant's, or abstract.p: the solution you mean (checked, not trusted)")
    P = sla.solve_sylvester(A, -S, -B @ Q)              # A P - P S = -B Q
    try:
        p0 = np.linalg.solve(A, P @ s0 - a - B @ q0)     # constant part: A p0 + a + B q0 = P s0
    except np.linalg.LinAlgError:
        raise DesignError("concrete.f_bar", "A is singular, so the offset p0 of p(xi) = P xi + p0 is not determined", "an invertible A, or offsets that vanish") from None
    exact = _solve_sylvester_exact(model)
    if exact is not None:
        return exact
    return sp.Matrix(P.tolist()) * model.xi + sp.Matrix(p0.tolist())


#: Coefficients of a fitted polynomial p within this (relative) distance of a simple rational are tried as it.
RECOGNISE_RTOL = 1e-10


def recognise_exact(model: Model, p: sp.Matrix) -> sp.Matrix | None:
    """The fitted polynomial p with each coefficient replaced by the nearest simple rational (sympy's nsimplify,
    RECOGNISE_RTOL), if that p solves eq. (14a) exactly (the residual, in exact rationals, simplifies to 0); else None.

    A collocation that has found an exact polynomial solution (p = [xi, xi^2] of a bilinear cascade) then
    carries it exactly, and the PDE row is proved instead of sampled; a p that is only close is never changed.

    Parameters
    ----------
    model : Model
        The spec's systems (for eq. (14a) and its exact rationals).
    p : sympy Matrix (n, 1)
        The fitted p, with float coefficients, in xi.

    Returns
    -------
    sympy Matrix (n, 1) or None
        p with rational coefficients; None when p has no floats, a coefficient is not near a rational with
        denominator <= 10^6, or the rational p does not solve eq. (14a) exactly.
    """
    floats = set().union(*(e.atoms(sp.Float) for e in p))
    if not floats:
        return None
    swap = {}
    for f in floats:
        value = float(f)
        r = sp.nsimplify(value, rational=True, tolerance=RECOGNISE_RTOL * max(1.0, abs(value)))
        if not isinstance(r, sp.Rational) or r.q > 10**6:
            return None
        swap[f] = r
    candidate = sp.Matrix([sp.expand(e.xreplace(swap)) for e in p])
    return candidate if proofs.symbolic_zero(list(proofs.exact(model, _pde_residual_expr(model, candidate)))) else None


#: The Sylvester equation is solved in exact rationals up to this many unknowns n x n_hat.
EXACT_SYLVESTER_UNKNOWNS = 64


def _solve_sylvester_exact(model: Model) -> sp.Matrix | None:
    """p(xi) = P xi + p0 solving A P + B Q = P S and A p0 + a + B q0 = P s0 in exact rationals (every parameter
    and number the exact rational of its double), or None above EXACT_SYLVESTER_UNKNOWNS unknowns.

    Then p solves eq. (14a) exactly, and sympy proves it (the residual simplifies to 0), as for a closed form.
    """
    if model.n * model.n_hat > EXACT_SYLVESTER_UNKNOWNS:
        return None
    unknowns = sp.symbols(f"_p0:{model.n * (model.n_hat + 1)}")
    Pm = sp.Matrix(model.n, model.n_hat, unknowns[:model.n * model.n_hat])
    p0 = sp.Matrix(unknowns[model.n * model.n_hat:])
    p = Pm * model.xi + p0
    residual = proofs.exact(model, _pde_residual_expr(model, p))
    equations = []
    for r in residual:
        poly = sp.Poly(sp.expand(r), *model.xi)
        equations += poly.coeffs()
    try:
        solution = sp.solve(equations, unknowns, dict=True)
    except (NotImplementedError, ValueError):
        return None
    if len(solution) != 1 or set(solution[0]) != set(unknowns):
        return None
    return p.xreplace(solution[0])



#: ``domain: auto`` grows V while ||dp/dxi|| stays below this many times its largest value on kappa^-1(Y).
AUTO_SLOPE_RATIO = 10.0
AUTO_GRID = 20001


def _auto_search_box(model: Model) -> np.ndarray:
    """Where ``domain: auto`` searches: the interval of xi with l(xi) in U (one abstract state, l affine).

    Raises
    ------
    DesignError
        For several abstract states, or an l that is not affine or does not bound xi.
    """
    if model.n_hat != 1 or model.p != 1:
        raise DesignError("abstract.domain", f"'auto' handles one abstract state and one output (n_hat = {model.n_hat}, p = {model.p})", "a box [[lo, hi], ...] per abstract state")
    xi = model.xi[0]
    lo, hi = -np.inf, np.inf
    for k, (e, (u_lo, u_hi)) in enumerate(zip(model.l, model.U)):
        slope = sp.diff(e, xi)
        if slope.free_symbols & {xi} or model.substitute(slope) == 0:
            raise DesignError("abstract.l", f"'auto' needs each l_i affine and not constant in xi (l[{k}] = {e})", "a box for abstract.domain")
        a, b = float(model.substitute(slope)), float(model.substitute(e.xreplace({xi: 0})))
        ends = sorted(((u_lo - b) / a, (u_hi - b) / a))
        lo, hi = max(lo, ends[0]), min(hi, ends[1])
    if not lo < hi:
        raise DesignError("abstract.l", "no xi has l(xi) in U", "l mapping some interval into U")
    return np.array([[lo, hi]])


def _auto_domain(model: Model, p: sp.Matrix) -> np.ndarray:
    """``abstract.domain: auto`` for one abstract state (p a formula, or a series fitted on the search interval):
    the largest interval V around kappa^-1(Y) on which
    l(xi) is in U, p is finite and C^1, kappa = h o p is strictly monotone (so p is injective and kappa(V)
    covers Y), and the manifold is no steeper than ``AUTO_SLOPE_RATIO`` times its steepest point over
    kappa^-1(Y) (beyond that dbar, hence the error bound, grows without helping the outputs in Y).

    The search runs over the interval where l(xi) is in U (l affine in xi).

    Raises
    ------
    DesignError
        For several abstract states or outputs, an l that does not bound xi, or a Y that kappa does not
        reach monotonically from a point of that interval.
    """
    lo, hi = _auto_search_box(model)[0]
    xi = model.xi[0]
    xs = np.linspace(lo, hi, AUTO_GRID)
    if isinstance(p, (chebyshev.Series, chebyshev.PiecewiseSeries)):
        # A fitted p (no closed form): kappa = h(p) and dkappa/dxi = dh/dx(p) dp/dxi from the series' values.
        P, dP = p(xs)[:, 0, :], p.jacobian()(xs)[:, 0, :]
        k = model.numeric(model.h, list(model.x))(*P)[0, 0]
        dh = np.broadcast_to(model.numeric(model.h.jacobian(model.x), list(model.x))(*P), (1, model.n, len(xs)))[0]
        dk, slope = np.einsum("iN,iN->N", dh, dP), np.linalg.norm(dP, axis=0)
    else:
        kappa = model.h.xreplace(dict(zip(model.x, p)))
        k = model.numeric(kappa, [xi])(xs)[0, 0]
        dk = model.numeric(kappa.diff(xi), [xi])(xs)[0, 0]
        slope = np.linalg.norm(model.numeric(p.diff(xi), [xi])(xs)[:, 0, :], axis=0)
    ok = np.isfinite(k) & np.isfinite(dk) & np.isfinite(slope) & (dk != 0)
    Y = model.Y[0]
    inside = ok & (k >= Y[0]) & (k <= Y[1])
    if not inside.any():
        raise DesignError("abstract.domain", f"'auto': kappa(xi) never enters Y = {Y.tolist()} for xi in [{lo:.6g}, {hi:.6g}] (where l(xi) is in U)",
                          "an output_set that the equilibria reach, or a box for abstract.domain", check="V_covers_Y")
    # The run of admissible points with one sign of dkappa that contains the first point in Y.
    start = int(np.flatnonzero(inside)[0])
    sign = np.sign(dk[start])
    good = ok & (np.sign(dk) == sign)
    left, right = start, start
    while left > 0 and good[left - 1]:
        left -= 1
    while right < len(xs) - 1 and good[right + 1]:
        right += 1
    run_k = k[left:right + 1]
    if not (run_k.min() <= Y[0] and Y[1] <= run_k.max()):
        raise DesignError("abstract.domain", f"'auto': kappa is monotone only on [{xs[left]:.6g}, {xs[right]:.6g}], where it spans [{run_k.min():.6g}, {run_k.max():.6g}], not all of Y = {Y.tolist()}",
                          "a smaller output_set, or a box for abstract.domain", check="V_covers_Y")
    need = (k >= Y[0]) & (k <= Y[1]) & good
    need[:left] = need[right + 1:] = False
    cap = AUTO_SLOPE_RATIO * slope[need].max()
    need_idx = np.flatnonzero(need)
    a_idx, b_idx = need_idx[0], need_idx[-1]
    while a_idx > left and slope[a_idx - 1] <= cap:
        a_idx -= 1
    while b_idx < right and slope[b_idx + 1] <= cap:
        b_idx += 1
    # Stay one grid cell inside an inadmissible neighbour (a pole or a turning point of kappa).
    a_idx += a_idx > 0 and not good[a_idx - 1]
    b_idx -= b_idx < len(xs) - 1 and not good[b_idx + 1]
    return np.array([[xs[a_idx], xs[b_idx]]])


def run(model: Model, upstream: dict[str, Artefact]) -> Artefact:
    """Solve eq. (14a) for p and check it.

    Parameters
    ----------
    model : Model
        The spec's systems.
    upstream : dict of str to Artefact
        Unused (the manifold reads only the spec).

    Returns
    -------
    Artefact
        Expressions p (n x 1) and dp_dxi (n x n_hat); values xi_grid, p_grid, residual.

    Raises
    ------
    DesignError
        If the spec needs the PDE solver (phi_bar != 0; not in this version), no solution exists, or
        l(V) is not inside U.
    NumericalError
        If the residual of the PDE on V is above tolerance.
    """
    plant = ManifoldPlant(model)
    p, series, branches, method, tolerance, found_V = _solve(model, plant)
    V = found_V if found_V is not None else _auto_domain(model, p)
    try:
        on = _on_grid(model, plant, p, series, V, tolerance)
    except NumericalError as exc:
        if model.p_given is None:
            raise
        raise DesignError("abstract.p", f"the given p does not solve eq. (14a) on V: the {exc.what}",
                          f"dp/dxi phi_bar = f_bar(p) + g(p) l(xi) on V, to {tolerance:g} relative; or leave abstract.p out to have p solved for",
                          check="pde_residual") from None
    if model.p_given is not None and not _full_rank(on["dp_grid"]):
        raise DesignError("abstract.p", f"dp/dxi of the given p has rank < n_hat = {model.n_hat} somewhere on V: p is not injective there",
                          "a p with dp/dxi of full rank on V (Theorem 6 needs a left inverse m)", check="pde_residual")
    l_range, excursion, l_proved, grid_excursion, l_inside = _l_in_U(model, V, on["l_grid"])
    art = Artefact(stage=NAME, meta={"method": method, "branches": branches,
                                      "grid_points": int(on["grid"].shape[1]), "residual_rtol": tolerance,
                                      "domain": "auto" if model.V is None else "spec"})
    if series is not None:
        art.set_series("p", series, model.xi)
        art.set_series("dp_dxi", on["dp_series"], model.xi)
        art.values["p_formula_deviation"] = on["deviation"]
    else:
        art.exprs.update({"p": p, "dp_dxi": on["dp"]})
    if isinstance(series, chebyshev.PiecewiseSeries):
        art.checks["p_continuous"] = _continuity_check(series, on["p_grid"], tolerance)
    art.values.update({"V": V, "xi_grid": on["grid"], "p_grid": on["p_grid"], "residual": on["residual"], "residual_scale": on["scale"],
                       "residual_relative": on["relative"], "residual_rows": on["rows"], "residual_row_scales": on["scales"],
                       "l_range": l_range, "p_error": _p_error(model, p, series, method, tolerance, V)})
    points = on["grid"].shape[1]
    if series is None and not p.atoms(sp.Float) and proofs.symbolic_zero(list(proofs.exact(model, _pde_residual_expr(model, p)))):
        art.checks["pde_residual"] = Check(0.0, True, "dp/dxi phi_bar - f_bar(p) - g(p) l simplifies to 0 (sympy): p solves eq. (14a) exactly", proofs.PROVED)
    else:
        which = f" (the Chebyshev series and its formula; they differ by {on['deviation']:.2g})" if series is not None else ""
        art.checks["pde_residual"] = Check(on["residual"], True, f"max over a {points}-point grid of V of |dp/dxi phi_bar - f_bar(p) - g(p) l| (eq. (14a)){which}; "
                                                                    f"{on['relative']:.3g} of the size of its row's terms at the worst row")
        if series is not None:
            _prove_residual(model, series, art)
    if l_proved:
        how = ("l affine: its values at the corners of V, in exact rationals" if proofs.affine_in(model.l, list(model.xi))
               else "the ball-arithmetic enclosure of l(V)")
        art.checks["l_in_U"] = Check(excursion, True, f"largest excursion of l(V) outside U, {how} (<= 0: l maps V into U)", proofs.PROVED)
    else:
        art.checks["l_in_U"] = Check(grid_excursion, l_inside, f"largest excursion of l(V) outside U on a {points}-point grid (<= 0: l maps V into U)")
    return art


def _prove_residual(model: Model, series, art: Artefact) -> None:
    """A fitted p's residual rho of eq. (14a), bounded over V by Chebyshev models (``values/residual_proved``, per row):
    p does not solve eq. (14a) exactly, and the bound stage carries rho as a disturbance (rho_bar, docs/guaranteed.md)."""
    proof = series_proofs.prove_pde_residual(model, series)
    jump = float(series_proofs.jumps(series).max())
    if proof["bounds"] is not None and jump > 0:    # e = p(xi) - x would jump where xi crosses a break: not in the bound
        proof = {"bounds": None, "how": f"not proved: the pieces of p jump by up to {jump:.3g} at their breaks (the bound carries rho, not the jumps)"}
    art.meta["residual_proof"] = proof["how"]
    if proof["bounds"] is None:
        return
    art.values["residual_proved"] = proof["bounds"]
    chk = art.checks["pde_residual"]
    art.checks["pde_residual"] = Check(float(proof["bounds"].max()), chk.passed,
                                       f"{chk.description}; proved: sup over V of |rho_i| <= residual_proved_i, largest {proof['bounds'].max():.3g} "
                                       f"({proof['how']}), carried into the bound as a disturbance", proofs.PROVED)


def _solve(model: Model, plant: ManifoldPlant):
    """(p, series, branches, method, tolerance, V): p by the first method that applies (a closed form, Newton
    continuation with a Chebyshev fit, the Sylvester equation, Chebyshev collocation), its coefficients
    recognised as exact where they are; ``series`` is p kept numeric (then p is that series too); tolerance is
    the residual p must meet (round-off for a closed form, the spec's pde_tolerance for a fit); V is the domain, found
    here for ``domain: auto`` without a closed form (else the spec's, or None for ``auto`` to be found from p)."""
    # A closed form must solve the PDE to round-off; a fitted p to the spec's pde_tolerance.
    tolerance, fitted_tolerance = RESIDUAL_RTOL, max(RESIDUAL_RTOL, model.spec.abstract.pde_tolerance)
    if model.p_given is not None:
        return model.p_given, None, 1, EXPLICIT_P, fitted_tolerance, model.V
    if all(sp.simplify(e) == 0 for e in model.phi_bar):
        p, closed_form_failure = None, "numeric fast path chosen (sympy not tried)"
        if not (model.use_numeric and model.V is not None):
            try:
                p, branches = _solve_algebraic(model)
                method = "closed form (sympy.solve of f(p, l(xi)) = 0)"
            except DesignError as exc:
                # every solution sympy found leaves the state box: Newton would find one of them, or nothing
                if (model.V is None and model.n_hat != 1) or exc.where == "abstract.p":
                    raise
                closed_form_failure = exc.what
        if p is None:
            try:
                if model.V is None:
                    # domain: auto without a closed form: fit p where l(xi) is in U, find V along it, fit p on V.
                    searched, _ = solve_numeric_equilibria(dataclasses.replace(model, V=_auto_search_box(model)), plant)[:2]
                    model = dataclasses.replace(model, V=_auto_domain(model, searched))
                p, degree, fit_residual = solve_numeric_equilibria(model, plant)
            except DesignError as numeric_failure:
                raise DesignError(numeric_failure.where, f"{closed_form_failure}; numerically: {numeric_failure.what}", numeric_failure.expected,
                                  check=numeric_failure.check) from None
            branches, tolerance = 1, fitted_tolerance
            method = f"Newton continuation on Chebyshev nodes + Chebyshev fit, {_fit_text(p, degree)} (relative residual {fit_residual:.2g} on an independent grid)"
    else:
        p, branches = _solve_sylvester(model), 1
        method = "Sylvester equation A P + B Q = P S (scipy.linalg.solve_sylvester)"
        if p is None:
            if model.V is None:
                raise DesignError("abstract.domain", "'auto' needs a p defined independently of V (phi_bar = 0 with a closed form, or a linear plant)",
                                  "a box [[lo, hi], ...] per abstract state for the PDE solver")
            p, degree, fit_residual, work = solve_collocation(model, plant)
            if not _full_rank(p.jacobian().at(domain_grid(model.V, 201))):
                # Several solutions (the abstraction is the plant itself, l = 0: p = 0 and p = xi): start again from
                # xi in the first n_hat states, and keep the injective solution if that reaches one.
                seed = np.zeros((model.n, model.n_hat))
                seed[:model.n_hat] = np.eye(model.n_hat)
                p, degree, fit_residual, more = solve_collocation(model, plant, seed=seed)
                work += more
                if not _full_rank(p.jacobian().at(domain_grid(model.V, 201))):
                    raise DesignError("abstract.p", f"eq. (14a) is solved by a p whose dp/dxi has rank < n_hat = {model.n_hat} on V (from p = 0 and from "
                                      "p = xi in the first states): p is not injective, and no left inverse m exists",
                                      "abstract.p: the manifold you mean, n expressions in the abstract states (checked, not trusted)", check="pde_residual")
            tolerance = fitted_tolerance
            method = (f"Chebyshev collocation, {_fit_text(p, degree)} (relative residual {fit_residual:.2g} on an independent grid; "
                      f"least-squares work {work:.3g} of abstract.pde_work = {model.spec.abstract.pde_work:.3g})")
    found_V = model.V
    series = None
    if isinstance(p, (chebyshev.Series, chebyshev.PiecewiseSeries)):
        if p.kept_numeric:
            series = p
        else:   # a low degree: the expanded, chopped polynomial (an exact solution reads as one) is p
            p = p.to_sympy(list(model.xi))
    if series is None and p.atoms(sp.Float):
        exact_p = recognise_exact(model, p)
        if exact_p is not None:
            p, tolerance = exact_p, RESIDUAL_RTOL
            method += "; its coefficients recognised as rationals that solve eq. (14a) exactly (sympy)"
    return p, series, branches, method, tolerance, found_V


#: Points of V at which a fitted p of equilibria is compared with the equilibria themselves (``values/p_error``).
P_ERROR_POINTS = 201


def _p_error(model: Model, p, series, method: str, tolerance: float, V: np.ndarray) -> np.ndarray:
    """Per state, how far p may be from the exact solution of eq. (14a): 0 for a closed form or an exact p (its
    residual is round-off), the distance to the Newton-solved equilibria on ``P_ERROR_POINTS`` points of V for a
    fit of equilibria, NaN for a collocation (not estimated: the checks that compose p keep their own tolerances)."""
    if not method.startswith(("Newton continuation", "Chebyshev collocation")) or "recognised as rationals" in method:
        return np.zeros(model.n)   # a closed form, the Sylvester solution, an exact p recognised, or the spec's p
    if method.startswith("Newton continuation"):
        fn = series if series is not None else model.numeric(p, list(model.xi))
        return equilibrium_error(model, fn, domain_grid(V, P_ERROR_POINTS))
    return np.full(model.n, np.nan)


def _continuity_check(series: chebyshev.PiecewiseSeries, p_grid: np.ndarray, tolerance: float) -> Check:
    """The pieces of a fitted p must join smoothly: at every break, |jump of p| <= 1e3 tolerance max(1, |p|) and
    |jump of dp/dxi| <= sqrt(tolerance) max(1, |dp/dxi|) (a smooth p fitted to ``tolerance`` meets both by
    orders of magnitude); a DesignError names the break where p has a kink instead."""
    value, slope = series.jumps()
    dp = np.abs(series.jacobian().at(domain_grid(series.box, GRID_POINTS))).max()
    value_rel = value / max(1.0, float(np.abs(p_grid).max()))
    slope_rel = slope / max(1.0, float(dp))
    bad = np.flatnonzero((value_rel > 1e3 * tolerance) | (slope_rel > np.sqrt(tolerance)))
    if bad.size:
        k = int(bad[np.argmax(slope_rel[bad])])
        raise DesignError("abstract.domain", f"p is not smooth at xi = {series.breaks[k + 1]:.6g}: where two pieces of the fit meet, p jumps by {value[k]:.3g} "
                          f"and dp/dxi by {slope[k]:.3g} (p has a kink or a singularity there)", "a domain V that stops short of it, or an l that makes p smooth", check="p_continuous")
    worst = float(max(value_rel.max(), slope_rel.max()))
    return Check(worst, True, f"the {len(series.pieces)} pieces of p join smoothly: the largest jump at a break, of p relative to max(1, |p|) and of dp/dxi relative "
                 f"to max(1, |dp/dxi|) (<= 1e3 x {tolerance:g} and <= sqrt({tolerance:g}))")


EXPLICIT_P = "explicit p from the spec (abstract.p), checked: eq. (14a) and the rank of dp/dxi on a grid of V"
#: dp/dxi has full rank where its smallest singular value is above this, relative to max(1, its largest).
RANK_RTOL = 1e-9


def _full_rank(dp_grid: np.ndarray) -> bool:
    """Whether dp/dxi (n, n_hat, N) has rank n_hat at every point of the grid."""
    sv = np.linalg.svd(np.moveaxis(np.asarray(dp_grid, dtype=float), -1, 0), compute_uv=False)   # (N, n_hat)
    return bool(np.all(sv.min(axis=1) > RANK_RTOL * np.maximum(1.0, sv.max(axis=1))))


def _fit_text(p, degree: int) -> str:
    """How a fitted p is made up: ``degree 17``, or ``6 pieces of degree <= 32 (breaks at ...)``."""
    if isinstance(p, chebyshev.PiecewiseSeries):
        return f"{len(p.pieces)} pieces of degree <= {degree} on V (breaks at {', '.join(f'{b:.6g}' for b in p.breaks[1:-1])})"
    return f"degree {degree}"


def _on_grid(model: Model, plant: ManifoldPlant, p, series, V: np.ndarray, tolerance: float) -> dict:
    """p, dp/dxi, phi_bar and l on a grid of V, and the PDE residual there (the series and its formula both);
    a NumericalError if the residual is above ``tolerance`` relative to the size of its terms."""
    grid = domain_grid(V, GRID_POINTS)
    xi_args = list(model.xi)
    on = {"grid": grid, "deviation": 0.0}
    phi_grid = model.numeric(model.phi_bar, xi_args)(*grid)[:, 0, :]         # (n_hat, N)
    on["l_grid"] = l_grid = model.numeric(model.l, xi_args)(*grid)[:, 0, :]  # (m, N)
    if series is not None:
        # Kept numeric (Chebyshev series, evaluated by numpy): no sympy Jacobian or compiled formula of p.
        on["dp_series"] = dp_series = series.jacobian()
        p_grid, dp_grid = series.at(grid)[:, 0, :], dp_series.at(grid)      # (n, N), (n, n_hat, N)
    else:
        on["dp"] = dp = p.jacobian(model.xi)
        p_grid = model.numeric(p, xi_args)(*grid)[:, 0, :]                   # (n, N)
        dp_grid = model.numeric(dp, xi_args)(*grid)                          # (n, n_hat, N)
    rows, scales = _grid_residual(plant, grid, p_grid, dp_grid, phi_grid, l_grid)
    if series is not None:
        # Readers of the artefact get p's formula (Horner on power coefficients), which differs from the series
        # by the round-off of that conversion: it must solve the PDE too, and the check covers both.
        p_formula = series.formula_at(grid)[:, 0, :]
        on["deviation"] = float(np.abs(p_formula - p_grid).max())
        formula_rows, formula_scales = _grid_residual(plant, grid, p_formula, dp_series.formula_at(grid), phi_grid, l_grid)
        rows, scales = np.maximum(rows, formula_rows), np.maximum(scales, formula_scales)
    # each row against the size of its own terms (a large row must not hide another row's residual)
    relative = rows / scales
    worst = int(np.argmax(np.where(np.isfinite(relative), relative, np.inf)))
    if not np.all(np.isfinite(rows)) or relative[worst] > tolerance:
        raise NumericalError(NAME, f"residual of eq. (14a) on V is {rows[worst]:.3g} in row {worst + 1} (the size of that row's terms {scales[worst]:.3g})"
                             f"{resonance(model, p_grid[:, int(np.argmin(np.abs(grid - np.mean(V, axis=1)[:, None]).sum(axis=0)))])}",
                             f"below {tolerance:g} relative: a smaller abstract.domain, a larger abstract.pde_tolerance, or abstract.p written by hand (checked, not trusted)")
    on.update(p_grid=p_grid, dp_grid=dp_grid, residual=float(rows.max()), scale=float(scales.max()), relative=float(relative[worst]),
              rows=rows, scales=scales)
    return on


def _l_in_U(model: Model, V: np.ndarray, l_grid: np.ndarray):
    """(l_range, excursion, proved, grid_excursion, inside): l(V) inside U, proved (exactly for an affine l, in
    ball arithmetic otherwise) or on the grid; a DesignError if l(V) leaves U."""
    U = model.U
    l_lo, l_hi = l_grid.min(axis=1), l_grid.max(axis=1)
    excursion, l_proved = _prove_l_in_U(model, V)
    # Proved inside, proved outside, or (no proof) inside on the grid with no slack.
    grid_excursion = float(np.max(np.r_[U[:, 0] - l_lo, l_hi - U[:, 1]]))
    decided = l_proved or (np.isfinite(excursion) and proofs.affine_in(model.l, list(model.xi)))
    l_inside = l_proved if decided else grid_excursion <= 0
    if not l_inside:
        by = excursion if decided else grid_excursion
        tiny = " (at the level of rounding: shrink abstract.domain by that much)" if by <= 1e-12 * max(1.0, float(np.abs(U).max())) else ""
        raise DesignError("abstract.l", f"l(V) = {np.c_[l_lo, l_hi].tolist()} is not inside U = {U.tolist()}: it leaves U by {by:.3g}"
                          f"{' (decided exactly)' if decided else ' on a grid of V'}{tiny}",
                          "l: V -> U (Theorem 4); shrink abstract.domain or change l", check="l_in_U")
    return np.c_[l_lo, l_hi], excursion, l_proved, grid_excursion, l_inside


def _grid_residual(plant: ManifoldPlant, grid: np.ndarray, p_grid: np.ndarray, dp_grid: np.ndarray, phi_grid: np.ndarray,
                   l_grid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Row by row: max |dp/dxi phi_bar - f_bar(p) - g(p) l| over a grid, and the size of that row's terms
    max(1, |dp/dxi phi_bar|_i, |f_bar(p)|_i, |g(p) l|_i, the sum of its additive parts); each (n,)."""
    fbar, gl = plant.sides_at(p_grid, l_grid)
    lhs = np.einsum("ijk,jk->ik", dp_grid, phi_grid)
    residual = np.abs(lhs - (fbar + gl)).max(axis=1)
    return residual, np.max(np.abs(np.stack([lhs, fbar, gl, plant.sizes(p_grid, grid)])), axis=(0, 2), initial=1.0)


def _pde_residual_expr(model: Model, p: sp.Matrix) -> sp.Matrix:
    """dp/dxi phi_bar - f_bar(p) - g(p) l(xi), symbolically (eq. (14a) as a residual)."""
    if not model.affine:
        return p.jacobian(model.xi) * model.phi_bar - model.f_on(p, model.l)
    on_p = dict(zip(model.x, p))
    return p.jacobian(model.xi) * model.phi_bar - model.f_bar.xreplace(on_p) - model.g.xreplace(on_p) * model.l


def _prove_l_in_U(model: Model, V: np.ndarray) -> tuple[float, bool]:
    """The largest excursion of l(V) outside U, from proved bounds of each l_i over V; and whether l(V) is inside U.

    An affine l is decided exactly: its extremes are at the corners of V, evaluated in rationals (the spec's
    decimals, :func:`proofs.exact`), so an l that meets the end of U exactly is inside, and one that leaves it by
    2e-16 is outside.  Otherwise each l_i is enclosed by branch and bound in ball arithmetic.
    """
    if proofs.affine_in(model.l, list(model.xi)):
        l_exact = proofs.exact(model, model.l)
        corners = itertools.product(*[(proofs.exact_number(lo), proofs.exact_number(hi)) for lo, hi in V])
        at = [l_exact.xreplace(dict(zip(model.xi, c))) for c in corners]
        excursion = max(max(proofs.exact_number(model.U[i, 0]) - a[i], a[i] - proofs.exact_number(model.U[i, 1])) for a in at for i in range(model.m))
        return float(excursion), bool(excursion <= 0)
    try:
        f = proofs.compile_claims(model, list(model.l), list(model.xi))
    except proofs.interval.UnsupportedExpression:
        return np.inf, False
    excursion = -np.inf
    for i in range(model.m):
        lo, hi, ok = proofs.range_on_box(f, V, index=i)
        if not ok:
            return np.inf, False
        excursion = max(excursion, model.U[i, 0] - lo, hi - model.U[i, 1])
    return float(excursion), bool(excursion <= 0)


def summarise(art: Artefact) -> dict:
    """Headline numbers for ``ashc summary``.

    Parameters
    ----------
    art : Artefact
        The manifold stage's artefact.

    Returns
    -------
    dict
        ``p`` (entries as text), ``residual`` (the PDE residual on the grid of V) and ``method``.
    """
    return {"p": [str(e) for e in art.exprs["p"]], "residual": float(art.values["residual"]), "method": art.meta.get("method")}


def headline(art: Artefact) -> str:
    """One progress line.

    Parameters
    ----------
    art : Artefact
        The manifold stage's artefact.

    Returns
    -------
    str
        The number of branches and the PDE residual.
    """
    return f"p found ({art.meta.get('branches')} branch(es)), PDE residual = {art.values['residual']:.2g}"

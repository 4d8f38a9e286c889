"""The inverse stage's exact decisions: where m is real (its radicands, solved by sympy), and the left inverse m
with conditions (i) and (ii) of Theorem 6 decided exactly (affine p, in rationals) or in ball arithmetic (one or
several abstract states); the stage's checks relabelled as proved where they are."""

from __future__ import annotations

import itertools
from dataclasses import replace

import numpy as np
import sympy as sp

from ashc_cli.design import series_proofs
from ashc_cli.design.artefacts import Artefact
from ashc_cli.design.inverse_construct import CONDITION_II_RTOL, LEFT_INVERSE_TOL
from ashc_cli.errors import DesignError
from ashc_cli.numerics import proofs
from ashc_cli.problem.model import Model, sparse_jacobian


#: Exact (rational) proofs of the affine inverse are attempted up to this many unknowns n_hat x n of K.
EXACT_MAX_UNKNOWNS = 64


def prove_affine_inverse(model: Model, man: Artefact, kap: Artefact, T: np.ndarray, K: np.ndarray, kappa_affine: bool) -> dict:
    """Prove the inverse stage's claims for an affine p(xi) = P xi + p0 in exact rational arithmetic.

    P and p0 are p's stored formula with every parameter and number the exact rational of its double.  Then:

    * p injective: rank P = n_hat (exact);
    * a left inverse K_ex with K_ex P = I and T (I - P K_ex) = 0 exactly, found from the rationals (the
      pseudo-inverse (P^T P)^-1 P^T, or the least-norm solution of both equations): m(x) = K_ex (x - p0) gives
      m(p(xi)) = xi (the left-inverse row, and condition (i): p(m(p(xi))) = p(xi)) and, since h reads x only
      through T x (T = C for a linear h), h(p(m(x))) = h(x) for every x (condition (ii));
    * m is linear, hence real everywhere;
    * eq. (10) for an affine kappa = C P xi + C p0: for one output the exact range of kappa over V's corners
      contains Y; otherwise each vertex of Y is reached from V (an exact linear program, sympy's simplex).

    Parameters
    ----------
    model, man, kap : Model, Artefact, Artefact
        The spec's systems, the manifold artefact (``p``, ``dp_dxi``) and the kappa artefact (not read).
    T, K : ndarray (r, n), (n_hat, n)
        The rows h reads x through (C, or the unit rows of the states h names); the stage's floating-point K.
    kappa_affine : bool
        Whether kappa is affine in xi; only then is eq. (10) decided exactly (when C P and C p0 are constant).

    Returns
    -------
    dict
        ``K`` (the doubles nearest K_ex, or the given K if not proved), booleans ``injective``, ``left_inverse``,
        ``condition_ii``, ``covers`` (None when not decided exactly), ``K_deviation`` (max |K - K_ex| of the
        given K) and ``how``.
    """
    out = {"K": K, "injective": False, "left_inverse": False, "condition_ii": False, "covers": None, "K_deviation": np.nan, "how": "not proved"}
    n, n_hat = model.n, model.n_hat
    if n * n_hat > EXACT_MAX_UNKNOWNS:
        out["how"] = f"not attempted: n_hat x n = {n * n_hat} unknowns (exact rational proofs up to {EXACT_MAX_UNKNOWNS})"
        return out
    p = man.expr("p")
    P = proofs.exact(model, man.expr("dp_dxi"))
    if P.free_symbols & set(model.xi):
        out["how"] = "not proved: dp/dxi is not constant in exact arithmetic"
        return out
    p0 = proofs.exact(model, p.xreplace({s: 0 for s in model.xi}))
    if P.rank() < n_hat:
        out["how"] = "not proved: P has exact rank below n_hat"
        return out
    out["injective"] = True
    Tq = sp.Matrix([[proofs.exact_number(t) for t in row] for row in np.asarray(T, dtype=float)])
    I_n, I_hat = sp.eye(n), sp.eye(n_hat)
    K_ex = (P.T * P).inv() * P.T
    if Tq * (I_n - P * K_ex) != sp.zeros(*Tq.shape):
        # The least-norm solution of K P = I, T P K = T in vec(K) (column-major), exactly.
        unknowns = sp.symbols(f"k0:{n_hat * n}")
        Ks = sp.Matrix(n_hat, n, lambda i, j: unknowns[i + j * n_hat])
        eqs = list(Ks * P - I_hat) + list(Tq * P * Ks - Tq)
        A, b = sp.linear_eq_to_matrix(eqs, unknowns)
        try:
            sol = A.pinv() * b
        except (ValueError, ZeroDivisionError):
            sol = None
        if sol is None or A * sol != b:
            out["how"] = "not proved: no left inverse K of P with T (I - P K) = 0 exists in exact arithmetic"
            return out
        K_ex = Ks.xreplace(dict(zip(unknowns, sol)))
    assert K_ex * P == I_hat
    out.update(left_inverse=True, condition_ii=True)
    K_float = np.array(K_ex.evalf(17).tolist(), dtype=float)
    out["K_deviation"] = float(np.abs(np.asarray(K, dtype=float) - K_float).max())
    out["K"] = K_float
    how = "exact rationals: rank P = n_hat, K_ex P = I and T (I - P K_ex) = 0 with m = K_ex (x - p0) rounded to doubles"
    if kappa_affine:
        Cq = proofs.exact(model, sparse_jacobian(model.h, model.x))
        Kk, k0 = Cq * P, Cq * p0
        if Kk.free_symbols or k0.free_symbols:
            out["how"] = how
            return out
        corners = list(itertools.product(*[(proofs.exact_number(lo), proofs.exact_number(hi)) for lo, hi in model.V]))
        Yq = [(proofs.exact_number(lo), proofs.exact_number(hi)) for lo, hi in model.Y]
        if model.p == 1:
            vals = [(Kk * sp.Matrix(c) + k0)[0] for c in corners]
            out["covers"] = bool(min(vals) <= Yq[0][0] and max(vals) >= Yq[0][1])
            gap = max(min(vals) - Yq[0][0], Yq[0][1] - max(vals))
            out["covers_gap"] = float(gap)
            out["kappa_V_exact"] = [float(min(vals)), float(max(vals))]
        else:
            from sympy.solvers.simplex import InfeasibleLPError, linprog

            covers = True
            # xi = lo + z with 0 <= z <= hi - lo (sympy's simplex keeps its variables non-negative)
            Vq = [(proofs.exact_number(lo), proofs.exact_number(hi)) for lo, hi in model.V]
            lo_vec = sp.Matrix([lo for lo, _ in Vq])
            A_in, b_in = sp.eye(n_hat), sp.Matrix([hi - lo for lo, hi in Vq])
            for vertex in itertools.product(*Yq):
                try:
                    linprog(sp.zeros(1, n_hat), A_in, b_in, Kk, sp.Matrix(vertex) - k0 - Kk * lo_vec)
                except InfeasibleLPError:
                    covers = False
                    break
            out["covers"] = covers
        how += "; eq. (10) decided exactly (" + ("kappa's range at the corners of V" if model.p == 1 else "a rational linear program per vertex of Y") + ")"
    out["how"] = how
    return out


def prove_scalar_inverse(model: Model, kappa: sp.Expr, dkappa: sp.Expr, m_of_y: sp.Expr, y: sp.Symbol, symbolic_ii: bool) -> dict:
    """Prove the inverse stage's claims for one abstract state and one output, in ball arithmetic over V and Y.

    * kappa strictly monotone on V: dkappa/dxi enclosed away from 0 on V (so p is injective on V);
    * eq. (10): kappa(V) = [kappa(a), kappa(b)] (monotone) with the end values enclosed, Y inside;
    * m real and finite on Y: the enclosure of m over Y is finite (a square root of a ball reaching below 0,
      or a division by a ball containing 0, is not);
    * conditions (i) and (ii): kappa(m(y)) = y simplifies to 0 (sympy) wherever m is defined, so
      h(p(m(x))) = kappa(m(h(x))) = h(x) on X_y; and m maps kappa(V) into an interval V' around V on which
      kappa is strictly monotone, so m(kappa(xi)) is the only preimage of kappa(xi) in V', xi itself:
      m(p(xi)) = xi on V.

    Parameters
    ----------
    model : Model
        The spec's systems (V, Y, xi and the parameter values).
    kappa, dkappa : sympy Expr
        kappa(xi) and dkappa/dxi, in the one abstract state.
    m_of_y : sympy Expr
        The branch of m as a function of the output y.
    y : Symbol
        The output symbol of ``m_of_y``.
    symbolic_ii : bool
        Whether kappa(m(y)) - y simplified to 0 (the caller's sympy check); without it neither condition (ii)
        nor the left inverse is claimed.

    Returns
    -------
    dict
        Booleans monotone, covers, real_on_Y, left_inverse, condition_ii; min_abs_dkappa (proved lower
        bound); covers_margin (proved); how (text).
    """
    V, Y = model.V, model.Y
    out = {"monotone": False, "covers": False, "real_on_Y": False, "left_inverse": False, "condition_ii": False, "how": "not proved"}
    try:
        dk = proofs.compile_claims(model, [dkappa], [model.xi[0]])
        k = proofs.compile_claims(model, [kappa], [model.xi[0]])
        mf = proofs.compile_claims(model, [m_of_y], [y])
    except proofs.interval.UnsupportedExpression as exc:
        out["how"] = f"not proved: {exc}"
        return out
    lo, hi, ok = proofs.range_on_box(dk, V)
    sign = 1 if ok and lo > 0 else (-1 if ok and hi < 0 else 0)
    if sign == 0:
        out["how"] = "not proved: the enclosure of dkappa/dxi on V contains 0"
        return out
    out.update(monotone=True, min_abs_dkappa=float(lo if sign > 0 else -hi))
    ka, kb = k([proofs.arb(float(V[0, 0]))])[0], k([proofs.arb(float(V[0, 1]))])[0]
    first, last = (ka, kb) if sign > 0 else (kb, ka)
    kV = np.array([[proofs.lower(first), proofs.upper(last)]])        # contains kappa(V)
    margin = max(proofs.upper(first) - Y[0, 0], Y[0, 1] - proofs.lower(last))
    out.update(covers=bool(margin <= 0), covers_margin=float(margin))
    m_lo, m_hi, m_ok = proofs.range_on_box(mf, Y)
    out["real_on_Y"] = bool(m_ok)
    out["condition_ii"] = bool(symbolic_ii and m_ok)
    if symbolic_ii:
        r_lo, r_hi, r_ok = proofs.range_on_box(mf, kV, rtol=1e-12)
        if r_ok:
            wider = np.array([[min(V[0, 0], r_lo), max(V[0, 1], r_hi)]])
            w_lo, w_hi, w_ok = proofs.range_on_box(dk, wider)
            out["left_inverse"] = bool(w_ok and (w_lo > 0 if sign > 0 else w_hi < 0))
    out["how"] = ("ball arithmetic: dkappa/dxi " + ("> 0" if sign > 0 else "< 0") + " on V, kappa at the ends of V, m enclosed over Y"
                  + ("; kappa(m(y)) = y symbolically and m(kappa(V)) inside an interval where kappa is monotone" if out["left_inverse"] else ""))
    return out


def prove_multi_inverse(model: Model, kappa: sp.Matrix, m_of_y: sp.Matrix, ys: list[sp.Symbol]) -> dict:
    """Prove the inverse stage's claims for several abstract states and as many outputs (m = kappa^-1 in closed form).

    * m real and finite on Y: each component's ball-arithmetic enclosure over the box Y is finite;
    * eq. (10): those enclosures lie inside V, and kappa(m(y)) - y simplifies to 0 (sympy): every y in Y is
      kappa(m(y)) with m(y) in V;
    * condition (ii): h(p(m(x))) = kappa(m(h(x))) = h(x) for h(x) in Y, by the same identity;
    * p injective on V with m as left inverse (and condition (i)): m(kappa(xi)) - xi simplifies to 0 and
      m(kappa(xi)) is enclosed finite over V (so the identity holds at every xi of V).

    Parameters
    ----------
    model : Model
        The spec's systems (V, Y, xi and the parameter values).
    kappa : sympy Matrix (p, 1)
        kappa(xi).
    m_of_y : sympy Matrix (n_hat, 1)
        m = kappa^-1 in the outputs ``ys``.
    ys : list of Symbol
        The p output symbols.

    Returns
    -------
    dict
        Booleans covers, real_on_Y, left_inverse, condition_ii; covers_margin (proved); how (text).
    """
    V, Y = model.V, model.Y
    out = {"monotone": False, "covers": False, "real_on_Y": False, "left_inverse": False, "condition_ii": False, "how": "not proved"}
    try:
        mf = proofs.compile_claims(model, list(m_of_y), ys)
        composed = [e.xreplace(dict(zip(ys, kappa))) for e in m_of_y]
        mk = proofs.compile_claims(model, composed, list(model.xi))
    except proofs.interval.UnsupportedExpression as exc:
        out["how"] = f"not proved: {exc}"
        return out
    margin, finite = -np.inf, True
    for i in range(model.n_hat):
        lo, hi, ok = proofs.range_on_box(mf, Y, index=i)
        finite = finite and ok
        margin = max(margin, V[i, 0] - lo, hi - V[i, 1]) if ok else np.inf
    if not finite:
        out["how"] = "not proved: the enclosure of m over Y is not finite"
        return out
    right = proofs.symbolic_zero(list(proofs.exact(model, kappa.xreplace(dict(zip(model.xi, m_of_y))) - sp.Matrix(ys))))
    left = proofs.symbolic_zero(list(proofs.exact(model, sp.Matrix(composed) - model.xi)))
    left_finite = all(proofs.range_on_box(mk, V, index=i)[2] for i in range(model.n_hat)) if left else False
    out.update(real_on_Y=True, covers=bool(right and margin <= 0), covers_margin=float(margin), condition_ii=bool(right),
               left_inverse=bool(left and left_finite))
    out["how"] = ("ball arithmetic: m enclosed finite over Y" + (f" and inside V (margin {margin:.3g})" if margin <= 0 else "")
                  + ("; kappa(m(y)) = y symbolically" if right else "") + ("; m(kappa(xi)) = xi symbolically, defined on all of V" if out["left_inverse"] else ""))
    return out


def mark_proved(art: Artefact, proof: dict) -> None:
    """Re-label the checks the proof covers as "proved" (their descriptions say how).

    Parameters
    ----------
    art : Artefact
        The inverse stage's artefact; its checks are replaced in place.
    proof : dict
        The result of :func:`prove_scalar_inverse` or :func:`prove_multi_inverse`; ``min_abs_dkappa`` and
        ``covers_margin``, where present, become the values of ``kappa_monotone`` and ``V_covers_Y``.
    """
    how = proof["how"]
    values = {"kappa_monotone": proof.get("min_abs_dkappa"), "V_covers_Y": proof.get("covers_margin")}
    relabel = {"kappa_monotone": proof["monotone"], "V_covers_Y": proof["covers"], "m_real_on_Y": proof["real_on_Y"],
               "left_inverse": proof["left_inverse"], "condition_i": proof["left_inverse"], "condition_ii": proof["condition_ii"]}
    for name, proved in relabel.items():
        if proved:
            relabel_proved(art, name, how, values.get(name))


def prove_scalar_rows(art: Artefact, model: Model, man: Artefact, proof: dict, m: tuple) -> None:
    """Mark the scalar path's rows proved: by :func:`prove_scalar_inverse` (``proof``), and for a fitted p (a Chebyshev
    series) by Chebyshev models (:func:`ashc_cli.design.series_proofs.prove_fitted_inverse`): the left inverse, kappa's
    monotonicity, condition (i) and, where eq. (10) is proved, condition (ii), each with its proved value (relative
    as the check measures it) when that is within the check's tolerance.

    Parameters
    ----------
    art : Artefact
        The inverse stage's artefact (checks left_inverse, kappa_monotone, condition_i, condition_ii), changed in place.
    model, man : Model, Artefact
        The spec's systems and the manifold's artefact (series ``p`` when p was fitted; ``p_grid``).
    proof : dict
        :func:`prove_scalar_inverse`'s result.
    m : (sympy Expr, Symbol)
        m's formula in the output and that output's symbol.
    """
    art.meta["proof"] = proof["how"]
    mark_proved(art, proof)
    series = man.series.get("p")
    if series is None or art.checks["left_inverse"].evidence == proofs.PROVED:
        return
    fitted = series_proofs.prove_fitted_inverse(model, series, m[0], m[1], LEFT_INVERSE_TOL)
    art.meta["proof_fitted_p"] = fitted["how"]
    if fitted["left"] is None or fitted["left"] > LEFT_INVERSE_TOL:
        return
    how = fitted["how"]
    relabel_proved(art, "left_inverse", how, fitted["left"])
    relabel_proved(art, "kappa_monotone", how, fitted["min_abs_dkappa"])
    cond_i = fitted["condition_i"] / max(1.0, float(np.abs(np.asarray(man.value("p_grid"))).max()))
    if cond_i <= LEFT_INVERSE_TOL and art.checks["condition_i"].evidence != proofs.PROVED:
        relabel_proved(art, "condition_i", how, cond_i)
    covers = art.checks.get("V_covers_Y")
    if fitted["condition_ii"] is not None and covers is not None and covers.evidence == proofs.PROVED:
        cond_ii = fitted["condition_ii"] / max(1.0, float(np.ptp(model.Y, axis=1).max()))
        if cond_ii <= CONDITION_II_RTOL and art.checks["condition_ii"].evidence != proofs.PROVED:
            relabel_proved(art, "condition_ii", how + "; every y of Y is kappa(xi) for a xi of V (eq. (10), proved)", cond_ii)


def relabel_proved(art: Artefact, name: str, how: str, value: float | None = None) -> None:
    """Mark a passed check as proved, saying how (and with the proved number, when the proof gives one).

    Parameters
    ----------
    art : Artefact
        The artefact holding the check; changed in place (nothing happens if the check is absent or failed).
    name : str
        The check's name.
    how : str
        How it was proved, appended to the description.
    value : float, optional
        The proved number, replacing the check's value; None keeps the value.
    """
    chk = art.checks.get(name)
    if chk is not None and chk.passed:
        art.checks[name] = replace(chk, value=chk.value if value is None else value, description=f"{chk.description}; proved ({how})",
                                   evidence=proofs.PROVED)


def real_interval(m_of_y: sp.Expr, y: sp.Symbol, model: Model) -> tuple[float, float, list[str]]:
    """The interval of y on which every square-root argument of m(y) is non-negative.

    Parameters
    ----------
    m_of_y : sympy Expr
        m as a function of the output y.
    y : Symbol
        The output symbol.
    model : Model
        For the parameter values substituted into each radicand.

    Returns
    -------
    lo, hi : float
        The interval (-inf / inf where unbounded).
    radicands : list of str
        The radicands, as formulas in y.
    """
    lo, hi, texts = -np.inf, np.inf, []
    for power in sorted(m_of_y.atoms(sp.Pow), key=sp.default_sort_key):   # a set: its order follows str hashing
        if power.exp.is_Rational and power.exp.q % 2 == 0:
            radicand = power.base
            texts.append(str(radicand))
            numeric = model.substitute(radicand)
            region = sp.solve_univariate_inequality(numeric >= 0, y, relational=False)
            hull = sp.Interval(region.inf, region.sup)
            if region != hull:
                raise DesignError("abstract", f"m is real on a union of intervals {region}", "a left inverse real on one interval of outputs")
            lo, hi = max(lo, float(region.inf)), min(hi, float(region.sup))
    return lo, hi, texts

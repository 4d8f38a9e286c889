"""Proofs about a fitted p (a Chebyshev series in one abstract state) by Chebyshev models: the PDE residual of eq. (14a)
bounded over V, so that the bound stage can carry it as a disturbance (docs/guaranteed.md, "A fitted p").

A fitted p solves eq. (14a) only up to its residual rho(xi) = dp/dxi phi_bar(xi) - f_bar(p(xi)) - g(p(xi)) l(xi).
Sampled on a grid, rho is ~1e-9 of its terms; an interval evaluation over V sees the terms' whole range, 1e3 times
larger than rho.  Chebyshev models (:mod:`ashc_cli.numerics.chebmodel`) compute rho's coefficients, so the
cancellation happens on the coefficients and the bound is rho's own size plus round-off.
"""

from __future__ import annotations

import numpy as np
import sympy as sp
from flint import arb, ctx

from ashc_cli.numerics import chebyshev
from ashc_cli.numerics.chebmodel import ChebModel, TooWide, bound_on_pieces, evaluate, reexpand
from ashc_cli.errors import UnsupportedExpression
from ashc_cli.problem.model import Model

__all__ = ["prove_pde_residual", "residual_norm_bound", "prove_fitted_inverse", "jumps"]


def _pieces(series) -> list:
    return list(series.pieces) if isinstance(series, chebyshev.PiecewiseSeries) else [series]


def _derivative(coeffs: np.ndarray, lo: float, hi: float) -> tuple[np.ndarray, np.ndarray]:
    """d/dxi of the series sum_k c_k T_k(s), s = (2 xi - lo - hi) / (hi - lo): coefficients in s (midpoints) and a
    proved remainder per row (arb, 128 bits: the recurrence d_(k-1) = d_(k+1) + 2 k c_k, times 2 / (hi - lo))."""
    rows, K = coeffs.shape
    mid, rad = np.zeros((rows, K)), np.zeros(rows)
    prec = ctx.prec
    try:
        ctx.prec = 128
        scale = 2 / (arb(hi) - arb(lo))
        for i in range(rows):
            d = [arb(0)] * (K + 1)
            for k in range(K - 1, 0, -1):
                d[k - 1] = d[k + 1] + 2 * k * arb(coeffs[i, k])
            d[0] = d[0] / 2
            for k in range(K):
                v = d[k] * scale
                mid[i, k] = float(v.mid())
                rad[i] += float(abs(v - mid[i, k]).upper()) * (1.0 + 2.0**-50) + 1e-300
    finally:
        ctx.prec = prec
    return mid, rad


def _field(model: Model) -> list:
    """F_i(x, xi) = f_bar_i(x) + g_i(x) l(xi) (or f_i(x, l(xi)) for a plant that is not input-affine): eq. (14a)'s right side."""
    F = model.f_bar + model.g * model.l if model.affine else model.f_on(model.x, model.l)
    return [sp.sympify(e) for e in F]


def prove_pde_residual(model: Model, series) -> dict:
    """Proved bounds of |rho_i(xi)| over V for a fitted p of one abstract state (eq. (14a) as a residual).

    Parameters
    ----------
    model : Model
        The spec's systems (f_bar, g, l or f, phi_bar; ``model.values`` as the parameters' doubles).
    series : chebyshev.Series or chebyshev.PiecewiseSeries
        p, a column of n series on V (one piece or several).

    Returns
    -------
    dict
        ``bounds`` (n,) with sup over V of |rho_i| <= bounds[i], or None where no proof is found; ``pieces`` (the
        sub-intervals the models needed); ``how`` (text: how, or why not).
    """
    if model.n_hat != 1:
        return {"bounds": None, "pieces": 0, "how": f"not proved: Chebyshev models in one abstract state (n_hat = {model.n_hat})"}
    xi = model.xi[0]
    phi = sp.sympify(model.phi_bar[0])
    moving = phi != 0
    F = _field(model)
    bounds, pieces = np.zeros(model.n), 0
    try:
        for piece in _pieces(series):
            lo, hi = (float(v) for v in piece.box[0])
            coeffs = piece.coeffs.reshape(model.n, -1)
            dmid, drad = _derivative(coeffs, lo, hi) if moving else (None, None)

            def build(centre: float, half: float, coeffs=coeffs, lo=lo, hi=hi, dmid=dmid, drad=drad) -> list[ChebModel]:
                env = {**_row_models(coeffs, centre, half, model.x), xi: _xi_model(lo, hi, centre, half)}
                memo: dict = {}
                out = [-evaluate(e, env, model.values, memo) for e in F]
                if moving:
                    phi_m = evaluate(phi, env, model.values, memo)
                    dc, dr = reexpand(dmid, centre, half)
                    out = [o + ChebModel(dci, dri + dradi) * phi_m for o, dci, dri, dradi in zip(out, dc, dr, drad)]
                return out

            here, used = bound_on_pieces(build)
            bounds, pieces = np.maximum(bounds, here), pieces + used
    except TooWide as exc:
        return {"bounds": None, "pieces": pieces, "how": f"not proved: {exc} on 64 sub-intervals of V"}
    except UnsupportedExpression as exc:
        return {"bounds": None, "pieces": pieces, "how": f"not proved: {exc}"}
    return {"bounds": bounds, "pieces": pieces,
            "how": f"Chebyshev models of rho on {pieces} sub-interval(s) of V (coefficients and proved remainders; |T_k| <= 1)"}


def _ends(ball: arb) -> tuple[arb, arb]:
    return arb(ball.lower()), arb(ball.upper())


def residual_norm_bound(M: np.ndarray, bounds: np.ndarray) -> float:
    """rho_bar >= sup over V of |L^T rho| = sqrt(rho^T M rho), from |rho_i| <= bounds_i: sqrt(b^T |M| b), rounded up.

    Parameters
    ----------
    M : ndarray (n, n)
        The matrix of W (M = L L^T).
    bounds : ndarray (n,)
        Proved bounds of |rho_i| over V.

    Returns
    -------
    float
    """
    b = np.asarray(bounds, dtype=float)
    q = float(b @ np.abs(np.asarray(M, dtype=float)) @ b) * (1.0 + 4.0 * (len(b) + 2) * 2.0**-53) + 1e-300
    return float(np.nextafter(np.sqrt(q), np.inf))


def _row_models(coeffs: np.ndarray, centre: float, half: float, symbols) -> dict:
    c, r = reexpand(coeffs, centre, half)
    return {s: ChebModel(ci, ri) for s, ci, ri in zip(symbols, c, r)}


def _xi_model(lo: float, hi: float, centre: float, half: float) -> ChebModel:
    """xi = m + w (centre + half tau) on a piece of [lo, hi] (m, w its midpoint and half width, enclosed in arb)."""
    m, w = (arb(lo) + arb(hi)) / 2, (arb(hi) - arb(lo)) / 2
    return ChebModel.interval(*_ends(m + w * centre)) + ChebModel.interval(*_ends(w * half)) * ChebModel.affine(0.0, 1.0)


def jumps(series) -> np.ndarray:
    """Proved bounds of the jumps of each p_i where the pieces of a piecewise p meet (sum c_k at the right end of one
    piece, sum (-1)^k c_k at the left end of the next, in arb); zeros for one piece.

    Parameters
    ----------
    series : chebyshev.Series or chebyshev.PiecewiseSeries

    Returns
    -------
    ndarray (rows,)
    """
    pieces = _pieces(series)
    out = np.zeros(pieces[0].coeffs.shape[0])
    for left, right in zip(pieces[:-1], pieces[1:]):
        a, b = left.coeffs.reshape(len(out), -1), right.coeffs.reshape(len(out), -1)
        for i in range(len(out)):
            at_end = sum((arb(float(v)) for v in a[i]), arb(0))
            at_start = sum((arb(float(v)) * (-1) ** k for k, v in enumerate(b[i])), arb(0))
            out[i] = max(out[i], float(abs(at_end - at_start).upper()) * (1.0 + 2.0**-50))
    return out


def prove_fitted_inverse(model: Model, series, m_of_y: sp.Expr, y: sp.Symbol, tolerance: float) -> dict:
    """The inverse rows of a fitted m (a Chebyshev interpolant of kappa^-1, one abstract state and one output) proved
    with Chebyshev models over V.

    * kappa strictly monotone on V: the models of dkappa/dxi = sum_j dh/dx_j(p) dp_j/dxi keep one sign, so p is
      injective on V;
    * the left inverse: sup over V of |m(kappa(xi)) - xi| <= delta (m's formula composed with kappa's models; a
      Piecewise m is decided on each piece's range, or hulled where a piece straddles a break);
    * condition (i): |p(m(p(xi))) - p(xi)| <= L_p delta + (the jumps of a piecewise p), L_p a proved bound of |dp/dxi|
      on V widened by delta (p's series restricted to the wider interval);
    * condition (ii): every y in Y is kappa(xi) for some xi in V (eq. (10), proved by the inverse stage), so
      |kappa(m(y)) - y| = |kappa(xi + e) - kappa(xi)| <= L_kappa delta (+ C times the jumps for a linear h).

    Parameters
    ----------
    model : Model
        The spec's systems (h, V, the parameters).
    series : chebyshev.Series or chebyshev.PiecewiseSeries
        p.
    m_of_y : sympy Expr
        m's formula in the output y (the interpolant as the artefact stores it).
    y : Symbol
        Its output symbol.
    tolerance : float
        The left inverse's tolerance: a piece whose bound is above a quarter of it is halved (at most 2^10 pieces).

    Returns
    -------
    dict
        ``left`` (delta), ``condition_i`` and ``condition_ii`` (absolute bounds; None where not proved),
        ``min_abs_dkappa`` (proved), ``pieces``, ``how``.
    """
    out = {"left": None, "condition_i": None, "condition_ii": None, "min_abs_dkappa": None, "pieces": 0, "how": "not proved"}
    if model.n_hat != 1 or model.p != 1:
        out["how"] = "not proved: Chebyshev models for one abstract state and one output"
        return out
    xi, h = model.xi[0], sp.sympify(model.h[0])
    reads = [k for k, s in enumerate(model.x) if s in h.free_symbols]
    dsyms = [sp.Dummy(f"d{k}") for k in reads]
    g_expr = m_of_y.xreplace({y: h}) - xi
    dk_expr = sum((sp.diff(h, model.x[k]) * d for k, d in zip(reads, dsyms)), sp.Integer(0))
    xs = [model.x[k] for k in reads]
    left, signs, lows, pieces = 0.0, set(), [], 0
    lip_p, lip_k = 0.0, 0.0
    try:
        for piece in _pieces(series):
            lo, hi = (float(v) for v in piece.box[0])
            coeffs = piece.coeffs.reshape(model.n, -1)
            mine = coeffs[reads]
            dmid, drad = _derivative(mine, lo, hi)

            def build(centre: float, half: float, mine=mine, dmid=dmid, drad=drad, lo=lo, hi=hi) -> list:
                env = {**_row_models(mine, centre, half, xs), xi: _xi_model(lo, hi, centre, half)}
                dc, dr = reexpand(dmid, centre, half)
                env.update({d: ChebModel(c, r + rr) for d, c, r, rr in zip(dsyms, dc, dr, drad)})
                memo: dict = {}
                g = evaluate(g_expr, env, model.values, memo)
                if g.bound() > tolerance / 4 and half > 2.0**-10:
                    raise TooWide(xi, f"|m(kappa(xi)) - xi| bounded by {g.bound():.3g} on a piece: halve it")
                dk_lo, dk_hi = evaluate(dk_expr, env, model.values, memo).range()
                if dk_lo <= 0 <= dk_hi and half > 2.0**-10:
                    raise TooWide(xi, "the range of dkappa/dxi on a piece holds 0: halve it")
                signs.add(1 if dk_lo > 0 else (-1 if dk_hi < 0 else 0))
                lows.append(dk_lo if dk_lo > 0 else -dk_hi)
                return [g]

            here, used = bound_on_pieces(build, max_depth=10)
            left, pieces = max(left, float(here[0])), pieces + used
        eps = max(2.0 ** int(np.ceil(np.log2(max(left, 1e-300) * 2.0 / min(float(np.diff(s.box[0])[0]) for s in _pieces(series))))), 2.0**-40)
        for piece in _pieces(series):
            lo, hi = (float(v) for v in piece.box[0])
            coeffs = piece.coeffs.reshape(model.n, -1)
            dmid, drad = _derivative(coeffs, lo, hi)
            dc, dr = reexpand(dmid, 0.0, 1.0 + eps)             # dp/dxi on the piece widened by delta (and more)
            bounds = [ChebModel(c, r + rr).bound() for c, r, rr in zip(dc, dr, drad)]
            lip_p = max(lip_p, max(bounds))
            env = {**_row_models(coeffs[reads], 0.0, 1.0 + eps, xs)}
            env.update({d: ChebModel(c, r + rr) for d, c, r, rr in zip(dsyms, dc[reads], dr[reads], drad[reads])})
            lip_k = max(lip_k, evaluate(dk_expr, env, model.values).bound())
    except TooWide as exc:
        out["how"] = f"not proved: {exc}"
        return out
    except UnsupportedExpression as exc:
        out["how"] = f"not proved: {exc}"
        return out
    if signs - {1} and signs - {-1}:
        out["how"] = "not proved: the models of dkappa/dxi do not keep one sign on V"
        return out
    jumps_p = jumps(series)
    jump_k = float((np.abs(np.asarray(model.C, dtype=float)) @ jumps_p).max()) if model.C is not None else (0.0 if not jumps_p.any() else np.inf)
    out.update(left=left, min_abs_dkappa=float(min(lows)), pieces=pieces,
               condition_i=float(np.nextafter(lip_p * left * (1 + 1e-12) + jumps_p.max(), np.inf)),
               condition_ii=float(np.nextafter(lip_k * left * (1 + 1e-12) + jump_k, np.inf)) if np.isfinite(jump_k) else None,
               how=f"Chebyshev models of m(kappa(xi)) - xi and dkappa/dxi on {pieces} sub-interval(s) of V; (i) and (ii) through "
                   f"the Lipschitz bounds {lip_p:.3g} of p and {lip_k:.3g} of kappa on V widened by delta")
    return out

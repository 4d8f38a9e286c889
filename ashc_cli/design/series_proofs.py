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

__all__ = ["prove_pde_residual", "residual_norm_bound"]


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
                c, r = reexpand(coeffs, centre, half)
                env = {x: ChebModel(ci, ri) for x, ci, ri in zip(model.x, c, r)}
                # xi = m + w (centre + half tau), m and w the midpoint and half width of the piece, enclosed in arb
                m, w = (arb(lo) + arb(hi)) / 2, (arb(hi) - arb(lo)) / 2
                env[xi] = ChebModel.interval(*_ends(m + w * centre)) + ChebModel.interval(*_ends(w * half)) * ChebModel.affine(0.0, 1.0)
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

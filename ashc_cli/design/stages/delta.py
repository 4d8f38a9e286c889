"""Stage 5: the abstract input matrix delta and the m-relation link v = b(x) + c(x) u (Theorem 5).

delta comes from the spec (``identity`` or expressions in xi; eq. (39) for the converter), or is designed
by ``flatten``: delta(xi) = c R(xi)^-1 with R the Cholesky factor of dp/dxi^T M dp/dxi (for one abstract state
c / ||sqrt(M) dp/dxi(xi)||), c the smallest singular value of sqrt(M) dp/dxi on V, so ||theta(xi, .)|| with
q = 0 equals c on all of V.  Any delta with max ||delta||_2 = 1 on V has dbar >= c, so flatten gives the least
dbar for that scale (ERRATA item 11: delta only rescales v).  Theorem 5 needs delta of full row rank on V; the stage measures its smallest singular value there.  Then

    b(x) = delta^+(m(x)) (dm/dx f_bar(x) - phi_bar(m(x))),    c(x) = delta^+(m(x)) dm/dx g(x)

solve eqs. (21a), (21b), which the stage re-checks numerically on samples of X_y.  For a plant x' = f(x, u) that is
not input-affine, b(x, u) = delta^+(m(x)) (dm/dx f(x, u) - phi_bar(m(x))) and c = 0: v = b(x, u) solves eq. (20) of
Definition 2 for every u (delta has full row rank), the m-relation without Theorem 5.
For the converter b is eq. (40) (with chi read as a square root, ERRATA item 3) and c = 0.
"""

from __future__ import annotations

import numpy as np
import scipy.optimize as sopt
import sympy as sp

from ashc_cli.numerics import proofs
from ashc_cli.design.artefacts import Artefact, Check
from ashc_cli.errors import DesignError, NumericalError
from ashc_cli.problem.grids import sample_states_with_output
from ashc_cli.problem.model import Model, tidy
from ashc_cli.design.upstream import dp_function, sample_box
from ashc_cli.numerics.linalg import sqrt_M_times

NAME = "delta"
UPSTREAM = ("stabilise", "manifold", "inverse")

#: delta counts as full row rank where its smallest singular value exceeds this times max(1, largest).
RANK_RTOL = 1e-10
#: The residual of eqs. (21a), (21b) must be below this, relative to dm/dx f_bar.
LINK_RTOL = 1e-9
SAMPLES = 2000


def _right_inverse(delta: sp.Matrix) -> sp.Matrix:
    """delta^+ for a full-row-rank delta: the inverse if square, else delta^T (delta delta^T)^-1."""
    if delta.shape == (1, 1):
        return sp.Matrix([[1 / delta[0, 0]]])
    if delta.is_square:
        return delta.inv()
    return delta.T * (delta * delta.T).inv()


def _singular_values(delta_grid: np.ndarray) -> np.ndarray:
    """Singular values of delta at each grid point; delta_grid has shape (n_hat, m_hat, N)."""
    return np.linalg.svd(np.moveaxis(delta_grid, -1, 0), compute_uv=False)


def _smallest_singular_value(model: Model, delta: sp.Matrix, grid: np.ndarray, delta_grid: np.ndarray) -> tuple[float, float, np.ndarray]:
    """The smallest singular value of delta over V, where it is reached, and the largest.

    A grid alone can step over an isolated zero (delta = xi - 0.5 on a grid missing 0.5), so for a square
    delta a sign change of det(delta) between neighbouring grid points counts as a zero, and for a scalar
    abstraction the grid minimum is refined by a bounded search in its neighbouring cells.
    """
    sv = _singular_values(delta_grid)
    smin_each, smax = sv.min(axis=1), float(np.nanmax(sv))
    k = int(np.nanargmin(smin_each))
    smin, at = float(smin_each[k]), grid[:, k]
    if model.n_hat == 1:
        xs = grid[0]
        f = model.numeric(delta, list(model.xi))
        if delta.is_square:
            det = np.linalg.det(np.moveaxis(delta_grid, -1, 0))
            flips = np.flatnonzero(np.sign(det[:-1]) * np.sign(det[1:]) < 0)
            if flips.size:
                j = flips[0]
                root = sopt.brentq(lambda s: np.linalg.det(f(s)), xs[j], xs[j + 1], xtol=1e-14)
                return 0.0, smax, np.array([root])
        lo, hi = xs[max(k - 1, 0)], xs[min(k + 1, len(xs) - 1)]
        if hi > lo:
            res = sopt.minimize_scalar(lambda s: _singular_values(f(np.array([s]))).min(), bounds=(lo, hi), method="bounded", options={"xatol": 1e-14})
            if res.success and res.fun < smin:
                smin, at = float(res.fun), np.array([float(res.x)])
    return smin, smax, np.asarray(at, dtype=float)


def flatten(model: Model, stab: Artefact, man: Artefact, grid: np.ndarray) -> sp.Matrix:
    """delta for ``abstract.delta: flatten``: ||theta(xi, .)|| with q = 0 is the same at every xi of V.

    With J(xi) = sqrt(M) dp/dxi (n x n_hat, full column rank) and the Cholesky factor R of its Gram matrix
    G = dp/dxi^T M dp/dxi = R^T R (R upper triangular), delta = c R^-1 gives J delta = c Q with Q^T Q = I, so
    every singular value of theta = J delta equals c (one abstract state: delta = c / ||sqrt(M) dp/dxi||).
    c = min over V of sigma_min(J) scales delta so that max over V of ||delta||_2 = 1.  That is the least dbar
    at this scale: any delta with max over V of ||delta||_2 = 1 reaches ||delta(xi*) w|| = 1 for a unit w at
    some xi*, where ||theta(xi*)|| >= ||J(xi*) delta(xi*) w|| >= sigma_min(J(xi*)) >= c (ERRATA item 11:
    delta only rescales v).

    Parameters
    ----------
    model : Model
        The spec's systems (needs m_hat = n_hat).
    stab : Artefact
        The stabilise artefact (``M`` is read).
    man : Artefact
        The manifold artefact (``dp_dxi``, as formula and for numpy).
    grid : ndarray (n_hat, N)
        The points of V on which c is taken (the manifold's ``xi_grid``).

    Returns
    -------
    sympy Matrix (n_hat, n_hat)
        delta(xi).
    """
    if model.m_hat != model.n_hat:
        raise DesignError("abstract.delta", f"'flatten' designs a square delta: it needs as many abstract inputs as states (n_hat = {model.n_hat}, m_hat = {model.m_hat})",
                          "identity or an n_hat x m_hat matrix of expressions")
    M = np.asarray(stab.value("M"), dtype=float)
    L = np.linalg.cholesky(M)
    dp = man.expr("dp_dxi")
    dp_grid = np.broadcast_to(dp_function(man, model)(*grid), dp.shape + (grid.shape[1],))
    J = sqrt_M_times(L, np.ascontiguousarray(dp_grid))
    c = float(np.linalg.svd(J, compute_uv=False).min())
    if not c > 0:
        raise DesignError("abstract.delta", "'flatten' needs dp/dxi of full column rank on V (p an immersion)", "a p whose derivative has full rank on V", check="rank_delta")
    gram = dp.T * sp.Matrix(M.tolist()) * dp
    if model.n_hat == 1:
        return sp.Matrix([[sp.Float(c) / sp.sqrt(gram[0, 0])]])
    R = gram.cholesky(hermitian=False).T
    return sp.Float(c) * R.inv()


def run(model: Model, upstream: dict[str, Artefact]) -> Artefact:
    """Check the rank of delta on V and build b, c of Theorem 5 (the m-relation's eq. (11a) through eqs. (21a), (21b)).

    Parameters
    ----------
    model : Model
        The spec's systems (V fixed).
    upstream : dict of str to Artefact
        The stabilise (M), manifold (xi_grid, p_grid, V; dp_dxi) and inverse (m, dm_dx) artefacts; M and dp_dxi
        are read only for ``flatten``.

    Returns
    -------
    Artefact
        Expressions delta, b, c; values min_singular_value, link residuals.

    Raises
    ------
    DesignError
        If delta loses row rank on V (or has fewer columns than rows), or ``flatten`` cannot design it
        (m_hat != n_hat, or dp/dxi not of full column rank on V).
    NumericalError
        If b, c do not solve eqs. (21a), (21b) to tolerance.
    """
    man, inv = upstream["manifold"], upstream["inverse"]
    grid = np.asarray(man.value("xi_grid"))
    delta = model.delta if model.delta is not None else flatten(model, upstream["stabilise"], man, grid)
    delta_grid = model.numeric(delta, list(model.xi))(*grid)
    if model.m_hat < model.n_hat:
        raise DesignError("abstract.inputs", f"delta is {model.n_hat} x {model.m_hat}, which cannot have full row rank", "at least as many abstract inputs as abstract states (Theorem 5)")
    smin, smax, at = _smallest_singular_value(model, delta, grid, delta_grid)
    if not np.isfinite(smin) or smin <= RANK_RTOL * max(1.0, smax):
        raise DesignError("abstract.delta", f"delta loses row rank on V: smallest singular value {smin:.3g} at xi = {np.round(at, 6).tolist()}",
                          "delta(xi) of full row rank for every xi in V (Theorem 5)", check="rank_delta")

    m = inv.expr("m")
    dm = inv.expr("dm_dx")
    xi_to_m = dict(zip(model.xi, m))
    delta_at_m = delta.xreplace(xi_to_m)
    pinv = _right_inverse(delta_at_m)
    # A plant that is not input-affine: v = b(x, u) = delta^+(m) (dm/dx f(x, u) - phi_bar(m)) solves eq. (20) of
    # Definition 2 directly (delta(m) delta^+(m) = I), for every u; c = 0 and f_bar, g below stand for f and 0.
    f_bar = model.f_bar if model.affine else model.f
    g = model.g if model.affine else sp.zeros(model.n, model.m)
    b = tidy(pinv * (dm * f_bar - model.phi_bar.xreplace(xi_to_m)))
    c = tidy(pinv * dm * g)

    # Re-check eqs. (21a), (21b) on samples of X_y (for f(x, u): on samples of X_y x U).
    p_grid = np.asarray(man.value("p_grid"))
    samples = sample_states_with_output(model.numeric(model.h, list(model.x)), model.C, model.Y, sample_box(model, p_grid), SAMPLES, seed=1)
    xs = list(model.x)
    if not model.affine:
        xs = xs + list(model.u)
        inputs = np.random.default_rng(2).uniform(model.U[:, 0, None], model.U[:, 1, None], (model.m, samples.shape[1]))
        samples = np.vstack([samples, inputs])
    dm_f = model.numeric(dm * f_bar, xs)(*samples)[:, 0, :]
    dm_g = model.numeric(dm * g, xs)(*samples)
    phi_m = model.numeric(model.phi_bar.xreplace(xi_to_m), xs)(*samples)[:, 0, :]
    d_m = model.numeric(delta_at_m, xs)(*samples)
    b_s = model.numeric(b, xs)(*samples)[:, 0, :]
    c_s = model.numeric(c, xs)(*samples)
    res_diff = np.abs(dm_f - phi_m - np.einsum("ijk,jk->ik", d_m, b_s)).max(axis=0)
    res_in = np.abs(dm_g - np.einsum("ijk,jlk->ilk", d_m, c_s)).reshape(-1, samples.shape[1]).max(axis=0)
    scale = float(max(1.0, np.abs(dm_f).max(), np.abs(dm_g).max()))
    link_residual = float(max(res_diff.max(), res_in.max()) / scale)
    if not np.isfinite(link_residual) or link_residual > LINK_RTOL:
        raise NumericalError(NAME, f"b, c solve eqs. (21a), (21b) only to {link_residual:.3g} (relative)", f"below {LINK_RTOL:g}")

    art = Artefact(stage=NAME, meta={"delta_source": model.spec.abstract.delta if isinstance(model.spec.abstract.delta, str) else "matrix",
                                      "samples": SAMPLES, "sample_seed": 1, "rank_rtol": RANK_RTOL, "link_rtol": LINK_RTOL,
                                      "link_form": "v = b(x) + c(x) u (eq. (22))" if model.affine else "v = b(x, u) (eq. (20), f not input-affine)"})
    art.exprs.update({"delta": delta, "b": b, "c": c})
    art.values.update({"min_singular_value": smin, "max_singular_value": smax, "min_singular_value_at": at,
                       "link_residual": link_residual, "c_is_zero": bool(all(e == 0 for e in c))})
    threshold = RANK_RTOL * max(1.0, smax)
    proved_smin = _prove_rank(model, delta, np.asarray(man.value("V"), dtype=float))
    if proved_smin > threshold:
        art.values["min_singular_value_proved"] = proved_smin
        art.checks["rank_delta"] = Check(proved_smin, True, f"proved lower bound of the smallest singular value of delta on V (> {RANK_RTOL:g} max(1, largest): full row rank)",
                                         proofs.PROVED)
    else:
        art.checks["rank_delta"] = Check(smin, True, f"smallest singular value of delta on a grid of V (> {RANK_RTOL:g} max(1, largest): full row rank)")
    link = list(dm * f_bar - model.phi_bar.xreplace(xi_to_m) - delta_at_m * b) + list(dm * g - delta_at_m * c)
    if proofs.symbolic_zero(link):
        what = ("dm/dx f_bar - phi_bar(m) - delta(m) b and dm/dx g - delta(m) c simplify to 0 (sympy): b, c solve eqs. (21a), (21b)" if model.affine else
                "dm/dx f(x, u) - phi_bar(m) - delta(m) b(x, u) simplifies to 0 (sympy): v = b(x, u) solves eq. (20) for every u")
        art.checks["m_relation_link"] = Check(0.0, True, f"{what} wherever delta(m(x)) has full row rank", proofs.PROVED)
    else:
        art.checks["m_relation_link"] = Check(link_residual, True, "max residual of eqs. (21a), (21b) on samples of X_y, relative")
    return art


def _prove_rank(model: Model, delta: sp.Matrix, V: np.ndarray) -> float:
    """A proved lower bound of the smallest singular value of delta on V (0 when no proof is found).

    A constant delta: the arb Cholesky bound of lambda_min(delta delta^T), square-rooted.  A scalar delta:
    the ball-arithmetic bound of min |delta| over V (branch and bound on delta and on -delta).
    Other shapes are left to the grid.
    """
    try:
        return _rank_bound(model, delta, V)
    except proofs.interval.UnsupportedExpression:
        return 0.0


def _rank_bound(model: Model, delta: sp.Matrix, V: np.ndarray) -> float:
    if not delta.free_symbols & set(model.xi):
        f = proofs.BoxFunction(model, {"d": delta}, list(model.xi))
        if delta.shape[0] > proofs.MAX_PROOF_STATES:
            return 0.0
        D = f([proofs.arb(0)] * model.n_hat)["d"]
        Dt = [[D[i][j] for i in range(len(D))] for j in range(len(D[0]))]
        lam = proofs.psd_lower_bound_balls(proofs.quadratic_form_terms(np.eye(len(Dt)), Dt))
        return float(np.sqrt(lam)) if lam > 0 else 0.0
    if delta.shape != (1, 1):
        return 0.0
    d = proofs.compile_claims(model, [delta[0, 0]], list(model.xi))
    lo, hi, ok = proofs.range_on_box(d, V)
    if ok and lo > 0:
        return float(lo)
    return float(-hi) if ok and hi < 0 else 0.0


def summarise(art: Artefact) -> dict:
    """Headline numbers for ``ashc summary``.

    Parameters
    ----------
    art : Artefact
        The delta stage's artefact.

    Returns
    -------
    dict
        ``delta``, ``b``, ``c`` (entries as text), ``min_singular_value`` and ``link_residual``.
    """
    return {
        "delta": [str(e) for e in art.exprs["delta"]], "b": [str(e) for e in art.exprs["b"]], "c": [str(e) for e in art.exprs["c"]],
        "min_singular_value": float(art.values["min_singular_value"]), "link_residual": float(art.values["link_residual"]),
    }


def headline(art: Artefact) -> str:
    """One progress line.

    Parameters
    ----------
    art : Artefact
        The delta stage's artefact.

    Returns
    -------
    str
        The smallest singular value of delta on V and the link residual.
    """
    return f"min singular value of delta on V = {art.values['min_singular_value']:.4g}, link residual = {art.values['link_residual']:.2g}"

"""Stage 6: the simulation function's error bound (Section V, eqs. egConditionB, iota, egErrorBound).

With W(xi, x) = (p(xi) - x)^T M (p(xi) - x) (eq. egSimuFunc) and the interface u_w = l(xi) + q(xi, x) v:

* alpha_h: the largest c with M >= c C^T C for h(x) = C x, i.e. 1 / lambda_max(C M^-1 C^T) (eq. SimuFuncCondi1
  with alpha_h(r) = c r^2; the paper rounds it to 0.52, ERRATA item 4); for a nonlinear h,
  lambda_min(M) / L_h^2 with L_h the Lipschitz constant of Assumption 1, computed over ``concrete.state_box``;
* epsilon = lambda / 2, which maximises (lambda - epsilon) epsilon;
* theta(xi, x) = sqrt(M) (dp/dxi delta(xi) - g(x) q(xi, x)) (eq. iota, the paper's vartheta);
* dbar = sup over V of ||theta|| with q = 0 (a plain norm, as in Section V; Proposition condB's dbar is its
  square, stored as ``dbar_q0_squared``, ERRATA item 10), for the spec's delta and for delta = I;
* dbar_ls: the same with the least-squares q of eq. egqLS, on the manifold x = p(xi).  Off the manifold
  g(x) can vanish (the converter's g is zero at x2 = 0, x3 = x1) and theta is then the q = 0 value, so only
  dbar_q0 bounds theta uniformly on V x R^n;
* the gain of eq. egErrorBound, G = sqrt(2 / (alpha_h (lambda - epsilon) epsilon)) dbar_q0, so that
  |psi - y| <= G ||v||_inf when W(xi0, x0) = 0.  This keeps the factor 2 of Theorem ErrorBound's max-form
  (the paper's form); ``gain_comparison`` = G / sqrt(2) is what the comparison lemma gives for linear eta
  (ERRATA item 7).
"""

from __future__ import annotations

import numpy as np
import scipy.optimize as sopt

from ..artefacts import Artefact, Check
from ..errors import DesignError
from ..grids import domain_grid
from ..model import Model

NAME = "bound"
UPSTREAM = ("stabilise", "manifold", "delta")

GRID_POINTS = 20001


def alpha_h_linear(M: np.ndarray, C: np.ndarray) -> float:
    """Largest c with M >= c C^T C: 1 / lambda_max(C M^-1 C^T) (ERRATA item 4)."""
    return float(1.0 / np.linalg.eigvalsh(C @ np.linalg.solve(M, C.T)).max())


def alpha_h_lipschitz(M: np.ndarray, lipschitz_h: float) -> float:
    """alpha_h for a nonlinear h with Lipschitz constant L_h (Assumption 1, proof of Theorem SimuDesign).

    W = (p - x)^T M (p - x) >= lambda_min(M) |p - x|^2 >= (lambda_min(M) / L_h^2) |h(p) - h(x)|^2.
    """
    return float(np.linalg.eigvalsh(M).min() / lipschitz_h**2)


def error_bound_gain(alpha_h: float, lam: float, eps: float, dbar: float) -> float:
    """The factor G of eq. egErrorBound: alpha_h^-1(eta^-1(2 gamma(|v|))) = G |v|.

    With eta(r) = (lambda - eps) r, gamma(r) = dbar^2 r^2 / eps and alpha_h(r) = alpha_h r^2,
    G = sqrt(2 / (alpha_h (lambda - eps) eps)) dbar (the paper's form, with Theorem ErrorBound's factor 2).
    """
    return float(np.sqrt(2.0 / (alpha_h * (lam - eps) * eps)) * dbar)


def theta_norms(L: np.ndarray, dpd: np.ndarray, g: np.ndarray | None) -> np.ndarray:
    """||theta|| (2-norm) at each point, theta = L^T (dp/dxi delta - g q) with M = L L^T (eq. iota).

    Parameters
    ----------
    L : ndarray (n, n)
        Cholesky factor of M, so ||L^T w|| = sqrt(w^T M w) = ||sqrt(M) w|| (ERRATA item 8).
    dpd : ndarray (n, m_hat, N)
        dp/dxi delta at N points.
    g : ndarray (n, m, N) or None
        g(x) at the same points for the least-squares q (eq. egqLS); None for q = 0.
    """
    A = np.einsum("ij,jkN->Nik", L.T, dpd)                       # sqrt(M) dp/dxi delta, (N, n, m_hat)
    if g is not None:
        B = np.einsum("ij,jkN->Nik", L.T, g)                     # sqrt(M) g, (N, n, m)
        # q = argmin ||A - B q|| = (g^T M g)^+ g^T M dp delta; theta = A - B q (pinv: q = 0 where g = 0).
        A = A - B @ (np.linalg.pinv(B) @ A)
    return np.linalg.norm(A, ord=2, axis=(1, 2)) if A.shape[2] > 1 else np.linalg.norm(A[:, :, 0], axis=1)


def sup_on_interval(fun, grid: np.ndarray, values: np.ndarray) -> tuple[float, float]:
    """Refine the largest of ``values`` on a 1-D grid by a bounded search in the neighbouring cells."""
    k = int(np.nanargmax(values))
    lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
    best_x, best = grid[k], float(values[k])
    if hi > lo:
        res = sopt.minimize_scalar(lambda s: -fun(np.array([s]))[0], bounds=(lo, hi), method="bounded", options={"xatol": 1e-12})
        if res.success and -res.fun > best:
            best_x, best = float(res.x), float(-res.fun)
    return best, float(best_x)


def run(model: Model, upstream: dict[str, Artefact]) -> Artefact:
    """Compute alpha_h, epsilon, dbar (q = 0 and least squares) and the gain of eq. egErrorBound.

    Returns
    -------
    Artefact
        Values alpha_h, epsilon, dbar_q0, dbar_q0_identity, dbar_ls, gain, gain_comparison, the theta
        norm curves on V; expressions dp_delta and g (for theta).

    Raises
    ------
    DesignError
        If theta is unbounded on V.
    SpecError
        If h is nonlinear and the spec gives no ``concrete.state_box`` to compute L_h on.
    """
    st, man, dl = upstream["stabilise"], upstream["manifold"], upstream["delta"]
    M = np.asarray(st.value("M"), dtype=float)
    lam = float(st.value("lambda"))
    C = model.C
    lipschitz_h, lipschitz_at = model.h_jacobian_bound()
    alpha_h = alpha_h_linear(M, C) if C is not None else alpha_h_lipschitz(M, lipschitz_h)
    eps = lam / 2.0
    L = np.linalg.cholesky(M)

    dp = man.expr("dp_dxi")
    delta = dl.expr("delta")
    dp_delta = dp * delta
    xi_args = list(model.xi)
    dpd_num = model.numeric(dp_delta, xi_args)
    dp_num = model.numeric(dp, xi_args)
    p_num = model.numeric(man.expr("p"), xi_args)
    g_num = model.numeric(model.g, list(model.x))

    grid = domain_grid(model.V, GRID_POINTS)
    norm_q0 = theta_norms(L, dpd_num(*grid), None)
    norm_q0_identity = theta_norms(L, dp_num(*grid), None)
    norm_ls = theta_norms(L, dpd_num(*grid), g_num(*p_num(*grid)[:, 0, :]))
    if not np.all(np.isfinite(norm_q0)):
        raise DesignError("abstract.delta", "||sqrt(M) dp/dxi delta|| is not finite on V (condition (B) fails)", "p continuously differentiable and delta continuous on V (Proposition condB)", check="condition_B")

    if model.n_hat == 1:
        xs = grid[0]
        dbar_q0, at_q0 = sup_on_interval(lambda s: theta_norms(L, dpd_num(s), None), xs, norm_q0)
        dbar_id, at_id = sup_on_interval(lambda s: theta_norms(L, dp_num(s), None), xs, norm_q0_identity)
        dbar_ls, at_ls = sup_on_interval(lambda s: theta_norms(L, dpd_num(s), g_num(*p_num(s)[:, 0, :])), xs, norm_ls)
        at = [[at_q0], [at_id], [at_ls]]
    else:
        dbar_q0, dbar_id, dbar_ls = float(norm_q0.max()), float(norm_q0_identity.max()), float(norm_ls.max())
        at = [grid[:, np.argmax(v)].tolist() for v in (norm_q0, norm_q0_identity, norm_ls)]

    gain = error_bound_gain(alpha_h, lam, eps, dbar_q0)
    art = Artefact(stage=NAME, meta={
        "grid_points": int(grid.shape[1]), "sup_method": "grid maximum refined by bounded scalar search",
        "sqrt_M": "Cholesky factor L of M, ||L^T w|| = ||sqrt(M) w|| (ERRATA item 8)",
        "gain_form": "paper (Theorem ErrorBound max-form, factor 2 kept, ERRATA item 7)",
        "dbar_ls_where": "on the manifold x = p(xi); not a uniform bound off it",
        "interface_q": model.spec.interface.q,
    })
    art.exprs.update({"dp_delta": dp_delta, "g": model.g})
    art.values.update({
        "M": M, "L": L, "lambda": lam, "alpha_h": alpha_h, "epsilon": eps, "C": C if C is not None else np.zeros((0, model.n)),
        "dbar_q0": dbar_q0, "dbar_q0_squared": dbar_q0**2, "dbar_q0_identity": dbar_id, "dbar_ls": dbar_ls,
        "dbar_argmax": np.array(at, dtype=float), "gain": gain, "gain_comparison": gain / np.sqrt(2.0),
        "xi_grid": grid, "theta_norm_q0": norm_q0, "theta_norm_q0_identity": norm_q0_identity, "theta_norm_ls_manifold": norm_ls,
    })
    art.checks["condition_B"] = Check(dbar_q0, bool(np.isfinite(dbar_q0) and 0 < eps < lam),
                                      "Proposition condB: V compact, p C^1, delta continuous, V quadratic: dbar_q0 finite and 0 < epsilon < lambda")
    art.checks["alpha_h"] = Check(alpha_h, alpha_h > 0, "largest c with M >= c C^T C (> 0, eq. SimuFuncCondi1)")
    art.values.update({"lipschitz_h": lipschitz_h, "lipschitz_h_at": lipschitz_at})
    where = "||C||_2 of the linear output map" if C is not None else f"sup of ||dh/dx||_2 over concrete.state_box = {model.state_box.tolist()} (grid + L-BFGS-B)"
    art.meta["alpha_h_form"] = "1 / lambda_max(C M^-1 C^T)" if C is not None else "lambda_min(M) / L_h^2 (Assumption 1)"
    art.checks["h_lipschitz"] = Check(lipschitz_h, bool(np.isfinite(lipschitz_h) and lipschitz_h > 0), f"Lipschitz constant L_h = {where} (finite: Assumption 1 holds)")
    return art


def summarise(art: Artefact) -> dict:
    """Headline numbers for ``ashc summary``."""
    v = art.values
    return {
        "alpha_h": float(v["alpha_h"]), "epsilon": float(v["epsilon"]), "dbar_q0": float(v["dbar_q0"]),
        "dbar_q0_identity": float(v["dbar_q0_identity"]), "dbar_ls": float(v["dbar_ls"]), "gain": float(v["gain"]),
        "gain_comparison": float(v["gain_comparison"]), "gain_form": art.meta.get("gain_form"),
        "dbar_argmax": {"q0": np.asarray(v["dbar_argmax"])[0].tolist(), "q0_identity": np.asarray(v["dbar_argmax"])[1].tolist(),
                        "ls": np.asarray(v["dbar_argmax"])[2].tolist()},
    }


def headline(art: Artefact) -> str:
    """One progress line."""
    v = art.values
    return f"alpha_h = {v['alpha_h']:.5g}, dbar_q0 = {v['dbar_q0']:.5g}, gain G = {v['gain']:.5g} (|psi - y| <= G ||v||_inf)"

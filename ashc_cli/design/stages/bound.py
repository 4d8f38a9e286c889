"""Stage 6: the simulation function's error bound (Section V, eqs. (36), (37), (38)).

With W(xi, x) = (p(xi) - x)^T M (p(xi) - x) (eq. (35)) and the interface u_w = l(xi) + q(xi, x) v:

* alpha_h: the largest c with M >= c C^T C for h(x) = C x, i.e. 1 / lambda_max(C M^-1 C^T) (eq. (6)
  with alpha_h(r) = c r^2; the paper rounds it to 0.52, ERRATA item 4); for a nonlinear h,
  lambda_min(M) / L_h^2 with L_h the Lipschitz constant of Assumption 1, computed over ``concrete.state_box``;
* epsilon = lambda / 2, which maximises (lambda - epsilon) epsilon;
* theta(xi, x) = sqrt(M) (dp/dxi delta(xi) - g(x) q(xi, x)) (eq. (37), the paper's vartheta);
* dbar = sup over V of ||theta|| with q = 0 (a plain norm, as in Section V; Proposition 1's dbar is its
  square, stored as ``dbar_q0_squared``, ERRATA item 10), for the spec's delta and for delta = I;
* dbar_ls: the same with the least-squares q of eq. (43), on the manifold x = p(xi).  Off the manifold
  g(x) can vanish (the converter's g is zero at x2 = 0, x3 = x1) and theta is then the q = 0 value, so only
  dbar_q0 bounds theta uniformly on V x R^n;
* the gain of eq. (38), G = sqrt(2 / (alpha_h (lambda - epsilon) epsilon)) dbar_q0, so that
  |psi - y| <= G ||v||_inf when W(xi0, x0) = 0.  This keeps the factor 2 of Theorem 2's max-form
  (the paper's form); ``gain_comparison`` = G / sqrt(2) is what the comparison lemma gives for linear eta
  (ERRATA item 7).

What the interface does to that argument (:func:`_interface_dbar`, :func:`certified_region`):

* the saturated interface applies u - l = S (K e + q v) with e = x - p(xi).  Clipping channel by channel
  (``saturate: true``) gives S = diag(s), s in [0, 1]^m; ``saturate: scale`` gives S = s I.  For identity
  feedback theta_S = sqrt(M) (dp/dxi delta - g S q) is affine in S, so its norm is largest at a vertex:
  with one input or ``scale`` the vertices are q = 0 and the least-squares q, and the least-squares q never
  does worse than q = 0, so dbar_q0 bounds every S; with several inputs clipped channel by channel the
  vertices are the 2^m clipping patterns, whose theta can be far larger (one channel clipped, another
  applied in full).  For a constant g that sup over V and the patterns is computed (``dbar_saturation``);
  for a state-dependent g it is not bounded on V x R^n and no uniform bound is certified;
* with ``feedback: linear_gain`` a clipped K e turns the certified A + B K back into A, so the certificate
  is local: it holds while no channel clips, i.e. on the sublevel set {W <= c} for which
  |K_i e| + |q_i v| <= the room of l_i(xi) in U_i on V.  With a state box (a Jacobian LMI or a nonlinear h)
  it holds while x stays in the box: on {W <= c} with p(V) + {e : e^T M e <= c} inside it.  Both sets are
  forward invariant when ||v|| <= v_c = sqrt(c eps (lambda - eps)) / dbar, since then W(t) <= max(W0, c).
  ``w0_max_certified`` = c and ``v_max_certified`` = v_c (inf when the bound is global).
"""

from __future__ import annotations

import numpy as np
import scipy.optimize as sopt
import sympy as sp

from ashc_cli.numerics import chebyshev, proofs
from ashc_cli.design import series_proofs
from ashc_cli.design.artefacts import Artefact, Check
from ashc_cli.design.bound_proofs import jacobian_norm_expr, prove_alpha_h, prove_sup_norm  # noqa: F401 (jacobian_norm_expr: bound's API)
from ashc_cli.numerics.proofs import PROVED, SAMPLED
from ashc_cli.errors import DesignError, SpecError
from ashc_cli.problem.grids import domain_grid, maximise_on_box
from ashc_cli.problem.model import Model
from ashc_cli.design.upstream import dp_function, p_function, theta_is_pointwise
from ashc_cli.numerics.linalg import least_squares_q, sqrt_M_times

#: The most inputs whose 2^m clipping patterns are enumerated for ``saturate: true``.
MAX_PATTERN_INPUTS = 12

NAME = "bound"
UPSTREAM = ("stabilise", "manifold", "delta")

GRID_POINTS = 20001

#: The checks every number of the published bound rests on (lambda and M; p and l; L_h, alpha_h, dbar and the
#: region): the bound is *proved* only when each of them is, and printed with "(sampled)" otherwise.
BOUND_CHECKS = (("stabilise", "lmi_margin"), ("stabilise", "M_positive"), ("manifold", "pde_residual"), ("manifold", "l_in_U"),
                ("bound", "h_lipschitz"), ("bound", "alpha_h"), ("bound", "condition_B"), ("bound", "certified_region"))


def alpha_h_linear(M: np.ndarray, C: np.ndarray) -> float:
    """Largest c with M >= c C^T C: 1 / lambda_max(C M^-1 C^T), the alpha_h of eq. (6) for h = C x (ERRATA item 4).

    Parameters
    ----------
    M, C : ndarray (n, n), (p, n)
        The positive definite matrix of W (stabilise's ``M``) and the output matrix of h(x) = C x.

    Returns
    -------
    float
    """
    return float(1.0 / np.linalg.eigvalsh(C @ np.linalg.solve(M, C.T)).max())


def _alpha_h_lipschitz(M: np.ndarray, lipschitz_h: float) -> float:
    """alpha_h for a nonlinear h with Lipschitz constant L_h (Assumption 1, proof of Theorem 4).

    W = (p - x)^T M (p - x) >= lambda_min(M) |p - x|^2 >= (lambda_min(M) / L_h^2) |h(p) - h(x)|^2.
    """
    return float(np.linalg.eigvalsh(M).min() / lipschitz_h**2)


def error_bound_gain(alpha_h: float, lam: float, eps: float, dbar: float) -> float:
    """The factor G of eq. (38): alpha_h^-1(eta^-1(2 gamma(|v|))) = G |v|, the second term of Theorem 2's bound
    (eq. (8)).

    With eta(r) = (lambda - eps) r, gamma(r) = dbar^2 r^2 / eps and alpha_h(r) = alpha_h r^2,
    G = sqrt(2 / (alpha_h (lambda - eps) eps)) dbar (the paper's form, with Theorem 2's factor 2).

    Parameters
    ----------
    alpha_h, lam, eps, dbar : float
        alpha_h r^2's coefficient, lambda (stabilise's rate), epsilon (0 < eps < lam) and the sup of ||theta||.

    Returns
    -------
    float
    """
    return float(np.sqrt(2.0 / (alpha_h * (lam - eps) * eps)) * dbar)


def theta_norms(L: np.ndarray, dpd: np.ndarray, g: np.ndarray | None) -> np.ndarray:
    """||theta|| (2-norm) at each point, theta = L^T (dp/dxi delta - g q) with M = L L^T (eq. (37)).

    Parameters
    ----------
    L : ndarray (n, n)
        Cholesky factor of M, so ||L^T w|| = sqrt(w^T M w) = ||sqrt(M) w|| (ERRATA item 8).
    dpd : ndarray (n, m_hat, N)
        dp/dxi delta at N points.
    g : ndarray (n, m, N) or None
        g(x) at the same points for the least-squares q (eq. (43)); None for q = 0.
    """
    A = sqrt_M_times(L, dpd)                                     # sqrt(M) dp/dxi delta, (N, n, m_hat)
    if g is not None:
        B = sqrt_M_times(L, g)                                   # sqrt(M) g, (N, n, m)
        # q = argmin ||A - B q|| = (g^T M g)^+ g^T M dp delta; theta = A - B q (pinv: q = 0 where g = 0).
        A = A - B @ (np.linalg.pinv(B) @ A)
    return np.linalg.norm(A, ord=2, axis=(1, 2)) if A.shape[2] > 1 else np.linalg.norm(A[:, :, 0], axis=1)


def _sup_on_interval(fun, grid: np.ndarray, values: np.ndarray) -> tuple[float, float]:
    """Refine the largest of ``values`` on a 1-D grid by a bounded search in the neighbouring cells."""
    k = int(np.nanargmax(values))
    lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
    best_x, best = grid[k], float(values[k])
    if hi > lo:
        res = sopt.minimize_scalar(lambda s: -fun(np.array([s]))[0], bounds=(lo, hi), method="bounded", options={"xatol": 1e-12})
        if res.success and -res.fun > best:
            best_x, best = float(res.x), float(-res.fun)
    return best, float(best_x)


def _constant_g(model: Model) -> np.ndarray | None:
    """g as a number matrix (n, m) when it does not depend on x, else None (also for a plant that is not input-affine)."""
    if not model.affine or model.g.free_symbols & set(model.x):
        return None
    return np.asarray(model.numeric(model.g, list(model.x))(*np.zeros(model.n)), dtype=float).reshape(model.n, model.m)


def _input_matrix(model: Model) -> sp.Matrix:
    """g(x); zero for a plant that is not input-affine, whose interface has q = 0 (Proposition 1, Remark 4), so the
    least-squares q of eq. (43) is 0 and dbar_ls is dbar_q0."""
    return model.g if model.affine else sp.zeros(model.n, model.m)


def pattern_theta_norms(L: np.ndarray, g: np.ndarray, dpd: np.ndarray) -> np.ndarray:
    """max over the clipping patterns s in {0, 1}^m of ||sqrt(M) (dp/dxi delta - g diag(s) q)|| at N points.

    The sup of ||theta|| over every per-channel clipping factor s in [0, 1]^m (``saturate: true``): theta is
    affine in s, so its norm (convex) is largest at a vertex of the cube.

    Parameters
    ----------
    L, g, dpd : ndarray (n, n), (n, m), (n, m_hat, N)
        Cholesky factor of M, the constant g, and dp/dxi delta at N points (q: the least-squares q of eq. (43)).

    Returns
    -------
    ndarray (N,)
    """
    m = g.shape[1]
    A = sqrt_M_times(L, dpd)                                     # (N, n, m_hat)
    q = least_squares_q(L, g, np.moveaxis(dpd, -1, 0))             # (N, m, m_hat), eq. (43)
    B = L.T @ g                                                  # (n, m)
    best = np.zeros(A.shape[0])
    for k in range(2 ** m):
        s = np.array([(k >> i) & 1 for i in range(m)], dtype=float)
        theta = A - (B * s[None, :])[None] @ q
        best = np.maximum(best, np.linalg.norm(theta, ord=2, axis=(1, 2)))
    return best


def _interface_dbar(model: Model, L: np.ndarray, dpd_grid: np.ndarray, dbar_q0: float) -> tuple[float, str]:
    """The sup of ||theta|| over V, the states and every factor the saturated interface can apply.

    Returns
    -------
    dbar : float
        dbar_q0 where it bounds every saturation factor; the sup over the clipping patterns for several
        inputs clipped channel by channel with a constant g; inf where no uniform bound exists.
    how : str
        Why (shown in the artefact and by ``ashc check``).
    """
    if theta_is_pointwise(model):
        return dbar_q0, ("q = 0 value: bounds the least-squares q pointwise and every saturation factor of one input, "
                         "of the scaled correction (saturate: scale) and of the unsaturated region of a feedback design")
    g = _constant_g(model)
    if g is None or model.m > MAX_PATTERN_INPUTS:
        why = "g depends on x" if g is None else f"more than {MAX_PATTERN_INPUTS} inputs"
        return np.inf, (f"interface.saturate: true clips the {model.m} channels of the least-squares correction separately and {why}: "
                        "||theta|| over the clipping patterns is not bounded uniformly")
    dbar = float(pattern_theta_norms(L, g, dpd_grid).max())
    return max(dbar, dbar_q0), f"sup over V and the 2^{model.m} per-channel clipping patterns of ||sqrt(M)(dp/dxi delta - g diag(s) q)|| (grid)"


def _balls(A):
    """A float matrix (or a nested list of arb balls) as a flint ``arb_mat``."""
    from flint import arb_mat

    return arb_mat([[proofs.arb(v) if not isinstance(v, proofs.arb) else v for v in row] for row in (A.tolist() if isinstance(A, np.ndarray) else A)])


def _constant_dp_delta(model: Model, dp_delta: sp.Matrix | None) -> list[list] | None:
    """dp/dxi delta as a ball matrix when it does not depend on xi (an affine p with a constant delta), else None."""
    if dp_delta is None or dp_delta.free_symbols & set(model.xi):
        return None
    try:
        return proofs.BoxFunction(model, {"w": dp_delta}, list(model.xi))([proofs.arb(0)] * model.n_hat)["w"]
    except proofs.interval.UnsupportedExpression:
        return None


def _least_squares_q_balls(M: np.ndarray, g: np.ndarray, w: list[list]):
    """q = (g^T M g)^-1 g^T M w (eq. (43), g of full column rank) as an arb_mat (m x m_hat), or None."""
    Mb, gb, wb = _balls(M), _balls(g), _balls(w)
    G = gb.transpose() * Mb * gb
    try:
        return G.inv() * (gb.transpose() * Mb * wb)
    except ZeroDivisionError:
        return None


def _prove_pattern_dbar(model: Model, M: np.ndarray, g: np.ndarray, dp_delta: sp.Matrix | None) -> float:
    """A proved upper bound of max over the 2^m clipping patterns S of ||sqrt(M) (dp/dxi delta - g S q)|| for a
    constant dp/dxi delta and a constant g (then theta does not depend on xi), or inf where not proved.

    q is the exact least-squares correction, enclosed in ball arithmetic; the norm of each pattern's theta is
    bounded by :func:`proofs.norm_sqrt_M` (exact for one abstract input, Gershgorin on the Gram matrix else).
    """
    w = _constant_dp_delta(model, dp_delta)
    if w is None or model.n > proofs.MAX_PROOF_STATES:
        return np.inf
    q = _least_squares_q_balls(M, g, w)
    if q is None:
        return np.inf
    gb, wb = _balls(g), _balls(w)
    worst = 0.0
    for k in range(2 ** model.m):
        S = _balls(np.diag([(k >> i) & 1 for i in range(model.m)]).astype(float))
        theta = wb - gb * S * q
        bound = proofs.upper(proofs.norm_sqrt_M(M, [[theta[i, j] for j in range(theta.ncols())] for i in range(theta.nrows())]))
        worst = max(worst, bound)
    return float(worst)


def _prove_region(model: Model, upstream: dict[str, Artefact], M: np.ndarray, dbar: float, eta_eps: float,
                 p_expr: sp.Matrix | None, dp_delta: sp.Matrix | None, p_range: np.ndarray | None = None) -> tuple[float, float] | None:
    """Proved lower bounds of the certified region's c and v_c (:func:`certified_region`), or None where not proved.

    Each limit of :func:`certified_region` is bounded in ball arithmetic over V: the room of l_i in U_i by
    branch and bound (inf over V of l_i - lo_i and hi_i - l_i), K_i M^-1 K_i^T with M^-1 enclosed (arb), the
    least-squares q for a constant dp/dxi delta and g (or q = 0); the distance of p(xi) to the state box by
    branch and bound on p's formula, and (M^-1)_jj enclosed.  c is the smallest of those lower bounds and
    v_c = sqrt(c eps (lambda - eps)) / dbar is rounded down.  ``p_range`` (n, 2), where given, is a proved
    enclosure of p(V) used instead of that branch and bound (a series in several abstract states: from its
    coefficients, where a box search on its cosine form took minutes).
    """
    if model.n > proofs.MAX_PROOF_STATES:
        return None
    stab = upstream["stabilise"]
    K = np.asarray(stab.values.get("K", np.zeros((model.m, model.n))), dtype=float).reshape(model.m, model.n)
    try:
        Minv = _balls(M).inv()
    except ZeroDivisionError:
        return None
    bounds = []
    try:
        if _input_must_stay_in_U(model, upstream):
            Kb = _balls(K)
            KMK = Kb * Minv * Kb.transpose()
            g = _constant_g(model)
            qn = [proofs.arb(0)] * model.m
            if model.spec.interface.q == "least_squares" and g is not None:
                w = _constant_dp_delta(model, dp_delta)
                q = _least_squares_q_balls(M, g, w) if w is not None else None
                if q is None:
                    return None
                qn = [sum((q[i, j] ** 2 for j in range(q.ncols())), proofs.arb(0)).sqrt() for i in range(model.m)]
            lf = proofs.compile_claims(model, _rooms(model.l, model.U), list(model.xi))
            factor = (proofs.arb(eta_eps).sqrt() / proofs.arb(dbar))
            for i in range(model.m):
                room_lo, ok_lo = proofs.inf_on_box(lf, model.V, index=2 * i)
                room_hi, ok_hi = proofs.inf_on_box(lf, model.V, index=2 * i + 1)
                if not (ok_lo and ok_hi):
                    return None
                room = max(0.0, min(room_lo, room_hi))
                denom = KMK[i, i].sqrt() + qn[i] * factor
                if not denom.is_finite():
                    return None
                if proofs.upper(denom) > 0:
                    bounds.append(proofs.arb(room) / proofs.arb(proofs.upper(denom)))
        if _rests_on_state_box(model, stab) and model.state_box is not None:
            if p_expr is None and p_range is None:
                return None
            pf = proofs.compile_claims(model, _rooms(p_expr, model.state_box), list(model.xi)) if p_range is None else None
            for j in range(model.n):
                if p_range is not None:   # outward-rounded ends: the distance is rounded down
                    d_lo, d_hi = np.nextafter(p_range[j, 0] - model.state_box[j, 0], -np.inf), np.nextafter(model.state_box[j, 1] - p_range[j, 1], -np.inf)
                else:
                    d_lo, ok_lo = proofs.inf_on_box(pf, model.V, index=2 * j)
                    d_hi, ok_hi = proofs.inf_on_box(pf, model.V, index=2 * j + 1)
                    if not (ok_lo and ok_hi):
                        return None
                dist = max(0.0, min(d_lo, d_hi))
                bounds.append(proofs.arb(dist) / Minv[j, j].sqrt())
    except proofs.interval.UnsupportedExpression:
        return None
    if not bounds:
        return np.inf, np.inf
    root = min(proofs.lower(b) for b in bounds)            # sqrt(c) <= every bound
    c_low = proofs.lower(proofs.arb(root) ** 2)
    v_low = proofs.lower((proofs.arb(c_low) * proofs.arb(eta_eps)).sqrt() / proofs.arb(dbar))
    return float(c_low), float(v_low)


def _rooms(exprs, box: np.ndarray) -> list[sp.Expr]:
    """[e_0 - lo_0, hi_0 - e_0, e_1 - lo_1, ...]: how far each expression is inside its interval (the ends exact doubles)."""
    out = []
    for e, (lo, hi) in zip(exprs, np.asarray(box, dtype=float)):
        out += [e - sp.Float(float(lo)), sp.Float(float(hi)) - e]
    return out


def _rests_on_state_box(model: Model, stab: Artefact) -> bool:
    """Whether a quantity of the bound is taken over ``concrete.state_box`` only, so that the region must keep x in it:
    a Jacobian LMI (lambda), a nonlinear h (L_h and alpha_h) or a disturbance matrix e(x) that depends on the states
    (ebar = sup over the box of ||sqrt(M) e(x)||).  Only when none is can the region be global."""
    e_varies = model.e is not None and bool(model.e.free_symbols & set(model.x))
    return "state_box" in stab.meta or model.C is None or e_varies


def _input_must_stay_in_U(model: Model, upstream: dict[str, Artefact]) -> bool:
    """Whether the certificate needs the applied u inside U: a clipped K (x - p) loses A + B K (saturating feedback),
    and without clipping (``saturate: false``) an A(u) or a Jacobian that depends on u is certified on U only."""
    itf, st = model.spec.interface, model.spec.stabilisability
    if itf.saturate is not False:
        return st.feedback == "linear_gain"
    A = upstream["stabilise"].exprs.get("A")
    return A is not None and any(e.free_symbols & set(model.u) for e in A)


def certified_region(model: Model, upstream: dict[str, Artefact], L: np.ndarray, dbar: float, eta_eps: float,
                     grid: np.ndarray, l_grid: np.ndarray, p_grid: np.ndarray, dpd_grid: np.ndarray) -> tuple[float, float, list[str]]:
    """The sublevel set {W <= c} on which the bound is certified, and the largest ||v|| that keeps it invariant.

    Parameters
    ----------
    eta_eps : float
        (lambda - eps) eps.
    l_grid, p_grid, dpd_grid : ndarray
        l(xi) (m, 1, N), p(xi) (n, 1, N) and dp/dxi delta (n, m_hat, N) on ``grid``.

    Returns
    -------
    c : float
        ``w0_max_certified`` (inf when the bound is global).
    v_c : float
        ``v_max_certified`` = sqrt(c eps (lambda - eps)) / dbar (inf when global).
    reasons : list of str
        What limits the region.
    """
    M = L @ L.T
    Minv = np.linalg.inv(M)
    c, reasons = np.inf, []
    stab = upstream["stabilise"]
    K = np.asarray(stab.values.get("K", np.zeros((model.m, model.n))), dtype=float).reshape(model.m, model.n)
    # _interface_dbar leaves the clipping patterns out for linear_gain, so the region must exclude clipping
    # whatever K came out as (even a zero K); without clipping, an A(u) certified on U needs u to stay in U.
    if _input_must_stay_in_U(model, upstream) and model.spec.interface.saturate is False and _constant_g(model) is None:
        raise DesignError("interface.saturate", "false with a g that depends on x: eq. (28) holds for u in U only (A(u) depends on u "
                          "through dg/dx u), and without clipping u = l + K (x - p) + q v leaves U for large v, with a q that grows "
                          "where g(x) is small, so no region of W0 and v keeps u in U", "interface.saturate: true or scale (u stays in U)",
                          check="certified_region")
    if _input_must_stay_in_U(model, upstream):
        # No channel clips while |K_i e| + |q_i v| <= room_i(xi): |K_i e| <= sqrt(c K_i M^-1 K_i^T) on {W <= c}
        # and |q_i v| <= ||q_i|| v_c with v_c = sqrt(c eta_eps) / dbar, so sqrt(c) <= room / (k_i + ||q_i|| sqrt(eta_eps) / dbar).
        k = np.sqrt(np.einsum("ij,jk,ik->i", K, Minv, K))
        g = _constant_g(model)
        if model.spec.interface.q == "least_squares" and g is not None:
            qn = np.linalg.norm(least_squares_q(L, g, np.moveaxis(dpd_grid, -1, 0)), axis=2).T            # (m, N)
        else:
            qn = np.zeros((model.m, grid.shape[1]))
        l = l_grid[:, 0, :]
        room = np.minimum(l - model.U[:, 0:1], model.U[:, 1:2] - l)                   # (m, N)
        denom = k[:, None] + qn * np.sqrt(eta_eps) / dbar
        with np.errstate(divide="ignore", invalid="ignore"):
            root = np.where(denom > 0, np.maximum(room, 0.0) / denom, np.inf)
        c_sat = float(np.min(root) ** 2)
        c = min(c, c_sat)
        reasons.append(f"feedback K (x - p) does not clip (c <= {c_sat:.6g})" if model.spec.interface.saturate is not False
                        else f"u = l + K (x - p) + q v stays in U, where A(u) is certified (c <= {c_sat:.6g})")
    if _rests_on_state_box(model, stab) and model.state_box is not None:
        # p(xi) + e stays in the box for every e^T M e <= c: |e_j| <= sqrt(c (M^-1)_jj).
        p = p_grid[:, 0, :]
        dist = np.minimum(p - model.state_box[:, 0:1], model.state_box[:, 1:2] - p)    # (n, N)
        c_box = float(np.min(np.maximum(dist, 0.0) ** 2 / np.diag(Minv)[:, None]))
        c = min(c, c_box)
        reasons.append(f"x stays in concrete.state_box (c <= {c_box:.6g})")
    v_c = float(np.sqrt(c * eta_eps) / dbar) if np.isfinite(c) and dbar > 0 else np.inf
    return c, v_c, reasons


def run(model: Model, upstream: dict[str, Artefact]) -> Artefact:
    """Compute alpha_h, epsilon, dbar (q = 0 and least squares) and the gain of eq. (38).

    For W = (p(xi) - x)^T M (p(xi) - x) (eq. (35)), condition (B) (eq. (16), for this W eq. (36)) holds by
    Proposition 1 when dbar is finite and 0 < epsilon < lambda; W then decreases as eq. (7) asks.

    Parameters
    ----------
    model : Model
        The spec's systems.
    upstream : dict of str to Artefact
        The stabilise, manifold and delta artefacts.

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
    st = upstream["stabilise"]
    M = np.asarray(st.value("M"), dtype=float)
    lam = float(st.value("lambda"))
    eps = lam / 2.0
    L = np.linalg.cholesky(M)
    alpha = _alpha_h(model, M)
    th = _theta_on_V(model, upstream["manifold"], upstream["delta"], L)
    db = _dbar(model, M, L, th)
    gain = error_bound_gain(alpha["alpha_h"], lam, eps, db["dbar"])
    region = _region(model, upstream, M, L, lam, eps, db, th)
    residual = _residual(upstream["manifold"], M, alpha["alpha_h"], lam, eps)
    empty = None
    if residual and np.isfinite(region["w0_max"]):
        # rho, like a disturbance, takes rho_bar / dbar of the v that keeps {W <= c} invariant ((dbar v + rho_bar)^2
        # <= eps (lambda - eps) c at W = c); with dbar = 0 it must fit by itself
        rho, room = residual["rho_bar"], float(np.sqrt(eps * (lam - eps) * region["w0_max"]))
        if db["dbar"] > 0 and np.isfinite(region["v_max"]):
            region["v_max"] = region["v_max"] - rho / db["dbar"]
        if not region["v_max"] > 0 or rho > room:
            empty = f"p's PDE residual (rho_bar = {rho:.3g}) leaves no v that keeps {{W <= {region['w0_max']:.4g}}} invariant (room {room:.3g})"
    art = _artefact(model, upstream, M, L, lam, eps, gain, alpha, th, db, region)
    art.values.update(residual)
    if empty is not None:
        chk = art.checks["certified_region"]
        art.checks["certified_region"] = Check(chk.value, False, f"{chk.description}; fails: {empty}", chk.evidence)
    if model.e is not None:
        _disturbance(model, art, M, L)
        art.values["bound_sampled"] = ", ".join(bound_sampled({**upstream, NAME: art})) or "none"
        art.values["bound_evidence"] = PROVED if art.values["bound_sampled"] == "none" else SAMPLED
    return art


def _residual(man: Artefact, M: np.ndarray, alpha_h: float, lam: float, eps: float) -> dict:
    """A fitted p's residual rho of eq. (14a), carried like a disturbance: e' gains rho(xi), |L^T rho| <= rho_bar on V,
    so |psi - y| gains residual_term = G(rho_bar) (:func:`error_bound_gain` with rho_bar for dbar, the Young step of
    eq. (36)).  From the manifold's proved bounds where it has them, else from its grid (then sampled, like the
    check).  Empty for a p that solves eq. (14a) exactly."""
    chk = man.checks.get("pde_residual")
    if chk is None or (chk.evidence == PROVED and "residual_proved" not in man.values):
        return {}
    proved = "residual_proved" in man.values
    rows = np.asarray(man.values["residual_proved"] if proved else man.values.get("residual_rows", [chk.value]), dtype=float)
    rows = np.broadcast_to(rows, (M.shape[0],))
    rho_bar = series_proofs.residual_norm_bound(M, rows)
    return {"rho_bar": rho_bar, "residual_term": error_bound_gain(alpha_h, lam, eps, rho_bar), "evidence_residual": PROVED if proved else SAMPLED}


def _disturbance(model: Model, art: Artefact, M: np.ndarray, L: np.ndarray) -> None:
    """The disturbance's term of the bound, x' = f + e(x) w: |L^T (theta v - e w)| <= dbar |v| + ebar |w| with
    ebar = sup over concrete.state_box of ||sqrt(M) e(x)||, so |psi - y| <= G ||v||_inf + G_w ||w||_inf with
    G_w = error_bound_gain(..., ebar) (the same Young step as eq. (38)), and the region's ||v||_inf limit shrinks by
    ebar w_max / dbar (the sublevel set of W stays invariant).  ebar is proved in ball arithmetic where it can be."""
    v = art.values
    lam, eps, alpha_h, dbar = (float(v[k]) for k in ("lambda", "epsilon", "alpha_h", "dbar"))
    varying = bool(model.e.free_symbols & set(model.x))
    if varying and model.state_box is None:
        raise SpecError("concrete.state_box", "missing: e(x) depends on the states, so its sup ||sqrt(M) e(x)|| is taken over a box of states",
                        "one pair [lo, hi] per state")
    box = model.state_box if model.state_box is not None else np.zeros((model.n, 2))
    grid = domain_grid(box, 20000) if varying else box[:, :1]
    e_fun = model.numeric(model.e, list(model.x))

    def norms_at(points: np.ndarray) -> np.ndarray:
        values = e_fun(*points).reshape(model.n, -1, points.shape[1])
        return np.linalg.norm(np.einsum("ji,jkN->Nik", L, values), ord=2, axis=(1, 2))

    norms = norms_at(grid)
    # the grid maximum refined by bounded local searches (a grid alone sat 1.8e-5 below an interior sup)
    ebar_sampled, at = maximise_on_box(grid, norms, lambda z: float(norms_at(z.reshape(-1, 1))[0]), box, starts=5) if varying else (float(norms[0]), grid[:, 0])
    proved = prove_sup_norm(model, M, model.e, box, np.asarray(at, dtype=float), args=list(model.x))
    ebar = max(ebar_sampled, proved) if np.isfinite(proved) else ebar_sampled
    evidence = PROVED if np.isfinite(proved) else SAMPLED
    w_max = float(np.linalg.norm(np.abs(model.W).max(axis=1)))
    gain_w = error_bound_gain(alpha_h, lam, eps, ebar)
    v_max = float(v["v_max_certified"])
    v_max_w = v_max - ebar * w_max / dbar if np.isfinite(v_max) and dbar > 0 else v_max
    v.update({"ebar": ebar, "ebar_sampled": ebar_sampled, "ebar_proved": proved, "gain_w": gain_w, "w_max": w_max,
              "disturbance_term": gain_w * w_max, "v_max_certified_with_w": v_max_w, "evidence_ebar": evidence})
    region = "the region's ||v||_inf limit is global" if not np.isfinite(v_max) else f"the region's ||v||_inf limit {v_max:.6g} becomes {v_max_w:.6g} for w in disturbance_bounds (> 0)"
    art.checks["disturbance_term"] = Check(ebar, bool(np.isfinite(ebar) and (not np.isfinite(v_max) or v_max_w > 0)),
                                           f"ebar = sup over concrete.state_box of ||sqrt(M) e(x)|| ({'proved upper bound, ball arithmetic' if evidence == PROVED else 'grid'}): "
                                           f"|psi - y| gains G_w ||w||_inf, G_w = {gain_w:.6g}; {region}", evidence)


def _alpha_h(model: Model, M: np.ndarray) -> dict:
    """alpha_h and L_h (1 / lambda_max(C M^-1 C^T) for a linear h, Assumption 1 otherwise), proved where ball arithmetic can."""
    lipschitz_h, lipschitz_at = model.h_jacobian_bound()
    alpha_h = alpha_h_linear(M, model.C) if model.C is not None else _alpha_h_lipschitz(M, lipschitz_h)
    out = {"alpha_h_sampled": alpha_h, "lipschitz_h_sampled": lipschitz_h, "lipschitz_at": lipschitz_at, "how": "numpy", "proved": False}
    proof = prove_alpha_h(model, M, alpha_h)
    if proof is not None:
        alpha_h, lipschitz_h, out["how"] = proof
        out["proved"] = True
    out.update(alpha_h=alpha_h, lipschitz_h=lipschitz_h)
    return out


def _theta_on_V(model: Model, man: Artefact, dl: Artefact, L: np.ndarray) -> dict:
    """dp/dxi delta (a formula, or a series when p is numeric and delta constant), its numpy forms and
    ||sqrt(M) theta|| on a grid of V for q = 0, delta = I and the least-squares q.

    Raises
    ------
    DesignError
        If ||sqrt(M) dp/dxi delta|| is not finite on the grid (condition (B) fails).
    """
    delta = dl.expr("delta")
    xi_args = list(model.xi)
    th = {"dpd_series": None}
    if "dp_dxi" in man.series and not delta.free_symbols & set(model.xi):
        # p kept numeric and delta constant: dp/dxi delta is a series too, evaluated by numpy (no formula built).
        th["dpd_series"] = man.series["dp_dxi"].right(np.array(model.substitute(delta), dtype=float))
        th["dp_delta"], th["dpd_num"] = None, th["dpd_series"]
    else:
        th["dp_delta"] = man.expr("dp_dxi") * delta
        th["dpd_num"] = model.numeric(th["dp_delta"], xi_args)
    th["dp_num"], th["p_num"] = dp_function(man, model), p_function(man, model)
    th["g_num"] = model.numeric(_input_matrix(model), list(model.x))
    grid = th["grid"] = domain_grid(model.V, GRID_POINTS)
    th["dpd_grid"], th["p_grid"] = th["dpd_num"](*grid), th["p_num"](*grid)          # evaluated once, used by every sup below
    th["norm_q0"] = theta_norms(L, th["dpd_grid"], None)
    th["norm_q0_identity"] = theta_norms(L, th["dp_num"](*grid), None)
    th["norm_ls"] = theta_norms(L, th["dpd_grid"], th["g_num"](*th["p_grid"][:, 0, :]))
    if not np.all(np.isfinite(th["norm_q0"])):
        raise DesignError("abstract.delta", "||sqrt(M) dp/dxi delta|| is not finite on V (condition (B) fails)",
                          "p continuously differentiable and delta continuous on V (Proposition 1)", check="condition_B")
    th["p_expr"] = man.exprs["p"] if "p" in man.exprs else (man.series["p"].to_sympy(xi_args) if "p" in man.series else None)
    return th


def _dbar(model: Model, M: np.ndarray, L: np.ndarray, th: dict) -> dict:
    """The sups of ||theta|| over V (q = 0, delta = I, least squares; refined by a scalar search for one
    abstract state), dbar_q0 proved in ball arithmetic where it can be, and the dbar of the interface."""
    grid, dpd_num, dp_num, g_num, p_num = th["grid"], th["dpd_num"], th["dp_num"], th["g_num"], th["p_num"]
    if model.n_hat == 1:
        xs = grid[0]
        dbar_q0, at_q0 = _sup_on_interval(lambda s: theta_norms(L, dpd_num(s), None), xs, th["norm_q0"])
        dbar_id, at_id = _sup_on_interval(lambda s: theta_norms(L, dp_num(s), None), xs, th["norm_q0_identity"])
        dbar_ls, at_ls = _sup_on_interval(lambda s: theta_norms(L, dpd_num(s), g_num(*p_num(s)[:, 0, :])), xs, th["norm_ls"])
        at = [[at_q0], [at_id], [at_ls]]
    else:
        dbar_q0, dbar_id, dbar_ls = (float(th[k].max()) for k in ("norm_q0", "norm_q0_identity", "norm_ls"))
        at = [grid[:, np.argmax(th[k])].tolist() for k in ("norm_q0", "norm_q0_identity", "norm_ls")]
    dp_delta = th["dp_delta"] if th["dp_delta"] is not None else th["dpd_series"].to_sympy(list(model.xi))
    db = {"dbar_q0_sampled": dbar_q0, "dbar_q0_proved": np.inf, "dbar_id": dbar_id, "dbar_ls": dbar_ls, "at": at}
    # the proof works on the formula (the one readers get); above MAX_PROOF_STATES states for a diagonal M only
    if model.n <= proofs.MAX_PROOF_STATES or not np.any(M - np.diag(np.diag(M))):
        db["dbar_q0_proved"] = prove_sup_norm(model, M, dp_delta, model.V, np.asarray(at[0], dtype=float))
    if np.isfinite(db["dbar_q0_proved"]):
        dbar_q0 = max(dbar_q0, db["dbar_q0_proved"])
    # The interface's saturation (several inputs clipped separately) and feedback (local) enter here.
    dbar, dbar_how = _interface_dbar(model, L, th["dpd_grid"], dbar_q0)
    evidence = PROVED if np.isfinite(db["dbar_q0_proved"]) and dbar == dbar_q0 else SAMPLED
    if np.isfinite(dbar) and dbar != dbar_q0 and np.isfinite(db["dbar_q0_proved"]):
        # The clipping patterns of several inputs: proved where theta does not depend on xi (affine p, constant delta and g).
        g_const = _constant_g(model)
        pattern_proved = _prove_pattern_dbar(model, M, g_const, th["dp_delta"]) if g_const is not None else np.inf
        if np.isfinite(pattern_proved):
            dbar = max(dbar, pattern_proved, dbar_q0)
            dbar_how = dbar_how.replace("(grid)", "(proved in ball arithmetic: theta is constant on V)")
            evidence = PROVED
    if not np.isfinite(dbar):
        raise DesignError("interface.saturate", f"no uniform bound is certified: {dbar_how} (condition (B) fails for this interface)",
                          "interface.saturate: scale (one factor for the whole correction), q: zero, or a constant g", check="condition_B")
    db.update(dbar_q0=dbar_q0, dbar=dbar, dbar_how=dbar_how, evidence=evidence)
    return db


def _region(model: Model, upstream: dict[str, Artefact], M: np.ndarray, L: np.ndarray, lam: float, eps: float, db: dict, th: dict) -> dict:
    """Where the bound is certified (W0 and ||v||_inf limits; infinite for a global bound), the published limits
    proved where ball arithmetic can (then a little smaller than the sampled ones)."""
    grid = th["grid"]
    l_num = model.numeric(model.l, list(model.xi))
    w0_max, v_max, limits = certified_region(model, upstream, L, db["dbar"], (lam - eps) * eps, grid, l_num(*grid), th["p_grid"], th["dpd_grid"])
    # A global region rests on the structural argument of _interface_dbar and on dbar itself; a local one on the
    # proved lower bounds of its limits (then the region published is the proved one, a little smaller).
    region = {"w0_max_sampled": w0_max, "v_max_sampled": v_max, "limits": limits,
              "evidence": db["evidence"] if not np.isfinite(w0_max) else SAMPLED}
    if np.isfinite(w0_max):
        series = upstream["manifold"].series.get("p")
        p_range = series.range_bound() if isinstance(series, chebyshev.Series) and len(series.box) > 1 else None
        proved_region = _prove_region(model, upstream, M, db["dbar"], (lam - eps) * eps, th["p_expr"], th["dp_delta"], p_range)
        if proved_region is not None and proved_region[0] > 0:
            w0_max, v_max = min(w0_max, proved_region[0]), min(v_max, proved_region[1])
            region["evidence"] = db["evidence"]
    region.update(w0_max=w0_max, v_max=v_max)
    return region


def _artefact(model: Model, upstream: dict[str, Artefact], M: np.ndarray, L: np.ndarray, lam: float, eps: float, gain: float,
              alpha: dict, th: dict, db: dict, region: dict) -> Artefact:
    """The bound stage's artefact: values, expressions, and the checks of condition (B), the region, alpha_h and L_h."""
    C = model.C
    art = Artefact(stage=NAME, meta={
        "grid_points": int(th["grid"].shape[1]), "sup_method": "grid maximum refined by bounded scalar search",
        "sqrt_M": "Cholesky factor L of M, ||L^T w|| = ||sqrt(M) w|| (ERRATA item 8)",
        "gain_form": "paper (Theorem 2 max-form, factor 2 kept, ERRATA item 7)",
        "dbar_ls_where": "on the manifold x = p(xi); not a uniform bound off it",
        "interface_q": model.spec.interface.q,
    })
    if th["dp_delta"] is None:
        art.set_series("dp_delta", th["dpd_series"], model.xi)
    else:
        art.exprs["dp_delta"] = th["dp_delta"]
    art.exprs["g"] = _input_matrix(model)
    alpha_h, dbar, dbar_how, w0_max, v_max, limits = alpha["alpha_h"], db["dbar"], db["dbar_how"], region["w0_max"], region["v_max"], region["limits"]
    art.values.update({
        "M": M, "L": L, "lambda": lam, "alpha_h": alpha_h, "epsilon": eps, "C": C if C is not None else np.zeros((0, model.n)),
        "dbar_q0": db["dbar_q0"], "dbar_q0_squared": db["dbar_q0"]**2, "dbar_q0_identity": db["dbar_id"], "dbar_ls": db["dbar_ls"],
        "dbar_argmax": np.array(db["at"], dtype=float), "gain": gain, "gain_comparison": gain / np.sqrt(2.0),
        "dbar": dbar, "dbar_how": dbar_how, "dbar_q0_sampled": db["dbar_q0_sampled"], "dbar_q0_proved": db["dbar_q0_proved"],
        "alpha_h_sampled": alpha["alpha_h_sampled"], "lipschitz_h_sampled": alpha["lipschitz_h_sampled"],
        "w0_max_certified": w0_max, "v_max_certified": v_max,
        "w0_max_sampled": region["w0_max_sampled"], "v_max_sampled": region["v_max_sampled"],
        "region_limits": "; ".join(limits) if limits else "none: the bound holds on V x R^n for every v",
        "xi_grid": th["grid"], "theta_norm_q0": th["norm_q0"], "theta_norm_q0_identity": th["norm_q0_identity"], "theta_norm_ls_manifold": th["norm_ls"],
    })
    how = "proved upper bound by ball arithmetic over V" if db["evidence"] == PROVED else "grid of V"
    art.checks["condition_B"] = Check(dbar, bool(np.isfinite(dbar) and 0 < eps < lam),
                                      "Proposition 1: sup of ||theta|| over V, the states and the interface's saturation finite and 0 < epsilon < lambda "
                                      f"(dbar = {dbar_how}; {how})", db["evidence"])
    text = "global (every W0, every v)" if not np.isfinite(w0_max) else f"W(xi0, x0) <= {w0_max:.6g} and ||v||_inf <= {v_max:.6g} ({'; '.join(limits)})"
    art.checks["certified_region"] = Check(w0_max, bool(w0_max > 0),
                                           f"where |psi - y| <= sqrt(W0 e^(-(lambda - eps) t) / alpha_h) + G ||v||_inf is certified: {text} (non-empty)",
                                           region["evidence"])
    alpha_evidence = PROVED if alpha["proved"] else SAMPLED
    art.checks["alpha_h"] = Check(alpha_h, alpha_h > 0, f"alpha_h with W >= alpha_h |kappa(xi) - h(x)|^2 (> 0, eq. (6); {alpha['how']})", alpha_evidence)
    lipschitz_h = alpha["lipschitz_h"]
    art.values.update({"lipschitz_h": lipschitz_h, "lipschitz_h_at": alpha["lipschitz_at"]})
    where = "||C||_2 of the linear output map" if C is not None else f"sup of ||dh/dx||_2 over concrete.state_box = {model.state_box.tolist()} (grid + L-BFGS-B)"
    art.meta["alpha_h_form"] = "1 / lambda_max(C M^-1 C^T)" if C is not None else "lambda_min(M) / L_h^2 (Assumption 1)"
    if C is None and alpha["proved"]:
        where = f"proved upper bound of sup ||dh/dx||_2 over concrete.state_box = {model.state_box.tolist()} (ball arithmetic)"
    # A linear h is Lipschitz with the constant ||C||_2 by definition: nothing is sampled.
    h_evidence = PROVED if C is not None or alpha["proved"] else SAMPLED
    art.checks["h_lipschitz"] = Check(lipschitz_h, bool(np.isfinite(lipschitz_h) and lipschitz_h > 0), f"Lipschitz constant L_h = {where} (finite: Assumption 1 holds)", h_evidence)
    # How each number that enters G and the region was established (proved or sampled), for `ashc summary`.
    lmi = [upstream["stabilise"].checks[k].evidence for k in ("lmi_margin", "M_positive") if k in upstream["stabilise"].checks]
    art.values.update({"evidence_lambda": PROVED if lmi and all(e == PROVED for e in lmi) else SAMPLED,
                       "evidence_alpha_h": PROVED if alpha_evidence == PROVED and h_evidence == PROVED else SAMPLED,
                       "evidence_dbar": db["evidence"], "evidence_region": region["evidence"]})
    sampled = bound_sampled({**upstream, NAME: art})
    art.values["bound_evidence"] = PROVED if not sampled else SAMPLED
    art.values["bound_sampled"] = ", ".join(sampled) if sampled else "none"
    return art


def bound_sampled(arts: dict[str, Artefact]) -> list[str]:
    """The checks of :data:`BOUND_CHECKS` that are not proved (``stage.check``; a missing one counts as not proved).

    Parameters
    ----------
    arts : dict of str to Artefact
        The stabilise, manifold and bound artefacts (by stage name).

    Returns
    -------
    list of str
    """
    out = []
    extra = (("bound", "disturbance_term"),) if "bound" in arts and "disturbance_term" in arts["bound"].checks else ()
    for stage, name in BOUND_CHECKS + extra:
        chk = arts[stage].checks.get(name) if stage in arts else None
        if chk is None or chk.evidence != PROVED:
            out.append(f"{stage}.{name}")
    return out


def gain_text(v: dict, fmt: str = ".5g") -> str:
    """G as printed wherever the bound is published: with "(sampled)" when a number it rests on is only sampled.

    Parameters
    ----------
    v, fmt : dict, str
        The bound artefact's values (``gain``; ``bound_evidence``, missing: sampled) and G's format spec.

    Returns
    -------
    str
    """
    text = format(float(v["gain"]), fmt)
    return text + (" (sampled)" if str(v.get("bound_evidence", SAMPLED)) != PROVED else "")


def summarise(art: Artefact) -> dict:
    """Headline numbers for ``ashc summary``.

    Parameters
    ----------
    art : Artefact
        The bound stage's artefact.
    """
    v = art.values
    return {
        "alpha_h": float(v["alpha_h"]), "epsilon": float(v["epsilon"]), "dbar_q0": float(v["dbar_q0"]),
        "dbar_q0_identity": float(v["dbar_q0_identity"]), "dbar_ls": float(v["dbar_ls"]), "gain": float(v["gain"]),
        "gain_comparison": float(v["gain_comparison"]), "gain_form": art.meta.get("gain_form"),
        "dbar": float(v.get("dbar", v["dbar_q0"])), "dbar_how": v.get("dbar_how", ""),
        "w0_max_certified": float(v.get("w0_max_certified", np.inf)), "v_max_certified": float(v.get("v_max_certified", np.inf)),
        "region_limits": v.get("region_limits", ""),
        **{k: float(v[k]) for k in ("ebar", "gain_w", "w_max", "disturbance_term", "v_max_certified_with_w", "rho_bar", "residual_term") if k in v},
        "bound_evidence": str(v.get("bound_evidence", SAMPLED)), "bound_sampled": str(v.get("bound_sampled", "")),
        "evidence": {k: str(v.get(f"evidence_{k}", SAMPLED)) for k in ("lambda", "alpha_h", "dbar", "region")},
        "dbar_argmax": {"q0": np.asarray(v["dbar_argmax"])[0].tolist(), "q0_identity": np.asarray(v["dbar_argmax"])[1].tolist(),
                        "ls": np.asarray(v["dbar_argmax"])[2].tolist()},
    }


def headline(art: Artefact) -> str:
    """One progress line.

    Parameters
    ----------
    art : Artefact
        The bound stage's artefact.
    """
    v = art.values
    w = f" + G_w ||w||_inf, G_w = {float(v['gain_w']):.5g}" if "gain_w" in v else ""
    w += f" + {float(v['residual_term']):.3g} (p's PDE residual)" if float(v.get("residual_term", 0.0)) > 0 else ""
    return f"alpha_h = {v['alpha_h']:.5g}, dbar = {v.get('dbar', v['dbar_q0']):.5g}, gain G = {gain_text(v)} (|psi - y| <= G ||v||_inf{w} {region_text(v)})"


def disturbance_text(v: dict) -> str:
    """The disturbance's term of the published bound, `` + G_w ||w||_inf`` with its number, or empty without one.

    Parameters
    ----------
    v : dict
        The bound artefact's values (``gain_w`` when the plant has disturbances).

    Returns
    -------
    str
    """
    rho = f" + {float(v['residual_term']):.3g}" if float(v.get("residual_term", 0.0)) > 0 else ""
    return (f" + {float(v['gain_w']):.5g} ||w||_inf" if "gain_w" in v else "") + rho


def region_text(v: dict) -> str:
    """Where the uniform bound holds, in words: 'for every W0 and v' or 'when W0 <= c and ||v||_inf <= v_c'.

    Parameters
    ----------
    v : dict
        The bound artefact's values (``w0_max_certified`` and ``v_max_certified``; missing means infinite).

    Returns
    -------
    str
        ``when W(xi0, x0) = 0; region: global`` when both limits are infinite, else with the limits W0 <= c, ||v||_inf <= v_c.
    """
    w0, vm = float(v.get("w0_max_certified", np.inf)), float(v.get("v_max_certified", np.inf))
    if not np.isfinite(w0) and not np.isfinite(vm):
        return "when W(xi0, x0) = 0; region: global"
    if "v_max_certified_with_w" in v:      # a disturbance in its bounds takes up part of the v the region allows
        return f"when W(xi0, x0) = 0; region: W0 <= {w0:.4g}, ||v||_inf <= {float(v['v_max_certified_with_w']):.4g} with w in disturbance_bounds"
    return f"when W(xi0, x0) = 0; region: W0 <= {w0:.4g}, ||v||_inf <= {vm:.4g}"

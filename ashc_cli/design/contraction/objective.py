"""``objective: min_gain``: the M that makes the bound smallest, not the one with the largest decay rate.

The uniform bound is |psi - y| <= G ||v||_inf with G = sqrt(2 / (alpha_h (lambda - eps) eps)) dbar, eps = lambda / 2
(eq. (9) and Section V), that is G = (2 sqrt 2 / lambda) dbar / sqrt(alpha_h), with dbar = sup_V ||sqrt(M) w(xi)||,
w = dp/dxi delta, and alpha_h = 1 / lambda_max(C M^-1 C^T) for a linear h (lambda_min(M) / L_h^2 otherwise).  The
ratio dbar^2 / alpha_h does not change when M is scaled, so the scale is fixed by alpha_h >= 1, which is
[[M, C^T], [C, I]] >= 0 (a Schur complement; M >= I for a nonlinear h), and at a fixed lambda

    minimise t  subject to  w(xi_j)^T M w(xi_j) <= t  at the points xi_j of a grid of V,
                            A_k^T M + M A_k + lambda (1 + margin) M <= 0  at every vertex,  alpha_h >= 1

is an SDP (t = dbar^2 on the grid; the bound stage proves dbar for the M found).  With ``maximise`` the frontier
lambda -> G(lambda) is traced at fractions of the largest certified rate and the smallest G taken: near the largest
rate M degenerates and G grows without bound, which is why maximising lambda alone gave G = 3932 on a quadruple tank
and 1209 on a 60-state chain.
"""

from __future__ import annotations

from ashc_cli.design.solvers import cp
import numpy as np

from ashc_cli.errors import NumericalError
from ashc_cli.design.contraction.vertex import value_of_M, solve_with_clarabel, unknown_M, lmi_margins

__all__ = ["min_gain_M", "frontier", "FRONTIER"]

#: Fractions of the largest certified rate at which the lambda-G frontier is traced first; the best is then refined
#: by the two midpoints beside it.
FRONTIER = (0.1, 0.3, 0.5, 0.7, 0.85, 0.95)
#: The LMI is imposed at lambda (1 + RATE_MARGIN) so the re-check at lambda is strict.
RATE_MARGIN = 1e-3


def min_gain_M(A_list: list[np.ndarray], lam: float, W: list[np.ndarray], C: np.ndarray | None,
               structure: str = "full") -> tuple[np.ndarray | None, float]:
    """The M minimising max_j ||sqrt(M) W_j||^2 subject to eq. (28) at lam and alpha_h >= 1, and that minimum t.

    Parameters
    ----------
    A_list : list of ndarray
        The vertex matrices (divided by the rate scale, as lam).
    lam : float
        The decay rate.
    W : list of ndarray (n, m_hat)
        dp/dxi delta at the grid points of V.
    C : ndarray (p, n) or None
        The linear output map (None: h nonlinear, normalised by M >= I).
    structure : {"full", "diagonal"}

    Returns
    -------
    M : ndarray or None
        None if the solver found no M.
    t : float
        The optimal max_j ||sqrt(M) W_j||^2 (inf without M).
    """
    n = A_list[0].shape[0]
    var, M, _ = unknown_M(n, structure)
    t = cp.Variable()
    eye = np.eye(n)
    constraints = [A.T @ M + M @ A + lam * (1 + RATE_MARGIN) * M << 0 for A in A_list]
    if C is not None:
        p = C.shape[0]
        constraints.append(cp.bmat([[M, C.T], [C, np.eye(p)]]) >> 0)
    else:
        constraints.append(M >> eye)
    for Wj in W:
        if Wj.shape[1] == 1:
            w = Wj[:, 0]
            constraints.append(cp.quad_form(w, M) <= t) if structure == "full" else constraints.append(w**2 @ cp.diag(M) <= t)
        else:
            constraints.append(Wj.T @ M @ Wj << t * np.eye(Wj.shape[1]))
    try:
        problem = solve_with_clarabel(cp.Problem(cp.Minimize(t), constraints), f"the smallest-gain LMI at lambda = {lam:g} ({structure} M)")
    except NumericalError:
        return None, np.inf          # a failed solve is no point of the frontier (the rate's M stays)
    if var.value is None or t.value is None or problem.status not in ("optimal", "optimal_inaccurate"):
        return None, np.inf
    Mv = value_of_M(var, structure)
    if np.linalg.eigvalsh(Mv).min() <= 0 or lmi_margins(A_list, Mv, lam).max() >= 0:
        return None, np.inf
    return Mv, float(t.value)


def gain_estimate(M: np.ndarray, lam: float, W: list[np.ndarray], C: np.ndarray | None, L_h: float | None = None) -> float:
    """G = (2 sqrt 2 / lambda) sqrt(max_j ||sqrt(M) W_j||^2 / alpha_h) on the grid (the bound stage computes the proved one).

    Parameters
    ----------
    M : ndarray (n, n)
        Symmetric positive definite.
    lam : float
        The decay rate (G scales as 1 / lam: the plant's units give the plant's G).
    W : list of ndarray (n, m_hat)
        dp/dxi delta at the grid points of V.
    C : ndarray (p, n) or None
        The linear output map: alpha_h = 1 / lambda_max(C M^-1 C^T); None for a nonlinear h.
    L_h : float, optional
        For a nonlinear h, its Lipschitz constant (Assumption 1): alpha_h = lambda_min(M) / L_h^2 (None or 0: 1).

    Returns
    -------
    float
    """
    dbar2 = max(float(np.linalg.eigvalsh(Wj.T @ M @ Wj).max()) for Wj in W)
    if C is not None:
        alpha = 1.0 / float(np.linalg.eigvalsh(C @ np.linalg.solve(M, C.T)).max())
    else:
        alpha = float(np.linalg.eigvalsh(M).min()) / (L_h or 1.0) ** 2
    return float(2.0 * np.sqrt(2.0) / lam * np.sqrt(dbar2 / alpha))


def frontier(A_list: list[np.ndarray], lam_max: float, W: list[np.ndarray], C: np.ndarray | None, structure: str = "full",
             L_h: float | None = None) -> list[tuple[float, float, np.ndarray]]:
    """(lambda, G, M) at the fractions FRONTIER of lam_max where the smallest-gain M is found (rates in the units of A_list).

    The fraction of the smallest G is then refined by the midpoints beside it.

    Parameters
    ----------
    A_list : list of ndarray (n, n)
        The vertex matrices (divided by the rate scale, as lam_max).
    lam_max : float
        The largest certified rate.
    W, C, L_h
        As for :func:`gain_estimate`.
    structure : {"full", "diagonal"}
        The form of M.

    Returns
    -------
    list of (float, float, ndarray)
        (lambda, G, M) in increasing lambda, only where :func:`min_gain_M` found an M.
    """
    out: dict = {}

    def at(frac: float) -> None:
        if frac not in out:
            M, _ = min_gain_M(A_list, frac * lam_max, W, C, structure)
            out[frac] = None if M is None else (frac * lam_max, gain_estimate(M, frac * lam_max, W, C, L_h), M)

    for frac in FRONTIER:
        at(frac)
    found = [f for f in FRONTIER if out[f] is not None]
    if found:
        k = FRONTIER.index(min(found, key=lambda f: out[f][1]))
        for other in (k - 1, k + 1):
            if 0 <= other < len(FRONTIER):
                at(round(0.5 * (FRONTIER[k] + FRONTIER[other]), 6))
    return [v for _, v in sorted(out.items()) if v is not None]

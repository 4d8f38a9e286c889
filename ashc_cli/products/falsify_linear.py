"""The falsifier's linearised worst case (``strategies``' ``linearised`` runs): the loop linearised about (xi, p(xi))
with v held over each hold, e+ = E e + Gamma v, e_y = C e; its Markov parameters C E^k Gamma, the linearised worst
ratio per point of V and the output direction and frequency that reach it."""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla

from ashc_cli.closedloop.batch import interface

__all__ = ["linearise", "discrete"]


def linearise(st, xi_grid: np.ndarray) -> dict:
    """The loop linearised about (xi, p(xi)), v = 0, at the columns of xi_grid: e' = J e + theta v, e_y = C e
    with e = p - x, theta = dp/dxi delta - g q (the unsaturated interface).

    Parameters
    ----------
    st : strategies.Setup
    xi_grid : ndarray (n_hat, N)
    """
    model, plant = st.model, st.plant
    n, Ng = model.n, xi_grid.shape[1]
    a = plant.at_xi(xi_grid)
    p, l = a["p"][:, :, 0], a["l"][:, :, 0]
    step = 1e-6 * np.maximum(1.0, np.abs(p))                                        # (Ng, n)
    X = np.repeat(p[None], 2 * n, axis=0)                                           # (2n, Ng, n)
    for j in range(n):
        X[2 * j, :, j] += step[:, j]
        X[2 * j + 1, :, j] -= step[:, j]
    Xf = X.reshape(-1, n)
    u = np.tile(l, (2 * n, 1)) + (Xf - np.tile(p, (2 * n, 1))) @ plant.K.T
    bx = plant.at_x(Xf.T, u.T)
    F = (bx["f_bar"][:, :, 0] + np.einsum("Nij,Nj->Ni", bx["g"], u)).reshape(2 * n, Ng, n)
    J = np.stack([(F[2 * j] - F[2 * j + 1]) / (2 * step[:, j:j + 1]) for j in range(n)], axis=2)   # (Ng, n, n)
    b0 = plant.at_x(p.T)
    pre = interface(model, plant, xi_grid, p.T)
    theta = a["dpd"] - b0["g"] @ pre["q"]
    return {"xi": xi_grid, "J": J, "theta": theta, "C": b0["dh"], "p": p}


def discrete(st, lin: dict) -> dict:
    """E = exp(J hold), Gamma = int_0^hold exp(J s) ds theta; the Markov parameters C E^k Gamma over the window
    where they matter; the linearised worst ratio per point and the output direction that reaches it.

    Parameters
    ----------
    st : strategies.Setup
        The hold, the number of holds, t_final and G.
    lin : dict
        :func:`linearise`'s result.

    Returns
    -------
    dict
        ``marks`` (N, K, p, m_hat), ``W`` (output directions), ``wbest``, ``ratio`` and ``f_star`` per point.
    """
    J, theta, C = lin["J"], lin["theta"], lin["C"]
    Ng, n, mh = theta.shape
    p = C.shape[1]
    aug = np.zeros((Ng, n + mh, n + mh))
    aug[:, :n, :n] = J * st.hold
    aug[:, :n, n:] = theta * st.hold
    with np.errstate(all="ignore"):
        Ea = sla.expm(aug)
    E, Gam = Ea[:, :n, :n], Ea[:, :n, n:]
    ok = np.all(np.isfinite(Ea), axis=(1, 2))
    E, Gam = np.where(ok[:, None, None], E, 0.0), np.where(ok[:, None, None], Gam, 0.0)
    marks = []
    Xk = Gam
    top = 0.0
    for k in range(st.holds):
        mk = C @ Xk                                                                 # (Ng, p, mh)
        marks.append(mk)
        size = float(np.max(np.abs(mk)))
        top = max(top, size)
        if k > 8 and size < 1e-4 * top:
            break
        Xk = E @ Xk
    mk = np.stack(marks, axis=1)                                                    # (Ng, K, p, mh)
    if p == 1:
        W = np.ones((1, 1))
    else:
        if p == 2:
            ang = np.linspace(0, np.pi, 16, endpoint=False)
            W = np.c_[np.cos(ang), np.sin(ang)]
        else:
            W = np.random.default_rng(0).standard_normal((32, p))
            W = np.r_[np.eye(p), W / np.linalg.norm(W, axis=1, keepdims=True)]
    gain = np.stack([np.linalg.norm(np.einsum("p,NKpm->NKm", w, mk), axis=2).sum(axis=1) for w in W], axis=1)   # (Ng, w)
    wbest = np.argmax(gain, axis=1)
    ratio = gain[np.arange(Ng), wbest] / st.G if st.G > 0 else np.full(Ng, np.inf)
    # Frequency of the largest sinusoidal gain sigma_max(C (j w - J)^-1 theta).
    omegas = np.geomspace(2 * np.pi / st.t_final, np.pi / st.hold, 48)
    sig = np.zeros((Ng, omegas.size))
    eye = np.eye(n)
    for i, w in enumerate(omegas):
        with np.errstate(all="ignore"):
            try:
                Hm = C @ np.linalg.solve(1j * w * eye - J, theta.astype(complex))
            except np.linalg.LinAlgError:
                continue
        sig[:, i] = np.linalg.norm(Hm, ord=2, axis=(1, 2)) if min(p, mh) > 1 else np.sqrt(np.sum(np.abs(Hm) ** 2, axis=(1, 2)))
    sig = np.where(np.isfinite(sig), sig, 0.0)
    f_star = omegas[np.argmax(sig, axis=1)] / (2 * np.pi)
    return {"marks": mk, "W": W, "wbest": wbest, "ratio": np.where(ok, ratio, 0.0), "f_star": f_star}
